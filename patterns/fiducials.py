"""Printed ArUco fiducials (docs/ARCHITECTURE.md "Fiducials").

A marker is the 6 x 6 cell bitmap of ``cv2.aruco`` ``DICT_4X4_50`` (4 x 4 data bits inside
a 1-cell black border) surrounded by a 1-cell white quiet frame: 8 x 8 cells, 16 mm at the
default 2 mm cell. Plastic forms the *white* cells, the plate shows through as black, so
light plastic on a dark plate reads as a normal marker and dark plastic on a light plate
as an inverted one (``detectInvertedMarker``).

White cells are filled by a single-layer raster of straight lines that overlap by at least
RASTER_OVERLAP of their width (a lagging Bowden extruder prints them narrower than
commanded; touching lines would then leave gaps). A raster line of width w centred at x
covers [x - w/2, x + w/2]; a run of white cells [xa, xb] is therefore printed from
xa + w/2 to xb - w/2, and the n = ceil(cell / ((1 - overlap) w)) lines of a cell row run
evenly from w/2 above its lower edge to w/2 below its upper edge (pitch (cell - w)/(n - 1);
lines of neighbouring cell rows touch). The lines are chained into serpentines (:func:`raster_chains`) that turn
only inside white cells, so the nozzle never crosses a black cell while it is still
flowing: between chains it retracts and travels (issue #10: travel across the black
cells without retraction left strings that made the markers unreadable).

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
#: Least overlap of neighbouring raster lines, as a fraction of the line width.
RASTER_OVERLAP = 0.10


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
    """One marker to print: its record for the manifest and its raster chains."""

    fiducial: Fiducial
    chains_mm: list[np.ndarray]       # each (N, 2): one serpentine, printed without stopping
    line_width_mm: float
    origin_mm: tuple[float, float]    # lower-left corner of the quiet frame


def raster_lines(bits: np.ndarray, origin_mm, cell_mm: float, line_width_mm: float,
                 overlap: float = RASTER_OVERLAP) -> list[tuple[float, list[tuple[float, float]]]]:
    """Raster lines filling the 1-cells of ``bits``, bottom line first: [(y, [(xa, xb), ...])].

    ``origin_mm`` is the lower-left corner of the bitmap on the bed; row 0 is on top.
    """
    n_rows, n_cols = bits.shape
    n_lines = max(1, int(np.ceil(cell_mm / ((1.0 - overlap) * line_width_mm) - 1e-9)))
    x0, y0 = map(float, origin_mm)
    half = 0.5 * line_width_mm
    out = []
    for r in range(n_rows - 1, -1, -1):          # bottom row first
        row = bits[r]
        runs, c = [], 0
        while c < n_cols:
            if row[c]:
                c0 = c
                while c < n_cols and row[c]:
                    c += 1
                runs.append((x0 + c0 * cell_mm + half, x0 + c * cell_mm - half))
            else:
                c += 1
        yb = y0 + (n_rows - 1 - r) * cell_mm
        # the outermost lines of a row sit w/2 inside it, the rest evenly between
        ys = np.linspace(yb + half, yb + cell_mm - half, n_lines) if n_lines > 1 else [yb + cell_mm / 2]
        out.extend((float(y), list(runs)) for y in ys)
    return out


def raster_chains(bits: np.ndarray, origin_mm, cell_mm: float, line_width_mm: float,
                  overlap: float = RASTER_OVERLAP) -> list[np.ndarray]:
    """Serpentines (N, 2) that print the raster of :func:`raster_lines` with turns only
    inside white cells.

    A run continues the serpentine of the run below it when the serpentine arrived at the
    run's own end (same x, the U-turn is a step of one pitch inside white); every other
    run starts a new chain. Chains come out in a nearest-start order from the bottom left.
    """
    lines = raster_lines(bits, origin_mm, cell_mm, line_width_mm, overlap)
    open_chains: list[dict] = []       # {"pts": [...], "end_x": x, "last": line index}
    done: list[list] = []
    for k, (y, runs) in enumerate(lines):
        used = set()
        for a, b in runs:
            host = None
            for ch in open_chains:
                if id(ch) in used or ch["last"] != k - 1:
                    continue
                if abs(ch["end_x"] - a) < 1e-9 or abs(ch["end_x"] - b) < 1e-9:
                    host = ch
                    break
            if host is None:
                host = {"pts": [], "end_x": None, "last": k}
                open_chains.append(host)
                start, end = a, b
            else:
                start, end = (a, b) if abs(host["end_x"] - a) < 1e-9 else (b, a)
            host["pts"] += [(start, y), (end, y)]
            host["end_x"], host["last"] = end, k
            used.add(id(host))
        for ch in [c for c in open_chains if c["last"] != k]:
            done.append(ch["pts"])
            open_chains.remove(ch)
    done += [c["pts"] for c in open_chains]
    chains = [np.array(c, dtype=float) for c in done if len(c) >= 2]
    ordered, here = [], np.array(origin_mm, dtype=float)
    while chains:
        i = int(np.argmin([min(np.hypot(*(c[0] - here)), np.hypot(*(c[-1] - here))) for c in chains]))
        c = chains.pop(i)
        if np.hypot(*(c[-1] - here)) < np.hypot(*(c[0] - here)):
            c = c[::-1]
        ordered.append(c)
        here = c[-1]
    return ordered


def plan_fiducial(marker_id: int, origin_mm, cell_mm: float = 2.0,
                  line_width_mm: float = 0.5) -> FiducialPlan:
    """Marker ``marker_id`` whose quiet frame has its lower-left corner at ``origin_mm``."""
    x0, y0 = map(float, origin_mm)
    bits = printed_bits(marker_id)
    chains = raster_chains(bits, (x0, y0), cell_mm, line_width_mm)
    bx, by = x0 + QUIET_CELLS * cell_mm, y0 + QUIET_CELLS * cell_mm   # black border corner
    size = MARKER_CELLS * cell_mm
    corners = [[bx, by + size], [bx + size, by + size], [bx + size, by], [bx, by]]
    fid = Fiducial(id=int(marker_id), center_mm=(bx + size / 2, by + size / 2), size_mm=size,
                   corners_mm=corners, dictionary=DICTIONARY)
    return FiducialPlan(fid, chains, line_width_mm, (x0, y0))


def corner_origins(rect_mm, cell_mm: float = 2.0) -> list[tuple[float, float]]:
    """Lower-left origins of four markers in the corners of ``rect_mm`` = (x0, y0, x1, y1).

    Order: ids 0..3 = bottom-left, bottom-right, top-right, top-left.
    """
    x0, y0, x1, y1 = rect_mm
    f = footprint_mm(cell_mm)
    return [(x0, y0), (x1 - f, y0), (x1 - f, y1 - f), (x0, y1 - f)]
