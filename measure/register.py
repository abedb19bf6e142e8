"""Registration: the mapping from bed mm to image px for one scan or photo.

The mapping is the one of :mod:`measure.camera` (homography H then radial distortion
k1, k2 about the image centre, OpenCV convention), estimated in three steps:

1. Start: the ArUco DICT_4X4_50 fiducials (docs/ARCHITECTURE.md "Fiducials"), corners
   refined with CORNER_REFINE_APRILTAG (0.05 px on renders, shared/REFERENCE.md), give
   point pairs bed corner -> image corner and H by RANSAC (``cv2.findHomography``).
   Normal markers (light plastic on a dark plate) and inverted ones (dark on light) are
   both accepted; the mirrored image is tried for a print scanned face down. Without
   fiducials the user's ``--points`` pairs give the start instead, or a pose found
   automatically from the track layout (``start_H``, measure.autoreg).
2. Refinement by the track layout: the manifest's tracks drawn through the mapping must
   lie on the ridge of a "track-likeness" image D (local contrast, polarity folded in,
   Gaussian-blurred at a coarse-to-fine ladder of scales). ``scipy.optimize.least_squares``
   (soft-L1 loss) updates the 8 homography entries and k1, k2 to maximise D along the
   projected centrelines, together with the marker corners (sd 0.3 px) and point hints
   (weak, sd ~1 % of the image) as extra residuals.
3. Residual: RMS of the marker corner misfit in mm (fiducials), or of the track-centre
   offsets found by the edge-pair fit (points only).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage, optimize

from calib.errors import UserError
from measure.camera import PHONE_FOCAL_FRACTION, Camera, apply_homography, distort_px

#: Corner misfit (px) above which a marker corner is an outlier in RANSAC.
RANSAC_PX = 4.0
#: Below this robust z (clarity) the tracks' polarity test gives way to the markers' (they
#: were found in the plain or in the negative image); 0.1-0.5 on the 600 dpi spiral renders.
POLARITY_CLEAR = 2.0
#: Spread of the image scale over the print (max / min - 1) above which the picture is
#: a photo whose lens distortion is estimated (a flatbed scan: < 1e-3)
PERSPECTIVE = 0.02
#: RMS corner misfit (px) of a detected marker, after the fit with the others, above which
#: its corners are taken again from the alignment of its whole pattern (well-detected
#: markers on the phone renders: 0.06-0.5 px)
SUSPECT_PX = 1.0
#: Offset of AprilTag-refined ArUco corners from the pixel-centre convention (px).
APRILTAG_OFFSET_PX = 0.5


class FiducialsNotFound(UserError):
    """Fewer than two of the manifest's fiducials were found, or those found do not fit one
    plane mapping (markers of the same ids where another pattern puts them): the caller may
    fall back to the automatic registration (measure.autoreg), which places the tracks
    themselves or refuses with the QA overlay of its best pose."""


@dataclass
class Registration:
    """Bed mm -> image px for one image, and how good it is.

    H              3x3 bed mm -> undistorted px
    distortion     {"center_px": (cx, cy), "f_px": f, "k1": k1, "k2": k2} (measure.camera)
    residual_mm    registration residual (mm): RMS marker-corner misfit, or RMS track
                   offset when registered from point hints
    n_markers      fiducials used
    mirrored       image is a mirror view of the bed (print scanned face down)
    method         "fiducials", "points" or "auto" (+ "+tracks" when the layout refinement ran)
    polarity       +1 light plastic on a dark plate, -1 dark on light
    """

    H: np.ndarray
    distortion: dict
    residual_mm: float
    n_markers: int
    mirrored: bool
    method: str
    image_size: tuple[int, int] = (0, 0)
    polarity: float = 1.0
    marker_ids: list = field(default_factory=list)
    marker_corners_px: list = field(default_factory=list)
    track_offset_rms_mm: float = float("nan")
    marker_bleed: tuple = (0.0, 0.0)
    corner_rms_px: float = float("nan")
    warnings: list = field(default_factory=list)
    track_score: float = float("nan")      # mean saturated track-likeness after refinement (0..1)
    info: dict = field(default_factory=dict)   # how an automatic pose was found (measure.autoreg)
    recovered_markers: list = field(default_factory=list)   # ids found by measure.fiducial_search
    #: how well the pose fixes where each bed point is (:func:`place_covariance`): bed
    #: points (K, 2) mm and the covariance (K, 2, 2) mm^2 of the bed point a pixel shows
    place_pts_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    place_cov_mm2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))

    @property
    def camera(self) -> Camera:
        d = self.distortion
        return Camera(H=self.H, image_size=self.image_size, center_px=tuple(d["center_px"]),
                      f_px=float(d["f_px"]), k1=float(d["k1"]), k2=float(d["k2"]),
                      mirrored=self.mirrored, kind="registered")

    def project(self, xy_mm) -> np.ndarray:
        """Bed points (N, 2) mm -> image px (N, 2)."""
        return self.camera.project(xy_mm)

    def unproject(self, uv_px) -> np.ndarray:
        return self.camera.unproject(uv_px)

    def px_per_mm(self, xy_mm) -> np.ndarray:
        return self.camera.px_per_mm(xy_mm)

    def place_sd_mm(self, xy_mm, direction) -> np.ndarray:
        """One-sigma uncertainty (mm) of the bed position the registration gives the points
        ``xy_mm`` (N, 2), along the unit ``direction`` (N, 2) (a track's tangent: the
        along-track error of a station). 0 where the pose's uncertainty is not known
        (refinement not run)."""
        xy = np.asarray(xy_mm, float).reshape(-1, 2)
        if len(self.place_pts_mm) == 0 or len(xy) == 0:
            return np.zeros(len(xy))
        from scipy.spatial import cKDTree
        _, j = cKDTree(self.place_pts_mm).query(xy)
        d = np.asarray(direction, float).reshape(-1, 2)
        return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", d, self.place_cov_mm2[j], d), 0.0))

    def to_dict(self) -> dict:
        return {"H_mm_to_px": np.asarray(self.H).tolist(),
                "distortion": {k: (list(map(float, v)) if k == "center_px" else float(v))
                               for k, v in self.distortion.items()},
                "residual_mm": float(self.residual_mm), "n_markers": int(self.n_markers),
                "mirrored": bool(self.mirrored), "method": self.method,
                "polarity": "light-on-dark" if self.polarity > 0 else "dark-on-light",
                "marker_ids": [int(i) for i in self.marker_ids],
                "track_offset_rms_mm": float(self.track_offset_rms_mm),
                "corner_rms_px": float(self.corner_rms_px),
                "recovered_markers": [int(i) for i in self.recovered_markers]}


# -- point hints --------------------------------------------------------------------------
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_PAIR = re.compile(rf"^\s*({_NUM})\s*,\s*({_NUM})\s*=\s*({_NUM})\s*,\s*({_NUM})\s*$")


def parse_points(text: str) -> tuple[np.ndarray, np.ndarray]:
    """``"x_mm,y_mm=u_px,v_px;..."`` -> (bed mm (N, 2), image px (N, 2)); N >= 4 required."""
    pairs = [p for p in str(text).split(";") if p.strip()]
    bed, img = [], []
    for p in pairs:
        m = _PAIR.match(p)
        if not m:
            raise UserError(f"--points: cannot read {p.strip()!r}; write pairs as "
                            "\"x_mm,y_mm=u_px,v_px;...\" (bed mm = image pixel)")
        x, y, u, v = map(float, m.groups())
        bed.append((x, y))
        img.append((u, v))
    if len(bed) < 4:
        raise UserError(f"--points: {len(bed)} point pair(s) given, at least 4 are needed "
                        "(e.g. the four corners of the pattern)")
    bed, img = np.array(bed), np.array(img)
    if _area(bed) < 1e-6 * max(1.0, np.ptp(bed, axis=0).prod()) or np.ptp(bed, axis=0).min() == 0:
        raise UserError("--points: the bed points are (nearly) on one line; pick points spread over the pattern")
    return bed, img


def _area(p):
    hull = cv2.convexHull(p.astype(np.float32))
    return float(cv2.contourArea(hull))


# -- fiducials ----------------------------------------------------------------------------
def detect_markers(gray, *, with_negative: bool = False):
    """ArUco DICT_4X4_50 markers in a gray image: (ids, corners (4, 2) px each), and with
    ``with_negative`` a third list: whether each was found in the negative image (its
    printed cells darker than the plate: dark plastic on a light plate).

    Dark plastic on a light plate gives inverted markers; ``detectInvertedMarker`` finds
    them with corners off by up to 2 px when the printed quiet frame is present, so the
    negative image is searched instead. Big images are searched at <= 1600 px and each marker is then re-detected in a
    full-resolution crop with AprilTag corner refinement (0.05 px, shared/REFERENCE.md),
    whose output is offset by (+0.5, +0.5) px from OpenCV's pixel-centre convention; we
    remove that offset.
    """
    g8 = _to_u8(gray)
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    fast = cv2.aruco.DetectorParameters()
    fine = cv2.aruco.DetectorParameters()
    fine.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    k = max(1.0, max(g8.shape) / 1600.0)
    small = g8 if k == 1.0 else cv2.resize(g8, (round(g8.shape[1] / k), round(g8.shape[0] / k)),
                                           interpolation=cv2.INTER_AREA)
    found: dict[int, np.ndarray] = {}
    negative: dict[int, bool] = {}
    # plain first; then with plate grain smoothed away (textured PEI on a light plate with
    # translucent plastic, measure/phenomena.py "grain": 0-2 of 4 markers found plain, all
    # four after a 3-5 px median at the search scale)
    for median_px in (0, 3, 5):
        img0 = cv2.medianBlur(small, median_px) if median_px else small
        for neg in (False, True):
            img = 255 - img0 if neg else img0
            corners, ids, _ = cv2.aruco.ArucoDetector(d, fast).detectMarkers(img)
            if ids is None:
                continue
            for i, c in zip(ids.ravel(), corners):
                if int(i) in found:
                    continue
                c = c.reshape(4, 2).astype(float) * k
                # the corners found at the search scale sit ~0.4 mm inside the printed
                # border: a marker whose crop fails plain is tried again through a median
                # (strings and grain: 2 of 3 markers of one render fell back to the search
                # corners, read 6 % small, and the registration was 13 % off in scale)
                own = (2 * int(round(median_px * k / 2)) + 1) if median_px else 0
                refined = None
                for med in dict.fromkeys((own, 5, 7)):
                    refined = _refine_in_crop(g8, c, int(i), neg, cv2.aruco.ArucoDetector(d, fine), median_px=med)
                    if refined is not None:
                        break
                found[int(i)] = refined if refined is not None else c
                negative[int(i)] = neg
            if len(found) >= 4:
                break
        if len(found) >= 4:
            break
    ids = sorted(found)
    if with_negative:
        return ids, [found[i] for i in ids], [negative[i] for i in ids]
    return ids, [found[i] for i in ids]


def _refine_in_crop(g8, approx, marker_id, negative, detector, median_px: int = 0):
    """Re-detect marker ``marker_id`` in a full-resolution crop around ``approx`` corners
    (median-filtered over ``median_px`` when it was found that way)."""
    size = np.ptp(approx, axis=0).max()
    lo = np.maximum(np.floor(approx.min(axis=0) - 0.5 * size), 0).astype(int)
    hi = np.minimum(np.ceil(approx.max(axis=0) + 0.5 * size), [g8.shape[1], g8.shape[0]]).astype(int)
    crop = g8[lo[1]:hi[1], lo[0]:hi[0]]
    if negative:
        crop = 255 - crop
    if median_px:
        crop = cv2.medianBlur(np.ascontiguousarray(crop), min(median_px, 255))
    corners, ids, _ = detector.detectMarkers(np.ascontiguousarray(crop))
    if ids is None:
        return None
    for i, c in zip(ids.ravel(), corners):
        if int(i) == marker_id:
            c = c.reshape(4, 2).astype(float) - APRILTAG_OFFSET_PX + lo
            if np.abs(c - approx).max() < 0.1 * size + 3:
                return c
    return None


def _to_u8(gray):
    g = np.asarray(gray)
    if g.dtype == np.uint8:
        return g
    return np.clip(g * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _match(manifest, ids, corners):
    fid = {f.id: np.asarray(f.corners_mm, float).reshape(4, 2) for f in manifest.fiducials}
    bed, img, used = [], [], []
    for i, c in zip(ids, corners):
        if i in fid and i not in used:
            bed.append(fid[i])
            img.append(c)
            used.append(i)
    return used, bed, img


# -- the mapping parametrisation ----------------------------------------------------------
class _Mapping:
    """H (normalised, 8 free entries) and k1, k2 as one parameter vector for least_squares."""

    def __init__(self, H0, image_size, with_distortion: bool, bed_pts):
        W, Hh = image_size
        self.center = np.array([(W - 1) / 2, (Hh - 1) / 2])
        self.f = PHONE_FOCAL_FRACTION * max(W, Hh)
        mb = bed_pts.mean(axis=0)
        sb = max(np.ptp(bed_pts, axis=0).max() / 2, 1.0)
        si = max(W, Hh) / 2
        self.Tb = np.array([[1 / sb, 0, -mb[0] / sb], [0, 1 / sb, -mb[1] / sb], [0, 0, 1]])
        self.Ti = np.array([[1 / si, 0, -self.center[0] / si], [0, 1 / si, -self.center[1] / si], [0, 0, 1]])
        self.Tii = np.linalg.inv(self.Ti)
        Hn = self.Ti @ H0 @ np.linalg.inv(self.Tb)
        self.Hn0 = Hn / Hn[2, 2]
        self.with_distortion = with_distortion

    def x0(self, k1=0.0, k2=0.0):
        x = np.zeros(8)
        return np.concatenate([x, [k1, k2]]) if self.with_distortion else x

    def H(self, x):
        D = np.zeros(9)
        D[:8] = x[:8]
        Hn = self.Hn0 + D.reshape(3, 3)
        return self.Tii @ Hn @ self.Tb

    def k(self, x):
        return (x[8], x[9]) if self.with_distortion else (0.0, 0.0)

    def project(self, x, xy):
        uv = apply_homography(self.H(x), xy)
        k1, k2 = self.k(x)
        if k1 or k2:
            uv = distort_px(uv, self.center, self.f, k1, k2)
        return uv


def _undistorted_homography(bed, img, center, f, k1, k2, ransac: bool, threshold_px: float = RANSAC_PX):
    from measure.camera import undistort_px
    u = undistort_px(img, center, f, k1, k2) if (k1 or k2) else img
    if ransac and len(bed) >= 8:
        H, mask = cv2.findHomography(bed, u, cv2.RANSAC, threshold_px)
    else:
        H, mask = cv2.findHomography(bed, u, 0)
    if H is None:
        return None, np.zeros(len(bed), bool)
    return H, (mask.ravel() > 0) if mask is not None else np.ones(len(bed), bool)


def _perspective(H, size, pts) -> float:
    """Spread of the local scale over ``pts`` (max / min - 1): 0 for a scanner's affine
    mapping, 0.2-0.7 for a phone at 25-35 deg."""
    s = Camera(H=H, image_size=size).px_per_mm(pts[:: max(1, len(pts) // 200)])
    return float(s.max() / s.min() - 1.0)


def _bled(bed, ctr, bleed):
    """Marker corners (bed mm) as printed: each marker scaled about its centre by
    (1 + bleed_x, 1 + bleed_y). Raster-printed cells spread or shrink (over/under-extrusion,
    rounded line ends along x) so the black border looks a little larger or smaller than
    drawn; a scale about the marker centre leaves the centre, which is what places the
    pattern, untouched."""
    return ctr + (bed - ctr) * (1.0 + np.asarray(bleed, float))


def _corner_fit(H0, size, bed, img, ctr) -> float:
    """RMS corner misfit (px) of a pure homography with marker bleed, fitted to the corners."""
    mp = _Mapping(H0, size, False, bed)

    def res(xx):
        return (mp.project(xx[:8], _bled(bed, ctr, xx[8:])) - img).ravel()
    sol = optimize.least_squares(res, np.zeros(10), method="lm", x_scale="jac", diff_step=1e-6, max_nfev=200)
    return float(np.sqrt(np.mean(sol.fun ** 2) * 2))


# -- layout points and the track-likeness image -------------------------------------------
def layout_points(manifest, spacing_mm: float = 0.5, max_points: int = 2500, labels: bool = False):
    """Points (N, 2) mm on the centrelines of all extruding tracks but labels (``labels``:
    of the labels only), their commanded widths (N,) mm (capped at 3 mm: third-party
    restore moves can read as absurd widths) and unit normals (N, 2)."""
    pts, wid, nrm = [], [], []

    def wanted(tr):
        return tr.length_mm > 0 and (tr.kind == "label") == labels

    total = sum(tr.length_mm for tr in manifest.tracks if wanted(tr))
    step = max(spacing_mm, total / max_points) if total > 0 else spacing_mm
    for tr in manifest.tracks:
        if not wanted(tr):
            continue
        s = np.arange(0.0, tr.length_mm + 1e-9, step)
        w = tr.interp("width_mm", s)
        keep = w > 0
        if keep.any():
            p, tan = tr.at(s[keep])
            pts.append(p)
            wid.append(np.minimum(w[keep], 3.0))
            nrm.append(np.column_stack([-tan[:, 1], tan[:, 0]]))
    if not pts:
        if labels:
            return np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2))
        raise UserError("the manifest has no extruding tracks to register against; "
                        "is it the manifest of this print?")
    return np.concatenate(pts), np.concatenate(wid), np.concatenate(nrm)


class _TrackImage:
    """Local-contrast image, polarity folded in (tracks positive), blurred by sigma_px.

    D = polarity * (G_sigma * I - mean) / sd, with mean and sd the local statistics over
    ``bg_sigma_px``; those are smooth, so they are computed and sampled on a reduced copy.
    """

    def __init__(self, gray, polarity, sigma_px, bg_sigma_px):
        self.fi = max(1, int(sigma_px // 2))
        self.fb = max(1, int(bg_sigma_px // 4))
        self.img = cv2.GaussianBlur(_reduce(gray, self.fi), (0, 0), max(sigma_px / self.fi, 0.3))
        g = _reduce(gray, self.fb)
        sb = max(bg_sigma_px / self.fb, 2.0)
        self.mean = cv2.GaussianBlur(g, (0, 0), sb)
        self.sd = np.sqrt(cv2.GaussianBlur((g - self.mean) ** 2, (0, 0), sb) + 1e-6)
        self.polarity = polarity

    def __call__(self, uv):
        a = _sample(self.img, uv, self.fi)
        return self.polarity * (a - _sample(self.mean, uv, self.fb)) / _sample(self.sd, uv, self.fb, cval=1.0)


def _reduce(gray, factor):
    if factor == 1:
        return gray
    return cv2.resize(gray, (gray.shape[1] // factor, gray.shape[0] // factor), interpolation=cv2.INTER_AREA)


def _sample(img, uv, factor=1, order=1, cval=0.0):
    # pixel centres: full-res u maps to (u + 0.5) / f - 0.5 in an f-times reduced image
    coords = np.array([(uv[:, 1] + 0.5) / factor - 0.5, (uv[:, 0] + 0.5) / factor - 0.5])
    return ndimage.map_coordinates(img, coords, order=order, mode="constant", cval=cval)


def estimate_polarity(gray, project, pts, wid, nrm) -> tuple[float, float]:
    """(+1 light-on-dark or -1, clarity) from the track centre vs. just beside the track.

    Compares the image at the centre line with the image w/2 + 0.3 mm to both sides along
    the track normal (close, so a neighbouring line 1-2 mm away is not hit); the sign of
    the median difference decides, its robust z-score (clarity) says how clear that is.
    """
    off = (np.asarray(wid) / 2 + 0.3)[:, None] * nrm
    uv = project(pts)
    a = _sample(gray, uv)
    d = a - 0.5 * (_sample(gray, project(pts + off)) + _sample(gray, project(pts - off)))
    inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < gray.shape[1] - 1) & (uv[:, 1] < gray.shape[0] - 1)
    d = d[inside]
    if len(d) < 10:
        return 1.0, 0.0
    med = float(np.median(d))
    mad = float(np.median(np.abs(d - med))) * 1.4826 + 1e-6
    return (1.0 if med >= 0 else -1.0), abs(med) / mad


# -- the registration ---------------------------------------------------------------------
def register(image, manifest, points=None, *, refine: bool = True,
             distortion: bool | None = None, start_H=None, recovered=None) -> Registration:
    """Bed mm -> image px for ``image`` (gray float 0..1, or uint8) showing ``manifest``'s print.

    points      optional point hints: text ``"x,y=u,v;..."`` or (bed (N, 2), img (N, 2)).
    refine      run the track-layout refinement (step 2 of the module docstring).
    distortion  estimate k1, k2: None = only when the image looks like a photo (the image
                scale varies over the print by > PERSPECTIVE, marker corners misfit a pure
                homography by > 0.5 px, or point hints or the automatic pose are used).
    start_H     a bed mm -> px homography to start from when there are neither fiducials
                nor points (measure.autoreg; good to ~1 mm): method "auto".
    recovered   {marker id: (4, 2) corners px} found by the guided search
                (measure.fiducial_search), used beside the detected ones. When the
                detector finds some but not all markers, register() runs that search on
                its own pose and registers again with what it found.
    Raises UserError when there is nothing to register with or it fails.
    """
    gray = np.asarray(image, dtype=np.float32)
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    if gray.max() > 1.5:
        gray = gray / 255.0
    Hh, W = gray.shape
    size = (W, Hh)
    warnings: list[str] = []
    hint_bed = hint_img = None
    if points is not None:
        hint_bed, hint_img = parse_points(points) if isinstance(points, str) else (
            np.asarray(points[0], float), np.asarray(points[1], float))

    ids, corners, neg = detect_markers(gray, with_negative=True)
    used, bed_c, img_c = _match(manifest, ids, corners)
    mirrored = False
    if len(used) < 4 and manifest.fiducials:
        flipped = np.ascontiguousarray(gray[:, ::-1])
        ids_m, corners_m, neg_m = detect_markers(flipped, with_negative=True)
        used_m, bed_m, img_m = _match(manifest, ids_m, corners_m)
        if len(used_m) > len(used):
            mirrored = True
            ids, used, bed_c, neg = ids_m, used_m, bed_m, neg_m
            # back to original image coordinates; the corner order reverses with the flip
            img_c = [np.column_stack([W - 1 - c[:, 0], c[:, 1]]) for c in img_m]
    recovered = dict(recovered or {})
    fid_mm = {f.id: np.asarray(f.corners_mm, float).reshape(4, 2) for f in manifest.fiducials}
    for i, c in sorted(recovered.items()):
        if i in used:
            img_c[used.index(i)] = np.asarray(c, float)
        elif i in fid_mm:
            used, bed_c, img_c = used + [i], bed_c + [fid_mm[i]], img_c + [np.asarray(c, float)]
    method = None
    bed_pts = img_pts = None
    if len(used) >= 2:
        method = "fiducials"
        bed_pts, img_pts = np.concatenate(bed_c), np.concatenate(img_c)
        # a recovered marker's corners are the drawn ones (the whole pattern was aligned):
        # its own corners as the "centre" leave it out of the bleed scale (_bled)
        ctr_pts = np.concatenate([b if i in recovered else np.repeat(b.mean(axis=0)[None], 4, axis=0)
                                  for i, b in zip(used, bed_c)])
        if len(used) < 4 and hint_bed is None:
            warnings.append(f"only {len(used)} fiducial(s) found; registration is less certain")
    elif hint_bed is not None:
        method = "points"
    elif start_H is not None:
        method = "auto"
    else:
        expected = sorted(f.id for f in manifest.fiducials)
        if not manifest.fiducials:
            raise UserError("the manifest has no fiducials (third-party print); give >= 4 point pairs "
                            "with --points \"x_mm,y_mm=u_px,v_px;...\"")
        if ids and not used:
            raise UserError(f"the image shows ArUco marker(s) {sorted(set(ids))} but the manifest expects "
                            f"{expected}: is it a picture of another pattern?")
        raise FiducialsNotFound(f"found {len(used)} of the pattern's {len(expected)} fiducials (need >= 2): "
                        "check the whole print is in the picture, in focus and without glare, "
                        "or give --points \"x_mm,y_mm=u_px,v_px;...\"")

    center = np.array([(W - 1) / 2, (Hh - 1) / 2])
    f_px = PHONE_FOCAL_FRACTION * max(W, Hh)
    if method == "fiducials":
        H0, inl = _undistorted_homography(bed_pts, img_pts, center, f_px, 0, 0, ransac=True)
        if H0 is None or inl.sum() < 8:
            # every marker shrunk or grown alike (translucent or lagging raster edges,
            # measure/phenomena.py) moves all corners by the bleed: wider gate, the corner
            # fit below models the bleed itself
            side = float(np.median([np.linalg.norm(c[0] - c[2]) for c in img_c])) / np.sqrt(2)
            H0, inl = _undistorted_homography(bed_pts, img_pts, center, f_px, 0, 0, ransac=True,
                                              threshold_px=max(RANSAC_PX, 0.06 * side))
        if H0 is None or inl.sum() < 8:
            raise FiducialsNotFound(f"the {len(used)} fiducials found do not fit one plane mapping (a picture "
                                    "of another pattern, or of a print not lying flat?): photograph the print "
                                    "flat and whole, or give --points")
        bed_pts, img_pts, ctr_pts = bed_pts[inl], img_pts[inl], ctr_pts[inl]
        # misfit of a pure homography (plus marker bleed) decides whether the lens distorts
        rms0 = _corner_fit(H0, size, bed_pts, img_pts, ctr_pts)
    elif method == "points":
        H0, _ = _undistorted_homography(hint_bed, hint_img, center, f_px, 0, 0, ransac=False)
        if H0 is None:
            raise UserError("--points: cannot compute a mapping from these pairs; check them")
        rms0 = np.inf
    else:
        H0 = np.asarray(start_H, float) / start_H[2, 2]
        rms0 = np.inf
        mirrored = bool(np.linalg.det(H0[:2, :2]) > 0)      # a top-down view flips y
    lay_pts, lay_w, lay_n = layout_points(manifest)
    if distortion is None:
        # a camera, not a scanner: the scale changes across the print (a flatbed's mapping
        # is affine); corners alone cannot tell once they fit a homography (phone seed 9
        # with its 4 markers: 0.4 px, k1 left at 0 and the pose 0.075 mm off; 0.015 with k1)
        distortion = method in ("points", "auto") or rms0 > 0.5 or _perspective(H0, size, lay_pts) > PERSPECTIVE
    mp = _Mapping(H0, size, distortion, lay_pts)
    x = mp.x0()
    # Sanity: the layout must fall inside the image.
    uv0 = mp.project(x, lay_pts)
    inside = ((uv0[:, 0] > -0.05 * W) & (uv0[:, 0] < 1.05 * W) & (uv0[:, 1] > -0.05 * Hh)
              & (uv0[:, 1] < 1.05 * Hh))
    if inside.mean() < 0.5:
        raise UserError(f"only {inside.mean():.0%} of the pattern's tracks fall inside the image with this "
                        "registration; check --points (x_mm,y_mm=u_px,v_px) or that the manifest matches")
    scale = float(np.median(Camera(H=H0, image_size=size).px_per_mm(lay_pts[::max(1, len(lay_pts) // 200)])))
    # the printed markers say it too: found in the negative image, their plastic is darker
    # than the plate; believed over the tracks when those are unclear (a dense spiral's
    # sides land on neighbours: clarity 0.1-0.5 on the 600 dpi renders, a coin toss)
    neg_used = {n for i, n in zip(ids, neg) if i in used}
    marker_polarity = (-1.0 if neg_used.pop() else 1.0) if len(neg_used) == 1 else None

    def polarity_at(x):
        pol, clear = estimate_polarity(gray, lambda p: mp.project(x, p), lay_pts, lay_w, lay_n)
        if marker_polarity is not None and clear < POLARITY_CLEAR:
            return marker_polarity, clear
        return pol, clear

    polarity, clarity = polarity_at(x)

    if refine:
        corners = (bed_pts, img_pts, ctr_pts) if method == "fiducials" else None
        hints = (hint_bed, hint_img) if hint_bed is not None else None
        if method in ("points", "auto"):
            # A hint start can be a line pitch off, which makes the polarity test
            # unreliable: refine with both and keep the better-aligned result.
            anchors = _label_anchors(manifest) if method == "auto" else None
            tries = [(_refine(gray, mp, x, lay_pts, lay_w, pol, scale, corners, hints, method, anchors), pol)
                     for pol in (1.0, -1.0)]
            (x, track_score, x_cov), polarity = max(tries, key=lambda tr: tr[0][1])
        else:
            x, track_score, x_cov = _refine(gray, mp, x, lay_pts, lay_w, polarity, scale, corners, hints,
                                            method)
        method += "+tracks"
        # Polarity again on the refined mapping (the hint start may have been too far off).
        polarity, clarity = polarity_at(x)
    k1, k2 = mp.k(x)
    reg = Registration(H=mp.H(x) / mp.H(x)[2, 2],
                       distortion={"center_px": tuple(center), "f_px": f_px, "k1": float(k1), "k2": float(k2)},
                       residual_mm=float("nan"), n_markers=len(used), mirrored=mirrored, method=method,
                       image_size=size, polarity=polarity, marker_ids=list(used),
                       marker_corners_px=[c for c in img_c] if used else [], warnings=warnings,
                       track_score=track_score if refine else float("nan"))
    if refine:
        sub = lay_pts[::max(1, len(lay_pts) // 400)]
        reg.place_pts_mm, reg.place_cov_mm2 = sub, place_covariance(mp, x, x_cov, sub)
    if method.startswith("fiducials"):
        cam = reg.camera
        bleed = x[-2:] if refine else np.zeros(2)
        reg.marker_bleed = tuple(float(b) for b in bleed)
        err_px = np.sqrt(np.sum((cam.project(_bled(bed_pts, ctr_pts, bleed)) - img_pts) ** 2, axis=1))
        reg.corner_rms_px = float(np.sqrt(np.mean(err_px ** 2)))
        reg.residual_mm = float(np.sqrt(np.mean((err_px / cam.px_per_mm(bed_pts)) ** 2)))
        if recovered:
            reg.recovered_markers = sorted(int(i) for i in recovered if i in used)
            return reg
        # Two markers on one side leave the far side to the tracks (phone seed 9: 0.1 mm
        # off, tau 6 % low; seed 3: 2 mm, every width wrong), and a marker detected with
        # corners off (a logo across its border) pulls the pose (seed 19: one at 2.4 px,
        # the others then 1.0): look for the missing ones where this pose puts them,
        # align the suspect ones by their whole pattern, and register again with those found
        misfit = {i: float(np.sqrt(np.mean(np.sum((cam.project(_bled(b, np.repeat(b.mean(axis=0)[None], 4, axis=0),
                                                                      bleed)) - c) ** 2, axis=1))))
                  for i, b, c in zip(used, bed_c, img_c)}
        todo = sorted(set(fid_mm) - set(used)) + [i for i in used if misfit[i] > SUSPECT_PX]
        if todo:
            from measure.fiducial_search import find_markers
            more = find_markers(gray, manifest, cam, todo, polarity)
            if more:
                return register(image, manifest, points, refine=refine, distortion=distortion, start_H=start_H,
                                recovered={m.id: m.corners_px for m in more})
    return reg


def _label_anchors(manifest):
    """Layout points (mm) on the labels' strokes when the test tracks all run one way
    (measure.placement.heading_resultant >= PARALLEL_RESULTANT), else None.

    An automatic start knows the pose to ~1 mm, and along parallel lines nothing in them
    says where it is: the labels do (our retract pattern printed without markers, flatbed
    render: 0.89 mm at the 95th percentile along its lines, sheared, with the ruler's
    periodic ticks alone; 0.039 mm with the labels; seed 1: 0.25 mm). Only then: small
    text prints worse than lines, and on the spiral, which its tracks hold every way, the
    labels moved the track refinement's pose 33 -> 67 um off and the final pose 0.6 -> 5.3
    um."""
    from measure.placement import PARALLEL_RESULTANT, heading_resultant
    from patterns.manifest import sample_points

    lab = layout_points(manifest, labels=True)[0]
    smp = sample_points(manifest, ds_mm=1.0)
    if len(lab) == 0 or len(smp) == 0:
        return None
    one_way = heading_resultant(smp.nx, smp.ny, np.ones(len(smp), bool)) >= PARALLEL_RESULTANT
    return lab if one_way else None


def _refine(gray, mp, x, lay_pts, lay_w, polarity, scale, corners, hints, method, extra_pts=None):
    """Track-layout refinement (module docstring, step 2). ``extra_pts`` (mm): more layout
    points (:func:`_label_anchors`).

    Returns (parameter vector, score, covariance): score = mean saturated track-likeness
    along the layout at the finest scale (higher = better aligned); covariance (JᵀJ)^-1
    of the parameters from the last step's Jacobian (its residuals are in units of their
    sd: corners 0.3 px, hints, the lens prior, and the track term, which carries the weight
    of ~400 unit residuals), the Laplace approximation of the pose's uncertainty."""
    W = gray.shape[1]
    w_med = float(np.median(lay_w))
    if method == "points":
        ladder_mm = [2.0, 1.0, 0.5, 0.25, max(0.1, w_med / 3)]
    elif method == "auto":      # the automatic start is already good to ~1 mm
        ladder_mm = [1.0, 0.5, 0.25, max(0.1, w_med / 3)]
    else:
        ladder_mm = [0.5, 0.25, max(0.1, w_med / 3)]
    sig_c = 0.3                       # px, AprilTag corner noise
    sig_h = 0.01 * W                  # px, a click on a phone photo

    def prior(xx):
        return [np.array([xx[8] / 0.2, xx[9] / 0.1])] if mp.with_distortion else []  # real lenses: |k1| < ~0.2, |k2| < ~0.1

    nm = 8 + (2 if mp.with_distortion else 0)
    if corners is not None:
        x = np.concatenate([x[:nm], [0.0, 0.0]])

    def corner_res(xx):
        return ((mp.project(xx, _bled(corners[0], corners[2], xx[nm:nm + 2])) - corners[1]) / sig_c).ravel()

    if corners is not None and mp.with_distortion:
        # Lens distortion from the corners alone first (k1 only: corners sit at similar
        # radii, where k1 and k2 trade off), to bring the layout within the capture range
        # of the finest track image.
        free = np.ones(len(x), bool)
        free[9] = False

        def corner_only(xf):
            xx = x.copy()
            xx[free] = xf
            return np.concatenate([corner_res(xx)] + prior(xx))
        x[free] = optimize.least_squares(corner_only, x[free], method="lm", x_scale="jac", diff_step=1e-6,
                                          max_nfev=200).x
    pts = lay_pts if extra_pts is None else np.concatenate([lay_pts, extra_pts])
    for sig_mm in ladder_mm:
        sig_px = max(0.7, sig_mm * scale)
        D = _TrackImage(gray, polarity, sig_px, bg_sigma_px=max(3 * sig_px, 2.5 * w_med * scale))
        # The track term carries the weight of ~400 unit residuals however many layout
        # points there are: enough to set what the corners leave open (k1, k2, and the
        # whole mapping for point hints) without overruling well-measured corners.
        wt = 20.0 / np.sqrt(len(pts))

        def resid(xx):
            uv = mp.project(xx, pts)
            # Saturating reward: a track centre scores ~1-2 sd of local contrast; capping it
            # keeps a few very contrasted spots (glare, markers) from pulling the layout, and
            # gaps or missing beads cost at most a bounded amount (robust like soft-L1).
            r = [wt * (2.0 - 2.0 * np.tanh(D(uv) / 2.0))]
            if corners is not None:
                r.append(corner_res(xx))
            if hints is not None:
                r.append(((mp.project(xx, hints[0]) - hints[1]) / (sig_h if corners is None else 10 * sig_h)).ravel())
            return np.concatenate(r + prior(xx))

        sol = optimize.least_squares(resid, x, method="lm", x_scale="jac", diff_step=1e-6, max_nfev=120)
        x = sol.x
    score = float(np.mean(np.tanh(D(mp.project(x, lay_pts)) / 2.0)))
    return x, score, np.linalg.pinv(sol.jac.T @ sol.jac)


