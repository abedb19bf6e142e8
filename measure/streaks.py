"""Glare streaks on a bead's flank: which stations' edge pairs take one, and at what depth.

A specular streak brightens the flank that faces the light (Blinn-Phong). Where it does,
measure/widths.py refits the station's edge pair with a streak line inside that edge
(measure/edges.py :func:`~measure.edges.fit_streak`) on either side, and keeps the better
of the two when it explains significantly more, F = [(RSS_plain - RSS_streak) / 2] /
[RSS_streak / (M - 7)] > ``STREAK_F``, and the streaks' sides agree with one light over the
scan (``STREAK_COHERENCE``). Widths in mm; the figures behind each constant are in the
comment above it and in docs/MEASUREMENT.md.
"""
from __future__ import annotations

import numpy as np

from measure import edges


#: F statistic above which a glare streak replaces the plain edge pair. Streak-free renders
#: (bead profile shaded, no glare) give F <= 27 on 300 stations, median 0.8 (99th
#: percentile 22); the streaks that bias the plain fit by +5..+12 um give F 300-600.
STREAK_F = 30.0
#: Streaks are believed only when at least this many stations show one and their sides,
#: as bed directions, agree: |mean of side x normal| >= STREAK_COHERENCE (glare renders
#: 0.91-0.95; edge-model misfit on translucent or phone renders 0.03-0.49).
STREAK_MIN_STATIONS = 20
STREAK_COHERENCE = 0.6
#: A streak is looked for only on beads at least this many blurs wide: on a narrower one
#: (a phone's 0.25 mm beads under 0.16 mm of blur, 1.6 blurs) the blurred streak is one more
#: bump of the bead's own shape, and trades with its contrast and width (streak fits read
#: those beads 52 um wide where the plain fit read -7 um; 0.5 mm beads, 3.2 blurs: -1 um).
STREAK_MIN_BLURS = 2.5
#: Streaks sit at one depth for the scan (:func:`_common_depth`) where the blur is wider than
#: this many flank radii (h/2): below it the free depth is read station by station (600
#: dpi flatbed, blur 0.03-0.05 mm for a 0.1 mm radius: one common depth moved the glare
#: row's bias -2.7 -> -4.2 um and the Bowden's seed 0 +3.6 -> +6.8 um).
STREAK_COMMON_BLUR = 1.0
#: The streak's depth common to a scan (:func:`_common_depth`) is searched on this grid
#: (fraction of the flank's radius h/2) over this many stations.
STREAK_DEPTH_STEP = 0.05
STREAK_DEPTH_SAMPLE = 400
#: On scans with >= this x STREAK_MIN_STATIONS fitted stations, one in this many is tried
#: for a streak first (:func:`with_glare_streaks`).
STREAK_SCREEN_EVERY = 8
#: ... and the light those show is believed only beyond this many times the coherence n
#: passes have with their sides at random (1 / sqrt(n)): a streak-free flatbed render,
#: despeckled, had 2 of 181 pass on one side (coherence 1), then 5 at 0.6, and the full
#: test ran for nothing (50 of 1446 passed, coherence 0.08). At 2.0, 4 of 4 on one side
#: passed the bar (1.0; chance 1 in 8 on parallel tracks) and the full test ran again for
#: nothing (42 passed, coherence 0.19); at 2.5 no n < 7 passes by chance.
STREAK_SCREEN_CHANCE = 2.5
#: ... and when those agree on the light this well, the others are tried on the side that
#: faces it first (the screen's coherence was within 0.11 of the full test's on six
#: renders' scans, 0.32-0.87).
STREAK_SURE_COHERENCE = 0.7


def _streak_fits(t, y, params, rows, sides, height_mm, fixed_s, wts, shadows=None, flank=edges.STREAK_FLANK):
    """Streak fits (len(rows), 8) of the stations ``rows``, each on its side (``sides``,
    -1 / +1), from ``params``; where ``shadows`` (a :class:`measure.shadows.Shadows`) has a
    shelf at a station it is fitted along (the lamp that lights one flank shades the
    plate beside the other)."""
    n = len(rows)
    k = len(edges.STREAK_PARAMS)
    out = edges.ProfileFit(np.full((n, k), np.nan), np.full((n, k), np.nan), np.full(n, np.nan), np.zeros(n, bool))
    shade = np.zeros(n) if shadows is None else shadows.side[rows]
    for side in (-1.0, 1.0):
        for sh in (-1.0, 0.0, 1.0):
            j = np.flatnonzero((sides == side) & (shade == sh))
            if len(j) == 0:
                continue
            i = rows[j]
            kw = {} if sh == 0.0 else dict(shade=sh, shelf=shadows.shelf[i])
            f = edges.fit_streak(t[i], y[i], params[i], side, height_mm[i], fixed_s=fixed_s, weights=wts[i],
                                 flank=flank, **kw)
            out.params[j], out.sd[j], out.rms[j], out.ok[j] = f.params[:, :k], f.sd[:, :k], f.rms, f.ok
    return out


