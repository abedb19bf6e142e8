"""Global search for the modes of a posterior before the local MAP polish.

A multi-start L-BFGS-B from a few prior draws misses narrow modes: on a real scan the
`pa` posterior had optima at tau = 4.97 s and tau = 0.0094 s, the second with a far better
BIC, and which one a fit returned depended on ``--seed``. Here a differential evolution
(Storn & Price 1997; scipy's implementation, vectorised: one population = one batched
physics call) runs over z (log theta for positive parameters, so decades are searched
evenly) with a *fixed* seed, so the starting points, and therefore the MAP, do not depend
on the user's ``--seed``. A space-filling screen of the physical parameters adds one start
per distinct basin (:func:`global_starts`), so rival modes are found and reported, not
only the best one; the caller polishes every start.

Two optima are the same mode when their physical parameters (noise parameters excluded)
agree within ``same_z`` in z; modes are reported best first with their BIC, so a user can
see a second explanation of the data and how much worse it is.
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import differential_evolution

#: fixed: the global search is part of the estimator, not of the Monte Carlo
SEARCH_SEED = 20261123


def physical_mask(param_names) -> np.ndarray:
    from fit.likelihood import is_noise

    return np.array([not is_noise(n) for n in param_names])


def global_starts(neg_logpost_z, zlo, zhi, phys, z_default, *, popsize: int = 12,
                  maxiter: int = 40, max_starts: int = 5, min_sep_z: float = 0.5,
                  n_screen: int | None = None) -> list[np.ndarray]:
    """Starting points (in z) for the local polish: the differential evolution's best,
    then one point per distinct basin of a space-filling screen, best first.

    neg_logpost_z(z) takes (S, d) and returns (S,) (inf outside the support). ``phys``
    marks the physical (non-noise) coordinates; ``z_default`` the start of the others.

    DE converges: its final population sits in one basin, so it finds the best mode but
    not the rivals. The screen (a scrambled Sobol sequence over the physical coordinates,
    noise parameters at their defaults, one batched call) finds the rivals: a screen point
    is a basin when no better screen point lies within ``min_sep_z`` (in z, per
    coordinate, at most its log-range) of it."""
    from scipy.stats import qmc

    d = len(zlo)

    def f(z):
        v = neg_logpost_z(np.atleast_2d(z))
        return np.where(np.isfinite(v), v, np.inf)

    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        res = differential_evolution(lambda zT: np.minimum(f(np.asarray(zT).T), 1e300),
                                     list(zip(zlo, zhi)), vectorized=True, updating="deferred",
                                     popsize=popsize, maxiter=maxiter, tol=0.0, polish=False,
                                     init="sobol", seed=SEARCH_SEED)
    starts = [np.asarray(res.x, dtype=float)]
    k = int(np.sum(phys))
    if k == 0:
        return starts
    n = n_screen or max(64, 32 * k)
    m = int(np.ceil(np.log2(n)))
    u = qmc.Sobol(k, scramble=True, seed=SEARCH_SEED).random_base2(m)
    pts = np.tile(np.asarray(z_default, dtype=float), (len(u), 1))
    pts[:, phys] = zlo[phys] + u * (zhi[phys] - zlo[phys])
    en = f(pts)
    scale = np.minimum(np.maximum(zhi - zlo, 1e-12), 1.0)[phys]
    P = pts[:, phys] / scale
    order = np.argsort(en, kind="stable")
    basins = []
    for r, i in enumerate(order):
        if not np.isfinite(en[i]):
            break
        better = P[order[:r]]
        if r == 0 or np.min(np.max(np.abs(better - P[i]), axis=1)) > min_sep_z:
            basins.append(i)
    for i in basins:
        if len(starts) >= max_starts:
            break
        if all(np.max(np.abs((pts[i] - s_)[phys]) / scale) > min_sep_z for s_ in starts):
            starts.append(pts[i].copy())
    return starts


def distinct_modes(optima, phys, same_z: float = 0.05) -> list:
    """``optima``: [(z, result)] sorted best first; keeps the first of each mode."""
    kept: list = []
    for z, r in optima:
        if all(np.max(np.abs(z - zk)[phys], initial=0.0) > same_z for zk, _ in kept):
            kept.append((z, r))
    return kept