def place_covariance(mp: "_Mapping", x, x_cov, pts_mm, eps: float = 1e-6) -> np.ndarray:
    """Covariance (K, 2, 2) mm^2 of the bed point that the image shows at the projection of
    each of ``pts_mm`` (K, 2), from the covariance ``x_cov`` of the mapping's parameters:
    a parameter error dx moves the projection by A dx (A = d uv / d x), which is the image
    of the bed point P - J^-1 A dx (J = d uv / d P), so Cov(P) = J^-1 A Cov(x) A^T J^-T.

    Along a straight track the layout holds the pose only across the track (the aperture
    problem): a registration from point hints on the parallel tracks of bench/foreign_printer's
    probe put every station 0.04-0.24 mm off along its track while the track-centre offsets
    read 0.015 mm (2026-11-27); at a width step the width then errs by slope x that."""
    pts = np.asarray(pts_mm, float)
    nx = len(x)
    if len(pts) == 0:
        return np.zeros((0, 2, 2))
    uv0 = mp.project(x, pts)
    A = np.empty((len(pts), 2, nx))
    for k in range(nx):
        h = eps * max(1.0, abs(x[k]))
        xp = x.copy()
        xp[k] += h
        A[:, :, k] = (mp.project(xp, pts) - uv0) / h
    d = 1e-3
    J = np.stack([(mp.project(x, pts + [d, 0.0]) - uv0) / d, (mp.project(x, pts + [0.0, d]) - uv0) / d], axis=2)
    Jinv = np.linalg.inv(J)
    G = Jinv @ A                                     # (K, 2, nx) mm per unit parameter
    return G @ np.asarray(x_cov)[:nx, :nx] @ np.transpose(G, (0, 2, 1))
