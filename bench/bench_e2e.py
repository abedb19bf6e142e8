"""End to end: print -> picture -> measure -> fit, and do the 90 % intervals hold the truth?

bench_fit scores the fitter on widths drawn from its own likelihood; bench_realism scores
the measurement on pictures it does not assume. Here the two meet (issue #11 item 5): the
direct-drive spiral-step pattern is printed on the virtual printer, rendered as a 600 dpi
flatbed scan with every phenomenon of measure/phenomena.py (the bead's shaded and
translucent profile, glare, strings, raster gaps, PEI grain, logos, uneven light, defocus,
JPEG, and the bead's own irregular width), measured by the full pipeline (`calib
measure`: markers, widths, the apparent-width calibration on the prime line) and fitted
on the test track. Truth = the virtual printer's parameters.

Rows, over ``CALIB_BENCH_E2E_SEEDS`` seeds (default 40; ``CALIB_BENCH_E2E_BP_SEEDS`` for the
back-pressure truth, default the same: its fits take ~5 min each; ``CALIB_BENCH_E2E_PHONE_SEEDS``
for the second scene, the `pa` print photographed by a 12 MP phone at 35 deg, default 24
or fewer; ``CALIB_BENCH_E2E_BOWDEN_SEEDS`` for the third, a Bowden Adventurer 3 with
thermal ooze and back-pressure (data/truths/bowden.toml) on its default spiral, default 10
or fewer; ``CALIB_BENCH_E2E_SPARKLE_SEEDS`` for the fourth, the back-pressure print
photographed by the phone on a plate that sparkles (measure/phenomena.py), default 6 or
fewer, and ``CALIB_BENCH_E2E_SPARKLE_STACK_SEEDS`` for the same print pictured 5 times
with the lamp moved (measure/stack.py), default 6 or fewer; ``CALIB_BENCH_E2E_DEMO_SEEDS`` for the fifth, `make demo`'s own setup (the Bowden
print on a flatbed with no phenomena, fitted with the demo's final model), default 10 or
fewer; ``CALIB_BENCH_E2E_PATTERN_SEEDS`` for the seed-001 patterns, the RetractTest and the
StartStopTest on a direct drive with a nonlinear nozzle, default 4 or fewer each (a
StartStopTest fit takes ~9 min); ``CALIB_BENCH_E2E_STOP_SEEDS`` for the stop-mid-path ooze
test on the Bowden printer with every phenomenon, default 2 or fewer (~19 min a fit); 2
processes):
- the share of seeds whose 90 % interval holds the truth, for tau of `pa+spread(+scan_bias)`
  and for tau, Kb, w_sat of `pa+backpressure+spread+scan_bias` (80-97 %; scan_bias with the
  prior `calib fit` gives it from the measurement's calibration; binomial sd at 90 % with 40 seeds
  4.7 points). A seed whose picture cannot be measured or whose fit fails counts as a miss;
- the same for plain `pa` (no target: it shows why `spread` is in the model: the bead
  smooths its own width beyond the nozzle window and `pa` alone reads tau high);
- median |tau error| and median width RMS / bias of the measurement against the truth;
- how many of the fits that miss the truth the trust verdict (fit/trust.py, as `calib fit`
  prints it) still calls trustworthy: the confident wrong numbers, and how many it trusts.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np

from bench.common import Row

PROFILE = "direct_drive"
#: seconds of the print before the test track that the fit simulates (see measured_scan)
PAD_S = 5.0
#: truth spec -> (values, the pattern's keywords (spiral step unless the key names another), fitted models)
CASES = {
    "pa": ({"pa.tau_s": 0.043},
           {"speeds_mm_s": (20.0,), "n_steps": 6, "step_s": (3.0,), "widths_mm": (0.35, 0.8)},
           ("pa+spread+scan_bias", "pa+spread", "pa")),
    # scan_bias: the calibrated widths still carry the calibration's own error and a width
    # scale error (b1 -1.9 % on seed 2); without it 2 of 3 w_sat misses came from there
    # Two speeds, as the pattern users print (spiral_step's default has two): at one speed
    # the nozzle's lag (tau, s) and the bead's (Kb A_f / h, mm of track) are one time and
    # the fit cannot tell them apart (seed 0: corr(tau, Kb) -0.73, tau 90 % [0.024, 0.074]
    # for 0.043, and 40 of 40 intervals held tau and w_sat); at 20 and 40 mm/s corr -0.45,
    # [0.033, 0.047], and the fit took no longer (232 s against 269)
    "pa+backpressure": ({"pa.tau_s": 0.043, "backpressure.kb": 0.2, "backpressure.w_sat_mm": 0.8},
                        {"speeds_mm_s": (20.0, 40.0), "n_steps": 6, "step_s": (3.0,),
                         "widths_mm": (0.35, 0.6, 0.8)},
                        ("pa+backpressure+spread+scan_bias",)),
    # A second scene, so coverage is not a property of one camera: the same `pa` print
    # photographed by a 12 MP phone at 35 deg (JPEG, lens distortion; every phenomenon)
    "pa, phone": ({"pa.tau_s": 0.043},
                  {"speeds_mm_s": (20.0,), "n_steps": 6, "step_s": (3.0,), "widths_mm": (0.35, 0.8)},
                  ("pa+spread+scan_bias",)),
    # A third printer, the one our real photos come from: a Bowden Adventurer 3 with the
    # truth of data/truths/bowden.toml (slow spring, thermal ooze, back-pressure), the
    # default spiral a user prints for it, flatbed with every phenomenon. Its width
    # reference does not settle, so the widths reach the fit as apparent widths and
    # scan_bias carries the offset; the model is the one `--model auto` chose on seed 1
    "pa+thermal+backpressure, flatbed, adventurer3": (
        {"pa.tau_s": 0.8, "thermal.a": 0.05, "thermal.tau_s": 25.0, "backpressure.kb": 1.0,
         "backpressure.w_sat_mm": 0.8},
        {}, ("pa+backpressure+thermal+scan_bias+view_light",)),
}
# The back-pressure print photographed by the phone at 35 deg on a plate whose grain
# sparkles under the lamp (measure/phenomena.py sparkle: the realdata photos' width
# scatter): the widths err ~50 um per station, with a width-dependent mean the straight
# line of scan_bias cannot take; what is asked is that no wrong value is trusted
CASES["pa+backpressure, phone, direct_drive, all+sparkle"] = CASES["pa+backpressure"]
# ... and the same print pictured 5 times from one camera, the lamp moved between the
# pictures (render's light_seed), measured together (measure/stack.py): the specks average out
SPARKLE_STACK = "pa+backpressure, phone, direct_drive, all+sparkle, spiral-step, 5 pictures"
CASES[SPARKLE_STACK] = CASES["pa+backpressure"]
#: pictures per case (1 unless named)
PICTURES = {SPARKLE_STACK: 5}
# `make demo`'s own setup: the Bowden print as the demo scans it (600 dpi flatbed, beads as
# the measurement assumes them: no phenomena) and the model the demo ends with. The widths
# are calibrated to ~1 um, so what is asked is the fit's own honesty: session 38 found
# thermal.tau_s's Laplace |z| up to 14 over seeds 2-11 before the linked measurement
# errors and the width offset's doubt (fit/offset_envelope.py)
DEMO = "pa+thermal+backpressure, flatbed, adventurer3, none"
CASES[DEMO] = (CASES["pa+thermal+backpressure, flatbed, adventurer3"][0], {}, ("pa+backpressure+thermal",))
# The seed-001 patterns (issue #10): the RetractTest (designs 1 and 4, 3 lines each: beads
# of different heights, and of different speeds at one height) and the StartStopTest, on
# the direct drive with a nonlinear nozzle, as in docs/MEASUREMENT.md "What lies under and
# beside the bead": where plate print passed for bead and the fit said chi2_nu 16 and 156
PATTERN_TRUTH = {"pa.tau_s": 0.04, "nonlinear.n": 0.8}
PATTERN_MODELS = ("pa+nonlinear+spread+scan_bias",)
RETRACT = "pa+nonlinear, flatbed, direct_drive, all, retract"
START_STOP = "pa+nonlinear, flatbed, direct_drive, all, start-stop"
CASES[RETRACT] = (PATTERN_TRUTH, {"designs": (1, 4), "n_steps": 3}, PATTERN_MODELS)
CASES[START_STOP] = (PATTERN_TRUTH, {}, PATTERN_MODELS)
# The stop-mid-path ooze test (seed 000, KISSlicer Preload) where ooze matters, on the Bowden
# Adventurer 3 with every phenomenon: the print that `calib pattern stop-mid-path` makes
STOP_MID_PATH = "pa+thermal+backpressure, flatbed, adventurer3, all, stop-mid-path"
CASES[STOP_MID_PATH] = (CASES["pa+thermal+backpressure, flatbed, adventurer3"][0], {},
                        ("pa+backpressure+thermal+spread+scan_bias",))
#: seconds of the print before the test track the fit simulates, where PAD_S is too short:
#: thermal ooze (25 s) still acts when the test track starts
PAD_S_CASE = {"pa+thermal+backpressure, flatbed, adventurer3": 60.0, DEMO: 60.0, STOP_MID_PATH: 60.0}


#: |z| of the 99 % interval's edge (Gaussian)
Z99 = 2.576


def _z(est: tuple, truth: float) -> float:
    """|truth - median| in posterior sds from a (median, 5 %, 95 %) triple, the sd taken from
    the interval's side that faces the truth (posteriors of positive scales are skewed)."""
    med, lo, hi = est
    half = (hi - med) if truth > med else (med - lo)
    return abs(truth - med) / max(half / 1.645, 1e-300)


