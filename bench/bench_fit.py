"""Fit bench (issue 5): recovery, interval calibration, efficiency, peers and speed, on
virtual-printer data at realistic noise.

Data: the spiral-step pattern (seed 004) printed on the virtual printer (fit/virtual.py);
widths + noise drawn from the likelihood's own noise model (fit/likelihood.py): white
measurement noise of the reported width_sd 0.01 mm plus a bead wobble of sd 0.01 mm,
AR(1) along each track with correlation length 1 mm (phi = exp(-0.25/1) between
stations). bench_e2e scores the same fits on rendered, measured widths instead.
Recovery, calibration, efficiency and peer rows fit the spiral's test track alone (the
manifest cut to it, as tests/test_fit_cli.py: the frame and labels are ~90 % of the
timeline and only cost time); the speed rows fit whole patterns as a user would.

Rows
- recovery: median |tau error| of `pa` over seeds, Bowden and direct drive (<= 3 %);
- calibration: share of seeds whose 90 % interval holds the truth, every physical
  parameter of pa, pa+thermal, pa+backpressure (80-97 %; with 40 seeds the binomial
  sd at 90 % is 4.7 points);
- efficiency: median over seeds of posterior sd(tau) / Cramer-Rao sd, the CR bound from
  the Fisher information J^T Sigma^-1 J (J = d width / d tau by central differences at
  the truth, Sigma the AR(1) covariance of the noise model above) on the same data
  (<= 1.5; the Gaussian Fisher matrix is block-diagonal between mean and noise
  parameters, so tau's bound is 1/sqrt(J^T Sigma^-1 J));
- peers: median |error| of the Duet3D method (fit.peers.duet3d_pa on the same track,
  first nozzle diameter after each step skipped) and of the OrcaSlicer PA Line ladder
  (fit.peers.ladder_pa: the ladder printed on the same virtual printer with the same
  noise, most even line) as a ratio to ours (> 1: ours is more accurate). The truths
  sit between ladder values, as a real printer's would;
- speed: wall time (median of 3 seeds) of a `pa` fit on ~20,000 samples (<= 15 s) and of the four-parameter
  nonlinear composition pa+nonlinear+backpressure (<= 60 s).

``CALIB_BENCH_FIT_SEEDS`` sets the calibration seed count (default 40). Seeds run in 2
processes; progress goes to stderr.
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from bench.common import Row
from calib.parallel import process_pool

NOISE = {"sd_mm": 0.01, "sigma_extra_mm": 0.01, "corr_len_mm": 1.0}
#: recovery/peer truths (between Orca ladder values: 0.042|0.044, 0.60|0.62)
TRUTH = {"direct_drive": {"pa.tau_s": 0.043}, "long_bowden": {"pa.tau_s": 0.61}}
#: Bead back-pressure of the direct drive. Kb is in mm of filament advance per mm of bead
#: width, so like tau it scales with the compliance of the filament spring: seed 001 and
#: the realdata AUTHOR-NOTES (Bowden) use Kf = tau 0.4-1 s with Kb 1-3, Kb / tau ~2-7.5
#: per s; the direct drive's tau = 0.043 s gives Kb ~0.1-0.3. (Kb = 1 on a direct drive,
#: 23x tau, made the bead the whole extruder lag and left pa/nonlinear unidentifiable.)
KB_DIRECT = 0.2
#: calibration truths (direct drive; data/truths/*.toml values where they fit 12 s of data)
CAL_TRUTH = {
    "pa": {"pa.tau_s": 0.043},
    "pa+thermal": {"pa.tau_s": 0.043, "thermal.a": 0.1, "thermal.tau_s": 3.0},
    "pa+backpressure": {"pa.tau_s": 0.043, "backpressure.kb": KB_DIRECT, "backpressure.w_sat_mm": 0.8},
}
SPIRAL = {"speeds": (20.0,), "n_steps": 6, "step_s": (3.0,)}        # 18 s, 1440 samples
CAL_SPIRAL = {"speeds": (20.0,), "n_steps": 4, "step_s": (3.0,)}    # 12 s, 960 samples
#: pa+backpressure: the saturating Kb*w_sat*tanh(w/w_sat) needs more than the default two
#: width levels to pin w_sat (with 0.35/0.8 only, w_sat ran up its prior to 1.5 mm and
#: dragged tau with it: 77.5 % coverage of tau); three levels over 18 s, 1440 samples
CAL_SPIRAL_BP = {"speeds": (20.0,), "n_steps": 6, "step_s": (3.0,), "widths_mm": (0.35, 0.6, 0.8)}


def _log(msg):
    print(f"  bench_fit: {msg}", file=sys.stderr, flush=True)


def make_data(profile_name, spec, values, seed, speeds=(20.0,), n_steps=6, step_s=(3.0,),
              trim=True, widths_mm=(0.35, 0.8), noise=None):
    """(model, ScanData, manifest) of a noisy virtual spiral-step print (``noise`` as
    :data:`NOISE`, the default)."""
    noise = noise or NOISE
    from fit.data import scan_from_table
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile(profile_name)
    _, man = spiral_step.generate(prof, speeds_mm_s=speeds, n_steps=n_steps, step_s=step_s,
                                  widths_mm=widths_mm)
    if trim:
        man = man.cut_to_test_tracks()
    model = build_model(spec, prof)
    t = print_virtual(man, model, values).table
    t.width_sd_mm[:] = noise["sd_mm"]
    sc = scan_from_table(t, man, f"seed{seed}")
    rng = np.random.default_rng(seed)
    phi = np.exp(-sc.gap_mm / noise["corr_len_mm"])         # 0 at a track start
    e = np.empty(sc.n_valid)
    for i in range(sc.n_valid):
        u = rng.standard_normal()
        e[i] = u if i == 0 or phi[i] == 0 else phi[i] * e[i - 1] + math.sqrt(1 - phi[i] ** 2) * u
    white = rng.standard_normal(sc.n_valid)
    t.width_mm[sc.order] = t.width_mm[sc.order] + noise["sigma_extra_mm"] * e + noise["sd_mm"] * white
    sc.y_mm = t.width_mm[sc.order].copy()
    return model, sc, man


def crb_sd(model, sc, values, name="pa.tau_s", rel_h=1e-3) -> float:
    """Cramer-Rao sd of ``name``: 1/sqrt(J^T Sigma^-1 J), J by central differences at
    the truth, Sigma the covariance of the noise model (whitened exactly by its Kalman
    filter, fit.likelihood.whiten)."""
    from fit.likelihood import whiten

    m = model.with_values(values)
    th = m.default_theta()
    j = m.param_names.index(name)
    h = rel_h * abs(th[j])
    pts = np.array([th, th])
    pts[0, j] += h
    pts[1, j] -= h
    pred = m.predict(sc.ctx, pts)[:, sc.order]
    J = (pred[0] - pred[1]) / (2 * h)
    w = whiten(J, sc.sd_mm, NOISE["sigma_extra_mm"], sc.gap_mm, NOISE["corr_len_mm"])
    return float(1.0 / math.sqrt(np.sum(w * w)))


def _one(job):
    from fit.peers import duet3d_pa, ladder_pa
    from fit.sampler import fit_mcmc

    kind, profile_name, spec, values, seed, kw, fit_kw = job
    model, sc, man = make_data(profile_name, spec, values, seed, **kw)
    t0 = time.perf_counter()
    r = fit_mcmc(model, sc, seed=seed, progress=False, n_loo_draws=50, **fit_kw)
    out = {"time_s": time.perf_counter() - t0, "converged": r.converged, "n": sc.n_valid,
           "steps": r.diagnostics["n_steps"]}
    for name, v in values.items():
        p = r.params[name]
        sd = float(np.std(r.samples[:, r.param_names.index(name)]))
        out[name] = (p.median, p.ci90[0], p.ci90[1], v, sd)
    if kind == "recovery":
        tau = values["pa.tau_s"]
        out["crb_sd"] = crb_sd(model, sc, values)
        tid = [tr.id for tr in man.tracks if tr.kind == "test"][0]
        sel = sc.table.track[sc.order] == tid
        v_mm_s, st = kw.get("speeds", (20.0,))[0], kw.get("step_s", (3.0,))[0]
        try:
            out["duet3d"] = duet3d_pa(sc.table.s_mm[sc.order][sel], sc.y_mm[sel], v_mm_s * st, v_mm_s,
                                      skip_mm=float(man.printer["nozzle_diameter_mm"]))
        except Exception:          # the method failing on a dataset counts as a miss
            out["duet3d"] = float("nan")
        out["ladder"] = ladder_pa(profile_name, values, spec=spec, seed=seed,
                                  noise_sd_mm=math.hypot(NOISE["sd_mm"], NOISE["sigma_extra_mm"]))
        out["ours"] = r.params["pa.tau_s"].median
        out["truth"] = tau
    return out


def _run(jobs, workers, label):
    t0 = time.perf_counter()
    from fit.kernels import set_threads

    # one numba thread per worker process: 2 workers x 2 threads would oversubscribe
    with process_pool(workers, initializer=set_threads, initargs=(1,)) as ex:
        res = []
        for i, r in enumerate(ex.map(_one, jobs)):
            res.append(r)
            _log(f"{label} {i + 1}/{len(jobs)} ({time.perf_counter() - t0:.0f} s)")
        return res


def _ratio(a, b):
    return float(a / b) if b > 0 else float("inf")


class _Rows(list):
    """A list of rows that also logs each row to stderr as it is measured."""

    def append(self, r: Row) -> None:
        _log(f"ROW {r.metric} = {r.value:.4g} {r.unit} (target {r.target}, ok={r.passed})")
        super().append(r)


def run() -> list[Row]:
    rows: list[Row] = _Rows()
    workers = 2
    fit_kw = {"max_steps": 4000, "max_time_s": 60.0}
    n_rec = int(os.environ.get("CALIB_BENCH_FIT_REC_SEEDS", "8"))
    for prof, vals in TRUTH.items():
        res = _run([("recovery", prof, "pa", vals, s, SPIRAL, fit_kw) for s in range(n_rec)],
                   workers, f"recovery {prof}")
        tau = vals["pa.tau_s"]
        err = np.array([abs(r["ours"] / tau - 1) for r in res]) * 100
        med = float(np.median(err))
        rows.append(Row("fit", f"pa tau median |error|, {prof} (tau {tau:g} s), {n_rec} seeds",
                        med, "%", "<= 3", med <= 3))
        eff = float(np.median([r["pa.tau_s"][4] / r["crb_sd"] for r in res]))
        rows.append(Row("fit", f"pa posterior sd(tau) / Cramer-Rao sd, {prof}, median of {n_rec}",
                        eff, "x", "<= 1.5", eff <= 1.5))
        for peer, what in (("duet3d", "Duet3D section-average exp fit"),
                           ("ladder", "Orca PA Line ladder, most even line")):
            perr = np.array([abs(r[peer] / tau - 1) if np.isfinite(r[peer]) else np.inf
                             for r in res]) * 100
            ratio = _ratio(float(np.median(perr)), med)
            rows.append(Row("fit", f"{what} median |error| {np.median(perr):.2f} % / ours, {prof}",
                            ratio, "x", "> 1 (ours better)", ratio > 1))
    n_seeds = int(os.environ.get("CALIB_BENCH_FIT_SEEDS", "40"))
    # each fit converges in 3-40 s on one thread; the cap only stops a pathological chain
    # (such a fit still counts: coverage is over every seed, and the row says how many
    # converged; R-hat just above 1.01 is the other way a fit is not counted converged)
    cal_kw = {"max_steps": 20000, "max_time_s": 120.0}
    for spec, vals in CAL_TRUTH.items():
        spiral = CAL_SPIRAL_BP if "backpressure" in spec else CAL_SPIRAL
        res = _run([("calibration", "direct_drive", spec, vals, 1000 + s, spiral, cal_kw)
                    for s in range(n_seeds)], workers, f"coverage {spec}")
        n_conv = sum(r["converged"] for r in res)
        for name, v in vals.items():
            cov = float(np.mean([r[name][1] < v < r[name][2] for r in res])) * 100
            rows.append(Row("fit", f"{spec}: 90% interval coverage of {name}, {n_seeds} seeds "
                                   f"({n_conv} converged)", cov, "%", "80-97", 80 <= cov <= 97))
    # speed: pa on ~20,000 samples (whole pattern: four spirals, ten 5 s steps), and the
    # four-parameter nonlinear composition; the step count until the stopping rule holds
    # varies from seed to seed (the 1 % tau-stability test), so each is timed on 3 seeds
    # and the median is the figure (the slowest is in the label)
    speed = (("pa", {"pa.tau_s": 0.043},
              {"speeds": (15.0, 20.0, 25.0, 30.0), "n_steps": 10, "step_s": (5.0,), "trim": False}, 15),
             ("pa+nonlinear+backpressure",
              {"pa.tau_s": 0.043, "nonlinear.n": 0.8, "backpressure.kb": KB_DIRECT,
               "backpressure.w_sat_mm": 0.8},
              {"speeds": (15.0, 30.0), "n_steps": 6, "step_s": (3.0,), "trim": False}, 60))
    for spec, vals, kw, target in speed:
        res = [_one(("speed", "direct_drive", spec, vals, seed, kw, {})) for seed in (7, 8, 9)]
        t = [r["time_s"] for r in res]
        conv = sum(r["converged"] for r in res)
        _log(f"speed {spec}: {', '.join(f'{x:.1f}' for x in t)} s")
        k = len(vals)
        rows.append(Row("fit", f"{spec} ({k} param{'s' * (k > 1)}) fit wall time, {res[0]['n']} samples, "
                               f"median of 3 seeds (max {max(t):.1f} s, {conv}/3 converged)",
                        float(np.median(t)), "s", f"<= {target}",
                        float(np.median(t)) <= target and conv == 3))
    return list(rows)


if __name__ == "__main__":
    from bench.common import print_table

    print_table(run())
