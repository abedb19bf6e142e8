"""start-stop pattern (seed 001 StartStopTest, spiral version: SpStartStopTest2, AUTHOR-NOTES.md).

Every test is one arc of a set of concentric circles (all start at 12 o'clock and run
clockwise, like the author's spiral version), sweeping the restore distance Re within a
group and the bead width w between groups. Per test, as in the author's G-code:

  prime   draw 4 mm at 1 mm/s (w = 0.5)            fill the nozzle
  drain   move 8 mm at 1 mm/s, no extrusion         let the pressure run out
  check   move 4 mm at 5 mm/s, no extrusion         confirm the nozzle is empty
  restore +Re at the retract speed                  apply the pressure
  draw    draw_s seconds at ve (mm/s of filament), vx = ve Af / A(w, h)
  retract -Re                                       relieve the pressure
  drool   move 20 mm at 5 mm/s, no extrusion        any ooze shows the residual pressure
  restore +Re, cooldown draw 5 mm at 5 mm/s (w = 0.5), then the profile retraction.

If Re matches the advance Pe = Kf vn + Kb Db (seed 001), the line starts at full width
and nothing drools; under-restored lines start thin, over-restored ones drool.
Narrow (long) groups go outside, wide (short) ones inside; rings are w + gap apart.
"""
from __future__ import annotations

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns import font, layout
from patterns.builder import PatternBuilder
from patterns.profile import load_profile

NAME = "start-stop"
SEG_MM = 1.0
PHASES = (("prime", 4.0, 1.0, True), ("drain", 8.0, 1.0, False), ("check", 4.0, 5.0, False))
DROOL_MM, DROOL_SPEED = 20.0, 5.0
COOL_MM, COOL_SPEED = 5.0, 5.0
AUX_WIDTH_MM = 0.5
LABEL_H_MM = 3.0
#: The author's restore sweep (mm of filament) for his Adventurer 3 (seed 001: Re 2-4 mm at
#: ve 1 mm/s; his fitted Kf 0.4 s, Kb 3.0 give Pe = Kf ve + Kb Db = 1.6-2.7 mm).
SEED_RE_MM = (2.0, 2.5, 3.0, 3.5, 4.0)


def default_re_mm(profile) -> tuple[float, ...]:
    """Restore distances Re (mm of filament) to sweep on this printer: seed 001's sweep
    scaled by the filament path's compliance (patterns.layout.seed001_scale), rounded to
    0.05 mm: 2-4 mm on the Adventurer 3, 0.2-0.4 mm on a direct drive (whose advance at
    1 mm/s is PA 0.02-0.08 s times 1 mm/s plus the bead's back-pressure), 4-8 mm on a
    400 mm Bowden. A direct drive restored by the Bowden's 2-4 mm lays blobs mm across
    that cover the neighbouring rings."""
    return layout.scaled_restore_mm(profile, SEED_RE_MM)


