"""Intervals that hold the width calibration's doubt: the posterior widened by what the
measurement does not know of the widths' common offset.

`calib measure` calibrates the apparent widths against the print's own width reference
and says how well it knows the offset that remains (``apparent_width.offset_sd_mm`` of
its summary: 0.67 um on `make demo`'s 600 dpi flatbed scan). A model without
``scan_bias`` takes that offset as exactly 0, and some parameters are steep in it. Measured
on the demo's setup (adventurer3 spiral, truth pa+backpressure+thermal, flatbed 600 dpi,
seeds 2-11, MAP of `pa+backpressure+thermal`; fit/influence.py, the response of the MAP to
a constant offset of every width): thermal.tau_s moves 4.0 s per um of offset (its
posterior sd 0.07 s), pa.tau_s 0.0017 s per um (sd 0.0004 s). The remaining offsets were
0.03-0.23 um, and the MAP's thermal.tau_s missed its truth by more than 1.96 sds on 6 of 10
seeds; the influence of the offset alone (-8.1 sds on seed 4, -5.1 on seed 10) was the
miss. Adding ``scan_bias`` to the model did not mend it (thermal.a then traded with its
width-scale term b1, |z| 4.8-5.2 on 3 of 6 seeds), and its posterior of b0 did not find the
offset (-0.43 to +0.19 um for -0.07 to +0.23): the model's shape places it, as
fit/trust.py says of the rides-the-offset check, so the doubt to carry is the
measurement's, not the posterior's.

So :func:`widen_offset`: for every scan whose widths were calibrated (the summary's
``applied``) and whose model has no ``scan_bias.b0_mm``, the offset's doubt b_k ~ N(0,
s_k^2), s_k the prior `calib fit` would give b0 (fit.measurement.b0_prior: the summary's
offset_sd_mm, floored), is carried through the MAP's linear response R_k (parameter per mm;
fit.influence.offset_response) into every posterior draw: x' = x + R_k b_k (x' = x exp(R_k
b_k / x_MAP) for a positive parameter, whose posterior is skewed), one b_k per draw shared
by all parameters. Every non-noise parameter's 68/90/95 % interval becomes the hull of the
posterior's and the shifted draws', and every derived value's (the firmware numbers) the
same; medians and firmware lines stay the posterior's. This is the Laplace limit of
marginalising an offset whose prior the data do not narrow.

A MAP fit (`--map-only`) gets the same in its Laplace covariance, C + sum_k s_k^2 R_k R_k^T
(:func:`widen_map_offset`).

The offset holds at the reference's layer height. A bead's flanks are half-rounds of its
height (fit/geometry.py), and shading, translucency and glare on them set the offset, so a
test track at another height has another offset, which no reference measured. Written
offset(h) = b0 (h / h_ref)^xi, its doubt at h is |b0| |ln(h / h_ref)| for an exponent xi
known to +-1 (a scale-free picture of the flanks gives xi = 1, a plate seen through
translucent flanks of fixed attenuation length less). Measured on RetractTest (design 1:
one line per height at one flow; 600 dpi flatbed render with every phenomenon, seed 0):
apparent offsets -47.7, -42.3, -38.6, -17.9 um at h 0.3, 0.2 (the reference), 0.164,
0.1125 mm, xi 0.3, 0.46 and 1.5; the 0.8 mm line at 0.1125 mm read 28 um wide of its
truth after calibration, and that alone moved the MAP's tau 4 % (fit/influence.py), a
trusted 0.0380 s, 95 % [0.0370, 0.0391], for a truth of 0.040. So every group of stations
at a height more than SAME_HEIGHT_LN from the reference's gets its own offset o_g ~ N(0,
s_g^2), s_g = (|b0| + 2 sd(b0)) |ln(h_g / h_ref)| (independent: xi differed per height),
carried through its own response R_g (fit.influence.direction_response) like the common
offset, whether or not the model has ``scan_bias`` (one b0 for all heights cannot take
them). On that scan: s_g 29, 10, 21 um at 0.1125, 0.164, 0.3 mm; tau's 95 % interval (Laplace)
[0.0347, 0.0413].

Uncalibrated widths are not widened here: their doubt is the whole apparent-width offset
(tens of um), and `calib fit` already says to add scan_bias (fit/measurement.py notes). The
response is linear only over a few um, so it could not carry that doubt anyway. Measured
on the demo's seed-2 scan marked uncalibrated, every width shifted by d, MAP of
`pa+backpressure+thermal` (2026-11-28): the linear response predicts pa.tau_s -2.8 ms and
thermal.tau_s -40 s per +10 um; the refits moved them -17.6 ms / -19 s at +10 um, +0.3 ms
/ +69 s at -10 um, and thermal.tau_s went to 2.8 s at +30 um and to its 300 s bound at -30.
What guards those fits is the misfit check: chi2_nu_bead 12.6 at +10 um, 11.8 at -30, 47
at +30 (the full fit at +10: NOT TRUSTWORTHY, "fit pa+backpressure+thermal+scan_bias
first"); at +-5 um 2.2-3.9; at +-2 um 1.3-1.4, under the check's 2, with pa.tau_s off by
0.4 % (~9 of its sds) and thermal.tau_s 17.5 / 33 s for 25, the scan_bias caution their
only warning (MAP fits; the structure check not run).
"""
from __future__ import annotations

