"""Registration without fiducials and without clicks: find the planned path in the picture.

For third-party G-code (no ArUco markers) and as the fallback when the markers are not
found. Nothing but the manifest's tracks (polylines with commanded widths) and the
picture is used. The feature on both sides is a *line field*: line strength times
exp(2i phi) of the line direction (:func:`ridge_maps`; Frangi et al. 1998 line measure,
Granlund & Knutsson 1995 double-angle representation), taken where a nozzle-wide bead is
~2 px. It ignores the plate's isotropic grain, keeps only the rim of broad logo strokes,
serves light-on-dark and dark-on-light alike, and tells horizontal lines from vertical
ones, which a plain intensity correlation did not (blocks of parallel lines matched
turned by 90 deg on the realdata PLA photo). Stages, coarse to fine:

1. Coarse pose search (template matching; Brown 1992, "A survey of image registration
   techniques": exhaustive search over a transform family, FFT correlation for the
   translation). The path's line field at ``COARSE_PX_PER_MM`` is correlated with the
   picture's, reduced so that the pattern would have that resolution, for every scale
   hypothesis (pattern extent vs image size, :data:`EXTENT_FRACTION`), every rotation
   (0-360 deg) and both the direct and the mirror view (a print scanned face down);
   normalised cross-correlation, so a busy spot is no match by loudness alone.
2. The best :data:`N_REFINE` candidates of each view: pattern search (Hooke & Jeeves) of
   scale, rotation, aspect, shear and perspective with the picture rectified into bed
   coordinates, FFT for the translation, at 1 then 2.5 px/mm (:func:`refine_search`).
   The final correlation ranks them; nothing above :data:`MIN_SCORE`, or a different
   pose within :data:`AMBIGUOUS_RATIO` of the best, is refused by the caller.
3. The winner starts :func:`measure.register.register` (``start_H``), whose track-layout
   refinement runs to bead scale with lens distortion k1, k2 (:func:`auto_register`).
4. After a width measurement, one ICP step moves the mapping so that the measured bead
   centre lines lie on the planned path (:func:`refine_with_centres`; measure.pipeline
   then measures again).

All image coordinates are OpenCV's (pixel centres at integers, u right, v down); bed
coordinates in mm (docs/ARCHITECTURE.md "Coordinate frames").
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import fft as sfft

from calib.errors import UserError

#: Resolution of the coarse search (px per mm of bed): 2.5 mm per pixel keeps the
#: pattern's large structure (rings, blocks of lines, ticks; the line directions are in
#: the field) while a 150 mm pattern is only ~60 px across.
COARSE_PX_PER_MM = 0.4
#: Rotation step of the coarse search (deg): a 75 mm radius moves 2 px at 0.4 px/mm.
ROTATION_STEP_DEG = 4.0
#: Ratio between neighbouring scale hypotheses.
SCALE_STEP = 1.1
#: The pattern may span this fraction of the image's larger side (smallest, largest):
#: a print photographed from far away (beads of 0.4 mm are then ~3 px wide in 12 MP)
#: down to one that is partly cut off.
EXTENT_FRACTION = (0.25, 1.5)
#: Segments commanded wider than this many nozzle diameters are left out of the template:
#: third-party restore/prime moves with little head travel read as absurd widths (10-25
#: mm) but print a blob or nothing, not a band. (The widest real test beads, 1.6 mm from
#: a 0.4 mm nozzle in the realdata spiral test, are 4 diameters.)
MAX_TEMPLATE_WIDTH_NOZZLES = 5.0


@dataclass
class Candidate:
    """One pose hypothesis: ``H`` bed mm -> full-image px, and its scores."""

    H: np.ndarray
    score: float              # coarse normalised correlation of the line fields (0..1)
    mirrored: bool
    scale_px_per_mm: float
    rotation_deg: float
    refined_score: float = float("nan")
    info: dict = field(default_factory=dict)


# -- the path as a raster -----------------------------------------------------------------
def path_segments(manifest) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Printed segments of all extruding tracks: starts (N, 2) mm, ends (N, 2) mm and widths
    (N,) mm (the smaller of the two vertex widths; segments wider than
    MAX_TEMPLATE_WIDTH_NOZZLES nozzle diameters are left out). Label tracks are left out
    (their text is drawn differently by every slicer), and so is the serpentine width
    reference (below); none at all raises UserError."""
    nozzle = float(manifest.printer.get("nozzle_diameter_mm", 0.4) or 0.4)
    cap = MAX_TEMPLATE_WIDTH_NOZZLES * nozzle
    a, b, w = [], [], []
    for tr in manifest.tracks:
        if tr.kind == "label" or len(tr.points_mm) < 2:
            continue
        if tr.params.get("role") == "width_reference" and tr.params.get("straight_mm"):
            # the serpentine width reference (patterns/builder.py frame_prime): parallel
            # passes that a mirrored pose lays onto themselves. On a phone render of a
            # one-spiral print the true pose scored 0.482 and its mirror 0.473 with them,
            # 0.426 / 0.356 with the first pass alone (four lines in the picture where
            # the template has one), 0.630 / 0.492 without the reference
            continue
        p = np.asarray(tr.points_mm, float)
        ww = np.minimum(np.asarray(tr.width_mm, float)[:-1], np.asarray(tr.width_mm, float)[1:])
        keep = (ww > 0.05) & (ww <= cap) & (np.hypot(*(p[1:] - p[:-1]).T) > 1e-6)
        a.append(p[:-1][keep])
        b.append(p[1:][keep])
        w.append(ww[keep])
    if not a or sum(len(x) for x in a) == 0:
        raise UserError("the manifest has no extruding tracks to register against; "
                        "is it the manifest of this print?")
    return np.concatenate(a), np.concatenate(b), np.concatenate(w)


