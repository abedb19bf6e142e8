"""A printed ruler: ticks every 1 mm (longer every 5 and 10 mm), numbers every 10 mm.

It gives a human (and the QA overlay) a scale reference independent of the fiducials:
a scan whose ruler reads 100 mm between the 0 and 100 marks has a correct scale.
Ticks hang from a common base line (no printed spine, so no bead is printed twice) and are
drawn alternately up and down so the zero-extrusion hop between two ticks is 1 mm long.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from patterns import font

TICK_MINOR_MM = 2.0
TICK_MID_MM = 3.0
TICK_MAJOR_MM = 4.5
NUMBER_GAP_MM = 1.0


@dataclass
class RulerPlan:
    strokes_mm: list[np.ndarray]
    info: dict = field(default_factory=dict)     # goes to Manifest.ruler


def ruler_height_mm(number_height_mm: float = 3.0) -> float:
    """Extent (mm) of a ruler across its direction, ticks plus numbers."""
    return TICK_MAJOR_MM + NUMBER_GAP_MM + number_height_mm


def plan_ruler(origin_mm, length_mm: float, angle_deg: float = 0.0, tick_mm: float = 1.0,
               number_height_mm: float = 3.0) -> RulerPlan:
    """Ruler from ``origin_mm`` (the 0 mark, on the tick base line) along ``angle_deg``.

    Ticks grow to the left of the direction (up for angle 0). Numbers sit above the
    10 mm ticks, centred on them, and are skipped near the end where they would overhang.
    """
    n = int(np.floor(length_mm / tick_mm + 1e-9))
    local: list[np.ndarray] = []
    for i in range(n + 1):
        x = i * tick_mm
        mm = round(x, 6)
        if abs(mm % 10) < 1e-6 or abs(mm % 10 - 10) < 1e-6:
            ln = TICK_MAJOR_MM
        elif abs(mm % 5) < 1e-6 or abs(mm % 5 - 5) < 1e-6:
            ln = TICK_MID_MM
        else:
            ln = TICK_MINOR_MM
        tick = np.array([[x, 0.0], [x, ln]])
        local.append(tick if i % 2 == 0 else tick[::-1])
    for i in range(0, n + 1):
        x = i * tick_mm
        if abs(round(x, 6) % 10) > 1e-6:
            continue
        text = f"{int(round(x))}"
        w = font.text_width_mm(text, number_height_mm)
        if x - w / 2 < -0.5 or x + w / 2 > length_mm + 0.5:
            continue
        local.extend(font.place_strokes(font.text_strokes(text, number_height_mm),
                                        (x - w / 2, TICK_MAJOR_MM + NUMBER_GAP_MM)))
    strokes = font.place_strokes(local, origin_mm, angle_deg)
    a = np.deg2rad(angle_deg)
    info = {"origin_mm": [float(origin_mm[0]), float(origin_mm[1])],
            "direction": [float(np.cos(a)), float(np.sin(a))],
            "length_mm": float(n * tick_mm), "tick_mm": float(tick_mm),
            "tick_lengths_mm": [TICK_MINOR_MM, TICK_MID_MM, TICK_MAJOR_MM],
            "number_every_mm": 10.0}
    return RulerPlan(strokes, info)
