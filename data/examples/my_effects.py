"""My own effect: extruder gear slip, a flow gain that falls with extruder speed.

Residuals of `pa` on this printer grow with extruder speed, and no library effect
explains them. RepRapFirmware's M592 models it as a speed-dependent flow multiplier

    ve_out = ve * (1 + A*|ve| + B*ve^2)        (ve: commanded extruder speed, mm/s)

so the effect is a dozen lines: a name, two parameters with units and bounds, and a
numpy `command` stage that transforms the commanded extruder velocity.
"""
import numpy as np

from fit.effects import Effect
from fit.params import Param


class GearSlip(Effect):
    """Speed-dependent flow gain from gear slip (RRF M592): ve * (1 + A|ve| + B ve^2)."""

    name = "gear_slip"
    params = (Param("a_s_mm", "s/mm", 0.0, -0.05, 0.05, doc="linear slip coefficient A"),
              Param("b_s2_mm2", "s^2/mm^2", 0.0, -0.01, 0.01, doc="quadratic slip coefficient B"))

    def command(self, ctx, ve, p):
        gain = 1.0 + p["a_s_mm"] * np.abs(ve) + p["b_s2_mm2"] * ve ** 2
        return ve * np.maximum(gain, 0.0)
