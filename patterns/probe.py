"""probe pattern: a print whose lines part the causes a missing effect can have, for
`calib diagnose` (docs/DISCOVER.md).

The other patterns each measure one thing well, and in them the candidate causes of a
misfit move together: on a spiral the time, the arc length and the heading grow as one; on
a stop-mid-path line every stop is as long and sits as far along. A residual that follows
one of them follows them all, and diagnose can only say so (fit/covariates.py
``aliases``). This print is the discovery bench's probe (fit/hidden.py ``probe_manifest``,
the ``separated`` variant of bench/foreign_printer.py ``PROBE_KW``) as G-code for a real
printer. Each straight line:

* starts slow (``slow_mm_s``, its first quarter) and then runs fast: the flow step that
  pressure advance, nonlinear flow and gear slip answer;
* has its own commanded width (``widths_dn`` nozzle diameters) and fast speed
  (``fast_mm_s``, capped by the printer's speed and ``max_flow_mm3_s``), cycled with
  periods 4 and 4 offset by the row, so that width, speed and flow do not move together
  (back-pressure acts on the width, nonlinear flow on the flow);
* stops with the nozzle at rest (a dwell, G4) for ``stops_s`` seconds at ``stops_at`` of
  its length, cycled with periods 3 and 2, and retracts at the stops ``stop_retract``
  marks: the last stop's length, the time since a stop, the time since a retraction and
  the arc length part (thermal ooze acts on the first two, an extruder's play on the
  reversal);
* runs the other way than the line before (heading), and the lines cover the content
  area (x, y: the bed's height).

Its retraction, at those stops and between the lines, is the bench probe's 1 mm
(``retract_mm``), not the profile's: a Bowden profile's 2-4 mm reversal is a test of its
own, where the library's forms and another printer's part most. On the foreign printer
(white noise, seeds 0-2) with the long_bowden profile's 4 mm its ooze and its play were
named `flow_gain` and `bed_mesh` (0 of 6 families), with 1 mm `thermal` and `backlash`
(6 of 6). The markers, ruler and labels keep the profile's retraction.

On the foreign printer's white-noise prints (6 seeds, session 59) the families were named
first on 30 of 30 with these stops against 27 of 30 with every stop alike (backlash 6/6
against 3/6; docs/DISCOVER.md, "A probe whose covariates part").

Lengths mm, speeds mm/s, times s, flows mm^3/s.
"""
from __future__ import annotations

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns import layout
from patterns.builder import PatternBuilder
from patterns.profile import load_profile

NAME = "probe"
#: fit/hidden.py probe_manifest's defaults (its widths 0.40-0.85 mm for a 0.4 mm nozzle)
DEFAULT_WIDTHS_DN = (1.0, 1.375, 1.75, 2.125)
DEFAULT_FAST_MM_S = (30.0, 60.0, 100.0, 140.0)
#: the ``separated`` probe of bench/foreign_printer.py (periods 3, 2 and 8: prime to each other)
DEFAULT_STOPS_S = (1.5, 3.0, 6.0)
DEFAULT_STOPS_AT = (0.5, 0.75)
DEFAULT_STOP_RETRACT = (True, False, False, True, False, True, True, False)
#: a common hot end melts 10-15 mm^3/s of PLA; beyond its rate the flow falls short of
#: the command whatever the extruder does, an effect of its own that would swamp the others
DEFAULT_MAX_FLOW_MM3_S = 10.0
SLOW_FRACTION = 0.25
#: lines 8 mm apart, as the bench's probe: a standing nozzle's blob (1-2 mm^3 on a Bowden at
#: these flows, piled 2-3 mm wide) stays clear of the next line's profile window
PITCH_MM = 8.0
#: the bench probe's retraction (fit/hidden.py: 1 mm) at the stops and between the lines,
#: whatever the profile's: enough to part the time since a retraction from the time since
#: a stop and to turn the drive round; a Bowden profile's 2-4 mm is a test of its own
#: (rendered tests showed the foreign printer's ooze and play misnamed after 4 mm, module
#: docstring)
DEFAULT_RETRACT_MM = 1.0


def _cycled(values, i: int):
    return values[i % len(values)]


