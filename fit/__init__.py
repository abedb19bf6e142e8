"""fit: the extruder physics (composable effects), the simulator, and the Bayesian fitters."""
