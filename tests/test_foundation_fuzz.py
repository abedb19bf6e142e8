"""Property-based fuzzing of the G-code parser and planner (hypothesis).

Whatever text comes in, `calib plan`'s library path either returns a manifest whose
timeline is finite and runs forward in time, or raises UserError (one line, exit 2 in the
CLI). Any other exception is a traceback a user would see.
"""
import math

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from calib.errors import UserError
from patterns.plan import manifest_from_gcode

NUMBERS = st.one_of(
    st.floats(-20, 220, allow_nan=False).map(lambda f: f"{f:.3f}"),
    st.integers(-5, 5).map(str),
    st.sampled_from(["", "NaN", "nan", "inf", "-inf", "1e400", "-1e400", "1e6", ".", "-", "+",
                     "0x10", "1.2.3", "9" * 30, "1e-400"]),
)
WORD = st.tuples(st.sampled_from("XYZEF"), NUMBERS).map(lambda t: t[0] + t[1])
MOVE = st.tuples(st.sampled_from(["G0", "G1", "G1", "G1", "G92", "G2", "G3"]),
                 st.lists(WORD, min_size=0, max_size=4)).map(lambda t: " ".join([t[0], *t[1]]))
OTHER = st.sampled_from(["G90", "G91", "M82", "M83", "G21", "G28", "M104 S200", "M109 S200",
                         "G4 P100", "M400", "; comment", "", "T0", "M900 K0.05", "G20",
                         ";TRACK id=1 kind=test h=0.2", ";END_TRACK", "M117 Hello",
                         "N10 G1 X10*12", "G1 X10 Y10 E1 F1200 ; print"])
GARBAGE = st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=30)
LINE = st.one_of(MOVE, MOVE, OTHER, GARBAGE)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(LINE, min_size=1, max_size=25))
@example(["N0"])                     # a line number alone (found by this test)
@example(["N7 *3", "G1 X1e400"])
def test_parser_and_planner_never_raise_anything_but_a_user_error(lines):
    text = "G21\nG90\nM82\nG28\n" + "\n".join(lines) + "\n"
    try:
        man = manifest_from_gcode(text, "ender3")
    except UserError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg.strip()
        return
    tl = man.timeline
    if tl is None or len(tl.t_s) == 0:
        return
    for name in ("t_s", "x_mm", "y_mm", "z_mm", "v_mm_s", "ve_mm_s", "e_mm"):
        assert np.all(np.isfinite(getattr(tl, name))), name
    assert np.all(np.diff(tl.t_s) >= 0)
    for tr in man.tracks:
        assert all(math.isfinite(v) for p in tr.points_mm for v in p)