def rasterise(seg, px_per_mm: float, origin_mm, shape, supersample: int = 4) -> np.ndarray:
    """Coverage image (float32 0..1, ``shape``) of the segments drawn at ``px_per_mm`` with
    bed point ``origin_mm`` at pixel (0, 0), bed +y pointing up the image (v down).

    Drawn ``supersample`` times finer with anti-aliased thick lines, then area-averaged,
    so beads narrower than a pixel keep their share of coverage (their ink)."""
    a, b, w = seg
    ss = supersample
    H, W = shape
    big = np.zeros((H * ss, W * ss), np.uint8)
    sh = 4                                              # cv2 fixed-point fraction bits
    k = px_per_mm * ss

    def px(p):
        u = (p[:, 0] - origin_mm[0]) * k + (ss - 1) / 2
        v = (origin_mm[1] - p[:, 1]) * k + (ss - 1) / 2
        return np.round(np.column_stack([u, v]) * (1 << sh)).astype(np.int64)

    pa, pb = px(a), px(b)
    th = np.maximum(1, np.round(w * k)).astype(int)
    for t in np.unique(th):
        sel = th == t
        lines = np.stack([pa[sel], pb[sel]], axis=1).astype(np.int32)
        cv2.polylines(big, list(lines), False, 255, int(t), cv2.LINE_AA, sh)
    return cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def rasterise_oriented(seg, px_per_mm: float, origin_mm, shape, bins: int = 36) -> np.ndarray:
    """Complex line field (complex64, ``shape``): coverage times exp(2i phi), phi the
    direction of each segment in the image (u right, v down), as :func:`ridge_maps`
    measures it in the picture. Segments are drawn per direction bin (``bins`` over 180
    deg) with :func:`rasterise`."""
    a, b, w = seg
    d = b - a
    phi = np.arctan2(-d[:, 1], d[:, 0]) % np.pi            # v = -y
    k = np.minimum((phi / np.pi * bins).astype(int), bins - 1)
    out = np.zeros(shape, np.complex64)
    for j in np.unique(k):
        sel = k == j
        cov = rasterise((a[sel], b[sel], w[sel]), px_per_mm, origin_mm, shape)
        out += cov * np.exp(2j * np.mean(phi[sel])).astype(np.complex64)
    return out


# -- features -----------------------------------------------------------------------------
def band_pass(img, sigma_fine_px: float, sigma_coarse_px: float) -> np.ndarray:
    """Difference of Gaussians: structure between the two scales, without slow shading."""
    return (cv2.GaussianBlur(img, (0, 0), sigma_fine_px)
            - cv2.GaussianBlur(img, (0, 0), sigma_coarse_px))


