"""CLI-wide behaviour: every bad input is one line on stderr and exit code 2."""
import pytest

from calib.cli import VERBS, build_parser, main


def test_every_verb_is_registered_with_help():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "verb")
    assert set(sub.choices) == set(VERBS)
    for verb, p in sub.choices.items():
        assert p.description, f"calib {verb} has no description"


@pytest.mark.parametrize("argv", [
    ["fitt"],
    ["pattern", "spiral-step", "--printer", "adventurer3", "--speeds", "abc", "-o", "x.gcode"],
    ["measure"],
    # values that are numbers but no print's: NaN/inf were tracebacks in the pattern builder,
    # a negative seed numpy's traceback, a zero Student-t an optimiser's RuntimeError, and a
    # negative steady time or a zero line were accepted silently
    ["pattern", "spiral-step", "--printer", "adventurer3", "--speeds", "15,nan", "-o", "x.gcode"],
    ["pattern", "spiral-step", "--printer", "adventurer3", "--step-s", "inf", "-o", "x.gcode"],
    ["pattern", "start-stop", "--printer", "adventurer3", "--draw-s", "nan", "-o", "x.gcode"],
    ["pattern", "stop-mid-path", "--printer", "adventurer3", "--steady-s", "-1", "-o", "x.gcode"],
    ["pattern", "retract", "--printer", "adventurer3", "--draw-mm", "0", "-o", "x.gcode"],
    ["simulate", "x.gcode", "--truth", "t.toml", "--seed", "-1"],
    ["simulate", "x.gcode", "--truth", "t.toml", "--tilt", "nan"],
    ["fit", "w.csv", "--manifest", "m.json", "--student-t", "0"],
    ["fit", "w.csv", "--manifest", "m.json", "--seed", "-1"],
    ["fit", "w.csv", "--manifest", "m.json", "--chi2-max", "nan"],
    ["export", "fit.json", "--to", "marlin", "--tool", "-1"],
])
def test_usage_errors_are_one_line(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0] and "--help" in err[0]


def test_corrupt_png_gives_our_line_only(tmp_path, capfd):
    """OpenCV's own decoder warnings (C-level stderr) must not precede our message."""
    bad = tmp_path / "scan.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"not really a png" * 10)
    assert main(["pattern", "spiral-step", "--printer", "adventurer3", "-o", str(tmp_path / "m.gcode")]) == 0
    man = tmp_path / "m.manifest.json"
    capfd.readouterr()
    assert main(["measure", str(bad), "--manifest", str(man), "-o", str(tmp_path / "w.csv")]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "corrupt or truncated PNG" in err[0], err
    assert not (tmp_path / "w.csv").exists()


def test_demo_rejects_unknown_printer_before_any_work(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--printer", "nope", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown printer 'nope'" in err[0]
    assert not out.exists()


def test_report_with_a_12_mp_photo_stays_under_2_mb(tmp_path):
    import numpy as np
    from PIL import Image

    from calib.report import build_report

    rng = np.random.default_rng(0)
    photo = tmp_path / "photo.png"
    Image.fromarray(rng.integers(0, 255, (3000, 4000, 3), dtype=np.uint8)).save(photo)
    html = build_report("t", scan=photo, overlay=photo)
    assert html.count("data:image/jpeg;base64,") == 2
    assert len(html.encode()) < 2_000_000


@pytest.mark.parametrize("field, value", [
    ("samples", [[0.04, "a"]]),
    ("envelope_samples", {"noise": [[0.04], [0.05, 1.0]]}),
])
def test_a_fit_json_with_draws_that_are_not_numbers_is_one_line(tmp_path, capsys, field, value):
    """A hand-edited or truncated fit.json: its draws are read as a table of numbers, and a
    ragged or non-numeric one is refused in one line (it was a ValueError traceback)."""
    import json

    doc = {"schema": "calib.fit/1", "model": "pa", "param_names": ["pa.tau_s"],
           "samples": [[0.04], [0.041]], field: value}
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(doc))
    assert main(["export", str(p), "--to", "marlin", "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a table of numbers" in err[0]


def test_export_of_a_map_only_fit_says_what_it_is(tmp_path, capsys):
    """`calib fit --map-only -o fit.json` writes schema calib.fit-map/1; `calib export` said
    "not a calib fit file; run `calib fit` first" to a user who had just run it."""
    import json

    p = tmp_path / "fit.json"
    p.write_text(json.dumps({"schema": "calib.fit-map/1", "model": "pa", "theta": {"pa.tau_s": 0.04}}))
    assert main(["export", str(p), "--to", "klipper"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a MAP-only fit" in err[0] and "without --map-only" in err[0]


@pytest.mark.parametrize("flag, content, said", [
    ("--fit", b"\xff\xfe\x00not text", "not a readable fit JSON file"),
    ("--compare", b'{"a": 1}', "not a calib compare file"),
    ("--diagnose", b'{"schema": "calib.fit/1", "model": "pa"}', "is a calib.fit/1 file, not a calib diagnose file"),
    ("--fit", b'{"schema": "calib.measure-summary/1"}', "not a calib fit file"),
    ("--scan", b"\x89PNG\r\n\x1a\n" + b"x" * 100, "cannot be read (corrupt, truncated"),
    ("--overlay", b"not an image", "cannot be read (corrupt, truncated"),
])
def test_report_refuses_a_file_of_another_kind_in_one_line(tmp_path, capsys, flag, content, said):
    """`calib report` read its inputs unchecked: JSON bytes that are not UTF-8 gave a
    traceback, a compare/diagnose file of another kind a KeyError, a fit of another kind an
    empty report, silently, and a corrupt scan or overlay image PIL's traceback."""
    p = tmp_path / "x.json"
    p.write_bytes(content)
    out = tmp_path / "r.html"
    assert main(["report", flag, str(p), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0] and not out.exists()


def test_a_layer_higher_than_the_nozzle_is_refused(tmp_path, capsys):
    out = tmp_path / "x.gcode"
    assert main(["pattern", "spiral-step", "--printer", "adventurer3", "--layer-height", "5", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "more than the nozzle's diameter" in err[0] and not out.exists()
