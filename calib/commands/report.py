"""`calib report`: one self-contained HTML file for a scan (plots embedded)."""
from __future__ import annotations

import sys
from pathlib import Path

from calib.errors import UserError


def add_parser(subparsers):
    p = subparsers.add_parser(
        "report", help="write one self-contained HTML report for a scan",
        description="Write ONE HTML file (plots embedded, no network needed): the scan with its "
                    "QA overlay, data vs models track by track, residuals and covariate panels, "
                    "the comparison table, the diagnosis verdict and corner plots. Uses the "
                    "compare/diagnose/fit JSON files you give; with --widths and --manifest it "
                    "runs the comparison (--models) and the diagnosis (--model) itself.")
    p.add_argument("--widths", help="widths CSV")
    p.add_argument("--manifest", help="the pattern's NAME.manifest.json")
    p.add_argument("--scan", help="the scan or photo (PNG/JPEG)")
    p.add_argument("--overlay", help="the QA overlay image from `calib measure`")
    p.add_argument("--compare", metavar="compare.json", help="output of `calib compare -o`")
    p.add_argument("--diagnose", metavar="diag.json", help="output of `calib diagnose -o`")
    p.add_argument("--fit", metavar="fit.json", help="output of `calib fit`")
    p.add_argument("--models", nargs="+", metavar="SPEC",
                   help="compare these models now (needs --widths and --manifest)")
    p.add_argument("--model", metavar="SPEC", help="diagnose this model now (needs --widths, --manifest)")
    p.add_argument("--effects", metavar="FILE.py", help="your own Effect classes")
    p.add_argument("--priors", help="with --models/--model: TOML file overriding parameter priors, applied to "
                                    "each model that has the parameter (see fit/priors.py)")
    p.add_argument("--candidates", metavar="A,B,...",
                   help="with --model: try only these library effects (default: every one not in the model)")
    p.add_argument("--full", action="store_true", help="full fits (emcee, PSIS-LOO, corner plots)")
    p.add_argument("--title", default="calib report", help="report title")
    p.add_argument("-o", "--output", required=True, metavar="report.html", help="the HTML file")
    return p


def _load_json(path, what):
    """A `calib <what>` output, checked by its schema (one line for a file of another kind,
    not a KeyError deep in the report)."""
    from calib.fileio import read_json_doc

    if not path:
        return None
    hint = f"run `calib {what}` first"
    doc = read_json_doc(path, "calib.", what, hint)
    kinds = ("calib.fit/", "calib.fit-map/") if what == "fit" else (f"calib.{what}/",)
    if not str(doc["schema"]).startswith(kinds):
        raise UserError(f"{path} is a {doc['schema']} file, not a calib {what} file; {hint}")
    return doc


def run(args) -> int:
    from calib.report import build_report, write_report

    from calib.report import image_file

    for p, what in ((args.scan, "scan"), (args.overlay, "overlay")):
        if p and not Path(p).is_file():
            raise UserError(f"{what} image {p} does not exist")
        if p:
            image_file(p, max_px=64)     # a corrupt image refused before minutes of fitting
    compare_doc = _load_json(args.compare, "compare")
    diagnose_doc = _load_json(args.diagnose, "diagnose")
    fit_doc = _load_json(args.fit, "fit")
    obs = comparison = diagnosis = None
    if (args.models or args.model) and not (args.widths and args.manifest):
        raise UserError("--models/--model need --widths and --manifest")
    if args.widths and args.manifest:
        from calib.commands.compare import load_inputs, scan_priors
        from fit.compare import compare_models, observe
        from fit.model import build_model
        manifest, table, extra = load_inputs(args.widths, args.manifest, args.effects)
        obs = observe(manifest, table)
        build = lambda s: build_model(s, manifest.printer, extra_effects=extra)  # noqa: E731
        specs = list(args.models or [])
        if not specs and compare_doc:
            specs = [r["model"] for r in compare_doc["models"]]
        if args.model and args.model not in specs:
            specs.insert(0, args.model)
        # the priors `calib fit` fits with (the width reference's for scan_bias...), so the
        # report's table shows the fits `calib fit` makes
        priors = scan_priors(args.widths, specs, args.priors, extra, "calib report") if specs else None
        if specs:
            comparison = compare_models(obs, {s: build(s) for s in specs}, full=args.full,
                                        progress=True, priors=priors)
            if compare_doc is None:
                compare_doc = comparison.to_json()
        if args.model:
            from calib.commands.diagnose import library_candidates
            from fit.diagnose import diagnose
            eff = f" --effects {args.effects}" if args.effects else ""
            eff += f" --priors {args.priors}" if args.priors else ""
            diagnosis = diagnose(obs, args.model, build, library_candidates(args.candidates), [c.name for c in extra],
                                 command_prefix=f"calib fit {args.widths} --manifest {args.manifest}",
                                 effects_arg=eff, priors=priors)
            diagnose_doc = diagnosis.to_json()
    if not any(x is not None for x in (compare_doc, diagnose_doc, fit_doc, obs)) and not args.scan:
        raise UserError("nothing to report: give --widths/--manifest, --compare, --diagnose, --fit or --scan")
    text = build_report(args.title, obs=obs, comparison=comparison, diagnosis=diagnosis,
                        compare_doc=compare_doc, diagnose_doc=diagnose_doc, fit_doc=fit_doc,
                        scan=args.scan, overlay=args.overlay)
    write_report(args.output, text)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0