def line_plan(profile, *, n_lines: int, length_mm: float, layer_height_mm: float, slow_mm_s: float,
              fast_mm_s, widths_dn, stops_s, stops_at, stop_retract, max_flow_mm3_s: float) -> list[dict]:
    """One dict per line: width (mm), slow and fast speeds (mm/s), the stop's place (mm
    along the line), dwell (s) and whether it retracts, the direction (+1: +x)."""
    dn = profile.nozzle_diameter_mm
    n_w = len(widths_dn)
    rows = []
    for i in range(n_lines):
        w = round(float(widths_dn[(i + i // len(fast_mm_s)) % n_w]) * dn, 3)
        area = float(bead_area_mm2(w, layer_height_mm))
        cap = min(profile.max_velocity_mm_s, max_flow_mm3_s / area)
        v_fast = min(float(_cycled(fast_mm_s, i)), cap)
        v_slow = min(slow_mm_s, cap)
        stop_mm = float(_cycled(stops_at, i)) * length_mm
        # speeds rounded down to 0.001 mm/s: the G-code's feed has that resolution
        # (F in mm/min, one decimal) and a rounded-up speed would pass the flow cap
        rows.append(dict(width_mm=w, slow_mm_s=float(np.floor(v_slow * 1e3) / 1e3),
                         fast_mm_s=float(np.floor(v_fast * 1e3) / 1e3),
                         slow_end_mm=SLOW_FRACTION * length_mm, stop_mm=stop_mm,
                         dwell_s=float(_cycled(stops_s, i)), retract=bool(_cycled(stop_retract, i)),
                         direction=1 if i % 2 == 0 else -1, flow_mm3_s=round(area * v_fast, 4)))
    return rows


def _label(r) -> str:
    w = f"{r['width_mm']:.2f}".lstrip("0")
    return f"w{w} v{r['fast_mm_s']:.0f} {r['dwell_s']:g}s{' R' if r['retract'] else ''}"


def generate(profile, *, n_lines: int = 8, length_mm: float = 60.0, layer_height_mm: float = 0.2,
             slow_mm_s: float = 20.0, fast_mm_s=DEFAULT_FAST_MM_S, widths_dn=DEFAULT_WIDTHS_DN,
             stops_s=DEFAULT_STOPS_S, stops_at=DEFAULT_STOPS_AT, stop_retract=DEFAULT_STOP_RETRACT,
             max_flow_mm3_s: float = DEFAULT_MAX_FLOW_MM3_S, retract_mm: float | None = DEFAULT_RETRACT_MM):
    """G-code and manifest of the probe (module docstring).

    n_lines         lines (>= 4: one of each fast speed)
    length_mm       line length (mm); the slow part is its first quarter
    slow_mm_s       head speed of the slow part (mm/s)
    fast_mm_s       head speeds of the fast parts, cycled over the lines (mm/s)
    widths_dn       commanded widths in nozzle diameters, cycled (offset by one every
                    len(fast_mm_s) lines)
    stops_s         dwell at each line's stop (s), cycled; stops_at its place as a fraction
                    of the length (after the slow part), cycled; stop_retract: retract the
                    profile's length for the dwell, cycled
    max_flow_mm3_s  the hot end's melt rate (mm^3/s): no line is commanded more
    retract_mm      retraction at the stops that retract and before the travels between
                    lines (mm of filament; None: the profile's); the markers, ruler and
                    labels keep the profile's
    """
    profile = load_profile(profile)
    r_mm = profile.retract_length_mm if retract_mm is None else float(retract_mm)
    fast = [float(v) for v in np.atleast_1d(fast_mm_s)]
    wdn = [float(v) for v in np.atleast_1d(widths_dn)]
    st = [float(v) for v in np.atleast_1d(stops_s)]
    at = [float(v) for v in np.atleast_1d(stops_at)]
    rt = [bool(v) for v in np.atleast_1d(stop_retract)]
    if n_lines < 4:
        raise UserError("probe: --lines must be >= 4")
    if not (fast and wdn and st and at and rt):
        raise UserError("probe: --speeds, the widths and the stops need one value at least")
    if not all(np.isfinite(v) and v > 0 for v in (*fast, *wdn, *st, slow_mm_s, length_mm, max_flow_mm3_s)):
        raise UserError("probe: speeds, widths, stops, --length-mm and --max-flow must be > 0")
    if not all(SLOW_FRACTION + 0.1 <= a <= 0.9 for a in at):
        raise UserError(f"probe: --stops-at must lie within {SLOW_FRACTION + 0.1:g}-0.9 of the line "
                        "(after its slow part, before its end)")
    rows = line_plan(profile, n_lines=n_lines, length_mm=length_mm, layer_height_mm=layer_height_mm,
                     slow_mm_s=slow_mm_s, fast_mm_s=fast, widths_dn=wdn, stops_s=st, stops_at=at,
                     stop_retract=rt, max_flow_mm3_s=max_flow_mm3_s)
    for r in rows:
        r.update(label=_label(r), length_mm=length_mm, group="probe")
    params = {"n_lines": int(n_lines), "length_mm": float(length_mm), "layer_height_mm": float(layer_height_mm),
              "slow_mm_s": float(slow_mm_s), "fast_mm_s": fast, "widths_dn": wdn, "stops_s": st,
              "stops_at": at, "stop_retract": rt, "max_flow_mm3_s": float(max_flow_mm3_s), "retract_mm": r_mm}
    frame = layout.place_rows(profile, NAME, rows, pitch_mm=PITCH_MM,
                              hint="reduce --lines or --length-mm")
    b = PatternBuilder(profile, NAME, params, layer_height_mm=layer_height_mm)
    b.set_z(layer_height_mm)
    b.frame_prime(frame)
    b.retract_mm = r_mm          # the test lines' own; the markers and labels keep the profile's
    for r in rows:
        x0, y = r["start_xy"]
        d = r["direction"]
        xa = x0 if d > 0 else x0 + length_mm
        at_x = lambda s: xa + d * s  # noqa: E731  (arc length -> x along this line)
        r["track"] = b.begin("test", (xa, y), params={
            "width_mm": r["width_mm"], "slow_mm_s": r["slow_mm_s"], "fast_mm_s": r["fast_mm_s"],
            "slow_end_s_mm": r["slow_end_mm"], "stop_s_mm": r["stop_mm"], "dwell_s": r["dwell_s"],
            "stop_retract_mm": r_mm if r["retract"] else 0.0,
            "flow_mm3_s": r["flow_mm3_s"]})
        w = r["width_mm"]
        b.extrude([(xa, y), (at_x(r["slow_end_mm"]), y)], w, r["slow_mm_s"])
        b.extrude([b.position, (at_x(r["stop_mm"]), y)], w, r["fast_mm_s"])
        if r["retract"]:
            b.retract()
        b.writer.dwell(r["dwell_s"])
        b.unretract()
        b.extrude([b.position, (at_x(length_mm), y)], w, r["fast_mm_s"])
        b.end()
    b.retract_mm = profile.retract_length_mm
    b.frame_furniture(frame, title="probe")
    for r in rows:
        b.label(r["label"], r["label_xy"], height_mm=layout.ROW_LABEL_H_MM, for_tracks=[r["track"]])
    return b.build()
