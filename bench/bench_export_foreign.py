"""The number a user pastes, scored without the inverse crime: `calib fit --model auto` and
`calib export --to marlin` on prints of the foreign printer (bench/foreign_printer.py: its
own integrator, deposition and forms of every hidden effect), the exported K printed by
that printer.

bench_export scores the width-optimal K on the library's own physics (the truth's optimum
found by the same simulation that finds the fit's); here the truth is the foreign
printer's: the standard move mix (fit/firmware_match.py ``standard_reference``) printed by
it with Marlin's linear advance (``foreign_printer.with_linear_advance``) at the exported K
and at its own best K (``optimal_advance``). For each foreign effect and the plain spring
(``RIGHT_MODEL``), ``SEEDS`` seeds: the probe print with 10 um of white noise
(make_foreign_case), fitted as `calib fit --model auto` fits it (calib.commands.fit
``run_fit``: the chain, the sampler, the trust verdict), the K `calib export` would write
(calib.commands.export ``width_match``: Marlin, no smoothing).

Scored: the width error the exported K leaves on the foreign printer beyond its own best
K, as a share of what linear advance gains there (no advance against the best); a *pasted
wrong value* is one the verdict trusts (export writes it without ``--force``) that loses
more than ``LOSS_MAX`` of that gain. Whether the foreign optimum lies in the exported 95 %
interval is shown too: that interval is the posterior's and holds no doubt of the model's
form, so it is narrower than the foreign optimum's distance on a right model already (the
footprint, ``optimal_advance``).
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time

import numpy as np

from bench.common import Row
from bench.foreign_printer import FOREIGN, RIGHT_MODEL, _draw, make_foreign_case, optimal_advance, width_error_mm

SEEDS = int(os.environ.get("CALIB_BENCH_EXPORT_FOREIGN_SEEDS", "1"))
#: a trusted export may lose at most this share of what linear advance gains on the printer
LOSS_MAX = 0.05


def _log(msg):
    print(f"  bench_export_foreign: {msg}", file=sys.stderr, flush=True)


def one(hidden: str, seed: int) -> dict:
    """Fit and export one foreign case as a user would; score the K on the foreign printer."""
    from calib.commands.export import width_match
    from calib.commands.fit import run_fit
    from fit import firmware_match as fm
    from fit.result import load_fit_json
    from patterns.profile import load_profile, profile_from_dict

    c = make_foreign_case(hidden, seed)
    _, _, tau, p = _draw(hidden, seed)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        w, m, f = (os.path.join(d, n) for n in ("probe.csv", "probe.manifest.json", "fit.json"))
        c.table.save(w)
        c.manifest.save(m)
        with contextlib.redirect_stdout(sys.stderr):        # the chain `calib fit` prints: a log line
            res, _ = run_fit([(w, m)], "auto", seed=seed, progress=False)
        res.save(f)
        doc = load_fit_json(f)
    t_fit = time.perf_counter() - t0
    # the probe's printer holds only what its physics needs; the move mix is planned on a
    # whole Bowden profile with the probe's filament, nozzle and Bowden
    doc["profile"] = {**load_profile("adventurer3").to_dict(), **(doc.get("profile") or {})}
    match = width_match(doc, "marlin")
    k = match.k_s if match is not None else doc["derived"]["pressure_advance_s"]
    k_med = float(k["median"])
    lo, hi = (float(v) for v in k.get("ci95", (k_med, k_med)))
    ref = fm.standard_reference(profile_from_dict(doc["profile"], source="bench"))
    k_star, e_star = optimal_advance(ref, tau, hidden, p)
    e_exp = width_error_mm(ref, tau, hidden, p, k_med)
    e_none = width_error_mm(ref, tau, hidden, p, 0.0)
    gain = e_none - e_star
    trusted = bool(res.trust.get("trustworthy")) and not (match is not None and match.n_at_limit)
    r = {"hidden": hidden, "seed": seed, "model": res.model, "tau_s": tau, "k_s": k_med, "ci95": (lo, hi),
         "k_star_s": k_star, "err_um": {"none": 1e3 * e_none, "exported": 1e3 * e_exp, "best": 1e3 * e_star},
         "loss": (e_exp - e_star) / gain if gain > 0 else float("nan"), "in_ci": lo <= k_star <= hi,
         "trusted": trusted, "problems": res.trust.get("problems") or [], "fit_s": t_fit}
    _log(f"{hidden} seed {seed}: {res.model}, K {k_med:.4f} [{lo:.4f}, {hi:.4f}] s, the printer's best "
         f"{k_star:.4f} s (spring tau {tau:.4f}); widths {1e3 * e_exp:.1f} um RMS against {1e3 * e_star:.1f} "
         f"at its best and {1e3 * e_none:.1f} without advance (loss {100 * r['loss']:.1f} % of the gain); "
         f"{'trusted' if trusted else 'refused'}; fit {t_fit:.0f} s")
    return r


def run() -> list[Row]:
    res = [one(h, s) for h in [*FOREIGN, RIGHT_MODEL] for s in range(SEEDS)]
    tag = "export (foreign)"
    rows = []
    for r in res:
        rows.append(Row(tag, f"{r['hidden']} seed {r['seed']}: {r['model']}, exported K {r['k_s']:.3f} s "
                        f"[{r['ci95'][0]:.3f}, {r['ci95'][1]:.3f}], the foreign printer's best {r['k_star_s']:.3f}; "
                        f"{'trusted' if r['trusted'] else 'refused'}: width error lost, share of the advance's gain",
                        100 * r["loss"], "%", f"<= {100 * LOSS_MAX:.0f} if trusted",
                        None if not r["trusted"] else bool(r["loss"] <= LOSS_MAX)))
    bad = [r for r in res if r["trusted"] and not r["loss"] <= LOSS_MAX]
    rows.append(Row(tag, f"pasted wrong values: trusted exports losing > {100 * LOSS_MAX:.0f} % of the gain "
                    f"({len(res)} prints, {sum(r['trusted'] for r in res)} trusted)", len(bad), "prints", "0",
                    not bad))
    rows.append(Row(tag, "the foreign optimum inside the exported 95 % interval (the posterior's: no doubt "
                    "of the model's form in it)", 100 * np.mean([r["in_ci"] for r in res]), "%", "-", None))
    return rows


if __name__ == "__main__":
    from bench.common import print_table

    print_table(run())
