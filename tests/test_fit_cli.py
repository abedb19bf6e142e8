"""`calib fit` / `calib export` on a small virtual print (direct drive, pa): bad input gives
one-line errors with exit code 2, a capped sampler exit code 3, export edits profiles.

The print is the spiral-step test track alone: the manifest keeps only the test track and
the planned timeline from shortly before it starts to shortly after it ends (the frame,
fiducials and labels are ~90 % of the timeline and only slow the physics down here)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calib.cli import main


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    d = tmp_path_factory.mktemp("fitcli")
    prof = load_profile("direct_drive")
    _, man = spiral_step.generate(prof, speeds_mm_s=(20.0,), n_steps=4, step_s=(3.0,))
    man = man.cut_to_test_tracks()
    mp = man.save(d / "a.manifest.json")
    t = print_virtual(man, build_model("pa", prof), {"pa.tau_s": 0.05}).table
    rng = np.random.default_rng(0)
    t.width_sd_mm[:] = 0.01
    t.width_mm = t.width_mm + 0.01 * rng.standard_normal(len(t))
    w = t.save(d / "a.csv")
    return d, w, mp, t


def test_capped_sampler_is_flagged_and_exit_code_3(scan, capsys):
    d, w, mp, _ = scan
    out = d / "fit.json"
    rc = main(["fit", str(w), "--manifest", str(mp), "--model", "pa", "--max-steps", "150",
               "--quiet", "-o", str(out)])
    assert rc == 3
    doc = json.loads(out.read_text())
    assert doc["converged"] is False and "NOT CONVERGED" in doc["diagnostics"]["warning"]
    # even a short run puts tau near the truth (0.05 s)
    assert doc["params"]["pa.tau_s"]["median"] == pytest.approx(0.05, rel=0.05)
    assert float(doc["derived"]["firmware"]["marlin"].split("K")[1]) == pytest.approx(0.05, rel=0.05)
    assert doc["trust"]["trustworthy"] is False
    assert "did not converge" in doc["trust"]["problems"][0]
    capsys.readouterr()
    # export refuses an unconverged fit: one line, exit 2, the profile untouched, no backup
    prof = d / "filament.json"
    before = json.dumps({"name": "PLA", "pressure_advance": ["0.02"]})
    prof.write_text(before)
    assert main(["export", str(out), "--to", "orca", "--profile", str(prof)]) == 2
    err = capsys.readouterr().err
    assert "not trustworthy" in err and "--force" in err and err.count("\n") == 1
    assert prof.read_text() == before and not list(d.glob("filament.json.bak-*"))
    # --force: orca filament JSON (string array) updated in place with a backup; the
    # reasons go to stderr, never into the snippet on stdout
    assert main(["export", str(out), "--to", "marlin", "--force"]) == 0
    cap = capsys.readouterr()
    assert cap.out.strip().startswith("M900 K") and cap.out.count("\n") == 1
    assert "NOT TRUSTWORTHY" in cap.err
    assert main(["export", str(out), "--to", "orca", "--profile", str(prof), "--force"]) == 0
    new = json.loads(prof.read_text())
    assert new["pressure_advance"][0].startswith("0.0") and float(new["pressure_advance"][0]) == \
        pytest.approx(0.05, rel=0.05)
    assert len(list(d.glob("filament.json.bak-*"))) == 1
    cfg = d / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: cartesian\n[extruder]\nstep_pin: PB3\npressure_advance: 0.5\n")
    assert main(["export", str(out), "--to", "klipper", "--profile", str(cfg), "--force"]) == 0
    txt = cfg.read_text()
    assert "pressure_advance: 0.5\n" not in txt and txt.count("pressure_advance:") == 1


def test_empty_csv_is_a_user_error(scan, capsys):
    d, w, mp, _ = scan
    e = d / "empty.csv"
    e.write_text("")
    assert main(["fit", str(e), "--manifest", str(mp), "-o", str(d / "x.json")]) == 2
    err = capsys.readouterr().err
    assert "is empty" in err and err.count("\n") == 1


def test_nan_width_is_a_user_error(scan, capsys):
    d, w, mp, t = scan
    bad = t.subset(np.ones(len(t), bool))
    bad.width_mm[5] = np.nan
    p = d / "nan.csv"
    p.write_text(bad.to_csv_text())
    assert main(["fit", str(p), "--manifest", str(mp), "-o", str(d / "x.json")]) == 2
    assert "NaN" in capsys.readouterr().err


def test_manifest_that_does_not_match_is_a_user_error(scan, capsys):
    d, w, mp, t = scan
    moved = t.subset(np.ones(len(t), bool))
    moved.x_mm = moved.x_mm + 30.0
    p = d / "moved.csv"
    moved.save(p)
    assert main(["fit", str(p), "--manifest", str(mp), "-o", str(d / "x.json")]) == 2
    assert "different manifest" in capsys.readouterr().err
    other = t.subset(np.ones(len(t), bool))
    other.track = other.track + 100
    p2 = d / "other.csv"
    other.save(p2)
    assert main(["fit", str(p2), "--manifest", str(mp), "-o", str(d / "x.json")]) == 2
    assert "not in the manifest" in capsys.readouterr().err


def test_batch_on_local_dask_cluster(scan, tmp_path):
    """Two scans of different printers' tau fitted on a LocalCluster; summary has both."""
    from dask.distributed import LocalCluster

    from calib.commands.batch import run_batch, summary_csv
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns.manifest import Manifest
    from patterns.profile import load_profile

    d, w, mp, t = scan
    man = Manifest.load(mp)
    for name, tau in (("p1", 0.03), ("p2", 0.08)):
        man.save(tmp_path / f"{name}.manifest.json")
        tt = print_virtual(man, build_model("pa", load_profile("direct_drive")), {"pa.tau_s": tau}).table
        rng = np.random.default_rng(1)
        tt.width_sd_mm[:] = 0.01
        tt.width_mm = tt.width_mm + 0.01 * rng.standard_normal(len(tt))
        tt.save(tmp_path / f"{name}.csv")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        rows = run_batch(tmp_path, "pa", scheduler=c.scheduler_address, max_steps=300,
                         progress=False)
    assert [r["scan"] for r in rows] == ["p1", "p2"]
    assert rows[0]["pa.tau_s"] == pytest.approx(0.03, rel=0.08)
    assert rows[1]["pa.tau_s"] == pytest.approx(0.08, rel=0.08)
    assert (tmp_path / "p1.fit.json").exists()
    assert summary_csv(rows).splitlines()[0].startswith("scan,")