def ridge_maps(img, sigma_px: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bright-line strength, dark-line strength, line orientation) at scale ``sigma_px``.

    From the Hessian eigenvalues l1 <= l2 of the Gaussian-smoothed image (the line
    measure of Frangi et al. 1998, "Multiscale vessel enhancement filtering", in its
    simplest form): a bright line has l1 << 0 and l2 ~ 0, so max(0, -l1 - |l2|) sigma^2;
    a dark line the same with the signs swapped. Isotropic grain (the textured plate)
    has |l1| ~ |l2| and scores ~0; a broad logo stroke scores only along its rim, not
    over its area. Scale-normalised by sigma^2 (Lindeberg 1998).

    Orientation as the unit complex number exp(2i phi) of the eigenvector of l2 (the
    double-angle representation, Granlund & Knutsson 1995, so that a line and the same
    line turned by 180 deg agree): phi is the direction of a bright line (u right, v
    down); for a dark line it is the normal, so dark-line orientations take a minus sign.
    """
    g = cv2.GaussianBlur(img, (0, 0), sigma_px)
    ixx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
    iyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    ixy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
    tr = 0.5 * (ixx + iyy)
    d = np.sqrt(0.25 * (ixx - iyy) ** 2 + ixy ** 2)
    l1, l2 = tr - d, tr + d
    k = sigma_px ** 2
    # eigenvector of the larger eigenvalue l2 at angle t: (ixx - iyy) + 2i ixy = 2 d exp(2i t)
    z = ((0.5 * (ixx - iyy)) + 1j * ixy) / np.maximum(d, 1e-12)
    return (np.maximum(0.0, -l1 - np.abs(l2)) * k, np.maximum(0.0, l2 - np.abs(l1)) * k, z.astype(np.complex64))


# -- stage 1: coarse search ---------------------------------------------------------------
def _pattern_frame(seg):
    pts = np.concatenate([seg[0], seg[1]])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return (lo + hi) / 2, float(np.max(hi - lo)), float(np.hypot(*(hi - lo)))


def _similarity_H(centre_mm, k_px_per_mm, theta_rad, mirrored, t_px):
    """Bed mm -> px: rotate by theta (counter-clockwise as seen in the image), scale, and
    place the pattern centre at ``t_px``. Not mirrored = the top-down view (bed +y up the
    image, so a y flip); mirrored = the print seen from below (scanned face down)."""
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    R = np.array([[c, s], [-s, c]])                   # image v points down
    F = np.diag([1.0, 1.0]) if mirrored else np.diag([1.0, -1.0])
    A = k_px_per_mm * R @ F
    H = np.eye(3)
    H[:2, :2] = A
    H[:2, 2] = np.asarray(t_px, float) - A @ np.asarray(centre_mm, float)
    return H


def coarse_search(gray, seg, nozzle_mm: float = 0.4, *, views=(False, True), top: int = 6,
                  px_per_mm: float = COARSE_PX_PER_MM, rotation_step_deg: float = ROTATION_STEP_DEG,
                  scale_step: float = SCALE_STEP, extent_fraction=EXTENT_FRACTION) -> list[Candidate]:
    """Stage 1 of the module docstring: the ``top`` best distinct similarity poses.

    gray       full-resolution picture, float32 0..1 (H, W)
    seg        :func:`path_segments` of the manifest
    views      which views to search: False the direct (top-down) one, True the mirror view
    nozzle_mm  nozzle diameter: the picture is reduced so that a nozzle-wide bead is ~2 px
               before the line measure (:func:`ridge_maps`, sigma 1 px) is taken; the line
               strength is then pooled (area average) to ``px_per_mm``
    Returns up to ``top`` distinct candidates per view with H (bed mm -> full-image px),
    best first by score (a normalised cross-correlation, 0..1) within each view.
    """
    Hh, W = gray.shape
    L = max(W, Hh)
    centre, extent, diag = _pattern_frame(seg)
    r = px_per_mm
    n = int(np.ceil(diag * r)) + 6                         # any rotation fits in n x n
    c_px = (n - 1) / 2
    origin = (centre[0] - c_px / r, centre[1] + c_px / r)
    # the template: line field (every line drawn one nozzle wide, as the line measure sees
    # a bead of any width as about one line), band-passed like the picture
    T0 = rasterise_oriented((seg[0], seg[1], np.full(len(seg[2]), nozzle_mm)), r, origin, (n, n))
    sig_f, sig_c = 0.7, 4.0                                 # px at r
    angles = np.arange(0.0, 360.0, rotation_step_deg)
    mirrors = tuple(views)
    templates = []
    for m in mirrors:
        # mirrored: bed +y down the image, directions reflected (phi -> -phi)
        base = T0 if not m else np.conj(T0[::-1])
        for a in angles:
            M = cv2.getRotationMatrix2D((c_px, c_px), a, 1.0)
            # a counter-clockwise turn on screen (v down) takes direction phi to phi - a
            rot = np.exp(-2j * np.deg2rad(a))
            parts = []
            for ch in (base.real, base.imag):
                parts.append(band_pass(cv2.warpAffine(np.ascontiguousarray(ch), M, (n, n),
                                                      flags=cv2.INTER_LINEAR), sig_f, sig_c))
            Tc = (parts[0] + 1j * parts[1]) * rot
            Tc = Tc / (np.sqrt(np.sum(np.abs(Tc) ** 2)) + 1e-12)
            templates.append((m, a, Tc.real.astype(np.float32), Tc.imag.astype(np.float32)))
    yy, xx = np.mgrid[0:n, 0:n]
    disc = (((xx - c_px) ** 2 + (yy - c_px) ** 2) <= (n / 2) ** 2).astype(np.float32)
    support = float(disc.sum())
    # scale hypotheses: full-image px per mm
    s_lo = extent_fraction[0] * L / extent
    s_hi = extent_fraction[1] * L / extent
    scales = s_lo * scale_step ** np.arange(int(np.floor(np.log(s_hi / s_lo) / np.log(scale_step))) + 1)
    k_ridge = 2.0 / nozzle_mm                               # px/mm at which beads are ~2 px
    pre_f = min(1.0, k_ridge / scales[0])
    pre = cv2.resize(gray, (max(1, round(W * pre_f)), max(1, round(Hh * pre_f))), interpolation=cv2.INTER_AREA) \
        if pre_f < 1 else gray
    found = []
    for s in scales:
        fr = min(1.0, k_ridge / s)
        rid = cv2.resize(gray if fr * W > pre.shape[1] else pre, (max(8, round(W * fr)), max(8, round(Hh * fr))),
                         interpolation=cv2.INTER_AREA)
        maps = ridge_maps(rid, 1.0)
        f = r / s
        w_s, h_s = max(8, round(W * f)), max(8, round(Hh * f))
        fx, fy = w_s / W, h_s / Hh                          # exact reduction per axis
        P0, P1 = sfft.next_fast_len(h_s + n, real=True), sfft.next_fast_len(w_s + n, real=True)
        tv = np.arange(P0)
        tv = np.where(tv >= P0 - n, tv - P0, tv)
        tu = np.arange(P1)
        tu = np.where(tu >= P1 - n, tu - P1, tu)
        # valid shifts: the template centre inside the picture
        valid = (((tv + c_px >= 0) & (tv + c_px <= h_s - 1))[:, None]
                 & ((tu + c_px >= 0) & (tu + c_px <= w_s - 1))[None, :])
        DS = np.conj(sfft.rfft2(disc, s=(P0, P1)))
        # the picture's line field, strength times direction. Either polarity: a bright
        # line's measured orientation is its direction, a dark line's its normal (minus
        # sign), so the dark gaps between light beads point the same way as the beads and
        # one field serves light-on-dark and dark-on-light alike (the polarity is decided
        # in stage 2)
        zf = (maps[0] - maps[1]) * maps[2]
        if True:
            Fr = band_pass(cv2.resize(np.ascontiguousarray(zf.real), (w_s, h_s), interpolation=cv2.INTER_AREA),
                           sig_f, sig_c)
            Fi = band_pass(cv2.resize(np.ascontiguousarray(zf.imag), (w_s, h_s), interpolation=cv2.INTER_AREA),
                           sig_f, sig_c)
            FR, FJ = sfft.rfft2(Fr, s=(P0, P1)), sfft.rfft2(Fi, s=(P0, P1))
            # normalised cross-correlation: divide by the picture's energy under the
            # template's disc, so a busy spot (logo, mat, plate edge) is no match by
            # loudness alone
            e2 = Fr * Fr + Fi * Fi
            energy = sfft.irfft2(sfft.rfft2(e2, s=(P0, P1)) * DS, s=(P0, P1))
            floor = 0.05 * float(np.mean(e2)) * support + 1e-12
            norm = np.where(valid, 1.0 / np.sqrt(np.maximum(energy, floor)), 0.0)
            for m, a, Tr, Ti in templates:
                # Re sum F(x + t) conj(T(x)): aligned lines add, crossing ones cancel
                C = sfft.irfft2(FR * np.conj(sfft.rfft2(Tr, s=(P0, P1)))
                                + FJ * np.conj(sfft.rfft2(Ti, s=(P0, P1))), s=(P0, P1)) * norm
                i, j = np.unravel_index(np.argmax(C), C.shape)
                ctr_small = np.array([tu[j] + c_px, tv[i] + c_px])
                ctr_full = (ctr_small + 0.5) / np.array([fx, fy]) - 0.5
                H = _similarity_H(centre, s, np.deg2rad(a), m, ctr_full)
                found.append(Candidate(H=H, score=float(C[i, j]), mirrored=m,
                                       scale_px_per_mm=float(s), rotation_deg=float(a),
                                       info={"centre_px": ctr_full, "centre_mm": centre}))
    found.sort(key=lambda c: -c.score)
    out: list[Candidate] = []
    for m in mirrors:                                       # the best ``top`` of each view
        kept: list[Candidate] = []
        for c in found:
            if c.mirrored == m and all(not _same_pose(c, o, extent) for o in kept):
                kept.append(c)
                if len(kept) >= top:
                    break
        out += kept
    return out


def _same_pose(a: Candidate, b: Candidate, extent_mm: float) -> bool:
    """Two candidates that put the pattern's corners within 8 % of its extent of each other."""
    if a.mirrored != b.mirrored:
        return False
    k = 0.5 * (a.scale_px_per_mm + b.scale_px_per_mm)
    h = extent_mm / 2
    sq = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    ca = _apply(a.H, sq + _H_centre(a))
    cb = _apply(b.H, sq + _H_centre(a))
    return float(np.max(np.hypot(*(ca - cb).T))) < 0.08 * extent_mm * k


