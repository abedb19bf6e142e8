"""The fit reads what `calib measure` said of its widths (fit/measurement.py): a calibrated
scan's edge-offset sd becomes the scan_bias prior; apparent widths widen it, and without
scan_bias in the model they are a caution in the verdict and a line on stderr."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from calib.commands.fit import run_fit
from fit import measurement
from fit.trust import assess

EX = Path("data/examples/gear_slip")


def scan_with_summary(tmp_path, calibration):
    shutil.copy(EX / "widths.csv", tmp_path / "widths.csv")
    for f in ("probe.manifest.json", "probe.timeline.npz"):
        shutil.copy(EX / f, tmp_path / f)
    if calibration is not None:
        (tmp_path / "widths.summary.json").write_text(json.dumps({"apparent_width": calibration}))
    return [(str(tmp_path / "widths.csv"), str(tmp_path / "probe.manifest.json"))]


CAL = {"applied": True, "offset_mm": -0.031, "offset_sd_mm": 0.0024, "note": "apparent-width calibration: ..."}
UNCAL = {"applied": False, "offset_mm": None, "offset_sd_mm": None,
         "note": "apparent-width calibration not applied: the width reference had not settled; widths are apparent"}


def _prior(problem, name):
    return problem.priors[problem.param_names.index(name)]


@pytest.mark.parametrize("cal,sd", [(CAL, 0.0024), (UNCAL, measurement.UNCALIBRATED_SD_MM), (None, 0.005)])
def test_scan_bias_prior_follows_the_calibration(tmp_path, cal, sd, capsys):
    _, problem = run_fit(scan_with_summary(tmp_path, cal), "pa+scan_bias", map_only=True, progress=False)
    p = _prior(problem, "scan_bias.b0_mm")
    assert p.kind == "normal" and p.sd == pytest.approx(sd)       # None: the effect's own normal(0, 5 um)
    err = capsys.readouterr().err
    assert ("apparent widths" in err) == (cal is UNCAL) and "add scan_bias" not in err


def test_an_offset_measured_too_loosely_to_apply_is_still_the_prior_where_it_says_more():
    """A reference whose sections disagree (sd above measure/calibrate.py MAX_OFFSET_SD_MM)
    is not applied to the widths; its offset +- sd becomes scan_bias's prior when that sd
    is below the uncalibrated one, not when the reference had not settled or is looser."""
    from measure.calibrate import calibrate
    rng = np.random.default_rng(2)
    nominal = np.repeat([1.0, 0.4, 1.0, 0.4], 40)
    section = np.repeat(np.arange(4), 40)
    width = nominal - 0.039 + rng.normal(0, 0.002, 160) + np.array([0.012, -0.010, -0.012, 0.010])[section]
    cal = calibrate(width, np.ones(160, bool), nominal, section).to_dict()
    assert not cal["applied"] and cal["prior_ok"] and 0.010 < cal["offset_sd_mm"] < measurement.UNCALIBRATED_SD_MM
    prior = measurement.b0_prior(cal)
    assert prior["mu"] == pytest.approx(cal["offset_mm"]) and prior["sd"] == pytest.approx(cal["offset_sd_mm"])
    assert abs(prior["mu"] + 0.039) < 2 * prior["sd"]
    note = measurement.notes([{"scan": "s", "calibration": cal}], has_scan_bias=True)[0]
    assert f"{cal['offset_mm'] * 1000:+.0f} +- {cal['offset_sd_mm'] * 1000:.0f} um as its prior" in note
    loose = dict(cal, offset_sd_mm=0.035)
    unsettled = dict(cal, prior_ok=False)
    for c in (loose, unsettled, UNCAL):
        assert measurement.b0_prior(c) == {"prior": "normal", "mu": 0.0, "sd": measurement.UNCALIBRATED_SD_MM}
    # a photo's reference carries its place doubt as a prior too
    photo = calibrate(width, np.ones(160, bool), nominal, section, photo=True).to_dict()
    assert photo["offset_sd_mm"] > cal["offset_sd_mm"] and not photo["applied"]


def test_apparent_widths_without_scan_bias_are_said_and_a_caution(tmp_path, capsys):
    pairs = scan_with_summary(tmp_path, UNCAL)
    run_fit(pairs, "pa", map_only=True, progress=False)
    err = capsys.readouterr().err.strip().splitlines()
    # said once; the only other line is the sandwich's: the widths' uncalibrated offset,
    # which `pa` lacks, leaves the residuals scattering more than its noise model says
    said = [e for e in err if "widths are apparent widths" in e]
    assert len(said) == 1 and "add scan_bias" in said[0]
    assert all(e in said or "sandwich estimate" in e for e in err)
    notes = measurement.notes([{"scan": "widths", "calibration": UNCAL}], has_scan_bias=False)
    doc = {"converged": True, "information": {"chi2_nu": 1.0, "n_obs": 100}, "params": {}, "priors": {},
           "diagnostics": {"measurement": {"notes": notes}}}
    v = assess(doc)
    assert v.trustworthy and any("apparent widths" in c for c in v.cautions)


@pytest.mark.parametrize("cal,base", [(UNCAL, "pa+scan_bias"), (CAL, "pa"), (None, "pa")])
def test_model_auto_starts_with_scan_bias_on_apparent_widths(tmp_path, monkeypatch, cal, base):
    """--model auto: an unknown offset of tens of um would be read as back-pressure, so the
    chain starts with scan_bias (and the prior `calib fit` gives it) when the widths are
    apparent; the user's priors reach every model of the search that has the parameter."""
    import fit.auto
    from fit.auto import AutoResult

    seen = {}

    def fake_auto(scan, build, library, user=(), base_spec="pa", priors=None, **kw):
        seen.update(base=base_spec, priors=priors)
        return AutoResult(base_spec, stop="(test)")
    monkeypatch.setattr(fit.auto, "auto_model", fake_auto)
    (tmp_path / "p.toml").write_text('["thermal.a"]\nprior = "normal"\nmu = 0.0\nsd = 0.01\n')
    res, problem = run_fit(scan_with_summary(tmp_path, cal), "auto", map_only=True, progress=False,
                           priors=str(tmp_path / "p.toml"))
    assert seen["base"] == base and res.model == base
    # every model of the chain has the priors `calib fit` would give it, the base's or not
    want = {"thermal.a"} | ({"scan_bias.b0_mm"} if cal is not None else set())
    assert set(seen["priors"]) == want
    if cal is not None:
        assert seen["priors"]["scan_bias.b0_mm"] == measurement.b0_prior(cal)
    if base != "pa":
        assert _prior(problem, "scan_bias.b0_mm").sd == measurement.UNCALIBRATED_SD_MM
    # a prior of an effect the search did not choose does not stop the fit of the one it did
    assert "thermal.a" not in problem.param_names
    # ... but a name no effect has is a typo, said in one line
    from calib.errors import UserError
    (tmp_path / "q.toml").write_text('["thermal.aa"]\nprior = "normal"\nmu = 0.0\nsd = 0.01\n')
    with pytest.raises(UserError, match="thermal.aa"):
        run_fit(scan_with_summary(tmp_path, cal), "auto", map_only=True, progress=False,
                priors=str(tmp_path / "q.toml"))


