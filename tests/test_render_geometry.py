"""Renderer ground truth: the rendered bead, measured directly on the image through the
true camera, has the truth width; fiducials decode at their projected corners; the camera
model inverts exactly; the truth sidecar round-trips."""
import cv2
import numpy as np
import pytest

from calib.errors import UserError
from measure.camera import Camera, distort_px, undistort_px
from measure.render import half_contrast_widths, render
from measure.table import WidthTable
from measure.truth_io import load_scan_truth, save_scan_truth
from patterns.manifest import Fiducial, Manifest, Track

WIDTHS_MM = (0.25, 0.4, 0.8, 1.6)
SIDE_MM = 50.0


def toy_manifest(widths=WIDTHS_MM, side=SIDE_MM, cell=1.5):
    """Four slightly slanted straight test tracks and four ArUco markers drawn as cells."""
    tracks = [Track(id=i, kind="test", points_mm=[[15, 16 + i * 6], [side - 15, 16.7 + i * 6]],
                    width_mm=w, height_mm=0.2, flow_mm3_s=1.0) for i, w in enumerate(widths)]
    size = 6 * cell
    fids = []
    for k, (ox, oy) in enumerate([(2, 2), (side - 2 - 8 * cell, 2), (side - 2 - 8 * cell, side - 2 - 8 * cell),
                                  (2, side - 2 - 8 * cell)]):
        bx, by = ox + cell, oy + cell
        fids.append(Fiducial(id=k, center_mm=(bx + size / 2, by + size / 2), size_mm=size,
                             corners_mm=[[bx, by + size], [bx + size, by + size], [bx + size, by], [bx, by]]))
    return Manifest(printer={}, pattern={"name": "toy"}, tracks=tracks, fiducials=fids)


def measure_half_contrast(rendered, manifest):
    """(truth_mm, measured_mm): half-contrast width across each station along the true normal."""
    _, _, truth, meas = half_contrast_widths(rendered, manifest)
    assert np.isfinite(meas).all()
    return truth, meas


@pytest.fixture(scope="module")
def manifest():
    return toy_manifest()


@pytest.fixture(scope="module")
def flatbed():
    return Camera.flatbed((0, 0, SIDE_MM, SIDE_MM), 600, rotation_deg=3.0)


@pytest.fixture(scope="module")
def phone():
    # ~21 px/mm on the pattern, as a 12 MP photo of a 120 mm pattern at 25 deg tilt
    return Camera.phone((0, 0, SIDE_MM, SIDE_MM), image_size=(1800, 1350), tilt_deg=25, fill=0.9)


# -- camera ----------------------------------------------------------------------------
def test_camera_round_trip_and_jacobian(phone, flatbed):
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, SIDE_MM, (200, 2))
    for cam in (phone, flatbed, Camera.flatbed((0, 0, 50, 50), 300, mirrored=True)):
        np.testing.assert_allclose(cam.unproject(cam.project(xy)), xy, atol=1e-9)
        e = 1e-5
        num = np.stack([(cam.project(xy + [e, 0]) - cam.project(xy - [e, 0])) / (2 * e),
                        (cam.project(xy + [0, e]) - cam.project(xy - [0, e])) / (2 * e)], axis=-1)
        np.testing.assert_allclose(cam.jacobian(xy), num, atol=1e-5)
    uv = rng.uniform(0, 4000, (100, 2))
    back = undistort_px(distort_px(uv, (2000, 1500), 2900, -0.08, 0.03), (2000, 1500), 2900, -0.08, 0.03)
    np.testing.assert_allclose(back, uv, atol=1e-8)


