"""Peer methods, for the bench: what other tools would report on the same data.

Duet3D (seed 004): on a constant-speed track with stepped extrusion, split the width
trace into sections between steps, flip every other one upside down (so every section
is a rise), average the sections (averaging *before* fitting avoids the bias from
periodic width offsets), fit  w(x) = A + B exp(-C x)  and report  PA = 1 / (C R),  R the
head speed (mm/s), x the distance since the step (mm), C (1/mm), PA (s).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import curve_fit


def duet3d_pa(s_mm, width_mm, step_len_mm: float, head_speed_mm_s: float,
              skip_mm: float = 0.0) -> float:
    """PA (s) by the Duet3D section-flip-average-exponential method (seed 004).

    s_mm, width_mm  samples along one constant-speed track whose commanded flow steps
                    every ``step_len_mm`` (mm) starting at s = 0
    """
    s = np.asarray(s_mm, dtype=float)
    w = np.asarray(width_mm, dtype=float)
    ok = np.isfinite(w)
    s, w = s[ok], w[ok]
    n_sec = int(np.floor(s.max() / step_len_mm))
    x = np.linspace(skip_mm, step_len_mm, 200, endpoint=False)
    secs = []
    for k in range(n_sec):
        sel = (s >= k * step_len_mm) & (s < (k + 1) * step_len_mm)
        if sel.sum() < 5:
            continue
        y = np.interp(x, s[sel] - k * step_len_mm, w[sel])
        secs.append(y if k % 2 == 0 else -y)
    if len(secs) < 2:
        raise ValueError("need at least two sections between steps")
    # flipped sections have the opposite offset: remove each parity's mean level first
    even = np.mean(secs[0::2], axis=0)
    odd = np.mean(secs[1::2], axis=0)
    avg = 0.5 * ((even - even[-1]) + (odd - odd[-1]))
    p0 = (0.0, avg[0] - avg[-1] if avg[0] != avg[-1] else -0.1, 5.0 / step_len_mm)
    (a, b, c), _ = curve_fit(lambda xx, a, b, c: a + b * np.exp(-c * xx), x, avg, p0=p0, maxfev=20000)
    return float(1.0 / (c * head_speed_mm_s))


# -- the classic "print a ladder of PA values and pick the best line" ----------------------
#: OrcaSlicer PA Line defaults (src/libslic3r/calib.cpp, REFERENCE.md "Peers").
ORCA_LINE = {"slow_mm": 20.0, "fast_mm": 40.0, "slow_mm_s": 20.0, "fast_mm_s": 100.0,
             "spacing_mm": 3.5}
ORCA_LADDER = {"direct": (0.0, 0.1, 0.002), "bowden": (0.0, 1.0, 0.02)}


def orca_ladder_values(bowden: bool) -> np.ndarray:
    """The K values (s) of OrcaSlicer's PA Line test: 0..0.1 step 0.002 (direct drive) or
    0..1.0 step 0.02 (Bowden)."""
    k0, k1, dk = ORCA_LADDER["bowden" if bowden else "direct"]
    return np.round(np.arange(k0, k1 + dk / 2, dk), 6)


def pa_line_manifest(profile, n_lines: int = 1):
    """Manifest of ``n_lines`` OrcaSlicer PA lines: each 20 mm at 20 mm/s, 40 mm at
    100 mm/s, 20 mm at 20 mm/s, at the nominal line width, lines 3.5 mm apart."""
    from patterns.builder import PatternBuilder
    from patterns.profile import load_profile

    # no retraction before a line: the firmware_pa effect applies K to retractions too
    # (fit/effects.py), which a real firmware does not, and would starve the line start
    prof = dataclasses.replace(load_profile(profile), retract_length_mm=0.0)
    L = ORCA_LINE
    b = PatternBuilder(prof, "pa-line", dict(L))
    b.set_z(b.layer_height_mm)
    x0 = 0.5 * (prof.bed_x_mm[0] + prof.bed_x_mm[1]) - 40.0
    y0 = prof.bed_y_mm[0] + 30.0
    for i in range(n_lines):
        y = y0 + i * L["spacing_mm"]
        b.begin("test", (x0, y), params={"line": i})
        seg = 1.0
        def pts(a, c):
            xs = np.arange(a, c + seg / 2, seg)
            return np.column_stack([x0 + xs, np.full(len(xs), y)])
        b.extrude(pts(0.0, L["slow_mm"]), b.line_width_mm, L["slow_mm_s"])
        b.extrude(pts(L["slow_mm"], L["slow_mm"] + L["fast_mm"]), b.line_width_mm, L["fast_mm_s"])
        b.extrude(pts(L["slow_mm"] + L["fast_mm"], 2 * L["slow_mm"] + L["fast_mm"]),
                  b.line_width_mm, L["slow_mm_s"])
        b.end()
    _, man = b.build()
    return man, b.line_width_mm


def ladder_pa(profile, truth: dict, *, spec: str = "pa", ladder=None, noise_sd_mm: float = 0.0,
              seed: int = 0, smooth_time_s: float = 0.0, end_skip_mm: float = 1.0,
              return_scores: bool = False):
    """K (s) a user would pick from an OrcaSlicer PA Line ladder printed on the virtual
    printer ``spec`` with the true values ``truth``.

    Every line is printed with the firmware PA effect (fit/effects.py ``FirmwarePA``:
    e' = e + K de/dt, smoothed over ``smooth_time_s``; 0 = Marlin LA) set to its ladder
    value. Lines are independent (a retraction and a travel separate them), so one line's
    timeline is simulated once per K. Widths at the measuring stations (every 0.25 mm)
    get white noise of sd ``noise_sd_mm``; the score of a line is its RMS deviation from
    the nominal width (the line "looks most even"), ``end_skip_mm`` off each end cap;
    the line with the smallest score wins. ``ladder``: K values (default the Orca ladder
    for the profile: Bowden when ``bowden_length_mm`` > 0).
    """
    from fit.context import SimContext
    from fit.model import build_model
    from patterns.manifest import sample_points
    from patterns.profile import load_profile

    prof = load_profile(profile)
    if ladder is None:
        ladder = orca_ladder_values(float(getattr(prof, "bowden_length_mm", 0.0)) > 0)
    ladder = np.asarray(ladder, dtype=float)
    man, w_nom = pa_line_manifest(prof, 1)
    samples = sample_points(man, ds_mm=0.25)
    ctx = SimContext.build(man, samples)
    model = build_model("firmware_pa+" + spec, prof)
    s = ctx.s_mm
    length = 2 * ORCA_LINE["slow_mm"] + ORCA_LINE["fast_mm"]
    keep = ctx.printed & (s >= end_skip_mm) & (s <= length - end_skip_mm)
    rng = np.random.default_rng(seed)
    scores = np.empty(len(ladder))
    for i, k in enumerate(ladder):
        m = model.with_values({**truth, "firmware_pa.k_s": float(k),
                               "firmware_pa.smooth_time_s": float(smooth_time_s)})
        w = m.predict(ctx, m.default_theta())[0]
        y = w[keep] + noise_sd_mm * rng.standard_normal(int(keep.sum()))
        scores[i] = float(np.sqrt(np.mean((y - w_nom) ** 2))) if np.all(np.isfinite(y)) else np.inf
    best = float(ladder[int(np.argmin(scores))])
    return (best, scores) if return_scores else best
