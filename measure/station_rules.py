"""Rules that judge a measured station by its track's other stations (measure/widths.py
calls them after the edge fits; each returns a boolean mask over the stations).

A single profile can look like a good bead and still not be one: a logo edge among failed
fits (:func:`isolated`, :func:`enclosed`), a string of ooze running across the track
(:func:`oblique`), the strip mixing two widths where the bead changes fast (:func:`steep`),
a bead tip beside a station that saw no bead (:func:`beside_absence`), a one-station
misreading inside a bead seen on both sides (:func:`dropouts`), a fit far noisier than its
peers (:func:`unfit`). Stations are every 0.25 mm along a track; lengths are in mm along
the track (``s_mm``), widths in mm. The measurements behind each threshold are in the
comment above it and in docs/MEASUREMENT.md.
"""
from __future__ import annotations

import numpy as np


#: A valid station is flagged "isolated" when fewer than ISOLATED_FRACTION of its track's
#: stations within +-ISOLATED_HALF_MM (mm) are valid among those valid or flagged for a bad
#: profile (:func:`isolated`). End-to-end render (seed 7, orange beads over light-grey
#: plate logos): 5 stations 0.3-0.5 mm too wide, in stretches where 2 of 15 stations
#: passed, took the fit to chi2_nu 61 and Kb 24x the truth; flagged, the scan's RMS error
#: fell 24.9 -> 6.0 um (on the saved flatbed scene with every phenomenon, direct drive:
#: 8.8 -> 5.4 um) for 1-2 % of the stations.
ISOLATED_HALF_MM = 0.75
ISOLATED_FRACTION = 0.4
#: ... and when its run of valid stations lies inside contamination and reads another
#: width than the bead around it (:func:`enclosed`): a logo or letter on the plate beside
#: the bead, where it reaches the profile window's end, flags the station ``background``;
#: where it lies inside the window next to the bead, the edge pair takes it for part of
#: the bead and the window's ends see plain plate. On bench_realism's 35 deg phone photo
#: (direct drive, seed 1) 6 stations of a 1.6 mm bead read 2.12-2.30 mm with sds of
#: 15-25 um, between `background`+`steep` blocks 1.75 mm apart: 36 % of the scan's
#: squared error. The run is bounded by stations at most ENCLOSED_MM apart (twice
#: DROPOUT_REACH_MM, the span a dropout may have), with a contaminated flag in the block
#: on each side, and its median differs from the median of the valid stations within
#: ENCLOSED_REACH_MM by more than ENCLOSED_DEVIATION_MM. Without the width test (any run
#: so bounded) the rule took 9 % of realdata StartStopTestPLA1's valid stations (47.8 ->
#: 38.8 %), stations only 2x the scan's typical deviation; with it 1.2 points (46.6 %).
ENCLOSED_MM = 2.0
ENCLOSED_REACH_MM = 4.0
ENCLOSED_DEVIATION_MM = 0.1
#: A station within this (mm) of a station of its track that saw no bead (``missing``) has
#: the bead's tip in its strip or its despeckling window (measure/widths.py STRIP_MM / 2 +
#: SPECK_MM / 2): flagged "end" (:func:`beside_absence`).
TIP_REACH_MM = 0.35
#: A station that saw no bead, with stations of its track that saw one within this (mm)
#: before and after it, is a ``dropout`` (:func:`dropouts`): a misdetection, not an absence.
#: A printer that stops and restarts the flow tapers the bead out and in again over the
#: pressure's time constant at the head's speed (0.04 s at 20 mm/s is 0.8 mm, a Bowden's
#: 0.8 s is 16 mm) plus a nozzle's width each way, so a bead it interrupted is gone for
#: more than a millimetre. On bench_realism's 35 deg phone photos the narrowest beads
#: (0.25 mm, 1.5 blurs wide) were called missing at 3-157 stations of six scenes, most
#: one at a time between stations that showed them (dropouts now: 131 / 153 of 138 / 157
#: on the direct drive's seeds 1 and 0); the fit took each for a bead narrower than a
#: pixel, and those terms, independent of the wobble that ties the valid widths together,
#: pulled the width offset 25-34 um too negative (widths after the fit's offset 30.8 /
#: 31.9 um RMS; 26.3 / 20.8 with the dropouts; docs/MEASUREMENT.md, "A bead seen on both
#: sides of a gap").
DROPOUT_REACH_MM = 1.0
#: A station whose measured width changes faster than this along the track (mm/mm) is
#: flagged "steep" (:func:`steep`). Over five flatbed scenes of the virtual printer at the
#: truth (stop-mid-path direct drive and Bowden, spiral Bowden and direct drive,
#: start-stop direct drive) the 0-44 such stations read 3.5-8.8 um RMS from the model
#: through the measurement's kernel, the others 0.6-0.9 um; on the RetractTest the restore
#: bulges read 12-24 um wide.
STEEP_SLOPE = 0.2
#: Flags of a profile that something else than the bead spoiled: what :func:`isolated` and
#: :func:`enclosed` count as failed around a station that passed.
CONTAMINATED_FLAGS = ("fit", "glare", "blob", "oblique", "faint", "background")
#: A valid station is flagged "oblique" when the fitted centres of its track's valid
#: stations within +-ISOLATED_HALF_MM run across the track: slope |dc/ds| > OBLIQUE_SLOPE
#: (8.5 deg) at more than OBLIQUE_T standard errors (:func:`oblique`). A string of ooze
#: crossing a line that never printed passed as a 0.16 mm "bead" for 2.3 mm (slope 0.63,
#: t 560-1550); over 45,000 printed stations of four scenes (flatbed strings, flatbed and
#: phone with every phenomenon, light-plate JPEG) the largest was 0.29 (grain-jittered
#: centres, t <= 23) and no printed station reached both.
OBLIQUE_SLOPE = 0.15
OBLIQUE_T = 50.0
#: A station whose fit sd or relative residual exceeds this multiple of its track's median is flagged.
OUTLIER_FACTOR = 4.0
#: ... but a width whose sd is at most this (mm) is kept whatever its peers' sd: it carries
#: its own weight. On 600 dpi renders with every phenomenon the peers' median sd was 1.6 um,
#: so the rule flagged 1,009 stations of sd 7-18 um (12 % of the direct-drive scene, 10 %
#: of the Bowden one) whose widths erred 9.6 um RMS (8.9 for the valid ones) with |error|
#: > 3 sd on 0.8 %: honest widths, not contaminated profiles (those misfit: the residual
#: rule stays). Kept up to 15 um.
SD_OUTLIER_MIN_MM = 0.015


