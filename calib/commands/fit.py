"""`calib fit`: posterior of a composition of effects from measured widths.

    calib fit widths.csv --manifest OUT.manifest.json --model pa+thermal -o fit.json
    calib fit --data a.csv a.manifest.json --data b.csv b.manifest.json --model pa -o fit.json

Exit codes: 0 converged, 2 bad input, 3 the sampler did not converge (fit.json is still
written, with ``converged: false`` and the reason).
"""
from __future__ import annotations

import sys
from pathlib import Path

from calib.argtypes import integer, positive, seed
from calib.errors import UserError

EXIT_NOT_CONVERGED = 3


def add_parser(sub):
    p = sub.add_parser(
        "fit", help="fit extruder physics to measured widths (posterior with emcee)",
        description="Fit a model (effects joined by '+', e.g. pa+thermal) to a widths CSV and the "
                    "manifest that printed it: MAP, then an emcee posterior that stops on the "
                    "autocorrelation time. Writes fit.json (medians, 68/95 %% intervals, "
                    "diagnostics, BIC, PSIS-LOO, derived firmware values). Several --data pairs "
                    "make a joint fit (shared physics, per-scan flow gain and bed tilt). Exit code "
                    "3 when the sampler did not converge.")
    p.add_argument("widths", nargs="?", help="widths CSV from `calib measure`")
    p.add_argument("--manifest", help="manifest JSON the widths were measured against")
    p.add_argument("--data", nargs=2, action="append", metavar=("WIDTHS", "MANIFEST"), default=[],
                   help="a widths/manifest pair; repeat for a joint fit")
    p.add_argument("--model", default="pa",
                   help="effects joined by '+' (default: pa), or 'auto': start from pa (pa+scan_bias "
                        "when `calib measure` says the widths are apparent widths) and add "
                        "the effect `calib diagnose` names while it lowers BIC by >= 10 and the "
                        "reduced chi-square falls; the chain is printed")
    p.add_argument("--priors", help="TOML file overriding parameter priors (see fit/priors.py)")
    p.add_argument("--effects", help="Python file with user Effect classes")
    p.add_argument("--student-t", type=positive, default=None, metavar="NU",
                   help="Student-t noise with NU degrees of freedom (robust to outliers)")
    p.add_argument("--no-ar1", action="store_true", help="the bead's wobble uncorrelated along the track: samples independent (not advised)")
    p.add_argument("--constant-wobble", action="store_true",
                   help="the bead's wobble the same size at every width (default: a share "
                        "noise.rel_share of its variance grows with the width; fit/likelihood.py)")
    p.add_argument("--short-wobble", action="store_true",
                   help="a second wobble of the bead's width over ~0.4 mm besides the long one "
                        "(fit/likelihood.py): on the Bowden scenes it lowered BIC by 278-390 and its "
                        "intervals held tau where the default's missed; not the default (on "
                        "back-pressure scans it narrowed Kb's intervals below their error)")
    p.add_argument("--no-noise-envelope", action="store_true",
                   help="skip the second fit with the short wobble (one global-search MAP): by default, "
                        "when the widths carry a short wobble (BIC >= 10 lower with it), every interval is "
                        "widened to hold that fit too (fit/noise_envelope.py)")
    p.add_argument("--ignore-missing", action="store_true",
                   help="drop the stations flagged 'missing' (no bead seen) instead of fitting "
                        "them as beads narrower than the scan can see (default: fit them)")
    p.add_argument("--max-steps", type=integer(1), default=20000, help="cap on MCMC steps (default 20000)")
    p.add_argument("--max-time", type=positive, default=None, metavar="S", help="cap on wall time (s)")
    p.add_argument("--map-only", action="store_true", help="only the MAP fit (fast, no posterior)")
    p.add_argument("--jobs", type=integer(1), default=None,
                   help="threads for the physics kernels (default: every core)")
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--out", default="fit.json", help="output fit.json (default fit.json)")
    p.add_argument("--plots", metavar="DIR", help="write width/residual and corner plots here")
    p.add_argument("--chi2-max", type=positive, default=None, metavar="X",
                   help="reduced chi-square above which the fit is called a misfit and export "
                        "refuses its values (default 2.0, see fit/trust.py)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def data_pairs(args) -> list[tuple[str, str]]:
    pairs = [tuple(d) for d in args.data]
    if args.widths:
        if not args.manifest:
            raise UserError("give the manifest with --manifest OUT.manifest.json "
                            "(or use --data WIDTHS MANIFEST)")
        pairs.insert(0, (args.widths, args.manifest))
    elif args.manifest:
        raise UserError("--manifest given without a widths CSV")
    if not pairs:
        raise UserError("no data: give widths.csv --manifest M.json, or --data WIDTHS MANIFEST")
    return pairs


def run_fit(pairs, model_spec: str, *, priors=None, effects=None, student_nu=None, ar1=True,
            max_steps=20000, max_time_s=None, seed=0, progress=True, map_only=False,
            chi2_max=None, missing=True, relative=True, short=False, envelope=True):
    """Load, fit and return (FitResult or MapResult, JointProblem). Shared with `calib batch`.
    ``missing``: fit the stations flagged missing as censored data (fit/likelihood.py);
    False drops them (``--ignore-missing``). ``relative``: the wobble's sd has a part in
    proportion to the width (``--constant-wobble`` turns it off). ``short``: the bead's second,
    short wobble (``--short-wobble``). ``envelope``: widen the intervals to hold the fit with
    the short wobble too when the widths carry one (fit/noise_envelope.py;
    ``--no-noise-envelope`` turns it off)."""
    from fit.data import FitData
    from fit.derived import derived_values
    from fit.likelihood import NoiseOptions
    from fit.priors import load_priors_file
    from fit.sampler import fit_map, fit_mcmc, make_problem
    from fit.trust import CHI2_NU_MAX

    chi2_max = CHI2_NU_MAX if chi2_max is None else chi2_max

    extra = ()
    if effects:
        from fit.effects import load_effects_file
        extra = tuple(load_effects_file(effects))
    auto = None
    if model_spec == "auto":
        auto = choose_model(pairs, effects, extra, seed=seed, progress=progress, chi2_max=chi2_max,
                            missing=missing, priors=priors)
        model_spec = auto.model
    from fit import measurement

    data = FitData.load(pairs)
    user = load_priors_file(priors) if priors else {}
    if auto is not None:        # priors of effects the search did not choose do not apply
        names = make_problem(model_spec, data, None, None, extra).param_names
        user = {k: v for k, v in user.items() if k in names}
    noise = NoiseOptions(ar1=ar1, student_nu=student_nu, missing=missing, relative=relative, short=short)
    problem = make_problem(model_spec, data, noise, user or None, extra)
    # what `calib measure` said of its widths: scan_bias priors, and a caution (fit/measurement.py)
    states = measurement.scan_states(data)
    cal = {k: v for k, v in measurement.prior_overrides(states, problem.param_names).items() if k not in user}
    if cal:
        problem = make_problem(model_spec, data, noise, {**cal, **user}, extra)
    meas_notes = measurement.notes(states, any(n.startswith("scan_bias.") for n in problem.param_names),
                                   any(n.startswith("view_shift.") for n in problem.param_names))
    for n in meas_notes:
        print(f"calib fit: {n}", file=sys.stderr)
    for st in states:
        if st["widths"] and st["calibration"] is None:
            # Said, not assumed: a phone render's widths fitted without their summary (35 deg,
            # Bowden, seed 1) lost scan_bias's prior from the width reference and read tau
            # 0.887 [0.827, 0.965] for 0.8; with it 0.842 [0.786, 0.906]
            print(f"calib fit: {st['scan']}: no `calib measure` summary "
                  f"({Path(st['widths']).stem}.summary.json) beside its widths, so nothing says how "
                  f"they were measured or calibrated: they are fitted as given; if `calib measure` wrote "
                  f"them, keep its summary next to them", file=sys.stderr)
    x0 = None
    if auto is not None and auto.map_values:
        # The chain's own optimum is one start more: the global search alone can miss it. A
        # foreign back-pressure print's chain ended at chi2_nu_bead 1.85 and the final fit's
        # global search at 3.24 for the same model (bench_export_foreign), so the fit called
        # a model the chain had found to fit a misfit.
        x0 = problem.default_theta()
        for j, n in enumerate(problem.param_names):
            if n in auto.map_values:
                x0[j] = auto.map_values[n]
    m = fit_map(problem, seed=seed, global_search=True, x0=x0)
    if map_only:
        from fit.offset_envelope import doubt_text, widen_map_offset

        m.model = model_spec
        # the calibration's doubt of the widths' offset, as the full fit carries it
        info = widen_map_offset(problem, m, states)
        if info:
            print(f"calib fit: width calibration: {doubt_text(info)}; the sds carry it", file=sys.stderr)
        from fit.sandwich_envelope import MAX_RATIO, widen_map_sandwich

        sw = widen_map_sandwich(problem, m)
        if sw["applied"]:
            print("calib fit: the residuals scatter more than the noise model says (sandwich estimate); "
                  "the sds carry it: " + ", ".join(f"{p} x{min(sw['ratio'][p], MAX_RATIO):.2f}"
                                                   for p in sw["sd_before"]),
                  file=sys.stderr)
        return m, problem
    if m.chi2_nu_bead > chi2_max:
        # Said before the sampler's minutes (15 on a realdata photo), not only at the end:
        # no posterior makes a misfitting model's values trustworthy (fit/trust.py)
        print(f"calib fit: the best fit of {model_spec} already misfits the scan (reduced chi-square "
              f"{m.chi2_nu_bead:.3g} > {chi2_max:g} with the bead's own wobble allowed): its values will be "
              f"NOT TRUSTWORTHY (the verdict at the end says why and what to do); sampling the posterior "
              f"anyway (--map-only skips it)", file=sys.stderr)
    res = fit_mcmc(problem, map_result=m, max_steps=max_steps, max_time_s=max_time_s, seed=seed,
                   progress=progress)
    res.model = model_spec
    res.map.model = model_spec
    if auto is not None:
        res.diagnostics["model_search"] = auto.to_json()
    from fit.derived import problem_advance

    adv = problem_advance(problem)      # Kalico match for models with a nonlinear term

    def derive(samples):
        d = derived_values(res.param_names, samples, res.profile, advance_fn=adv[0] if adv else None,
                           v_max_mm_s=adv[1] if adv else None)
        # the firmware line of dynamics beyond linear PA, from the same draws: the offset
        # and noise envelopes below widen its interval as they widen tau's
        return firmware_k(d, {"model": model_spec, "param_names": res.param_names, "samples": samples,
                              "profile": res.profile})
    res.derived = derive(res.samples)
    from fit.firmware_match import tested_flow_range

    # `calib export` warns when a reference print goes beyond the flows the test covered
    flows = tested_flow_range(problem)
    if flows:
        res.derived["tested_flow_mm3_s"] = flows
    from fit.trust import assess, residual_structure

    res.diagnostics["residual_structure"] = residual_structure(problem, res.map.theta, seed=seed)
    from fit.offset_envelope import widen_offset

    # the calibration's doubt of the widths' offset, which a model without scan_bias takes as 0
    widen_offset(problem, res, states, seed=seed, derive=derive)
    if envelope:
        from fit.noise_envelope import widen

        widen(problem, res, seed=seed, derive=derive)
    from fit.sandwich_envelope import widen_sandwich

    # the residuals' own scatter at the scale the values are read at, where the noise
    # model's correlations are not theirs (measured widths smooth the bead's short wander)
    widen_sandwich(problem, res, seed=seed, derive=derive)
    if len(data.scans) == 1:    # a joint fit's per-scan parameters make the refit ambiguous; skipped
        from fit.nuisance import refit_checks

        def extended(spec):
            return make_problem(spec, data, noise, {**cal, **user} or None, extra)
        # After the envelopes: a refit that moves a value within the interval the user is
        # shown moves nothing they paste. Judged on the posterior's alone, `make demo`'s right
        # model was refused: `nonlinear` +95 BIC moved tau 0.7994 -> 0.798, outside the
        # posterior's [0.7986, 0.8001], inside the reported [0.7925, 0.8063].
        # --model auto's chain has already asked the library's effects.
        refit_checks(extended, model_spec, res, seed=seed, chi2_max=chi2_max, ask_missing=auto is None,
                     progress=progress)
    from fit.measurement import scatter

    res.diagnostics["measurement"] = {"scans": states, "notes": meas_notes,
                                      "scan_bias_priors": cal,
                                      "scatter": [{"scan": sc.name, **scatter(sc)} for sc in data.scans]}
    res.diagnostics["missing_stations"] = missing_info(problem)
    res.trust = assess(res.to_json(), chi2_max=chi2_max).to_json()
    return res, problem


def firmware_k(derived: dict, doc: dict) -> dict:
    """``derived`` (fit.derived.derived_values) where the fitted dynamics of ``doc`` (model,
    param_names, samples, profile) are more than linear PA: the firmware lines take the
    linear K that prints the standard move mix best (fit.firmware_match.fit_linear_k,
    Marlin/RRF: no smoothing), recorded as ``firmware_match``; ``pressure_advance_s`` stays
    the fitted time constant. A K at the search's limit gives no firmware line, nor do such
    dynamics where the move mix cannot be planned: tau is then only part of the advance (a
    probe print's partial printer dict gave "M900 K0.0471" for a best K of 0.201 s)."""
    from fit.derived import firmware_commands
    from fit.firmware_match import fit_linear_k

    out = {k: v for k, v in derived.items() if k != "firmware"}
    try:
        m = fit_linear_k(doc)
    except UserError as exc:
        out["firmware_match"] = {"unavailable": str(exc)}
        return out
    if m is None:
        return derived
    out["firmware_match"] = {"k_s": m.k_s, "reference": m.reference, "smooth_time_s": 0.0,
                             "rms_um": m.rms_opt_um, "n_at_limit": m.n_at_limit}
    if not m.n_at_limit:
        out["firmware"] = firmware_commands(m.k_s["median"])
    return out


def missing_info(problem) -> dict:
    """How many stations flagged missing (no bead seen) the fit used as censored data:
    {"used", "on_printed_tracks", "ignored"} (counts over all scans)."""
    from fit.likelihood import censored_rows

    on = int(sum(len(censored_rows(sc)) for sc in problem.scans))
    return {"used": int(problem.n_missing), "on_printed_tracks": on,
            "ignored": not problem.noise.missing}


def missing_text(info: dict) -> str:
    if info.get("ignored"):
        return (f"missing stations: {info['on_printed_tracks']} on printed tracks, ignored "
                "(--ignore-missing)")
    return (f"missing stations: {info['used']} fitted as beads narrower than the scan can see "
            f"(of {info['on_printed_tracks']} on printed tracks)")


def choose_model(pairs, effects_file, extra, *, seed=0, progress=True, chi2_max=None, missing=True,
                 priors=None):
    """``--model auto`` (fit/auto.py) on the one scan of ``pairs``; prints the chain.
    ``missing`` False (--ignore-missing): the search does not fit the missing stations either.
    The chain starts from ``pa``, or from ``pa+scan_bias`` when `calib measure` said the
    widths are apparent widths (fit/measurement.py: an unknown offset of tens of um passes
    for back-pressure or flow otherwise), with the same scan_bias prior `calib fit` uses,
    with ``+view_light`` when the widths carry the flank's angle to the light over its bands,
    and with ``+view_shift`` when the pose places the stations along their tracks loosely;
    ``priors``: the user's priors file, applied to every model that has the parameter."""
    from calib.commands.compare import scan_priors
    from fit import measurement
    from fit.auto import auto_model
    from fit.compare import observe
    from fit.effects import REGISTRY
    from fit.model import build_model
    from fit.trust import CHI2_NU_MAX
    from measure.table import WidthTable
    from patterns.manifest import Manifest

    if len(pairs) != 1:
        raise UserError("--model auto chooses the model on one scan; fit that scan with --model "
                        "auto first, then the joint fit with the model it chose")
    widths, manifest_path = pairs[0]
    manifest = Manifest.load(manifest_path)
    scan = observe(manifest, WidthTable.load(widths))
    if not missing:
        scan.missing_idx = scan.missing_idx[:0]
    base = measurement.start_for(scan, widths)[0]
    # every model of the chain with the priors `calib fit` gives the chosen one: a chain
    # from `pa` that adds scan_bias fits it with the calibration's prior, not the default
    pri = scan_priors(widths, (), priors, extra)
    res = auto_model(scan, lambda s: build_model(s, manifest.printer, extra_effects=extra),
                     list(REGISTRY), [c.name for c in extra], seed=seed, progress=progress,
                     chi2_max=CHI2_NU_MAX if chi2_max is None else chi2_max, base_spec=base,
                     priors=pri)
    print("model search (--model auto):")
    for line in res.lines():
        print(f"  {line}")
    return res


def run(args) -> int:
    pairs = data_pairs(args)
    for w, m in pairs:
        for f in (w, m):
            if not Path(f).exists():
                raise UserError(f"{f} does not exist")
    from fit.kernels import set_threads

    set_threads(args.jobs)
    res, problem = run_fit(pairs, args.model, priors=args.priors, effects=args.effects,
                           student_nu=args.student_t, ar1=not args.no_ar1,
                           max_steps=args.max_steps, max_time_s=args.max_time, seed=args.seed,
                           progress=not args.quiet, map_only=args.map_only, chi2_max=args.chi2_max,
                           missing=not args.ignore_missing, relative=not args.constant_wobble,
                           short=args.short_wobble, envelope=not args.no_noise_envelope)
    if args.map_only:
        import json
        from calib.fileio import atomic_write_text
        atomic_write_text(args.out, json.dumps({"schema": "calib.fit-map/1", **res.to_json()}, indent=1))
        print(missing_text(missing_info(problem)))
        for n, v in res.values.items():
            print(f"{n:32s} {v:.6g}")
        return 0
    res.save(args.out)
    print(summary_text(res))
    verdict = res.trust
    if verdict.get("trustworthy"):
        print(verdict_text(verdict))
    else:   # to stderr too: a redirected stdout must not hide it
        print(verdict_text(verdict), file=sys.stderr)
    if args.plots:
        from fit.plots import plot_fit
        for f in plot_fit(res, problem, args.plots):
            print(f"plot: {f}")
    print(f"wrote {args.out}")
    if not res.converged:
        print(f"calib fit: {res.diagnostics.get('warning', 'not converged')}", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return 0


def summary_text(res) -> str:
    lines = [f"model {res.model}: {res.map.n_obs} samples, rms {res.map.rms_mm * 1000:.1f} um, "
             f"chi2_nu {res.map.chi2_nu:.2f}, BIC {res.map.bic:.1f}, "
             f"elpd_loo {res.loo.get('elpd_loo', float('nan')):.1f}",
             *([missing_text(res.diagnostics["missing_stations"])]
               if "missing_stations" in res.diagnostics else []),
             f"{'parameter':32s} {'median':>10s} {'68% interval':>24s} {'95% interval':>24s}"]
    for n, p in res.params.items():
        lines.append(f"{n:32s} {p.median:10.5g} [{p.ci68[0]:10.5g}, {p.ci68[1]:10.5g}] "
                     f"[{p.ci95[0]:10.5g}, {p.ci95[1]:10.5g}]")
    d = res.diagnostics
    lines.append(f"sampler: {d['n_steps']} steps x {d['n_walkers']} walkers x {d['n_ensembles']} "
                 f"ensembles, max tau {max(d['tau_steps'].values()):.1f}, acceptance "
                 f"{d['acceptance_fraction']:.2f}, max R-hat {max(d['rhat'].values()):.4f}, "
                 f"{'converged' if res.converged else 'NOT CONVERGED'}")
    for i, m in enumerate(res.map.modes[1:4], start=2):
        phys = ", ".join(f"{n} {v:.4g}" for n, v in m["values"].items() if not n.startswith("noise."))
        lines.append(f"mode {i}: {phys}  (BIC {m['bic'] - res.map.modes[0]['bic']:+.1f} vs the best)")
    from fit.noise_envelope import envelope_line

    from fit.offset_envelope import offset_line
    from fit.sandwich_envelope import sandwich_line

    for env in (offset_line(res.diagnostics.get("offset_envelope")),
                envelope_line(res.diagnostics.get("noise_envelope")),
                sandwich_line(res.diagnostics.get("sandwich"))):
        if env:
            lines.append(env)
    fw = res.derived.get("firmware")
    # every value a user pastes (firmware PA, the slicer's VE, Kalico's constants) carries
    # the verdict on its own line: an interval printed beside an untrustworthy value reads
    # as a number to use (a Bowden user whose firmware ignores PA is sent to VE)
    trusted = res.trust.get("trustworthy", True)
    fm_k = res.derived.get("firmware_match")
    if (fw or fm_k) and not trusted:
        pa = res.derived["pressure_advance_s"]
        lines.append(f"pressure advance {pa['median']:.4f} s: NOT TRUSTWORTHY, no firmware line "
                     "(see the fit quality below)")
    elif fw and fm_k:
        pa, k = res.derived["pressure_advance_s"], fm_k["k_s"]
        lines.append(f"pressure advance (the fitted time constant) {pa['median']:.4f} s (95 % {pa['ci95'][0]:.4f}-"
                     f"{pa['ci95'][1]:.4f}); the dynamics are more than linear PA, so the linear K that prints "
                     f"{fm_k['reference']} best (no smoothing):")
        lines.append(f"  {k['median']:.4f} s (95 % {k['ci95'][0]:.4f}-{k['ci95'][1]:.4f}):"
                     f"  {fw['klipper']}  |  {fw['marlin']}  |  {fw['rrf']}  (`calib export --to TARGET` "
                     f"matches each firmware's smoothing)")
    elif fw:
        pa = res.derived["pressure_advance_s"]
        lines.append(f"pressure advance {pa['median']:.4f} s (95 % {pa['ci95'][0]:.4f}-{pa['ci95'][1]:.4f}):"
                     f"  {fw['klipper']}  |  {fw['marlin']}  |  {fw['rrf']}")
    elif fm_k and "unavailable" in fm_k:
        lines.append(f"pressure advance (the fitted time constant) {res.derived['pressure_advance_s']['median']:.4f} s: "
                     "no firmware line: the dynamics are more than linear PA, so tau is only part of the "
                     f"advance, and the move mix that gives the linear K cannot be planned ({fm_k['unavailable']})")
    elif fm_k:
        lines.append(f"pressure advance {res.derived['pressure_advance_s']['median']:.4f} s: no firmware line, "
                     f"the linear K that prints {fm_k['reference']} best lies at the search's limit "
                     "(see `calib export`)")
    if fw and trusted:
        prof = res.profile or {}
        if prof.get("firmware_pressure_advance", True) is False:
            # the Adventurer 3: its owner's tests found no effect of M900 even at K=200
            lines.append(f"  but the printer profile '{prof.get('name', '?')}' says its firmware ignores these "
                         "commands: use KISSlicer VE below (`calib export FIT --to kisslicer`)")
    ve = res.derived.get("kisslicer_ve_us")
    if ve and not trusted:
        lines.append(f"KISSlicer VE {ve['median']:.3f} us: NOT TRUSTWORTHY, not for the slicer profile "
                     "(see the fit quality below)")
    elif ve:
        lines.append(f"KISSlicer VE {ve['median']:.3f} us (95 % {ve['ci95'][0]:.3f}-{ve['ci95'][1]:.3f})")
    for kind in ("tanh", "recipr"):
        kd = res.derived.get(f"kalico_{kind}")
        if not kd:
            continue
        if not trusted:
            lines.append(f"Kalico {kind}: NOT TRUSTWORTHY, no firmware line (see the fit quality below)")
            continue
        parts = []
        for key, label, unit in (("pressure_advance_s", "linear_advance", "s"),
                                 ("offset_mm", "nonlinear_offset", "mm"),
                                 ("linearization_velocity_mm_s", "linearization_velocity", "mm/s")):
            q = kd[key]
            parts.append(f"{label} {q['median']:.4g} {unit} (95 % {q['ci95'][0]:.4g}-{q['ci95'][1]:.4g})")
        lines.append(f"Kalico {kind} (0-{kd['v_max_mm_s']:.2f} mm/s filament, rms "
                     f"{kd['rms_mm']['median'] * 1000:.1f} um): " + ", ".join(parts))
    return "\n".join(lines)


def verdict_text(verdict: dict) -> str:
    from fit.trust import Verdict

    return "\n".join(Verdict(**verdict).lines())
