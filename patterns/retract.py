"""retract pattern (seed 001, RetractTest, the four "Backpressure Testing" designs).

Each line: the StartStopTest preamble so no pressure carries over from the line before
(prime: draw 4 mm at 1 mm/s; drain: move 8 mm at 1 mm/s without extrusion; restore Re),
a straight line at steady state, then a *moving* retraction: the head keeps going for
40 mm at 10 mm/s while the extruder retracts 4 mm. The smear the nozzle leaves during the
retraction measures the pressure (advance) Pe it held (seed 001: Pe = Kf vn + Kb Db).

Designs (seed 001; Af = pi D^2 / 4). Seed 001 writes the bead area as w h; our bead
is the rounded rectangle A(w, h) (fit/geometry.py), so where the seed fixes ve we keep
ve and solve the head speed vx = ve Af / A(w, h):

1. constant ve, w = 0.3..0.8, h = 0.09 / w, ve = 0.3 * 0.3 * 10 / Af  (Pe vs w and h)
2. constant ve, w = 0.5, h = 0.1..0.35,   ve = 0.5 * 0.35 * 10 / Af  (Pe vs h, vx)
3. constant ve, h = 0.2, w = 0.3..0.8,    ve = 0.2 * 0.8 * 10 / Af   (Pe vs w, vx)
4. w = 0.5, h = 0.2, vx = 10..60 mm/s,    ve = A vx / Af             (Pe vs ve)
"""
from __future__ import annotations

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns import layout
from patterns.builder import PatternBuilder
from patterns.profile import load_profile

NAME = "retract"
PRIME_MM, PRIME_SPEED = 4.0, 1.0
DRAIN_MM, DRAIN_SPEED = 8.0, 1.0
SEED_RESTORE_MM = 1.0      # seed 001's RetractTest -Re=1.0 on its Adventurer 3
PRIME_WIDTH_MM = 0.5


def design_lines(design: int, n_steps: int, af_mm2: float) -> list[dict]:
    """(width_mm, height_mm, speed_mm_s, ve_mm_s) of each line of a seed-001 design."""
    out = []
    if design == 1:
        ws = np.linspace(0.3, 0.8, n_steps)
        hs = 0.09 / ws
        ve = 0.3 * 0.3 * 10 / af_mm2
    elif design == 2:
        hs = np.linspace(0.1, 0.35, n_steps)
        ws = np.full(n_steps, 0.5)
        ve = 0.5 * 0.35 * 10 / af_mm2
    elif design == 3:
        ws = np.linspace(0.3, 0.8, n_steps)
        hs = np.full(n_steps, 0.2)
        ve = 0.2 * 0.8 * 10 / af_mm2
    elif design == 4:
        vx = np.linspace(10.0, 60.0, n_steps)
        for v in vx:
            a = float(bead_area_mm2(0.5, 0.2))
            out.append(dict(width_mm=0.5, height_mm=0.2, speed_mm_s=float(v), ve_mm_s=a * v / af_mm2))
        return out
    else:
        raise UserError(f"retract: unknown design {design}: use 1, 2, 3 or 4 (seed 001)")
    for w, h in zip(ws, hs):
        a = float(bead_area_mm2(w, h))
        out.append(dict(width_mm=round(float(w), 4), height_mm=round(float(h), 4),
                        speed_mm_s=ve * af_mm2 / a, ve_mm_s=ve))
    return out


def _label(design, ln):
    f = lambda x: f"{x:.2f}".lstrip("0")  # noqa: E731
    if design == 1:
        return f"{design} w{f(ln['width_mm'])} h{f(ln['height_mm'])}"
    if design == 2:
        return f"{design} h{f(ln['height_mm'])}"
    if design == 3:
        return f"{design} w{f(ln['width_mm'])}"
    return f"{design} v{ln['speed_mm_s']:.0f}"


