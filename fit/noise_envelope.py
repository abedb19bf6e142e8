"""Intervals that hold under both noise models: the posterior widened by the fit with the
bead's second, short wobble.

The default noise model (fit/likelihood.py) is the measurement's own white error plus one
Ornstein-Uhlenbeck wobble of fitted length ell. Real widths wander on two scales, over
about the bead's own width (~0.4 mm) and over tens of mm, and neither noise model is the
truth; which one gives honest intervals depends on the scan (measured, issue #11, bench_e2e
renders with every phenomenon, measured by the pipeline):

- On the long-Bowden Adventurer 3 scene (tau 0.8 s: a flow transient runs ~16 mm of
  track) the one wobble's length collapses to 6-8 mm to absorb the short part, slow width
  structure is then scored as nearly independent, and tau's 90 % interval missed 0.80 on 2
  of 3 seeds (0.758 [0.729, 0.788], trusted; 0.852 [0.822, 0.882], refused only for a rival
  mode within 0.7 BIC). With the short wobble beside it (BIC 280-390 lower, ell 37-43 mm)
  every interval held tau.
- On the back-pressure scans (tau 0.043 s: transients of 1-6 mm) it is the other way round:
  the short wobble is also preferred (BIC 107-248 lower), but it lets the long wobble
  stiffen, and the measurement's own error in the first 0.15 s after each flow rise (a
  few um; its shape there, not its mean: fit/influence.py, its part under 1 mm alone moves
  Kb +10 % and tau -9 % on seed 1) then reads as signal: Kb's 90 % interval held the
  truth on 6 of 12 seeds against 10 of 12.

BIC picks the short wobble on both, so choosing by it trades one confident wrong number for
another. What holds on both is the hull: the default posterior (MCMC) and the short-wobble
fit's Laplace approximation, each parameter's interval the union of the two. Measured
(2026-11-26, bench_e2e scenes rendered with every phenomenon, measured by the pipeline):

- back-pressure, 12 seeds: 90 % coverage tau / Kb / w_sat 11 / 10 / 12 of 12 with the hull,
  the same as the default alone (the short interval lies inside it; widths +0-3 %); the
  short wobble alone 9 / 6 / 12 (MCMC), 11 / 8 / 11 (Laplace);
- Bowden, 8 seeds (`pa+backpressure+thermal+scan_bias+view_light`, BIC 300-530 lower with
  the short wobble): tau 7/8, thermal a and tau_s 8/8, Kb 7/8, w_sat 8/8, against 5, 5, 4,
  7, 6 of 8 by the default alone in the run before (docs/TRUST.md, the same scenes, before the
  per-scan sd); trusted 5/8 with one tau outside its
  interval (0.758 [0.689, 0.792]: the short fit moved tau down there), against 3/8 with two.

So :func:`widen`: when the default model was fitted (one wobble, ``ar1``) and the short
wobble's MAP (the same global search) is better by SHORT_BIC_MIN, its Laplace
approximation (Gaussian in the sampler's coordinates: log for positive parameters, so the
interval is skewed as the posterior's is) is drawn N_DRAWS times, and every non-noise
parameter's 68/90/95 % interval, and every derived value's (the firmware numbers come from
draws of tau: fit/derived.py), becomes the hull of the posterior's and those draws'. The
median stays the posterior's. A Laplace interval, not a second MCMC: on the back-pressure
seeds the short wobble's Laplace 90 % intervals were 1.1-1.2x as wide as its MCMC ones, and
the second sampler would double a Bowden fit's 7-40 minutes.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fit.likelihood import is_noise
from fit.result import envelope_rows

#: BIC by which the short wobble's MAP must beat the default's before it widens anything
#: (the usual "very strong" evidence; the measured scans were 107-532 below).
SHORT_BIC_MIN = 10.0
#: draws of the short-wobble fit's Laplace approximation
N_DRAWS = 4000
_LEVELS = ("ci68", "ci90", "ci95")


def laplace_draws(problem, map_result, n: int, rng) -> np.ndarray:
    """(n, k) draws of the MAP's Laplace approximation in the sampler's coordinates z (log
    theta for positive parameters, fit.sampler._Transform), clipped to the bounds, in theta."""
    from fit.sampler import _Transform

    tr = _Transform(problem)
    th = np.asarray(map_result.theta, dtype=float)
    J = np.where(tr.log, th, 1.0)
    cov_z = np.asarray(map_result.cov, dtype=float) / np.outer(J, J)
    cov_z = 0.5 * (cov_z + cov_z.T)
    w, V = np.linalg.eigh(cov_z)
    L = V * np.sqrt(np.clip(w, 0.0, None))
    z = tr.to_z(th) + rng.standard_normal((n, len(th))) @ L.T
    return tr.to_theta(np.clip(z, tr.zlo, tr.zhi))


def _hull(a, b) -> list:
    return [float(min(a[0], b[0])), float(max(a[1], b[1]))]


def hull_draws(result, draws, names) -> dict:
    """Widen each of ``names`` (parameters of ``result``, fit.result.FitResult) in place: its
    68/90/95 % interval becomes the hull with the same quantiles of ``draws`` (rows laid out
    as ``result.param_names``); the median stays. Returns {name: {"ci95_posterior", "ci95"}}
    for those whose 95 % interval grew."""
    grew = {}
    for n in names:
        p = result.params[n]
        q = np.quantile(draws[:, result.param_names.index(n)], [0.16, 0.84, 0.05, 0.95, 0.025, 0.975])
        new = {lvl: _hull(getattr(p, lvl), q[2 * i:2 * i + 2]) for i, lvl in enumerate(_LEVELS)}
        if new["ci95"] != [float(v) for v in p.ci95]:
            grew[n] = {"ci95_posterior": [float(v) for v in p.ci95], "ci95": new["ci95"]}
        result.params[n] = replace(p, **{k: tuple(v) for k, v in new.items()})
    return grew


def union_derived(post: dict, alt: dict) -> dict:
    """``post`` (fit.derived.derived_values of the posterior) with every interval replaced by
    its hull with ``alt``'s (the same values from the other fit's draws); medians, configs and
    firmware lines stay the posterior's."""
    out = {}
    for k, v in post.items():
        a = alt.get(k) if isinstance(alt, dict) else None
        if isinstance(v, dict) and isinstance(a, dict):
            out[k] = union_derived(v, a)
        elif k in _LEVELS and a is not None:
            out[k] = _hull(v, a)
        elif k == "pa_s_ci95" and a is not None and len(a) == len(v):
            out[k] = [_hull(x, y) for x, y in zip(v, a)]
        else:
            out[k] = v
    return out


