"""`calib simulate`: virtual print -> picture + truth sidecar; bad input -> one-line error, exit 2."""
import cv2
import numpy as np
import pytest

from calib.cli import main
from measure.truth_io import load_scan_truth
from patterns.manifest import Manifest

pytest.importorskip("fit.virtual")
pytest.importorskip("patterns.spiral_step")

TRUTH = "data/truths/direct_drive.toml"


@pytest.fixture(scope="module")
def small_pattern(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    gcode = d / "small.gcode"
    assert main(["pattern", "spiral-step", "--printer", "direct_drive", "--speeds", "20", "--step-s", "1",
                 "--steps", "3", "-o", str(gcode)]) == 0
    return gcode


def test_simulate_writes_scan_and_truth(small_pattern, tmp_path):
    from fit.model import build_model
    from fit.truth import load_truth
    from fit.virtual import print_virtual

    out = tmp_path / "scan.png"
    assert main(["simulate", str(small_pattern), "--truth", TRUTH, "--dpi", "300", "--seed", "3",
                 "-o", str(out), "--plot"]) == 0
    truth = load_scan_truth(tmp_path / "scan.truth.json")
    img = cv2.imread(str(out))
    assert (img.shape[1], img.shape[0]) == truth.camera.image_size
    assert truth.image == "scan.png" and truth.settings["seed"] == 3
    # the sidecar holds the virtual printer's widths for these truth values
    m = Manifest.load(small_pattern.with_name("small.manifest.json"))
    spec, values, _ = load_truth(TRUTH, m.printer)
    vp = print_virtual(m, build_model(spec, m.printer), values)
    np.testing.assert_allclose(truth.widths.width_mm, vp.table.width_mm, atol=1e-6)
    assert truth.model_spec == spec and truth.values == pytest.approx(values)
    # the fiducials sit where the true homography puts them (300 dpi: ~12 px/mm)
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), p)
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    assert ids is not None and len(ids) == len(m.fiducials)
    for c, i in zip(corners, ids.ravel()):
        fd = next(f for f in m.fiducials if f.id == i)
        assert np.abs(c[0] - truth.camera.project(fd.corners_mm)).max() < 0.7
    assert cv2.imread(str(tmp_path / "scan.widths.png")) is not None


@pytest.mark.parametrize("args,message", [
    (["--truth", "missing.toml"], "truth file missing.toml does not exist"),
    (["--truth", TRUTH, "--dpi", "200"], "--dpi 200 is outside 300-1200"),
    (["--truth", TRUTH, "--camera", "phone", "--tilt", "60"], "--tilt 60 is outside 0-45"),
    (["--truth", TRUTH, "-o", "scan.bmp"], "use a .png, .tif or .jpg"),
    (["--truth", "BAD_EFFECT"], "unknown effect"),
])
def test_bad_input_is_one_line_exit_2(small_pattern, tmp_path, capsys, args, message):
    if "BAD_EFFECT" in args:
        bad = tmp_path / "bad.toml"
        bad.write_text('[model]\neffects = ["pa", "warp_drive"]\n')
        args = [str(bad) if a == "BAD_EFFECT" else a for a in args]
    if "-o" not in args:
        args = args + ["-o", str(tmp_path / "x.png")]
    assert main(["simulate", str(small_pattern)] + args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err.lower() or message in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "x.png").exists()


def test_missing_manifest_needs_printer(tmp_path, capsys):
    g = tmp_path / "third_party.gcode"
    g.write_text("G1 X10 Y10 E1\n")
    assert main(["simulate", str(g), "--truth", TRUTH]) == 2
    assert "no manifest third_party.manifest.json" in capsys.readouterr().err
