"""Peer methods, for the bench: what other tools would report on the same data.

Duet3D (seed 004): on a constant-speed track with stepped extrusion, split the width
trace into sections between steps, flip every other one upside down (so every section
is a rise), average the sections (averaging *before* fitting avoids the bias from
periodic width offsets), fit  w(x) = A + B exp(-C x)  and report  PA = 1 / (C R),  R the
head speed (mm/s), x the distance since the step (mm), C (1/mm), PA (s).
"""
from __future__ import annotations

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