import math

import numpy as np

from fit.likelihood import is_noise
from fit.result import envelope_rows
from fit.noise_envelope import hull_draws, union_derived

#: the parameter named for the widths' common offset (a model with it carries the doubt)
OFFSET_PARAM = "scan_bias.b0_mm"
#: A station's layer height is the reference's when |ln(h / h_ref)| is below this (2 %).
SAME_HEIGHT_LN = 0.02


def offset_doubts(problem, states) -> list:
    """Per scan of ``problem``: the offset's doubt s_k (mm) to carry, or None (uncalibrated
    widths, no calibration known, or a model that fits the offset itself)."""
    from fit.measurement import b0_prior

    by_scan = {st.get("scan"): st.get("calibration") for st in states or ()}
    names = set(problem.param_names)
    out = []
    for sc in problem.scans:
        cal = by_scan.get(sc.name)
        own = {OFFSET_PARAM, f"{OFFSET_PARAM}@{sc.name}"} & names
        out.append(float(b0_prior(cal)["sd"]) if cal and cal.get("applied") and not own else None)
    return out


def height_doubts(problem, states) -> list:
    """Per scan of ``problem``: [(h_mm, mask over its valid stations, s_mm)] for every layer
    height of its valid stations that is not the width reference's (module docstring), or []
    (uncalibrated widths, a calibration without its height (widths measured before it was
    recorded), or every station at the reference's height)."""
    from fit.measurement import measured_offset

    by_scan = {st.get("scan"): st.get("calibration") for st in states or ()}
    out = []
    for sc in problem.scans:
        cal = by_scan.get(sc.name) or {}
        h_ref = cal.get("height_mm")
        b = ((cal.get("offset_mm"), cal.get("offset_sd_mm")) if cal.get("applied") else measured_offset(cal))
        if not (h_ref and h_ref > 0 and b and b[0] is not None and b[1] is not None
                and np.isfinite(b[0]) and np.isfinite(b[1])):
            out.append([])
            continue
        size = abs(float(b[0])) + 2.0 * float(b[1])
        h = np.round(np.asarray(sc.samples.height_mm, dtype=float)[sc.order], 4)
        groups = []
        for g in np.unique(h[np.isfinite(h) & (h > 0)]):
            ln = abs(math.log(g / h_ref))
            if ln >= SAME_HEIGHT_LN:
                groups.append((float(g), h == g, size * ln))
        out.append(groups)
    return out


def _directions(problem, states) -> tuple[list, list, dict, dict]:
    """The width errors to carry: ([(k, e)], their sds (mm), {scan: index into them} of the
    common offsets, {scan: {h: s_g}} of the heights)."""
    doubts, heights = offset_doubts(problem, states), height_doubts(problem, states)
    dirs, sds, common, by_h = [], [], {}, {}
    for k, sc in enumerate(problem.scans):
        if doubts[k] is not None:
            common[sc.name] = len(dirs)
            dirs.append((k, np.ones(len(sc.order))))
            sds.append(doubts[k])
        for h, mask, sd in heights[k]:
            dirs.append((k, mask.astype(float)))
            sds.append(sd)
            by_h.setdefault(sc.name, {})[f"{h:g}"] = sd
    return dirs, sds, common, by_h


