"""The camera model: the true mapping from bed millimetres to image pixels.

A point on the bed (x, y) in mm (docs/ARCHITECTURE.md "Coordinate frames": x right, y
away from the front, so up in a top-down picture) goes to the image in two steps:

1. a plane homography H (3x3), bed mm -> *undistorted* pixels::

       [u, v, 1]^T ~ H @ [x, y, 1]^T

2. radial lens distortion about the principal point (cx, cy), OpenCV's convention
   (Brown-Conrady, radial terms only; Zhang 2000, OpenCV ``calib3d`` docs)::

       xn = (u - cx) / f,  yn = (v - cy) / f,  r^2 = xn^2 + yn^2
       g  = 1 + k1 r^2 + k2 r^4
       ud = cx + f * xn * g,  vd = cy + f * yn * g

   with f the focal length in px. k1 < 0 is barrel distortion (typical of phone lenses).

Image pixels follow OpenCV: u right, v down, pixel (i, j) has its centre at u = i, v = j.
Measurement code reuses :func:`distort_px` / :func:`undistort_px` for its own lens model.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from calib.errors import UserError

#: A 26 mm (35 mm-equivalent) phone main camera: f = 26/36 of the sensor width.
PHONE_FOCAL_FRACTION = 26.0 / 36.0


# -- lens distortion of pixel coordinates (standalone, reused by measure/) -------------
def distort_px(uv_px, center_px, f_px: float, k1: float = 0.0, k2: float = 0.0) -> np.ndarray:
    """Undistorted -> distorted pixel coordinates (N, 2), radial model in the module docstring."""
    uv = np.asarray(uv_px, dtype=float)
    if uv.ndim == 2 and uv.shape[1] == 2:
        # compiled, one pass: the registration maps ~1,400 point sets per photo (0.34 s in
        # numpy temporaries); the same operations in the same order, the same bits
        out = np.empty_like(uv)
        _distort_kernel(uv, float(center_px[0]), float(center_px[1]), float(f_px), float(k1), float(k2), out)
        return out
    c = np.asarray(center_px, dtype=float)
    n = (uv - c) * (1.0 / f_px)
    # by component: the measurement maps millions of profile points per photo, and
    # np.sum(..., keepdims=True) over a length-2 axis is half of this function's time
    r2 = n[..., 0] * n[..., 0] + n[..., 1] * n[..., 1]
    return c + n * (f_px * (1.0 + r2 * (k1 + k2 * r2)))[..., None]


def undistort_px(uv_px, center_px, f_px: float, k1: float = 0.0, k2: float = 0.0,
                 iterations: int = 8) -> np.ndarray:
    """Distorted -> undistorted pixel coordinates (N, 2): Newton's method on :func:`distort_px`.

    The radial map is solved along the radius only (it preserves direction): find rn with
    rn * (1 + k1 rn^2 + k2 rn^4) = rd. Newton converges to 1e-12 px in a few steps for
    the distortions of real lenses (|k1| r^2 < 0.3).
    """
    uv = np.asarray(uv_px, dtype=float)
    c = np.asarray(center_px, dtype=float)
    d = (uv - c) / f_px
    rd = np.sqrt(np.sum(d * d, axis=-1, keepdims=True))
    r = rd.copy()
    for _ in range(iterations):
        r2 = r * r
        fval = r * (1.0 + k1 * r2 + k2 * r2 * r2) - rd
        fder = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2
        r = r - fval / fder
    scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
    return c + f_px * d * scale


def distortion_jacobian(uv_px, center_px, f_px: float, k1: float = 0.0, k2: float = 0.0) -> np.ndarray:
    """d(distorted px)/d(undistorted px), shape (N, 2, 2).

    J = g I + 2 g'(r^2) n n^T with n the normalised coordinates and g' = k1 + 2 k2 r^2.
    """
    uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
    n = (uv - np.asarray(center_px, dtype=float)) / f_px
    r2 = np.sum(n * n, axis=-1)
    g = 1.0 + k1 * r2 + k2 * r2 * r2
    gp = k1 + 2.0 * k2 * r2
    J = 2.0 * gp[:, None, None] * n[:, :, None] * n[:, None, :]
    J[:, 0, 0] += g
    J[:, 1, 1] += g
    return J


def apply_homography(H, xy) -> np.ndarray:
    """(N, 2) points through the 3x3 homography ``H`` (projective division included)."""
    p = np.asarray(xy, dtype=float)
    H = np.ascontiguousarray(H, dtype=float)
    # compiled and by component, not p @ H.T: a (N, 2) @ (2, 3) product is ~6x slower on
    # millions of points (12 MP phone photos: 1.2 of 5 s of the measurement)
    out = np.empty((len(p), 2))
    _homography_kernel(H, p, out)
    return out


@njit(cache=True)
def _homography_kernel(H, p, out):  # pragma: no cover - numba
    for i in range(p.shape[0]):
        x, y = p[i, 0], p[i, 1]
        w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        out[i, 0] = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
        out[i, 1] = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w


@njit(cache=True)
def _distort_kernel(uv, cx, cy, f_px, k1, k2, out):  # pragma: no cover - numba
    inv = 1.0 / f_px
    for i in range(uv.shape[0]):
        n0 = (uv[i, 0] - cx) * inv
        n1 = (uv[i, 1] - cy) * inv
        r2 = n0 * n0 + n1 * n1
        g = f_px * (1.0 + r2 * (k1 + k2 * r2))
        out[i, 0] = cx + n0 * g
        out[i, 1] = cy + n1 * g


# -- the camera --------------------------------------------------------------------------
@dataclass
class Camera:
    """Bed mm -> image px: homography ``H`` (mm -> undistorted px) then radial distortion.

    image_size   (width, height) in px
    center_px    principal point (cx, cy) in px (distortion centre)
    f_px         focal length in px (normalises the distortion radius)
    k1, k2       radial distortion coefficients (OpenCV convention, dimensionless)
    mirrored     True for a print scanned face down (the image is a mirror view of the bed)
    kind         "flatbed" or "phone" (informative)
    """

    H: np.ndarray
    image_size: tuple[int, int]
    center_px: tuple[float, float] = (0.0, 0.0)
    f_px: float = 1.0
    k1: float = 0.0
    k2: float = 0.0
    mirrored: bool = False
    kind: str = "custom"
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self.H = np.asarray(self.H, dtype=float).reshape(3, 3)
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        self.center_px = (float(self.center_px[0]), float(self.center_px[1]))

    # -- mapping ---------------------------------------------------------------------
    @property
    def has_distortion(self) -> bool:
        return self.k1 != 0.0 or self.k2 != 0.0

    def project(self, xy_mm) -> np.ndarray:
        """Bed points (N, 2) mm -> image points (N, 2) px (distorted)."""
        uv = apply_homography(self.H, np.atleast_2d(xy_mm))
        if self.has_distortion:
            uv = distort_px(uv, self.center_px, self.f_px, self.k1, self.k2)
        return uv

    def unproject(self, uv_px) -> np.ndarray:
        """Image points (N, 2) px -> bed points (N, 2) mm (inverse of :meth:`project`)."""
        uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
        if self.has_distortion:
            uv = undistort_px(uv, self.center_px, self.f_px, self.k1, self.k2)
        return apply_homography(np.linalg.inv(self.H), uv)

    def jacobian(self, xy_mm) -> np.ndarray:
        """Local px per mm, d(u, v)/d(x, y), shape (N, 2, 2).

        Homography part: with q = H [x, y, 1], u = q0/q2, v = q1/q2,
        du/dx = (H00 - u H20) / q2 etc.; times the distortion Jacobian.
        """
        xy = np.atleast_2d(np.asarray(xy_mm, dtype=float))
        H = self.H
        q = xy @ H[:, :2].T + H[:, 2]
        uv = q[:, :2] / q[:, 2:3]
        J = (H[None, :2, :2] - uv[:, :, None] * H[None, 2:3, :2]) / q[:, 2, None, None]
        if self.has_distortion:
            J = distortion_jacobian(uv, self.center_px, self.f_px, self.k1, self.k2) @ J
        return J

    def px_per_mm(self, xy_mm) -> np.ndarray:
        """Local linear scale (px/mm), sqrt(|det J|), at bed points (N, 2)."""
        return np.sqrt(np.abs(np.linalg.det(self.jacobian(xy_mm))))

    # -- serialisation -----------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"H_mm_to_px": np.asarray(self.H).tolist(), "image_size_px": list(self.image_size),
                "center_px": list(self.center_px), "f_px": float(self.f_px),
                "k1": float(self.k1), "k2": float(self.k2), "mirrored": bool(self.mirrored),
                "kind": self.kind, "info": self.info}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(H=np.asarray(d["H_mm_to_px"], dtype=float), image_size=tuple(d["image_size_px"]),
                   center_px=tuple(d.get("center_px", (0.0, 0.0))), f_px=float(d.get("f_px", 1.0)),
                   k1=float(d.get("k1", 0.0)), k2=float(d.get("k2", 0.0)),
                   mirrored=bool(d.get("mirrored", False)), kind=d.get("kind", "custom"),
                   info=dict(d.get("info", {})))

    # -- constructors --------------------------------------------------------------------
    @classmethod
    def flatbed(cls, bed_region_mm, dpi: float = 600.0, rotation_deg: float = 0.0,
                mirrored: bool = False, scale_error=(0.006, -0.002)) -> "Camera":
        """A flatbed scan of ``bed_region_mm`` = (x0, y0, x1, y1) at ``dpi``.

        Scale (px/mm) = dpi / 25.4 * (1 + e) per scanner axis, e = ``scale_error``
        (sx, sy): flatbed scanners carry ~0.6 % axis scale error (shared/REFERENCE.md).
        ``rotation_deg`` turns the print on the glass (counter-clockwise as seen in the
        image); ``mirrored`` = print laid face down (x flips). The image just covers the
        rotated region; there is no lens distortion.
        """
        if not 300 <= dpi <= 1200:
            raise UserError(f"flatbed dpi {dpi:g} is outside 300-1200; pick e.g. --dpi 600")
        x0, y0, x1, y1 = map(float, bed_region_mm)
        ex, ey = (scale_error, scale_error) if np.isscalar(scale_error) else scale_error
        s = dpi / 25.4
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        # bed -> viewed-from-above frame (y flipped so +y is up); face down also flips x
        F = np.diag([-1.0 if mirrored else 1.0, -1.0, 1.0])
        a = np.deg2rad(rotation_deg)
        # image v points down, so a counter-clockwise turn on screen is a clockwise matrix
        R = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])
        S = np.diag([s * (1 + ex), s * (1 + ey), 1.0])
        T0 = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1.0]])
        A = S @ R @ F @ T0
        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        uv = apply_homography(A, corners)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        w, h = int(np.ceil(hi[0] - lo[0])), int(np.ceil(hi[1] - lo[1]))
        # region centre at the image centre
        T1 = np.array([[1, 0, (w - 1) / 2], [0, 1, (h - 1) / 2], [0, 0, 1.0]])
        H = T1 @ A
        return cls(H=H, image_size=(w, h), center_px=((w - 1) / 2, (h - 1) / 2), f_px=float(max(w, h)),
                   mirrored=mirrored, kind="flatbed",
                   info={"dpi": float(dpi), "rotation_deg": float(rotation_deg),
                         "scale_error": [float(ex), float(ey)], "bed_region_mm": [x0, y0, x1, y1]})

    @classmethod
    def phone(cls, bed_region_mm, image_size=(4000, 3000), tilt_deg: float = 25.0,
              yaw_deg: float = 0.0, k1: float = -0.06, k2: float = 0.02, fill: float = 0.85,
              f_px: float | None = None) -> "Camera":
        """A pinhole phone camera aimed at the centre of ``bed_region_mm`` = (x0, y0, x1, y1).

        The camera stands in front of the bed (towards -y), tilted ``tilt_deg`` from
        looking straight down (0 = top-down, up to ~30), and turned ``yaw_deg`` about the
        vertical. H = K [r1 r2 t] (Hartley & Zisserman, eq. 8.1 for a plane z = 0) with K
        the intrinsics (focal ``f_px``, default a 26 mm-equivalent lens, principal point at
        the image centre) and the distance chosen so the region fills ``fill`` of the frame.
        Radial distortion k1, k2 (barrel by default) is applied after H.
        """
        if not 0 <= tilt_deg <= 45:
            raise UserError(f"phone tilt {tilt_deg:g} deg is outside 0-45; use e.g. --tilt 25")
        W, Hh = int(image_size[0]), int(image_size[1])
        f = float(f_px) if f_px else PHONE_FOCAL_FRACTION * W
        c = np.array([(W - 1) / 2, (Hh - 1) / 2])
        K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])
        x0, y0, x1, y1 = map(float, bed_region_mm)
        target = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
        t, yaw = np.deg2rad(tilt_deg), np.deg2rad(yaw_deg)
        back = np.array([np.sin(yaw) * np.sin(t), -np.cos(yaw) * np.sin(t), np.cos(t)])  # target -> camera
        up_w = np.array([-np.sin(yaw), np.cos(yaw), 0.0])  # bed +y turned by yaw: image up

        def homography(dist):
            C = target + dist * back
            zc = (target - C) / np.linalg.norm(target - C)
            yc = -(up_w - up_w @ zc * zc)
            yc /= np.linalg.norm(yc)
            xc = np.cross(yc, zc)
            R = np.vstack([xc, yc, zc])
            return K @ np.column_stack([R[:, 0], R[:, 1], -R @ C])

        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])

        def extent(dist):
            uv = distort_px(apply_homography(homography(dist), corners), c, f, k1, k2)
            return max(np.abs(uv[:, 0] - c[0]).max() / (W / 2), np.abs(uv[:, 1] - c[1]).max() / (Hh / 2))

        lo, hi = 1.0, 1e5   # mm; extent falls monotonically with distance
        for _ in range(80):
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if extent(mid) > fill else (lo, mid)
        H = homography(hi)
        return cls(H=H, image_size=(W, Hh), center_px=tuple(c), f_px=f, k1=float(k1), k2=float(k2),
                   kind="phone", info={"tilt_deg": float(tilt_deg), "yaw_deg": float(yaw_deg),
                                       "distance_mm": float(hi), "bed_region_mm": [x0, y0, x1, y1]})
