"""`--model auto` (fit/auto.py) on the gear-slip example (an effect outside the library,
RRF M592-style speed-dependent flow gain; fit/hidden.py). The candidate lists are cut to a
few effects to keep the test short; the rule under test is the stopping rule."""
import json
import tempfile

import pytest

from calib.cli import main
from fit.auto import auto_model
from fit.compare import observe
from fit.effects import load_effects_file
from fit.hidden import EXAMPLES_DIR, make_case
from fit.model import build_model

EFFECTS = str(EXAMPLES_DIR / "my_effects.py")


@pytest.fixture(scope="module")
def case():
    c = make_case("gear_slip", seed=0, ds_mm=0.5)
    return c, observe(c.manifest, c.table), load_effects_file(EFFECTS)


def _build(c, extra):
    return lambda s: build_model(s, c.manifest.printer, extra_effects=extra)


def test_auto_adds_the_effect_that_explains_the_data_and_stops_there(case):
    c, scan, extra = case
    r = auto_model(scan, _build(c, extra), ["thermal", "offset", "flow_gain"], ["gear_slip"])
    assert [s.model for s in r.steps] == ["pa", "pa+gear_slip"]
    assert r.model == "pa+gear_slip"
    assert r.steps[1].delta_bic >= 10 and r.steps[1].chi2_nu < 1.2 < r.steps[0].chi2_nu
    assert r.stop.startswith("the model explains the data")


def test_auto_says_when_no_library_effect_explains_the_rest(case):
    c, scan, _ = case
    r = auto_model(scan, _build(c, ()), ["thermal", "flow_gain", "heading"], [])
    assert r.steps[-1].chi2_nu > 2.0
    assert "no library effect explains the rest" in r.stop
    assert r.top_covariate in {"flow_mm3_s", "extruder_speed_mm_s"}
    assert r.top_covariate in r.stop


def test_model_auto_on_the_cli_prints_the_chain_and_records_it(case, tmp_path, capsys, monkeypatch):
    """The CLI's wiring of the search (user effects file, the chain printed, the model in the
    JSON), over the library cut to the three candidates of the test above: the whole
    library's search took 35 s of the suite and is the bench's (bench_discover_foreign)."""
    from fit import effects

    keep = ("pa", "thermal", "offset", "flow_gain")
    monkeypatch.setattr(effects, "REGISTRY", {k: v for k, v in effects.REGISTRY.items() if k in keep})
    c, _, _ = case
    c.manifest.save(tmp_path / "m.manifest.json")
    c.table.save(tmp_path / "w.csv")
    out = tmp_path / "fit.json"
    assert main(["fit", str(tmp_path / "w.csv"), "--manifest", str(tmp_path / "m.manifest.json"),
                 "--model", "auto", "--effects", EFFECTS, "--map-only", "--quiet", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "model search (--model auto):" in text and "pa+gear_slip" in text
    assert json.loads(out.read_text())["model"] == "pa+gear_slip"


def test_the_final_fit_starts_from_the_chains_optimum_too(case, monkeypatch):
    """The global search alone can miss the optimum the chain found (a foreign back-pressure
    print: chi2_nu_bead 1.85 in the chain, 3.24 after the final fit's own search), so the
    final MAP starts from it as well, and is never worse than the chain's."""
    from calib.commands import fit as cmd
    from fit import effects, sampler

    keep = ("pa", "thermal", "offset", "flow_gain")
    monkeypatch.setattr(effects, "REGISTRY", {k: v for k, v in effects.REGISTRY.items() if k in keep})
    starts = []
    real = sampler.fit_map

    def spy(problem, *a, **kw):
        starts.append((list(problem.param_names), kw.get("x0")))
        return real(problem, *a, **kw)
    monkeypatch.setattr(sampler, "fit_map", spy)
    chains = []
    real_choose = cmd.choose_model
    monkeypatch.setattr(cmd, "choose_model", lambda *a, **kw: chains.append(real_choose(*a, **kw)) or chains[-1])
    c, _, _ = case
    with tempfile.TemporaryDirectory() as d:
        c.manifest.save(f"{d}/m.manifest.json")
        c.table.save(f"{d}/w.csv")
        m, _ = cmd.run_fit([(f"{d}/w.csv", f"{d}/m.manifest.json")], "auto", effects=EFFECTS, map_only=True,
                           progress=False)
    names, x0 = starts[-1]                       # the final fit's call
    assert x0 is not None
    chain = chains[0]
    for n, v in chain.map_values.items():
        assert x0[names.index(n)] == pytest.approx(v)
    assert m.chi2_nu_bead <= chain.steps[-1].chi2_nu_bead * (1 + 1e-6)


def test_a_step_added_from_a_tie_says_so_in_the_chain():
    from fit.auto import AutoResult, AutoStep

    r = AutoResult("pa+kalico_tanh", [AutoStep("pa", 0.03, 7.6, -4600.0),
                                      AutoStep("pa+kalico_tanh", 0.02, 3.0, -4662.0, 61.7, 2.5, ["backlash"])])
    lines = r.lines()
    assert "as good: backlash" in lines[2] and "as good" not in lines[1]
    assert r.to_json()["steps"][1]["tied"] == ["backlash"]


def _fake_diagnose(rounds, top_aliases=()):
    """A stand-in for fit.diagnose.diagnose that returns the given rounds of candidates:
    each round (base (rms_mm, chi2_nu, bic), [(effect, delta_bic, chi2_nu_after), ...]);
    ``top_aliases``: what the print cannot tell from the top covariate, speed_mm_s."""
    from types import SimpleNamespace as NS
    it = iter(rounds)

    def fake(scan, spec, build, library, user, seed=0, base=None, progress=False, priors=None):
        (rms, chi2, bic), cands = next(it)
        b = base or NS(rms_mm=rms, chi2_nu=chi2, bic=bic, chi2_nu_bead=chi2 / 2, map=NS(values={}))
        cs = [NS(effect=e, spec=f"{spec}+{e}", delta_bic=db, chi2_nu_after=c2,
                 fit=NS(rms_mm=rms, chi2_nu=c2, bic=b.bic - db, chi2_nu_bead=c2 / 2, map=NS(values={})))
              for e, db, c2 in cands]
        return NS(base=b, covariates=[NS(name="speed_mm_s", score=0.3)], candidates=cs,
                  best=cs[0].effect if cs else None, tied=[], top_aliases=list(top_aliases))
    return fake


def test_a_nuisance_joins_on_bic_alone_unless_it_raises_the_misfit(monkeypatch):
    """spread (fit/nuisance.py) joins the chain on BIC even where it lowers chi2_nu by
    less than 5 %, but not where it raises it (realdata SpStartStopTest2: +27 BIC with
    chi2_nu 253 -> 267, the noise model re-balancing)."""
    import fit.auto
    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose([
        ((0.244, 252.5, 0.0), [("spread", 27.0, 267.2), ("heading", 5.0, 361.0)])]))
    r = auto_model(None, None, [], [], base_spec="pa+kalico_tanh+backlash")
    assert r.model == "pa+kalico_tanh+backlash" and len(r.steps) == 1
    assert "spread" in r.stop and "raises the reduced chi-square" in r.stop
    assert "no library effect explains the rest" in r.stop

    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose([
        ((0.010, 5.0, 0.0), [("spread", 27.0, 4.9), ("heading", 5.0, 4.0)]),
        ((0.010, 4.9, -27.0), [("heading", 3.0, 4.8)])]))
    r = auto_model(None, None, [], [], base_spec="pa")
    assert [s.model for s in r.steps] == ["pa", "pa+spread"]


