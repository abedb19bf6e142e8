"""Several pictures of one print, one widths table: each picture measured on its own
(:func:`measure.pipeline.measure_scan`), the widths averaged station by station.

Why: on a textured plate under a lamp the grain mirrors the lamp in specks as bright as
the bead (measure/phenomena.py ``sparkle``; the realdata photos' widths scatter 45 um).
What a speck does to a width is lost to that picture (docs/MEASUREMENT.md, "A textured
plate as a phone sees it": no filter along the track, no colour axis and no robust edge
fit took it), but the specks are the facets that happen to mirror the lamp into the
camera: move the lamp and other facets light up, while the bead stays where it is. So the
speck part of a station's error is independent between pictures taken with the lamp
moved, and the mean of N readings has 1/sqrt(N) of it.

Measured on bench_realism's sparkling scene (phone at 35 deg, every phenomenon + sparkle,
Bowden, seed 3; five renders that differ only in the lamp, ``render(light_seed=)``; the
errors' sd about their mean): one picture 49-50 um; the mean of the stations' valid
readings 35 / 29 / 22 um over 2 / 3 / 5 pictures where every picture read the station,
40 / 33 / 28 um where a majority did (the stations some pictures fail on are the hard
ones). Tried and not kept: the pixel-wise median of the aligned pictures (40 / 33 um over
3 / 5: half of that plate catches some light in any picture, so a median of few keeps a
weaker speck) and their minimum (33 / 32 um; it also keeps every picture's shadow,
which the renderer does not draw and a real lamp at 30 deg casts 0.5 mm beside a 0.3 mm
bead), the median of the readings (34 um over 5) and weights by the stations' sds
(34 um: a narrow bead's sd grows as it reads narrower, so 1/sd^2 weights pull wide).

Every picture is registered on its own, so the camera may move between them; the
stations are the manifest's, the same in every table.
"""
from __future__ import annotations

import math
from collections import Counter

import numpy as np

from measure.station_sd import calibrated_sd, scatter_factor
from measure.table import WidthTable

#: A station is valid when at least this share of the pictures read it valid (a majority
#: for three or more; one of two).
MIN_SHARE = 0.5


