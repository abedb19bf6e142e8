"""G-code -> Manifest: what ``calib plan`` does for any G-code (ours or third-party).

Tracks are polylines through the XY moves of each track (our ``;TRACK`` labels, or runs
of consecutive extruding XY moves at one z for unlabelled G-code). Per move, the
commanded bead comes from the volume balance (fit/geometry.py):

    A = de * Af / L_xy   (mm^2),   w = bead_width_mm(A, h),   q = A * v   (mm^3/s)

with Af = pi D^2 / 4, L_xy the move's XY length, h the layer height and v the planned
cruise head speed of the move. Where the width changes between moves the polyline
repeats the vertex, so widths step instead of ramping. Moves without extrusion inside a
labelled track get width 0 (coasting).

Layer height h: the commanded bead height where the G-code says it (our writer's
``;TRACK ... h=<mm>`` / ``;HEIGHT h=<mm>`` labels, ``Moves.height_mm``), so a track
printed with h different from the z spacing comes back with its commanded width.
Elsewhere (third-party G-code): z minus the highest lower z level that holds at least a
quarter as much filament as this level (so a prime line at z = 0.2 under a single-layer
test at z = 0.3 does not make the test 0.1 mm high); z itself on the first layer. Pass
``layer_height_mm`` to override both.
"""
from __future__ import annotations

import numpy as np

from fit.geometry import bead_width_mm
from patterns.gcode_parser import ParseResult, parse_gcode
from patterns.manifest import Manifest, Track
from patterns.planner import DS_MAX_MM, DT_MAX_S, _plan_with_details, track_ids
from patterns.profile import load_profile

#: Unlabelled extrusion runs shorter than this (mm) are kind "other" (text, dots, blobs).
MIN_TEST_LENGTH_MM = 3.0


def manifest_from_gcode(text, profile, pattern: dict | None = None, *,
                        layer_height_mm: float | None = None,
                        min_test_length_mm: float = MIN_TEST_LENGTH_MM) -> Manifest:
    """Parse, plan and describe G-code as a Manifest (no fiducials).

    ``pattern`` goes into the manifest as is (default: {"name": "gcode"} plus parse
    warnings). Kind: the ;TRACK label, else "test" for runs of at least
    ``min_test_length_mm`` and "other" for shorter ones.
    """
    prof = load_profile(profile)
    pr = parse_gcode(text, prof)
    return manifest_from_parse(pr, prof, pattern, layer_height_mm=layer_height_mm,
                               min_test_length_mm=min_test_length_mm)


def manifest_from_parse(pr: ParseResult, profile, pattern: dict | None = None, *,
                        layer_height_mm: float | None = None,
                        min_test_length_mm: float = MIN_TEST_LENGTH_MM) -> Manifest:
    """As :func:`manifest_from_gcode`, from an existing ParseResult."""
    prof = load_profile(profile)
    tl, mp = _plan_with_details(pr, prof, DS_MAX_MM, DT_MAX_S)
    mv = pr.moves
    track = track_ids(pr)
    af = prof.filament_area_mm2
    lxy = mv.xy_length_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        area = np.where(lxy > 1e-9, np.maximum(mv.de_mm, 0.0) * af / lxy, 0.0)
        l3 = mp.length_mm
        v_head = np.where((mp.kind == 0) & (l3 > 0), mp.v_cruise_mm_s * lxy / np.where(l3 > 0, l3, 1), 0.0)
    if layer_height_mm is None:
        heights = _layer_heights(mv, area, lxy)
        labelled_h = np.isfinite(mv.height_mm) & (mv.height_mm > 0)
        heights = np.where(labelled_h, mv.height_mm, heights)
    else:
        heights = np.full(len(mv), float(layer_height_mm))

    tracks = []
    on = track >= 0
    ids = np.unique(track[on])
    for tid in ids:
        sel = np.nonzero((track == tid) & (lxy > 1e-9))[0]
        if len(sel) == 0:
            continue
        pts, wid, hei, flo = [], [], [], []
        for i in sel:
            h = heights[i]
            w = float(bead_width_mm(area[i], h)) if area[i] > 0 else 0.0
            q = area[i] * v_head[i]
            p0 = (mv.x0_mm[i], mv.y0_mm[i])
            if not pts or pts[-1] != p0 or wid[-1] != w or flo[-1] != q:
                pts.append(p0)
                wid.append(w)
                hei.append(h)
                flo.append(q)
            pts.append((mv.x_mm[i], mv.y_mm[i]))
            wid.append(w)
            hei.append(h)
            flo.append(q)
        length = float(lxy[sel].sum())
        if pr.labelled:
            kind = pr.track_kinds.get(int(tid), "other")
        else:
            kind = "test" if length >= min_test_length_mm else "other"
        tracks.append(Track(id=int(tid), kind=kind, points_mm=np.array(pts), width_mm=wid,
                            height_mm=hei, flow_mm3_s=flo, z_mm=float(np.round(mv.z_mm[sel[0]], 4))))

    pat = dict(pattern) if pattern is not None else {"name": "gcode"}
    pat.setdefault("planned_duration_s", round(mp.total_time_s, 3))
    if pr.warnings:
        pat.setdefault("warnings", list(pr.warnings))
    if pr.pa_events:
        times = np.asarray(mp.t_start_s)
        pat.setdefault("firmware_pa", [
            {"t_s": float(times[e.move_index]) if e.move_index < len(times) else mp.total_time_s,
             "k_s": e.k_s, "smooth_time_s": e.smooth_time_s, "line": e.line}
            for e in pr.pa_events])
    return Manifest(printer=prof.to_dict(), pattern=pat, tracks=tracks, timeline=tl)


def _layer_heights(mv, area, lxy) -> np.ndarray:
    """Per-move layer height (mm), see the module docstring."""
    z = np.round(mv.z_mm, 4)
    ext = (area > 0) & (lxy > 1e-9)
    h = np.maximum(z, 1e-3)
    if not ext.any():
        return h
    levels, inv = np.unique(z[ext], return_inverse=True)
    fil = np.bincount(inv, weights=mv.de_mm[ext])
    lev_h = levels.copy()
    for j in range(1, len(levels)):
        below = [i for i in range(j) if fil[i] >= 0.25 * fil[j]]
        if below:
            lev_h[j] = levels[j] - levels[max(below)]
    lookup = dict(zip(levels.tolist(), lev_h.tolist()))
    return np.array([lookup.get(zz, max(zz, 1e-3)) for zz in z.tolist()])