def test_a_leader_that_raises_the_misfit_is_said_to_raise_it(monkeypatch):
    """The stop reason says what the BIC's leader did to chi2_nu: realdata StartStopTestPLA1's
    chain stopped on `kalico_tanh` (224.22 -> 231.08) and said it lowered chi2_nu "by less
    than 5 %"."""
    import fit.auto
    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose([
        ((0.30, 224.22, 0.0), [("kalico_tanh", 40.0, 231.08), ("bed_tilt", 8.0, 200.0)])]))
    r = auto_model(None, None, [], [], base_spec="pa+scan_bias+backpressure")
    assert len(r.steps) == 1 and "no library effect explains the rest" in r.stop
    assert "(kalico_tanh) raises the reduced chi-square (224.22 -> 231.08)" in r.stop
    assert "less than 5 %" not in r.stop


def test_a_chain_stopped_by_its_cap_says_when_the_model_still_misfits(monkeypatch):
    """realdata SpStartStopTest2 with the chain tried in session 53: four effects added,
    chi2_nu_bead 106 -> 33, and the stop reason only said "stopped after 4 added effects"."""
    import fit.auto
    rounds = [((0.16, 780.0 - 100 * k, -100.0 * k), [(e, 100.0, 680.0 - 100 * k)])
              for k, e in enumerate(("backpressure", "heading", "nonlinear", "spread", "thermal"))]
    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose(rounds))
    r = auto_model(None, None, [], [], base_spec="pa+scan_bias", max_rounds=4)
    assert len(r.steps) == 5 and r.stop.startswith("stopped after 4 added effects")
    assert "still does not fit" in r.stop and "speed_mm_s" in r.stop

    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose([((0.01, 1.2, 0.0), [("thermal", 30.0, 1.0)]),
                                                             ((0.01, 1.0, -30.0), [("spread", 30.0, 0.9)])]))
    r = auto_model(None, None, [], [], base_spec="pa", max_rounds=1)
    assert r.stop == "stopped after 1 added effects"


def test_the_stop_names_what_the_print_cannot_tell_from_the_covariate(monkeypatch):
    """When the chain stops with a misfit, the covariate it names comes with the ones this
    print cannot tell from it (fit/covariates.py aliases), and the effect is said to depend
    on one of them, not on the first alone."""
    import fit.auto
    rounds = [((0.30, 20.0, 0.0), [("thermal", 4.0, 19.0)])]
    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose(rounds, [("s_mm", 0.86), ("t_s", 0.79)]))
    r = auto_model(None, None, [], [], base_spec="pa")
    assert "line up with speed_mm_s (on this print as well with s_mm (86 %), t_s (79 %))" in r.stop
    assert "depends on one of them" in r.stop
    assert r.to_json()["top_aliases"] == [{"name": "s_mm", "share": 0.86}, {"name": "t_s", "share": 0.79}]
    monkeypatch.setattr(fit.auto, "diagnose", _fake_diagnose(rounds))
    r = auto_model(None, None, [], [], base_spec="pa")
    assert "line up with speed_mm_s, so the missing effect depends on it " in r.stop