def unfit(width_cmd_mm, sd_mm, sd_ref_mm, rel_rms, rel_rms_ref):
    """Stations whose edge fit is not to be trusted (bool array): a relative residual over
    OUTLIER_FACTOR x its peers' (something else in the profile: a logo, a scratch, a
    string), an sd over a quarter of the *commanded* width ``width_cmd_mm``, or an sd over
    OUTLIER_FACTOR x its peers' that is also above SD_OUTLIER_MIN_MM (below it the width
    carries its own weight). The bar is not the measured width: a narrow bead's sd grows
    as it reads narrower (width and contrast trade off under the blur), so a quarter of the
    measured width dropped the stations that erred narrow and kept those that erred wide
    (phone render of a sparkling plate, 0.25 mm beads: mean error -4 um of the kept ones,
    -14 um with the commanded width, against -45 um for 1.6 mm beads)."""
    return ((sd_mm > 0.25 * np.maximum(width_cmd_mm, 0.1))
            | (sd_mm > np.maximum(OUTLIER_FACTOR * sd_ref_mm, SD_OUTLIER_MIN_MM))
            | (rel_rms > OUTLIER_FACTOR * rel_rms_ref))


def isolated(track, s_mm, flag, half_mm: float | None = None, fraction: float | None = None):
    """Valid stations (flag "") in a stretch of contaminated ones (bool array): fewer than
    ``fraction`` (ISOLATED_FRACTION) of the other stations of the same track within
    +-``half_mm`` (ISOLATED_HALF_MM) are valid, counting only valid ones and those flagged
    for a bad profile (CONTAMINATED_FLAGS: geometric flags such as a crossing, and missing
    beads, say nothing of the profile). A bead over a plate logo lighter than the plate
    failed the fit on most stations, and the few that passed had found the logo's edge."""
    half_mm = ISOLATED_HALF_MM if half_mm is None else half_mm
    fraction = ISOLATED_FRACTION if fraction is None else fraction
    track, s_mm, flag = np.asarray(track), np.asarray(s_mm, float), np.asarray(flag, dtype=object)
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s = s_mm[idx]
        v = (flag[idx] == "").astype(float)
        bad = np.isin(flag[idx], CONTAMINATED_FLAGS).astype(float)
        cv, cb = np.concatenate([[0.0], np.cumsum(v)]), np.concatenate([[0.0], np.cumsum(bad)])
        lo = np.searchsorted(s, s - half_mm, "left")
        hi = np.searchsorted(s, s + half_mm, "right")
        n_valid = cv[hi] - cv[lo] - v
        n = n_valid + cb[hi] - cb[lo]
        out[idx] = (v > 0) & (n > 0) & (n_valid < fraction * n)
    return out