@pytest.mark.parametrize("cal,base", [(UNCAL, "pa+scan_bias"), (CAL, "pa")])
def test_the_demo_starts_where_model_auto_starts(tmp_path, cal, base):
    """`calib demo --camera phone` started from `pa` on apparent widths, and its diagnosis
    named their unknown offset `flow_gain` (0.90) where the truth is thermal ooze and
    back-pressure; it now starts where --model auto does."""
    from calib.demo import _start_model

    (widths, manifest), = scan_with_summary(tmp_path, cal)
    assert _start_model(widths, manifest) == base


def test_search_priors_apply_only_to_models_that_have_the_parameter():
    from fit.compare import _problem
    from fit.hidden import make_case
    from fit.compare import observe
    from fit.model import build_model

    c = make_case("gear_slip", seed=0, ds_mm=0.5)
    scan = observe(c.manifest, c.table)
    pri = {"scan_bias.b0_mm": {"prior": "normal", "mu": 0.0, "sd": 0.03}}
    with_sb = _problem(build_model("pa+scan_bias", c.manifest.printer), scan, priors=pri)
    without = _problem(build_model("pa", c.manifest.printer), scan, priors=pri)
    assert _prior(with_sb, "scan_bias.b0_mm").sd == 0.03
    assert "scan_bias.b0_mm" not in without.param_names


