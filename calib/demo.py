"""The whole loop on the built-in virtual printer, as a user would run it.

pattern -> preview -> print on the virtual printer (whose extruder hides effects the
base model lacks) -> scan -> measure -> fit the base model -> diagnose -> fit the
extended model -> watch the error fall -> export -> HTML report.

Every step is the `calib` command a user would type (printed before it runs), so the
demo doubles as a tutorial and as an end-to-end check of the CLI.
"""
from __future__ import annotations

import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from calib.errors import UserError


def _data_dir() -> Path:
    from patterns.profile import data_dir

    return Path(data_dir())


class _Runner:
    def __init__(self, out: Path, stream=sys.stdout):
        self.out = out
        self.stream = stream
        self.t0 = time.perf_counter()

    def say(self, text: str = "") -> None:
        print(text, file=self.stream, flush=True)

    def step(self, title: str, argv: list[str], ok_codes=(0,)) -> int:
        from calib.cli import main

        argv = [str(a) for a in argv]
        self.say(f"\n== {title}  [{time.perf_counter() - self.t0:5.0f} s]")
        self.say("$ calib " + " ".join(shlex.quote(a) for a in argv))
        code = main(argv)
        if code not in ok_codes:
            raise UserError(f"demo step '{title}' failed with exit code {code}")
        return code


def _truth_error(widths_csv: Path, truth_json: Path) -> dict:
    """Measured-vs-true width error (mm) over valid samples, matched by (track, s_mm)."""
    from measure.table import WidthTable
    from measure.truth_io import load_scan_truth

    meas = WidthTable.load(widths_csv)
    truth = load_scan_truth(truth_json).widths
    key = {(int(t), round(float(s), 3)): w for t, s, w in zip(truth.track, truth.s_mm, truth.width_mm)}
    err = [w - key[(int(t), round(float(s), 3))]
           for t, s, w, v in zip(meas.track, meas.s_mm, meas.width_mm, meas.valid)
           if v and (int(t), round(float(s), 3)) in key]
    err = np.asarray(err)
    return {"n": int(err.size), "valid_fraction": float(np.mean(meas.valid)),
            "rms_mm": float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan"),
            "bias_mm": float(np.mean(err)) if err.size else float("nan")}


def _fit_summary(fit_json: Path) -> dict:
    """The numbers the demo prints, from a full fit.json or a ``--map-only`` one."""
    doc = json.loads(fit_json.read_text())
    if "information" not in doc:  # MAP only: Laplace sd around the MAP
        names = [n for n in doc.get("param_names", [])] or list(doc["theta"])
        theta, sd = doc["theta"], doc.get("sd", {})
        params = {n: {"median": theta[n], "ci68": [theta[n] - sd.get(n, np.nan), theta[n] + sd.get(n, np.nan)]}
                  for n in names}
        return {"model": doc["model"], "params": params, "converged": None, "rms_mm": doc["rms_mm"],
                "chi2_nu": doc["chi2_nu"], "bic": doc["bic"], "elpd_loo": None, "map_only": True}
    info = doc.get("information", {})
    return {"model": doc["model"], "params": doc["params"], "converged": doc.get("converged"),
            "rms_mm": info.get("rms_mm"), "chi2_nu": info.get("chi2_nu"), "bic": info.get("bic"),
            "elpd_loo": (info.get("loo") or {}).get("elpd_loo"), "map_only": False}


def _print_params(r: _Runner, fit: dict, truth_values: dict) -> None:
    r.say(f"   {'parameter':26s} {'median':>10s}  {'68% interval':>22s}  {'truth':>8s}")
    for name, p in fit["params"].items():
        if name.startswith("noise."):
            continue
        lo, hi = p.get("ci68", [np.nan, np.nan])
        t = truth_values.get(name)
        ts = f"{t:8.4g}" if t is not None else "  hidden"
        r.say(f"   {name:26s} {p['median']:10.4g}  [{lo:9.4g}, {hi:9.4g}]  {ts}")


def _start_model(widths, manifest) -> str:
    from fit.compare import observe
    from fit.measurement import start_for
    from measure.table import WidthTable
    from patterns.manifest import Manifest

    return start_for(observe(Manifest.load(manifest), WidthTable.load(widths)), widths)[0]