def enclosed(track, s_mm, flag, w_mm, gap_mm: float | None = None,
             deviation_mm: float | None = None) -> np.ndarray:
    """Valid stations (flag "") inside contamination that read another width than the bead
    around them (bool array). A run of valid stations is taken when, on its track,
    - the stations flagged on each side of it are flagged for a bad profile
      (CONTAMINATED_FLAGS or ``steep``), the two at most ``gap_mm`` (ENCLOSED_MM) apart,
    - each side's block of such stations holds one of CONTAMINATED_FLAGS (``steep`` alone
      is a real change of width: a blob up and down again is steep-plateau-steep), and
    - the run's median width differs by more than ``deviation_mm`` (ENCLOSED_DEVIATION_MM)
      from the median of at least three valid stations outside it within ENCLOSED_REACH_MM.
    Geometric flags (a crossing, a neighbour, a bead's end) and absences bound nothing;
    without valid stations around, nothing says the run is wrong and it is kept."""
    gap_mm = ENCLOSED_MM if gap_mm is None else gap_mm
    deviation_mm = ENCLOSED_DEVIATION_MM if deviation_mm is None else deviation_mm
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    flag, w_mm = np.asarray(flag, dtype=object), np.asarray(w_mm, float)
    bounds = CONTAMINATED_FLAGS + ("steep",)
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s, f, w = s_mm[idx], flag[idx], w_mm[idx]
        v = f == ""
        bound = np.isin(f, bounds)
        dirty = np.isin(f, CONTAMINATED_FLAGS)
        edges = np.diff(np.r_[0, v.astype(np.int8), 0])
        for i, j in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            if i == 0 or j == len(idx) or not (bound[i - 1] and bound[j]) or s[j] - s[i - 1] > gap_mm:
                continue
            a = i - 1                                      # the blocks of bounds each side
            while a > 0 and bound[a - 1]:
                a -= 1
            b = j
            while b + 1 < len(idx) and bound[b + 1]:
                b += 1
            if not (dirty[a:i].any() and dirty[j:b + 1].any()):
                continue
            mid = 0.5 * (s[i] + s[j - 1])
            around = v & (np.abs(s - mid) <= ENCLOSED_REACH_MM)
            around[i:j] = False
            if around.sum() >= 3 and abs(np.median(w[i:j]) - np.median(w[around])) > deviation_mm:
                out[idx[i:j]] = True
    return out


def steep(track, s_mm, w_mm, sd_mm=None, max_slope: float | None = None) -> np.ndarray:
    """Stations where the measured width changes faster than ``max_slope`` (STEEP_SLOPE, mm
    of width per mm of track; central differences along the track, NaN as 0) by more than
    two sds of that difference (from the widths' sds ``sd_mm``): the strip then holds
    widths ``max_slope`` x STRIP_MM apart, whose mean profile's edge pair is not their
    mean width, and the outline the picture shows is the union of the bead's round
    footprints, wider than the width by ~w'^2 / 8 of it (the envelope of circles). Where
    the widths are noisy (a phone photo of a real print: sds of 20-60 um) the noise's
    slope is not a steep bead, and a bias of a few um is well inside the sd."""
    max_slope = STEEP_SLOPE if max_slope is None else max_slope
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    w = np.nan_to_num(np.asarray(w_mm, float))
    var = np.zeros(len(w)) if sd_mm is None else np.nan_to_num(np.asarray(sd_mm, float), nan=0.0) ** 2
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        if len(idx) < 2:
            continue
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s = s_mm[idx]
        if np.any(np.diff(s) <= 0):
            continue
        v = var[idx]
        # central difference (w[j+1] - w[j-1]) / (s[j+1] - s[j-1]); one-sided at the ends
        gap = np.r_[s[1] - s[0], s[2:] - s[:-2], s[-1] - s[-2]] if len(s) > 2 else np.full(len(s), s[1] - s[0])
        v_pair = np.r_[v[0] + v[1], v[2:] + v[:-2], v[-1] + v[-2]] if len(s) > 2 else np.full(len(s), v.sum())
        out[idx] = np.abs(np.gradient(w[idx], s)) - 2.0 * np.sqrt(v_pair) / gap > max_slope
    return out


