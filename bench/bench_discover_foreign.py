"""Discovery without the inverse crime (issue 11 item 4): `diagnose` on prints from the
foreign printer (bench/foreign_printer.py: its own integrator, deposition and functional
forms of every hidden effect), library candidates only.

For each foreign effect and ``SEEDS`` seeds: the probe print with the effect, 10 um of
measurement noise, fit `pa`, diagnose. Scored:

- named: the top candidate is of the effect's family (foreign_printer.FAMILY);
- where the best candidate leaves chi2_nu > 1.5 (no library form fits), whether the
  verdict says so and the covariate it names is a right one (foreign_printer.
  RIGHT_COVARIATES); a verdict that names none (nothing lines up beyond chance) is not.
  On the rendered cases also where it leaves > 1.5 with the bead's wobble allowed too
  (fit/diagnose.py NO_FIT_CHI2: a right model reads 1.0-2.1 there without it).

Targets (issue 11): named >= 80 % where a library family exists; "says so with the right
covariate" >= 80 % of the cases where no library form fits.

Rendered (``RENDERED_SEEDS``): the same prints pictured with every phenomenon of
measure/phenomena.py on a 600 dpi flatbed and measured by our pipeline (foreign_printer.
render_foreign_case), diagnosed from where `calib fit --model auto` starts on those widths
(fit/measurement.py auto_start: since session 60 the probe prints our width reference and
the widths come calibrated, the offset's sd deciding whether ``scan_bias`` stays in the
base; ``CALIB_BENCH_FOREIGN_REFERENCE=0``: apparent widths, ``pa+scan_bias``), a nuisance the chain would add first
(``spread``) added before the effect is named. "No library form fits" is judged as diagnose
judges it: chi2_nu over what the measurement alone gives a right model (fit/measurement.py
chi2_nu_expected).

``CALIB_BENCH_FOREIGN_PROBE=separated`` prints a probe whose stops vary in length, place
and retraction (bench/foreign_printer.py PROBE_KW), so the stop covariates part: with it
(session 59, 6 white-noise seeds) every family is named first (30/30) but a right
covariate only on 11 of 24 no-fit cases, against 27/30 and 14/18 on the plain probe
(docs/DISCOVER.md, "A probe whose covariates part").
"""
from __future__ import annotations

import os
import sys

import numpy as np

from bench.common import Row
from bench.foreign_printer import (FAMILY, FOREIGN, RIGHT_COVARIATES, RIGHT_MODEL, make_foreign_case,
                                   render_foreign_case)

#: Six: the covariate rules of fit/diagnose.py were shaped on seeds 0-2 (10 of 10 right
#: there); seeds 3-5 are their held-out check (6 of 10), and the bench reports both.
SEEDS = int(os.environ.get("CALIB_BENCH_FOREIGN_SEEDS", "6"))
SHAPED_ON_SEEDS = 3
#: Seeds of the rendered cases (every foreign effect pictured on a 600 dpi flatbed with
#: every phenomenon and measured by our pipeline; 1.5-6 min each on 2 cores, ~25 min for 2).
RENDERED_SEEDS = int(os.environ.get("CALIB_BENCH_FOREIGN_RENDERED_SEEDS", "2"))
NO_FIT_CHI2 = 1.5


def _log(msg):
    print(f"  bench_discover_foreign: {msg}", file=sys.stderr, flush=True)