def generate(profile, *, re_mm=None, widths_mm=(0.3, 0.4, 0.8, 1.6), ve_mm_s=1.0,
             height_mm=0.3, draw_s=3.0, gap_mm=1.0, group_gap_mm=2.0):
    """G-code and manifest of the spiral start-stop pattern.

    re_mm      restore distances Re (mm of filament) swept within each group; None: scaled
               to the printer's filament path (:func:`default_re_mm`)
    widths_mm  bead widths w (mm), one group each
    ve_mm_s    extruder velocity while drawing (mm/s of filament)
    height_mm  layer height (mm); draw_s drawing time per test (s)
    """
    profile = load_profile(profile)
    res = [float(r) for r in np.atleast_1d(default_re_mm(profile) if re_mm is None else re_mm)]
    widths = sorted(float(w) for w in np.atleast_1d(widths_mm))
    if min(res) < 0 or min(widths) <= 0 or ve_mm_s <= 0 or draw_s <= 0:
        raise UserError("start-stop: --re-mm must be >= 0 and --widths, --ve, --draw-s > 0")
    af = profile.filament_area_mm2
    params = {"re_mm": res, "widths_mm": widths, "ve_mm_s": float(ve_mm_s), "height_mm": float(height_mm),
              "draw_s": float(draw_s), "gap_mm": float(gap_mm)}
    max_w, max_h = layout.max_content_mm(profile)
    r_out = min(max_w, max_h, 120.0) / 2 - 1.0
    tests, r = [], r_out
    for g, w in enumerate(widths):
        v = ve_mm_s * af / float(bead_area_mm2(w, height_mm))
        if v > profile.max_velocity_mm_s:
            raise UserError(f"start-stop: w={w:g} mm needs {v:.0f} mm/s, more than the printer's "
                            f"{profile.max_velocity_mm_s:g} mm/s: lower --ve or raise --widths")
        for re_ in res:
            length = sum(p[1] for p in PHASES) + v * draw_s + DROOL_MM + COOL_MM
            if length > 2 * np.pi * r - 6.0:
                raise UserError(f"start-stop needs a ring of {length / (2 * np.pi) + 1:.0f} mm radius at "
                                f"{r:.0f} mm from the centre: use fewer --re-mm or --widths, or a shorter --draw-s")
            tests.append(dict(group=g, w=w, re=re_, v=v, r=r, length=length))
            r -= w + gap_mm
        r -= group_gap_mm
    if r < 3.0:
        raise UserError(f"start-stop needs {2 * (r_out - r + 3):.0f} mm of rings but the bed gives "
                        f"{2 * r_out:.0f} mm: use fewer --re-mm or --widths")
    side = 2 * r_out + 2.0
    frame = layout.make_frame(profile, NAME, side, side, "use fewer --re-mm or --widths")
    c = (0.5 * (frame.content_mm[0] + frame.content_mm[2]), 0.5 * (frame.content_mm[1] + frame.content_mm[3]))
    b = PatternBuilder(profile, NAME, params, layer_height_mm=height_mm)
    b.set_z(height_mm)
    b.frame_prime(frame)
    for t in tests:
        s_marks = np.cumsum([0.0] + [p[1] for p in PHASES] + [t["v"] * draw_s, DROOL_MM, COOL_MM])
        s = layout.resample_s(0.0, s_marks[-1], SEG_MM, s_marks)
        pts = layout.arc_points(c, t["r"], np.pi / 2, s)
        seg = lambda a, bnd: pts[(s >= a - 1e-9) & (s <= bnd + 1e-9)]  # noqa: E731
        t["track"] = b.begin("test", pts[0], group=f"w={t['w']:g}", params={
            "width_mm": t["w"], "restore_mm": t["re"], "ve_mm_s": float(ve_mm_s), "speed_mm_s": round(t["v"], 4),
            "height_mm": float(height_mm), "radius_mm": round(t["r"], 4),
            "draw_start_s_mm": float(s_marks[3]), "drool_start_s_mm": float(s_marks[4])})
        for k, (_, _, v, extrude) in enumerate(PHASES):
            if extrude:
                b.extrude(seg(s_marks[k], s_marks[k + 1]), AUX_WIDTH_MM, v)
            else:
                b.coast(seg(s_marks[k], s_marks[k + 1]), v)
        b.writer.extruder_move(t["re"], profile.retract_speed_mm_s)
        b.extrude(seg(s_marks[3], s_marks[4]), t["w"], t["v"])
        b.writer.extruder_move(-t["re"], profile.retract_speed_mm_s)
        b.coast(seg(s_marks[4], s_marks[5]), DROOL_SPEED)
        b.writer.extruder_move(t["re"], profile.retract_speed_mm_s)
        b.extrude(seg(s_marks[5], s_marks[6]), AUX_WIDTH_MM, COOL_SPEED)
        b.end()
    b.frame_furniture(frame, title="start-stop")
    # Group labels in the content corners, outside the outer ring.
    x0, y0, x1, y1 = frame.content_mm
    corners = [(x0, y1 - LABEL_H_MM), (x1, y1 - LABEL_H_MM), (x0, y0 + LABEL_H_MM + 2.0), (x1, y0 + LABEL_H_MM + 2.0)]
    rng = f"Re{min(res):g}-{max(res):g}"
    for g, w in enumerate(widths):
        ids = [t["track"] for t in tests if t["group"] == g]
        x, y = corners[g % 4]
        for i, txt in enumerate((f"w{w:g}", rng)):
            tw = font.text_width_mm(txt, LABEL_H_MM)
            xl = x if x == x0 else x - tw
            b.label(txt, (xl, y - i * (LABEL_H_MM + 1.5) + (0 if g < 2 else LABEL_H_MM + 1.5)),
                    height_mm=LABEL_H_MM, for_tracks=ids)
    return b.build()