def widen(problem, result, *, seed: int = 0, derive=None) -> dict:
    """Widen ``result`` (fit.result.FitResult of ``problem`` under the default noise model)
    in place to the hull with the short-wobble fit (module docstring) and return what was
    done (``result.diagnostics["noise_envelope"]``): {"applied", "bic_default", "bic_short",
    "sigma_short_mm", "short_values", "short_ci95": {name: the short fit's 95 % interval},
    "widened": {name: {"ci95_posterior", "ci95_short"}} for the intervals that grew}.
    ``derive(samples) -> dict``: fit.derived.derived_values for draws in ``problem``'s
    parameter order; ``result.derived`` is widened with it. Nothing happens (and None is
    returned) when ``problem`` already has the short wobble or no correlated wobble."""
    from fit.likelihood import SHORT_NAME
    from fit.sampler import fit_map

    if problem.noise.short or not problem.noise.ar1:
        return None
    alt_problem = problem.with_noise(replace(problem.noise, short=True))
    alt = fit_map(alt_problem, seed=seed, global_search=True)
    info = {"applied": False, "bic_default": float(result.map.bic), "bic_short": float(alt.bic),
            "sigma_short_mm": float(np.median([v for n, v in alt.values.items()
                                               if n.split("@")[0] == SHORT_NAME])),
            "short_values": {n: float(v) for n, v in alt.values.items() if not is_noise(n)},
            "short_ci95": {}, "widened": {}}
    result.diagnostics["noise_envelope"] = info
    if not alt.bic <= result.map.bic - SHORT_BIC_MIN:
        return info
    info["applied"] = True
    draws = laplace_draws(alt_problem, alt, N_DRAWS, np.random.default_rng(seed))
    cols = [alt_problem.param_names.index(n) for n in problem.param_names]
    draws = draws[:, cols]            # the default problem's layout (its names are all in alt)
    for j, n in enumerate(problem.param_names):
        if is_noise(n) or n not in result.params:
            continue
        p = result.params[n]
        q = np.quantile(draws[:, j], [0.16, 0.84, 0.05, 0.95, 0.025, 0.975])
        info["short_ci95"][n] = [float(q[4]), float(q[5])]
        new = {"ci68": _hull(p.ci68, q[0:2]), "ci90": _hull(p.ci90, q[2:4]), "ci95": _hull(p.ci95, q[4:6])}
        if new["ci95"] != [float(x) for x in p.ci95] or new["ci90"] != [float(x) for x in p.ci90]:
            info["widened"][n] = {"ci95_posterior": [float(x) for x in p.ci95],
                                  "ci95_short": [float(q[4]), float(q[5])]}
        result.params[n] = replace(p, **{k: tuple(v) for k, v in new.items()})
    if derive is not None and result.derived:
        result.derived = union_derived(result.derived, derive(draws))
    result.envelope_samples["noise"] = envelope_rows(draws, seed)
    return info


def envelope_line(info: dict | None) -> str | None:
    """One line for `calib fit`: which intervals the short-wobble fit widened (the firmware's
    own values, pa.*, first; at most three), or None."""
    if not info or not info.get("applied") or not info.get("widened"):
        return None
    shown = sorted(info["widened"], key=lambda n: not n.startswith(("pa.", "pa_ve.")))
    parts = []
    for n in shown[:3]:
        w = info["widened"][n]
        a, b = w["ci95_posterior"]
        c, d = min(a, w["ci95_short"][0]), max(b, w["ci95_short"][1])
        parts.append(f"{n} 95 % [{a:.4g}, {b:.4g}] -> [{c:.4g}, {d:.4g}]")
    return (f"noise model: the widths also carry a short wobble of the bead (BIC "
            f"{info['bic_default'] - info['bic_short']:.0f} lower with it), and the values move with it; "
            f"the intervals hold both fits: " + "; ".join(parts))