def beside_absence(track, s_mm, absent, reach_mm: float | None = None) -> np.ndarray:
    """Stations within ``reach_mm`` (TIP_REACH_MM) of an ``absent`` station of the same
    track (bool array): where a bead fades out or in, the strip of the last station that
    sees it holds the tip, a sliver whose edge pair reads wider than the sliver. The
    virtual direct drive's RetractTest at the truth: 15 valid stations read 0.12-0.16 mm
    where the bead, carried 0.3 mm past the commanded stop by the moving retraction, had
    tapered to 0.0-0.08 mm (7.2 um RMS over the valid stations, every station beyond
    40 um one of these), wherever the commanded stop's own reach (:func:`_at_end`) ended
    before the bead did."""
    reach_mm = TIP_REACH_MM if reach_mm is None else reach_mm
    track, s_mm, absent = np.asarray(track), np.asarray(s_mm, float), np.asarray(absent, bool)
    out = np.zeros(len(track), bool)
    for t in np.unique(track[absent]):
        idx = np.flatnonzero(track == t)
        s_abs = np.sort(s_mm[idx][absent[idx]])
        s = s_mm[idx]
        k = np.clip(np.searchsorted(s_abs, s), 1, len(s_abs) - 1) if len(s_abs) > 1 else np.zeros(len(s), int)
        d = np.abs(s - s_abs[k])
        if len(s_abs) > 1:
            d = np.minimum(d, np.abs(s - s_abs[k - 1]))
        out[idx] = (d <= reach_mm) & ~absent[idx]
    return out


def dropouts(track, s_mm, absent, seen, reach_mm: float | None = None) -> np.ndarray:
    """``absent`` stations (bool array) with a ``seen`` station of the same track within
    ``reach_mm`` (DROPOUT_REACH_MM) before *and* after them: a bead seen on both sides of a
    gap shorter than a printer can leave in it (DROPOUT_REACH_MM) was there, and the
    station that missed it misread the picture."""
    reach_mm = DROPOUT_REACH_MM if reach_mm is None else reach_mm
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    absent, seen = np.asarray(absent, bool), np.asarray(seen, bool)
    out = np.zeros(len(track), bool)
    for t in np.unique(track[absent]):
        idx = np.flatnonzero(track == t)
        s_seen = np.sort(s_mm[idx][seen[idx]])
        if len(s_seen) < 2:
            continue
        i_abs = idx[absent[idx]]
        s = s_mm[i_abs]
        k = np.searchsorted(s_seen, s)          # s_seen[k - 1] < s <= s_seen[k]
        before = np.where(k > 0, s - s_seen[np.maximum(k - 1, 0)], np.inf)
        after = np.where(k < len(s_seen), s_seen[np.minimum(k, len(s_seen) - 1)] - s, np.inf)
        out[i_abs] = (before <= reach_mm) & (after <= reach_mm)
    return out


def oblique(track, s_mm, centre_mm, ok, half_mm: float | None = None,
            max_slope: float | None = None, min_t: float | None = None):
    """Stations (bool array, among ``ok``) where what the edge fit found runs at an angle to
    the track: the least-squares line through the centres (mm, along the normal) of the
    ``ok`` stations of the same track within +-``half_mm`` of arc length has a slope over
    ``max_slope`` (OBLIQUE_SLOPE) that is ``min_t`` (OBLIQUE_T) standard errors from 0.
    A bead runs along its track (a misregistration shifts its centre slowly); a string or a
    line crossing at an angle is a straight feature whose centre walks off at once."""
    half_mm = ISOLATED_HALF_MM if half_mm is None else half_mm
    max_slope = OBLIQUE_SLOPE if max_slope is None else max_slope
    min_t = OBLIQUE_T if min_t is None else min_t
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    c, ok = np.asarray(centre_mm, float), np.asarray(ok, bool) & np.isfinite(centre_mm)
    out = np.zeros(len(track), bool)
    for t in np.unique(track[ok]):
        idx = np.flatnonzero((track == t) & ok)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s, y = s_mm[idx], c[idx]
        # windowed sums give every station's local regression at once
        cum = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(s), s, y, s * s, s * y, y * y)]
        lo = np.searchsorted(s, s - half_mm, "left")
        hi = np.searchsorted(s, s + half_mm, "right")
        n, sx, sy, sxx, sxy, syy = (q[hi] - q[lo] for q in cum)
        with np.errstate(invalid="ignore", divide="ignore"):
            vxx = sxx - sx * sx / n
            slope = (sxy - sx * sy / n) / vxx
            rss = np.maximum(syy - sy * sy / n - slope * (sxy - sx * sy / n), 0.0)
            se = np.sqrt(rss / np.maximum(n - 2, 1) / vxx)
            # a perfectly straight feature has rss ~ 0: its t is large, not undefined
            tval = np.abs(slope) / np.maximum(se, 1e-9)
        out[idx] = (n >= 4) & (np.abs(slope) > max_slope) & (tval > min_t)
    return out
