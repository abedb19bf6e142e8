"""A small analytic scene drawer for the measure tests, and checks that it is right.

Tracks are straight segments drawn from their exact distance field (box-filtered edge then
a Gaussian blur in image space, which keeps the half-maximum edge where it is), fiducials
from the ArUco bitmap; the image goes through a measure.camera.Camera (homography and
radial distortion), so the true width of every track is its commanded width.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from measure.camera import Camera
from patterns.manifest import Fiducial, Manifest, Track

MARKER = 12.0   # mm, black border square
CELL = MARKER / 6


def marker_bits(i):
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    return (cv2.aruco.generateImageMarker(d, i, 6) > 127).astype(np.float32)


def scene_manifest(widths=(0.25, 0.4, 0.6, 0.8, 1.2, 1.6), length_mm=60.0, pitch_mm=5.0,
                   with_fiducials=True) -> Manifest:
    """Straight test tracks along x at y = 20, 25, ... with the given widths, a diagonal
    prime line and four fiducials around them."""
    tracks = []
    y0 = 20.0
    for k, w in enumerate(widths):
        y = y0 + k * pitch_mm
        tracks.append(Track(id=k, kind="test", points_mm=[[20, y], [20 + length_mm, y]], width_mm=w,
                            height_mm=0.2, flow_mm3_s=2.0))
    ytop = y0 + (len(widths) - 1) * pitch_mm
    tracks.append(Track(id=len(widths), kind="prime", points_mm=[[20, ytop + 6], [20 + length_mm, ytop + 9]],
                        width_mm=0.5, height_mm=0.2, flow_mm3_s=2.0))
    fids = []
    if with_fiducials:
        x0, x1 = 2.0, 20 + length_mm + 4.0
        ya, yb = 2.0, ytop + 14.0
        for i, (x, y) in enumerate([(x0, yb), (x1, yb), (x1, ya), (x0, ya)]):
            fids.append(Fiducial(id=i, center_mm=(x + MARKER / 2, y + MARKER / 2), size_mm=MARKER,
                                 corners_mm=[[x, y + MARKER], [x + MARKER, y + MARKER], [x + MARKER, y], [x, y]]))
    return Manifest(printer={"name": "synthetic"}, pattern={"name": "synthetic"}, tracks=tracks,
                    fiducials=fids)


def scene_region(man: Manifest, margin=4.0):
    pts = np.concatenate([t.points_mm for t in man.tracks] +
                         [np.asarray(f.corners_mm) for f in man.fiducials])
    lo, hi = pts.min(axis=0) - margin, pts.max(axis=0) + margin
    return (lo[0], lo[1], hi[0], hi[1])


def draw(man: Manifest, cam: Camera, light_on_dark=True, noise=0.01, blur_px=0.8, seed=0,
         uneven=0.0, jpeg_quality=None, missing=None) -> np.ndarray:
    """uint8 gray image of ``man`` seen through ``cam``.

    missing: optional (track_id, s0_mm, s1_mm) stretch left unprinted.
    """
    W, H = cam.image_size
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    xy = cam.unproject(np.column_stack([uu.ravel(), vv.ravel()]))
    ppm = float(np.median(cam.px_per_mm(xy[:: max(1, len(xy) // 500)])))
    cov = np.zeros(len(xy))
    for tr in man.tracks:
        a, b = tr.points_mm[0], tr.points_mm[-1]
        d = b - a
        L = np.hypot(*d)
        tt = np.clip(((xy - a) @ d) / L ** 2, 0, 1)
        # distance to the segment; along the axis the ends are square cut
        along = ((xy - a) @ d) / L
        perp = np.abs(((xy - a) @ np.array([-d[1], d[0]])) / L)
        c = np.clip(0.5 + (tr.width_mm[0] / 2 - perp) * ppm, 0, 1) * np.clip(0.5 + np.minimum(along, L - along) * ppm, 0, 1)
        if missing is not None and missing[0] == tr.id:
            c *= 1 - np.clip(0.5 + np.minimum(along - missing[1], missing[2] - along) * ppm, 0, 1)
        cov = np.maximum(cov, c)
        del tt
    for f in man.fiducials:
        bits = np.pad(marker_bits(f.id), 1, constant_values=1)   # quiet frame
        x0, y0 = np.asarray(f.corners_mm)[3] - CELL            # lower-left of quiet frame
        col = np.floor((xy[:, 0] - x0) / CELL).astype(int)
        row = 7 - np.floor((xy[:, 1] - y0) / CELL).astype(int)
        ins = (col >= 0) & (col < 8) & (row >= 0) & (row < 8)
        cov[ins] = np.maximum(cov[ins], bits[row[ins], col[ins]])
    img = cov.reshape(H, W)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    bg, fg = (0.12, 0.85) if light_on_dark else (0.9, 0.15)
    light = 1.0 + uneven * (uu / W - 0.5) + 0.5 * uneven * (vv / H - 0.5)
    img = (bg + (fg - bg) * img) * light
    img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    out = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    if jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


def flatbed(man, dpi=300, rotation_deg=0.0, mirrored=False):
    return Camera.flatbed(scene_region(man), dpi=dpi, rotation_deg=rotation_deg, mirrored=mirrored)


def phone(man, size=(1600, 1200), tilt=25.0, k1=-0.06, k2=0.02, yaw=10.0):
    return Camera.phone(scene_region(man), image_size=size, tilt_deg=tilt, k1=k1, k2=k2, yaw_deg=yaw)


def test_drawn_markers_decode_at_their_true_corners():
    man = scene_manifest()
    cam = flatbed(man, dpi=300)
    img = draw(man, cam)
    d = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = d.detectMarkers(img)
    assert sorted(ids.ravel().tolist()) == [0, 1, 2, 3]
    for c, i in zip(corners, ids.ravel()):
        truth = cam.project(np.asarray(man.fiducials[i].corners_mm))
        assert np.abs(c.reshape(4, 2) - truth).max() < 1.5   # px, unrefined corners


@pytest.mark.parametrize("w", [0.4, 1.2])
def test_drawn_track_has_its_width_at_half_maximum(w):
    man = scene_manifest(widths=(w,))
    cam = flatbed(man, dpi=600)
    img = draw(man, cam, noise=0).astype(float)
    u, v = cam.project(np.array([[50.0, 20.0]]))[0]
    col = img[:, int(round(u))]
    half = 0.5 * (col.max() + np.median(col))
    above = np.flatnonzero(col[int(v) - 60:int(v) + 60] > half)
    assert (above[-1] - above[0] + 1) / (600 / 25.4 * 1.006) == pytest.approx(w, abs=0.05)


# -- renders through measure.render (the project's renderer), cached across test files ----
import functools


@functools.lru_cache(maxsize=None)
def rendered(kind: str, seed: int = 1, with_fiducials: bool = True):
    """(manifest, Rendered) of the scene: "flat" (400 dpi, turned 20 deg, dark plate),
    "flat-mirror-light" (face down, dark plastic on a light plate), "phone" (25 deg tilt,
    barrel distortion, JPEG 85), "phone-translucent" (light plate, translucent plastic)."""
    from measure.render import render
    man = scene_manifest(with_fiducials=with_fiducials)
    reg = scene_region(man)
    if kind == "flat":
        cam, kw = Camera.flatbed(reg, dpi=400, rotation_deg=20), dict(plate="dark")
    elif kind == "flat-mirror-light":
        cam, kw = Camera.flatbed(reg, dpi=400, mirrored=True), dict(plate="light")
    elif kind == "phone":
        cam, kw = Camera.phone(reg, image_size=(2000, 1500), tilt_deg=25, yaw_deg=5, k1=-0.06, k2=0.01), \
            dict(jpeg_quality=85)
    elif kind == "phone-translucent":
        cam, kw = Camera.phone(reg, image_size=(2000, 1500), tilt_deg=25, yaw_deg=-5, k1=-0.05, k2=0.0), \
            dict(jpeg_quality=85, plate="light", plastic="translucent")
    else:
        raise ValueError(kind)
    return man, render(man, None, cam, seed=seed, **kw)


def gray_of(r):
    return cv2.cvtColor(r.image, cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0


def true_registration_error_mm(reg, r):
    """RMS distance (mm) between the estimated and the true mapping along the test tracks."""
    tr = r.table
    p = np.column_stack([tr.x_mm, tr.y_mm])
    cam = r.camera
    return float(np.sqrt(np.mean((np.hypot(*(reg.project(p) - cam.project(p)).T) / cam.px_per_mm(p)) ** 2)))
