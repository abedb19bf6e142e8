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
Elsewhere (third-party G-code): z minus the top of the plastic already printed *under
this move's path* (a map of the top surface on a 0.5 mm grid, the bed at z = 0), so a
line printed straight on the bed at z = 0.3 is 0.3 mm high whatever was printed elsewhere
at z = 0.2 (tests that vary h line by line), and a second layer is the z spacing. A move
with nothing under it that ends up higher than 1.5 nozzle diameters is a bridge (or a
print in the air): its strand is taken as round, h = the nozzle diameter, with a warning.
Pass ``layer_height_mm`` to override both.
"""
from __future__ import annotations

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_width_mm
from patterns.gcode_parser import ParseResult, parse_gcode
from patterns.manifest import Manifest, Track
from patterns.planner import DS_MAX_MM, DT_MAX_S, _plan_with_details, klipper_refusals, track_ids
from patterns.profile import load_profile

#: Unlabelled extrusion runs shorter than this (mm) are kind "other" (text, dots, blobs).
MIN_TEST_LENGTH_MM = 3.0
#: A track turning by more than this (deg, in total) within a box of this diagonal (mm) is
#: a label's stroke, and so is a small track this close (mm) to one (_label_strokes).
TEXT_TURN_DEG = 150.0
TEXT_BOX_MM = 6.0
TEXT_NEAR_MM = 2.0
#: Ruler and dial ticks: at least TICK_FAMILY straight strokes (turning < TICK_TURN_DEG)
#: no longer than TICK_MAX_MM, of one length and width (within TICK_TOL_MM).
TICK_FAMILY = 8
TICK_MAX_MM = 8.0
TICK_TURN_DEG = 5.0
TICK_TOL_MM = 0.05
#: A tick stands on a line when an end of it lies within the tick's width plus this (mm)
#: of the line's centre.
TICK_TOUCH_MM = 0.1


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
    warnings = list(pr.warnings)
    if layer_height_mm is None:
        heights, hw = _layer_heights(mv, area, lxy, prof.nozzle_diameter_mm)
        warnings += hw
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
                            height_mm=hei, flow_mm3_s=flo, z_mm=float(np.round(mv.z_mm[sel[0]], 4)),
                            params={"gcode_lines": [int(mv.line[sel[0]]), int(mv.line[sel[-1]])]}))

    pat = dict(pattern) if pattern is not None else {"name": "gcode"}
    pat.setdefault("planned_duration_s", round(mp.total_time_s, 3))
    pat.setdefault("labelled", bool(pr.labelled))      # our ;TRACK labels: kinds are known
    odd = []      # implausible commanded beads (usually a wrong h)
    d = prof.nozzle_diameter_mm
    for tr in tracks:
        w = _typical_width_mm(tr)
        if np.isfinite(w) and (w > 4 * d or w < 0.5 * d):
            odd.append((tr.id, w, float(np.median(tr.height_mm))))
    if len(odd) == 1:
        tid, w, h = odd[0]
        warnings.append(f"track {tid}: commanded width {w:.2f} mm is implausible for a {d:g} mm nozzle "
                        f"(height {h:.3f} mm); check the layer height (--layer-height)")
    elif odd:
        ws, hs = [o[1] for o in odd], [o[2] for o in odd]
        warnings.append(f"{len(odd)} tracks have commanded widths implausible for a {d:g} mm nozzle "
                        f"({min(ws):.2f}-{max(ws):.2f} mm at heights {min(hs):.3f}-{max(hs):.3f} mm): "
                        f"{_id_ranges([o[0] for o in odd])}; check the layer height (--layer-height)")
    refused = klipper_refusals(mv, prof)
    if refused:
        line, why = refused[0]
        more = f" ({len(refused) - 1} more moves like it)" if len(refused) > 1 else ""
        warnings.append(f"Klipper would stop this print at G-code line {line}: {why}{more}; its [extruder] "
                        f"max_extrude_cross_section / max_extrude_only_distance (the profile's "
                        f"max_extrude_cross_section_mm2 / max_extrude_only_distance_mm) allow less")
        pat["firmware_refusals"] = [[ln, w] for ln, w in refused]
    if warnings:
        pat.setdefault("warnings", warnings)
    if pr.pa_events:
        times = np.asarray(mp.t_start_s)
        pat.setdefault("firmware_pa", [
            {"t_s": float(times[e.move_index]) if e.move_index < len(times) else mp.total_time_s,
             "k_s": e.k_s, "smooth_time_s": e.smooth_time_s, "line": e.line}
            for e in pr.pa_events])
    return Manifest(printer=prof.to_dict(), pattern=pat, tracks=tracks, timeline=tl)


def _typical_width_mm(tr: Track) -> float:
    """The commanded width (mm) over most of a track's length: the length-weighted median
    of its segments' widths (``width_mm[k]`` is the segment ending at point k). A test
    line of StartStopTestPLA1 restores its pressure over its first 1 mm at 50x the flow
    (a 42 mm "bead") and runs 14 mm at 0.41 mm: the median of its four points read 21 mm."""
    p = np.asarray(tr.points_mm, dtype=float)
    w = np.asarray(tr.width_mm, dtype=float)
    if len(p) < 2:
        return float(np.median(w)) if w.size else float("nan")
    L = np.hypot(*np.diff(p, axis=0).T)
    w = w[1:]
    ok = (w > 0) & (L > 0)
    if not ok.any():
        return float("nan")
    order = np.argsort(w[ok])
    cum = np.cumsum(L[ok][order])
    return float(w[ok][order][np.searchsorted(cum, 0.5 * cum[-1])])


#: grid of the top-surface map (mm)
SURFACE_CELL_MM = 0.5


def _layer_heights(mv, area, lxy, nozzle_mm: float) -> tuple[np.ndarray, list[str]]:
    """Per-move layer height (mm) and warnings, see the module docstring."""
    z = np.asarray(mv.z_mm, dtype=float)
    h = np.maximum(z, 1e-3)
    warnings: list[str] = []
    top: dict = {}                      # (ix, iy) -> top of the plastic there (mm)
    bridged = 0
    for i in np.flatnonzero((area > 0) & (lxy > 1e-9)):
        n = max(2, int(np.ceil(lxy[i] / SURFACE_CELL_MM)) + 1)
        xs = np.linspace(mv.x0_mm[i], mv.x_mm[i], n)
        ys = np.linspace(mv.y0_mm[i], mv.y_mm[i], n)
        cells = set(zip(np.round(xs / SURFACE_CELL_MM).astype(np.int64).tolist(),
                        np.round(ys / SURFACE_CELL_MM).astype(np.int64).tolist()))
        zi = float(z[i])
        # plastic of this same layer (a neighbouring line) is beside the bead, not under it
        below = [top[c] for c in cells if c in top and top[c] < zi - 0.01]
        base = max(below) if below else 0.0
        hi = zi - base
        if hi > 1.5 * nozzle_mm:
            bridged += 1
            hi = nozzle_mm
        h[i] = max(hi, 1e-3)
        for c in cells:
            top[c] = max(top.get(c, 0.0), zi)
    if bridged:
        warnings.append(f"{bridged} extruding move(s) have nothing printed under them more than "
                        f"{1.5 * nozzle_mm:.2f} mm down (bridges or prints in the air): their strand "
                        f"is taken as round, h = {nozzle_mm:g} mm")
    return h, warnings


def parse_id_ranges(text: str) -> set[int]:
    """"3-8,12" -> {3, 4, 5, 6, 7, 8, 12}; UserError on anything else."""
    from calib.errors import UserError

    out: set[int] = set()
    for part in (p.strip() for p in str(text).split(",") if p.strip()):
        try:
            if "-" in part[1:]:
                a, b = part.split("-", 1) if not part.startswith("-") else (part, part)
                out.update(range(int(a), int(b) + 1))
            else:
                out.add(int(part))
        except ValueError:
            raise UserError(f"--tracks: {part!r} is not a track id or a range like 3-8") from None
    return out


def tracks_matching_comment(manifest: Manifest, gcode_text: str, pattern: str) -> set[int]:
    """Ids of the tracks whose G-code comments match the regex ``pattern`` (case-insensitive,
    re.search): the last full-line comment before the track's first move (a slicer's
    ``;TYPE:`` or a test's own label) and every comment on its lines. Tracks planned by
    :func:`manifest_from_parse` carry their source lines (``params["gcode_lines"]``)."""
    import re

    try:
        rx = re.compile(pattern, re.I)
    except re.error as exc:
        raise UserError(f"--tracks-comment: {pattern!r} is not a regular expression ({exc})") from None
    lines = gcode_text.splitlines()
    last_comment = [""] * (len(lines) + 2)      # 1-based: the last full-line comment at or before
    cur = ""
    for i, ln in enumerate(lines, start=1):
        t = ln.strip()
        if t.startswith(";"):
            cur = t
        last_comment[i] = cur
    out = set()
    for tr in manifest.tracks:
        a, b = (tr.params or {}).get("gcode_lines", (None, None))
        if a is None:
            continue
        texts = [last_comment[max(0, a - 1)]]
        texts += [ln.split(";", 1)[1] for ln in lines[a - 1:b] if ";" in ln]
        if any(rx.search(t) for t in texts):
            out.add(tr.id)
    return out


def select_tracks(manifest: Manifest, ids: set[int] | None = None,
                  z_range_mm: tuple[float, float] | None = None, auto_exclude: bool = True,
                  bed_margin_mm: float = 10.0) -> list[str]:
    """Decide which tracks are the test (kind "test"); the others become "other" or
    "prime". Returns one line per decision a user should know about.

    ids / z_range_mm: only these track ids / tracks whose z lies in [lo, hi] (mm) are tests.
    auto_exclude (G-code without our labels): the first extruding track when it runs
    within ``bed_margin_mm`` of the bed edge is the prime line; closed loops (start and end
    within 1 mm, longer than 10 mm: skirts, dial rings, perimeters) and labels' strokes
    (:func:`_label_strokes`) are "other"."""
    notes: list[str] = []
    text: list[int] = []
    text_ids = _label_strokes(manifest) if auto_exclude and ids is None else set()
    tick_ids = _tick_strokes(manifest) if auto_exclude and ids is None else set()
    base_ids = _ruler_lines(manifest, tick_ids) if tick_ids else set()
    ticks: list[int] = []
    bases: list[int] = []
    prof = manifest.printer
    (x0, x1), (y0, y1) = prof.get("bed_x_mm", (-1e9, 1e9)), prof.get("bed_y_mm", (-1e9, 1e9))
    first = min((t.id for t in manifest.tracks), default=None)
    for t in manifest.tracks:
        if t.kind not in ("test", "other"):
            continue
        pts = np.asarray(t.points_mm, dtype=float)
        why = None
        if ids is not None and t.id not in ids:
            why = "not in --tracks"
        elif z_range_mm is not None and not (z_range_mm[0] - 1e-6 <= t.z_mm <= z_range_mm[1] + 1e-6):
            why = "outside --z-range-mm"
        elif auto_exclude and ids is None and len(pts) >= 2:
            near_edge = (pts[:, 0].min() - x0 < bed_margin_mm or x1 - pts[:, 0].max() < bed_margin_mm
                         or pts[:, 1].min() - y0 < bed_margin_mm or y1 - pts[:, 1].max() < bed_margin_mm)
            length = float(np.sum(np.hypot(*np.diff(pts, axis=0).T)))
            if t.id == first and near_edge:
                t.kind = "prime"
                notes.append(f"track {t.id} ({length:.0f} mm near the bed edge, printed first) is "
                             "taken as the prime line; --tracks to override")
                continue
            if np.hypot(*(pts[0] - pts[-1])) < 1.0 and length > 10.0 and t.kind == "test":
                t.kind = "other"
                notes.append(f"track {t.id} is a closed loop ({length:.0f} mm: skirt, ring or "
                             "perimeter), not a test line; --tracks to override")
                continue
            if t.id in text_ids:
                t.kind = "other"
                text.append(t.id)
                continue
            if t.id in tick_ids:
                t.kind = "other"
                ticks.append(t.id)
                continue
            if t.id in base_ids:
                t.kind = "other"
                bases.append(t.id)
                continue
        if why:
            t.kind = "other"
        elif ids is not None or z_range_mm is not None:
            t.kind = "test"
    if text:
        notes.append(f"{len(text)} tracks turn like letters or digits (> {TEXT_TURN_DEG:.0f} deg within "
                     f"{TEXT_BOX_MM:g} mm: labels), not test lines: {_id_ranges(text)}; --tracks to override")
    if ticks:
        notes.append(f"{len(ticks)} tracks are ruler or dial ticks (>= {TICK_FAMILY} straight strokes of one "
                     f"length <= {TICK_MAX_MM:g} mm), not test lines: {_id_ranges(ticks)}; --tracks to override")
    if bases:
        what = (f"track {bases[0]} is the line" if len(bases) == 1 else
                f"{len(bases)} tracks are the lines")
        notes.append(f"{what} ruler ticks stand on (>= {TICK_FAMILY} ticks touch each), not test lines: "
                     f"{_id_ranges(bases)}; --tracks to override")
    if ids is not None:
        have = {t.id for t in manifest.tracks}
        unknown = sorted(i for i in ids if i not in have)
        if unknown:
            notes.append(f"--tracks names {'ids' if len(unknown) > 1 else 'id'} no track has: "
                         f"{_id_ranges(unknown)} (the G-code's tracks are {_id_ranges(sorted(have)) or 'none'})")
    return notes


def _label_strokes(manifest: Manifest) -> set[int]:
    """Ids of the test tracks that are strokes of printed labels: small (box diagonal
    < TEXT_BOX_MM) and turning by more than TEXT_TURN_DEG, and the small tracks within
    TEXT_NEAR_MM of those (straight strokes: "1", "l", "-"). Test lines run straight or
    gently curved over tens of mm; the labels of the realdata tests ("Kf 10", "Kb 20")
    turned 170-460 deg within 3-4.5 mm and were measured as test tracks."""
    from scipy.spatial import cKDTree

    small, seeds = {}, set()
    for t in manifest.tracks:
        if t.kind != "test":
            continue
        pts = np.asarray(t.points_mm, dtype=float)
        if len(pts) < 2 or float(np.hypot(*np.ptp(pts, axis=0))) >= TEXT_BOX_MM:
            continue
        small[t.id] = t.at(np.linspace(0.0, t.length_mm, max(2, int(t.length_mm / 0.5) + 1)))[0]
        d = np.diff(pts, axis=0)
        d = d[np.hypot(*d.T) > 1e-6]
        if len(d) >= 2:
            a = np.arctan2(d[:, 1], d[:, 0])
            if float(np.degrees(np.abs(np.angle(np.exp(1j * np.diff(a)))).sum())) > TEXT_TURN_DEG:
                seeds.add(t.id)
    text, grow = set(seeds), set(seeds)
    trees = {k: cKDTree(v) for k, v in small.items()}
    while grow:
        new = set()
        for k in set(small) - text:
            if any(trees[g].query(small[k], distance_upper_bound=TEXT_NEAR_MM)[0].min() <= TEXT_NEAR_MM for g in grow):
                new.add(k)
        text |= new
        grow = new
    return text


def _tick_strokes(manifest: Manifest) -> set[int]:
    """Ids of the test tracks that are ruler or dial ticks: straight strokes (turning by
    less than TICK_TURN_DEG in all) no longer than TICK_MAX_MM, in a family of at least
    TICK_FAMILY of one length and width (within TICK_TOL_MM). On the realdata tests these
    were 24 dial ticks of 3.0 mm (SpStartStopTest2) and 44 + 44 ruler ticks of 3 and 5 mm
    (StartStopTestPLA1), measured as test tracks; the warm-up strokes beside the spiral
    test lines (3.9-5.9 mm, each length a few times) are not a family and stay."""
    cand = []
    for t in manifest.tracks:
        if t.kind != "test":
            continue
        pts = np.asarray(t.points_mm, dtype=float)
        d = np.diff(pts, axis=0)
        d = d[np.hypot(*d.T) > 1e-6]
        if not len(d):
            continue
        length = float(np.hypot(*d.T).sum())
        if length > TICK_MAX_MM:
            continue
        a = np.arctan2(d[:, 1], d[:, 0])
        if len(a) > 1 and float(np.degrees(np.abs(np.angle(np.exp(1j * np.diff(a)))).sum())) >= TICK_TURN_DEG:
            continue
        w = np.asarray(t.width_mm, dtype=float)
        cand.append((t.id, length, float(np.median(w[1:] if len(w) > 1 else w))))
    out: set[int] = set()
    for tid, length, w in cand:
        family = [c for c in cand if abs(c[1] - length) <= TICK_TOL_MM and abs(c[2] - w) <= TICK_TOL_MM]
        if len(family) >= TICK_FAMILY:
            out.add(tid)
    return out


def _ruler_lines(manifest: Manifest, tick_ids: set[int]) -> set[int]:
    """Ids of the test tracks that at least TICK_FAMILY of the ticks ``tick_ids`` touch (an
    end within a tick's width plus TICK_TOUCH_MM of the track's centre line: a ruler's line
    is drawn like its ticks, and a track's own commanded width can be a blob's, 42 mm over
    the 1 mm a test line restores its pressure in): a ruler's base line. StartStopTestPLA1
    draws each block's ruler as a 90 mm line with 44 ticks standing on it; measured as a
    test line, 82 % of its stations were flagged `crossing` (the ticks every 2 mm), 1180
    of the print's 2200."""
    from scipy.spatial import cKDTree

    ends = []
    for t in manifest.tracks:
        if t.id in tick_ids:
            pts = np.asarray(t.points_mm, dtype=float)
            w = float(np.median(np.asarray(t.width_mm, dtype=float)))
            ends += [(pts[0], w), (pts[-1], w)]
    if not ends:
        return set()
    xy = np.array([e[0] for e in ends])
    wt = np.array([e[1] for e in ends])
    out = set()
    for t in manifest.test_tracks():
        if t.id in tick_ids or t.length_mm <= TICK_MAX_MM:
            continue
        s = np.linspace(0.0, t.length_mm, max(2, int(t.length_mm / 0.1) + 1))
        line = np.asarray(t.at(s)[0], dtype=float)
        d, _ = cKDTree(line).query(xy)
        touch = d <= wt + TICK_TOUCH_MM
        # a tick touches with one end; count ticks, not ends
        n_ticks = int(np.sum(touch.reshape(-1, 2).any(axis=1)))
        if n_ticks >= TICK_FAMILY:
            out.add(t.id)
    return out


def _id_ranges(ids) -> str:
    """[3, 4, 5, 9] -> "3-5,9" (the --tracks syntax)."""
    ids = sorted(ids)
    out, start = [], ids[0]
    for a, b in zip(ids, ids[1:] + [None]):
        if b != a + 1:
            out.append(f"{start}-{a}" if a != start else f"{a}")
            start = b
    return ",".join(out)
