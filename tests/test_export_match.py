"""The width-optimal firmware setting (fit/firmware_match.py) and `calib export --on`.

Known answers: a firmware compensation A(v) equal to the printer's steady advance
Preq(v) cancels the lag exactly (dP/dt = v_e - v_n with P = Preq(v_e) gives v_n = v_e),
so linear PA K = tau on a pure `pa` printer and Kalico tanh with (LA, off, v_lin) = the
truth's on a pa+kalico_tanh printer print the commanded widths; with shear thinning or
bead back-pressure no linear K cancels the lag, and the searched K must beat K = tau.
Fits are posterior draws written as fit.json (draws around a truth), so each test costs
seconds, not a sampler run.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from calib.cli import main
from fit import firmware_match as fm
from patterns.profile import load_profile

PROF = load_profile("direct_drive")
TAU = 0.04


@pytest.fixture(scope="module")
def ref():
    return fm.prepare_reference(fm.standard_reference(PROF), "standard")


def fit_doc(values: dict, spec: str, n=40, rel_sd=0.02, seed=1, derived=None) -> dict:
    """fit.json of a trustworthy fit whose draws scatter ``rel_sd`` around ``values``."""
    rng = np.random.default_rng(seed)
    names = list(values)
    S = np.array([[values[k] * (1 + rel_sd * rng.standard_normal()) for k in names] for _ in range(n)])
    return {"schema": "calib.fit/1", "model": spec, "converged": True,
            "information": {"chi2_nu": 1.0, "rms_mm": 0.01, "n_obs": 500, "loo": {}},
            "param_names": names,
            "params": {k: {"median": float(np.median(S[:, j])),
                           "ci95": [float(np.min(S[:, j])), float(np.max(S[:, j]))]}
                       for j, k in enumerate(names)},
            "priors": {"pa.tau_s": {"kind": "loguniform", "lower": 0.005, "upper": 5.0}},
            "derived": {"pressure_advance_s": {"median": float(np.median(S[:, 0]))},
                        **(derived or {})},
            "profile": PROF.to_dict(), "samples": S.tolist()}


def write(tmp_path, doc, name="fit.json"):
    p = tmp_path / name
    p.write_text(json.dumps(doc))
    return str(p)


def test_the_bead_and_the_picture_are_not_dynamics():
    """pa with the picture's and the bead's nuisances is linear PA: tau cancels it, and no
    "more than linear PA" width match runs (a phone fit of pa+scan_bias+view_light did)."""
    vals = {"pa.tau_s": TAU, "scan_bias.b0_mm": -0.04, "view_light.o0_mm": 0.004, "spread.sigma_mm": 0.15,
            "bed_mesh.dz11_mm": 0.01}
    phys = fm.physics_from_fit(fit_doc(vals, "pa+scan_bias+view_light+spread+bed_mesh", n=4), n_draws=2)
    assert phys.linear and phys.spec == "pa"
    assert set(phys.dropped) == {"scan_bias", "view_light", "spread", "bed_mesh"}


def test_linear_physics_optimum_is_tau_and_prints_the_commanded_widths(ref):
    doc = fit_doc({"pa.tau_s": TAU}, "pa", n=8, rel_sd=0.0)
    phys = fm.physics_from_fit(doc, n_draws=1)
    opt = fm.optimal_linear(phys, ref, smooth_time_s=0.0)      # searched, not assumed
    assert opt["k_s"][0] == pytest.approx(TAU, rel=0.01)
    errs = fm.width_errors_mm(phys, ref, fm._theta_for(phys, [fm.Setting("none"),
                                                              fm.Setting("linear", TAU, 0.0)]))
    assert errs["all"][1] < 0.002 and opt["rms_mm"][0] < 0.002          # ~0 (< 2 um) ...
    assert errs["all"][0] > 0.05 and errs["stops"][0] > 0.1              # ... against > 50 um
    # the Orca-table mode with a flat table is the same linear PA
    tab = fm._theta_for(phys, [fm.Setting("table", table_flow_mm3_s=(1.0, 20.0), table_k_s=(TAU, TAU))])
    assert fm.width_errors_mm(phys, ref, tab)["all"][0] == pytest.approx(errs["all"][1], abs=2e-4)


def test_kalico_compensation_cancels_a_kalico_shaped_advance(ref):
    truth = {"pa.tau_s": 0.02, "kalico_tanh.off_mm": 0.15, "kalico_tanh.v_lin_mm_s": 0.5}
    phys = fm.physics_from_fit(fit_doc(truth, "pa+kalico_tanh", n=4, rel_sd=0.0), n_draws=1)
    exact = fm.Setting("tanh", 0.02, 0.0, 0.15, 0.5)
    e = fm.width_errors_mm(phys, ref, fm._theta_for(phys, [fm.Setting("none"), exact,
                                                           fm.Setting("linear", 0.02, 0.0)]))
    assert e["all"][1] < 0.003 < e["all"][2] < e["all"][0]


@pytest.mark.parametrize("spec,values", [
    ("pa+nonlinear", {"pa.tau_s": TAU, "nonlinear.n": 0.7}),
    ("pa+backpressure", {"pa.tau_s": TAU, "backpressure.kb": 0.1, "backpressure.w_sat_mm": 0.8}),
])
def test_nonlinear_physics_optimal_k_beats_tau_and_no_pa(ref, spec, values):
    doc = fit_doc(values, spec, n=40)
    m = fm.match_firmware(doc, ref, smooth_time_s=0.0, n_draws=4)
    assert m.optimised
    rows = list(m.rows.values())          # no PA, K = tau, the exported K
    no_pa, at_tau, best = (r["all"]["median"] for r in rows[:3])
    assert best < at_tau < no_pa
    assert m.k_s["ci95"][0] <= m.k_s["median"] <= m.k_s["ci95"][1]
    assert abs(m.k_s["median"] / TAU - 1) > 0.02          # a different K, not tau again
    # the search found the minimum: 5 % either side is worse on every draw
    phys = fm.physics_from_fit(doc, n_draws=4)
    k = m.k_s["median"]
    e = fm.width_errors_mm(phys, ref, fm._theta_for(phys, [fm.Setting("linear", f * k, 0.0)
                                                           for f in (0.95, 1.0, 1.05)]))["all"]
    e = e.reshape(3, -1).mean(axis=1)
    assert e[1] < e[0] and e[1] < e[2]


def test_an_advance_carried_by_a_nonlinear_term_is_searched_past_the_first_bound(ref):
    # tau 0.02 s, the reciprocal term the rest: Preq / v = 0.02 + off / (v + v_lin), 0.2-0.6 s
    # at the move mix's filament speeds (0.8-7 mm/s). The search starts at max(4 tau, 0.2 s); an optimum
    # on that bound was exported as 0.2000 [0.2000, 0.2000] (bench_export_foreign).
    truth = {"pa.tau_s": 0.02, "kalico_recip.off_mm": 3.0, "kalico_recip.v_lin_mm_s": 3.0}
    phys = fm.physics_from_fit(fit_doc(truth, "pa+kalico_recip", n=4, rel_sd=0.0), n_draws=1)
    k = float(fm.optimal_linear(phys, ref, smooth_time_s=0.0)["k_s"][0])
    grid = np.linspace(0.05, 1.5, 59)
    e = fm.width_errors_mm(phys, ref, fm._theta_for(phys, [fm.Setting("linear", g, 0.0) for g in grid]))["all"]
    assert k > 0.25                                        # past the first bound, ...
    assert abs(k - grid[np.argmin(e)]) <= 0.03             # ... at the grid's minimum
    e_k = fm.width_errors_mm(phys, ref, fm._theta_for(phys, [fm.Setting("linear", k, 0.0)]))["all"][0]
    assert e_k <= e.min() + 1e-5


def test_an_optimum_at_the_search_limit_is_said_not_to_be_a_measurement(ref, tmp_path, capsys):
    # an advance no printer has (off 500 mm, about 10 s): the K search ends at its 5 s limit
    truth = {"pa.tau_s": 0.02, "kalico_recip.off_mm": 500.0, "kalico_recip.v_lin_mm_s": 50.0}
    doc = fit_doc(truth, "pa+kalico_recip", n=4, rel_sd=0.0)
    m = fm.match_firmware(doc, ref, smooth_time_s=0.0, n_draws=2)
    assert m.k_s["median"] >= 0.99 * fm.K_LIMIT_S and m.n_at_limit == 2
    assert any("search's limit" in n and "do not paste" in n for n in m.notes)
    # `calib export` refuses it with one line and leaves the profile as it was
    fit = write(tmp_path, doc)
    cfg = tmp_path / "start.gcode"
    cfg.write_text("M900 K0.05\n")
    capsys.readouterr()
    assert main(["export", fit, "--to", "marlin", "--profile", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "lies at the search's limit: nothing to paste" in err and "Traceback" not in err
    assert cfg.read_text() == "M900 K0.05\n"
    assert main(["export", fit, "--to", "marlin", "--profile", str(cfg), "--force"]) == 0
    assert cfg.read_text().startswith("M900 K5.0") or cfg.read_text().startswith("M900 K4.9")


def test_nonlinear_dynamics_that_cannot_be_planned_are_not_exported_as_tau(tmp_path, capsys):
    """A printer dict without the planner's limits (a hand-made or old manifest): the move
    mix cannot be planned, and with more than linear PA tau is only part of the advance (a
    probe print's fit would have written tau 0.047 s for a printer whose best K is 0.201 s).
    Refused with one line; --force writes tau with a note; a linear fit keeps tau as before."""
    partial = {"name": "probe", "filament_diameter_mm": 1.75, "nozzle_diameter_mm": 0.4}
    doc = fit_doc({"pa.tau_s": 0.047, "kalico_recip.off_mm": 0.5, "kalico_recip.v_lin_mm_s": 2.0},
                  "pa+kalico_recip", n=8)
    fit = write(tmp_path, {**doc, "profile": partial})
    cfg = tmp_path / "start.gcode"
    cfg.write_text("M900 K0.05\n")
    capsys.readouterr()
    assert main(["export", fit, "--to", "marlin", "--profile", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "more than linear PA" in err and "--force" in err and "Traceback" not in err
    assert err.count("\n") == 1 and cfg.read_text() == "M900 K0.05\n"
    assert main(["export", fit, "--to", "marlin", "--profile", str(cfg), "--force"]) == 0
    assert "the value is tau" in capsys.readouterr().err
    assert cfg.read_text().startswith("M900 K0.04")
    lin = fit_doc({"pa.tau_s": 0.047}, "pa", n=8)
    assert main(["export", write(tmp_path, {**lin, "profile": partial}, "lin.json"), "--to", "marlin"]) == 0
    assert capsys.readouterr().out.startswith("M900 K0.04")


def test_the_k_interval_holds_the_fits_envelopes(ref, tmp_path, capsys):
    """fit.json's envelope draws (the width offset's doubt, the short-wobble fit) widen
    the exported K's 95 % interval as they widen `calib fit`'s: the median stays the
    posterior's; the interval reaches the envelope's K. Linear PA: the envelope's tau;
    nonlinear: the width-optimal K of the envelope's draws."""
    doc = fit_doc({"pa.tau_s": TAU}, "pa", n=40, rel_sd=0.002)
    doc["envelope_samples"] = {"noise": np.asarray(doc["samples"]) * 1.10}
    fit = write(tmp_path, {**doc, "envelope_samples": {"noise": doc["envelope_samples"]["noise"].tolist()}})
    capsys.readouterr()
    assert main(["export", fit, "--to", "marlin"]) == 0
    cap = capsys.readouterr()
    k = float(cap.out.split("K")[1])
    assert k == pytest.approx(TAU, rel=0.005)                        # the posterior's median
    hi = float(cap.err.split("(95 % ")[1].split("-")[1].split(")")[0])
    assert hi == pytest.approx(1.10 * TAU, rel=0.01)
    assert "short-wobble noise model" in cap.err and "(and 32 of the fit's envelopes)" in cap.err
    truth = {"pa.tau_s": 0.02, "nonlinear.n": 0.7}
    nl = fit_doc(truth, "pa+nonlinear", n=4, rel_sd=0.0)
    post = fm.match_firmware(nl, ref, smooth_time_s=0.0, n_draws=4)
    nl["envelope_samples"] = {"offset": fit_doc({"pa.tau_s": 0.025, "nonlinear.n": 0.7}, "pa+nonlinear",
                                                n=4, rel_sd=0.0)["samples"]}
    both = fm.match_firmware(nl, ref, smooth_time_s=0.0, n_draws=4)
    assert both.k_s["median"] == post.k_s["median"] and both.n_envelope_draws == 4
    other = fm.match_firmware({**nl, "samples": nl["envelope_samples"]["offset"]}, ref, smooth_time_s=0.0,
                              n_draws=4, envelopes=False).k_s["median"]
    assert abs(other - post.k_s["median"]) > 0.002                 # the envelope's K differs ...
    lo, hi = both.k_s["ci95"]
    assert lo <= min(other, post.k_s["median"]) + 1e-9 and hi >= max(other, post.k_s["median"]) - 1e-9


