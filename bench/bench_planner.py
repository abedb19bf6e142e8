"""Planner speed: parse + plan (moves per second) on the largest realdata G-code and on a
synthetic 50 000-move slicer-like program; manifest building time."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bench.common import Row, best_time_s
from patterns.gcode_parser import parse_gcode
from patterns.plan import manifest_from_gcode
from patterns.planner import plan, plan_gcode
from patterns.profile import load_profile

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
TARGET_MOVES_S = 20000.0
#: The realdata programs are slow (1-5 mm/s moves, 40 min of printing): sampling every
#: 5 ms makes ~130 samples per move, so their throughput is bounded by samples/s.
TARGET_REALDATA_MOVES_S = 5000.0
TARGET_SAMPLES_S = 1.0e6


def _synthetic(n_moves: int) -> str:
    """Concentric polygons with 0.5-2 mm segments, relative E, varying feed (slicer-like)."""
    rng = np.random.default_rng(1)
    lines = ["M83", "G1 Z0.2 F600"]
    ang = 0.0
    for i in range(n_moves):
        r = 20 + 60 * (i / n_moves)
        ang += rng.uniform(0.5, 2.0) / r
        lines.append(f"G1 X{100 + r * math.cos(ang):.3f} Y{100 + r * math.sin(ang):.3f} "
                     f"E{rng.uniform(0.02, 0.08):.5f} F{rng.choice([1800, 3600, 6000])}")
    return "\n".join(lines) + "\n"


def run() -> list[Row]:
    rows: list[Row] = []
    files = sorted(REALDATA.glob("*.g"), key=lambda p: p.stat().st_size) if REALDATA.is_dir() else []
    if files:
        text = files[-1].read_text()
        prof = load_profile("adventurer3")
        pr = parse_gcode(text, prof)
        n = len(pr.moves)
        t_all = best_time_s(lambda: plan_gcode(text, prof), repeat=3)
        t_plan = best_time_s(lambda: plan(pr, prof), repeat=3)
        t_man = best_time_s(lambda: manifest_from_gcode(text, prof), repeat=2)
        tl, _ = plan_gcode(text, prof)
        rows += [
            Row("planner", f"parse+plan {files[-1].name} ({n} moves, {len(tl)} samples)",
                n / t_all, "moves/s", f">= {TARGET_REALDATA_MOVES_S:g}", n / t_all >= TARGET_REALDATA_MOVES_S),
            Row("planner", "plan only (look-ahead + sampling), same file", len(tl) / t_plan, "samples/s",
                f">= {TARGET_SAMPLES_S:g}", len(tl) / t_plan >= TARGET_SAMPLES_S),
            Row("planner", "manifest_from_gcode, same file", t_man, "s", "<= 2", t_man <= 2.0),
        ]
    else:
        rows.append(Row("planner", "realdata G-code absent (../shared/realdata)", float("nan"), "-", "-", None))
    syn = _synthetic(50000)
    prof = load_profile("direct_drive")
    t_syn = best_time_s(lambda: plan_gcode(syn, prof), repeat=2)
    rows.append(Row("planner", "parse+plan synthetic 50k-move program (klipper)", 50000 / t_syn, "moves/s",
                    f">= {TARGET_MOVES_S:g}", 50000 / t_syn >= TARGET_MOVES_S))
    return rows