def _H_centre(c: Candidate):
    return c.info.get("centre_mm", np.zeros(2))


def _apply(H, xy):
    p = np.asarray(xy, float) @ H[:2, :2].T + H[:2, 2]
    q = np.asarray(xy, float) @ H[2, :2] + H[2, 2]
    return p / q[:, None]


# -- stage 2: tile matching on the rectified picture -------------------------------------
#: Levels of stage 2 (:func:`refine_search`): px per mm of the rectified picture,
#: translation radius (mm), first steps of the pattern search for the 8 parameters of
#: :func:`_pose_D` (translation is searched by FFT, so its steps are 0; rotation in rad,
#: the others relative, normalised by the pattern's half extent).
STAGE2_LEVELS = (
    (1.0, 8.0, (0, 0, 0.03, 0.04, 0.04, 0.04, 0.06, 0.06)),
    (2.5, 2.0, (0, 0, 0.01, 0.01, 0.01, 0.01, 0.02, 0.02)),
)
#: Sweeps of the pattern search per level.
STAGE2_SWEEPS = 8


def _rect_frame(lo, hi, r):
    """Rectified raster of the bed box lo..hi (mm) at r px/mm: pixel (i, j) is centred on
    bed (lo_x + (i + 0.5) / r, hi_y - (j + 0.5) / r), so an area reduction by an integer
    factor q gives the raster at r / q exactly. Returns (M 3x3 rect px -> bed mm,
    (width, height)); ``lo``/``hi`` must span a multiple of 1 / r (:func:`_snap_box`)."""
    W = int(round((hi[0] - lo[0]) * r))
    H = int(round((hi[1] - lo[1]) * r))
    M = np.array([[1 / r, 0, lo[0] + 0.5 / r], [0, -1 / r, hi[1] - 0.5 / r], [0, 0, 1.0]])
    return M, (W, H)


def _snap_box(lo, hi, unit_mm):
    """Grow the box so that its sides are multiples of ``unit_mm``."""
    size = np.ceil((hi - lo) / unit_mm) * unit_mm
    return lo, lo + size


class _Pyramid:
    """The picture area-reduced by powers of 1.5, so that rectifying at any resolution
    starts from a copy no more than 1.5x finer than needed (no aliasing in the warp)."""

    def __init__(self, gray):
        self.gray = gray
        self.levels = {0: gray}

    def at(self, f_wanted):
        """(image, f) with f >= f_wanted the reduction factor actually used."""
        if f_wanted >= 1:
            return self.gray, 1.0
        k = int(np.floor(np.log(f_wanted) / np.log(1 / 1.5)))
        if k not in self.levels:
            Hh, W = self.gray.shape
            f = 1.5 ** -k
            self.levels[k] = cv2.resize(self.gray, (max(8, round(W * f)), max(8, round(Hh * f))),
                                        interpolation=cv2.INTER_AREA)
        img = self.levels[k]
        return img, img.shape[1] / self.gray.shape[1]


