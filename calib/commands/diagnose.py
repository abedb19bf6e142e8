"""`calib diagnose`: which physical effect is the model missing?"""
from __future__ import annotations

import json
import sys

from calib.argtypes import integer, seed


def add_parser(subparsers):
    p = subparsers.add_parser(
        "diagnose", help="find which physical effect the model is missing",
        description="Fit MODEL, score its residuals against physical covariates of the print "
                    "(time since a flow change or a stop, flow, speed, acceleration, width, "
                    "heading, x, y, E), add every library effect not in the model (and your "
                    "own from --effects) in turn, rank them by the drop in BIC, and say in "
                    "plain words which effect is most likely missing and how to fit it.")
    p.add_argument("widths", help="widths CSV from `calib measure`")
    p.add_argument("--manifest", required=True, help="the pattern's NAME.manifest.json")
    p.add_argument("--model", required=True, metavar="SPEC", help="the model to diagnose, e.g. pa")
    p.add_argument("--effects", metavar="FILE.py",
                   help="a Python file with your own Effect classes; they become candidates too")
    p.add_argument("--priors", help="TOML file overriding parameter priors, applied to the model and to "
                                    "each candidate that has the parameter (see fit/priors.py)")
    p.add_argument("--candidates", metavar="A,B,...",
                   help="try only these library effects (default: every one not in the model); "
                        "effects from --effects are always tried")
    p.add_argument("--confirm", type=integer(0), default=0, metavar="N",
                   help="confirm the N best candidates with a full fit (emcee run to "
                        "convergence + PSIS-LOO)")
    p.add_argument("--seed", type=seed, default=0, help="random seed")
    p.add_argument("--json", action="store_true", help="print the diagnosis as JSON on stdout")
    p.add_argument("-o", "--output", metavar="diag.json", help="also write the JSON here")
    p.add_argument("--plots", metavar="DIR", help="write one plot per top covariate here")
    return p


def run(args) -> int:
    from calib.commands.compare import load_inputs, scan_priors
    from calib.fileio import atomic_write_text
    from calib.errors import UserError
    from fit.compare import observe
    from fit.diagnose import diagnose
    from fit.model import build_model

    if args.confirm < 0:
        raise UserError("--confirm must be 0 or more")
    manifest, table, extra = load_inputs(args.widths, args.manifest, args.effects)
    build_model(args.model, manifest.printer, extra_effects=extra)  # bad spec -> one line
    library = library_candidates(args.candidates)
    obs = observe(manifest, table)
    # the priors `calib fit` would fit with: the table then ranks the models it would fit
    priors = scan_priors(args.widths, [args.model], args.priors, extra, "calib diagnose")
    eff = f" --effects {args.effects}" if args.effects else ""
    eff += f" --priors {args.priors}" if args.priors else ""
    d = diagnose(obs, args.model, lambda s: build_model(s, manifest.printer, extra_effects=extra),
                 library, [c.name for c in extra], confirm_top=args.confirm,
                 seed=args.seed, progress=True, priors=priors,
                 command_prefix=f"calib fit {args.widths} --manifest {args.manifest}", effects_arg=eff)
    doc = d.to_json()
    doc.update({"widths": str(args.widths), "manifest": str(args.manifest),
                "effects": str(args.effects) if args.effects else None})
    text = json.dumps(doc, indent=1)
    if args.output:
        atomic_write_text(args.output, text)
    if args.json:
        print(text)
    else:
        print(format_diagnosis(doc))
    if args.plots:
        from calib.report import plot_covariates
        for path in plot_covariates(d, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0


def library_candidates(arg: str | None) -> list[str]:
    """The library effects ``--candidates A,B,...`` names (every one when None); an unknown
    name is a UserError listing the known ones."""
    from calib.errors import UserError
    from fit.effects import REGISTRY

    if arg is None:
        return list(REGISTRY)
    names = [n.strip() for n in arg.split(",") if n.strip()]
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise UserError(f"--candidates: unknown library effect(s) {', '.join(map(repr, unknown))}; "
                        f"known: {', '.join(REGISTRY)}")
    if not names:
        raise UserError("--candidates names no effect")
    return names


def format_diagnosis(doc: dict) -> str:
    out = [f"model {doc['model']}: RMS {1000 * doc['rms_mm']:.1f} um, reduced chi-square "
           f"{doc['chi2_nu']:.2f}", "", "residual structure (share of residual variance explained "
           "beyond chance" + ("; within each track, since a picture's error is partly shared by whole "
                              "tracks; print time and E, which within a track only count its progress, "
                              "are not scored" if doc.get("covariates_within_tracks") else "") + "):"]
    for c in doc["covariates"][:6]:
        out.append(f"  {c['name']:<28} {c['score']:.3f}   (R^2 {c['r2']:.3f}, p {c['p_value']:.3g})")
    out += ["", "candidate effects (drop in BIC with the noise model of `calib fit`; RMS after):"]
    for c in doc["candidates"]:
        if c.get("error"):
            out.append(f"  {c['effect']:<16} failed: {c['error']}")
            continue
        out.append(f"  {c['effect']:<16} {c['delta_bic']:>10.1f}   "
                   f"{1000 * c['rms_mm_after']:.1f} um  chi2_nu {c['chi2_nu_after']:.2f}"
                   + (f" ({c['chi2_nu_bead_after']:.2f} with the bead's wobble)"
                      if c.get("chi2_nu_bead_after") is not None else "")
                   + ("  (your effect)" if c.get("user") else ""))
    out += ["", doc["verdict"]]
    return "\n".join(out)
