"""Export bench (issue 12 item 2): the width-optimal firmware setting from a real fit.

Data: the demo truth (data/truths/direct_drive.toml: pa + nonlinear, tau 0.04 s, n 0.8)
printed on the virtual direct-drive printer as a spiral-step test track at 20 and 80 mm/s
(bench_fit.make_data, its noise: width_sd 0.01 mm, 0.01 mm unreported, AR(1) 1 mm), fitted
with pa+nonlinear (MAP with the global search, emcee to convergence) and exported as
`calib export` does (fit.firmware_match on the standard move mix, 64 posterior draws,
no firmware smoothing for any of the compensations, so they compare like for like).

Rows (widths on the *true* physics, so they are what the user would print):
- predicted width error (um RMS) at starts and at stops, and over all stations, for no PA,
  linear PA at the exported K, Kalico tanh (the fit's match) and Orca's adaptive table
  (the fit's K(q) table);
- the exported K (median of per-draw optima) against the truth's optimal K (the same
  search on the true values): relative error, and whether the 95 % interval holds it.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from bench.common import Row

SPEEDS = (20.0, 80.0)


def _log(msg):
    print(f"  bench_export: {msg}", file=sys.stderr, flush=True)


def _fit_doc(seed: int = 0) -> tuple[dict, dict, str]:
    """(fit.json dict of the demo-truth fit, true values, model spec)."""
    from bench.bench_fit import make_data
    from fit.derived import derived_values, problem_advance
    from fit.firmware_match import tested_flow_range
    from fit.model import build_model
    from fit.sampler import fit_map, fit_mcmc, make_problem
    from fit.truth import load_truth
    from patterns.profile import data_dir, load_profile

    prof = load_profile("direct_drive")
    spec, values, _ = load_truth(data_dir() / "truths" / "direct_drive.toml", prof)
    _, sc, _ = make_data("direct_drive", spec, values, seed, speeds=SPEEDS, n_steps=4,
                         step_s=(3.0,))
    pb = make_problem(build_model(spec, prof), sc)
    t0 = time.perf_counter()
    r = fit_mcmc(pb, map_result=fit_map(pb, seed=seed, global_search=True), seed=seed,
                 progress=False, max_steps=8000, n_loo_draws=50)
    adv = problem_advance(pb)
    r.derived = derived_values(r.param_names, r.samples, r.profile,
                               advance_fn=adv[0] if adv else None, v_max_mm_s=adv[1] if adv else None)
    r.derived["tested_flow_mm3_s"] = tested_flow_range(pb)
    r.model = spec
    _log(f"fit {spec} in {time.perf_counter() - t0:.0f} s: "
         + ", ".join(f"{k} {p.median:.4f} [{p.ci95[0]:.4f}, {p.ci95[1]:.4f}]" for k, p in r.params.items()))
    doc = r.to_json()
    doc["samples"] = np.asarray(doc["samples"])
    return doc, values, spec


def run() -> list[Row]:
    from fit import firmware_match as fm
    from patterns.profile import load_profile

    doc, values, spec = _fit_doc()
    ref = fm.prepare_reference(fm.standard_reference(load_profile("direct_drive")), "standard")
    t0 = time.perf_counter()
    # Marlin/RRF: no smoothing; Kalico and the table compared without it too (same firmware)
    m = fm.match_firmware(doc, ref, smooth_time_s=0.0, kalico_smooth_time_s=0.0)
    t_match = time.perf_counter() - t0
    # the truth: the same physics with the true values, one "draw"
    names = list(values)
    true_doc = {"model": spec, "param_names": names, "samples": np.array([[values[k] for k in names]]),
                "profile": doc["profile"]}
    truth = fm.physics_from_fit(true_doc, n_draws=1)
    k_true = float(fm.optimal_linear(truth, ref, smooth_time_s=0.0)["k_s"][0])
    settings = [s for s in m.settings if s.kind != "linear"] + \
        [fm.Setting("linear", m.k_s["median"], 0.0), fm.Setting("linear", values["pa.tau_s"], 0.0)]
    labels = {"none": "no PA", "tanh": "Kalico tanh", "recipr": "Kalico recipr",
              "table": "adaptive table"}
    e = fm.width_errors_mm(truth, ref, fm._theta_for(truth, settings))
    rows = []
    names_out = [labels.get(s.kind, "linear PA (exported K)") for s in settings[:-1]] + ["linear PA = tau"]
    for i, (lab, s) in enumerate(zip(names_out, settings)):
        if s.kind == "recipr":
            continue
        for c in ("starts", "stops", "all"):
            rows.append(Row("export", f"demo truth, standard mix: width error at {c}, {lab}",
                            1e3 * float(e[c][i]), "um", "-", None))
    lo, hi = m.k_s["ci95"]
    rows += [
        Row("export", f"exported K {m.k_s['median']:.4f} s vs truth's optimal K {k_true:.4f} s "
                      f"(tau {values['pa.tau_s']:.3f} s): relative error", 100 * abs(m.k_s["median"] / k_true - 1),
            "%", "<= 5", abs(m.k_s["median"] / k_true - 1) <= 0.05),
        Row("export", f"95 % interval of the exported K [{lo:.4f}, {hi:.4f}] holds the truth's optimal K",
            float(lo <= k_true <= hi), "bool", "1", bool(lo <= k_true <= hi)),
        Row("export", f"width match time ({m.n_draws} draws, standard mix)", t_match, "s", "<= 30",
            t_match <= 30),
    ]
    _log(f"exported K {m.k_s['median']:.4f} [{lo:.4f}, {hi:.4f}], truth's optimal K {k_true:.4f}, "
         f"match {t_match:.1f} s")
    return rows


if __name__ == "__main__":
    from bench.common import print_table
    print_table(run())
