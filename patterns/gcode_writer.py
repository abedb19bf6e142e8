"""G-code writer: the only place that turns pattern geometry into G-code text.

Filament per line (the slicer's volume balance, fit/geometry.py):

    E = A(w, h) * length / Af * flow_multiplier,   Af = pi D^2 / 4,
    A(w, h) = (w - h) h + pi h^2 / 4               (rounded-rectangle bead)

Conventions (docs/ARCHITECTURE.md "G-code conventions"): relative E (M83) by default,
absolute E (M82) when asked or when the printer lacks M83; firmware pressure advance
switched off in the header unless a value is given (Marlin ``M900 K``, Klipper
``SET_PRESSURE_ADVANCE ADVANCE=``, RRF ``M572 D0 S``); feedrates in mm/min and only
written when they change; every track labelled ``;TRACK id=<n> kind=<kind> h=<mm>`` ...
``;END_TRACK``, where ``h`` is the commanded bead height (mm) of its extruding moves; a
move inside a track that commands another height is preceded by ``;HEIGHT h=<mm>``. The
parser reads these back, so the manifest reproduces the commanded width even when a track
is printed at a height other than the z spacing. Every XY target is checked against the
profile's bed.
"""
from __future__ import annotations

import math

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns.profile import PrinterProfile, format_gcode_template, load_profile

_E_DECIMALS = 5
_XY_DECIMALS = 3
_H_DECIMALS = 4     # bead height in the labels (0.1 um)


