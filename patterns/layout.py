"""Where things go on the bed: the frame (fiducials, ruler, prime line, content area),
spiral geometry, the bed-fit check and the no-overlap check.

Frame (all mm, bed coordinates)::

    +--[F0 3]-- prime line --- title --[F 2]--+   top band, F = marker footprint (16 mm)
    |                                          |   gap >= 3 mm
    |              content (test tracks,       |
    |              their labels)               |
    |                                          |   gap >= 3 mm
    +--[F 0]------- ruler -------------[F 1]--+   bottom band
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.errors import UserError
from patterns.fiducials import footprint_mm

BAND_GAP_MM = 3.0
BED_MARGIN_MM = 2.0
MIN_FRAME_W_MM = 100.0     # room for a useful ruler between the bottom markers
VE_SEED000_S = 0.65e-6     # KISSlicer viscoelasticity of ABS (seed 000), s


@dataclass
class Frame:
    rect_mm: tuple[float, float, float, float]      # x0, y0, x1, y1 of the whole print
    content_mm: tuple[float, float, float, float]   # where the pattern's test tracks go
    cell_mm: float = 2.0

    @property
    def fiducial_mm(self) -> float:
        return footprint_mm(self.cell_mm)


def bed_size_mm(profile) -> tuple[float, float]:
    return (profile.bed_x_mm[1] - profile.bed_x_mm[0], profile.bed_y_mm[1] - profile.bed_y_mm[0])


def make_frame(profile, pattern: str, content_w_mm: float, content_h_mm: float, hint: str,
               cell_mm: float = 2.0) -> Frame:
    """A frame around a content area of the given size, centred on the bed.

    Raises UserError naming the pattern and the overflow when it does not fit, e.g.
    "spiral-step needs 180 mm in x but the bed is 150 mm: reduce --speeds".
    """
    f = footprint_mm(cell_mm)
    w = max(content_w_mm, MIN_FRAME_W_MM)
    h = content_h_mm + 2 * (f + BAND_GAP_MM)
    bw, bh = bed_size_mm(profile)
    for axis, need, have in (("x", w, bw), ("y", h, bh)):
        if need > have - 2 * BED_MARGIN_MM + 1e-9:
            raise UserError(f"{pattern} needs {need + 2 * BED_MARGIN_MM:.0f} mm in {axis} but the bed "
                            f"is {have:.0f} mm: {hint}")
    cx = 0.5 * (profile.bed_x_mm[0] + profile.bed_x_mm[1])
    cy = 0.5 * (profile.bed_y_mm[0] + profile.bed_y_mm[1])
    rect = (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)
    content = (cx - content_w_mm / 2, rect[1] + f + BAND_GAP_MM,
               cx + content_w_mm / 2, rect[3] - f - BAND_GAP_MM)
    return Frame(rect, content, cell_mm)


def max_content_mm(profile, cell_mm: float = 2.0) -> tuple[float, float]:
    """Largest content area (w, h) in mm that :func:`make_frame` accepts on this bed."""
    bw, bh = bed_size_mm(profile)
    f = footprint_mm(cell_mm)
    return bw - 2 * BED_MARGIN_MM, bh - 2 * BED_MARGIN_MM - 2 * (f + BAND_GAP_MM)


def tau_guess_s(profile, ve_s: float = VE_SEED000_S, floor_s: float = 0.03) -> float:
    """Elastic ooze time constant guess (s), seed 000: tau = 32 D^2 L l / d^4 * VE.

    D filament, L Bowden, l nozzle land length, d nozzle diameter (mm); VE = 0.65 us (ABS
    datasheet value quoted in seed 000). Direct drive (L = 0) gets ``floor_s``.
    """
    D = profile.filament_diameter_mm
    tau = 32.0 * D * D * profile.bowden_length_mm * profile.nozzle_land_length_mm \
        / profile.nozzle_diameter_mm ** 4 * ve_s
    return max(float(tau), floor_s)


#: Seed 001's author's printer (Adventurer 3): filament D, Bowden L, nozzle land l, nozzle d
#: (mm), the shipped adventurer3 profile's geometry. His restore distances (RetractTest
#: Re 1 mm, StartStopTest Re 2-4 mm) were chosen for it.
SEED001_PATH_MM = dict(D=1.75, L=200.0, l=0.6, d=0.4)


def seed001_scale(profile) -> float:
    """Factor (1) from seed 001's filament advances on its Adventurer 3 to this printer's.

    The advance Pe = Kf vn + Kb Db (seed 001, mm of filament) is a pressure times the
    filament path's compliance, which grows with the Bowden length as seed 000's time
    constant does: tau_guess(profile) / tau_guess(Adventurer 3), with :func:`tau_guess_s`
    (a direct drive floored at 0.03 s: 0.1; a 400 mm Bowden: 2)."""
    g = SEED001_PATH_MM
    seed_tau = 32.0 * g["D"] ** 2 * g["L"] * g["l"] / g["d"] ** 4 * VE_SEED000_S
    return tau_guess_s(profile) / seed_tau


def scaled_restore_mm(profile, seed_mm) -> tuple[float, ...]:
    """Seed 001's restore distances ``seed_mm`` (mm of filament) on this printer
    (:func:`seed001_scale`), rounded to 0.05 mm and at least 0.05 mm."""
    f = seed001_scale(profile)
    return tuple(max(round(round(r * f / 0.05) * 0.05, 2), 0.05) for r in np.atleast_1d(seed_mm))


# -- spirals ----------------------------------------------------------------------
def spiral_length_mm(r_in_mm: float, r_out_mm: float, pitch_mm: float) -> float:
    """Arc length (mm) of an Archimedean spiral r = r_in + b theta, b = pitch / 2 pi.

    Exact: s = [g(r_out) - g(r_in)] / (2 b), g(r) = r sqrt(r^2 + b^2) + b^2 asinh(r / b).
    """
    b = pitch_mm / (2 * np.pi)
    g = lambda r: r * np.sqrt(r * r + b * b) + b * b * np.arcsinh(r / b)  # noqa: E731
    return float((g(r_out_mm) - g(r_in_mm)) / (2 * b))


def spiral_radius_for_length_mm(r_in_mm: float, length_mm: float, pitch_mm: float) -> float:
    """Outer radius (mm) of an Archimedean spiral of ``length_mm`` starting at ``r_in_mm``."""
    lo, hi = r_in_mm, r_in_mm + length_mm
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if spiral_length_mm(r_in_mm, mid, pitch_mm) < length_mm:
            lo = mid
        else:
            hi = mid
    return hi


def spiral_theta(r_in_mm: float, pitch_mm: float, s_mm) -> np.ndarray:
    """Polar angle (rad, from the start) at arc length ``s_mm`` along r = r_in + b theta."""
    s = np.atleast_1d(np.asarray(s_mm, dtype=float))
    b = pitch_mm / (2 * np.pi)
    th_max = (np.sqrt(r_in_mm ** 2 + 2 * b * s.max()) - r_in_mm) / b + 1.0 if len(s) else 1.0
    th = np.linspace(0.0, th_max, max(2000, int(th_max * 400)))
    r = r_in_mm + b * th
    ds = np.sqrt(r * r + b * b)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (ds[1:] + ds[:-1]) * np.diff(th))])
    return np.interp(s, cum, th)


def spiral_points(center_mm, r_in_mm: float, pitch_mm: float, s_mm, theta0_rad: float = 0.0,
                  outward: bool = True) -> np.ndarray:
    """(N, 2) points at arc lengths ``s_mm`` on an Archimedean spiral, counter-clockwise.

    outward=True: starts at r_in and grows; outward=False: the same curve run backwards from
    the outer end (``s_mm`` measured from that end), so it winds inward.
    """
    s = np.asarray(s_mm, dtype=float)
    b = pitch_mm / (2 * np.pi)
    if outward:
        th = spiral_theta(r_in_mm, pitch_mm, s)
    else:
        total = s.max() if len(s) else 0.0
        th = spiral_theta(r_in_mm, pitch_mm, total - s)
    r = r_in_mm + b * th
    a = theta0_rad + th
    c = np.asarray(center_mm, dtype=float)
    return np.column_stack([c[0] + r * np.cos(a), c[1] + r * np.sin(a)])


def arc_points(center_mm, radius_mm: float, theta0_rad: float, s_mm, clockwise: bool = True) -> np.ndarray:
    """(N, 2) points at arc lengths ``s_mm`` along a circle starting at angle ``theta0_rad``."""
    s = np.asarray(s_mm, dtype=float)
    a = theta0_rad + (-1 if clockwise else 1) * s / radius_mm
    c = np.asarray(center_mm, dtype=float)
    return np.column_stack([c[0] + radius_mm * np.cos(a), c[1] + radius_mm * np.sin(a)])


def resample_s(s_start_mm: float, s_end_mm: float, step_mm: float, breaks=()) -> np.ndarray:
    """Arc-length stations from start to end every <= step_mm, including every break point."""
    n = max(1, int(np.ceil((s_end_mm - s_start_mm) / step_mm - 1e-9)))
    s = np.linspace(s_start_mm, s_end_mm, n + 1)
    b = [x for x in breaks if s_start_mm < x < s_end_mm]
    return np.unique(np.concatenate([s, b]))


# -- checks -------------------------------------------------------------------------
def overlapping_tracks(tracks, margin_mm: float = 0.25, res_mm: float = 0.1,
                       coast_width_mm: float = 0.4) -> list[tuple[int, int]]:
    """Pairs of different tracks whose beads, each buffered by width/2 + margin, touch.

    The raster chains of one printed marker (kind "fiducial", same ``marker_id``) are
    meant to touch: they are one solid print and are not reported against each other.

    A raster occupancy test: every segment is drawn as a thick line of width
    w + 2 margin (w = larger vertex width of the segment, ``coast_width_mm`` where the
    pattern coasts without extrusion, since ooze lands there) into a grid of ``res_mm``.
    """
    import cv2

    marker = {t.id: t.params["marker_id"] for t in tracks
              if t.kind == "fiducial" and "marker_id" in (t.params or {})}
    allp = np.concatenate([t.points_mm for t in tracks])
    lo = allp.min(axis=0) - 3.0
    hi = allp.max(axis=0) + 3.0
    nx, ny = (np.ceil((hi - lo) / res_mm).astype(int) + 1)
    owner = np.full((ny, nx), -1, dtype=np.int32)
    pairs: set[tuple[int, int]] = set()
    shift = 4                                       # cv2 sub-pixel bits
    for t in tracks:
        mask = np.zeros((ny, nx), dtype=np.uint8)
        p = np.round((t.points_mm - lo) / res_mm * (1 << shift)).astype(np.int64)
        w = np.asarray(t.width_mm, dtype=float)
        for i in range(len(p) - 1):
            wi = max(w[i], w[i + 1]) if len(w) > i + 1 else w[i]
            wi = wi if wi > 0 else coast_width_mm
            th = max(1, int(round((wi + 2 * margin_mm) / res_mm)))
            cv2.line(mask, tuple(map(int, p[i])), tuple(map(int, p[i + 1])), 1, th, cv2.LINE_8, shift)
        hit = owner[mask > 0]
        for other in np.unique(hit[hit >= 0]):
            if marker.get(int(other), -1) == marker.get(t.id, -2):
                continue
            pairs.add((int(min(other, t.id)), int(max(other, t.id))))
        owner[mask > 0] = t.id
    return sorted(pairs)


def steps_angles_spread(angles_rad) -> float:
    """Mean resultant length R of angles (0 = evenly spread, 1 = all at one angle)."""
    a = np.asarray(angles_rad, dtype=float)
    return float(np.hypot(np.cos(a).mean(), np.sin(a).mean())) if len(a) else 0.0


# -- rows (straight-line patterns: stop-mid-path, retract) ---------------------------
ROW_LABEL_H_MM = 2.8        # rows 4 mm apart: 1.2 mm between labels, 0.8 mm clear of the 0.4 mm strokes
ROW_LABEL_GAP_MM = 4.0


def place_rows(profile, pattern, rows, *, pitch_mm=4.5, group_gap_mm=2.0, hint=""):
    """Stack rows (label on the left, straight test line in +x to its right) top to bottom.

    rows: dicts with ``label``, ``length_mm``, ``group``; adds ``label_xy`` (lower-left of
    the label) and ``start_xy`` (line start) to each and returns the :class:`Frame`.
    Rows are ``pitch_mm`` apart, groups another ``group_gap_mm``.
    """
    from patterns import font

    label_w = max(font.text_width_mm(r["label"], ROW_LABEL_H_MM) for r in rows)
    line_w = max(r["length_mm"] for r in rows)
    n_gaps = sum(1 for a, b in zip(rows, rows[1:]) if a["group"] != b["group"])
    content_w = label_w + ROW_LABEL_GAP_MM + line_w + 1.0
    content_h = len(rows) * pitch_mm + n_gaps * group_gap_mm
    frame = make_frame(profile, pattern, content_w, content_h, hint)
    x0, _, _, y1 = frame.content_mm
    y = y1 - pitch_mm / 2
    for i, r in enumerate(rows):
        if i and rows[i - 1]["group"] != r["group"]:
            y -= group_gap_mm
        r["label_xy"] = (x0, y - ROW_LABEL_H_MM / 2)
        r["start_xy"] = (x0 + label_w + ROW_LABEL_GAP_MM, y)
        y -= pitch_mm
    return frame