def test_model_auto_starts_with_view_light_only_where_the_light_angle_spans_its_bands():
    """A spiral's beads meet the lamp at every angle: view_light's band offsets are apart
    from the reference beyond 60 deg. Parallel lines share one angle, where the offsets would
    be one offset for all (read as flow or back-pressure); an unknown angle is no light."""
    spiral = np.degrees(np.abs(np.arcsin(np.sin(np.linspace(0, 20 * np.pi, 4000)))))   # 0-90 deg
    assert measurement.light_varies(spiral)
    assert not measurement.light_varies(np.full(4000, 3.0))                 # parallel lines
    assert not measurement.light_varies(np.full(4000, 75.0))
    assert not measurement.light_varies(np.where(np.arange(4000) < 2500, np.nan, spiral))   # mostly unknown
    assert not measurement.light_varies(None) and not measurement.light_varies(np.array([]))
    assert measurement.auto_start("s", CAL, light=True) == ("pa+view_light", {})
    base, pri = measurement.auto_start("s", UNCAL, light=True)
    assert base == "pa+scan_bias+view_light" and set(pri) == {"scan_bias.b0_mm"}
    assert measurement.auto_start("s", UNCAL)[0] == "pa+scan_bias"


def test_model_auto_carries_a_photos_loose_applied_offset_with_scan_bias():
    """A photo's applied offset is known to >= 10 um (its place doubt): --model auto starts
    with scan_bias and that sd as its prior, where a flatbed's (a few um) starts with pa."""
    photo = dict(CAL, offset_sd_mm=0.0116)
    base, pri = measurement.auto_start("s", photo)
    assert base == "pa+scan_bias" and pri == {"scan_bias.b0_mm": {"prior": "normal", "mu": 0.0, "sd": 0.0116}}
    edge = dict(CAL, offset_sd_mm=measurement.AUTO_SCAN_BIAS_SD_MM * 0.99)
    assert measurement.auto_start("s", edge) == ("pa", {})


def test_a_loose_along_track_place_gives_view_shift_its_prior_and_auto_starts_with_it(tmp_path):
    """The summary's registration.along_track_sd_mm (measure/autoreg.py icp_covariance)
    becomes view_shift's prior sd (floored at MIN_SHIFT_SD_MM), per scan in joint fits;
    --model auto starts with view_shift from ALONG_SD_MM on (0.33 mm: StartStopTestPLA1's
    markerless pose), not below (0.023 mm: the spiral's), and a model without it hears why;
    no summary, no prior."""
    pairs = scan_with_summary(tmp_path, CAL)
    doc = json.loads((tmp_path / "widths.summary.json").read_text())
    doc["registration"] = {"along_track_sd_mm": 0.33}
    (tmp_path / "widths.summary.json").write_text(json.dumps(doc))
    assert measurement.load_along_sd(pairs[0][0]) == pytest.approx(0.33)
    state = [{"scan": "a", "calibration": None, "along_sd_mm": 0.33},
             {"scan": "b", "calibration": None, "along_sd_mm": 0.001}]
    names = ["view_shift.dx_mm@a", "view_shift.dy_mm@a", "view_shift.dx_mm@b", "view_shift.dy_mm@b"]
    pri = measurement.prior_overrides(state, names)
    assert pri["view_shift.dy_mm@a"] == {"prior": "normal", "mu": 0.0, "sd": 0.33}
    assert pri["view_shift.dx_mm@b"]["sd"] == measurement.MIN_SHIFT_SD_MM
    base, pri = measurement.auto_start("s", CAL, along_sd_mm=0.33)
    assert base == "pa+view_shift" and pri["view_shift.dx_mm"]["sd"] == pytest.approx(0.33)
    base, pri = measurement.auto_start("s", UNCAL, along_sd_mm=0.33)
    assert base == "pa+scan_bias+view_shift" and set(pri) == {"scan_bias.b0_mm", "view_shift.dx_mm",
                                                             "view_shift.dy_mm"}
    assert measurement.auto_start("s", CAL, along_sd_mm=0.023) == ("pa", {})
    # a model without view_shift on such a scan gets a caution in the verdict; with it, none
    said = measurement.notes(state, has_scan_bias=False, has_view_shift=False)
    assert len(said) == 1 and said[0].startswith("a: ") and "+-0.33 mm" in said[0] and "add view_shift" in said[0]
    assert measurement.notes(state, has_scan_bias=False, has_view_shift=True) == []
    assert measurement.auto_start("s", CAL) == ("pa", {})
    (tmp_path / "widths.summary.json").unlink()
    assert measurement.load_along_sd(pairs[0][0]) is None


