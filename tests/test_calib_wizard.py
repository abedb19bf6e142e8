"""The wizard's question flow: defaults, re-asking on a bad choice, files written, clear EOF error."""
import io

import pytest

from calib.errors import UserError
from calib.wizard import Asker, run_wizard


def test_asker_defaults_and_reasks_on_bad_choice():
    out = io.StringIO()
    a = Asker(io.StringIO("\nbogus\nretract\n"), out)
    assert a.ask("printer", "adventurer3") == "adventurer3"
    assert a.ask("pattern", "spiral-step", ("spiral-step", "retract")) == "retract"
    assert "please answer one of: spiral-step, retract" in out.getvalue()


@pytest.mark.parametrize("pattern", ["stop-mid-path", "probe"])
def test_wizard_writes_the_pattern_then_stops_clearly_when_answers_run_out(tmp_path, monkeypatch, pattern):
    monkeypatch.chdir(tmp_path)
    answers = f"direct_drive\nsession\n{pattern}\nn\n"
    out = io.StringIO()
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO(answers), out=out)
    files = sorted(p.name for p in (tmp_path / "session").iterdir())
    assert files == sorted(["session.json", f"{pattern}.gcode", f"{pattern}.manifest.json",
                            f"{pattern}.preview.png", f"{pattern}.timeline.npz"])
    text = out.getvalue()
    # every step shows the command a user could type by hand
    assert f"$ calib pattern {pattern} --printer direct_drive -o session/{pattern}.gcode" in text
    assert "path to the photo or scan" in text


def test_wizard_asks_again_after_an_unknown_printer(tmp_path, monkeypatch):
    """A typo in the printer's name said why and ended the session; it is asked again."""
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO("no_such_printer\ndirect_drive\nsession\n"), out=out)
    text = out.getvalue()
    assert "no_such_printer" in text and text.count("? printer profile") == 2
    assert "? folder for the files" in text


def test_wizard_with_a_port_asks_before_heating_and_sends_nothing_on_no(tmp_path, monkeypatch):
    """--port used to start heating and homing without a question; now the user confirms
    that the bed is clear, and 'no' (the default) opens no port at all."""
    import calib.sender

    def no_port(*a, **k):
        raise AssertionError("the printer must not be contacted without a yes")
    monkeypatch.setattr(calib.sender, "open_port", no_port)
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO("direct_drive\nsession\nstop-mid-path\n\n"), out=out,
                   port="/dev/ttyUSB9")
    text = out.getvalue()
    assert "the bed clear and the nozzle clean? start printing now" in text
    assert "not sent: print it when the printer is ready" in text


def test_several_photos_in_one_answer_are_measured_together(tmp_path, monkeypatch):
    """On a textured plate the wizard asks for 3-5 photos with the lamp moved: one answer
    with several paths (quoted where a name has a space) is one `calib measure` of them
    all (measure/stack.py); a path that is no file is said and asked again."""
    import calib.demo

    seen = []
    real_step = calib.demo._Runner.step

    def step(self, title, argv, ok_codes=(0,)):
        if argv[0] == "measure":
            seen.append([str(a) for a in argv])
            raise UserError("stop here")
        return real_step(self, title, argv, ok_codes)
    monkeypatch.setattr(calib.demo._Runner, "step", step)
    monkeypatch.chdir(tmp_path)
    for name in ("a.jpg", "b c.jpg"):
        (tmp_path / name).write_bytes(b"x")
    out = io.StringIO()
    answers = "direct_drive\nsession\nretract\nn\nnope.jpg a.jpg\na.jpg 'b c.jpg'\n"
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO(answers), out=out)
    text = out.getvalue()
    assert "nope.jpg is not a file; try again" in text and "lamp moved" in text
    assert len(seen) == 1 and seen[0][1:3] == ["a.jpg", "b c.jpg"] and seen[0][3] == "--manifest"


def test_a_second_run_resumes_without_rewriting_the_pattern(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO("direct_drive\nsession\nretract\nn\n"), out=io.StringIO())
    gcode = tmp_path / "session" / "retract.gcode"
    stamp = gcode.stat().st_mtime_ns
    out = io.StringIO()
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO("direct_drive\nsession\ny\nn\n"), out=out)
    text = out.getvalue()
    assert "has a session (pattern done): resume it?" in text and "resuming" in text
    assert "$ calib pattern" not in text and "test pattern (" not in text
    assert gcode.stat().st_mtime_ns == stamp
    assert "path to the photo or scan" in text


def test_a_typo_in_the_model_is_asked_again_and_the_virtual_truth_follows_the_printer():
    from calib.demo import _Runner
    from calib.wizard import _ask_model, _virtual_truth
    from patterns.profile import load_profile

    out = io.StringIO()
    prof = load_profile("direct_drive")
    model = _ask_model(Asker(io.StringIO("pa+termal\npa+thermal\n"), out), _Runner(".", out), prof,
                       "auto")
    assert model == "pa+thermal" and "unknown effect" in out.getvalue()
    assert _virtual_truth(prof).name == "direct_drive.toml"
    assert _virtual_truth(load_profile("adventurer3")).name == "bowden.toml"


def test_the_wizard_ends_with_the_exports_the_user_picks(tmp_path, capsys):
    import json

    from calib.demo import _Runner
    from calib.wizard import _exports
    from patterns.profile import load_profile

    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps({
        "schema": "calib.fit/1", "model": "pa", "converged": True,
        "information": {"chi2_nu": 1.0, "rms_mm": 0.01, "n_obs": 500, "loo": {}},
        "params": {"pa.tau_s": {"median": 0.0412, "ci95": [0.04, 0.042]}},
        "priors": {"pa.tau_s": {"kind": "loguniform", "lower": 0.005, "upper": 5.0}},
        "derived": {"pressure_advance_s": {"median": 0.0412}}, "profile": {}, "samples": []}))
    preset = tmp_path / "PLA.json"
    preset.write_text('{"name": "PLA", "pressure_advance": ["0.02"]}')
    out = io.StringIO()
    answers = f"klipper-typo,marlin\nmarlin, orca\n\n{preset}\n"
    _exports(Asker(io.StringIO(answers), out), _Runner(".", out), load_profile("direct_drive"), fit)
    assert "unknown export(s) klipper-typo" in out.getvalue()
    assert "M900 K0.0412" in capsys.readouterr().out
    assert json.loads(preset.read_text())["pressure_advance"] == ["0.0412"]