class GcodeWriter:
    """Accumulates G-code for one print. Positions in mm, speeds in mm/s, filament in mm."""

    def __init__(self, profile, *, relative_e: bool = True, pressure_advance_s: float | None = None,
                 smooth_time_s: float | None = None, layer_height_mm: float = 0.2,
                 flow_multiplier: float = 1.0):
        self.profile: PrinterProfile = load_profile(profile)
        if not layer_height_mm > 0:
            raise UserError(f"layer height must be > 0 mm, got {layer_height_mm}")
        if not flow_multiplier > 0:
            raise UserError(f"flow multiplier must be > 0, got {flow_multiplier}")
        self.relative_e = bool(relative_e) and self.profile.supports_relative_e
        self._relative_e_requested = bool(relative_e)
        self.pressure_advance_s = pressure_advance_s
        self.smooth_time_s = smooth_time_s
        self.layer_height_mm = float(layer_height_mm)
        self.flow_multiplier = float(flow_multiplier)
        self._lines: list[str] = []
        self._x = self._y = None
        self._z = None
        self._f_mm_min: float | None = None
        self._e_abs = 0.0          # what the firmware's E register holds (absolute mode)
        self._e_total = 0.0        # cumulative commanded filament, never reset
        self._n_moves = 0
        self._track: int | None = None
        self._track_h_mm: float | None = None   # bead height the labels last declared
        self._af = self.profile.filament_area_mm2

    # -- state --------------------------------------------------------------
    @property
    def position(self) -> tuple[float | None, float | None, float | None]:
        """Current (x, y, z) in mm, as written (None before the first move on that axis)."""
        return (self._x, self._y, self._z)

    @property
    def e_total_mm(self) -> float:
        """Cumulative commanded filament (mm), retractions subtracted, never reset."""
        return self._e_total

    def text(self) -> str:
        return "\n".join(self._lines) + "\n"

    # -- blocks ---------------------------------------------------------------
    def header(self, title: str, params: dict) -> None:
        """Title and parameters as comments, start G-code, temperatures, E mode, PA."""
        p = self.profile
        self.comment(f"calib: {title}")
        self.comment(f"printer: {p.name} ({p.firmware})")
        for k, v in params.items():
            self.comment(f"param {k} = {v}")
        start = format_gcode_template(p.start_gcode, p)
        if "{nozzle_temp_c}" not in p.start_gcode:
            # The start code does not heat: do it here, waiting for both temperatures.
            self._emit(f"M140 S{_num(p.bed_temp_c)}")
            self._emit(f"M104 S{_num(p.nozzle_temp_c)}")
            self._emit(f"M190 S{_num(p.bed_temp_c)}")
            self._emit(f"M109 S{_num(p.nozzle_temp_c)}")
        self.section("start gcode")
        for line in start.strip("\n").splitlines():
            self._emit(line.rstrip())
        self.section("calib setup")
        self._emit("G90")
        self._emit("G21")
        if self.relative_e:
            self._emit("M83 ; relative E")
        else:
            if self._relative_e_requested:
                self.comment(f"{p.name} does not support M83: absolute E")
            self._emit("M82 ; absolute E")
        self._emit("G92 E0")
        self._e_abs = 0.0
        self.set_pressure_advance(self.pressure_advance_s or 0.0, self.smooth_time_s)

    def comment(self, text: str) -> None:
        for line in str(text).splitlines() or [""]:
            self._lines.append(f"; {line}".rstrip())

    def section(self, name: str) -> None:
        self._lines.append(";")
        self._lines.append(f";=== {name} ===")

    def footer(self) -> None:
        if self._track is not None:
            self.end_track()
        self.section("end gcode")
        for line in format_gcode_template(self.profile.end_gcode, self.profile).strip("\n").splitlines():
            self._emit(line.rstrip())

    # -- tracks ---------------------------------------------------------------
    def begin_track(self, track_id: int, kind: str, height_mm: float | None = None) -> None:
        """Open track ``track_id``: ``;TRACK id=<n> kind=<kind> h=<mm>``.

        ``height_mm`` is the bead height of its extruding moves (default: the writer's
        layer height); extrude_line with another height adds a ``;HEIGHT h=<mm>`` line.
        """
        if self._track is not None:
            raise ValueError(f"begin_track({track_id}) inside track {self._track}; call end_track first")
        h = self.layer_height_mm if height_mm is None else float(height_mm)
        if not h > 0:
            raise UserError(f"track {track_id}: bead height must be > 0 mm, got {h}")
        self._track = int(track_id)
        self._track_h_mm = round(h, _H_DECIMALS)
        self._lines.append(f";TRACK id={int(track_id)} kind={kind} h={_fmt(self._track_h_mm, _H_DECIMALS)}")

    def end_track(self) -> None:
        self._track = None
        self._track_h_mm = None
        self._lines.append(";END_TRACK")

    # -- motion ---------------------------------------------------------------
    def set_z(self, z_mm, speed_mm_s=None) -> None:
        z = round(float(z_mm), _XY_DECIMALS)
        if not (0 <= z <= self.profile.max_z_mm):
            raise UserError(f"move {self._n_moves + 1} (set_z to Z{z}) is outside the printer's "
                            f"Z range 0..{self.profile.max_z_mm} mm")
        v = float(speed_mm_s) if speed_mm_s is not None else self.profile.max_z_velocity_mm_s
        self._n_moves += 1
        self._emit(f"G0 Z{_fmt(z, _XY_DECIMALS)}{self._feed(v)}")
        self._z = z

    def travel(self, x_mm, y_mm, speed_mm_s=None) -> None:
        """G0 to (x, y) without extrusion, at ``speed_mm_s`` (default: profile travel speed)."""
        x, y = self._target(x_mm, y_mm, "travel")
        v = float(speed_mm_s) if speed_mm_s is not None else self.profile.travel_speed
        self._emit(f"G0 X{_fmt(x, _XY_DECIMALS)} Y{_fmt(y, _XY_DECIMALS)}{self._feed(v)}")
        self._x, self._y = x, y

    def extrude_line(self, x_mm, y_mm, width_mm, speed_mm_s, height_mm=None) -> float:
        """G1 to (x, y) depositing a bead of ``width_mm`` x ``height_mm``; returns filament mm.

        E = bead_area_mm2(w, h) * length / Af * flow_multiplier (fit/geometry.py).
        """
        if self._x is None:
            raise ValueError("extrude_line before any travel: position unknown")
        h = self.layer_height_mm if height_mm is None else float(height_mm)
        w = float(width_mm)
        if w < 0 or h <= 0:
            raise UserError(f"move {self._n_moves + 1}: bead width {w} mm / height {h} mm must be positive")
        x, y = self._target(x_mm, y_mm, "extrude_line")
        if self._track is not None and round(h, _H_DECIMALS) != self._track_h_mm:
            self._track_h_mm = round(h, _H_DECIMALS)
            self._lines.append(f";HEIGHT h={_fmt(self._track_h_mm, _H_DECIMALS)}")
        length = math.hypot(x - self._x, y - self._y)
        e = float(bead_area_mm2(w, h)) * length / self._af * self.flow_multiplier
        return self._g1_e(x, y, e, speed_mm_s)

    def move_with_e(self, x_mm, y_mm, e_mm, speed_mm_s) -> None:
        """G1 to (x, y) with an explicit filament length ``e_mm`` (0 allowed: coasting)."""
        if self._x is None:
            raise ValueError("move_with_e before any travel: position unknown")
        x, y = self._target(x_mm, y_mm, "move_with_e")
        self._g1_e(x, y, float(e_mm), speed_mm_s)

    def extruder_move(self, e_mm, speed_mm_s) -> None:
        """E-only move: retract (e < 0) or prime/restore (e > 0), filament mm at mm/s."""
        e_str, de = self._e_word(float(e_mm))
        self._n_moves += 1
        self._emit(f"G1 E{e_str}{self._feed(float(speed_mm_s))}")
        self._e_total += de

    def dwell(self, seconds) -> None:
        ms = int(round(float(seconds) * 1000.0))
        if ms < 0:
            raise UserError(f"dwell of {seconds} s is negative")
        self._emit(f"G4 P{ms}")

    def display_message(self, text: str) -> None:
        """Show ``text`` on the printer's display: ``M117 <text>`` (Marlin, Klipper's
        display_status and RRF all take M117), preceded by the same text as a comment.

        The text is made firmware-safe: ASCII only, no ``;`` or ``()`` (they start
        comments), at most 40 characters (longer status lines scroll or are cut).
        """
        clean = "".join(c for c in str(text) if 32 <= ord(c) < 127 and c not in ";()").strip()[:40]
        self.comment(f"display: {clean}")
        if self.profile.firmware in ("marlin", "klipper", "rrf"):
            self._emit(f"M117 {clean}" if clean else "M117")

    def set_pressure_advance(self, k_s, smooth_time_s=None) -> None:
        """Firmware pressure advance K (s): M900 K / SET_PRESSURE_ADVANCE / M572 D0 S."""
        k = float(k_s)
        if k < 0:
            raise UserError(f"pressure advance must be >= 0 s, got {k}")
        fw = self.profile.firmware
        if fw == "klipper":
            line = f"SET_PRESSURE_ADVANCE ADVANCE={_num(k, 4)}"
            if smooth_time_s is not None:
                line += f" SMOOTH_TIME={_num(float(smooth_time_s), 4)}"
        elif fw == "rrf":
            line = f"M572 D0 S{_num(k, 4)}"
        else:
            line = f"M900 K{_num(k, 4)}"
        self._emit(line)

    # -- internals --------------------------------------------------------------
    def _target(self, x_mm, y_mm, what: str) -> tuple[float, float]:
        x = round(float(x_mm), _XY_DECIMALS)
        y = round(float(y_mm), _XY_DECIMALS)
        p = self.profile
        if not bool(p.in_bed(x, y)):
            raise UserError(f"move {self._n_moves + 1} ({what} to X{x:g} Y{y:g}) is outside the bed of "
                            f"{p.name}: x {p.bed_x_mm[0]:g}..{p.bed_x_mm[1]:g}, "
                            f"y {p.bed_y_mm[0]:g}..{p.bed_y_mm[1]:g} mm")
        self._n_moves += 1
        return x, y

    def _g1_e(self, x: float, y: float, e: float, speed_mm_s) -> float:
        e_str, de = self._e_word(e)
        self._emit(f"G1 X{_fmt(x, _XY_DECIMALS)} Y{_fmt(y, _XY_DECIMALS)} E{e_str}"
                   f"{self._feed(float(speed_mm_s))}")
        self._x, self._y = x, y
        self._e_total += de
        return de

    def _e_word(self, de: float) -> tuple[str, float]:
        """The E word for a filament step ``de`` and the step as the firmware will see it.

        Rounding is done on what is written (relative: each step; absolute: the running
        register), so e_total_mm equals the sum a parser reads back.
        """
        if self.relative_e:
            de_r = round(de, _E_DECIMALS)
            return _fmt(de_r, _E_DECIMALS), de_r
        new_abs = round(self._e_abs + de, _E_DECIMALS)
        de_r = new_abs - self._e_abs
        self._e_abs = new_abs
        return _fmt(new_abs, _E_DECIMALS), de_r

    def _feed(self, v_mm_s: float) -> str:
        if not v_mm_s > 0:
            raise UserError(f"move {self._n_moves}: speed must be > 0 mm/s, got {v_mm_s}")
        f = round(v_mm_s * 60.0, 1)
        if f == self._f_mm_min:
            return ""
        self._f_mm_min = f
        return f" F{_fmt(f, 1)}"

    def _emit(self, line: str) -> None:
        self._lines.append(line)


def _fmt(v: float, decimals: int) -> str:
    s = f"{v:.{decimals}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _num(v: float, decimals: int = 1) -> str:
    return _fmt(float(v), decimals)
