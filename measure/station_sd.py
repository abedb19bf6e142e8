"""The one-sigma uncertainty of each measured width (mm): the edge fit's own sd made honest
by what the scan itself shows.

:func:`calibrated_sd` scales and floors the fits' sds per scan until they explain the
scatter of the widths about their smooth course (second differences along each track);
:func:`slope_sd` adds what a station's place along the track, as far as the registration
knows it (:func:`registration_place_sd`), moves its width where the width changes. Used by
measure/widths.py; the figures behind each constant are in the comment above it.
"""
from __future__ import annotations

import numpy as np
from scipy import optimize, special


#: calibrated_sd: second differences over this arc length (mm), in this many bins of the
#: formal variance, with the robust sd from this quantile of |d| (0.68: a little more of the
#: tails than the median, still blind to the few steps and blobs of a track). The lag was
#: 1 mm until the strips were despeckled: the despeckled station noise fell 3x on a
#: flatbed render saved as JPEG 15, what its blocks share over a millimetre much less, and
#: 1 mm left 53 % of its errors within their sd (62 % before); 2 mm gives 60 %, the
#: bench_realism scenes within 0.02 of 1 mm's coverage.
SD_LAG_MM = 2.0
SD_BINS = 5
SD_QUANTILE = 0.68


def registration_place_sd(registration, xy_mm, tangent) -> np.ndarray:
    """Along-track sd (mm) of where the registration puts each station (0 when it does not say)."""
    f = getattr(registration, "place_sd_mm", None)
    return np.zeros(len(xy_mm)) if f is None else np.nan_to_num(f(xy_mm, tangent))


def slope_sd(track, s_mm, w_mm, sd_mm, valid, place_sd_mm, half_mm: float = 0.5,
             k_sig: float = 3.0) -> np.ndarray:
    """Width sd (mm) from not knowing where along its track a station is: |dw/ds| x
    ``place_sd_mm`` (errors in the independent variable carried through the slope: the
    effective-variance method, Orear 1982, Am. J. Phys. 50, 912).

    The slope (mm/mm) is the larger of two estimates from the valid stations of the same
    track: the least-squares line over +-``half_mm``, its square debiased by its variance
    from the widths' sds (so that noise alone adds little: ~0.2 um per um of sd at a 0.2
    mm place sd); and, where a width steps faster than that line can follow, the one-sided
    differences to the neighbours that exceed ``k_sig`` sds of their two widths (the RMS
    of the two sides: a step's corner station has a flat side and a steep one). 0 at
    invalid stations and where ``place_sd_mm`` is 0 (markers hold the pose to ~0.01 mm).

    Why: registered from point hints, the parallel tracks of the foreign printer's probe
    (bench/foreign_printer.py) sat 0.04-0.24 mm off along their length (the pose's own
    sd there: 0.08-0.28 mm), and the stations on the slow-to-fast width step (slope
    0.4-0.6) read 25-105 um off with sds of 6-7 um: 63 % of a right model's chi2 on 1 %
    of its stations."""
    track, s = np.asarray(track), np.asarray(s_mm, float)
    w, sd = np.asarray(w_mm, float), np.asarray(sd_mm, float)
    place = np.asarray(place_sd_mm, float)
    out = np.zeros(len(s))
    ok = np.asarray(valid, bool) & np.isfinite(w) & np.isfinite(sd) & (place > 0)
    for t in np.unique(track[ok]):
        i = np.flatnonzero((track == t) & ok)
        i = i[np.argsort(s[i], kind="stable")]
        if len(i) < 2:
            continue
        ss, ww, vv = s[i] - s[i].mean(), w[i], sd[i] ** 2     # centred: the sums cancel less
        # windowed least-squares slope and its variance sum((s_j - mean)^2 var_j) / Sxx^2,
        # every station's window at once from cumulative sums
        cum = [np.concatenate([[0.0], np.cumsum(v)])
               for v in (np.ones_like(ss), ss, ww, ss * ss, ss * ww, vv, ss * vv, ss * ss * vv)]
        lo = np.searchsorted(ss, ss - half_mm, "left")
        hi = np.searchsorted(ss, ss + half_mm, "right")
        n, sx, sy, sxx, sxy, sv, ssv, sssv = (q[hi] - q[lo] for q in cum)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = sx / n
            vxx = sxx - sx * mean
            g = (sxy - mean * sy) / vxx
            var_g = (sssv - 2 * mean * ssv + mean * mean * sv) / vxx ** 2
            g2 = np.where((n >= 3) & (vxx > 1e-12), np.maximum(g * g - var_g, 0.0), 0.0)
        ds = np.maximum(np.diff(ss), 1e-6)
        dw2 = np.diff(ww) ** 2
        step = (dw2 > k_sig ** 2 * (vv[1:] + vv[:-1])) & (ds <= 2 * half_mm)
        side = np.where(step, (dw2 - vv[1:] - vv[:-1]) / ds ** 2, 0.0)
        both = (np.concatenate([[0.0], side]) + np.concatenate([side, [0.0]])) / 2
        out[i] = np.sqrt(np.maximum(g2, both))
    return out * np.where(ok, place, 0.0)


