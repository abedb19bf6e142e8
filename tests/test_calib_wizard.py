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


def test_wizard_writes_the_pattern_then_stops_clearly_when_answers_run_out(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    answers = "direct_drive\nsession\nstop-mid-path\nn\n"
    out = io.StringIO()
    with pytest.raises(UserError, match="ran out of answers"):
        run_wizard(inp=io.StringIO(answers), out=out)
    files = sorted(p.name for p in (tmp_path / "session").iterdir())
    assert files == ["stop-mid-path.gcode", "stop-mid-path.manifest.json",
                     "stop-mid-path.preview.png", "stop-mid-path.timeline.npz"]
    text = out.getvalue()
    # every step shows the command a user could type by hand
    assert "$ calib pattern stop-mid-path --printer direct_drive -o session/stop-mid-path.gcode" in text
    assert "path to the photo or scan" in text


def test_wizard_rejects_unknown_printer(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError):
        run_wizard(inp=io.StringIO("no_such_printer\n"), out=io.StringIO())


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