def _truth_camera(case: str) -> tuple[str, str, str]:
    """(truth spec, camera, printer profile) of a CASES key: "pa", "pa, phone",
    "spec, camera, profile", "spec, camera, profile, realism" (see :func:`_realism`) or
    "spec, camera, profile, realism, pattern" (see :func:`_pattern`)."""
    parts = [p.strip() for p in case.split(",")] + ["", ""]
    return parts[0], parts[1] or "flatbed", parts[2] or PROFILE


def _realism(case: str) -> str:
    """The phenomena a CASES key renders: its fourth part with "+" for ",", default "all"."""
    parts = [p.strip() for p in case.split(",")]
    return parts[3].replace("+", ",") if len(parts) > 3 and parts[3] else "all"


def _pattern(case: str):
    """The patterns module a CASES key prints: its fifth part (a `calib pattern` name),
    default the spiral step."""
    from patterns import retract, spiral_step, start_stop, stop_mid_path

    parts = [p.strip() for p in case.split(",")]
    name = parts[4] if len(parts) > 4 and parts[4] else "spiral-step"
    return {"spiral-step": spiral_step, "retract": retract, "start-stop": start_stop,
            "stop-mid-path": stop_mid_path}[name]


def _log(msg):
    print(f"  bench_e2e: {msg}", file=sys.stderr, flush=True)