def rectified_field(pyr: _Pyramid, H, lo, hi, r, scale_px_per_mm, r_ridge):
    """The picture's line field (complex, both polarities; :func:`ridge_maps`) mapped into
    bed coordinates (the :func:`_rect_frame` raster at r px/mm) through the homography H
    (bed mm -> full-image px).

    The line measure needs beads of ~2 px: the picture is rectified at ``r_ridge`` (an
    integer multiple of r, ~2 px per nozzle width), measured there and area-reduced to r,
    as in the coarse search."""
    q = max(1, int(round(r_ridge / r)))
    rr = r * q
    M, size = _rect_frame(lo, hi, rr)
    img, f = pyr.at(rr / scale_px_per_mm)
    S = np.array([[f, 0, 0.5 * f - 0.5], [0, f, 0.5 * f - 0.5], [0, 0, 1.0]])
    A = S @ np.asarray(H, float) @ M
    rect = cv2.warpPerspective(img, A, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)
    inside = cv2.warpPerspective(np.ones_like(img), A, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    rb, rd, z = ridge_maps(rect, 1.0)
    zf = (rb - rd) * z * inside
    if q > 1:
        Wr, Hr = size[0] // q, size[1] // q
        zf = (cv2.resize(np.ascontiguousarray(zf.real), (Wr, Hr), interpolation=cv2.INTER_AREA)
              + 1j * cv2.resize(np.ascontiguousarray(zf.imag), (Wr, Hr), interpolation=cv2.INTER_AREA))
    return zf


def _band(z, r):
    s_c = 2.5 * r                                         # 2.5 mm: beyond the bead scale
    return (band_pass(np.ascontiguousarray(z.real), 0.7, s_c)
            + 1j * band_pass(np.ascontiguousarray(z.imag), 0.7, s_c)).astype(np.complex64)


class PathTemplate:
    """The path's line field rasterised in bed coordinates per stage-2 resolution (cached)."""

    def __init__(self, seg, nozzle_mm, margin_mm=12.0):
        self.seg = (seg[0], seg[1], np.full(len(seg[2]), nozzle_mm))
        pts = np.concatenate([seg[0], seg[1]])
        self.r_ridge = 2.0 / nozzle_mm                     # px/mm with beads ~2 px
        # box sides a multiple of 2 mm: every level's raster divides it exactly
        self.lo, self.hi = _snap_box(pts.min(axis=0) - margin_mm, pts.max(axis=0) + margin_mm, 2.0)
        self._cache: dict = {}

    def ridge_px_per_mm(self, r):
        return r * max(1, int(np.ceil(self.r_ridge / r - 1e-9)))

    def at(self, r):
        if r not in self._cache:
            M, (W, H) = _rect_frame(self.lo, self.hi, r)
            origin = (M[0, 2], M[1, 2])                    # bed point of pixel (0, 0)
            self._cache[r] = _band(rasterise_oriented(self.seg, r, origin, (H, W)), r)
        return self._cache[r]


def _pose_D(p):
    """3x3 map of normalised bed coordinates: translation (p0, p1), rotation p2 (rad), log
    scale p3, log aspect p4, shear p5, perspective p6, p7; identity at p = 0."""
    tx, ty, th, ls, a, sh, p1, p2 = p
    c, s = np.cos(th), np.sin(th)
    T = np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1.0]])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    S = np.diag([np.exp(ls), np.exp(ls), 1.0])
    A = np.array([[np.exp(a), sh, 0], [0, np.exp(-a), 0], [0, 0, 1.0]])
    P = np.array([[1, 0, 0], [0, 1, 0], [p1, p2, 1.0]])
    return T @ R @ S @ A @ P


def _box_norm(lo, hi):
    ctr, h = (lo + hi) / 2, float(np.max(hi - lo)) / 2
    return np.array([[1 / h, 0, -ctr[0] / h], [0, 1 / h, -ctr[1] / h], [0, 0, 1.0]])


def _shift_search(FF, P, T, Tn, rad):
    """Best translation (px, within +-rad) of the template T (complex) in the field whose
    real and imaginary parts have the FFTs ``FF`` on the canvas ``P``; correlation of the
    complex fields Re sum F(x + t) conj(T(x)) divided by ``Tn``. Returns (score, dx, dy)."""
    P0, P1 = P
    C = sfft.irfft2(FF[0] * np.conj(sfft.rfft2(T.real, s=P)) + FF[1] * np.conj(sfft.rfft2(T.imag, s=P)), s=P)
    # shifts -rad..rad wrap around the FFT canvas
    idx0 = np.r_[np.arange(0, rad + 1), np.arange(P0 - rad, P0)]
    idx1 = np.r_[np.arange(0, rad + 1), np.arange(P1 - rad, P1)]
    sub = C[np.ix_(idx0, idx1)]
    j, i = np.unravel_index(np.argmax(sub), sub.shape)
    dy = idx0[j] if idx0[j] <= rad else idx0[j] - P0
    dx = idx1[i] if idx1[i] <= rad else idx1[i] - P1
    return float(sub[j, i]) / Tn, int(dx), int(dy)


def refine_search(pyr: _Pyramid, tmpl: "PathTemplate", H0, levels=STAGE2_LEVELS):
    """Stage 2: improve the homography H0 (bed mm -> full px) by a pattern search.

    At each level (:data:`STAGE2_LEVELS`: px/mm, translation radius mm, first steps) the
    picture's line field is mapped into bed coordinates with the current H, and the
    path's line field is warped by small changes D of scale, rotation, aspect, shear and
    perspective (normalised bed coordinates); for each D the best translation comes from
    one FFT correlation. Each parameter is tried at +-step in turn, the best change kept,
    the steps halved when nothing improves (Hooke & Jeeves 1961 pattern search). Local
    directions turn by at most a few degrees, which the double-angle correlation
    tolerates (cos 2 x 3 deg = 0.99), so the field is not re-oriented.

    Returns (H, score): score = the normalised correlation at the last level (0..1)."""
    H = np.asarray(H0, float) / H0[2, 2]
    lo, hi = tmpl.lo, tmpl.hi
    N = _box_norm(lo, hi)
    Ni = np.linalg.inv(N)
    score = 0.0
    for r, rad_mm, steps0 in levels:
        k = float(np.median(_local_scale(H, np.array([(lo + hi) / 2]))))
        T = tmpl.at(r)
        Fz = _band(rectified_field(pyr, H, lo, hi, r, k, tmpl.ridge_px_per_mm(r)), r)
        M, (W, Hh) = _rect_frame(lo, hi, r)
        Mi = np.linalg.inv(M)
        rad = max(2, int(np.ceil(rad_mm * r)))
        fn = float(np.sqrt(np.sum(np.abs(Fz) ** 2))) + 1e-12
        P = (sfft.next_fast_len(Hh + rad, real=True), sfft.next_fast_len(W + rad, real=True))
        FF = (sfft.rfft2(Fz.real, s=P), sfft.rfft2(Fz.imag, s=P))
        cache = {}

        def evaluate(p):
            key = tuple(np.round(p, 6))
            if key not in cache:
                Dr = Mi @ Ni @ _pose_D(p) @ N @ M                 # template raster -> moved raster
                Tw = (cv2.warpPerspective(np.ascontiguousarray(T.real), Dr, (W, Hh), flags=cv2.INTER_LINEAR)
                      + 1j * cv2.warpPerspective(np.ascontiguousarray(T.imag), Dr, (W, Hh), flags=cv2.INTER_LINEAR))
                Tn = float(np.sqrt(np.sum(np.abs(Tw) ** 2))) * fn + 1e-12
                sc, dx, dy = _shift_search(FF, P, Tw, Tn, rad)
                cache[key] = (sc, dx, dy)
            return cache[key]

        p = np.zeros(8)
        best = evaluate(p)
        step = np.array(steps0, float)
        for _ in range(STAGE2_SWEEPS):
            improved = False
            for q in range(8):
                if step[q] <= 0:
                    continue
                for sgn in (1.0, -1.0):
                    pt = p.copy()
                    pt[q] += sgn * step[q]
                    res = evaluate(pt)
                    if res[0] > best[0]:
                        p, best, improved = pt, res, True
                        break
            if not improved:
                step = step / 2
        sc, dx, dy = best
        score = sc
        # the template at bed x sits in the rectified field at D(x) + t: the picture shows
        # bed x at H(D(x) + t)
        t_bed = M[:2, :2] @ [dx, dy]
        Tt = np.array([[1, 0, t_bed[0]], [0, 1, t_bed[1]], [0, 0, 1.0]])
        H = H @ Tt @ Ni @ _pose_D(p) @ N
        H = H / H[2, 2]
    return H, score