def test_same_seed_same_chains_at_any_thread_count(scan):
    """A fit is a function of its data and --seed: the physics kernels run one parameter
    set per thread with no cross-set reduction, so 1 and 2 numba threads give bit-identical
    chains, and a second run with the same seed repeats them; another seed does not."""
    from fit.data import FitData
    from fit.kernels import set_threads
    from fit.sampler import fit_mcmc, make_problem

    d, w, mp, _ = scan

    def chains(threads, seed):
        set_threads(threads)
        pb = make_problem("pa", FitData.load([(str(w), str(mp))]))
        r = fit_mcmc(pb, seed=seed, max_steps=200, progress=False, n_loo_draws=30)
        return r.samples

    try:
        one, two, again, other = chains(1, 4), chains(2, 4), chains(2, 4), chains(2, 5)
    finally:
        set_threads(None)
    assert one.shape == two.shape and np.array_equal(one, two)
    assert np.array_equal(two, again)
    assert not np.array_equal(two, other)


def test_misfit_is_flagged_and_the_right_model_is_not(tmp_path, capsys):
    """Truth pa+thermal (strong slow ooze); `pa` alone returns a narrow interval around a
    biased tau. Its fit must say NOT TRUSTWORTHY with the reduced chi-square, print no
    firmware line, and export must refuse; pa+thermal on the same scan passes."""
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile("direct_drive")
    _, man = spiral_step.generate(prof, speeds_mm_s=(20.0,), n_steps=4, step_s=(3.0,))
    man = man.cut_to_test_tracks()
    mp = man.save(tmp_path / "t.manifest.json")
    truth = {"pa.tau_s": 0.05, "thermal.a": 0.3, "thermal.tau_s": 3.0}
    t = print_virtual(man, build_model("pa+thermal", prof), truth).table
    t.width_sd_mm[:] = 0.005
    t.width_mm = t.width_mm + 0.005 * np.random.default_rng(3).standard_normal(len(t))
    w = t.save(tmp_path / "t.csv")
    docs = {}
    for model in ("pa", "pa+thermal"):
        out = tmp_path / f"{model}.json"
        assert main(["fit", str(w), "--manifest", str(mp), "--model", model, "--quiet",
                     "-o", str(out)]) == 0
        docs[model] = (json.loads(out.read_text()), capsys.readouterr())
    bad, cap = docs["pa"]
    assert bad["trust"]["trustworthy"] is False and bad["information"]["chi2_nu"] > 2
    assert "does not fit" in cap.err and "diagnose" in cap.err
    # said before the sampler runs, too
    assert "already misfits the scan" in cap.err
    # widths from the virtual printer have no `calib measure` summary beside them: said
    assert "no `calib measure` summary (t.summary.json)" in cap.err
    assert "M900" not in cap.out and "NOT TRUSTWORTHY" in cap.out
    assert main(["export", str(tmp_path / "pa.json"), "--to", "klipper"]) == 2
    good, cap = docs["pa+thermal"]
    assert good["trust"]["trustworthy"] is True, good["trust"]["problems"]
    assert "fit quality: OK" in cap.out and "M900 K" in cap.out and "misfits" not in cap.err
    lo, hi = good["params"]["pa.tau_s"]["ci95"]
    assert lo < 0.05 < hi