def with_glare_streaks(t, y, fit, wts, height_mm, normals, fixed_s: bool = True, shadows=None):
    """The plain fit, with stations where a glare streak explains significantly more
    (F > STREAK_F, module docstring) on the side that faces the scan's light replaced by
    the streak fit; and which were. normals (N, 2): profile direction (bed frame).

    The streak fits cost more than the rest of the measurement: on large scans one station
    in STREAK_SCREEN_EVERY is tried first, on both sides, and when those show no coherent
    light (under half the stations or half the coherence the full test needs) the scan has
    no glare and the rest are not tried. When they show a light beyond doubt (coherence >=
    STREAK_SURE_COHERENCE), the rest are tried on the side facing it, and on the other
    side only where that one passes; in between, on both sides, since then the full test's
    coherence decides (a light plate with every phenomenon: 0.32 on the screen, 0.28 on
    all stations, no streaks; trying the facing side first made it 0.9 and the widths'
    RMS 22 -> 40 um). ``shadows`` (measure/shadows.py): the lamp's shadow already found
    at some stations, kept in their streak fits."""
    n = len(t)
    streak = np.zeros(n, bool)
    idx = np.flatnonzero(fit.ok & (fit.params[:, 4] >= STREAK_MIN_BLURS * fit.params[:, 5]))
    if len(idx) == 0:
        return fit, streak
    k = STREAK_SCREEN_EVERY
    light = None
    if len(idx) >= k * STREAK_MIN_STATIONS:
        sub = idx[::k]
        use, _, toward = _streak_test(t, y, fit, wts, height_mm, normals, sub, fixed_s, shadows=shadows)
        light = toward[use].mean(axis=0) if use.any() else np.zeros(2)
        if (use.sum() < 0.5 * STREAK_MIN_STATIONS / k
                or np.hypot(*light) < max(0.5 * STREAK_COHERENCE, STREAK_SCREEN_CHANCE / np.sqrt(use.sum()))):
            return fit, streak
        if np.hypot(*light) < STREAK_SURE_COHERENCE:
            light = None
    # The lamp whose shadow the beads show lights their other flank: a "streak" on the
    # shadow's side is the shadow misfitted (where the picture blurs it over, or a colour
    # axis keeps little of a grey shadow: +66 um on the beads across the lamp of a light
    # plate's flatbed scan in glare, its streaks on the shadow's side at 99 % of them).
    lamp = _lamp(shadows)
    if lamp is not None:
        light = lamp
    use, best, toward = _streak_test(t, y, fit, wts, height_mm, normals, idx, fixed_s, light, shadows=shadows)
    # One light lights one flank: the streak's side, as a bed direction (side x normal),
    # points the same way at every station. Edge-model misfit that merely looks like a
    # streak (translucent edges: 6 % of stations passed the F test, 57 % of those then
    # outside 3 sd) picks its side at random.
    light = toward[use].mean(axis=0) if use.sum() >= STREAK_MIN_STATIONS else np.zeros(2)
    if np.hypot(*light) < STREAK_COHERENCE:
        use[:] = False
    else:
        use &= toward @ (light if lamp is None else lamp) > 0
    streak[idx[use]] = True
    side = np.sign(np.einsum("ij,ij->i", toward, normals[idx]))
    best = _common_depth(t, y, fit, wts, height_mm, idx, use, best, side, fixed_s, shadows)
    params, sd, rms = fit.params.copy(), fit.sd.copy(), fit.rms.copy()
    params[idx[use]] = best.params[use, :6]
    sd[idx[use]] = best.sd[use, :6]
    rms[idx[use]] = best.rms[use]
    return edges.ProfileFit(params, sd, rms, fit.ok), streak


