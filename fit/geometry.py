"""Bead cross-section geometry: the one place where width, layer height and area meet.

Both the G-code writer (width -> E) and the simulator (flow -> width) use these two
functions, so a pattern printed on the virtual printer at steady state comes out at
exactly its commanded width.

Model (the slicer's rounded rectangle, see shared/REFERENCE.md "Width from flow"):

    w >= h :  A = (w - h) * h + pi * h**2 / 4        (rectangle with semicircular sides)
    w <  h :  A = pi * w * h / 4                     (ellipse of width w, height h)

The two branches meet at w = h (A = pi h^2 / 4), so the map is continuous and strictly
increasing: every area has exactly one width. Units: w, h in mm, A in mm^2.
"""
from __future__ import annotations

import numpy as np

_PI4 = np.pi / 4.0


def bead_area_mm2(width_mm, height_mm):
    """Cross-section area (mm^2) of a bead of width ``width_mm`` and height ``height_mm``."""
    w = np.asarray(width_mm, dtype=float)
    h = np.asarray(height_mm, dtype=float)
    return np.where(w >= h, (w - h) * h + _PI4 * h * h, _PI4 * w * h)


def bead_width_mm(area_mm2, height_mm):
    """Inverse of :func:`bead_area_mm2`: width (mm) of a bead of area ``area_mm2`` (mm^2).

    Negative areas (no plastic) give width 0.
    """
    a = np.maximum(np.asarray(area_mm2, dtype=float), 0.0)
    h = np.asarray(height_mm, dtype=float)
    a0 = _PI4 * h * h
    return np.where(a >= a0, (a - a0) / h + h, a / (_PI4 * h))


def filament_area_mm2(filament_diameter_mm):
    """Filament cross-section Af = pi D^2 / 4 (mm^2)."""
    return _PI4 * float(filament_diameter_mm) ** 2