def scatter_factor(track, w, sd, valid, rho=None) -> float:
    """Factor >= 1 on the fit sd so that it explains the observed station-to-station scatter:
    the station's own error (``width_sd_own_mm``), what the fit's white term takes.

    Second differences d2 = w[i-1] - 2 w[i] + w[i+1] along a track remove the smooth
    (physical) width changes; for errors whose neighbours correlate by rho_i (station i with
    i - 1; ``rho``, :func:`neighbour_corr`, None: 0) and no further, var(d2) =
    (6 - 4 (rho_i + rho_(i+1))) sd^2: 6 sd^2 for independent ones, 2.4 sd^2 despeckled
    (dividing by 6 there read the own error 1.6x small). The fit sd misses
    correlated noise (JPEG blocks, texture), which shows up here. Robust (MAD) so steps
    and blobs do not count.
    """
    same = (track[1:-1] == track[:-2]) & (track[1:-1] == track[2:])
    ok = same & valid[1:-1] & valid[:-2] & valid[2:]
    if ok.sum() < 30:
        return 1.0
    r = np.zeros(len(track)) if rho is None else np.asarray(rho, dtype=float)
    d2 = ((w[:-2] - 2 * w[1:-1] + w[2:]) / np.sqrt(6.0 - 4.0 * (r[1:-1] + r[2:])))[ok]
    observed = 1.4826 * np.median(np.abs(d2 - np.median(d2)))
    predicted = np.median(sd[1:-1][ok])
    return float(max(1.0, observed / predicted)) if predicted > 0 else 1.0