def generate(profile, *, designs=(1, 2, 3, 4), n_steps=6, draw_mm=40.0, restore_mm=None,
             retract_mm=4.0, retract_move_mm=40.0, retract_move_speed_mm_s=10.0):
    """G-code and manifest of the retract pattern.

    designs    which seed-001 designs to print (1..4)
    n_steps    lines per design (seed 001 uses 11: 10 steps)
    draw_mm    length of the steady line (mm)
    restore_mm Re (mm of filament) applied after the drain, before the line; None: seed 001's
               1 mm on its Adventurer 3 scaled to this printer's filament path
               (patterns.layout.scaled_restore_mm: 0.1 mm on a direct drive)
    retract_mm filament retracted during the moving retraction (mm), over
    retract_move_mm at retract_move_speed_mm_s (seed 001: 4 mm over 40 mm at 10 mm/s)
    """
    profile = load_profile(profile)
    if restore_mm is None:
        restore_mm = layout.scaled_restore_mm(profile, SEED_RESTORE_MM)[0]
    designs = [int(d) for d in np.atleast_1d(designs)]
    if n_steps < 2:
        raise UserError("retract: --steps must be >= 2")
    af = profile.filament_area_mm2
    params = {"designs": designs, "n_steps": int(n_steps), "draw_mm": float(draw_mm),
              "restore_mm": float(restore_mm), "retract_mm": float(retract_mm),
              "retract_move_mm": float(retract_move_mm),
              "retract_move_speed_mm_s": float(retract_move_speed_mm_s)}
    rows = []
    for d in designs:
        for ln in design_lines(d, n_steps, af):
            if ln["speed_mm_s"] > profile.max_velocity_mm_s:
                raise UserError(f"retract: design {d} needs {ln['speed_mm_s']:.0f} mm/s, more than the "
                                f"printer's {profile.max_velocity_mm_s:g} mm/s: drop design {d}")
            rows.append(dict(ln, design=d, group=str(d), label=_label(d, ln),
                             length_mm=PRIME_MM + DRAIN_MM + draw_mm + retract_move_mm))
    frame = layout.place_rows(profile, NAME, rows, pitch_mm=4.0,
                              hint="reduce --steps, --draw-mm or the number of --designs")
    b = PatternBuilder(profile, NAME, params, layer_height_mm=0.2)
    b.set_z(0.2)
    b.frame_prime(frame)
    for r in rows:
        x, y = r["start_xy"]
        h = r["height_mm"]
        r["track"] = b.begin("test", (x, y), z_mm=h, group=f"design {r['design']}", params={
            "design": r["design"], "width_mm": r["width_mm"], "height_mm": h,
            "speed_mm_s": round(r["speed_mm_s"], 4), "ve_mm_s": round(r["ve_mm_s"], 5),
            "restore_mm": float(restore_mm), "retract_mm": float(retract_mm),
            "draw_start_s_mm": PRIME_MM + DRAIN_MM, "retract_start_s_mm": PRIME_MM + DRAIN_MM + draw_mm})
        x1 = x + PRIME_MM
        b.extrude([(x, y), (x1, y)], PRIME_WIDTH_MM, PRIME_SPEED, height_mm=h)
        b.coast([(x1, y), (x1 + DRAIN_MM, y)], DRAIN_SPEED)
        x1 += DRAIN_MM
        b.writer.extruder_move(restore_mm, profile.retract_speed_mm_s)
        b.extrude([(x1, y), (x1 + draw_mm, y)], r["width_mm"], r["speed_mm_s"], height_mm=h)
        x1 += draw_mm
        b.coast([(x1, y), (x1 + retract_move_mm, y)], retract_move_speed_mm_s, e_mm=-retract_mm)
        b.end()
        # The line ends retracted by retract_mm - restore_mm relative to its start.
        b.note_retracted(max(retract_mm - restore_mm, 0.0))
    b.frame_furniture(frame, title="retract")
    for r in rows:
        b.label(r["label"], r["label_xy"], height_mm=layout.ROW_LABEL_H_MM, for_tracks=[r["track"]])
    return b.build()