def widen_offset(problem, result, states, *, seed: int = 0, derive=None) -> dict | None:
    """Widen ``result`` (fit.result.FitResult of ``problem``) in place by the width offset's
    doubt (module docstring) and return what was done (``result.diagnostics
    ["offset_envelope"]``): {"applied", "offset_sd_mm": {scan: s_k}, "response":
    {name: {scan: R_k}} (parameter unit per mm, the common offsets'), "height_sd_mm": {scan:
    {h: s_g}}, "widened": {name: {"ci95_posterior", "ci95"}}}. ``derive(samples) -> dict``:
    fit.derived.derived_values for draws in ``problem``'s order; ``result.derived`` is
    widened with it. None when no scan has a doubt to carry."""
    from fit.influence import direction_response

    dirs, sds, common, by_h = _directions(problem, states)
    if not dirs:
        return None
    theta = np.asarray(result.map.theta, dtype=float)
    names, R = direction_response(problem, theta, dirs)
    s = np.asarray(sds, dtype=float)
    draws = np.array(result.samples, dtype=float, copy=True)
    b = np.random.default_rng(seed).standard_normal((len(draws), len(s))) * s
    shift = b @ R                                   # (n_draws, len(names))
    info = {"applied": True, "offset_sd_mm": {name: sds[i] for name, i in common.items()}, "height_sd_mm": by_h,
            "response": {n: {name: float(R[i, j]) for name, i in common.items()} for j, n in enumerate(names)},
            "widened": {}}
    lo, hi = problem.bounds.T
    for j, n in enumerate(names):
        col = result.param_names.index(n)
        x = draws[:, col]
        if np.all(x > 0) and theta[col] > 0:
            x = x * np.exp(shift[:, j] / theta[col])
        else:
            x = x + shift[:, j]
        # beyond a bound the model has no value; the trust verdict judges bounds by the
        # posterior's own interval (fit/trust.py)
        draws[:, col] = np.clip(x, lo[col], hi[col])
    info["widened"] = hull_draws(result, draws, [n for n in result.params
                                                 if not is_noise(n) and n in result.param_names])
    if derive is not None and result.derived:
        result.derived = union_derived(result.derived, derive(draws))
    result.envelope_samples["offset"] = envelope_rows(draws, seed)
    result.diagnostics["offset_envelope"] = info
    return info


def widen_map_offset(problem, map_result, states) -> dict | None:
    """The Laplace form of :func:`widen_offset` for a MAP fit (fit.result.MapResult of
    ``problem``): its covariance gains sum_k s_k^2 R_k R_k^T over the responding
    parameters (and s_g^2 R_g R_g^T per height), in place. Returns {"applied",
    "offset_sd_mm", "height_sd_mm", "sd_before": {name: sd}} or None when no scan has a
    doubt to carry."""
    from fit.influence import direction_response

    dirs, sds, common, by_h = _directions(problem, states)
    if not dirs:
        return None
    names, R = direction_response(problem, np.asarray(map_result.theta, dtype=float), dirs)
    cols = [list(problem.param_names).index(n) for n in names]
    cov = np.array(map_result.cov, dtype=float, copy=True)
    before = {n: float(np.sqrt(cov[c, c])) for n, c in zip(names, cols)}
    for d, r in zip(sds, R):
        cov[np.ix_(cols, cols)] += d * d * np.outer(r, r)
    map_result.cov = cov
    return {"applied": True, "offset_sd_mm": {name: sds[i] for name, i in common.items()}, "height_sd_mm": by_h,
            "sd_before": before}


def offset_line(info: dict | None) -> str | None:
    """One line for `calib fit`: how far the calibration's doubt widened the intervals (the
    firmware's own values, pa.*, first; at most three), or None."""
    if not info or not info.get("applied") or not info.get("widened"):
        return None
    shown = sorted(info["widened"], key=lambda n: not n.startswith(("pa.", "pa_ve.")))
    parts = [f"{n} 95 % [{w['ci95_posterior'][0]:.4g}, {w['ci95_posterior'][1]:.4g}] -> "
             f"[{w['ci95'][0]:.4g}, {w['ci95'][1]:.4g}]" for n, w in
             ((n, info["widened"][n]) for n in shown[:3])]
    return f"width calibration: {doubt_text(info)}; the intervals carry it: " + "; ".join(parts)


def doubt_text(info: dict) -> str:
    """What the widths' calibration does not know, in words (``widen_offset``'s or
    ``widen_map_offset``'s ``info``)."""
    what = []
    if info.get("offset_sd_mm"):
        sd = ", ".join(f"{v * 1000:.2g} um" for v in info["offset_sd_mm"].values())
        what.append(f"the widths' common offset is known to +-{sd} (1 sd, `calib measure`'s width reference) "
                    "and the model has no scan_bias")
    heights = {h: v for by in (info.get("height_sd_mm") or {}).values() for h, v in by.items()}
    if heights:
        hs = ", ".join(f"{v * 1000:.2g} um at h {h} mm" for h, v in sorted(heights.items()))
        what.append(f"the width reference was printed at one layer height and the test at others, where its "
                    f"offset is known to +-{hs}")
    return "; ".join(what)