def calibrated_sd(track, s_mm, w, sd, valid, lag_mm: float = SD_LAG_MM, bins: int = SD_BINS):
    """Per-station sd (mm) rescaled so that it explains the scatter the scan itself shows:
    sd' = sqrt((k sd)^2 + f^2), k >= 1, f >= 0 (mm). Returns (sd', k, f).

    Second differences d_i = w(s_i - L) - 2 w(s_i) + w(s_i + L) along a track remove the
    smooth (physical) width changes; for errors independent over L their variance is
    v_i = sd(s_i - L)^2 + 4 sd(s_i)^2 + sd(s_i + L)^2 when the sds are right, and
    k^2 v_i + 6 f^2 under the model. Stations are put in ``bins`` quantile bins of v; in
    each the robust variance of d (``SD_QUANTILE`` of |d|, steps and blobs do not count)
    gives one equation, and k^2 - 1 and f^2 come from non-negative least squares: a scale
    where the errors grow with the formal sd, a floor where they do not. Never below the
    edge fit's own sd (k, f = 1, 0 when the scatter is smaller or there are < 30 stations a bin).

    Why a floor and a lag of L = ``SD_LAG_MM`` (1 mm then; 2 mm since the strips are
    despeckled, see SD_LAG_MM), not one factor on adjacent stations:
    on 600 dpi renders with every phenomenon (bench_realism) the errors are 3.4-7 um
    whatever the formal sd (2-14 um) and correlated between neighbours (0.29-0.5 at
    0.25 mm): one factor from adjacent stations (1.7) left the smallest-sd fifth's errors at
    1.6 x their sd and the largest at 0.5 x; this gives 0.94 and 0.75 (k 1.05, f 3.3 um;
    Bowden 0.89 and 0.78; light-plate JPEG 1.80 / 1.18 -> 1.33 / 1.19 with k 3.0, f 8.5 um).
    """
    track, s_mm, w, sd = (np.asarray(a) for a in (track, s_mm, w, sd))
    valid = np.asarray(valid, dtype=bool)
    triples = []                # (before, station, after) indices
    for tid in np.unique(track[valid]):
        on = np.flatnonzero((track == tid) & valid)
        if len(on) < 3:
            continue
        on = on[np.argsort(s_mm[on], kind="stable")]
        s = s_mm[on]
        # the valid stations nearest L before and after (flags leave gaps in the grid)
        a, b = _nearest(s, s - lag_mm), _nearest(s, s + lag_mm)
        ok = (np.abs(s[a] - (s - lag_mm)) < 0.25 * lag_mm) & (np.abs(s[b] - (s + lag_mm)) < 0.25 * lag_mm)
        triples.append(np.column_stack([on[a[ok]], on[ok], on[b[ok]]]))
    if not triples or sum(len(x) for x in triples) < 30 * bins:
        return sd, 1.0, 0.0
    i, j, k_ = np.concatenate(triples).T
    d = w[i] - 2 * w[j] + w[k_]
    d = d - np.median(d)
    v = sd[i] ** 2 + 4 * sd[j] ** 2 + sd[k_] ** 2
    good = np.isfinite(d) & np.isfinite(v)
    d, v = d[good], v[good]
    if len(d) < 30 * bins:
        return sd, 1.0, 0.0
    c = 1.0 / special.ndtri(0.5 + SD_QUANTILE / 2)
    edges_v = np.quantile(v, np.linspace(0.0, 1.0, bins + 1))
    keep = np.ones(len(d), bool)
    for _ in range(2):
        A, y = [], []
        for b0, b1 in zip(edges_v[:-1], edges_v[1:]):
            m = (v >= b0) & (v <= b1) & keep
            if m.sum() < 10:
                continue
            vm = np.mean(v[m])      # rows in units of their own variance: each bin counts alike
            A.append([1.0, 6.0 / vm])
            y.append((c * np.quantile(np.abs(d[m]), SD_QUANTILE)) ** 2 / vm - 1.0)
        if len(A) < 2:
            return sd, 1.0, 0.0
        (k2m1, f2), _ = optimize.nnls(np.array(A), np.array(y))
        # second pass without the flow steps and blobs the first one still counted (4 %
        # of the stations of a track with one step 1 mm either side of it read k 1.02-1.07
        # for 1.00): beyond 4 sd of the model they are not measurement error
        keep = np.abs(d) <= 4.0 * np.sqrt((1.0 + k2m1) * v + 6.0 * f2)
    k, f = float(np.sqrt(1.0 + k2m1)), float(np.sqrt(f2))
    return np.sqrt((k * sd) ** 2 + f ** 2), k, f


def _nearest(s, target):
    """Index of the element of the sorted ``s`` nearest each ``target``."""
    idx = np.clip(np.searchsorted(s, target), 1, len(s) - 1)
    return np.where(np.abs(s[idx - 1] - target) <= np.abs(s[idx] - target), idx - 1, idx)