def combine_tables(tables: list[WidthTable], offsets_mm=None) -> tuple[WidthTable, dict]:
    """One widths table from ``tables`` measured on pictures of the same print (same
    manifest, so the same stations in the same order).

    offsets_mm   per table, the apparent-width offset (mm) its valid widths were corrected
                 by (measure/calibrate.py; 0 or None: not corrected). It is added back
                 before the mean, so the tables are combined as apparent widths; the
                 caller decides whether to correct the mean (:func:`combined_calibration`).

    A station is valid where >= MIN_SHARE of the tables read it valid; its width is the
    plain mean of those readings, w = (1/n) sum w_i, and its sd
    sqrt(mean(sd_i^2) (1 - r + r / n)), r the share of a reading's variance that is its
    picture's own (:func:`own_share`: what the pictures share, the plate's grain, the
    translucent flanks, the blur, does not average out), then calibrated by the combined
    widths' own scatter along the tracks (measure/station_sd.py calibrated_sd, which only
    widens).
    Elsewhere the station takes the flag most of the tables give it (``missing``: width 0,
    the absence the fit uses). The blur is the readings' mean; the light angle is left
    out (each picture has its own light). Returns (table, info) with per-picture counts.
    """
    if not tables:
        raise ValueError("no tables to combine")
    ref = tables[0]
    for t in tables[1:]:
        if len(t) != len(ref) or not (np.array_equal(t.track, ref.track) and np.allclose(t.s_mm, ref.s_mm)):
            raise ValueError("the tables do not hold the same stations (pictures of different patterns?)")
    n = len(tables)
    off = np.zeros(n) if offsets_mm is None else np.nan_to_num(np.asarray(offsets_mm, dtype=float))
    V = np.array([t.valid for t in tables])
    W = np.array([np.where(t.valid & (t.width_mm > 0), t.width_mm + o, t.width_mm) for t, o in zip(tables, off)])
    S = np.array([t.width_sd_mm for t in tables])
    S_own = np.array([np.where(np.isfinite(t.width_sd_own_mm), t.width_sd_own_mm, t.width_sd_mm) for t in tables])
    nv = V.sum(axis=0)
    valid = nv >= max(1, math.ceil(MIN_SHARE * n - 1e-9))
    k = np.maximum(nv, 1)
    w = np.where(V, W, 0.0).sum(axis=0) / k
    # each reading's error: a part the pictures share (the plate's grain, the translucent
    # flanks, the blur) and a part of its own (the specks, the sensor); only the second
    # averages out, so var(mean) = mean(sd_i^2) (1 - r + r / k), r the own part's share
    ratio = scatter_ratio(W, S, V)
    r = float(np.clip(ratio, 0.0, 1.0))
    shrink = (1.0 - r) + r / k
    sd = np.sqrt(np.where(V, S ** 2, 0.0).sum(axis=0) / k * shrink)
    sd_own = np.sqrt(np.where(V, S_own ** 2, 0.0).sum(axis=0) / k * shrink)
    flag = np.array([""] * len(ref), dtype=object)
    for i in np.flatnonzero(~valid):
        flag[i] = Counter(t.flag[i] or "fit" for t in tables if not t.valid[i]).most_common(1)[0][0]
    missing = flag == "missing"
    w = np.where(valid, w, np.where(missing, 0.0, np.nan))
    # a missing station's sd is the scan's detection scale (measure/widths.py), the smallest
    # of the pictures' (the sharpest one would have seen a bead)
    det = np.array([np.where(t.flag == "missing", t.width_sd_mm, np.inf) for t in tables]).min(axis=0)
    sd = np.where(valid, sd, np.where(missing & np.isfinite(det), det, np.nan))
    sd_own = np.where(valid, sd_own, np.nan)
    rho = np.mean(np.array([t.width_corr_prev for t in tables]), axis=0)
    # the pictures' own scatter is what the mean has less of; what they share the combined
    # widths still show along the tracks, and the calibration takes it from there
    sd_own = sd_own * scatter_factor(ref.track, np.nan_to_num(w), np.where(valid, sd_own, 1.0), valid, rho)
    sd_cal, k_sd, f_sd = calibrated_sd(ref.track, ref.s_mm, np.nan_to_num(w), np.where(valid, sd, 1.0), valid)
    sd = np.where(valid, sd_cal, sd)
    sd_own = np.where(valid, np.minimum(sd_own, sd), np.nan)
    blur = np.array([t.blur_mm for t in tables])
    seen = np.isfinite(blur).sum(axis=0)
    blur = np.where(seen > 0, np.nansum(blur, axis=0) / np.maximum(seen, 1), np.nan)
    table = WidthTable(track=ref.track, s_mm=ref.s_mm, x_mm=ref.x_mm, y_mm=ref.y_mm, t_s=ref.t_s,
                       width_mm=w, width_sd_mm=sd, valid=valid, flag=flag, blur_mm=blur,
                       width_sd_own_mm=sd_own, width_corr_prev=np.nan_to_num(rho))
    info = {"pictures": n, "min_share": MIN_SHARE, "own_share": round(r, 3), "scatter_ratio": round(ratio, 3),
            "valid_per_picture": [int(v.sum()) for v in V],
            "readings_per_valid_station": float(np.mean(nv[valid])) if valid.any() else 0.0,
            "station_sd": {"scale": round(k_sd, 3), "floor_mm": round(f_sd, 5)}}
    return table, info


#: Pictures whose readings of one station scatter about their mean this many times more
#: than each picture's sds allow are not of one print (or not of one state of it): said.
#: Of one print the ratio reads 0.88-0.93 (own_share's, unclipped, on the sparkling scene).
DISAGREE_RATIO = 2.0