def test_diagnose_and_compare_fit_with_the_priors_calib_fit_uses(tmp_path, capsys):
    """`calib diagnose` and `calib compare` read the summary beside the widths as `calib fit`
    does: a phone scan's apparent widths diagnosed with scan_bias's default prior (0 +-
    5 um) read reduced chi-square 90 where `calib fit` read 26 for the same model, and the
    candidate table ranked effects against a base `calib fit` never fits. The same model
    on the same widths now gives the same MAP from all three; a typo in --priors is one
    line, exit 2."""
    from calib.cli import main

    cal = dict(UNCAL, offset_mm=-0.02, offset_sd_mm=0.012, prior_ok=True)   # measured, not applied
    (widths, man), = scan_with_summary(tmp_path, cal)
    spec = "pa+scan_bias"
    m, _ = run_fit([(widths, man)], spec, map_only=True, progress=False)
    assert main(["compare", widths, "--manifest", man, "--models", spec, "pa", "--fast",
                 "-o", str(tmp_path / "c.json")]) == 0
    row = next(f for f in json.loads((tmp_path / "c.json").read_text())["models"] if f["model"] == spec)
    assert row["params"]["scan_bias.b0_mm"] == pytest.approx(m.values["scan_bias.b0_mm"], abs=2e-4)
    assert main(["diagnose", widths, "--manifest", man, "--model", spec, "--candidates", "thermal",
                 "-o", str(tmp_path / "d.json")]) == 0
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["params"]["scan_bias.b0_mm"] == pytest.approx(m.values["scan_bias.b0_mm"], abs=2e-4)
    assert d["chi2_nu"] == pytest.approx(m.chi2_nu, rel=0.02)
    # the prior pulls: without the summary the offset goes elsewhere
    (tmp_path / "widths.summary.json").unlink()
    assert main(["diagnose", widths, "--manifest", man, "--model", spec, "--candidates", "thermal",
                 "-o", str(tmp_path / "d0.json")]) == 0
    d0 = json.loads((tmp_path / "d0.json").read_text())
    assert abs(d0["params"]["scan_bias.b0_mm"] - d["params"]["scan_bias.b0_mm"]) > 1e-3
    # `calib report --models` compares with them too
    import fit.compare
    seen = {}
    real = fit.compare.compare_models

    def spy(*a, priors=None, **k):
        seen["priors"] = priors
        return real(*a, priors=priors, **k)
    (tmp_path / "widths.summary.json").write_text(json.dumps({"apparent_width": cal}))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit.compare, "compare_models", spy)
        assert main(["report", "--widths", widths, "--manifest", man, "--models", spec,
                     "-o", str(tmp_path / "r.html")]) == 0
    assert seen["priors"]["scan_bias.b0_mm"] == measurement.b0_prior(cal)
    capsys.readouterr()
    (tmp_path / "q.toml").write_text('["scan_bias.b00"]\nprior = "normal"\nmu = 0.0\nsd = 0.01\n')
    for verb in (["diagnose", widths, "--manifest", man, "--model", spec],
                 ["compare", widths, "--manifest", man, "--models", spec, "--fast"],
                 ["report", "--widths", widths, "--manifest", man, "--models", spec, "-o", str(tmp_path / "r.html")]):
        assert main([*verb, "--priors", str(tmp_path / "q.toml")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "scan_bias.b00" in err[0]


def test_the_refits_judge_a_value_against_the_interval_the_user_is_shown(tmp_path, monkeypatch):
    """The spread, structure and missing-effect refits call a value moved when it leaves its
    95 % interval. They ran before the width offset's doubt widened the intervals, and
    `make demo`'s right model was refused: `nonlinear` +95 BIC moved tau 0.7994 -> 0.798,
    outside the posterior's [0.7986, 0.8001], inside the reported [0.7925, 0.8063]. They
    now get the widened intervals, and the missing-effect check asks every fit within the
    misfit line, whatever its chi2_nu_bead."""
    import fit.nuisance

    seen = {}
    real = fit.nuisance.missing_check

    def spy(make_problem, spec, map_values, map_bic, ci95, seed=0, progress=False):
        seen["ci95"] = dict(ci95)
        return real(make_problem, spec, map_values, map_bic, ci95, seed=seed)
    monkeypatch.setattr(fit.nuisance, "missing_check", spy)
    cal = dict(CAL, offset_sd_mm=0.004)         # a doubt wide enough to widen tau
    # the example's right model (its user effect), which passes the misfit line
    res, _ = run_fit(scan_with_summary(tmp_path, cal), "pa+gear_slip", effects="data/examples/my_effects.py",
                     progress=False, max_steps=1500)
    widened = res.diagnostics["offset_envelope"]["widened"]
    assert "pa.tau_s" in widened
    assert list(seen["ci95"]["pa.tau_s"]) == list(res.params["pa.tau_s"].ci95) == widened["pa.tau_s"]["ci95"]
    assert list(seen["ci95"]["pa.tau_s"]) != widened["pa.tau_s"]["ci95_posterior"]