def test_export_prints_the_optimal_k_with_interval_and_the_table(tmp_path, capsys):
    derived = {"tested_flow_mm3_s": {"lo": 0.5, "hi": 20.0},
               "kalico_tanh": {"pressure_advance_s": {"median": 0.02}, "offset_mm": {"median": 0.05},
                               "linearization_velocity_mm_s": {"median": 1.0}},
               "pa_vs_flow": {"flow_mm3_s": [1.0, 5.0, 10.0, 15.0], "pa_s_median": [0.05, 0.042, 0.038, 0.036],
                              "pa_s_ci95": [[0.04, 0.06]] * 4, "v_mm_s": [0.4, 2, 4, 6], "v_max_mm_s": 6.0}}
    fit = write(tmp_path, fit_doc({"pa.tau_s": TAU, "nonlinear.n": 0.7}, "pa+nonlinear", derived=derived))
    assert main(["export", fit, "--to", "marlin"]) == 0
    cap = capsys.readouterr()
    assert cap.out.startswith("M900 K") and cap.out.count("\n") == 1      # stdout: the snippet only
    k = float(cap.out.split("K")[1])
    assert abs(k - TAU) > 0.002
    assert f"{k:.4f} s (95 % " in cap.err
    for row in ("no PA", "linear PA = tau", "(exported)", "Kalico tanh", "Orca adaptive table"):
        assert row in cap.err
    assert "starts" in cap.err and "corners" in cap.err and "warning" not in cap.err
    # Klipper: the smooth time is searched too and written with the advance
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[extruder]\nstep_pin: PB3\npressure_advance: 0.5\n")
    assert main(["export", fit, "--to", "klipper", "--profile", str(cfg)]) == 0
    txt = cfg.read_text()
    assert "pressure_advance_smooth_time: 0.0" in txt and "pressure_advance: 0.5\n" not in txt
    start = tmp_path / "start.gcode"
    start.write_text("SET_PRESSURE_ADVANCE ADVANCE=0.02 SMOOTH_TIME=0.04\n")
    assert main(["export", fit, "--to", "klipper-gcode", "--profile", str(start)]) == 0
    assert "SMOOTH_TIME=0.04\n" not in start.read_text()