def test_compiled_projection_matches_the_written_formulas():
    """measure/camera.py maps (N, 2) points with compiled kernels (speed); they must give the
    module docstring's formulas to the last bit, or a registration's numerical derivatives
    move (they did by 2 um when the formulas were only reordered)."""
    from measure.camera import apply_homography
    rng = np.random.default_rng(1)
    uv = rng.uniform(-100, 4100, (500, 2))
    c, f, k1, k2 = (2010.5, 1497.25), 2900.0, -0.08, 0.03
    n = (uv - c) / f
    r2 = n[:, 0] ** 2 + n[:, 1] ** 2
    ref = c + n * (f * (1 + r2 * (k1 + k2 * r2)))[:, None]
    np.testing.assert_allclose(distort_px(uv, c, f, k1, k2), ref, rtol=0, atol=1e-9)
    # the (..., 2) form still takes the numpy path: the same numbers
    np.testing.assert_array_equal(distort_px(uv[None], c, f, k1, k2)[0], distort_px(uv, c, f, k1, k2))
    H = np.array([[11.8, 0.9, 310.0], [-0.4, -12.1, 2800.0], [1e-4, -2e-4, 1.0]])
    xy = rng.uniform(0, 220, (500, 2))
    h = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    np.testing.assert_allclose(apply_homography(H, xy), h[:, :2] / h[:, 2:], rtol=1e-14)


def test_flatbed_scale_orientation_and_mirror():
    cam = Camera.flatbed((0, 0, 100, 50), 600, scale_error=(0.006, -0.002))
    J = cam.jacobian([[50, 25]])[0]
    # 600 dpi = 23.622 px/mm with the scanner's axis scale error; +y is up (v falls)
    assert J[0, 0] == pytest.approx(600 / 25.4 * 1.006, rel=1e-12)
    assert J[1, 1] == pytest.approx(-600 / 25.4 * 0.998, rel=1e-12)
    mir = Camera.flatbed((0, 0, 100, 50), 600, mirrored=True)
    assert mir.jacobian([[50, 25]])[0, 0, 0] < 0
    with pytest.raises(UserError, match="outside 300-1200"):
        Camera.flatbed((0, 0, 10, 10), 200)


def test_phone_tilt_makes_near_side_larger():
    cam = Camera.phone((0, 0, 120, 120), tilt_deg=25)
    assert cam.image_size == (4000, 3000)
    # camera stands at the front (-y): the front edge is closer, so more px per mm
    front, back = cam.px_per_mm([[60, 0], [60, 120]])
    assert front > 1.3 * back
    uv = cam.project([[0, 0], [120, 120]])
    assert (uv >= 0).all() and (uv[:, 0] < 4000).all() and (uv[:, 1] < 3000).all()


# -- width truth -------------------------------------------------------------------------
@pytest.mark.parametrize("plate", ["dark", "light"])
def test_flatbed_600dpi_widths_match_truth(manifest, flatbed, plate):
    r = render(manifest, None, flatbed, plate=plate, seed=3)
    truth, meas = measure_half_contrast(r, manifest)
    err_um = (meas - truth) * 1000
    for w in WIDTHS_MM:
        e = err_um[truth == w]
        assert abs(e.mean()) < 2.0, (w, e.mean())    # bias per width, um
        assert e.std() < 5.0
    assert np.sqrt(np.mean(err_um ** 2)) < 4.0


@pytest.mark.parametrize("plate,plastic", [("dark", "translucent"), ("light", "opaque")])
def test_phone_widths_match_truth(manifest, phone, plate, plastic):
    r = render(manifest, None, phone, plate=plate, plastic=plastic, seed=4, jpeg_quality=85)
    truth, meas = measure_half_contrast(r, manifest)
    err_um = (meas - truth) * 1000
    assert np.sqrt(np.mean(err_um ** 2)) < 12.0
    for w in WIDTHS_MM[1:]:
        assert abs(err_um[truth == w].mean()) < 3.0
    # the narrowest bead is only ~2.5 blur sigmas wide: half-max reads slightly wide
    assert 0 < err_um[truth == 0.25].mean() < 12.0


def test_varying_width_follows_the_table(flatbed):
    """A width ramp from the table (not the commanded width) is what gets drawn."""
    tr = Track(id=7, kind="test", points_mm=[[12, 25], [38, 25]], width_mm=0.5, height_mm=0.2, flow_mm3_s=1)
    m = Manifest(printer={}, pattern={}, tracks=[tr])
    s = np.arange(0, 26.0001, 0.25)
    w = 0.3 + 0.9 * s / 26
    n = len(s)
    table = WidthTable(track=np.full(n, 7), s_mm=s, x_mm=12 + s, y_mm=np.full(n, 25.0), t_s=s / 50,
                       width_mm=w, width_sd_mm=np.zeros(n), valid=np.ones(n))
    r = render(m, table, flatbed, seed=5, noise=0.0, clutter=False)
    truth, meas = measure_half_contrast(r, m)
    np.testing.assert_allclose(r.table.width_mm, w)
    assert np.abs(meas - truth).max() < 0.006
    assert np.polyfit(truth, meas, 1)[0] == pytest.approx(1.0, abs=0.01)