def own_share(W, S, V, min_stations: int = 30) -> float:
    """:func:`scatter_ratio` clipped to 0-1: the share of a reading's variance that is its
    picture's own."""
    return float(np.clip(scatter_ratio(W, S, V, min_stations), 0.0, 1.0))


def scatter_ratio(W, S, V, min_stations: int = 30) -> float:
    """How far the pictures' readings of one station scatter about their mean, in units of
    what each picture's sds allow; of one print, the share r (0-1) of a reading's variance
    that is its picture's own (more than 1: the pictures disagree). At a station every
    picture read, the sample variance s^2 of its n readings estimates the own part, r
    sd^2 on average, and mean(sd_i^2) the whole (the stations' sds are calibrated to their
    errors per picture: measure/station_sd.py). Robust: r = median(s^2 / mean(sd_i^2)) /
    (median(chi2_(n-1)) / (n - 1)). ``W``, ``S``, ``V``: (pictures, stations) readings (mm),
    sds (mm), valid. 1 (all own) with fewer than ``min_stations`` stations read by all.
    On bench_realism's sparkling phone scene (5 pictures, seeds 0 and 1) r reads 0.92 and
    0.91, and the combined stations' errors within their sd went 0.58 -> 0.63 (seed 0);
    what the pictures share beyond it is mostly a width-dependent offset, the fit's
    scan_bias and view effects, which no station's sd is meant to hold."""
    from scipy import stats

    n = W.shape[0]
    full = V.all(axis=0)
    if n < 2 or full.sum() < min_stations:
        return 1.0
    between = np.var(W[:, full], axis=0, ddof=1)
    whole = np.mean(S[:, full] ** 2, axis=0)
    ok = whole > 0
    if ok.sum() < min_stations:
        return 1.0
    return float(np.median(between[ok] / whole[ok]) / (stats.chi2.median(n - 1) / (n - 1)))


def combined_calibration(blocks: list[dict]) -> dict:
    """The ``apparent_width`` block (measure/calibrate.py ``WidthCalibration.to_dict``) of
    the widths combined from pictures whose blocks are ``blocks``; its ``applied`` says
    whether the combined (apparent) widths are to be corrected by its ``offset_mm``.

    Every picture applied its offset: the mean offset is applied, its sd the RMS of
    theirs, not divided by sqrt(N): the reference is one print seen through one plastic, and
    its offset's doubt (a photo's place, the blur it was read with) is much the same in
    every picture. Otherwise none is, and the block keeps what the references said of the
    apparent widths as the fit's prior (fit/measurement.py ``b0_prior``): the mean and RMS
    sd of the offsets that were applied or could be a prior (``prior_ok``).
    """
    out = dict(blocks[0])
    said = [b for b in blocks if (b.get("applied") or b.get("prior_ok"))
            and b.get("offset_mm") is not None and b.get("offset_sd_mm") is not None]
    applied = all(b.get("applied") for b in blocks)
    out["per_picture"] = [{"offset_mm": b.get("offset_mm"), "offset_sd_mm": b.get("offset_sd_mm"),
                           "applied": bool(b.get("applied"))} for b in blocks]
    if said:
        out["offset_mm"] = float(np.mean([b["offset_mm"] for b in said]))
        out["offset_sd_mm"] = float(np.sqrt(np.mean([b["offset_sd_mm"] ** 2 for b in said])))
    out["applied"] = bool(applied and said)
    out["prior_ok"] = bool(said) and not out["applied"]
    n = len(blocks)
    if out["applied"]:
        out["note"] = (f"apparent-width offset {out['offset_mm'] * 1000:+.1f} +- {out['offset_sd_mm'] * 1000:.1f} um "
                       f"(the mean of the {n} pictures' references) taken off the widths")
    elif said:
        out["note"] = (f"not corrected: {n - sum(bool(b.get('applied')) for b in blocks)} of the {n} pictures' "
                       f"references were not tight enough; their offset {out['offset_mm'] * 1000:+.1f} +- "
                       f"{out['offset_sd_mm'] * 1000:.1f} um is the fit's prior for scan_bias")
    return out


