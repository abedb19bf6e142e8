"""Hidden-effect benchmark: does `diagnose` find the effect the fitted model lacks?

For each hidden effect (five library effects and gear slip, which is outside the library
and supplied as the user effect of data/examples/my_effects.py) and 10 seeds: simulate
the probe print (fit/hidden.py) with pa + the effect, add 10 um measurement noise, fit
`pa`, diagnose it (MAP fits of every candidate), and record whether the true effect is
ranked first, whether the top covariate is the right one (gear slip), and RMS / reduced
chi-square before and after adding the true effect.
"""
from __future__ import annotations

import numpy as np
from calib.progress import progress

from bench.common import Row

SEEDS = 10
EFFECTS = ("thermal", "backpressure", "nonlinear", "backlash", "bed_tilt", "gear_slip")


def one(hidden: str, seed: int) -> dict:
    from fit.compare import observe
    from fit.diagnose import diagnose
    from fit.effects import REGISTRY
    from fit.hidden import FAMILIES, RIGHT_COVARIATES, make_case
    from fit.model import build_model

    c = make_case(hidden, seed=seed, ds_mm=0.5)
    obs = observe(c.manifest, c.table)
    d = diagnose(obs, "pa", lambda s: build_model(s, c.manifest.printer, c.extra_effects),
                 list(REGISTRY), [e.name for e in c.extra_effects], n_null=100, seed=seed)
    top = d.candidates[0]
    true = next(x for x in d.candidates if x.effect == hidden)
    return {"first": top.effect == hidden,
            "first_family": top.effect in FAMILIES.get(hidden, {hidden}),
            "cov_right": d.covariates[0].name in RIGHT_COVARIATES[hidden],
            "rms_before": d.base.rms_mm, "rms_after": true.rms_mm_after,
            "chi2_before": d.base.chi2_nu, "chi2_after": true.chi2_nu_after,
            "visible": c.effect_rms_mm > 2 * c.noise_mm, "size": c.effect_rms_mm / c.noise_mm}


def run() -> list[Row]:
    rows: list[Row] = []
    lib_first, lib_n = 0, 0
    chi2_after_all = []
    with progress(total=SEEDS * len(EFFECTS), desc="bench_discover") as bar:
        for h in EFFECTS:
            res = []
            for s in range(SEEDS):
                res.append(one(h, s))
                bar.update()
            first = np.mean([r["first"] for r in res])
            vis = [r for r in res if r["visible"]]
            if h != "gear_slip":
                lib_first += sum(r["first"] for r in vis)
                lib_n += len(vis)
            chi2_after_all += [r["chi2_after"] for r in res]
            area = "discover"
            rows.append(Row(area, f"{h}: true effect ranked first (10 seeds, effect/noise median "
                            f"{np.median([r['size'] for r in res]):.1f})", 100 * first, "%",
                            ">= 80", bool(first >= 0.8)))
            if h == "nonlinear":
                rows.append(Row(area, f"{h}: a nozzle-nonlinearity form ranked first",
                                100 * np.mean([r["first_family"] for r in res]), "%", "", None))
            if h == "gear_slip":
                rows.append(Row(area, "gear_slip (outside library): top covariate is extruder speed/flow",
                                100 * np.mean([r["cov_right"] for r in res]), "%", "", None))
            rows.append(Row(area, f"{h}: RMS before -> after (median)",
                            f"{1000 * np.median([r['rms_before'] for r in res]):.1f} -> "
                            f"{1000 * np.median([r['rms_after'] for r in res]):.1f}", "um", "", None))
            ca = np.median([r["chi2_after"] for r in res])
            rows.append(Row(area, f"{h}: chi2_nu before -> after (median)",
                            f"{np.median([r['chi2_before'] for r in res]):.2f} -> {ca:.2f}", "",
                            "after <= 1.2", bool(ca <= 1.2)))
    rows.insert(0, Row("discover", "library effects (> 2x noise) ranked first, all seeds",
                       100 * lib_first / max(lib_n, 1), "%", ">= 80", lib_first >= 0.8 * lib_n))
    return rows


if __name__ == "__main__":
    from bench.common import print_table
    print_table(run())
