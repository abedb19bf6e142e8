"""Guided search for the printed markers the ArUco detector missed.

On a phone photo at 35 deg the detector finds 2-3 of the 4 markers on about a fifth of the
renders (bench_e2e's phone seeds: 2 of 4 on seeds 3 and 9): a plate logo or a ring of
text crossing a marker's quiet frame breaks the square contour the detector starts from,
and the near markers are the most defocused. Two markers on one side of the print leave
the far side to the track refinement alone, which then ends 0.1-4 mm off (seed 9: 0.10 mm
median, 0.46 mm at worst, enough to read tau 6 % low with an interval that missed; seed
3: 2 mm, every width wrong).

Once the found markers give a pose, the missing ones are no longer searched for in the
whole picture but where they must be, and by their whole printed pattern rather than by
a contour: the picture is resampled into the marker's own frame (cells, bed-parallel, so
the perspective is gone), the known pattern (data bits, black border, plastic quiet frame
and one cell of plate around it) is located by normalised cross-correlation over +-4
cells, and aligned by ECC with an affine map (Evangelidis & Psarakis 2008, OpenCV
``findTransformECC``: zero-mean normalised, so indifferent to the plastic's brightness
and the light's gradient; the perspective left over a 16 mm marker is negligible), twice
more without the pixels the pattern does not explain (a logo's ring or letters). A marker
is accepted only when its data bits read back as its own id (at most one of 16 wrong, at
least 12 readable beside a logo) and the quiet frame is brighter than the black border in
the plastic's polarity, so a pose that is wrong cannot invent a marker. The same search
re-reads a detected marker whose corners misfit the pose of the others (measure/register.py).

The corners come from aligning the whole printed pattern, whose edges move in opposite
directions when the plastic bleeds (the quiet frame's outer edge out, the border's edge
in), so they are the drawn corners, not the bled ones the detector returns.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: cells of plate around the printed quiet frame in the template (the frame's outer edge)
PLATE_CELLS = 1.0
#: cells searched beyond the template on each side (the pose of two markers is good to ~2 mm)
SEARCH_CELLS = 4.0
#: least ECC correlation of an accepted marker (0.8-0.95 on the phone renders' found markers)
MIN_ECC = 0.5
#: ECC alignments repeated without the pixels the pattern does not explain
ROBUST_ROUNDS = 2
#: data bits (of 16) that may read wrong in an accepted marker
MAX_BIT_ERRORS = 1
#: data bits (of 16) that must be readable (not under a logo) in an accepted marker
MIN_BITS_SEEN = 12


@dataclass
class FoundMarker:
    """A marker located by the guided search.

    corners_px   (4, 2) image px of the black border's outer corners, ArUco order
    ecc          ECC correlation of the aligned pattern (0..1)
    bit_errors   data bits that read wrong (of 16)
    """

    id: int
    corners_px: np.ndarray
    ecc: float
    bit_errors: int


def _frame(corners_mm):
    """(origin, du, dv): bed mm of the border's top-left corner and of one cell along the
    marker's rows (u, to the right) and columns (v, down) from the manifest's corners."""
    c = np.asarray(corners_mm, float).reshape(4, 2)
    return c[0], (c[1] - c[0]) / 6.0, (c[3] - c[0]) / 6.0


def _to_bed(frame, u, v):
    o, du, dv = frame
    return o + np.multiply.outer(u, du) + np.multiply.outer(v, dv)


def _template(bits8, q: int, polarity: float) -> np.ndarray:
    """The printed pattern (plastic 1, plate 0, light plastic) in marker cells u, v in
    [-1 - PLATE_CELLS, 7 + PLATE_CELLS] at q px per cell, blurred by a fifth of a cell
    (the camera's blur and the rasters' rounded edges)."""
    pad = int(round(PLATE_CELLS * q))
    t = np.kron(bits8.astype(np.float32), np.ones((q, q), np.float32))
    t = np.pad(t, pad, constant_values=0.0)
    if polarity < 0:
        t = 1.0 - t
    return cv2.GaussianBlur(t, (0, 0), 0.2 * q)


def _resample(gray, camera, frame, lo: float, n: int, q: int) -> np.ndarray:
    """The picture in marker cells u, v in [lo, lo + n / q), pixel centres at lo + (i + 0.5) / q."""
    g = lo + (np.arange(n) + 0.5) / q
    uu, vv = np.meshgrid(g, g)
    uv = camera.project(_to_bed(frame, uu.ravel(), vv.ravel()).reshape(-1, 2))
    mx = uv[:, 0].reshape(n, n).astype(np.float32)
    my = uv[:, 1].reshape(n, n).astype(np.float32)
    return cv2.remap(np.asarray(gray, np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _outliers(aligned, templ, warp, n_s: int, q: int) -> tuple[np.ndarray, np.ndarray]:
    """(outliers in the template's px (bool), uint8 mask of the pixels to use (255) in the
    search image's px): the pixels the aligned pattern does not explain, those whose
    residual from gain * template + offset exceeds half the plastic's contrast, widened by a
    quarter cell (a plate logo or a string across the marker: a ring over two markers
    pulled their corners 1-2 px without this). Half
    the contrast, not a few noise sd: an edge blurred a little more than the template's
    leaves residuals of a few sd all along the pattern, and masking those leaves ECC
    nothing to align."""
    A = np.column_stack([templ.ravel(), np.ones(templ.size)])
    coef, *_ = np.linalg.lstsq(A, aligned.ravel(), rcond=None)
    r = aligned - (A @ coef).reshape(aligned.shape)
    bad = (np.abs(r) > 0.5 * abs(float(coef[0])) * float(np.ptp(templ))).astype(np.uint8)
    k = max(1, q // 4)
    bad = cv2.dilate(bad, np.ones((2 * k + 1, 2 * k + 1), np.uint8))
    bad_s = cv2.warpAffine(bad * 255, warp, (n_s, n_s), flags=cv2.INTER_NEAREST)
    return bad > 0, np.where(bad_s > 0, 0, 255).astype(np.uint8)


def _read_cells(aligned, bad, q: int, pad: int) -> np.ndarray:
    """(8, 8) median of each printed cell's central half in the aligned pattern, over the
    pixels the pattern explains; NaN where fewer than a quarter of them are left (a
    logo's letters over the cell)."""
    m = np.full((8, 8), np.nan)
    a, b = q // 4, q - q // 4
    for r in range(8):
        for c in range(8):
            y0, x0 = pad + r * q, pad + c * q
            v = aligned[y0 + a:y0 + b, x0 + a:x0 + b][~bad[y0 + a:y0 + b, x0 + a:x0 + b]]
            if v.size >= 0.25 * (b - a) ** 2:
                m[r, c] = float(np.median(v))
    return m


def find_marker(gray, camera, marker_id: int, corners_mm, polarity: float = 1.0,
                cell_px: int = 0) -> FoundMarker | None:
    """Locate marker ``marker_id`` near where ``camera`` (bed mm -> image px, a
    :class:`measure.camera.Camera`) puts its ``corners_mm``; None when it is not there.

    gray      picture, float 0..1 (or uint8)
    polarity  +1 light plastic on a dark plate, -1 dark on light
    cell_px   resampling (px per cell); 0: the picture's own scale at the marker, 6-16
    """
    from patterns.fiducials import marker_bits, printed_bits

    g = np.asarray(gray, np.float32)
    if g.max() > 1.5:
        g = g / 255.0
    frame = _frame(corners_mm)
    if not cell_px:
        centre = _to_bed(frame, np.array([3.0]), np.array([3.0])).reshape(1, 2)
        cell_mm = float(np.linalg.norm(frame[1]))
        cell_px = int(np.clip(round(float(camera.px_per_mm(centre)[0]) * cell_mm), 6, 16))
    q = cell_px
    lo_t = -1.0 - PLATE_CELLS
    n_t = int(round((8 + 2 * PLATE_CELLS) * q))
    templ = _template(printed_bits(marker_id), q, polarity)
    n_s = n_t + int(round(2 * SEARCH_CELLS * q))
    search = _resample(g, camera, frame, lo_t - SEARCH_CELLS, n_s, q)
    if not np.isfinite(search).all() or float(search.std()) < 1e-4:
        return None
    cc = cv2.matchTemplate(search, templ, cv2.TM_CCOEFF_NORMED)
    _, best, _, (tx, ty) = cv2.minMaxLoc(cc)
    if best < 0.3:
        return None
    warp = np.array([[1, 0, tx], [0, 1, ty]], np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    mask = None
    pad = int(round(PLATE_CELLS * q))
    for _ in range(1 + ROBUST_ROUNDS):
        try:
            ecc, warp = cv2.findTransformECC(templ, search, warp, cv2.MOTION_AFFINE, crit, mask, 3)
        except cv2.error:                  # ECC diverged: no pattern there
            return None
        aligned = cv2.warpAffine(search, warp, (n_t, n_t), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REPLICATE)
        bad, mask = _outliers(aligned, templ, warp, n_s, q)
    if not ecc >= MIN_ECC:
        return None
    cells = _read_cells(aligned, bad, q, pad) * np.sign(polarity)
    frame_cells = np.r_[cells[0, :], cells[-1, :], cells[1:-1, 0], cells[1:-1, -1]]    # quiet frame: plastic
    border_cells = np.r_[cells[1, 1:-1], cells[-2, 1:-1], cells[2:-2, 1], cells[2:-2, -2]]  # black border: plate
    if not (np.isfinite(frame_cells).any() and np.isfinite(border_cells).any()):
        return None                        # every cell of the frame or the border unread
    lit, dark = np.nanmedian(frame_cells), np.nanmedian(border_cells)
    if not lit > dark:
        return None
    data = cells[2:6, 2:6]
    seen = np.isfinite(data)
    errors = int(np.sum((data > 0.5 * (lit + dark))[seen] != marker_bits(marker_id)[1:5, 1:5].astype(bool)[seen]))
    if errors > MAX_BIT_ERRORS or seen.sum() < MIN_BITS_SEEN:
        return None
    # the border's corners in template px (pixel-centre convention), through the ECC warp
    # into the search image, back to cells, bed mm and picture px
    c_cells = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]])
    p = (c_cells - lo_t) * q - 0.5
    ps = p @ warp[:, :2].T.astype(float) + warp[:, 2].astype(float)
    uv = (ps + 0.5) / q + (lo_t - SEARCH_CELLS)
    bed = _to_bed(frame, uv[:, 0], uv[:, 1]).reshape(-1, 2)
    return FoundMarker(id=int(marker_id), corners_px=camera.project(bed), ecc=float(ecc), bit_errors=errors)


def find_markers(gray, manifest, camera, ids, polarity: float = 1.0) -> list[FoundMarker]:
    """The manifest's fiducials ``ids``, each searched for where ``camera`` puts it
    (:func:`find_marker`); those found, in id order."""
    out = []
    for f in sorted(manifest.fiducials, key=lambda f: f.id):
        if f.id not in set(ids) or getattr(f, "dictionary", "DICT_4X4_50") != "DICT_4X4_50":
            continue
        m = find_marker(gray, camera, f.id, f.corners_mm, polarity)
        if m is not None:
            out.append(m)
    return out
