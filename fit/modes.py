"""Global search for the modes of a posterior before the local MAP polish.

A multi-start L-BFGS-B from a few prior draws misses narrow modes: on a real scan the
`pa` posterior had optima at tau = 4.97 s and tau = 0.0094 s, the second with a far better
BIC, and which one a fit returned depended on ``--seed``. Here a differential evolution
(Storn & Price 1997; scipy's implementation, vectorised: one population = one batched
physics call) runs over z (log theta for positive parameters, so decades are searched
evenly) with a *fixed* seed, so the starting points, and therefore the MAP, do not depend
on the user's ``--seed``. The final population is split into distinct basins (points
further apart than ``min_sep_z`` in the physical coordinates); the best point of each of
the ``max_starts`` best basins is polished by the caller.

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
    from fit.likelihood import CORR_NAME, SIGMA_NAME

    return np.array([not n.startswith((SIGMA_NAME, CORR_NAME)) for n in param_names])


def global_starts(neg_logpost_z, zlo, zhi, phys, *, popsize: int = 12, maxiter: int = 40,
                  max_starts: int = 4, min_sep_z: float = 0.5) -> list[np.ndarray]:
    """Starting points (in z) for the local polish, one per distinct basin, best first.

    neg_logpost_z(z) takes (S, d) and returns (S,) (inf outside the support). ``phys``
    marks the physical (non-noise) coordinates that define a basin."""
    d = len(zlo)

    def f(zT):                                # scipy's vectorised call: zT (d, S)
        v = neg_logpost_z(np.asarray(zT).T)
        return np.where(np.isfinite(v), v, 1e300)

    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        res = differential_evolution(f, list(zip(zlo, zhi)), vectorized=True, updating="deferred",
                                     popsize=popsize, maxiter=maxiter, tol=0.0, polish=False,
                                     init="sobol", seed=SEARCH_SEED)
    pop, en = np.asarray(res.population), np.asarray(res.population_energies)
    order = np.argsort(en, kind="stable")
    starts: list[np.ndarray] = []
    span = np.maximum(zhi - zlo, 1e-12)
    for i in order:
        if not en[i] < 1e299:
            break
        z = pop[i]
        # basins are told apart in units of the log-range of each coordinate, capped so a
        # parameter with a narrow range still separates at min_sep_z in z
        if all(np.max(np.abs(z - s)[phys] / np.minimum(span[phys], 1.0)) > min_sep_z for s in starts):
            starts.append(z.copy())
        if len(starts) >= max_starts:
            break
    if d and not starts:
        starts.append(np.asarray(res.x, dtype=float))
    return starts


def distinct_modes(optima, phys, same_z: float = 0.05) -> list:
    """``optima``: [(z, result)] sorted best first; keeps the first of each mode."""
    kept: list = []
    for z, r in optima:
        if all(np.max(np.abs(z - zk)[phys], initial=0.0) > same_z for zk, _ in kept):
            kept.append((z, r))
    return kept
