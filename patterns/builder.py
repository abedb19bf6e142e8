"""PatternBuilder: emits tracks through the G-code writer and assembles the manifest.

A pattern module plans its geometry in plain bed coordinates, then calls the builder:
``begin``/``extrude``/``coast``/``end`` for test tracks and ``fiducials``/``ruler``/
``label``/``prime_line`` for the furniture. The builder assigns track ids, keeps each
track's group and swept parameters, retracts around travels (profile retract length and
speed) and finally builds the :class:`~patterns.manifest.Manifest` from the G-code itself
(``patterns.plan.manifest_from_gcode``: tracks and planned timeline) plus what only the
pattern knows: fiducials, labels, ruler, pattern name and parameters.

``PATTERNS`` maps a pattern name to its ``generate(profile, **params) -> (gcode, Manifest)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns import font
from patterns.fiducials import FiducialPlan, corner_origins, plan_fiducial
from patterns.gcode_writer import GcodeWriter
from patterns.layout import Frame
from patterns.manifest import Manifest, Track
from patterns.profile import load_profile
from patterns.ruler import plan_ruler, ruler_height_mm

#: Width-reference prime line (frame_prime): lead-in duration (s), measured part of each
#: section after it settled (s), settling time in pressure time constants and its floor
#: (s), and the fastest section (mm/s).
REFERENCE_LEAD_S = 4.0
REFERENCE_MEASURE_S = 3.0
REFERENCE_SETTLE_TAUS = 8.0
REFERENCE_SETTLE_MIN_S = 3.0
REFERENCE_MAX_SPEED_MM_S = 25.0
#: Section widths in nozzle diameters (alternating); the lead-in has the first one's width.
REFERENCE_WIDTHS_DN = (2.5, 1.0, 2.5, 1.0)
#: Serpentine: most passes, their largest centre-to-centre spacing (mm), segments per
#: half-circle turn.
REFERENCE_PASSES = 4
REFERENCE_PITCH_MM = 2.5
REFERENCE_TURN_SEGMENTS = 12
#: Marker rasters: slow, so a lagging extruder's start transient spans few millimetres.
FIDUCIAL_SPEED_MM_S = 10.0
FURNITURE_SPEED_MM_S = 20.0     # fiducials, labels, ruler: slow enough to stick on layer 1
HOP_SPEED_MM_S = 60.0           # zero-extrusion hops between strokes of one track
LABEL_HEIGHT_MM = 3.5

@dataclass(frozen=True)
class ReferenceLine:
    """The width-reference prime line's geometry and schedule (:func:`reference_line`).

    points_mm (N, 2) path vertices; s_node_mm (N,) their arc length (mm); cuts_mm: arc
    lengths where the lead-in and each section begin and the last ends (mm);
    widths_mm / speeds_mm_s: commanded width (mm) and head speed (mm/s) of the lead-in and
    each section; sections_mm [[s0, s1, w]] (mm) the measured sections; straight_mm
    [[s0, s1]] the straight passes; flow_mm3_s the one volumetric flow; settle_s the
    settling time each section is designed for (s)."""

    points_mm: np.ndarray
    s_node_mm: np.ndarray
    cuts_mm: np.ndarray
    widths_mm: list
    speeds_mm_s: list
    sections_mm: list
    straight_mm: list
    flow_mm3_s: float
    settle_s: float

    def params(self) -> dict:
        """The track params measure/calibrate.py reads the reference by."""
        return {"role": "width_reference", "sections_mm": self.sections_mm, "straight_mm": self.straight_mm,
                "flow_mm3_s": float(self.flow_mm3_s), "settle_s": float(self.settle_s),
                "speed_mm_s": [float(v) for v in self.speeds_mm_s[1:]]}


def reference_line(xa_mm: float, xb_mm: float, y_top_mm: float, n_pass: int, pitch_mm: float,
                   nozzle_mm: float, height_mm: float, tau_s: float) -> ReferenceLine:
    """The width reference of :meth:`PatternBuilder.frame_prime` between x = ``xa_mm`` and
    ``xb_mm`` (the turns included), its first pass at ``y_top_mm`` and ``n_pass`` passes
    ``pitch_mm`` apart downwards; sections REFERENCE_WIDTHS_DN x ``nozzle_mm`` wide at
    one volumetric flow, each lasting settle + REFERENCE_MEASURE_S, settle =
    REFERENCE_SETTLE_TAUS x ``tau_s`` (the pressure time constant guess, s), at least
    REFERENCE_SETTLE_MIN_S (frame_prime's docstring says why)."""
    r = pitch_mm / 2
    xa, xb = xa_mm + r, xb_mm - r
    # alternating direction, half-circle turns outside [xa, xb]
    path, straight = [], []
    s = 0.0
    for k in range(n_pass):
        y = y_top_mm - k * pitch_mm
        a_, b_ = (xa, xb) if k % 2 == 0 else (xb, xa)
        if k:
            yc, side = y + r, (1.0 if k % 2 == 1 else -1.0)
            xc = a_
            ang = np.linspace(0.5 * np.pi, -0.5 * np.pi, REFERENCE_TURN_SEGMENTS + 1)[1:]
            turn = np.column_stack([xc + side * r * np.cos(ang), yc + r * np.sin(ang)])
            s += np.pi * r
            path.extend(turn)
        else:
            path.append(np.array([a_, y]))
        straight.append([float(s), float(s + (xb - xa))])
        path.append(np.array([b_, y]))
        s += xb - xa
    pts = np.array(path)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s_node = np.concatenate([[0.0], np.cumsum(seg)])
    L = float(s_node[-1])

    widths = [k * nozzle_mm for k in REFERENCE_WIDTHS_DN]
    settle = max(REFERENCE_SETTLE_MIN_S, REFERENCE_SETTLE_TAUS * tau_s)
    t_sec = settle + REFERENCE_MEASURE_S
    durs = [REFERENCE_LEAD_S] + [t_sec] * len(widths)
    ws = [widths[0]] + widths
    inv_a = [1.0 / float(bead_area_mm2(w, height_mm)) for w in ws]
    q = L / sum(d * ia for d, ia in zip(durs, inv_a))
    q = min(q, REFERENCE_MAX_SPEED_MM_S / max(inv_a))      # no section faster than the cap
    lengths = np.array([q * d * ia for d, ia in zip(durs, inv_a)])
    lengths *= L / lengths.sum()        # a capped Q: the line still fills the band (longer sections)
    cuts = np.concatenate([[0.0], np.cumsum(lengths)])
    cuts[-1] = L
    speeds = [q * ia for ia in inv_a]
    sections = [[float(cuts[i + 1]), float(cuts[i + 2]), float(w)] for i, w in enumerate(widths)]
    return ReferenceLine(pts, s_node, cuts, ws, speeds, sections, straight, float(q), float(settle))



@dataclass
class _Rec:
    """What the builder itself knows of a track (used when no planner is available)."""

    id: int
    kind: str
    group: str
    params: dict
    points: list = field(default_factory=list)
    widths: list = field(default_factory=list)
    heights: list = field(default_factory=list)
    flows: list = field(default_factory=list)


class PatternBuilder:
    """Builds one single-layer pattern. Lengths mm, speeds mm/s, filament mm."""

    def __init__(self, profile, name: str, params: dict, *, layer_height_mm: float = 0.2,
                 line_width_mm: float | None = None):
        self.profile = load_profile(profile)
        #: the retraction before a travel (mm of filament): the profile's unless a pattern
        #: sets its own for its test lines
        self.retract_mm = self.profile.retract_length_mm
        self.name = name
        self.params = dict(params)
        self.layer_height_mm = float(layer_height_mm)
        self.line_width_mm = float(line_width_mm or round(1.2 * self.profile.nozzle_diameter_mm, 2))
        self.writer = GcodeWriter(self.profile, layer_height_mm=self.layer_height_mm)
        self.fiducial_list = []
        self.labels: list[dict] = []
        self.ruler_info: dict = {}
        self._recs: dict[int, _Rec] = {}
        self._cur: _Rec | None = None
        self._next_id = 0
        self._retracted_mm = 0.0
        self._z = None
        self.writer.header(f"{name} pattern", self.params)

    # -- low level --------------------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        x, y, _ = self.writer.position
        return np.array([np.nan if x is None else x, np.nan if y is None else y])

    def set_z(self, z_mm: float) -> None:
        if self._z is None or abs(self._z - z_mm) > 1e-9:
            self.writer.set_z(z_mm)
            self._z = float(z_mm)

    def retract(self, length_mm: float | None = None) -> None:
        """Retract to ``length_mm`` (default ``retract_mm``) of total retraction."""
        target = self.retract_mm if length_mm is None else float(length_mm)
        if target > self._retracted_mm + 1e-9:
            self.writer.extruder_move(-(target - self._retracted_mm), self.profile.retract_speed_mm_s)
            self._retracted_mm = target

    def note_retracted(self, length_mm: float) -> None:
        """Tell the builder the pattern itself left the filament retracted by ``length_mm``."""
        self._retracted_mm = float(length_mm)

    def unretract(self) -> None:
        if self._retracted_mm > 1e-9:
            self.writer.extruder_move(self._retracted_mm, self.profile.retract_speed_mm_s)
            self._retracted_mm = 0.0

    def travel_to(self, xy, z_mm: float | None = None) -> None:
        """Retract, lift 0.4 mm, travel, lower to ``z_mm`` (default: layer height)."""
        z = self.layer_height_mm if z_mm is None else float(z_mm)
        here = self.position
        if np.all(np.isfinite(here)) and np.hypot(*(np.asarray(xy) - here)) < 1e-6:
            self.set_z(z)
            return
        self.retract()
        if self._z is not None:
            self.set_z(max(self._z, z) + 0.4)
        self.writer.travel(float(xy[0]), float(xy[1]))
        self.set_z(z)

    # -- tracks -----------------------------------------------------------------
    def begin(self, kind: str, start_xy, *, group: str = "", params: dict | None = None,
              z_mm: float | None = None, restore: bool = True) -> int:
        """Travel to ``start_xy`` and open a track; returns its id."""
        self.travel_to(start_xy, z_mm)
        if restore:
            self.unretract()
        tid = self._next_id
        self._next_id += 1
        self._cur = _Rec(tid, kind, group, dict(params or {}))
        self._recs[tid] = self._cur
        self.writer.begin_track(tid, kind)
        self._vertex(self.position, 0.0, 0.0, self.layer_height_mm)
        return tid

    def end(self) -> None:
        self.writer.end_track()
        self._cur = None

    def _vertex(self, xy, w, q, h_mm=None):
        """Record a vertex with bead width ``w`` (mm), flow ``q`` (mm^3/s) and bead height
        ``h_mm`` (mm; default: the previous vertex's)."""
        r = self._cur
        if r is None:
            return
        r.points.append([float(xy[0]), float(xy[1])])
        r.widths.append(float(w))
        r.heights.append(float(h_mm if h_mm is not None else (r.heights[-1] if r.heights else self.layer_height_mm)))
        r.flows.append(float(q))
        if len(r.points) == 2:          # the start vertex takes the first segment's values
            r.widths[0], r.flows[0], r.heights[0] = r.widths[1], r.flows[1], r.heights[1]

    def extrude(self, points_mm, width_mm, speed_mm_s: float, height_mm: float | None = None) -> float:
        """Extrude along ``points_mm`` (N, 2); width per segment (scalar or N-1). Returns filament mm."""
        pts = np.asarray(points_mm, dtype=float).reshape(-1, 2)
        w = np.broadcast_to(np.asarray(width_mm, dtype=float), (len(pts) - 1,))
        h = self.layer_height_mm if height_mm is None else float(height_mm)
        e = 0.0
        for p, wi in zip(pts[1:], w):
            e += self.writer.extrude_line(p[0], p[1], wi, speed_mm_s, height_mm=h)
            self._vertex(p, wi, float(bead_area_mm2(wi, h)) * speed_mm_s, h)
        return e

    def coast(self, points_mm, speed_mm_s, e_mm=0.0) -> None:
        """Move along ``points_mm`` with filament ``e_mm`` per segment (0: extrusion stopped).

        ``speed_mm_s`` is a scalar or one speed per segment (a feed ramp).
        """
        pts = np.asarray(points_mm, dtype=float).reshape(-1, 2)
        v = np.broadcast_to(np.asarray(speed_mm_s, dtype=float), (len(pts) - 1,))
        e = np.broadcast_to(np.asarray(e_mm, dtype=float), (len(pts) - 1,))
        for p, vi, ei in zip(pts[1:], v, e):
            self.writer.move_with_e(p[0], p[1], ei, vi)
            self._vertex(p, 0.0, 0.0)

    def strokes_track(self, kind: str, strokes, *, width_mm: float | None = None,
                      speed_mm_s: float = FURNITURE_SPEED_MM_S, group: str = "",
                      params: dict | None = None) -> int:
        """One track drawing several polylines joined by zero-extrusion hops."""
        strokes = [np.asarray(s, dtype=float) for s in strokes if len(s) >= 2]
        w = self.line_width_mm if width_mm is None else float(width_mm)
        tid = self.begin(kind, strokes[0][0], group=group, params=params)
        for k, s in enumerate(strokes):
            if k:
                self.coast([self.position, s[0]], HOP_SPEED_MM_S)
            self.extrude(s, w, speed_mm_s)
        self.end()
        return tid

    # -- furniture --------------------------------------------------------------
    def prime_line(self, p0, p1, width_mm: float | None = None, speed_mm_s: float = 15.0) -> int:
        w = self.line_width_mm * 1.5 if width_mm is None else width_mm
        tid = self.begin("prime", p0)
        self.extrude([p0, p1], w, speed_mm_s)
        self.end()
        return tid

    def fiducial(self, plan: FiducialPlan) -> int:
        """Print a marker: one track per raster chain, each reached by a retracted travel
        (patterns/fiducials.py: the nozzle never crosses a black cell while flowing).
        Returns the first chain's track id."""
        first = None
        for chain in plan.chains_mm:
            tid = self.begin("fiducial", chain[0], params={"marker_id": plan.fiducial.id})
            self.extrude(chain, plan.line_width_mm, FIDUCIAL_SPEED_MM_S)
            self.end()
            first = tid if first is None else first
        self.fiducial_list.append(plan.fiducial)
        return first

    def ruler(self, origin_mm, length_mm: float, angle_deg: float = 0.0) -> int:
        plan = plan_ruler(origin_mm, length_mm, angle_deg)
        tid = self.strokes_track("ruler", plan.strokes_mm, width_mm=self.profile.nozzle_diameter_mm)
        self.ruler_info = dict(plan.info, track=tid)
        return tid

    def label(self, text: str, origin_mm, *, height_mm: float = LABEL_HEIGHT_MM,
              angle_deg: float = 0.0, for_tracks=(), anchor: str = "left") -> int:
        """Print ``text`` with its lower-left corner (``anchor``="left") or lower-centre
        (``anchor``="center") at ``origin_mm``; recorded in Manifest.labels."""
        strokes = font.text_strokes(text, height_mm)
        if anchor == "center":
            strokes = [s - [font.text_width_mm(text, height_mm) / 2, 0] for s in strokes]
        strokes = font.place_strokes(strokes, origin_mm, angle_deg)
        tid = self.strokes_track("label", strokes, width_mm=self.profile.nozzle_diameter_mm)
        self.labels.append({"text": text, "track": tid, "height_mm": height_mm,
                            "angle_deg": angle_deg, "bbox_mm": list(font.strokes_bbox(strokes)),
                            "for_tracks": [int(t) for t in for_tracks]})
        return tid

    def frame_furniture(self, frame: Frame, title: str | None = None) -> None:
        """Four corner fiducials, the ruler along the bottom band and the title on top."""
        x0, y0, x1, y1 = frame.rect_mm
        f = frame.fiducial_mm
        for i, origin in enumerate(corner_origins(frame.rect_mm, frame.cell_mm)):
            self.fiducial(plan_fiducial(i, origin, frame.cell_mm, line_width_mm=0.5))
        length = np.floor((x1 - x0 - 2 * f - 10.0) / 10.0) * 10.0
        self.ruler((0.5 * (x0 + x1) - length / 2, y0 + (f - ruler_height_mm()) / 2), length)
        if title:
            self.label(title, (0.5 * (x0 + x1), y1 - f + 1.0), height_mm=3.5, anchor="center")

    def frame_prime(self, frame: Frame) -> int:
        """Prime line in the top band, between the top markers, printed as the scan's width
        reference (measure/calibrate.py): a serpentine of REFERENCE_PASSES straight passes
        joined by half-circle turns; a lead-in, then sections of commanded width
        REFERENCE_WIDTHS_DN nozzle diameters, alternating (the calibration fits apparent =
        g w + b0 to the sections' settled widths; two widths separate the scan's edge
        offset b0 from a flow/scale factor g, and the alternation lets g drift slowly).

        The whole line runs at one volumetric flow Q (mm^3/s): the width changes by the
        head's speed, v_k = Q / A(w_k, h), so the extruder never sees a flow step. A flow
        step settles over the pressure time constant and, with thermal ooze (seed 000),
        over tens of seconds: on the Adventurer 3 truth (tau 0.8 s, thermal 0.05 over 25 s,
        back-pressure Kb 1) the sections of the constant-*speed* reference of earlier
        versions drifted by 60-100 um over their settled part and the calibration could
        never be applied (README, the Bowden row). At constant flow only the bead's
        back-pressure changes with the width (Kb w_sat (tanh(w2/w_sat) - tanh(w1/w_sat))
        mm of filament, seed 001), and it drains over tau + Kb sech^2(w/w_sat) Af / (v h)
        (the back-pressure's feedback through the bead width): slow lines settle slowly,
        hence the serpentine, which buys length for speed. The lead-in takes the start
        transient.

        Each section lasts ``settle_s + REFERENCE_MEASURE_S``; ``settle_s`` (in the track's
        params with the sections and the straight parts, read by measure/calibrate.py) is
        REFERENCE_SETTLE_TAUS x the profile's pressure time constant guess, at least
        REFERENCE_SETTLE_MIN_S.
        """
        from patterns.layout import tau_guess_s

        x0, _, x1, y1 = frame.rect_mm
        f = frame.fiducial_mm
        dn = self.profile.nozzle_diameter_mm
        w_max = max(REFERENCE_WIDTHS_DN) * dn
        # passes from y1 - 3 down to above the title (frame_furniture: its baseline at
        # y1 - f + 1), at most REFERENCE_PITCH_MM apart, beads >= 1 mm apart
        room = (y1 - 3.0) - (y1 - f + 1.0 + LABEL_HEIGHT_MM + 1.0 + w_max / 2)
        n_pass = int(min(REFERENCE_PASSES, 1 + max(0.0, room) // (w_max + 1.0)))
        pitch = min(REFERENCE_PITCH_MM, room / (n_pass - 1)) if n_pass > 1 else REFERENCE_PITCH_MM
        ref = reference_line(x0 + f + 4.0, x1 - f - 4.0, y1 - 3.0, n_pass, pitch, dn,
                             self.layer_height_mm, tau_guess_s(self.profile))
        pts, s_node, cuts, ws, speeds = ref.points_mm, ref.s_node_mm, ref.cuts_mm, ref.widths_mm, ref.speeds_mm_s
        tid = self.begin("prime", pts[0], params=ref.params())
        # split the path at the section cuts; each piece at its section's width and speed
        for k in range(len(ws)):
            inside = (s_node > cuts[k] + 1e-9) & (s_node < cuts[k + 1] - 1e-9)
            piece = [np.interp(cuts[k + 1], s_node, pts[:, 0]), np.interp(cuts[k + 1], s_node, pts[:, 1])]
            self.extrude(np.vstack([self.position, pts[inside], piece]), ws[k], speeds[k])
        self.end()
        return tid

    # -- output -----------------------------------------------------------------
    def build(self, *, plan: bool = True) -> tuple[str, Manifest]:
        """Finish the G-code and return (gcode_text, manifest).

        With ``plan`` the manifest comes from re-reading the G-code
        (``patterns.plan.manifest_from_gcode``: tracks plus the planned timeline, widths
        at the commanded bead heights that the ``h=`` track labels carry); the builder's
        own records fill in kind, group and params.
        """
        self.retract()
        self.writer.footer()
        text = self.writer.text()
        pattern = {"name": self.name, "params": self.params}
        manifest = None
        if plan:
            try:
                from patterns.plan import manifest_from_gcode
            except ImportError:
                manifest_from_gcode = None
            if manifest_from_gcode is not None:
                manifest = manifest_from_gcode(text, self.profile, pattern=pattern)
                refused = (manifest.pattern or {}).get("firmware_refusals")
                if refused:
                    # a test print the firmware stops half-way is worse than none
                    line, why = refused[0]
                    raise UserError(f"{self.name}: Klipper would stop this pattern at G-code line {line} "
                                    f"({why}); choose narrower widths or a lower layer height, or raise "
                                    f"the profile's max_extrude_cross_section_mm2 to match printer.cfg")
        if manifest is None:
            manifest = Manifest(printer=self.profile.to_dict(), pattern=pattern,
                                tracks=self.own_tracks())
        # keep what the planner added (planned_duration_s, warnings), the pattern's own keys win
        manifest.pattern = {**(manifest.pattern or {}), **pattern}
        for tr in manifest.tracks:
            rec = self._recs.get(tr.id)
            if rec is not None:
                tr.kind, tr.group, tr.params = rec.kind, rec.group, dict(rec.params)
        manifest.fiducials = list(self.fiducial_list)
        manifest.labels = list(self.labels)
        manifest.ruler = dict(self.ruler_info)
        return text, manifest

    def own_tracks(self) -> list[Track]:
        """Tracks as the builder recorded them (commanded geometry, no planner)."""
        out = []
        for r in self._recs.values():
            out.append(Track(id=r.id, kind=r.kind, points_mm=np.array(r.points),
                             width_mm=np.array(r.widths), height_mm=np.array(r.heights),
                             flow_mm3_s=np.array(r.flows), z_mm=float(r.heights[0]),
                             group=r.group, params=dict(r.params)))
        return out


def _registry() -> dict:
    from patterns import probe, retract, spiral_step, start_stop, stop_mid_path
    return {"spiral-step": spiral_step.generate, "stop-mid-path": stop_mid_path.generate,
            "retract": retract.generate, "start-stop": start_stop.generate, "probe": probe.generate}


class _Patterns(dict):
    """Lazy name -> generate mapping (the pattern modules import this one)."""

    def _fill(self):
        if not dict.__len__(self):
            self.update(_registry())

    def __getitem__(self, k):
        self._fill()
        return dict.__getitem__(self, k)

    def __iter__(self):
        self._fill()
        return dict.__iter__(self)

    def __len__(self):
        self._fill()
        return dict.__len__(self)

    def __contains__(self, k):
        self._fill()
        return dict.__contains__(self, k)

    def keys(self):
        self._fill()
        return dict.keys(self)

    def items(self):
        self._fill()
        return dict.items(self)


#: pattern name -> generate(profile, **params) -> (gcode_text, Manifest)
PATTERNS = _Patterns()
