"""Registration without markers and without clicks (measure.autoreg, issue #10 item 3).

Renders of a small spiral-step print (virtual printer, clutter on: plate logos, scratches,
cutting mat) are measured with the markers taken out of the manifest, so the printed
markers are only clutter; the automatic pose must reproduce the true camera. Pictures
of something else are refused in one line with the QA overlay still written. The two
realdata photos (../shared/realdata, beside the clone in CI) must register without
--points.
"""
import copy
import functools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.cli import main

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


@functools.lru_cache(maxsize=None)
def _print():
    from fit.truth import load_truth
    from patterns import spiral_step
    from patterns.profile import data_dir

    _, man = spiral_step.generate("long_bowden", widths_mm=(0.5, 1.0), speeds_mm_s=(20.0,), n_steps=4)[:2]
    spec, values, _ = load_truth(data_dir() / "truths" / "bowden.toml")
    return man, spec, values


def _without_markers(man):
    m = copy.deepcopy(man)
    m.fiducials = []
    m.tracks = [tr for tr in m.tracks if tr.kind != "fiducial"]
    return m


@functools.lru_cache(maxsize=None)
def _scan(camera: str):
    from calib.commands.simulate import simulate_scan
    man, spec, values = _print()
    # phone: every phenomenon of measure/phenomena.py but the 40 % light gradient; with it as
    # well (realism "all") the markerless pose is refused as ambiguous (0.37 vs 0.35), a
    # refusal rather than a wrong pose (the printed markers register that picture)
    realism = "profile,translucent,glare,strings,raster_gaps,grain,logos,defocus,jpeg" if camera == "phone" else None
    r, _ = simulate_scan(man, spec, values, camera, profile=man.printer, dpi=400.0, seed=0, realism=realism)
    return r


@pytest.mark.parametrize("camera", ["flatbed", "flatbed-face-down", "phone"])
def test_automatic_pose_reproduces_the_true_camera(camera, tmp_path):
    """Flatbed 400 dpi turned ~1 deg (and the same scan mirrored: the print laid face
    down); 12 MP phone, 25 deg tilt, barrel distortion, realistic render. Measured: true
    error 5 um (flatbed), 15-17 um (phone; the fiducial registration of the same picture:
    13 um); bead-centre residual < 10 um."""
    from measure.pipeline import measure_scan

    r = _scan(camera.split("-")[0])
    mirrored = camera.endswith("face-down")
    path = tmp_path / "scan.png"
    cv2.imwrite(str(path), r.image[:, ::-1] if mirrored else r.image)
    res = measure_scan(path, _without_markers(_print()[0]))
    reg = res.registration
    assert reg.method.startswith("auto") and reg.n_markers == 0 and reg.mirrored == mirrored
    p = np.column_stack([r.table.x_mm, r.table.y_mm])
    truth = r.camera.project(p)
    if mirrored:
        truth[:, 0] = r.image.shape[1] - 1 - truth[:, 0]
    err = np.hypot(*(reg.project(p) - truth).T) / r.camera.px_per_mm(p)
    assert np.sqrt(np.mean(err ** 2)) <= 0.02
    assert reg.residual_mm <= 0.02 and res.summary["fraction_valid"] > 0.7
    info = res.summary["automatic_registration"]
    assert not info["ambiguous"] and info["score"] > 0.5


def test_parallel_lines_without_markers_are_placed_along_their_lines_by_the_labels(tmp_path):
    """Our retract pattern (8 straight parallel lines; across them only the ruler's
    periodic 1 mm ticks) printed without markers, 400 dpi flatbed: the pose along the
    lines comes from the labels' strokes in the track refinement's layout
    (measure/register.py `_label_anchors`). Without them it sat 0.89 mm off along the
    lines at the 95th percentile (sheared, 0.9 mm at the top); with them 0.039 mm, and the
    along-track sd the measurement reports still covers it."""
    from calib.commands.simulate import simulate_scan
    from fit.truth import load_truth
    from measure.pipeline import measure_scan
    from patterns import retract
    from patterns.profile import data_dir

    man = _without_markers(retract.generate("long_bowden", designs=(3, 4), n_steps=4, restore_mm=1.0)[1])
    spec, values, _ = load_truth(data_dir() / "truths" / "bowden.toml")
    r, _ = simulate_scan(man, spec, values, "flatbed", profile=man.printer, dpi=400.0, seed=0)
    path = tmp_path / "scan.png"
    cv2.imwrite(str(path), r.image)
    res = measure_scan(path, man, max_residual_mm=None)
    reg, t, m = res.registration, res.table, res.measurement
    assert reg.method.startswith("auto")
    ok = t.valid
    q = np.column_stack([t.x_mm, t.y_mm])[ok]
    tan = np.column_stack([-m.ny, m.nx])[ok]
    along = np.sum((reg.unproject(r.camera.project(q)) - q) * tan, axis=1)
    assert np.percentile(np.abs(along), 95) < 0.1
    assert np.all(np.abs(along) < 3 * m.place_sd_mm[ok])