def one(hidden: str, seed: int, rendered: bool = False) -> dict:
    """Diagnose one case. ``rendered``: the print pictured with every phenomenon and
    measured (foreign_printer.render_foreign_case), diagnosed from where `calib fit --model
    auto` starts on its widths (fit/measurement.py auto_start on what the probe's width
    reference gave); else its widths with white noise, from ``pa``."""
    from fit import measurement
    from fit.compare import observe
    from fit.diagnose import diagnose
    from fit.effects import REGISTRY
    from fit.diagnose import SUPPORTED_DELTA_BIC
    from fit.model import build_model
    from fit.nuisance import NUISANCE

    if rendered:
        c = render_foreign_case(hidden, seed)
        t = c.table
        spec, priors = measurement.auto_start(hidden, c.calibration,
                                              measurement.light_varies(t.light_angle_deg[t.valid]))
    else:
        c = make_foreign_case(hidden, seed)
        spec, priors = "pa", None
    obs = observe(c.manifest, c.table)

    def run(spec, base=None):
        return diagnose(obs, spec, lambda s: build_model(s, c.manifest.printer), list(REGISTRY), [],
                        n_null=100, seed=seed, priors=priors, base=base)
    d = run(spec)
    ok = [x for x in d.candidates if np.isfinite(x.delta_bic)]
    top = ok[0]
    if rendered and top.effect in NUISANCE and top.delta_bic >= SUPPORTED_DELTA_BIC:
        # an effect every real bead has (spread: the bead smoothing its width beyond the
        # deposit window; this printer lays each step with a 0.12 mm Gaussian footprint)
        # joins `--model auto`'s chain first, which then looks again: so does the bench
        d = run(top.spec, base=top.fit)
        ok = [x for x in d.candidates if np.isfinite(x.delta_bic)]
        top = ok[0]
    cov = d.named_covariate        # "" when the verdict names none (nothing beyond chance)
    says_no_fit = ("explains only part" in d.verdict or "No effect in the library" in d.verdict
                   or "No missing effect" in d.verdict)
    fam = FAMILY.get(hidden, set())
    r = {"hidden": hidden, "seed": seed, "top": top.effect, "model": d.model, "named": top.effect in fam,
         "named_or_tied": bool({top.effect, *d.tied} & fam), "best": d.best,
         "chi2_before": d.base.chi2_nu, "chi2_after": top.chi2_nu_after, "cov": cov,
         "bead_before": d.base.chi2_nu_bead, "bead_after": top.chi2_nu_bead_after,
         "expected": d.chi2_nu_expected, "misfit_after": top.misfit_after,
         "misfit_bead_after": top.misfit_bead_after,
         "cov_right": cov in RIGHT_COVARIATES.get(hidden, set()), "says_no_fit": says_no_fit,
         # the covariates the verdict says this print cannot tell from the named one
         "aliases": [n for n, _ in d.aliases],
         "alias_right": bool(cov) and bool({cov, *(n for n, _ in d.aliases)}
                                           & RIGHT_COVARIATES.get(hidden, set())),
         # a misfit called (something is missing that the library does not have)
         "says_misfit": "explains only part" in d.verdict or "No effect in the library" in d.verdict,
         "size": c.effect_rms_mm / c.noise_mm, "figures": getattr(c, "figures", None),
         # a geometric best candidate is weighed against the picture's own pattern (view_xy)
         "picture_caution": "Caution: the picture" in d.verdict,
         # a bed effect named with the measurement's width curve taking it (fit/diagnose.py CURVE_TWINS)
         "curve_caution": "Caution: beside" in d.verdict}
    _log(f"{hidden} seed {seed}{' (rendered)' if rendered else ''}: {d.model} + top {top.effect} (dBIC {top.delta_bic:.0f}"
         + (f"; tied: {', '.join(d.tied)}" if d.tied else "") + "), chi2 "
         f"{r['chi2_before']:.1f} -> {r['chi2_after']:.2f} (expected {r['expected']:.2f}; with the bead's wobble "
         f"{r['bead_before']:.2f} -> {r['bead_after']:.2f}), top covariate {cov}"
         + (f" (this print cannot tell it from {', '.join(r['aliases'])})" if r["aliases"] else "")
         + (", says no library form fits" if says_no_fit else "")
         + (", and that the picture's own pattern explains it as well or better" if r["picture_caution"] else "")
         + (", and that the measurement's width curve takes it" if r["curve_caution"] else ""))
    return r


def run() -> list[Row]:
    res = [one(h, s) for h in FOREIGN for s in range(SEEDS)]
    rows = _white_rows(res)
    if RENDERED_SEEDS > 0:
        rows += _rendered_rows([one(h, s, rendered=True) for h in [*FOREIGN, RIGHT_MODEL]
                                for s in range(RENDERED_SEEDS)])
    return rows