def measured_scan(case: str, seed: int, realism: str | None = None):
    """(ScanData of the measured test track, manifest cut to it, measurement figures) of a
    CASES key (truth spec, and camera after a comma); ``realism`` default: the case's."""
    realism = realism or _realism(case)
    from calib.commands.simulate import simulate_scan, write_image
    from fit.data import scan_from_table
    from measure.stack import measure_pictures
    from patterns.profile import load_profile

    values, pattern_kw, _ = CASES[case]
    spec, camera, profile = _truth_camera(case)
    prof = load_profile(profile)
    _, man = _pattern(case).generate(prof, **pattern_kw)
    n_pic = PICTURES.get(case, 1)
    renders = [simulate_scan(man, spec, values, camera, profile=prof, dpi=600.0, seed=seed, realism=realism,
                             tilt_deg=35.0, light_seed=k if n_pic > 1 else None)[0] for k in range(n_pic)]
    rendered = renders[0]
    with tempfile.TemporaryDirectory() as d:
        res = measure_pictures([write_image(os.path.join(d, f"scan{k}.jpg" if r.encoded else f"scan{k}.png"), r)
                                for k, r in enumerate(renders)], man)
    test = [t.id for t in man.tracks if t.kind == "test"]
    sel = np.isin(res.table.track, test)
    tb, tr = res.table.subset(sel), rendered.table.subset(sel)
    ok = tb.valid & np.isfinite(tr.width_mm) & (tr.width_mm > 0)
    e = tb.width_mm[ok] - tr.width_mm[ok]
    figs = {"rms_mm": float(np.sqrt(np.mean(e ** 2))), "bias_mm": float(np.mean(e)),
            "valid": float(np.mean(tb.valid)), "calibrated": bool(res.summary["apparent_width"]["applied"]),
            "calibration": res.summary["apparent_width"]}
    # The fit's timeline starts PAD_S before the test track: the extruder's state there
    # comes from the prime line and markers printed before it, and with back-pressure it
    # is still felt 1 s later (146 um at the track start with a 1 s pad, 0.09 um with 5 s, 0 with 10 s).
    cut = man.cut_to_test_tracks(pad_s=PAD_S_CASE.get(case, PAD_S))
    return scan_from_table(tb, cut, f"seed{seed}"), cut, figs


