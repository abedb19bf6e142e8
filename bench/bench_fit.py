"""Fit bench: recovery, interval calibration and speed on virtual-printer data.

Data: the spiral-step pattern printed on the virtual printer, widths + white noise
(sd 0.01 mm, reported as width_sd_mm) + AR(1) correlated noise (0.01 mm, 1 mm
correlation length) that the fitter must absorb with sigma_extra and the AR(1) term.
Seeds run in parallel processes. ``CALIB_BENCH_FIT_SEEDS`` sets the calibration seed
count (default 40).
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bench.common import Row

TRUTH = {"direct_drive": {"pa.tau_s": 0.04}, "long_bowden": {"pa.tau_s": 0.6}}


def make_data(profile_name, spec, values, seed, speeds=(20.0,), n_steps=4, step_s=(3.0,)):
    from fit.data import scan_from_table
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile(profile_name)
    _, man = spiral_step.generate(prof, speeds_mm_s=speeds, n_steps=n_steps, step_s=step_s)
    model = build_model(spec, prof)
    t = print_virtual(man, model, values).table
    rng = np.random.default_rng(seed)
    n = len(t)
    phi = np.exp(-0.25 / 1.0)
    e = np.empty(n)
    e[0] = rng.standard_normal()
    for i in range(1, n):
        e[i] = phi * e[i - 1] + np.sqrt(1 - phi * phi) * rng.standard_normal()
    t.width_sd_mm[:] = 0.01
    t.width_mm = t.width_mm + 0.01 * rng.standard_normal(n) + 0.01 * e
    return model, scan_from_table(t, man, f"seed{seed}")


def _one(job):
    from fit.sampler import fit_mcmc

    profile_name, spec, values, seed, kw = job
    model, sc = make_data(profile_name, spec, values, seed, **kw)
    t0 = time.perf_counter()
    r = fit_mcmc(model, sc, seed=seed, progress=False, max_steps=6000, n_loo_draws=50)
    out = {"time_s": time.perf_counter() - t0, "converged": r.converged, "n": sc.n_valid}
    for name, v in values.items():
        p = r.params[name]
        out[name] = (p.median, p.ci90[0], p.ci90[1], v)
    return out


def _run(jobs, workers):
    with ProcessPoolExecutor(max_workers=workers) as ex:
        res = []
        for i, r in enumerate(ex.map(_one, jobs)):
            res.append(r)
            print(f"  bench_fit: {i + 1}/{len(jobs)}", flush=True)
        return res


def run() -> list[Row]:
    rows: list[Row] = []
    workers = 2
    for prof, vals in TRUTH.items():
        res = _run([(prof, "pa", vals, s, {}) for s in range(6)], workers)
        err = [abs(r["pa.tau_s"][0] / r["pa.tau_s"][3] - 1) for r in res]
        med = float(np.median(err)) * 100
        rows.append(Row("fit", f"pa tau median |error|, {prof}, 6 seeds", med, "%", "<= 3", med <= 3))
    n_seeds = int(os.environ.get("CALIB_BENCH_FIT_SEEDS", "40"))
    res = _run([("direct_drive", "pa", TRUTH["direct_drive"], 1000 + s, {}) for s in range(n_seeds)],
               workers)
    cov = float(np.mean([r["pa.tau_s"][1] < r["pa.tau_s"][3] < r["pa.tau_s"][2] for r in res])) * 100
    rows.append(Row("fit", f"pa 90% interval coverage of tau, {n_seeds} seeds", cov, "%", "80-97",
                    80 <= cov <= 97))
    # speed: pa on ~20,000 samples (five 5 s steps at 4 speeds)
    kw = {"speeds": (15.0, 20.0, 25.0, 30.0), "n_steps": 10, "step_s": (5.0,)}
    r = _one(("direct_drive", "pa", TRUTH["direct_drive"], 7, kw))
    rows.append(Row("fit", f"pa fit wall time, {r['n']} samples (converged={r['converged']})",
                    r["time_s"], "s", "<= 15", r["time_s"] <= 15))
    return rows


if __name__ == "__main__":
    from bench.common import print_table

    print_table(run())