def _distinct(warnings: list[str]) -> list[str]:
    """The warnings once each, two that differ only in their numbers counted as one."""
    seen, out = set(), []
    for w in warnings:
        key = "".join(c for c in w if not (c.isdigit() or c in ".+-%"))
        if key not in seen:
            seen.add(key)
            out.append(w)
    return out


def measure_pictures(image_paths, manifest, points=None, overlay_path=None, *,
                     max_residual_mm: float | None = None):
    """``calib measure`` on one or several pictures of one print: each measured by
    :func:`measure.pipeline.measure_scan` (registered on its own, so the camera may move),
    the widths combined by :func:`combine_tables` and the apparent-width offsets by
    :func:`combined_calibration`. One picture: ``measure_scan`` itself.

    A picture that is refused (not this print, blurred, ...) is left out with a warning; when
    every one is, the first one's refusal is raised (MeasureRefused, with its overlay's data).
    The result's registration, measurement and colour are the first measured picture's (the
    QA overlay shows it); its summary has a ``stack`` block with each picture's figures.
    """
    from measure.pipeline import MeasureRefused, MeasureResult, measure_scan, table_figures

    paths = list(image_paths)
    if len(paths) == 1:
        return measure_scan(paths[0], manifest, points, overlay_path, max_residual_mm=max_residual_mm)
    from calib.progress import progress

    results, refused = [], []
    # closed only when every picture was read: a bad file's one line stays the only one
    bar = progress(total=len(paths), desc="measure", unit="pictures")
    for p in paths:
        try:
            results.append((p, measure_scan(p, manifest, points, max_residual_mm=max_residual_mm)))
        except MeasureRefused as exc:
            refused.append((p, exc))
        bar.update(1)
    bar.close()
    if not results:
        raise refused[0][1]
    blocks = [r.summary["apparent_width"] for _, r in results]
    cal = combined_calibration(blocks)
    offsets = [b.get("offset_mm") if b.get("applied") else 0.0 for b in blocks]
    table, info = combine_tables([r.table for _, r in results], offsets)
    if cal["applied"]:
        table.width_mm = np.where(table.valid & (table.width_mm > 0), table.width_mm - cal["offset_mm"], table.width_mm)
    first = results[0][1]
    ok = table.valid
    warnings = [f"{p}: left out, {exc}" for p, exc in refused]
    if info["scatter_ratio"] > DISAGREE_RATIO:
        # averaging two prints (two flows, two settings) would give widths of neither
        warnings.insert(0, f"the pictures' readings of one station scatter {info['scatter_ratio']:.1f}x what each "
                           "picture's sds allow: are they all of this one print? Widths of different prints "
                           "averaged are the widths of neither; measure each print's pictures on their own")
    warnings += _distinct([w for _, r in results for w in r.summary["warnings"]])
    info["per_picture"] = [{"image": str(p), "fraction_valid": r.summary["fraction_valid"],
                            "residual_mm": r.registration.residual_mm,
                            "width_sd_mm_median": r.summary["width_sd_mm_median"]} for p, r in results]
    info["left_out"] = [{"image": str(p), "why": str(exc)} for p, exc in refused]
    summary = dict(first.summary)
    summary.update({
        "images": [str(p) for p, _ in results],
        **table_figures(table),
        # each picture has its own light: no one axis for the combined widths
        "light_axis_deg": None,
        "station_sd": {**info["station_sd"],
                       "own_mm_median": float(np.median(table.width_sd_own_mm[ok])) if ok.any() else None},
        "apparent_width": cal,
        "warnings": warnings,
        "stack": info,
    })
    if overlay_path is not None:
        from measure.overlay import draw_overlay, save_overlay
        save_overlay(overlay_path, draw_overlay(first.color, manifest, first.registration, first.measurement))
    return MeasureResult(table=table, registration=first.registration, summary=summary,
                         measurement=first.measurement, color=first.color, placement=first.placement)