def run_demo(out_dir, printer: str = "adventurer3", truth: str | None = None, camera: str = "flatbed",
             base_model: str | None = None, seed: int = 1, rounds: int = 2, stream=sys.stdout) -> dict:
    """Run the loop into ``out_dir``; return a summary dict (also written as demo.json).
    ``base_model`` None: where `calib fit --model auto` starts on the measured widths
    (fit.measurement.start_for): ``pa`` on a calibrated flatbed scan, ``pa+scan_bias``
    (and the picture's nuisances) on a phone's apparent widths, whose unknown offset the
    diagnosis would otherwise name as flow_gain (a phone demo from ``pa``: flow_gain 0.90,
    then back-pressure, never the thermal ooze)."""
    from calib.fileio import atomic_write_text
    from fit.truth import load_truth

    from patterns.profile import load_profile

    prof = load_profile(printer)  # a bad printer or truth is one clear line before any work starts
    truth = Path(truth) if truth else _data_dir() / "truths" / "bowden.toml"
    spec_true, values_true, _ = load_truth(truth)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    r = _Runner(out, stream)
    r.say(f"calib demo: the virtual printer '{printer}' runs the hidden truth {truth.name} "
          f"({spec_true}); we fit " + (f"'{base_model}'" if base_model else "the base model")
          + " and let the diagnosis find what is missing.")

    gcode, man = out / "spiral.gcode", out / "spiral.manifest.json"
    scan, widths, qa = out / "scan.png", out / "widths.csv", out / "qa.png"
    r.step("1. the test pattern (spiral, stepped extrusion, seed 004)",
           ["pattern", "spiral-step", "--printer", printer, "-o", gcode])
    r.step("2. preview", ["preview", gcode, "-o", out / "preview.png"])
    r.step("3. print it on the virtual printer and scan it", [
        "simulate", gcode, "--truth", truth, "--camera", camera, "--dpi", "600", "--seed", seed,
        "--plot", "-o", scan])
    r.step("4. measure the bead width along every track", [
        "measure", scan, "--manifest", man, "-o", widths, "--overlay", qa,
        "--summary", out / "measure.json"])
    err = _truth_error(widths, scan.with_name(scan.stem + ".truth.json"))
    r.say(f"   measured vs true width: RMS {err['rms_mm'] * 1000:.1f} um, bias "
          f"{err['bias_mm'] * 1000:+.1f} um over {err['n']} samples "
          f"({err['valid_fraction']:.0%} valid)")

    if base_model is None:
        base_model = _start_model(widths, man)
        r.say(f"   base model '{base_model}': where `calib fit --model auto` starts on these widths"
              + (" (apparent widths: scan_bias takes their unknown offset)" if "scan_bias" in base_model else ""))
    history = []
    model = base_model
    step_no = 5

    def fit(model: str, full: bool) -> dict:
        nonlocal step_no
        tag = model.replace("+", "_")
        fit_json = out / f"fit_{tag}.json"
        how = "MAP, then emcee until the chains converge" if full else "MAP with Laplace errors"
        argv = ["fit", widths, "--manifest", man, "--model", model, "--seed", seed, "-o", fit_json]
        argv += ["--plots", out / f"plots_{tag}"] if full else ["--map-only"]
        r.step(f"{step_no}. fit '{model}' ({how})", argv, ok_codes=(0, 3))
        step_no += 1
        fs = _fit_summary(fit_json) | {"file": fit_json}
        _print_params(r, fs, values_true)
        r.say(f"   residual RMS {fs['rms_mm'] * 1000:.1f} um, reduced chi-square {fs['chi2_nu']:.2f}"
              + ("   (chains NOT converged: see the fit json)" if fs["converged"] is False else ""))
        history.append(fs)
        return fs

    fit(model, full=True)
    for _ in range(rounds):
        tag = model.replace("+", "_")
        diag_json = out / f"diagnose_{tag}.json"
        r.step(f"{step_no}. diagnose '{model}': which effect is missing?", [
            "diagnose", widths, "--manifest", man, "--model", model, "--seed", seed,
            "-o", diag_json, "--plots", out / f"covariates_{tag}"])
        step_no += 1
        diag = json.loads(diag_json.read_text())
        cands = [c for c in diag.get("candidates", []) if np.isfinite(c.get("delta_bic", np.nan))]
        if not cands or cands[0]["delta_bic"] < 10:
            r.say("   no candidate effect improves BIC by 10 or more: the model explains the data.")
            break
        model = f"{model}+{cands[0]['effect']}"
        fit(model, full=False)
    if model != base_model:
        fit(model, full=True)  # the final model gets the full posterior

    r.say("\n== the error falling")
    r.say(f"   {'model':36s} {'RMS (um)':>9s} {'chi2_nu':>8s} {'BIC':>12s}")
    full_models = {h["model"] for h in history if not h["map_only"]}
    for h in history:
        if h["map_only"] and h["model"] in full_models:
            continue  # the same model's full fit is listed instead
        r.say(f"   {h['model']:36s} {h['rms_mm'] * 1000:9.1f} {h['chi2_nu']:8.2f} {h['bic']:12.1f}")
    r.say(f"   (truth: {spec_true})")

    last = history[-1]["file"]
    # an untrustworthy final fit is refused by export (exit 2, one line saying why): shown,
    # not a failed demo (a phone's uncalibrated widths: tau rides the width offset)
    trusted = bool((json.loads(Path(last).read_text()).get("trust") or {}).get("trustworthy"))
    ok = (0,) if trusted else (0, 2)
    r.step("export the pressure advance for Klipper", ["export", last, "--to", "klipper"], ok_codes=ok)
    if prof.bowden_length_mm > 0:   # VE needs the Bowden length (seed 000)
        r.step("the same fit as KISSlicer VE (applied by the slicer, for firmware without PA)",
               ["export", last, "--to", "kisslicer"], ok_codes=ok)
    if not trusted:
        r.say("   the export refuses this fit: its verdict (above) says why and what to do; "
              "`--force` would write it anyway")
    r.step("the report", ["report", "--widths", widths, "--manifest", man, "--scan", scan,
                          "--overlay", qa, "--fit", last, "--models", base_model, history[-1]["model"],
                          "-o", out / "report.html"])
    summary = {"truth": {"spec": spec_true, "values": values_true}, "measure_error": err,
               "fits": [{k: v for k, v in h.items() if k not in ("params", "file")} |
                        {"medians": {n: p["median"] for n, p in h["params"].items()}} for h in history],
               "seconds": time.perf_counter() - r.t0}
    atomic_write_text(out / "demo.json", json.dumps(summary, indent=1))
    r.say(f"\nall outputs in {out}/ (open report.html); {summary['seconds']:.0f} s")
    return summary