def _one(job):
    from fit.model import build_model
    from fit.nuisance import refit_checks
    from fit.sampler import fit_map, fit_mcmc, make_problem
    from fit.measurement import prior_overrides, scatter
    from fit.noise_envelope import widen
    from fit.offset_envelope import widen_offset
    from fit.sandwich_envelope import widen_sandwich
    from fit.trust import assess, residual_structure
    from patterns.profile import load_profile

    spec, seed = job
    values, _, models = CASES[spec]
    out = {"spec": spec, "seed": seed, "fits": {}}
    t0 = time.perf_counter()
    try:
        sc, _, figs = measured_scan(spec, seed)
    except Exception as exc:          # a picture the pipeline refuses counts as a miss
        out["error"] = f"measure: {exc}"
        return out
    # the scan_bias prior `calib fit` takes from the measurement's summary (fit/measurement.py)
    states = [{"scan": sc.name, "calibration": figs.pop("calibration")}]
    out.update(figs)
    prof = load_profile(_truth_camera(spec)[2])

    def problem(spec):
        names = make_problem(build_model(spec, prof), sc).param_names
        return make_problem(build_model(spec, prof), sc, None, prior_overrides(states, names) or None)

    for m in models:
        try:
            pb = problem(m)
            # the MAP `calib fit` starts from (global search): the sampler's own local MAP sat
            # at spread 0 on phone seed 5 (tau 0.0459, outside the posterior's [0.0416,
            # 0.0450]), and the residual structure and the refits are judged at the MAP
            r = fit_mcmc(pb, map_result=fit_map(pb, seed=seed, global_search=True), seed=seed, progress=False,
                         n_loo_draws=50)
            # the verdict `calib fit` would print (fit/trust.py): is a miss flagged?
            r.diagnostics["residual_structure"] = residual_structure(pb, r.map.theta, seed=seed)
            # the intervals `calib fit` reports: widened by the width calibration's doubt where
            # the model has no scan_bias, and to hold the short-wobble fit too
            widen_offset(pb, r, states, seed=seed)
            env = widen(pb, r, seed=seed)
            widen_sandwich(pb, r, seed=seed)
            refit_checks(problem, m, r, seed=seed)      # judged against those intervals
            # the scan's own scatter, as `calib fit` writes it for the verdict
            r.diagnostics["measurement"] = {"scatter": [{"scan": sc.name, **scatter(sc)}]}
            v = assess(r.to_json())
        except Exception as exc:
            out["fits"][m] = {"error": str(exc)}
            continue
        out["fits"][m] = {"converged": bool(r.converged), "trustworthy": bool(v.trustworthy),
                          "why": "; ".join(p[:70] for p in v.problems),
                          "chi2_nu_bead": float(r.map.chi2_nu_bead),
                          # values the verdict names as riding an uncalibrated width offset
                          "flagged": [x["param"] for x in v.checks.get("offset_riders", [])],
                          # a misfit the verdict puts down to the scan's own scatter (rescan first)
                          "rescan": bool(v.checks.get("misfit_within_measurement_scatter")),
                          "envelope": {"applied": bool(env and env["applied"]),
                                       "delta_bic": env["bic_default"] - env["bic_short"] if env else None,
                                       "widened": sorted(env["widened"]) if env else []},
                          # a model without some of the truth's effects (a misspecified one)
                          # reports the values it has
                          **{n: (r.params[n].median, *r.params[n].ci90) for n in values if n in r.params}}
    out["time_s"] = time.perf_counter() - t0
    return out


