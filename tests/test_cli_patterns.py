"""The pattern / plan / preview verbs through calib.cli.main: help texts, the three output
files, one-line exit-2 errors with nothing left behind, and a preview PNG whose pixels sit
where the tracks are."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.cli import main
from patterns.manifest import Manifest
from patterns.profile import data_dir, load_profile
from patterns.preview import FIGSIZE_IN, render_preview_mapped


def _help(capsys, argv) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_help_of_calib_and_each_verb_lists_its_options(capsys):
    top = _help(capsys, ["--help"])
    for verb in ("pattern", "plan", "preview"):
        assert verb in top
    pat = _help(capsys, ["pattern", "--help"])
    for name in ("spiral-step", "stop-mid-path", "retract", "start-stop", "probe"):
        assert name in pat
    opts = {
        ("pattern", "spiral-step"): ("--printer", "--output", "--speeds", "--step-s", "--steps", "--widths",
                                     "--layer-height"),
        ("pattern", "stop-mid-path"): ("--printer", "--speeds", "--tau", "--variants", "--steady-s",
                                       "--wizard-wait-s", "--layer-height"),
        ("pattern", "retract"): ("--designs", "--steps", "--draw-mm", "--restore-mm"),
        ("pattern", "start-stop"): ("--re-mm", "--widths", "--ve", "--layer-height", "--draw-s"),
        ("pattern", "probe"): ("--lines", "--length-mm", "--speeds", "--stops-s", "--max-flow", "--layer-height"),
        ("plan",): ("--printer", "--output", "--layer-height-mm", "--min-test-length-mm"),
        ("preview",): ("--printer", "--output", "--dpi"),
    }
    for argv, names in opts.items():
        text = _help(capsys, [*argv, "--help"])
        missing = [n for n in names if n not in text]
        assert not missing, f"calib {' '.join(argv)} --help lacks {missing}"


@pytest.fixture(scope="module")
def spiral(tmp_path_factory):
    """`calib pattern spiral-step --printer adventurer3 -o x.gcode`, run once."""
    d = tmp_path_factory.mktemp("spiral")
    rc = main(["pattern", "spiral-step", "--printer", "adventurer3", "-o", str(d / "x.gcode")])
    return rc, d


def test_pattern_writes_gcode_manifest_and_timeline(spiral):
    rc, d = spiral
    assert rc == 0
    assert sorted(p.name for p in d.iterdir()) == ["x.gcode", "x.manifest.json", "x.timeline.npz"]
    man = Manifest.load(d / "x.manifest.json")
    assert man.gcode == "x.gcode" and man.pattern["name"] == "spiral-step"
    assert len(man.test_tracks()) == 2 and len(man.fiducials) == 4
    gcode = (d / "x.gcode").read_text()
    assert gcode.count(";TRACK id=") == len(man.tracks)
    # the timeline sidecar is the planned print of this G-code: it ends where E ends
    assert man.timeline.e_mm[-1] > 0 and man.timeline.duration_s == pytest.approx(
        man.pattern["planned_duration_s"], abs=1e-3)


def _bad_profile(tmp_path) -> Path:
    src = (data_dir() / "printers" / "adventurer3.toml").read_text()
    lines = [ln for ln in src.splitlines() if not ln.startswith("nozzle_diameter_mm")]
    p = tmp_path / "bad.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


def _setup_inputs(tmp_path):
    (tmp_path / "notes.gcode").write_text("hello, this is a shopping list\nmilk\n")
    (tmp_path / "photo.gcode").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(64))
    (tmp_path / "afile").write_text("a file where a folder is expected\n")
    (tmp_path / "ok.gcode").write_text("G90\nM83\nG1 Z0.2 F600\nG1 X0 Y0\nG1 X20 Y0 E1 F1200\n")
    _bad_profile(tmp_path)


BAD = {
    "unknown printer": (["pattern", "spiral-step", "--printer", "no_such_printer", "-o", "{d}/x.gcode"],
                        "unknown printer 'no_such_printer'"),
    "profile missing a key": (["pattern", "retract", "--printer", "{d}/bad.toml", "-o", "{d}/x.gcode"],
                              "missing key 'nozzle_diameter_mm'"),
    "pattern too big for the bed": (["pattern", "spiral-step", "--printer", "adventurer3", "--speeds",
                                     "10,15,20,25,30,35,40", "--step-s", "6,8,10", "-o", "{d}/x.gcode"],
                                    "but the bed is"),
    "a pattern Klipper would stop half-way": (["pattern", "spiral-step", "--printer", "direct_drive", "--widths",
                                               "0.4,3.5", "--layer-height", "0.3", "-o", "{d}/x.gcode"],
                                              "Move exceeds maximum extrusion"),
    "text file to plan": (["plan", "{d}/notes.gcode", "--printer", "adventurer3"], "not G-code"),
    "binary file to plan": (["plan", "{d}/photo.gcode", "--printer", "adventurer3"], "not G-code"),
    "text file to preview": (["preview", "{d}/notes.gcode", "--printer", "adventurer3", "-o", "{d}/p.png"],
                             "not G-code"),
    "binary file to preview": (["preview", "{d}/photo.gcode", "--printer", "adventurer3",
                                "-o", "{d}/p.png"], "not G-code"),
    "pattern into a file": (["pattern", "spiral-step", "--printer", "adventurer3", "-o", "{d}/afile/x.gcode"],
                            "afile is a file, not a folder"),
    "plan into a file": (["plan", "{d}/ok.gcode", "--printer", "adventurer3", "-o",
                          "{d}/afile/ok.manifest.json"], "afile is a file, not a folder"),
    "preview into a file": (["preview", "{d}/ok.gcode", "--printer", "adventurer3", "-o", "{d}/afile/p.png"],
                            "afile is a file, not a folder"),
    "preview onto a folder": (["preview", "{d}/ok.gcode", "--printer", "adventurer3", "-o", "{d}"],
                              "that is a folder"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line_exit_2_and_leaves_nothing(case, tmp_path, capsys):
    _setup_inputs(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    argv, expect = BAD[case]
    rc = main([a.replace("{d}", str(tmp_path)) for a in argv])
    out = capsys.readouterr()
    err = out.err.strip()
    assert rc == 2
    assert err.startswith(f"calib {argv[0]}: error: ") and "\n" not in err, err
    assert expect in err and "Traceback" not in out.err + out.out
    assert sorted(p.name for p in tmp_path.rglob("*")) == before, "an output file was left behind"


def test_failed_gcode_write_removes_the_manifest_and_timeline(tmp_path, capsys, monkeypatch):
    """The disk fills up while writing the G-code (the last of the three files): neither the
    G-code nor the manifest/timeline written just before it may stay behind."""
    import calib.fileio

    def full(path, text):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(calib.fileio, "atomic_write_text", full)
    rc = main(["pattern", "spiral-step", "--printer", "adventurer3", "--speeds", "20", "-o",
               str(tmp_path / "x.gcode")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "No space left on device" in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []


def test_preview_png_size_and_track_pixels(spiral, tmp_path, capsys):
    _, d = spiral
    dpi = 100
    png_path = tmp_path / "x.png"
    assert main(["preview", str(d / "x.gcode"), "-o", str(png_path), "--dpi", str(dpi)]) == 0
    img = cv2.imdecode(np.frombuffer(png_path.read_bytes(), np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (FIGSIZE_IN * dpi, FIGSIZE_IN * dpi, 3)

    man = Manifest.load(d / "x.manifest.json")
    prof = load_profile("adventurer3")
    png2, to_px = render_preview_mapped(man, prof, dpi=dpi)
    img2 = cv2.imdecode(np.frombuffer(png2, np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(img, img2)        # the CLI drew the same picture the mapping belongs to

    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    # the highest-flow vertex of the test tracks is drawn in the top colour of viridis (yellow)
    tr = max(man.test_tracks(), key=lambda t: np.max(t.flow_mm3_s))
    k = int(np.argmax(tr.flow_mm3_s))
    u, v = np.round(to_px(tr.points_mm[k])[0]).astype(int)
    patch = img[v - 1:v + 2, u - 1:u + 2].reshape(-1, 3).astype(float)
    yellow_bgr = np.array([37.0, 231.0, 253.0])
    assert np.min(np.linalg.norm(patch - yellow_bgr, axis=1)) < 60, patch
    assert hsv[v - 1:v + 2, u - 1:u + 2, 1].max() > 150          # saturated, not grey/white
    # an empty spot of the bed, 5 mm inside its corner, is background white
    ue, ve = np.round(to_px([prof.bed_x_mm[0] + 5, prof.bed_y_mm[0] + 5])[0]).astype(int)
    assert img[ve, ue].min() > 245
