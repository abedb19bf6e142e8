"""spiral-step pattern (seed 004, Duet3D "Extrusion behaviour and pressure advance", part 2).

An Archimedean spiral r = r_in + (p / 2 pi) theta printed at constant head speed v while
the commanded bead width steps between levels (default 0.35 <-> 0.8 mm) every ``step_s``
seconds. Head speed is constant, so position along the spiral is proportional to time
(s = v t) and the width transient after each step is the extruder's step response:
for linear pressure advance w(s) - w_inf ~ exp(-s / (v tau)) (seed 004: PA = 1 / (C R)).

Steps are *not* synchronised with the angle around the centre, so periodic, direction-
dependent width artefacts average out (seed 004): the inner radius is chosen (within one
pitch) to spread the step boundaries' angles as evenly as possible (smallest mean
resultant length). Pitch = max width + gap, so neighbouring turns never touch. One spiral
per (head speed, step duration); the default step of 6 s lets a Bowden tau of 1 s settle.
"""
from __future__ import annotations

import itertools

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns import font, layout
from patterns.builder import PatternBuilder

NAME = "spiral-step"
SEG_MM = 1.0          # polyline segment (chord error < 1/(8 r_in) mm)
RAMP_SEG_MM = 0.05    # sub-steps of a width step where the firmware limits the extruder's jump
LABEL_H_MM = 3.5


def _boundaries_mm(v_mm_s, step_s, n_steps):
    return v_mm_s * step_s * np.arange(1, n_steps)