# -- the whole search ---------------------------------------------------------------------
#: Stage-2 score (normalised correlation of the line fields, 0..1) below which nothing
#: convincing of the pattern was found. Measured: the realdata photos 0.43-0.45 (the
#: wrong candidates 0.08-0.33).
MIN_SCORE = 0.35
#: A different pose (the two differ by more than AMBIGUOUS_MM somewhere on the test
#: tracks) scoring at least this fraction of the best makes the match ambiguous.
AMBIGUOUS_RATIO = 0.9
AMBIGUOUS_MM = 1.5
#: Candidates of stage 1 refined in stage 2 (the true pose ranked <= 3rd in stage 1 on the
#: realdata photos and renders; 180-deg turns of a nearly symmetric layout come first).
N_REFINE = 5


def _pose_distance_mm(H1, H2, pts, scale_px_per_mm):
    """Largest distance (mm, at the image scale) between two mappings over ``pts``."""
    return float(np.max(np.hypot(*(_apply(H1, pts) - _apply(H2, pts)).T))) / scale_px_per_mm


def find_pose(gray, manifest, *, hint_rotation_deg: float | None = None, mirror: bool | None = None) -> dict:
    """Stages 1 and 2: the best homography bed mm -> px for ``manifest``'s print in ``gray``
    (float32 0..1, full resolution) with no fiducials and no clicks.

    hint_rotation_deg  optional rough rotation of the print in the picture (deg,
                       counter-clockwise, 0 = bed +x to the right): only +-25 deg around
                       it are kept
    mirror             None: search the direct and the mirror view (a print scanned face
                       down); False: the direct view only; True: the mirror view only
    Returns {"H", "score", "second_score", "ambiguous", "scale_px_per_mm", "mirrored",
    "candidates", "time_s"}.
    """
    t0 = time.perf_counter()
    gray = np.asarray(gray, np.float32)
    nozzle = float(manifest.printer.get("nozzle_diameter_mm", 0.4) or 0.4)
    seg = path_segments(manifest)
    pyr = _Pyramid(gray)
    tmpl = PathTemplate(seg, nozzle)
    tests = manifest.test_tracks()
    test_pts = np.concatenate([tr.points_mm for tr in tests]) if tests else np.concatenate([seg[0], seg[1]])
    results = []

    # a print scanned face down is seen mirrored; a mirror-image pose of a spiral pattern
    # can score ~0.5 on the direct view, so both views compete unless told otherwise
    views = {None: (False, True), False: (False,), True: (True,)}[mirror]
    cands = coarse_search(gray, seg, nozzle, views=views, top=N_REFINE)
    if hint_rotation_deg is not None:
        cands = [c for c in cands if abs((c.rotation_deg - hint_rotation_deg + 180) % 360 - 180) <= 25] or cands
    for c in cands:
        H, sc = refine_search(pyr, tmpl, c.H)
        c.refined_score = sc
        results.append((sc, H, c))
    results.sort(key=lambda r: -r[0])
    best_sc, best_H, best_c = results[0]
    k = float(np.median(_local_scale(best_H, test_pts[:: max(1, len(test_pts) // 200)])))
    second = 0.0
    for sc, H, c in results[1:]:
        if _pose_distance_mm(best_H, H, test_pts, k) > AMBIGUOUS_MM:
            second = max(second, sc)
    return {"H": best_H, "score": best_sc, "second_score": second,
            "ambiguous": bool(best_sc >= MIN_SCORE and second >= AMBIGUOUS_RATIO * best_sc),
            "scale_px_per_mm": k, "mirrored": bool(np.linalg.det(best_H[:2, :2]) > 0),
            "candidates": [(round(r[2].score, 3), round(r[0], 3), r[2].rotation_deg, round(r[2].scale_px_per_mm, 2),
                            r[2].mirrored) for r in results],
            "time_s": time.perf_counter() - t0}


def _local_scale(H, pts):
    """px per mm of the homography at ``pts`` (sqrt of the local Jacobian determinant)."""
    e = 0.5
    a = _apply(H, pts)
    bx = _apply(H, pts + [e, 0.0]) - a
    by = _apply(H, pts + [0.0, e]) - a
    return np.sqrt(np.abs(bx[:, 0] * by[:, 1] - bx[:, 1] * by[:, 0])) / e


def auto_register(gray, manifest, **kw):
    """Registration (measure.register.Registration, method "auto+tracks") of a picture with
    no fiducials and no point hints: :func:`find_pose`, then the track-layout refinement of
    :func:`measure.register.register` from that start (bead scale, lens k1, k2).

    The result's ``info`` holds the search's scores; ``info["refusal"]`` is set (one line)
    when nothing convincing was found or two different poses fit alike, for the caller to
    refuse after drawing the QA overlay. Keywords go to :func:`find_pose`."""
    from measure.register import PHONE_FOCAL_FRACTION, Registration, register

    found = find_pose(gray, manifest, **kw)
    t1 = time.perf_counter()
    try:
        reg = register(gray, manifest, start_H=found["H"])
    except UserError:
        if found["score"] >= MIN_SCORE and not found["ambiguous"]:
            raise
        # nothing convincing was found, and its best guess does not even hold the print:
        # that guess, unrefined, so the refusal below still comes with its overlay
        h, w = np.asarray(gray).shape[:2]
        reg = Registration(H=found["H"] / found["H"][2, 2],
                           distortion={"center_px": ((w - 1) / 2, (h - 1) / 2),
                                       "f_px": PHONE_FOCAL_FRACTION * max(w, h), "k1": 0.0, "k2": 0.0},
                           residual_mm=float("nan"), n_markers=0, mirrored=found["mirrored"], method="auto",
                           image_size=(w, h))
    info = {k: v for k, v in found.items() if k not in ("H",)}
    info["time_s"] = found["time_s"] + (time.perf_counter() - t1)
    if found["score"] < MIN_SCORE:
        info["refusal"] = (f"automatic registration found no convincing match of the pattern's tracks "
                           f"(score {found['score']:.2f} < {MIN_SCORE:g}): is it a picture of this print? "
                           "Give --points \"x_mm,y_mm=u_px,v_px;...\" to register it by hand")
    elif found["ambiguous"]:
        info["refusal"] = (f"automatic registration is ambiguous: two different poses fit the tracks alike "
                           f"(scores {found['score']:.2f} and {found['second_score']:.2f}); give --points "
                           "\"x_mm,y_mm=u_px,v_px;...\" to register it by hand")
    reg.info = info
    return reg


# -- stage 4: the measured bead centres ---------------------------------------------------
#: Stations used by :func:`refine_with_centres` (speed; spread over all tracks).
ICP_STATIONS = 4000


def refine_with_centres(reg, x_mm, y_mm, nx, ny, centre_mm, valid, track=None):
    """The registration moved so that the measured bead centre lines lie on the planned
    path: an ICP step (Besl & McKay 1992) with point-to-line distances (Chen & Medioni
    1992), each station's correspondence being the bead centre the width fit found along
    the track normal.

    Station i at bed x_i with unit normal n_i had its bead centre at x_i + c_i n_i under
    ``reg``; the new mapping (8 homography entries and k1, k2, as in measure.register)
    should put x_i where ``reg`` put that centre, along the image normal. Soft-L1 loss
    with a 0.03 mm scale: beads that are not where planned (blobs, ooze, a line bent by
    the nozzle) are outliers. Returns a new Registration (method + "+centres") whose place
    covariance is that of the new pose (:func:`icp_covariance`, stations clustered by
    ``track`` when given), or ``reg`` when there are fewer than 50 usable stations."""
    from dataclasses import replace

    from scipy import optimize

    from measure.register import _Mapping

    c = np.asarray(centre_mm, float)
    good = np.asarray(valid, bool) & np.isfinite(c)
    if good.sum() < 50:
        return reg
    idx = np.flatnonzero(good)
    idx = idx[np.linspace(0, len(idx) - 1, min(len(idx), ICP_STATIONS)).astype(int)]
    p = np.column_stack([x_mm, y_mm])[idx].astype(float)
    n = np.column_stack([nx, ny])[idx].astype(float)
    c = c[idx]
    target = reg.project(p + c[:, None] * n)
    d = reg.project(p + 0.05 * n) - reg.project(p)
    ppm = np.hypot(d[:, 0], d[:, 1]) / 0.05                  # px per mm across the track
    nimg = d / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    mp = _Mapping(reg.H, reg.image_size, True, p)
    x0 = mp.x0(reg.distortion["k1"], reg.distortion["k2"])
    n_st = len(p)
    # The start pose holds what no station constrains (along a set of parallel lines the
    # homography's stretch and shear trade with perspective and the lens): a pull, in mm,
    # on where the new pose puts 9 points spread over the stations, of sd PULL_SD_MM each.
    # A weak pull on the normalised homography entries instead let the along-line scale of
    # synthetic parallel lines collapse tenfold, and so did this one at 1.5 mm.
    lo, hi = p.min(axis=0), p.max(axis=0)
    ctrl = np.array([[u, v] for u in (lo[0], (lo[0] + hi[0]) / 2, hi[0]) for v in (lo[1], (lo[1] + hi[1]) / 2, hi[1])])
    ctrl_uv = reg.project(ctrl)
    ctrl_ppm = reg.px_per_mm(ctrl)
    pull_w = ICP_SCALE_MM / PULL_SD_MM
    # Lens terms: over a pattern that fills part of the picture k1 and k2 trade off, and a
    # free k2 runs off (-0.7 on a 12 MP phone render); their pull to 0 costs as much as a
    # 10 um misfit of every station would at |k1| = 0.2, |k2| = 0.1 (real phone lenses
    # stay inside that)
    w = 0.01 * np.sqrt(n_st)

    def stations(x):
        return np.sum((mp.project(x, p) - target) * nimg, axis=1) / ppm

    def resid(x):
        pull = ((mp.project(x, ctrl) - ctrl_uv) / ctrl_ppm[:, None]).ravel() * pull_w
        return np.concatenate([stations(x), pull, [w * x[8] / 0.2, w * x[9] / 0.1]])

    sol = optimize.least_squares(resid, x0, method="trf", loss="soft_l1", f_scale=ICP_SCALE_MM, x_scale="jac",
                                 max_nfev=50)
    xs = sol.x
    H = mp.H(xs)
    k1, k2 = mp.k(xs)
    dist = dict(reg.distortion, k1=float(k1), k2=float(k2))
    groups = np.asarray(track)[idx] if track is not None else np.arange(n_st)
    cov = icp_covariance(stations, resid, xs, groups, n_pull=2 * len(ctrl), start_shift=START_SD_MM * pull_w)
    from measure.register import place_covariance
    return replace(reg, H=H / H[2, 2], distortion=dist, method=reg.method + "+centres",
                   info=dict(reg.info), warnings=list(reg.warnings),
                   place_cov_mm2=place_covariance(mp, xs, cov, reg.place_pts_mm))


#: :func:`refine_with_centres`: the soft-L1 scale of the stations' misfit (mm); the sd
#: (mm) of the pull on each of the 9 points, which keeps the ICP from drifting where no
#: station holds it; and the sd (mm) of the start pose's place as a whole (a shift of all
#: 9 points alike), which :func:`icp_covariance` carries where no station holds the pose:
#: the track refinement's pose sat 0.05-0.16 mm off along the lines where the centres
#: held it (0.107 mm on a flatbed render of PLA1's G-code, 0.16 on SpStartStopTest2; its
#: Laplace sd said 0.026-0.056), and 0.5-0.9 mm along the parallel lines of our retract
#: pattern printed without markers (bench_autoreg: lines whose ends thin out, nothing
#: across them).
ICP_SCALE_MM = 0.03
PULL_SD_MM = 0.15
START_SD_MM = 0.5


def icp_covariance(stations, resid, x, groups, n_pull: int = 0, start_shift: float = 0.0,
                   h: float = 1e-7) -> np.ndarray:
    """Covariance of the ICP pose ``x`` (10,) of :func:`refine_with_centres`: the sandwich
    Cov = B^-1 M B^-1 of its M-estimator (Huber 1967) under a random-effects model of the
    stations' misfits, each track k laid off its line as a whole:

        psi(r_i) = u_k(i) + e_i,   Var u_k = tau^2,   Var e_i = sigma^2
        B = J^T Psi' J,   M = sigma^2 J_s^T J_s + tau^2 sum_k q_k q_k^T + (priors),
        q_k = sum_{i in k} J_i

    r the residual vector ``resid`` (the stations' misfits ``stations(x)`` in mm, then
    ``n_pull`` pulls to the start, (x, y) of each point in turn, and the rest lens priors),
    J its Jacobian (J_s the stations' rows), psi the soft-L1 influence r / sqrt(1 + (r/c)^2)
    and psi' its slope. sigma^2 is the variance of the stations' psi about their track's
    mean, tau^2 the variance of the track means less their own noise (method of moments),
    k over the ``groups`` (a station's track). The pulls' residuals err by the start pose's
    own error: a shift of every point alike, sd ``start_shift`` in residual units in x and
    in y, so directions no station constrains keep the start's uncertainty whatever the
    pulls' weight; the lens priors are pseudo-observations of sd ICP_SCALE_MM.

    Why: a printer lays each track off its commanded line as a whole (0.1-0.2 mm on
    StartStopTestPLA1, measure/placement.py), so along straight parallel lines the pose is
    set by the few tracks that cross them, and their placements, not hundreds of stations'
    noise, say how well: the centres moved PLA1's pose 0.19-0.23 mm along its lines, where
    the Laplace sd of the step before said 0.026 mm. The random-effects meat rather than
    the cluster-robust one (Liang & Zeger 1986): that needs many clusters in every
    direction, and with 3 tracks across it read about half the true spread.

    Only the start's shift is carried, not its stretch or turn: as large a turn at the
    print's edge (0.5 mm) made the spiral renders' sd 0.09-0.14 mm for errors of 1-10 um
    (circles turn onto themselves; the track refinement held the turn by the rest of the
    layout); the retract render's start, sheared 0.9 mm at its edge, is covered by the
    shift's sd at |z| <= 1.7 (bench_autoreg)."""
    x = np.asarray(x, float)
    r = resid(x)
    n_st = len(stations(x))
    J = np.empty((len(r), len(x)))
    for k in range(len(x)):
        step = h * max(1.0, abs(x[k]))
        xp = x.copy()
        xp[k] += step
        J[:, k] = (resid(xp) - r) / step
    dpsi = (1.0 + (r / ICP_SCALE_MM) ** 2) ** -1.5
    B = J.T @ (dpsi[:, None] * J)
    # the random-effects variances of the stations' influences psi (their scores' parts)
    z = 1.0 + (r[:n_st] / ICP_SCALE_MM) ** 2
    psi, Js = r[:n_st] / np.sqrt(z), J[:n_st]
    _, inv = np.unique(np.asarray(groups), return_inverse=True)
    G = inv.max() + 1
    n_k = np.bincount(inv, minlength=G).astype(float)
    m_k = np.bincount(inv, weights=psi, minlength=G) / np.maximum(n_k, 1.0)
    sigma2 = float(np.sum((psi - m_k[inv]) ** 2) / max(n_st - G, 1))
    big = n_k >= 2
    tau2 = max(float(np.var(m_k[big], ddof=1) - np.mean(sigma2 / n_k[big])), 0.0) if big.sum() >= 2 else 0.0
    q = np.zeros((G, len(x)))
    np.add.at(q, inv, Js)
    M = sigma2 * (Js.T @ Js) + tau2 * (q.T @ q)
    pull = slice(n_st, n_st + n_pull)
    Jp = dpsi[pull, None] * J[pull]
    # the start's shift moves every x residual alike, and every y residual alike
    sx, sy = Jp[0::2].sum(axis=0), Jp[1::2].sum(axis=0)
    M += start_shift ** 2 * (np.outer(sx, sx) + np.outer(sy, sy))
    lens = slice(n_st + n_pull, len(r))
    Jl = dpsi[lens, None] * J[lens]
    M += ICP_SCALE_MM ** 2 * (Jl.T @ Jl)
    Bi = np.linalg.pinv(B)
    return Bi @ M @ Bi
