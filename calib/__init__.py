"""calib: the user's face of the extrusion calibration tool (CLI, wizard, batch, exports, reports)."""
__version__ = "0.1.0"
