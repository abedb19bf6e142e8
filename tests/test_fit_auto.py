"""`--model auto` (fit/auto.py) on the gear-slip example (an effect outside the library,
RRF M592-style speed-dependent flow gain; fit/hidden.py). The candidate lists are cut to a
few effects to keep the test short; the rule under test is the stopping rule."""
import json

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


def test_model_auto_on_the_cli_prints_the_chain_and_records_it(case, tmp_path, capsys):
    c, _, _ = case
    c.manifest.save(tmp_path / "m.manifest.json")
    c.table.save(tmp_path / "w.csv")
    out = tmp_path / "fit.json"
    assert main(["fit", str(tmp_path / "w.csv"), "--manifest", str(tmp_path / "m.manifest.json"),
                 "--model", "auto", "--effects", EFFECTS, "--map-only", "--quiet", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "model search (--model auto):" in text and "pa+gear_slip" in text
    assert json.loads(out.read_text())["model"] == "pa+gear_slip"


def test_a_step_added_from_a_tie_says_so_in_the_chain():
    from fit.auto import AutoResult, AutoStep

    r = AutoResult("pa+kalico_tanh", [AutoStep("pa", 0.03, 7.6, -4600.0),
                                      AutoStep("pa+kalico_tanh", 0.02, 3.0, -4662.0, 61.7, 2.5, ["backlash"])])
    lines = r.lines()
    assert "as good: backlash" in lines[2] and "as good" not in lines[1]
    assert r.to_json()["steps"][1]["tied"] == ["backlash"]
