"""Is the value robust to the effect every printed bead has? The nuisance check.

Some effects are not a property of one printer but of every real bead, and a model that
lacks them reads the physics wrong without misfitting visibly. The one measured so far:
``spread`` (fit/effects.py), the bead smoothing its own width along the track. On
realistic renders (bench/bench_e2e.py) `pa` alone read tau 4 % high with a 2 %-wide
interval, on 11 of 12 seeds outside it, at chi2_nu_bead ~1 and with no residual structure
the covariate scores can see (the misfit sits in a few stations at each flow step).

:func:`nuisance_check` refits the MAP with each such effect added (warm-started at the
fit's own optimum) and reports the BIC gain and which physical parameters move outside
their 95 % interval. fit/trust.py turns a decisive gain (Delta BIC >= ``DECISIVE_BIC``,
10: "very strong", Kass & Raftery 1995) that moves a value into a problem.
"""
from __future__ import annotations

import numpy as np

from fit.modes import physical_mask

#: Effects every real bead has: (name, start value of its parameters in the warm start).
NUISANCE = {"spread": {"spread.sigma_mm": 0.15}}
DECISIVE_BIC = 10.0


def nuisance_check(make_problem, spec: str, map_values: dict, map_bic: float, ci95: dict,
                   seed: int = 0) -> list[dict]:
    """For each nuisance effect not in ``spec``: the MAP of ``spec+effect`` and what it changes.

    make_problem(spec) -> JointProblem on the same data and priors; map_values, map_bic: the
    fitted model's MAP (``MapResult.values``, ``.bic``); ci95: {name: (lo, hi)} of its
    physical parameters. Returns [{"effect", "model", "delta_bic" (> 0: the effect helps),
    "moved": {name: [value, value with the effect]} outside the 95 % interval}].
    """
    from fit.diagnose import split_spec
    from fit.sampler import fit_map

    out = []
    for effect, start in NUISANCE.items():
        if effect in split_spec(spec):
            continue
        ext = f"{spec}+{effect}"
        pb = make_problem(ext)
        x0 = np.array([start.get(n, map_values.get(n, d)) for n, d in zip(pb.param_names, pb.default_theta())])
        m = fit_map(pb, x0=np.clip(x0, *pb.bounds.T), n_starts=2, seed=seed)
        moved = {}
        for n, phys in zip(pb.param_names, physical_mask(pb.param_names)):
            if phys and n in ci95 and n in map_values:
                lo, hi = ci95[n]
                v = float(m.values[n])
                if not lo <= v <= hi:
                    moved[n] = [float(map_values[n]), v]
        out.append({"effect": effect, "model": ext, "delta_bic": float(map_bic - m.bic), "moved": moved})
    return out