def _trusted_fit_json(path, profile):
    doc = {"schema": "calib.fit/1", "model": "pa", "converged": True,
           "information": {"chi2_nu": 1.0, "rms_mm": 0.01, "n_obs": 500, "loo": {}},
           "params": {"pa.tau_s": {"median": 0.6, "ci95": [0.59, 0.61]}},
           "priors": {"pa.tau_s": {"kind": "loguniform", "lower": 0.005, "upper": 5.0}},
           "derived": {"kisslicer_ve_us": {"median": 1.7404}, "pressure_advance_s": {"median": 0.6}},
           "profile": profile, "samples": []}
    path.write_text(json.dumps(doc))
    return path


def test_kisslicer_export_uses_kisslicer2_key_and_states_the_geometry(tmp_path, capsys):
    prof = {"name": "adventurer3", "bowden_length_mm": 200.0, "nozzle_land_length_mm": 0.6,
            "nozzle_diameter_mm": 0.4, "filament_diameter_mm": 1.75, "firmware_pressure_advance": False}
    fit = _trusted_fit_json(tmp_path / "fit.json", prof)
    assert main(["export", str(fit), "--to", "kisslicer"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "matl_viscosity_over_elasticity_us=1.740\n"
    assert "drive_len_1" in cap.err and "200.0 mm" in cap.err
    # a material ini with the key written by an older calib: replaced, the rest kept
    ini = tmp_path / "PLA.ini"
    ini.write_text("matl_name=PLA\nviscoelasticity_us=0.500\npreload_factor=1\n")
    assert main(["export", str(fit), "--to", "kisslicer", "--profile", str(ini)]) == 0
    assert ini.read_text() == "matl_name=PLA\nmatl_viscosity_over_elasticity_us=1.740\npreload_factor=1\n"
    # this printer's firmware ignores M900: the line is printed, with a warning on stderr
    capsys.readouterr()
    assert main(["export", str(fit), "--to", "marlin"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "M900 K0.6000\n" and "ignores the pressure-advance command" in cap.err
    assert "--to kisslicer" in cap.err


def test_fit_says_when_the_printer_ignores_the_firmware_line_and_gates_every_pasteable_line(scan, capsys, monkeypatch):
    """The Adventurer 3's firmware ignores M900 (its owner found no effect even at K=200):
    `calib fit` still prints the line, and says on the next that it changes nothing there
    and which route does."""
    d, w, mp, _ = scan
    doc = json.loads(mp.read_text())
    doc["printer"]["firmware_pressure_advance"] = False
    doc["printer"]["name"] = "adventurer3"
    mp2 = d / "ignored.manifest.json"
    mp2.write_text(json.dumps(doc))
    capsys.readouterr()
    from calib.commands import fit as fit_cmd

    kept = []
    run_fit = fit_cmd.run_fit
    monkeypatch.setattr(fit_cmd, "run_fit", lambda *a, **k: kept.append(run_fit(*a, **k)) or kept[-1])
    assert main(["fit", str(w), "--manifest", str(mp2), "--model", "pa", "--quiet",
                 "-o", str(d / "ignored.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    i = next(k for k, line in enumerate(out) if line.startswith("pressure advance"))
    assert "M900 K" in out[i]
    assert "'adventurer3' says its firmware ignores these commands" in out[i + 1] and "kisslicer" in out[i + 1]
    # the same fit on a printer whose firmware honours M900 (the profile is what differs)
    res = kept[0][0]
    res.profile = {**res.profile, "firmware_pressure_advance": True}
    text = fit_cmd.summary_text(res)
    assert "M900 K" in text and "ignores" not in text
    # A fit refused by the verdict prints none of its pasteable values as a number to use:
    # not the firmware line, not KISSlicer VE (where this printer's owner is sent), not
    # Kalico's constants (seen on the realdata SpStartStopTest2: "KISSlicer VE 3.500 us (95 %
    # 3.334-3.698)" under a NOT TRUSTWORTHY verdict)
    q = {"median": 0.05, "ci95": [0.04, 0.06]}
    res.derived = {**res.derived, "kisslicer_ve_us": {"median": 3.5, "ci95": [3.334, 3.698]},
                   "kalico_tanh": {"v_max_mm_s": 2.0, "rms_mm": {"median": 0.001}, "pressure_advance_s": q,
                                   "offset_mm": q, "linearization_velocity_mm_s": q}}
    text = fit_cmd.summary_text(res)
    assert "KISSlicer VE 3.500 us (95 % 3.334-3.698)" in text and "Kalico tanh (0-2.00 mm/s" in text
    res.trust = {**(res.trust or {}), "trustworthy": False}
    lines = fit_cmd.summary_text(res).splitlines()
    ve = [x for x in lines if x.startswith("KISSlicer VE")]
    kal = [x for x in lines if x.startswith("Kalico")]
    assert len(ve) == 1 and "NOT TRUSTWORTHY" in ve[0] and "95 %" not in ve[0]
    assert len(kal) == 1 and "NOT TRUSTWORTHY" in kal[0] and "linear_advance" not in kal[0]
    assert not any(x.startswith("pressure advance") and "95 %" in x for x in lines)


def test_a_nonlinear_fits_firmware_line_is_the_width_optimal_k_not_tau(scan, capsys):
    """With a saturating term the fitted tau is only the linear part of the advance: a
    foreign Bowden print fitted as pa+kalico_recip read tau 0.036 s where the linear K that
    printed best was 0.201 s, and `calib fit` printed the 0.036 as its firmware line. The
    line is now the width match's K on the standard move mix (no smoothing), the number
    `calib export --to marlin` writes."""
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns.manifest import Manifest

    d, _, mp, _ = scan
    man = Manifest.load(mp)
    truth = {"pa.tau_s": 0.01, "kalico_recip.off_mm": 0.3, "kalico_recip.v_lin_mm_s": 1.0}
    t = print_virtual(man, build_model("pa+kalico_recip", man.printer), truth).table
    t.width_sd_mm[:] = 0.005
    t.width_mm = t.width_mm + 0.005 * np.random.default_rng(5).standard_normal(len(t))
    w = t.save(d / "recip.csv")
    out = d / "recip.json"
    capsys.readouterr()
    rc = main(["fit", str(w), "--manifest", str(mp), "--model", "pa+kalico_recip", "--quiet", "-o", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    tau = doc["derived"]["pressure_advance_s"]["median"]
    k = doc["derived"]["firmware_match"]["k_s"]["median"]
    assert tau == pytest.approx(doc["params"]["pa.tau_s"]["median"], rel=0.01)      # the time constant stays
    assert k > 3 * tau
    assert doc["derived"]["firmware"]["marlin"] == f"M900 K{k:.4f}"
    if doc["trust"]["trustworthy"]:
        assert "the fitted time constant" in text and f"M900 K{k:.4f}" in text
    assert main(["export", str(out), "--to", "marlin", "--force"]) == 0
    assert capsys.readouterr().out.strip() == f"M900 K{k:.4f}"


def test_no_firmware_line_where_nonlinear_dynamics_cannot_be_planned():
    """A printer dict without the planner's limits (a hand-made or old manifest) cannot plan
    the move mix the linear K comes from; tau is then only part of the advance, so no
    firmware line at all (a rendered probe print's fit printed "M900 K0.0471" for a printer
    whose best K is 0.201 s). A linear `pa` fit keeps tau, which cancels it exactly."""
    from calib.commands.fit import firmware_k
    from fit.derived import derived_values

    names = ["pa.tau_s", "kalico_recip.off_mm", "kalico_recip.v_lin_mm_s"]
    S = np.tile([0.047, 0.5, 2.0], (40, 1)) * (1 + 0.01 * np.random.default_rng(0).standard_normal((40, 3)))
    partial = {"name": "probe", "filament_diameter_mm": 1.75, "nozzle_diameter_mm": 0.4}
    d = derived_values(names, S, partial)
    assert d["firmware"]["marlin"].startswith("M900 K0.04")           # tau, before
    out = firmware_k(d, {"model": "pa+kalico_recip", "param_names": names, "samples": S, "profile": partial})
    assert "firmware" not in out and "missing key" in out["firmware_match"]["unavailable"]
    assert out["pressure_advance_s"] == d["pressure_advance_s"]       # the time constant stays
    lin = derived_values(names[:1], S[:, :1], partial)
    assert firmware_k(lin, {"model": "pa", "param_names": names[:1], "samples": S[:, :1],
                            "profile": partial}) == lin
