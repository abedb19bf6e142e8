"""Printed ArUco fiducials (docs/ARCHITECTURE.md "Fiducials").

A marker is the 6 x 6 cell bitmap of ``cv2.aruco`` ``DICT_4X4_50`` (4 x 4 data bits inside
a 1-cell black border) surrounded by a 1-cell white quiet frame: 8 x 8 cells, 16 mm at the
default 2 mm cell. Plastic forms the *white* cells, the plate shows through as black, so
light plastic on a dark plate reads as a normal marker and dark plastic on a light plate
as an inverted one (``detectInvertedMarker``).

White cells are filled by a single-layer raster of straight lines at a spacing equal to the
line width, so neighbouring beads touch and the cells print solid. A raster line of width w
centred at x covers [x - w/2, x + w/2]; a run of white cells [xa, xb] is therefore printed
from xa + w/2 to xb - w/2 and the n = cell/w lines of a cell row sit at y0 + w/2 + k w.

Bitmap row 0 is the marker's top, at the largest bed y. ``corners_mm`` are the outer
corners of the black border in ArUco order TL, TR, BR, BL (TL = (x0, y0 + size)).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from patterns.manifest import Fiducial

DICTIONARY = "DICT_4X4_50"
MARKER_CELLS = 6          # 4 data bits + 1-cell black border each side
QUIET_CELLS = 1           # white frame around the border
DICT_SIZE = 50


def marker_bits(marker_id: int) -> np.ndarray:
    """(6, 6) uint8 bitmap of ArUco DICT_4X4_50 marker ``marker_id``; 1 = white, row 0 on top."""
    import cv2

    if not 0 <= marker_id < DICT_SIZE:
        raise ValueError(f"marker id {marker_id} outside DICT_4X4_50 (0..49)")
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    return (cv2.aruco.generateImageMarker(d, int(marker_id), MARKER_CELLS) > 127).astype(np.uint8)


def printed_bits(marker_id: int) -> np.ndarray:
    """(8, 8) bitmap as printed: the marker with its white quiet frame; 1 = plastic."""
    return np.pad(marker_bits(marker_id), QUIET_CELLS, constant_values=1)


def footprint_mm(cell_mm: float = 2.0) -> float:
    """Side (mm) of a printed marker including its quiet frame (8 cells)."""
    return (MARKER_CELLS + 2 * QUIET_CELLS) * cell_mm


@dataclass
class FiducialPlan:
    """One marker to print: its record for the manifest and its raster strokes."""

    fiducial: Fiducial
    strokes_mm: list[np.ndarray]      # each (2, 2): start and end of one raster line
    line_width_mm: float
    origin_mm: tuple[float, float]    # lower-left corner of the quiet frame


def raster_strokes(bits: np.ndarray, origin_mm, cell_mm: float, line_width_mm: float) -> list[np.ndarray]:
    """Raster lines (boustrophedon order) filling the 1-cells of ``bits``.

    ``origin_mm`` is the lower-left corner of the bitmap on the bed; row 0 is on top.
    The line count per cell row is round(cell/w) and the spacing is then cell/n, so the
    beads exactly tile the row (a spacing equal to the line width).
    """
    n_rows, n_cols = bits.shape
    n_lines = max(1, int(round(cell_mm / line_width_mm)))
    pitch = cell_mm / n_lines
    x0, y0 = map(float, origin_mm)
    strokes = []
    flip = False
    for r in range(n_rows - 1, -1, -1):          # bottom row first
        row = bits[r]
        runs = []
        c = 0
        while c < n_cols:
            if row[c]:
                c0 = c
                while c < n_cols and row[c]:
                    c += 1
                runs.append((c0, c))
            else:
                c += 1
        yb = y0 + (n_rows - 1 - r) * cell_mm
        for k in range(n_lines):
            y = yb + pitch * (k + 0.5)
            segs = [(x0 + a * cell_mm + pitch / 2, x0 + b * cell_mm - pitch / 2) for a, b in runs]
            if flip:
                segs = [(b, a) for a, b in reversed(segs)]
            strokes.extend(np.array([[a, y], [b, y]]) for a, b in segs)
            flip = not flip
    return strokes


def plan_fiducial(marker_id: int, origin_mm, cell_mm: float = 2.0,
                  line_width_mm: float = 0.5) -> FiducialPlan:
    """Marker ``marker_id`` whose quiet frame has its lower-left corner at ``origin_mm``."""
    x0, y0 = map(float, origin_mm)
    bits = printed_bits(marker_id)
    strokes = raster_strokes(bits, (x0, y0), cell_mm, line_width_mm)
    bx, by = x0 + QUIET_CELLS * cell_mm, y0 + QUIET_CELLS * cell_mm   # black border corner
    size = MARKER_CELLS * cell_mm
    corners = [[bx, by + size], [bx + size, by + size], [bx + size, by], [bx, by]]
    fid = Fiducial(id=int(marker_id), center_mm=(bx + size / 2, by + size / 2), size_mm=size,
                   corners_mm=corners, dictionary=DICTIONARY)
    return FiducialPlan(fid, strokes, line_width_mm, (x0, y0))


def corner_origins(rect_mm, cell_mm: float = 2.0) -> list[tuple[float, float]]:
    """Lower-left origins of four markers in the corners of ``rect_mm`` = (x0, y0, x1, y1).

    Order: ids 0..3 = bottom-left, bottom-right, top-right, top-left.
    """
    x0, y0, x1, y1 = rect_mm
    f = footprint_mm(cell_mm)
    return [(x0, y0), (x1 - f, y0), (x1 - f, y1 - f), (x0, y1 - f)]