def _common_depth(t, y, fit, wts, height_mm, idx, use, best, side, fixed_s, shadows=None):
    """The streak fits ``best`` of the stations ``idx[use]`` (streak on ``side``, -1 / +1)
    refitted with the streak's depth held at one value for the scan: one light over the
    scan puts the highlight where the flank's slope is half its zenith angle, at one depth
    (as a fraction of the flank's radius h/2). Each keeps its own depth unless at least
    STREAK_MIN_STATIONS free fits ended inside the depth's bounds.

    That depth maximises the joint likelihood of those stations (a subsample of
    STREAK_DEPTH_SAMPLE), each with its own noise level: sum_i m_i ln RSS_i(d) is least,
    over a grid of STREAK_DEPTH_STEP refined by a parabola through the least three.

    Where the blur is wider than the flank (a phone's 0.16 mm against 0.1 mm), a free depth
    trades with the edge: on a phone render (direct drive, seed 0) 80 % of the free streak
    fits ended on a bound of the depth, those at 0.4 reading the beads 11-13 um narrow and
    those at 1.0 scattering 64-100 um (0.5 and 1.6 mm beads), and the width's sd, with the
    depth free in its covariance, 15x its peers': 70 % of the streak stations were
    flagged. Held at 0.71 the streak stations read within 3 um of the others (6-9 um
    RMS). Why not every streak station's likelihood: the renderer's shaded crown is
    no edge pair, and the stations whose depth went to the bound pulled the common one
    there too (0.40; the widths 10-14 um narrower than the stations without a streak).
    Nor the median of the free depths: 0.77 on synthetic profiles whose depth is 0.70."""
    on = np.flatnonzero(use & best.ok)
    h = np.broadcast_to(np.asarray(height_mm, float), (len(t),))
    if len(on) == 0 or np.median(fit.params[idx[on], 5]) <= STREAK_COMMON_BLUR * np.median(h[idx[on]]) / 2:
        return best
    lo, hi = edges.STREAK_FLANK
    frac = best.params[on, 7] / (0.5 * h[idx[on]])
    free = on[(frac > lo + STREAK_DEPTH_STEP / 5) & (frac < hi - STREAK_DEPTH_STEP / 5)]
    if len(free) < STREAK_MIN_STATIONS:
        return best

    def refit(o, d):
        return _streak_fits(t, y, fit.params, idx[o], side[o], h, fixed_s, wts, shadows, flank=(d, d))

    grid = np.arange(lo, hi + 1e-9, STREAK_DEPTH_STEP)
    sub = free[:: max(1, len(free) // STREAK_DEPTH_SAMPLE)]
    m = wts[idx[sub]].sum(axis=1)
    rss = np.array([np.where(f.ok, f.rms ** 2 * np.maximum(m - 7, 1), np.nan)
                    for f in (refit(sub, d) for d in grid)])
    every = np.isfinite(rss).all(axis=0)
    cost = (m[every] * np.log(np.maximum(rss[:, every], 1e-300))).sum(axis=1)
    j = int(np.clip(np.argmin(cost), 1, len(grid) - 2))
    c0, c1, c2 = cost[j - 1:j + 2]
    curv = c0 - 2 * c1 + c2
    d = float(np.clip(grid[j] + (0.5 * STREAK_DEPTH_STEP * (c0 - c2) / curv if curv > 0 else 0.0), lo, hi))
    f = refit(on, d)
    # a station whose held fit failed keeps its free one
    on, f = on[f.ok], edges.ProfileFit(f.params[f.ok], f.sd[f.ok], f.rms[f.ok], f.ok[f.ok])
    out = edges.ProfileFit(best.params.copy(), best.sd.copy(), best.rms.copy(), best.ok.copy())
    out.params[on], out.sd[on], out.rms[on] = f.params, f.sd, f.rms
    return out


def _lamp(shadows):
    """The bed direction toward the lamp whose shadows the beads show (unit; modelled or
    blurred over), or None."""
    if shadows is None:
        return None
    away = shadows.away if shadows.away is not None else shadows.unresolved
    return None if away is None else -np.asarray(away, float) / np.hypot(*away)


def _streak_test(t, y, fit, wts, height_mm, normals, idx, fixed_s, light=None, shadows=None):
    """For the stations ``idx``: whether a streak passes the F test, the better side's fit,
    and that side as a bed direction (side x normal). ``light`` (a bed direction): try the
    side that faces it, and the other only where that one passes; None: both everywhere."""
    n = len(idx)
    m_eff = wts[idx].sum(axis=1)
    # a station with a shadow's shelf: its fit had the shelf's reach and penumbra free (the
    # depth held), which its streak fits hold
    k0 = np.full(n, 5 if fixed_s else 6) + (0 if shadows is None else 2 * (shadows.side[idx] != 0))
    rss0 = fit.rms[idx] ** 2 * np.maximum(m_eff - k0, 1)
    best_rss = np.full(n, np.inf)
    best_side = np.zeros(n)
    k = len(edges.STREAK_PARAMS)
    best = edges.ProfileFit(np.full((n, k), np.nan), np.full((n, k), np.nan), np.full(n, np.nan), np.zeros(n, bool))

    def try_sides(on, sides):
        for side in (-1.0, 1.0):
            o = on[sides == side]
            if len(o) == 0:
                continue
            f = _streak_fits(t, y, fit.params, idx[o], np.full(len(o), side), height_mm, fixed_s, wts, shadows)
            rss = np.where(f.ok, f.rms ** 2 * np.maximum(m_eff[o] - k0[o] - 2, 1), np.inf)
            better = rss < best_rss[o]
            j = o[better]
            best_rss[j], best_side[j] = rss[better], side
            best.params[j], best.sd[j] = f.params[better], f.sd[better]
            best.rms[j], best.ok[j] = f.rms[better], f.ok[better]

    def passes():
        with np.errstate(invalid="ignore"):
            F = 0.5 * (rss0 - best_rss) / np.maximum(best_rss / np.maximum(m_eff - k0 - 2, 1), 1e-300)
        return np.isfinite(F) & (F > STREAK_F) & (best.params[:, 6] > 0)

    every = np.arange(n)
    if light is None:
        try_sides(np.repeat(every, 2), np.tile([-1.0, 1.0], n))
    else:
        # the side facing the light first; the other only where that one passes, to see
        # which explains more (misfit that merely looks like a streak fits either side)
        facing = np.where(normals[idx] @ np.asarray(light, float) >= 0, 1.0, -1.0)
        try_sides(every, facing)
        cand = np.flatnonzero(passes())
        try_sides(cand, -facing[cand])
    return passes(), best, best_side[:, None] * normals[idx]