def _run(jobs, workers):
    from calib.parallel import process_pool
    from fit.kernels import set_threads

    t0 = time.perf_counter()
    res = []
    with process_pool(workers, initializer=set_threads, initargs=(1,)) as ex:
        for i, r in enumerate(ex.map(_one, jobs)):
            res.append(r)
            fits = "; ".join(
                f"{m}: " + (f["error"][:60] if "error" in f else ", ".join(
                    f"{n.split('.')[-1]} {v[0]:.4g} [{v[1]:.4g}, {v[2]:.4g}]" for n, v in f.items()
                    if isinstance(v, tuple)) + f" (chi2_nu_bead {f['chi2_nu_bead']:.2f}, "
                    + ("trusted)" if f["trustworthy"] else f"NOT TRUSTWORTHY: {f['why']})"))
                for m, f in r["fits"].items()) or r.get("error", "")
            _log(f"{i + 1}/{len(jobs)} {r['spec']} seed {r['seed']} ({time.perf_counter() - t0:.0f} s) {fits}")
    return res


def run() -> list[Row]:
    n = int(os.environ.get("CALIB_BENCH_E2E_SEEDS", "40"))
    n_bp = int(os.environ.get("CALIB_BENCH_E2E_BP_SEEDS", str(n)))
    n_ph = int(os.environ.get("CALIB_BENCH_E2E_PHONE_SEEDS", str(min(n, 24))))
    n_bw = int(os.environ.get("CALIB_BENCH_E2E_BOWDEN_SEEDS", str(min(n, 10))))
    n_sp = int(os.environ.get("CALIB_BENCH_E2E_SPARKLE_SEEDS", str(min(n, 6))))
    n_sps = int(os.environ.get("CALIB_BENCH_E2E_SPARKLE_STACK_SEEDS", str(min(n, 6))))
    n_demo = int(os.environ.get("CALIB_BENCH_E2E_DEMO_SEEDS", str(min(n, 10))))
    n_pat = int(os.environ.get("CALIB_BENCH_E2E_PATTERN_SEEDS", str(min(n, 4))))
    n_stop = int(os.environ.get("CALIB_BENCH_E2E_STOP_SEEDS", str(min(n, 2))))
    bowden = "pa+thermal+backpressure, flatbed, adventurer3"
    sparkle = "pa+backpressure, phone, direct_drive, all+sparkle"
    # the slow fits first, so the two workers finish together
    jobs = [(STOP_MID_PATH, s) for s in range(n_stop)] + \
        [(START_STOP, s) for s in range(n_pat)] + [(RETRACT, s) for s in range(n_pat)] + \
        [(bowden, s) for s in range(n_bw)] + [(DEMO, s) for s in range(n_demo)] + \
        [(SPARKLE_STACK, s) for s in range(n_sps)] + [(sparkle, s) for s in range(n_sp)] + \
        [("pa+backpressure", s) for s in range(n_bp)] + [("pa, phone", s) for s in range(n_ph)] + \
        [("pa", s) for s in range(n)]
    res = _run(jobs, workers=2)
    rows: list[Row] = []
    for spec, (values, _, models) in CASES.items():
        rs = [r for r in res if r["spec"] == spec]
        if not rs:
            continue
        meas = [r for r in rs if "error" not in r]
        if meas:
            rows.append(Row("e2e", f"truth {spec}: measured width RMS / bias vs truth, median of {len(meas)} "
                                   f"(calibrated {sum(r['calibrated'] for r in meas)}/{len(meas)})",
                            float(np.median([r["rms_mm"] for r in meas])), "mm", "-", None))
            rows.append(Row("e2e", f"truth {spec}: measured width bias, median",
                            float(np.median([r["bias_mm"] for r in meas])), "mm", "-", None))
        for m in models:
            fits = [r["fits"].get(m, {"error": r.get("error", "")}) for r in rs]
            good = [f for f in fits if "error" not in f]
            conv = sum(f["converged"] for f in good)
            for name, truth in values.items():
                if good and not any(name in f for f in good):
                    continue
                hit = sum(1 for f in good if name in f and f[name][1] <= truth <= f[name][2])
                cov = hit / len(rs)
                target = "80-97 %" if m != "pa" else "- (no spread)"
                rows.append(Row("e2e", f"truth {spec}, fit {m}: 90% interval coverage of {name}, {len(rs)} seeds "
                                       f"({len(good)} fitted, {conv} converged)", 100 * cov, "%", target,
                                None if m == "pa" else bool(0.80 <= cov <= 0.97)))
            if good:
                # "never a confident wrong number": a fit whose 90 % interval misses the truth
                # on any parameter should have been called not trustworthy
                miss = [f for f in good if any(n in f and not f[n][1] <= t <= f[n][2] for n, t in values.items())]
                quiet = sum(f["trustworthy"] for f in miss)
                rescan = sum(bool(f.get("rescan")) for f in good)
                rows.append(Row("e2e", f"truth {spec}, fit {m}: misses (90 % interval) the verdict let through "
                                       f"of {len(miss)}; fits trusted {sum(f['trustworthy'] for f in good)}/{len(good)}"
                                       + (f", refused as the scan's scatter (rescan) {rescan}" if rescan else ""),
                                float(quiet), "fits", "-", None))
                # a 90 % interval misses one time in ten by design; what a user must not
                # get is a trusted value far outside it: the truth beyond the 99 % interval
                # (a value the verdict names as riding the width offset is warned, not quiet)
                trusted = [f for f in good if f["trustworthy"]]
                far = [f for f in trusted if max((_z(f[n], t) for n, t in values.items()
                                                  if n in f and n not in f.get("flagged", [])), default=0.0) > Z99]
                named = sum(len(f.get("flagged", [])) for f in good)
                expect = len(trusted) * (1 - 0.99 ** len(values))
                zmax = max((_z(f[n], t) for f in trusted for n, t in values.items()
                            if n in f and n not in f.get("flagged", [])), default=float("nan"))
                rows.append(Row("e2e", f"truth {spec}, fit {m}: trusted fits with the truth outside the 99 % "
                                       f"interval, of {len(trusted)} ({expect:.1f} expected; largest |z| {zmax:.2f}; "
                                       f"values named as riding the width offset: {named})",
                                float(len(far)), "fits", "-", None))
                # the noise-model hull (fit/noise_envelope.py): how often the short wobble's
                # fit was decisive, and how often it widened tau's interval
                env = [f.get("envelope") or {} for f in good]
                rows.append(Row("e2e", f"truth {spec}, fit {m}: intervals widened by the noise-model hull "
                                       f"(short wobble >= 10 BIC better on {sum(bool(e.get('applied')) for e in env)}"
                                       f"/{len(good)}; tau's widened on)",
                                float(sum("pa.tau_s" in e.get("widened", []) for e in env)), "fits", "-", None))
                err = [abs(f["pa.tau_s"][0] / values["pa.tau_s"] - 1) for f in good]
                rows.append(Row("e2e", f"truth {spec}, fit {m}: median |tau error|", 100 * float(np.median(err)),
                                "%", "-", None))
    return rows


if __name__ == "__main__":
    from bench.common import print_table
    print_table(run())