def _stepped_widths(profile, sp: dict, widths, h_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc-length stations s (mm) of a spiral and the commanded width (mm) of each segment
    between them: the levels ``widths`` cycled every step, each step taken in sub-steps
    RAMP_SEG_MM apart where the firmware slows the head for a change of extrusion rate
    (patterns/planner.py ``extruder_junction_limit_mm_s``: Klipper's
    instantaneous_corner_velocity, 1 mm/s by default). Taken at once, a 0.35 -> 0.8 mm step
    at 40 mm/s slowed a Klipper printer's head to 27 mm/s for ~0.3 mm, and bench_e2e's
    back-pressure fits read it confidently wrong (2 of 9 trusted fits with the truth outside
    their 99 % interval, |z| up to 3.6, where the same seeds held it before); not because
    the picture smooths the short bulge (the fit reads it as the measurement does since
    fit/observe.py, and the two stayed) but through the fast steps, which carry tau
    (docs/TRUST.md). In sub-steps of at most 0.9 of the limit the head keeps its speed, and
    the ramp lasts (n - 1) RAMP_SEG_MM / v: 1.25 ms at 40 mm/s for that step (n = 2)."""
    from patterns.planner import extruder_junction_limit_mm_s

    v = sp["speed_mm_s"]
    bounds = np.asarray(sp["boundaries_mm"], float)
    widths = np.asarray(widths, float)
    lim = extruder_junction_limit_mm_s(profile)
    ratio = bead_area_mm2(widths, h_mm) / profile.filament_area_mm2          # filament mm per mm
    jump = np.abs(np.diff(np.r_[ratio, ratio[0]])).max() if len(widths) > 1 else 0.0
    n_sub = 1 if lim is None or jump * v <= 0.9 * lim else int(np.ceil(jump * v / (0.9 * lim)))
    extra = [b + k * RAMP_SEG_MM for b in bounds for k in range(1, n_sub)]
    s = layout.resample_s(0.0, sp["length_mm"], SEG_MM, np.r_[bounds, extra])
    mid = 0.5 * (s[1:] + s[:-1])
    step_len = v * sp["step_s"]
    k = np.floor(mid / step_len).astype(int)
    level = k % len(widths)
    w = widths[level]
    if n_sub > 1:
        # the first n_sub - 1 segments after a boundary: equal steps of extrusion rate (the
        # bead's area is linear in its width at a fixed height, so equal steps of width)
        into = mid - k * step_len
        j = np.floor(into / RAMP_SEG_MM).astype(int)
        ramp = (k > 0) & (j < n_sub - 1)
        prev = widths[(k - 1) % len(widths)]
        w = np.where(ramp, prev + (w - prev) * (j + 1) / n_sub, w)
    return s, w


def _pick_r_in(r_min_mm, pitch_mm, boundaries_mm, n_try=24):
    """Inner radius in [r_min, r_min + pitch) that spreads the step angles the most."""
    best = None
    for r in r_min_mm + pitch_mm * np.arange(n_try) / n_try:
        R = layout.steps_angles_spread(layout.spiral_theta(r, pitch_mm, boundaries_mm))
        if best is None or R < best[0]:
            best = (R, r)
    return best[1], best[0]


def plan(profile, *, speeds_mm_s=(15.0, 30.0), step_s=(6.0,), n_steps=8, widths_mm=(0.35, 0.8),
         layer_height_mm=0.2, gap_mm=1.0, r_in_mm=4.0):
    """Spiral geometry (plain coordinates, centres relative to (0, 0) cell origin)."""
    speeds = [float(v) for v in np.atleast_1d(speeds_mm_s)]
    steps = [float(s) for s in np.atleast_1d(step_s)]
    widths = [float(w) for w in np.atleast_1d(widths_mm)]
    if len(widths) < 2:
        raise UserError("spiral-step needs at least two --widths levels to step between, e.g. 0.35,0.8")
    if min(widths) <= 0 or min(speeds) <= 0 or min(steps) <= 0 or n_steps < 2:
        raise UserError("spiral-step: widths, speeds and step durations must be > 0 and --steps >= 2")
    if max(speeds) > profile.max_velocity_mm_s:
        raise UserError(f"spiral-step: speed {max(speeds):g} mm/s exceeds the printer's max "
                        f"{profile.max_velocity_mm_s:g} mm/s: reduce --speeds")
    pitch = max(widths) + gap_mm
    spirals = []
    for v, st in itertools.product(speeds, steps):
        length = v * st * n_steps
        bnd = _boundaries_mm(v, st, n_steps)
        r0, spread = _pick_r_in(r_in_mm, pitch, bnd)
        r_out = layout.spiral_radius_for_length_mm(r0, length, pitch)
        label = f"{v:g}mm/s {st:g}s"
        spirals.append(dict(speed_mm_s=v, step_s=st, length_mm=length, r_in_mm=r0, r_out_mm=r_out,
                            pitch_mm=pitch, boundaries_mm=bnd, spread=spread, label=label,
                            cell_w=max(2 * r_out + max(widths), font.text_width_mm(label, LABEL_H_MM)) + 4.0,
                            cell_h=2 * r_out + max(widths) + LABEL_H_MM + 6.0))
    return spirals


def _pack(spirals, max_w):
    """Shelf packing of spiral cells into rows no wider than ``max_w``; returns (w, h)."""
    rows, cur, x = [], [], 0.0
    for sp in spirals:
        if cur and x + sp["cell_w"] > max_w:
            rows.append(cur)
            cur, x = [], 0.0
        sp["cell_x"] = x
        cur.append(sp)
        x += sp["cell_w"]
    rows.append(cur)
    y = 0.0
    for row in reversed(rows):           # first row at the top
        h = max(sp["cell_h"] for sp in row)
        for sp in row:
            sp["cell_y"] = y
            sp["row_h"] = h
        y += h
    width = max(sum(sp["cell_w"] for sp in row) for row in rows)
    return width, y


def generate(profile, *, speeds_mm_s=(15.0, 30.0), step_s=(6.0,), n_steps=8, widths_mm=(0.35, 0.8),
             layer_height_mm=0.2, gap_mm=1.0, r_in_mm=4.0):
    """G-code and manifest of the spiral-step pattern.

    speeds_mm_s  head speeds (mm/s), one spiral each (times each step_s)
    step_s       durations (s) of each width level
    n_steps      levels per spiral (the spiral lasts n_steps * step_s seconds)
    widths_mm    commanded bead widths (mm) cycled through at each step
    """
    from patterns.profile import load_profile
    profile = load_profile(profile)
    params = {"speeds_mm_s": list(map(float, np.atleast_1d(speeds_mm_s))),
              "step_s": list(map(float, np.atleast_1d(step_s))), "n_steps": int(n_steps),
              "widths_mm": list(map(float, np.atleast_1d(widths_mm))),
              "layer_height_mm": float(layer_height_mm), "gap_mm": float(gap_mm), "r_in_mm": float(r_in_mm)}
    spirals = plan(profile, speeds_mm_s=speeds_mm_s, step_s=step_s, n_steps=n_steps, widths_mm=widths_mm,
                   layer_height_mm=layer_height_mm, gap_mm=gap_mm, r_in_mm=r_in_mm)
    max_w, _ = layout.max_content_mm(profile)
    cw, ch = _pack(spirals, max_w)
    frame = layout.make_frame(profile, NAME, cw, ch, "reduce --speeds, --step-s or --steps")
    cx0, cy0 = frame.content_mm[0], frame.content_mm[1]
    b = PatternBuilder(profile, NAME, params, layer_height_mm=layer_height_mm)
    b.set_z(layer_height_mm)
    b.frame_prime(frame)
    widths = params["widths_mm"]
    for sp in spirals:
        centre = (cx0 + sp["cell_x"] + sp["cell_w"] / 2, cy0 + sp["cell_y"] + sp["r_out_mm"] + max(widths) / 2 + 2.0)
        sp["center_mm"] = centre
        s, w = _stepped_widths(profile, sp, widths, layer_height_mm)
        pts = layout.spiral_points(centre, sp["r_in_mm"], sp["pitch_mm"], s)
        b.begin("test", pts[0], group=sp["label"], params={
            "speed_mm_s": sp["speed_mm_s"], "step_s": sp["step_s"], "n_steps": int(n_steps),
            "widths_mm": widths, "pitch_mm": sp["pitch_mm"], "r_in_mm": round(sp["r_in_mm"], 4),
            "center_mm": [round(c, 4) for c in centre], "step_boundaries_mm": sp["boundaries_mm"].tolist(),
            "flows_mm3_s": [float(bead_area_mm2(x, layer_height_mm)) * sp["speed_mm_s"] for x in widths]})
        b.extrude(pts, w, sp["speed_mm_s"])
        b.end()
        sp["track"] = b._next_id - 1
    b.frame_furniture(frame, title=f"spiral-step h{layer_height_mm:g}")
    for sp in spirals:
        x, y = sp["center_mm"]
        b.label(sp["label"], (x, y + sp["r_out_mm"] + max(widths) / 2 + 2.0), height_mm=LABEL_H_MM,
                anchor="center", for_tracks=[sp["track"]])
    return b.build()
