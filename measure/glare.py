"""Where the scan's light is: the axis of the glare streaks, and each station's angle to it.

A glossy flank that faces the light throws a highlight into the camera (Blinn-Phong: the
highlight needs the flank's normal near the half vector between light and view), so the
stations whose edge pair needed a glare streak (measure/widths.py) have normals that point
along one bed axis, the light's. Their doubled-angle mean gives that axis (a bead printed
either way is the same cylinder to the light: period pi); each station's angle between its
normal and the axis (0 = the flank faces the light, 90 = it runs along the light) is
written to the widths table for the fit (fit/effects.py ViewLight).

Why: on bench_e2e's back-pressure flatbed renders (every phenomenon, lamp along y) beads
along x read ~2.5 um wider than beads along y, uniformly along the track; one offset for
all beads (`scan_bias`) cannot take that, and it pulled Kb 7 % high (fit/influence.py).
Taken out before the fit by band medians it lowered Kb on 12 of 12 seeds, but only the
fit knows the true width along a track (a Bowden's slow rise read as 4-10 um of glare), so
the correction belongs there.
"""
from __future__ import annotations

import numpy as np

#: Streak stations needed to find the light's axis, and how well their normals must agree
#: on it (|mean of exp(2 i phi)|; one light: ~0.9 on the glare renders).
MIN_STREAK = 20
AXIS_COHERENCE = 0.5


def light_axis(nx, ny, streak) -> float | None:
    """The light's axis (rad, modulo pi, bed frame) from the normals of the glare-streak
    stations, or None when there are too few or they do not agree on one axis."""
    streak = np.asarray(streak, dtype=bool)
    if streak.sum() < MIN_STREAK:
        return None
    phi = np.arctan2(np.asarray(ny, dtype=float)[streak], np.asarray(nx, dtype=float)[streak])
    z = np.mean(np.exp(2j * phi))
    if abs(z) < AXIS_COHERENCE:
        return None
    return float(np.angle(z) / 2.0)


def angle_to_light_deg(nx, ny, axis_rad: float) -> np.ndarray:
    """Angle (deg, 0-90) between each normal (nx, ny) and the light's axis."""
    phi = np.arctan2(np.asarray(ny, dtype=float), np.asarray(nx, dtype=float))
    d = np.abs(np.angle(np.exp(1j * (phi - axis_rad))))
    return np.degrees(np.minimum(d, np.pi - d))