# -- fiducials ---------------------------------------------------------------------------
def _detect(image, inverted):
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.detectInvertedMarker = inverted
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), p)
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    return {} if ids is None else {int(i): c[0] for c, i in zip(corners, ids.ravel())}


@pytest.mark.parametrize("plate,camera_name", [("dark", "flatbed"), ("light", "phone")])
def test_fiducials_decode_at_projected_corners(manifest, request, plate, camera_name):
    cam = request.getfixturevalue(camera_name)
    r = render(manifest, None, cam, plate=plate, seed=6,
               jpeg_quality=85 if camera_name == "phone" else None)
    found = _detect(r.image, inverted=(plate == "light"))
    assert sorted(found) == [0, 1, 2, 3]
    for fd in manifest.fiducials:
        err = np.abs(found[fd.id] - cam.project(fd.corners_mm))
        assert err.max() < 0.5, (fd.id, err.max())
    # a light-plate (dark plastic) print does not read as a normal marker
    if plate == "light":
        assert _detect(r.image, inverted=False) == {}


# -- truth sidecar -----------------------------------------------------------------------
def test_truth_json_round_trip(tmp_path, manifest, phone):
    r = render(manifest, None, phone, seed=7, model={"spec": "pa", "values": {"pa.tau_s": 0.42}})
    r.truth.image = "SCAN.png"
    path = save_scan_truth(tmp_path / "SCAN.truth.json", r.truth)
    back = load_scan_truth(path)
    np.testing.assert_allclose(back.camera.H, phone.H, rtol=1e-12)
    assert (back.camera.k1, back.camera.k2, back.camera.image_size) == (phone.k1, phone.k2, phone.image_size)
    np.testing.assert_allclose(back.widths.width_mm, r.table.width_mm, atol=1e-7)
    np.testing.assert_array_equal(back.widths.track, r.table.track)
    assert back.values == {"pa.tau_s": 0.42} and back.model_spec == "pa"
    assert back.settings["plate"] == "dark" and back.image == "SCAN.png"
    xy = np.array([[10.0, 20.0]])
    np.testing.assert_allclose(back.camera.project(xy), phone.project(xy), atol=1e-9)
    (tmp_path / "bad.json").write_text('{"schema": "other"}')
    with pytest.raises(UserError, match="not a calib scan truth file"):
        load_scan_truth(tmp_path / "bad.json")
    with pytest.raises(UserError, match="does not exist"):
        load_scan_truth(tmp_path / "missing.json")


def test_a_bending_width_is_drawn_along_its_curve_not_the_stations_chords():
    """Station widths of a decay w = 0.4 + 0.5 exp(-s / 0.8) mm every 0.25 mm: between the
    stations the bead is drawn along the monotone cubic through them (within 1 um of the
    decay), not along their chords (up to 4 um above it); a straight run stays linear, and
    a width falling to zero does not overshoot."""
    from measure.render import _curved_spans, _station_curve

    s = np.arange(0.0, 6.01, 0.25)
    w = 0.4 + 0.5 * np.exp(-s / 0.8)
    tab = (s, w)
    curve = _curved_spans(s, w)
    x = np.linspace(0.0, 6.0, 601)
    truth = 0.4 + 0.5 * np.exp(-x / 0.8)
    drawn = _station_curve(x, tab, curve)
    chords = np.interp(x, s, w)
    assert np.max(np.abs(drawn - truth)) < 0.001
    assert np.max(chords - truth) > 0.003
    flat = np.full(len(s), 0.45)
    assert _curved_spans(s, flat) is None
    np.testing.assert_allclose(_station_curve(x, (s, flat), None), 0.45)
    stop = np.where(s < 3.0, 0.5, 0.0)
    ws = _station_curve(x, (s, stop), _curved_spans(s, stop))
    assert ws.max() <= 0.5 + 1e-12 and ws.min() >= 0.0