def test_a_picture_of_something_else_is_refused_in_one_line_with_the_overlay(tmp_path, capsys):
    from test_measure_synth import rendered

    d = tmp_path
    _without_markers(_print()[0]).save(d / "spiral.manifest.json")
    # another pattern (straight lines, no markers), and a plate with nothing printed on it
    _, other = rendered("flat", with_fiducials=False)
    cv2.imwrite(str(d / "other.png"), other.image)
    rng = np.random.default_rng(3)
    plate = cv2.GaussianBlur(rng.normal(0.2, 0.05, (1200, 1600)).astype(np.float32), (0, 0), 2.0)
    cv2.imwrite(str(d / "plate.png"), np.clip(plate * 255, 0, 255).astype(np.uint8))
    for name in ("other.png", "plate.png"):
        qa, out = d / f"qa_{name}", d / f"w_{name}.csv"
        rc = main(["measure", str(d / name), "--manifest", str(d / "spiral.manifest.json"), "-o", str(out),
                   "--overlay", str(qa), "--summary", str(d / f"{name}.json")])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1 and not out.exists()
        assert "automatic registration" in err and str(qa) in err and qa.stat().st_size > 1000
        assert json.loads((d / f"{name}.json").read_text())["refused"]


@pytest.mark.skipif(not REALDATA.is_dir(), reason="../shared/realdata not present")
@pytest.mark.parametrize("photo, gcode, max_residual_mm, along_sd_mm", [
    # measured 0.015 mm, 78 % valid, ~23 s (the whole measurement); a spiral
    ("SpStartStopTest2.jpg", "SpStartStopTest2_Te210Tp50Fe10Fc10Kf04Kb10Re15R.g", 0.05, (0.0, 0.05)),
    # measured 0.061 mm, 65 % valid, ~40 s: the printer put this print's tracks -0.13..+0.24 mm
    # off their lines (5-95 %; the same G-code line's 1 mm/s and 20-100 mm/s sections sit
    # 0.05-0.16 mm apart), which no map of the bed onto the picture can follow; the beads
    # lie within 0.018 mm of their own track's line (measure/placement.py); issue #10 asks 0.05.
    # Straight parallel lines: the pose along them is held only by the tracks across them;
    # its along-track sd says so (0.076 mm median since the strips are despeckled and 356
    # stations across the lines are valid, 0.36-0.46 mm with 167; 1 LSB of noise moved the
    # stations 0.004-0.019 mm along their lines, 0.1-0.5 mm before), where the spiral's says
    # 0.014 mm (its stations moved 2-5 um). Since partial reads off their track's line are
    # flagged (measure/widths.py OFF_PATH, session 44) the stations across the lines agree
    # better and it says 0.025 mm, within those 1-LSB moves
    ("StartStopTestPLA1.jpg", "StartStopTestPLA1_Kf10_Kb20_Re10_RPv.g", 0.09, (0.01, 0.5)),
])
def test_realdata_photos_register_without_points(photo, gcode, max_residual_mm, along_sd_mm, tmp_path):
    from measure.pipeline import measure_scan
    from patterns.manifest import Manifest

    # planned as a user would (README): the prime line and closed loops are not test tracks
    assert main(["plan", str(REALDATA / gcode), "--printer", "adventurer3", "-o", str(tmp_path / "m.json")]) == 0
    res = measure_scan(REALDATA / photo, Manifest.load(tmp_path / "m.json"), max_residual_mm=None)
    reg = res.registration
    assert reg.method.startswith("auto") and not res.summary["automatic_registration"]["ambiguous"]
    assert reg.residual_mm <= max_residual_mm
    # what is left once each track's own placement is taken out is the pose's (and the edge
    # fit's) error: 0.013 and 0.021 mm measured
    assert res.placement.within_track_mm <= 0.05
    assert res.summary["fraction_valid"] > 0.35
    along_sd = res.summary["registration"]["along_track_sd_mm"]
    assert along_sd_mm[0] <= along_sd < along_sd_mm[1]
    # a user is told when the pose holds the stations along their lines only loosely
    assert any("along their lines only to" in w for w in res.summary["warnings"]) == (along_sd >= 0.05)
    # StartStopTestPLA1 lies over the plate's FLASHFORGE and CAUTION print (10 % of its
    # stations 'background'): the user is told
    if photo.startswith("StartStopTestPLA1"):
        assert any("other than the bare plate beside the bead" in w for w in res.summary["warnings"])
