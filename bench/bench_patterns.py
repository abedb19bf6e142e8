"""Pattern generation on the Adventurer 3: wall time to generate each pattern with its
defaults (G-code + planned manifest), the G-code size and the planned print time.
Figures without targets (passed=None): they describe what a user gets."""
from __future__ import annotations

from bench.common import Row, best_time_s
from patterns.builder import PATTERNS
from patterns.profile import load_profile

PRINTER = "adventurer3"
NAMES = ("spiral-step", "stop-mid-path", "retract", "start-stop")


def run() -> list[Row]:
    prof = load_profile(PRINTER)
    rows: list[Row] = []
    for name in NAMES:
        gen = PATTERNS[name]
        gcode, man = gen(prof)
        t_s = best_time_s(lambda: gen(prof), repeat=2)
        n_moves = sum(1 for ln in gcode.splitlines() if ln[:2] in ("G0", "G1"))
        rows += [
            Row("patterns", f"generate {name} on {PRINTER} (G-code + planned manifest)", t_s, "s", "-", None),
            Row("patterns", f"{name} G-code size ({n_moves} moves, {len(man.test_tracks())} test tracks)",
                len(gcode.encode()) / 1024.0, "KiB", "-", None),
            Row("patterns", f"{name} planned print time", man.timeline.duration_s / 60.0, "min", "-", None),
        ]
    return rows