def _rendered_rows(res: list[dict]) -> list[Row]:
    """The rendered cases: measurement figures, families, and the no-fit verdicts, judged
    as diagnose judges them on measured widths: chi2_nu over what a right model reads from
    the measurement alone (fit/measurement.py chi2_nu_expected, ~5 on these renders)."""
    tag = "discover (foreign, rendered)"
    right = [r for r in res if r["hidden"] == RIGHT_MODEL]
    res = [r for r in res if r["hidden"] != RIGHT_MODEL]
    fig = [r["figures"] for r in res]
    n_cal = sum(not f["apparent"] for f in fig)
    rows = [Row(tag, f"measured widths ({len(res)} prints, 600 dpi flatbed, every phenomenon, pose from "
                     f"8 points of the true camera): RMS / bias (median), valid "
                     f"{100 * np.median([f['valid'] for f in fig]):.0f} %, calibrated by the width reference "
                     f"{n_cal} of {len(fig)}",
                1000 * np.median([f["rms_mm"] for f in fig]), "um",
                f"bias {1000 * np.median([f['bias_mm'] for f in fig]):+.1f} um", None)]
    for h in FOREIGN:
        rr = [r for r in res if r["hidden"] == h]
        rows.append(Row(tag, f"{h}: family named first ({len(rr)} seeds; top: "
                        f"{', '.join(sorted({r['top'] for r in rr}))}; chi2_nu / expected "
                        f"{np.median([r['chi2_before'] / r['expected'] for r in rr]):.2f} -> "
                        f"{np.median([r['misfit_after'] for r in rr]):.2f})",
                        100 * np.mean([r["named"] for r in rr]), "%", "-", None))
    fam = [r for r in res if r["hidden"] != "gear_slip"]
    rows.append(Row(tag, "library families named first (all but gear slip)",
                    100 * np.mean([r["named"] for r in fam]), "%", ">= 80",
                    bool(np.mean([r["named"] for r in fam]) >= 0.8)))
    nofit = [r for r in res if r["misfit_after"] > NO_FIT_CHI2]
    if nofit:
        share = np.mean([r["says_no_fit"] and r["cov_right"] for r in nofit])
        rows.append(Row(tag, f"no library form fits (chi2_nu after / expected > {NO_FIT_CHI2}, {len(nofit)} cases): "
                        "says so and names a right covariate", 100 * share, "%", ">= 80", bool(share >= 0.8)))
    # a right model reads chi2_nu 1.0-2.1 times chi2_nu_expected on these renders (the
    # bead's slow wander: fit/diagnose.py NO_FIT_CHI2), so the row above counts right
    # forms; with the bead's wobble allowed as well (what diagnose and the trust verdict judge)
    both = [r for r in nofit if not r["misfit_bead_after"] <= NO_FIT_CHI2]
    if both:
        share = np.mean([r["says_no_fit"] and r["cov_right"] for r in both])
        rows.append(Row(tag, f"... and > {NO_FIT_CHI2} with the bead's wobble allowed too ({len(both)} cases): "
                        "says so and names a right covariate", 100 * share, "%", ">= 80", bool(share >= 0.8)))
        rows.append(_alias_row(tag, both))
    if right:
        # the false-alarm side: a print with nothing hidden, measured the same way
        rows.append(Row(tag, f"a right model (the foreign plain spring, {len(right)} seeds; named: "
                        f"{', '.join(r['best'] or '-' for r in right)}): no effect named without a caution, and "
                        "no 'no library form fits'",
                        100 * np.mean([(r["best"] is None or r["picture_caution"] or r["curve_caution"])
                                       and not r["says_misfit"] for r in right]), "%", "-", None))
    return rows


def _white_rows(res: list[dict]) -> list[Row]:
    rows = []
    for h in FOREIGN:
        rr = [r for r in res if r["hidden"] == h]
        rows.append(Row("discover (foreign)", f"{h}: family named first ({len(rr)} seeds; top: "
                        f"{', '.join(sorted({r['top'] for r in rr}))}; chi2_nu "
                        f"{np.median([r['chi2_before'] for r in rr]):.1f} -> "
                        f"{np.median([r['chi2_after'] for r in rr]):.2f})",
                        100 * np.mean([r["named"] for r in rr]), "%", "-", None))
    fam = [r for r in res if r["hidden"] != "gear_slip"]
    rows.append(Row("discover (foreign)", "library families named first (all but gear slip)",
                    100 * np.mean([r["named"] for r in fam]), "%", ">= 80",
                    bool(np.mean([r["named"] for r in fam]) >= 0.8)))
    # the verdict names every candidate within 2 BIC of the best as a tie (fit/diagnose.py)
    rows.append(Row("discover (foreign)", "library families named first or as a tie with the first",
                    100 * np.mean([r["named_or_tied"] for r in fam]), "%", "-", None))
    nofit = [r for r in res if r["chi2_after"] > NO_FIT_CHI2]
    if nofit:
        share = np.mean([r["says_no_fit"] and r["cov_right"] for r in nofit])
        unnamed = sum(r["cov"] == "" for r in nofit)
        rows.append(Row("discover (foreign)", f"no library form fits (chi2_nu after > {NO_FIT_CHI2}, "
                        f"{len(nofit)} cases, {unnamed} naming none: nothing beyond chance): says so and "
                        "names a right covariate",
                        100 * share, "%", ">= 80", bool(share >= 0.8)))
        rows.append(_alias_row("discover (foreign)", nofit))
        # the rules that name the covariate (fit/diagnose.py _explains_part) were shaped on
        # seeds 0-2: the later seeds are their held-out check
        held = [r for r in nofit if r["seed"] >= SHAPED_ON_SEEDS]
        if held:
            rows.append(Row("discover (foreign)", f"... on the held-out seeds {SHAPED_ON_SEEDS}-{SEEDS - 1} only "
                            f"({len(held)} cases)",
                            100 * np.mean([r["says_no_fit"] and r["cov_right"] for r in held]), "%", "-", None))
    return rows


def _alias_row(tag: str, cases: list[dict]) -> Row:
    """The named covariate, or one the verdict says this print cannot tell from it
    (fit/covariates.py aliases), is right: what a user reading the verdict is pointed at."""
    return Row(tag, f"... says so, and the named covariate or one the verdict says the print cannot tell "
                    f"from it is right ({len(cases)} cases)",
               100 * np.mean([r["says_no_fit"] and r["alias_right"] for r in cases]), "%", "-", None)
