"""`calib compare`: fit several models to one scan and compare them (RMS, chi2_nu, BIC, PSIS-LOO)."""
from __future__ import annotations

import json
import sys

from calib.argtypes import integer, seed
from calib.errors import UserError


def add_parser(subparsers):
    p = subparsers.add_parser(
        "compare", help="fit several models to one widths table and compare them",
        description="Fit each model (MAP with the noise model of `calib fit`, then emcee "
                    "run to convergence + PSIS-LOO unless --fast) to "
                    "the measured widths and print a table: residual RMS (mm), reduced "
                    "chi-square, BIC, PSIS-LOO elpd and its se, the differences to the best "
                    "model, and each model's parameters. Plots of data vs every model and the "
                    "residuals, track by track, with --plots DIR.")
    p.add_argument("widths", help="widths CSV from `calib measure` (or a simulation's truth)")
    p.add_argument("--manifest", required=True, help="the pattern's NAME.manifest.json")
    p.add_argument("--models", nargs="+", required=True, metavar="SPEC",
                   help="models to compare, e.g. pa pa+thermal pa+thermal+backpressure")
    p.add_argument("--effects", metavar="FILE.py",
                   help="a Python file with your own Effect classes, usable in --models")
    p.add_argument("--priors", help="TOML file overriding parameter priors, applied to each model that "
                                    "has the parameter (see fit/priors.py)")
    p.add_argument("--fast", action="store_true", help="MAP fits only (no emcee, no LOO)")
    p.add_argument("--steps", type=integer(1), default=20000,
                   help="cap on emcee steps per walker (the run stops earlier once it has "
                        "converged; a run that hits the cap is reported as not converged)")
    p.add_argument("--seed", type=seed, default=0, help="random seed")
    p.add_argument("-o", "--output", metavar="compare.json", help="write the comparison as JSON")
    p.add_argument("--plots", metavar="DIR", help="write data-vs-models and residual plots here")
    return p


def load_inputs(widths, manifest_path, effects=None):
    """(manifest, table, user effect classes) from CLI arguments, with one-line errors."""
    from measure.table import WidthTable
    from patterns.manifest import Manifest
    manifest = Manifest.load(manifest_path)
    table = WidthTable.load(widths)
    extra = []
    if effects:
        from fit.effects import load_effects_file
        extra = load_effects_file(effects)
    return manifest, table, extra


def scan_priors(widths, specs, priors_file=None, extra=(), prog: str = "calib") -> dict[str, dict]:
    """Prior overrides for every model fitted to the widths CSV ``widths``: what `calib
    measure` wrote beside it (fit.measurement.priors_for: the width offset's prior for
    ``scan_bias``, the stations' place for ``view_shift``), as `calib fit` applies it, then
    the user's ``priors_file`` over it. `calib fit`'s notes on those widths for the models
    ``specs`` (apparent widths and no ``scan_bias``...; none when empty) go to stderr. A name no effect
    (library or ``extra``) has is a one-line error: a search over models applies each prior
    to the models that have it, so a typo would apply to none, silently."""
    from fit.effects import REGISTRY
    from fit.measurement import notes, priors_for, scan_state
    from fit.priors import load_priors_file

    user = load_priors_file(priors_file) if priors_file else {}
    known = {f"{c.name}.{p.name}" for c in [*REGISTRY.values(), *extra] for p in c.params}
    bad = [k for k in user if k.split("@")[0] not in known and not k.startswith("noise.")]
    if bad:
        raise UserError(f"priors file names parameter {bad[0]!r}, which no effect has")
    parts = [set(s.split("+")) for s in specs]
    for n in notes([scan_state("widths", widths)], all("scan_bias" in p for p in parts),
                   all("view_shift" in p for p in parts)) if parts else ():
        print(f"{prog}: {n}", file=sys.stderr)
    return {**priors_for("widths", widths), **user}


def run(args) -> int:
    from calib.fileio import atomic_write_text
    from fit.compare import compare_models, observe
    from fit.model import build_model

    manifest, table, extra = load_inputs(args.widths, args.manifest, args.effects)
    if args.steps < 200:
        raise UserError("--steps must be at least 200 (emcee needs ~50 autocorrelation times)")
    models = {}
    for spec in args.models:
        if spec in models:
            raise UserError(f"model {spec} is listed twice in --models")
        models[spec] = build_model(spec, manifest.printer, extra_effects=extra)
    obs = observe(manifest, table)
    comp = compare_models(obs, models, full=not args.fast, seed=args.seed, max_steps=args.steps,
                          progress=True, priors=scan_priors(args.widths, list(models), args.priors, extra,
                                                             "calib compare"))
    print(format_table(comp.rows()))
    doc = comp.to_json()
    doc.update({"widths": str(args.widths), "manifest": str(args.manifest),
                "effects": str(args.effects) if args.effects else None})
    if args.output:
        atomic_write_text(args.output, json.dumps(doc, indent=1))
        print(f"wrote {args.output}", file=sys.stderr)
    if args.plots:
        from calib.report import plot_tracks
        path = plot_tracks(obs, comp.fits, args.plots)
        print(f"wrote {path}", file=sys.stderr)
    return 0


def format_table(rows: list[dict]) -> str:
    head = ("model", "RMS um", "chi2_nu", "BIC", "dBIC", "corr mm", "elpd_loo", "se", "d_elpd", "d_se",
            "converged")
    lines = []
    for r in rows:
        def f(x, fmt="{:.1f}"):
            return "-" if x is None or x != x else fmt.format(x)
        lines.append((r["model"], f(1000 * r["rms_mm"]), f(r["chi2_nu"], "{:.2f}"), f(r["bic"]),
                      f(r["delta_bic"]), f(r.get("corr_len_mm"), "{:.2g}"), f(r["elpd_loo"]),
                      f(r["elpd_loo_se"]), f(r["delta_elpd_loo"]), f(r["delta_elpd_loo_se"]),
                      {None: "-", True: "yes", False: "NO"}[r.get("converged")]))
    w = [max(len(h), *(len(l[i]) for l in lines)) for i, h in enumerate(head)]
    out = ["  ".join(h.ljust(x) for h, x in zip(head, w))]
    out += ["  ".join(c.ljust(x) for c, x in zip(l, w)) for l in lines]
    out.append("")
    for r in rows:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in r["params"].items() if v is not None)
        out.append(f"{r['model']}: {ps}")
    return "\n".join(out)
