"""Synthetic flatbed scans and phone photos of a printed pattern, with exact ground truth.

What "true width" means
-----------------------
A bead of width w seen from above is rendered as the *Gaussian-softened footprint* of a
band of width w about the track's centre line: its plastic coverage at distance d (mm)
from the centre line is

    alpha(d) = Phi((w/2 - d) / s_e) - Phi((-w/2 - d) / s_e)              (1)

with Phi the standard normal CDF and s_e (mm) the edge softness of the rounded bead
(default 0.15 h, h the layer height: the bead's rounded flank thins the plastic towards
the edge). Each edge therefore passes through coverage 1/2 exactly at d = w/2: **the true
width is the distance between the two 50 % coverage points**, and it is the ``w`` of the
edge-pair erf model the measurement fits (shared/REFERENCE.md "Measuring width").
Image intensity is linear in coverage, I = plate (1 - o alpha) + plastic o alpha (o the
opacity), and every later blur (optics, pixel area) is symmetric, so the half-contrast
crossings of a straight bead stay at +-w/2 for w >> s_e.

Geometry is exact because nothing is resampled: every camera (sub)pixel is unprojected
to bed mm through the true :class:`~measure.camera.Camera` and the coverage (1) is
evaluated analytically there, against the distance to the track's polyline (union of
stadium-shaped segments with linearly varying width). Test tracks take their width from
the ``widths`` table (interpolated between samples along s); every other track (prime,
fiducial, ruler, label) its commanded width. Separate tracks add coverage (clipped at 1)
so touching raster lines of a fiducial print solid, as they do on a real plate.

That footprint is the very edge model measure/edges.py fits. ``realism`` (measure/
phenomena.py) renders what it does not assume: with "profile" a bead is the slicer's
rounded rectangle seen from above (:func:`_track_profile`: hard footprint edge, shaded
flanks, Beer-Lambert translucency, specular highlights) and the true width is the
footprint, not the 50 % point of (1); "strings" and "raster_gaps" draw the virtual
printer's deposition on travel moves and non-test tracks.

Everything that is not the pattern (plate texture, plate logos, scratches, cutting mat)
is drawn on a bed-space raster and mapped into the camera with ``cv2.remap``; lighting,
vignetting, defocus blur, shot + read noise and JPEG compression follow in image space.
Images are uint8 BGR (OpenCV order).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit, prange
from scipy.special import ndtr

from measure.camera import Camera
from measure.table import WidthTable
from measure.truth_io import ScanTruth
from patterns.manifest import Manifest, sample_points

#: Edge softness s_e as a fraction of the layer height (see module docstring, eq. 1).
EDGE_SOFTNESS_PER_HEIGHT = 0.15
#: Coverage is evaluated out to this many s_e beyond the edge.
_EDGE_REACH = 6.0


@dataclass
class Lighting:
    """Uneven illumination, as factors on the exposure.

    exposure        reflectance 1.0 -> this many DN (0-255) at the brightest spot
    gradient        (gx, gy) fractional brightness change across the image width/height
    vignetting      fractional fall-off at the image corners (quadratic in radius)
    glare           amplitude (DN) of a soft additive hotspot (phone flash/window), 0 = none
    """

    exposure: float = 235.0
    gradient: tuple[float, float] = (0.0, 0.0)
    vignetting: float = 0.0
    glare: float = 0.0

    @classmethod
    def for_camera(cls, kind: str, rng: np.random.Generator) -> "Lighting":
        if kind == "phone":
            return cls(exposure=225.0, gradient=tuple(rng.uniform(-0.15, 0.15, 2)), vignetting=0.30,
                       glare=float(rng.uniform(6.0, 14.0)))
        return cls(exposure=235.0, gradient=tuple(rng.uniform(-0.03, 0.03, 2)), vignetting=0.0, glare=0.0)


@dataclass
class Rendered:
    """A synthetic picture and its ground truth.

    image     (H, W, 3) uint8 BGR, what the file holds (after JPEG if any)
    truth     :class:`measure.truth_io.ScanTruth` (camera, true widths, settings)
    encoded   the JPEG bytes when ``jpeg_quality`` was set (write these, do not re-encode)
    """

    image: np.ndarray
    truth: ScanTruth
    encoded: bytes | None = None

    @property
    def camera(self) -> Camera:
        return self.truth.camera

    @property
    def table(self) -> WidthTable:
        return self.truth.widths


# =====================================================================================
# numba kernels
# =====================================================================================
@njit(parallel=True, cache=True)
def unproject_grid(Hinv, cx, cy, f, k1, k2, width, height, ss, X, Y):  # pragma: no cover - numba
    """Bed mm (X, Y float32 (height*ss, width*ss)) of every sub-pixel centre of the image.

    Sub-pixel (i, j) of a grid ``ss`` times finer sits at u = (i + 0.5)/ss - 0.5 (OpenCV
    pixel centres at integers). Undistortion by Newton along the radius (camera.undistort_px).
    """
    distorted = (k1 != 0.0) or (k2 != 0.0)
    for j in prange(height * ss):
        v = (j + 0.5) / ss - 0.5
        for i in range(width * ss):
            u = (i + 0.5) / ss - 0.5
            if distorted:
                dx = (u - cx) / f
                dy = (v - cy) / f
                rd = math.sqrt(dx * dx + dy * dy)
                r = rd
                for _ in range(4):
                    r2 = r * r
                    r = r - (r * (1.0 + k1 * r2 + k2 * r2 * r2) - rd) / (1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2)
                s = r / rd if rd > 0 else 1.0
                uu = cx + f * dx * s
                vv = cy + f * dy * s
            else:
                uu = u
                vv = v
            q0 = Hinv[0, 0] * uu + Hinv[0, 1] * vv + Hinv[0, 2]
            q1 = Hinv[1, 0] * uu + Hinv[1, 1] * vv + Hinv[1, 2]
            q2 = Hinv[2, 0] * uu + Hinv[2, 1] * vv + Hinv[2, 2]
            X[j, i] = q0 / q2
            Y[j, i] = q1 / q2


@njit(cache=True)
def _window(bbox, k0, k1):  # pragma: no cover - numba
    """Sub-pixel window (i0, i1, j0, j1) covering the segments k0..k1 of one bead."""
    return bbox[k0:k1, 0].min(), bbox[k0:k1, 1].max(), bbox[k0:k1, 2].min(), bbox[k0:k1, 3].max()


@njit(cache=True)
def _nearest_field(X, Y, seg, segw, bbox, k0, k1, i0, j0, E, Wd, OX, OY):  # pragma: no cover - numba
    """For the sub-pixels of one bead (segments k0..k1, window offset i0, j0): signed
    distance inside the edge E = w/2 - d (mm) to the nearest segment (largest E wins),
    the width there, and (if OX has the window's shape) the unit offset direction from
    the centre line. Serial: segments are small, a parallel launch per segment costs more
    than it saves."""
    with_dir = OX.shape[0] == E.shape[0]
    for k in range(k0, k1):
        ax, ay, bx, by = seg[k, 0], seg[k, 1], seg[k, 2], seg[k, 3]
        w0, w1 = segw[k, 0], segw[k, 1]
        dx = bx - ax
        dy = by - ay
        L2 = dx * dx + dy * dy
        for j in range(bbox[k, 2], bbox[k, 3]):
            for i in range(bbox[k, 0], bbox[k, 1]):
                px = X[j, i] - ax
                py = Y[j, i] - ay
                tp = (px * dx + py * dy) / L2 if L2 > 0 else 0.0
                tp = min(1.0, max(0.0, tp))
                ex = px - tp * dx
                ey = py - tp * dy
                w = w0 + tp * (w1 - w0)
                dist = math.sqrt(ex * ex + ey * ey)
                e = 0.5 * w - dist
                if e > E[j - j0, i - i0]:
                    E[j - j0, i - i0] = e
                    Wd[j - j0, i - i0] = w
                    if with_dir:
                        OX[j - j0, i - i0] = ex / dist if dist > 1e-9 else 0.0
                        OY[j - j0, i - i0] = ey / dist if dist > 1e-9 else 0.0


@njit(parallel=True, cache=True)
def _track_coverage(X, Y, seg, segw, bbox, starts, track_sigma, alpha):  # pragma: no cover - numba
    """Add the coverage (eq. 1) of every track to ``alpha`` (clipped at 1).

    seg (N, 4) segment end points (ax, ay, bx, by) mm; segw (N, 2) widths at the ends (mm);
    bbox (N, 4) sub-pixel window (i0, i1, j0, j1) of each segment; starts (T+1) segment
    index ranges per track; track_sigma (T,) edge softness s_e (mm).
    Within one track the nearest segment (largest w/2 - d) wins: a bead does not add to
    itself where consecutive segments overlap.
    """
    for t in range(len(starts) - 1):
        k0, k1 = starts[t], starts[t + 1]
        if k1 <= k0:
            continue
        i0, i1, j0, j1 = _window(bbox, k0, k1)
        if i1 <= i0 or j1 <= j0:
            continue
        E = np.full((j1 - j0, i1 - i0), -1e9, dtype=np.float32)
        Wd = np.zeros((j1 - j0, i1 - i0), dtype=np.float32)
        nodir = np.zeros((1, 1), dtype=np.float32)
        _nearest_field(X, Y, seg, segw, bbox, k0, k1, i0, j0, E, Wd, nodir, nodir)
        sg = track_sigma[t] * math.sqrt(2.0)
        reach = -_EDGE_REACH * track_sigma[t]
        for j in prange(j0, j1):
            for i in range(i0, i1):
                e = E[j - j0, i - i0]
                if e > reach:
                    w = Wd[j - j0, i - i0]
                    # Phi(e/s) - Phi((e - w)/s): eq. (1) with d = w/2 - e
                    a = 0.5 * (math.erf(e / sg) - math.erf((e - w) / sg))
                    alpha[j, i] = min(1.0, alpha[j, i] + a)


@njit(parallel=True, cache=True)
def _track_profile(X, Y, seg, segw, bbox, starts, track_h, aa_mm, hv, p_spec, ambient,
                   cov, thick, shade, spec, tmax):  # pragma: no cover - numba
    """Beads with their physical cross-section (measure/phenomena.py "profile").

    The slicer's rounded rectangle (fit/geometry.py): flat crown of half-width w/2 - r
    and elliptical flanks of lateral radius r = min(h/2, w/2) and height h, seen from
    above. Per sub-pixel: ``cov`` footprint coverage (a hard edge at w/2, box-filtered
    over ``aa_mm`` = one sub-pixel), ``thick`` summed plastic thickness (mm), and of the
    topmost bead: ``shade`` = ambient + (1 - ambient) n_z (Lambert, overhead diffuse
    light) and ``spec`` = max(0, n . hv)^p_spec (Blinn-Phong); ``tmax`` its thickness.
    """
    for t in range(len(starts) - 1):
        k0, k1 = starts[t], starts[t + 1]
        if k1 <= k0:
            continue
        i0, i1, j0, j1 = _window(bbox, k0, k1)
        if i1 <= i0 or j1 <= j0:
            continue
        E = np.full((j1 - j0, i1 - i0), -1e9, dtype=np.float32)
        Wd = np.zeros((j1 - j0, i1 - i0), dtype=np.float32)
        OX = np.zeros((j1 - j0, i1 - i0), dtype=np.float32)
        OY = np.zeros((j1 - j0, i1 - i0), dtype=np.float32)
        _nearest_field(X, Y, seg, segw, bbox, k0, k1, i0, j0, E, Wd, OX, OY)
        h = track_h[t]
        aa = aa_mm[t]
        for j in prange(j0, j1):
            for i in range(i0, i1):
                e = E[j - j0, i - i0]
                if e <= -0.5 * aa:
                    continue
                w = Wd[j - j0, i - i0]
                c = min(1.0, e / aa + 0.5)
                d = max(0.0, 0.5 * w - e)
                rl = min(0.5 * h, 0.5 * w)
                a = 0.5 * w - rl
                if d <= a:
                    tk = h
                    nh = 0.0
                    nz = 1.0
                else:
                    u = min(1.0, (d - a) / rl)
                    q = math.sqrt(max(0.0, 1.0 - u * u))
                    tk = h * q
                    gx = u / rl
                    gz = q / (0.5 * h)
                    nn = math.sqrt(gx * gx + gz * gz)
                    nh = gx / nn
                    nz = gz / nn
                tk *= c
                cov[j, i] = min(1.0, cov[j, i] + c)
                thick[j, i] += tk
                if tk > tmax[j, i]:
                    tmax[j, i] = tk
                    shade[j, i] = ambient + (1.0 - ambient) * nz
                    ndoth = nh * (OX[j - j0, i - i0] * hv[0] + OY[j - j0, i - i0] * hv[1]) + nz * hv[2]
                    spec[j, i] = max(0.0, ndoth) ** p_spec


# =====================================================================================
# geometry preparation
# =====================================================================================
def _track_pieces(track, widths: WidthTable | None, step_mm: float = 0.25, turn_deg: float = 100.0):
    """Segments to draw for one track, split into pieces that each form one bead.

    Returns a list of (seg (K, 4) [ax, ay, bx, by] mm, w (K, 2) end widths mm). Each
    vertex-to-vertex segment is cut into pieces of <= ``step_mm``; widths come from the
    ``widths`` table (test tracks, linear in s between samples) or from the per-vertex
    commanded widths. A segment with zero width at both ends (coasting, travel inside the
    track) is not drawn and ends the piece; a turn sharper than ``turn_deg`` (raster
    U-turns) starts a new piece, so neighbouring raster lines add up instead of leaving a
    half-coverage seam where one bead's max-distance union would meet itself. Furniture
    (markers, labels) turns at 60 deg: a marker's serpentine makes its U-turns as two
    90-degree turns (patterns/fiducials.py raster_chains).
    """
    pts, cl = track.points_mm, track.cumlen_mm
    tab = curve = None
    if widths is not None and track.kind == "test":
        sel = widths.track == track.id
        if sel.any():
            order = np.argsort(widths.s_mm[sel])
            tab = widths.s_mm[sel][order], np.maximum(np.nan_to_num(widths.width_mm[sel][order]), 0.0)
            curve = _curved_spans(*tab)
    pieces, cur_seg, cur_w = [], [], []
    last_dir = None
    cos_turn = np.cos(np.deg2rad(turn_deg if track.kind == "test" else min(turn_deg, 60.0)))

    def flush():
        if cur_seg:
            pieces.append((np.vstack(cur_seg), np.vstack(cur_w)))
            cur_seg.clear()
            cur_w.clear()

    for i in range(len(pts) - 1):
        L = cl[i + 1] - cl[i]
        if L <= 1e-9:
            continue
        n = int(np.ceil(L / step_mm))
        f = np.linspace(0.0, 1.0, n + 1)
        if tab is not None:
            f = _refined(f, cl[i], L, curve)
            w = _station_curve(cl[i] + f * L, tab, curve)
        else:
            w = track.width_mm[i] + f * (track.width_mm[i + 1] - track.width_mm[i])
        w = np.maximum(np.nan_to_num(w), 0.0)
        d = (pts[i + 1] - pts[i]) / L
        if w.max() <= 0:
            flush()
            last_dir = None
            continue
        if last_dir is not None and float(d @ last_dir) < cos_turn:
            flush()
        last_dir = d
        xy = pts[i] + f[:, None] * (pts[i + 1] - pts[i])
        cur_seg.append(np.hstack([xy[:-1], xy[1:]]))
        cur_w.append(np.column_stack([w[:-1], w[1:]]))
    flush()
    return pieces


#: Between stations whose widths bend (second difference above this, mm) a bead is drawn
#: along the monotone cubic through them every CURVE_STEP_MM, not along their chords: the
#: chords of a convex decay lie above it, and the measurement's strip read them 1-2 um wide
#: on the RetractTest's restore tails ((w[j-1] - 2 w[j] + w[j+1]) / 8 for a strip one
#: station long), which a fit of the right model took for `spread` (Delta BIC 520) and a
#: 1 % longer tau.
CURVE_D2_MM = 4e-4
CURVE_STEP_MM = 0.05


def _curved_spans(s, w):
    """Station intervals [s_j-1, s_j+1] (rows of an (n, 2) array, mm) around the stations
    where the widths bend, with the monotone cubic (PCHIP, Fritsch & Carlson 1980) through
    all the stations: (spans, interpolant), or None where nothing bends."""
    from scipy.interpolate import PchipInterpolator

    if len(s) < 3 or np.any(np.diff(s) <= 0):
        return None
    d2 = np.abs(w[:-2] - 2 * w[1:-1] + w[2:])
    j = np.flatnonzero(d2 > CURVE_D2_MM) + 1
    if not len(j):
        return None
    # overlapping spans merged: disjoint, in order (searchsorted finds a point's span)
    a, b = s[j - 1], s[j + 1]
    new = np.r_[True, a[1:] > b[:-1]]
    starts = a[new]
    ends = np.maximum.reduceat(b, np.flatnonzero(new))
    return np.column_stack([starts, ends]), PchipInterpolator(s, w, extrapolate=False)


def _refined(f, s0, L, curve):
    """Fractions ``f`` of a segment starting at arc length ``s0`` (length L mm) with the
    points every CURVE_STEP_MM added where it crosses a curved span."""
    if curve is None:
        return f
    spans = curve[0]
    lo, hi = s0, s0 + L
    k0 = max(int(np.searchsorted(spans[:, 1], lo, "right")), 0)
    k1 = int(np.searchsorted(spans[:, 0], hi, "left"))
    hit = spans[k0:k1]
    if not len(hit):
        return f
    extra = [np.arange(max(a, lo), min(b, hi), CURVE_STEP_MM) for a, b in hit]
    return np.unique(np.concatenate([f] + [(e - s0) / L for e in extra]).clip(0.0, 1.0))


def _station_curve(s, tab, curve):
    """Widths (mm) at arc lengths ``s``: linear between stations, the monotone cubic where
    they bend (:func:`_curved_spans`)."""
    w = np.interp(s, tab[0], tab[1])
    if curve is not None:
        spans, pchip = curve
        k = np.searchsorted(spans[:, 0], s, "right") - 1
        inside = (k >= 0) & (s <= spans[np.maximum(k, 0), 1])
        if inside.any():
            w[inside] = np.nan_to_num(pchip(s[inside]), nan=0.0)
    return w


def _segments(manifest: Manifest, widths: WidthTable | None, camera: Camera, ss: int,
              edge_mm: float | None, deposits=None, blobs=()):
    """Segments of every bead piece, their sub-pixel windows, and per piece (s_e, h).

    ``deposits`` = (track_pieces, strings) of :func:`measure.phenomena.deposit_pieces`:
    non-test tracks drawn at their deposited widths, travel strings added (h = d).
    ``blobs``: discs (x_mm, y_mm, diameter_mm, h_mm), each a piece of its own (a segment
    of zero length is a disc).
    """
    track_over, strings = deposits if deposits is not None else ({}, [])
    seg, segw, sig, hs, starts = [], [], [], [], [0]

    def add(sg, sw, h):
        seg.append(sg)
        segw.append(sw)
        starts.append(starts[-1] + len(sg))
        sig.append(edge_mm if edge_mm is not None else EDGE_SOFTNESS_PER_HEIGHT * max(h, 0.05))
        hs.append(max(h, 0.02))

    for tr in manifest.tracks:
        h = float(np.nanmean(tr.height_mm)) if len(tr.height_mm) else 0.2
        pieces = track_over[tr.id] if tr.id in track_over else \
            _track_pieces(tr, widths, step_mm=0.25 if tr.kind == "test" else 1.0)
        for sg, sw in pieces:
            add(sg, sw, h)
    for sg, sd, d_mean in strings:
        add(sg, sd, d_mean)
    for x, y, dia, h in blobs:
        if dia > 0:
            add(np.array([[x, y, x, y]], float), np.array([[dia, dia]], float), h)
    if not seg:
        return None
    seg = np.vstack(seg)
    segw = np.vstack(segw)
    sig = np.asarray(sig, dtype=float)
    track_of_seg = np.repeat(np.arange(len(sig)), np.diff(starts))
    r = segw.max(axis=1) / 2 + _EDGE_REACH * sig[track_of_seg] + 0.01
    lo = np.minimum(seg[:, :2], seg[:, 2:]) - r[:, None]
    hi = np.maximum(seg[:, :2], seg[:, 2:]) + r[:, None]
    corners = np.stack([lo, np.column_stack([hi[:, 0], lo[:, 1]]), hi,
                        np.column_stack([lo[:, 0], hi[:, 1]])], axis=1).reshape(-1, 2)
    uv = camera.project(corners).reshape(-1, 4, 2)
    W, H = camera.image_size
    # sub-pixel index of u is (u + 0.5) ss - 0.5; 2 sub-pixels of margin for lens curvature
    sub = (uv + 0.5) * ss - 0.5
    i0 = np.clip(np.floor(sub[..., 0].min(axis=1)) - 2, 0, W * ss).astype(np.int64)
    i1 = np.clip(np.ceil(sub[..., 0].max(axis=1)) + 3, 0, W * ss).astype(np.int64)
    j0 = np.clip(np.floor(sub[..., 1].min(axis=1)) - 2, 0, H * ss).astype(np.int64)
    j1 = np.clip(np.ceil(sub[..., 1].max(axis=1)) + 3, 0, H * ss).astype(np.int64)
    bbox = np.column_stack([i0, np.maximum(i1, i0), j0, np.maximum(j1, j0)])
    return seg, segw, bbox, np.asarray(starts, dtype=np.int64), sig, np.asarray(hs, dtype=float)


def _aruco_bits(marker_id: int, dictionary: str) -> np.ndarray:
    """(8, 8) printed bitmap (marker + 1-cell quiet frame), 1 = plastic, row 0 on top."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    bits = (cv2.aruco.generateImageMarker(d, int(marker_id), 6) > 127).astype(float)
    return np.pad(bits, 1, constant_values=1.0)


def _fiducial_cells(manifest: Manifest, X, Y, camera: Camera, ss: int, sigma_mm: float, alpha):
    """Draw fiducials that no ``fiducial`` track prints, as solid cells.

    The blurred indicator of a union of disjoint cells is the sum of separable terms
    [Phi((a - a0)/s) - Phi((a - a1)/s)] [Phi((b - b0)/s) - Phi((b - b1)/s)] in marker
    coordinates (a, b), so cells join without seams.
    """
    fid_pts = [tr.points_mm for tr in manifest.tracks if tr.kind == "fiducial"]
    fid_pts = np.vstack(fid_pts) if fid_pts else np.zeros((0, 2))
    W, H = camera.image_size
    for fd in manifest.fiducials:
        c = np.asarray(fd.corners_mm, dtype=float)          # TL, TR, BR, BL
        size = float(fd.size_mm)
        cell = size / 6.0
        bl = c[3]
        ea = (c[2] - c[3]) / np.linalg.norm(c[2] - c[3])
        eb = (c[0] - c[3]) / np.linalg.norm(c[0] - c[3])
        if len(fid_pts):
            rel = fid_pts - bl
            a, b = rel @ ea, rel @ eb
            if np.any((a > -cell) & (a < size + cell) & (b > -cell) & (b < size + cell)):
                continue   # printed as raster tracks: drawn with the tracks
        m = cell + 5 * sigma_mm
        quad = bl + np.array([[-m, -m], [size + m, -m], [size + m, size + m], [-m, size + m]]) @ np.vstack([ea, eb])
        sub = (camera.project(quad) + 0.5) * ss - 0.5
        i0, j0 = np.clip(np.floor(sub.min(axis=0)) - 2, 0, [W * ss, H * ss]).astype(int)
        i1, j1 = np.clip(np.ceil(sub.max(axis=0)) + 3, 0, [W * ss, H * ss]).astype(int)
        if i1 <= i0 or j1 <= j0:
            continue
        px = X[j0:j1, i0:i1].astype(float) - bl[0]
        py = Y[j0:j1, i0:i1].astype(float) - bl[1]
        a = px * ea[0] + py * ea[1]
        b = px * eb[0] + py * eb[1]
        bits = _aruco_bits(fd.id, fd.dictionary)
        edges = (np.arange(9) - 1) * cell                     # cell boundaries, a and b
        Fa = ndtr((a[None] - edges[:, None, None]) / sigma_mm)  # (9, h, w)
        Fb = ndtr((b[None] - edges[:, None, None]) / sigma_mm)
        fa = Fa[:-1] - Fa[1:]                                  # column c covers [edges[c], edges[c+1]]
        fb = Fb[:-1] - Fb[1:]
        # bitmap row r (0 = top) covers b in [edges[7 - r], edges[8 - r]]
        cov = np.einsum("rc,rhw,chw->hw", bits[::-1], fb, fa)
        alpha[j0:j1, i0:i1] = np.minimum(1.0, alpha[j0:j1, i0:i1] + cov.astype(np.float32))


# =====================================================================================
# background: plate, clutter, cutting mat (bed-space raster)
# =====================================================================================
_PLATE_WORDS = ("PEI", "TEXTURED", "SMOOTH", "235 x 235", "HOT", "CAUTION", "FRONT", "SPRING STEEL",
                "DO NOT TOUCH", "v2.1", "MAX 110 C")


def _pattern_rect(manifest: Manifest) -> np.ndarray:
    pts = [tr.points_mm for tr in manifest.tracks]
    pts += [np.asarray(f.corners_mm, dtype=float) for f in manifest.fiducials]
    P = np.vstack(pts) if pts else np.zeros((1, 2))
    return np.concatenate([P.min(axis=0), P.max(axis=0)])


def _background(manifest: Manifest, camera: Camera, Xc, Yc, plate: str, rng, clutter: bool,
                logos_inside: bool = False, logo_rng=None):
    """Reflectance image (H, W, 3) float32 of everything behind the plastic.

    ``logos_inside``: plate print (text, a logo ring) also under the pattern itself, drawn
    with ``logo_rng`` so the rest of the scene does not change.
    """
    W, H = camera.image_size
    pr = _pattern_rect(manifest)
    excl = pr + np.array([-4.0, -4.0, 4.0, 4.0])           # keep clutter off the pattern
    bx, by = manifest.printer.get("bed_x_mm"), manifest.printer.get("bed_y_mm")
    if isinstance(bx, (list, tuple)) and isinstance(by, (list, tuple)) and len(bx) == len(by) == 2:
        # the printer's plate, but never tighter than the pattern plus 10 mm
        plate_rect = np.array([min(float(bx[0]), pr[0] - 10), min(float(by[0]), pr[1] - 10),
                               max(float(bx[1]), pr[2] + 10), max(float(by[1]), pr[3] + 10)])
    else:
        m = rng.uniform(25.0, 45.0, 4)
        plate_rect = pr + np.array([-m[0], -m[1], m[2], m[3]])
    # bed-space extent seen by the camera
    border = np.concatenate([
        np.column_stack([np.linspace(0, W - 1, 41), np.zeros(41)]),
        np.column_stack([np.linspace(0, W - 1, 41), np.full(41, H - 1.0)]),
        np.column_stack([np.zeros(41), np.linspace(0, H - 1, 41)]),
        np.column_stack([np.full(41, W - 1.0), np.linspace(0, H - 1, 41)])])
    xy = camera.unproject(border)
    lo = np.maximum(xy.min(axis=0) - 2, pr[:2] - 250)
    hi = np.minimum(xy.max(axis=0) + 2, pr[2:] + 250)
    # clutter needs no more than ~10 px/mm; cap the raster at ~6 MP for speed and memory
    area = float(np.prod(hi - lo))
    ppmm = float(np.clip(min(np.max(camera.px_per_mm(xy)), np.sqrt(6e6 / area)), 1.0, 10.0))
    bw, bh = int(np.ceil((hi[0] - lo[0]) * ppmm)) + 1, int(np.ceil((hi[1] - lo[1]) * ppmm)) + 1

    def to_px(x, y):   # bed mm -> raster (col, row); the raster has +y up
        return (x - lo[0]) * ppmm, (hi[1] - y) * ppmm

    def ipt(x, y):
        c, r = to_px(x, y)
        return int(round(c * 16)), int(round(r * 16))   # 4 fractional bits

    # cutting mat: green with a 10 mm grid, bold lines every 50 mm
    img = np.empty((bh, bw, 3), np.float32)
    img[:] = (0.20, 0.36, 0.16) if clutter else (0.5, 0.5, 0.5)
    if clutter:
        for k in range(int(lo[0] // 10), int(hi[0] // 10) + 1):
            cv2.line(img, ipt(k * 10, lo[1]), ipt(k * 10, hi[1]), (0.55, 0.75, 0.5),
                     2 if k % 5 == 0 else 1, cv2.LINE_AA, 4)
        for k in range(int(lo[1] // 10), int(hi[1] // 10) + 1):
            cv2.line(img, ipt(lo[0], k * 10), ipt(hi[0], k * 10), (0.55, 0.75, 0.5),
                     2 if k % 5 == 0 else 1, cv2.LINE_AA, 4)
    # the plate, with rounded corners and its texture
    mask = np.zeros((bh, bw), np.float32)
    rad = 6.0
    x0, y0, x1, y1 = plate_rect
    rect_pts = np.array([ipt(x0 + rad, y0), ipt(x1 - rad, y0), ipt(x1, y0 + rad), ipt(x1, y1 - rad),
                         ipt(x1 - rad, y1), ipt(x0 + rad, y1), ipt(x0, y1 - rad), ipt(x0, y0 + rad)])
    cv2.fillPoly(mask, [rect_pts], 1.0, cv2.LINE_AA, 4)
    if plate == "dark":
        base = np.array([0.10, 0.10, 0.11], np.float32)
        grain = cv2.GaussianBlur(rng.standard_normal((bh, bw)).astype(np.float32), (0, 0), 0.6) * 0.05
        blot = _smooth_noise((bh, bw), 3 * ppmm, rng)
        tex = base[None, None, :] * (1.0 + grain + 0.06 * blot)[..., None]
        ink = (0.62, 0.62, 0.60)
    else:
        base = np.array([0.74, 0.76, 0.78], np.float32)
        blot = _smooth_noise((bh, bw), 8 * ppmm, rng)
        tex = base[None, None, :] * (1.0 + 0.015 * blot + 0.004 * rng.standard_normal((bh, bw)).astype(np.float32))[..., None]
        ink = (0.40, 0.40, 0.42)
    img = img * (1 - mask[..., None]) + tex * mask[..., None]
    if clutter or logos_inside:
        ink_mask = np.zeros((bh, bw), np.uint8)      # cv2.putText draws on 8-bit images only
        if clutter:
            _draw_clutter(ink_mask, plate_rect, excl, rng, ipt, ppmm)
        if logos_inside:
            _draw_plate_print(ink_mask, pr, logo_rng, ipt, ppmm)
        m = (ink_mask.astype(np.float32) / 255.0)[..., None]
        img = img * (1 - m) + np.asarray(ink, np.float32)[None, None, :] * m
    maps = ((Xc - lo[0]) * ppmm).astype(np.float32), ((hi[1] - Yc) * ppmm).astype(np.float32)
    return cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _smooth_noise(shape, sigma_px: float, rng) -> np.ndarray:
    """Unit-variance Gaussian random field of correlation length ``sigma_px``, made on a
    coarse grid and resized up (a full-size blur with a large kernel is slow)."""
    h, w = shape
    f = max(1.0, sigma_px / 2.0)
    small = rng.standard_normal((max(2, int(h / f) + 1), max(2, int(w / f) + 1))).astype(np.float32)
    small = cv2.GaussianBlur(small, (0, 0), 2.0)
    small /= max(float(small.std()), 1e-6)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _draw_clutter(mask, plate_rect, excl, rng, ipt, ppmm):
    """Plate logos/text and stray marks, only where they cannot touch the pattern."""
    x0, y0, x1, y1 = plate_rect
    bands = [(x0 + 3, y0 + 3, excl[0], y1 - 3), (excl[2], y0 + 3, x1 - 3, y1 - 3),
             (x0 + 3, y0 + 3, x1 - 3, excl[1]), (x0 + 3, excl[3], x1 - 3, y1 - 3)]
    for bx0, by0, bx1, by1 in bands:
        if bx1 - bx0 < 8 or by1 - by0 < 6:
            continue
        for _ in range(int(rng.integers(1, 4))):
            word = str(rng.choice(_PLATE_WORDS))
            height_mm = min(float(rng.uniform(3.0, 7.0)), (by1 - by0) * 0.6)
            scale = height_mm * ppmm / 22.0                    # HERSHEY_SIMPLEX cap ~22 px
            thick = max(1, int(round(height_mm * ppmm / 8)))
            (tw, th), _ = cv2.getTextSize(word, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
            tw_mm = tw / ppmm
            if tw_mm > bx1 - bx0 - 1:
                continue
            x = rng.uniform(bx0, bx1 - tw_mm)
            y = rng.uniform(by0, by1 - height_mm)
            c, r = ipt(x, y)
            cv2.putText(mask, word, (c // 16, r // 16), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thick, cv2.LINE_AA)
        for _ in range(int(rng.integers(2, 6))):              # scratches and stray strings
            p = rng.uniform([bx0, by0], [bx1, by1], (2, 2))
            cv2.line(mask, ipt(*p[0]), ipt(*p[1]), int(rng.integers(60, 200)), 1, cv2.LINE_AA, 4)


def _draw_plate_print(mask, rect, rng, ipt, ppmm):
    """Printed plate text and a logo ring across the pattern area (under the plastic)."""
    x0, y0, x1, y1 = rect
    for _ in range(int(rng.integers(2, 5))):
        word = str(rng.choice(_PLATE_WORDS))
        height_mm = float(rng.uniform(2.5, 6.0))
        scale = height_mm * ppmm / 22.0
        thick = max(1, int(round(height_mm * ppmm / 10)))
        c, r = ipt(rng.uniform(x0, max(x0 + 1, x1 - 20)), rng.uniform(y0 + height_mm, y1))
        cv2.putText(mask, word, (c // 16, r // 16), cv2.FONT_HERSHEY_SIMPLEX, scale, int(rng.integers(120, 256)),
                    thick, cv2.LINE_AA)
    c, r = ipt(rng.uniform(x0, x1), rng.uniform(y0, y1))
    rad = int(round(rng.uniform(4.0, 12.0) * ppmm * 16))
    cv2.circle(mask, (c, r), rad, 200, max(1, int(round(0.8 * ppmm))), cv2.LINE_AA, 4)


# =====================================================================================
# the renderer
# =====================================================================================
def _plastic(plate: str, plastic: str, rng):
    """(reflectance BGR, opacity) of the filament."""
    if plate == "dark":
        colors = [(0.86, 0.86, 0.86), (0.35, 0.80, 0.92), (0.30, 0.55, 0.92), (0.80, 0.82, 0.70)]
    else:
        colors = [(0.08, 0.08, 0.09), (0.45, 0.20, 0.10), (0.10, 0.10, 0.50), (0.12, 0.30, 0.12)]
    col = np.asarray(colors[int(rng.integers(len(colors)))], np.float32)
    return col, (1.0 if plastic == "opaque" else float(rng.uniform(0.5, 0.65)))


def render(manifest: Manifest, widths: WidthTable | None, camera: Camera, *, plate: str = "dark",
           plastic: str = "opaque", seed: int = 0, lighting: Lighting | None = None,
           noise: float = 1.0, blur_px: float | None = None, jpeg_quality: int | None = None,
           clutter: bool = True, supersample: int = 2, edge_mm: float | None = None,
           model: dict | None = None, progress: bool = False, realism=None,
           deposits=None, blobs=(), truth_widths: WidthTable | None = None,
           light_seed: int | None = None) -> Rendered:
    """Render ``manifest`` as ``camera`` sees it; test tracks at ``widths`` (mm).

    widths        true widths along the test tracks (e.g. ``print_virtual(...).table``);
                  None renders the commanded widths
    plate         "dark" (textured) or "light" (smooth)
    plastic       "opaque" or "translucent" (opacity 0.5-0.65: lower contrast, plate shows)
    lighting      :class:`Lighting`; default per camera kind (seeded)
    noise         multiplier on the sensor noise (shot: full well 4000 e- at 255 DN;
                  read 1.2 DN); 0 = noiseless
    blur_px       Gaussian sigma (px) of the optics/defocus; default 0.7 flatbed, 1.2 phone
    jpeg_quality  encode as JPEG at this quality (phone photos), None = lossless
    clutter       plate logos, scratches and a cutting mat around the plate
    supersample   sub-pixels per pixel side (pixel-area integration of the coverage)
    edge_mm       edge softness s_e (mm) of eq. (1); default 0.15 x layer height
    model         {"spec": ..., "values": {...}} recorded in the truth
    realism       :class:`measure.phenomena.Realism` (or its text: "all", "profile,grain");
                  None = none. With "profile" the true width is the footprint (the bead's
                  widest point), no longer the 50 % point of eq. (1)
    deposits      (track_pieces, strings) from :func:`measure.phenomena.deposit_pieces`,
                  used by the "strings" and "raster_gaps" phenomena
    blobs         discs (x_mm, y_mm, diameter_mm, h_mm) drawn over the beads: the dwells'
                  blobs (fit/blobs.py), whose widths ``widths`` then leaves out
    truth_widths  the widths the truth records (default ``widths``): with ``blobs``, the
                  beads with the discs' chords (fit/virtual.py ``VirtualPrint.table``)
    light_seed    where the lamp stands, apart from ``seed``: the light's gradient and glare,
                  the highlight on the flanks, the plate's specks (``sparkle``) and the
                  exposure's sensor noise come from it, everything else (the print, plate,
                  plastic, camera) from ``seed``. Several renders that differ only in it are
                  photos from one camera with the lamp moved between them (measure/stack.py).
                  None: every draw from ``seed``, as before it existed
    """
    if plate not in ("dark", "light"):
        raise ValueError(f"plate must be 'dark' or 'light', not {plate!r}")
    if plastic not in ("opaque", "translucent"):
        raise ValueError(f"plastic must be 'opaque' or 'translucent', not {plastic!r}")
    from calib.progress import progress as progress_bar

    from measure import phenomena as ph

    if not isinstance(realism, ph.Realism):
        realism = ph.Realism.parse(realism if realism is not None else "none", camera.kind)
    rng = np.random.default_rng(seed)
    # the phenomena draw from their own stream: switching one on does not reshuffle the rest
    prng = np.random.default_rng([int(seed), 11])
    # the lamp's draws: from the two streams above unless it has a seed of its own
    lrng = None if light_seed is None else np.random.default_rng([int(light_seed), 17])
    lamp_p = prng if lrng is None else lrng
    lamp_r = rng if lrng is None else lrng
    if lighting is None and "light" in realism:
        g = lamp_p.uniform(0.25, 0.40, 2) * lamp_p.choice([-1.0, 1.0], 2)
        lighting = Lighting(exposure=225.0, gradient=(float(g[0]), float(g[1])), vignetting=0.45,
                            glare=float(lamp_p.uniform(15.0, 25.0)))
    lighting = lighting or Lighting.for_camera(camera.kind, lamp_r)
    if blur_px is None:
        blur_px = 1.2 if camera.kind == "phone" else 0.7
    if jpeg_quality is None and "jpeg" in realism:
        jpeg_quality = realism.jpeg_quality
    dep = None
    if deposits is not None:
        tp, strings = deposits
        dep = (tp if "raster_gaps" in realism else {}, strings if "strings" in realism else [])
    W, H = camera.image_size
    ss = int(supersample)
    bar = progress_bar(total=5, desc="render", unit="step", disable=not progress, leave=False)
    Hinv = np.linalg.inv(camera.H)
    cx, cy = camera.center_px
    # 1. bed coordinates of every sub-pixel and every pixel
    Xs = np.empty((H * ss, W * ss), np.float32)
    Ys = np.empty_like(Xs)
    unproject_grid(Hinv, cx, cy, camera.f_px, camera.k1, camera.k2, W, H, ss, Xs, Ys)
    bar.update()
    # 2. plastic coverage, exact (eq. 1) or the physical profile, then pixel-area average
    alpha_s = np.zeros((H * ss, W * ss), np.float32)
    prep = _segments(manifest, widths, camera, ss, edge_mm, dep, blobs)
    shade_s = spec_s = None
    attenuation = None
    height_px = None
    if prep is not None and "profile" in realism:
        seg, segw, bbox, starts, sig, hs = prep
        ppmm = float(np.median(camera.px_per_mm(seg[:, :2])))
        aa = np.full(len(hs), 1.0 / (ss * ppmm))
        light = ph.light_vector(camera.kind, lamp_p)
        hv = ph.half_vector(light)
        p_spec = float(prng.uniform(40.0, 80.0))
        thick = np.zeros_like(alpha_s)
        shade_s = np.zeros_like(alpha_s)
        spec_s = np.zeros_like(alpha_s)
        tmax = np.zeros_like(alpha_s)
        _track_profile(Xs, Ys, seg, segw, bbox, starts, hs, aa, hv, p_spec, realism.ambient,
                       alpha_s, thick, shade_s, spec_s, tmax)
        del tmax
        if "translucent" in realism:
            attenuation = realism.attenuation_mm or float(prng.uniform(0.08, 0.15))
            alpha_s = alpha_s * (1.0 - np.exp(-thick / np.float32(attenuation)))
        if "shadows" in realism:           # the height field the lamp's shadows are cast from
            height_px = thick.reshape(H, ss, W, ss).mean(axis=(1, 3)) if ss > 1 else thick.copy()
            shadow_step_mm = 0.5 / ppmm
        del thick
        shade_s *= alpha_s                 # plastic radiance weight: coverage x Lambert shade
        spec_s *= alpha_s if "glare" in realism else 0.0
    elif prep is not None:
        seg, segw, bbox, starts, sig, hs = prep
        _track_coverage(Xs, Ys, seg, segw, bbox, starts, sig, alpha_s)
    fid_sigma = edge_mm if edge_mm is not None else EDGE_SOFTNESS_PER_HEIGHT * 0.2
    fid_alpha = np.zeros_like(alpha_s) if shade_s is not None else alpha_s
    _fiducial_cells(manifest, Xs, Ys, camera, ss, fid_sigma, fid_alpha)
    if shade_s is not None:               # unprinted marker cells: flat, unshaded
        shade_s += fid_alpha
        alpha_s = np.minimum(1.0, alpha_s + fid_alpha)
        shade_s = np.minimum(shade_s, 1.0)
    del Xs, Ys, fid_alpha

    def pixel_area(a):
        return a.reshape(H, ss, W, ss).mean(axis=(1, 3)) if ss > 1 else a

    alpha = pixel_area(alpha_s)
    del alpha_s
    radiance = pixel_area(shade_s) if shade_s is not None else alpha
    specular = pixel_area(spec_s) if spec_s is not None else None
    del shade_s, spec_s
    bar.update()
    # 3. background seen through the camera
    Xc = np.empty((H, W), np.float32)
    Yc = np.empty_like(Xc)
    unproject_grid(Hinv, cx, cy, camera.f_px, camera.k1, camera.k2, W, H, 1, Xc, Yc)
    back = _background(manifest, camera, Xc, Yc, plate, rng, clutter,
                       logos_inside="logos" in realism, logo_rng=prng)
    if "grain" in realism:
        back *= ph.pei_grain(Xc, Yc, seed=int(seed))[..., None]
    # the specks are the grain's facets that mirror the lamp: another lamp, other facets
    speck_seed = int(seed) if light_seed is None else int(seed) + 104729 * (int(light_seed) + 1)
    sparkle = ph.pei_sparkle(Xc, Yc, seed=speck_seed) * np.float32(realism.sparkle) if "sparkle" in realism else None
    shadow = None
    if height_px is not None:
        # its own stream: switching shadows on leaves every other draw as it was
        srng = np.random.default_rng([int(seed if light_seed is None else light_seed), 23])
        flat = camera.kind == "flatbed"
        shadow_depth = realism.shadow_depth or (0.5 if flat else float(srng.uniform(0.3, 0.6)))
        lamp_deg = realism.lamp_deg if realism.lamp_deg is not None else float(srng.uniform(*((4, 12) if flat
                                                                                             else (1, 8))))
        shadow = ph.cast_shadow(height_px, _toward_lamp_px(camera, Xc, Yc, light, shadow_step_mm), light,
                                step_mm=shadow_step_mm, lamp_deg=lamp_deg)
        del height_px
    del Xc, Yc
    bar.update()
    # 4. compose (linear in coverage), light, blur
    col, opacity = _plastic(plate, plastic, rng)
    if attenuation is not None:
        opacity = 1.0                      # the thickness sets the opacity (Beer-Lambert)
    a = (opacity * alpha)[..., None]
    img = back * (1.0 - a) + col[None, None, :] * (opacity * radiance)[..., None]
    if shadow is not None:                 # the lamp's share of the light is gone in shadow
        img *= (1.0 - np.float32(shadow_depth) * shadow)[..., None]
        lit = 1.0 - shadow
        sparkle = sparkle * lit if sparkle is not None else None
        specular = specular * lit if specular is not None else None
    if sparkle is not None:                # the lamp mirrored by the plate, where it is seen
        img += (sparkle[..., None] * (1.0 - a))
    del back, a, sparkle
    img *= _light_field(W, H, lighting, rng)[..., None]
    if specular is not None:
        img += (realism.glare_dn * specular)[..., None]
    if lighting.glare > 0:
        img += _glare(W, H, lighting.glare, lamp_r)[..., None]
    if "defocus" in realism:
        img = ph.varying_blur(img, ph.defocus_map(W, H, prng, lo_px=blur_px * 0.8, hi_px=blur_px * 3.0))
    elif blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    bar.update()
    # 5. sensor noise: shot (Poisson ~ Gaussian, variance DN * 255 / full well) + read
    if noise > 0:
        var = np.maximum(img, 0.0) * (255.0 / 4000.0) + 1.2 ** 2
        img += noise * np.sqrt(var) * lamp_r.standard_normal(img.shape, dtype=np.float32)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    del img
    encoded = None
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        encoded = buf.tobytes()
        image = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    bar.update()
    bar.close()
    table = true_widths(manifest, truth_widths if truth_widths is not None else widths)
    settings = {"plate": plate, "plastic": plastic, "opacity": opacity, "plastic_bgr": col.tolist(),
                "seed": int(seed), "light_seed": light_seed, "noise": float(noise), "blur_px": float(blur_px),
                "jpeg_quality": jpeg_quality, "clutter": bool(clutter), "supersample": ss,
                "edge_mm": edge_mm, "edge_softness_per_height": EDGE_SOFTNESS_PER_HEIGHT,
                "realism": realism.label, "attenuation_mm": attenuation,
                "shadow_depth": shadow_depth if shadow is not None else None,
                "lamp_deg": lamp_deg if shadow is not None else None,
                "lighting": {"exposure": lighting.exposure, "gradient": list(map(float, lighting.gradient)),
                             "vignetting": lighting.vignetting, "glare": lighting.glare},
                "width_definition": ("footprint: the bead's widest point (physical cross-section)"
                                     if "profile" in realism else
                                     "distance between the 50 % coverage points of the bead edges")}
    model = model or {}
    truth = ScanTruth(camera=camera, widths=table, model_spec=str(model.get("spec", "")),
                      values=dict(model.get("values", {})), settings=settings)
    return Rendered(image=image, truth=truth, encoded=encoded)


def true_widths(manifest: Manifest, widths: WidthTable | None) -> WidthTable:
    """The width truth per sample: ``widths`` itself, or the commanded widths at the stations."""
    if widths is not None:
        n = len(widths)
        return WidthTable(track=widths.track, s_mm=widths.s_mm, x_mm=widths.x_mm, y_mm=widths.y_mm,
                          t_s=widths.t_s, width_mm=widths.width_mm, width_sd_mm=np.zeros(n),
                          valid=np.ones(n, bool))
    smp = sample_points(manifest, ds_mm=0.25)
    n = len(smp)
    return WidthTable(track=smp.track, s_mm=smp.s_mm, x_mm=smp.x_mm, y_mm=smp.y_mm, t_s=smp.t_s,
                      width_mm=smp.width_nominal_mm, width_sd_mm=np.zeros(n), valid=np.ones(n, bool))


def _toward_lamp_px(camera: Camera, Xc, Yc, light, step_mm: float, every_px: int = 16) -> np.ndarray:
    """(H, W, 2) image offset (px) of ``step_mm`` on the bed toward the lamp, per pixel:
    the camera's Jacobian at the pixel's bed point times the lamp's horizontal direction,
    evaluated every ``every_px`` pixels and interpolated (it varies over the picture's
    width, not over a bead's)."""
    H, W = Xc.shape
    xs, ys = Xc[::every_px, ::every_px], Yc[::every_px, ::every_px]
    d = np.asarray(light[:2], float)
    d = d / max(float(np.hypot(*d)), 1e-12) * step_mm
    J = camera.jacobian(np.column_stack([xs.ravel(), ys.ravel()]).astype(float))
    off = (J @ d).reshape(xs.shape + (2,)).astype(np.float32)
    return np.dstack([cv2.resize(off[..., k], (W, H), interpolation=cv2.INTER_LINEAR) for k in (0, 1)])


def _light_field(W, H, lighting: Lighting, rng) -> np.ndarray:
    """Exposure x (1 + gradient) x (1 - vignetting r^2), r = 1 at the image corners."""
    gx, gy = lighting.gradient
    u = np.linspace(-1, 1, W, dtype=np.float32)[None, :]
    v = np.linspace(-1, 1, H, dtype=np.float32)[:, None]
    r2 = (u * u + v * v) / 2.0
    return (lighting.exposure * (1.0 + 0.5 * gx * u + 0.5 * gy * v) * (1.0 - lighting.vignetting * r2)).astype(np.float32)


def _glare(W, H, amplitude, rng) -> np.ndarray:
    cu, cv = rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * H
    s = 0.25 * min(W, H)
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(H, dtype=np.float32)[:, None]
    return (amplitude * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * s * s))).astype(np.float32)


def half_contrast_widths(rendered: Rendered, manifest: Manifest, margin_mm: float = 1.5,
                         step_mm: float = 0.004):
    """Oracle width check: half-contrast width (mm) at every truth station, using the TRUE camera.

    Profiles across the bead are sampled (``scipy.ndimage.map_coordinates``, bilinear) at
    bed points p + t n along the true normal n, mapped through the true camera, so t is
    in mm. Background = median beyond w/2 + 0.3 mm, plateau = median inside w/2 - 0.15 mm
    (the extreme for narrower beads); the two half-level crossings are interpolated
    linearly. Straight tracks only (corners and crossings are not excluded). Used by the
    tests and the bench to show the renderer honours its width definition.

    Returns (track, s_mm, truth_mm, measured_mm) arrays.
    """
    from scipy.ndimage import map_coordinates

    g = cv2.cvtColor(rendered.image, cv2.COLOR_BGR2GRAY).astype(float)
    cam, tab = rendered.camera, rendered.table
    out = []
    for tr in manifest.test_tracks():
        sel = (tab.track == tr.id) & (tab.s_mm > margin_mm) & (tab.s_mm < tr.length_mm - margin_mm)
        sel &= tab.width_mm > 0
        if not sel.any():
            continue
        s, wt = tab.s_mm[sel], tab.width_mm[sel]
        pos, tan = tr.at(s)
        nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
        t = np.arange(-(wt.max() / 2 + 0.6), wt.max() / 2 + 0.6 + 1e-9, step_mm)
        pts = pos[:, None, :] + t[None, :, None] * nrm[:, None, :]
        uv = cam.project(pts.reshape(-1, 2)).reshape(len(s), len(t), 2)
        prof = map_coordinates(g, [uv[..., 1], uv[..., 0]], order=1, mode="nearest")
        for k, (p, w) in enumerate(zip(prof, wt)):
            bg = np.median(p[np.abs(t) > w / 2 + 0.3])
            core, inner = np.abs(t) < w / 2 - 0.15, np.abs(t) < w / 2
            pk = np.median(p[core]) if core.sum() > 5 else p[inner][np.argmax(np.abs(p[inner] - bg))]
            q = np.sign(pk - bg) * (p - (bg + pk) / 2)
            above = np.flatnonzero(q > 0)
            if len(above) == 0 or above[0] == 0 or above[-1] == len(t) - 1:
                meas = np.nan
            else:
                i0, i1 = above[0], above[-1]
                t_left = t[i0 - 1] + (t[i0] - t[i0 - 1]) * -q[i0 - 1] / (q[i0] - q[i0 - 1])
                t_right = t[i1] + (t[i1 + 1] - t[i1]) * q[i1] / (q[i1] - q[i1 + 1])
                meas = t_right - t_left
            out.append((tr.id, s[k], w, meas))
    arr = np.array(out, dtype=float).reshape(-1, 4)
    return arr[:, 0].astype(np.int64), arr[:, 1], arr[:, 2], arr[:, 3]