def test_plain_pa_fit_keeps_tau(tmp_path, capsys):
    fit = write(tmp_path, fit_doc({"pa.tau_s": TAU}, "pa", rel_sd=0.02))
    tau = json.loads((tmp_path / "fit.json").read_text())["derived"]["pressure_advance_s"]["median"]
    assert main(["export", fit, "--to", "klipper-gcode"]) == 0
    cap = capsys.readouterr()
    assert cap.out == f"SET_PRESSURE_ADVANCE ADVANCE={tau:.4f} SMOOTH_TIME=0.040\n"
    assert "the fitted physics is linear PA" in cap.err and "no PA" in cap.err
    # what the interval does not hold is said beside it, on stderr, never in the snippet
    assert "not the doubt of its form" in cap.err


def test_on_gcode_file_and_bad_gcode(tmp_path, capsys):
    fit = write(tmp_path, fit_doc({"pa.tau_s": TAU, "nonlinear.n": 0.7}, "pa+nonlinear",
                                  derived={"tested_flow_mm3_s": {"lo": 0.5, "hi": 30.0}}))
    g = tmp_path / "part.gcode"
    g.write_text("G21\nG90\nM83\nG1 Z0.2 F600\nG1 X50 Y50 F9000\nG1 X90 Y50 E1.6 F3000\n"
                 "G1 X90 Y60 E0.4\nG1 X50 Y60 E1.6\nG1 E-0.5 F2100\nG1 X50 Y80 F9000\n"
                 "G1 E0.5 F2100\nG1 X150 Y80 E4.0 F6000\nG1 X150 Y90 E0.4\n")
    assert main(["export", fit, "--to", "rrf", "--on", str(g)]) == 0
    cap = capsys.readouterr()
    assert cap.out.startswith("M572 D0 S") and cap.out.count("\n") == 1
    assert "width check on part.gcode" in cap.err
    k_on = float(cap.out.split("S")[1])
    assert main(["export", fit, "--to", "rrf"]) == 0
    assert float(capsys.readouterr().out.split("S")[1]) != k_on       # the reference matters
    for text in ("G1 X1e400 Y2 E1\n", "; only a comment\nG28\n"):
        bad = tmp_path / "bad.gcode"
        bad.write_text(text)
        assert main(["export", fit, "--to", "rrf", "--on", str(bad)]) == 2
        cap = capsys.readouterr()
        assert cap.out == "" and cap.err.count("\n") == 1 and "--on" in cap.err
    assert main(["export", fit, "--to", "rrf", "--on", str(tmp_path / "missing.gcode")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["export", fit, "--to", "kisslicer", "--on", str(g)]) == 2


def test_extrapolation_warning_when_the_reference_flows_exceed_the_tested_ones(tmp_path, capsys, ref):
    values = {"pa.tau_s": TAU, "nonlinear.n": 0.7}
    hi_ref = ref.flow_mm3_s[1]
    assert 10.0 < hi_ref < 20.0               # the standard mix reaches ~13 mm^3/s
    low = write(tmp_path, fit_doc(values, "pa+nonlinear", derived={"tested_flow_mm3_s": {"lo": 0.5, "hi": 6.0}}),
                "low.json")
    assert main(["export", low, "--to", "marlin"]) == 0
    err = capsys.readouterr().err
    assert "warning: the reference print reaches" in err and "0.5-6.0 mm^3/s" in err
    wide = write(tmp_path, fit_doc(values, "pa+nonlinear", derived={"tested_flow_mm3_s": {"lo": 0.5, "hi": 16.0}}),
                 "wide.json")
    assert main(["export", wide, "--to", "marlin"]) == 0
    assert "reaches" not in capsys.readouterr().err


def test_orca_table_lookup_follows_orcas_rules():
    """OrcaSlicer's AdaptivePAInterpolator: PCHIP between rows (exact on a straight line),
    the end rows' K held outside the table (no extrapolation), rounded to 0.001 s."""
    x = np.array([2.0, 5.0, 9.0, 14.0])
    lin = 0.06 - 0.002 * x
    q = np.array([0.5, 2.0, 3.3, 7.7, 14.0, 30.0])
    np.testing.assert_allclose(fm.orca_table_k(q, x, lin), np.round(0.06 - 0.002 * np.clip(q, 2, 14), 3))
    k = fm.orca_table_k(np.linspace(2, 14, 200), x, np.array([0.05, 0.041, 0.036, 0.035]))
    assert np.all(np.diff(k) <= 0) and np.all(np.round(k * 1000) == k * 1000)   # monotone (PCHIP), 3 decimals
