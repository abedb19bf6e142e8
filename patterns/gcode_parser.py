"""G-code parser: third-party, slicer and our own G-code -> a flat table of moves.

Reads G0/G1, G2/G3 arcs (I/J or R; linearised into chords whose sagitta is at most
``arc_tolerance_mm``, sagitta = r (1 - cos(dtheta/2))), G90/G91, M82/M83, G92 (any axis),
G20/G21, G4 (P ms, S s), G10/G11 firmware retraction (the profile's retract length and
speed), G28 (position := 0), modal F, comments (``;`` and ``( )``), our ``;TRACK id=<n>
kind=<kind> h=<mm>`` / ``;HEIGHT h=<mm>`` / ``;END_TRACK`` labels (``h``: the commanded bead
height of the following extruding moves, so a track printed at h != z spacing keeps its
commanded width), pressure-advance commands (``M900 K``,
``SET_PRESSURE_ADVANCE ADVANCE= SMOOTH_TIME=``, ``M572 S``) and acceleration changes
(``M204 S/P``, ``SET_VELOCITY_LIMIT ACCEL=``). Anything else is skipped and counted.

Positions are machine coordinates (G92 shifts the logical origin, not the head), E is
cumulative commanded filament: G92 E never resets it.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from calib.errors import UserError
from patterns.manifest import TRACK_KINDS

#: Commands with no effect on motion or extrusion timing that we accept silently.
HARMLESS = frozenset("""M104 M105 M106 M107 M109 M110 M111 M112 M114 M115 M117 M119 M140 M190 M141 M191
M84 M18 M17 M73 M75 M76 M77 M31 M400 M500 M501 M502 M503 M420 M300 G29 G80 G21 M155 M862.1 M862.3
T0 T1 T2 T3 M601 M602 M701 M702 M486 M413 M1001""".split())

_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)?")
_KLIPPER_ARG = re.compile(r"([A-Z_]+)\s*=\s*([^\s]+)")
_PAREN = re.compile(r"\([^)]*\)")
_TRACK = re.compile(r"^;\s*TRACK\s+id\s*=\s*(-?\d+)(?:\s+kind\s*=\s*(\w+))?"
                    r"(?:\s+h\s*=\s*(\d+\.?\d*|\.\d+))?", re.I)
_HEIGHT = re.compile(r"^;\s*HEIGHT\s+h\s*=\s*(\d+\.?\d*|\.\d+)", re.I)
_END_TRACK = re.compile(r"^;\s*END_TRACK\b", re.I)

MOVE_FIELDS = ("x0_mm", "y0_mm", "z0_mm", "x_mm", "y_mm", "z_mm", "de_mm", "feed_mm_s",
               "dwell_s", "accel_mm_s2", "track", "line", "height_mm")


@dataclass
class Moves:
    """One row per elementary move (arcs are already split into chords), all arrays (M,).

    x0_mm, y0_mm, z0_mm   machine position at the start of the move (mm)
    x_mm, y_mm, z_mm      machine position at its end (mm)
    de_mm                 commanded filament in this move (mm; < 0 retracts)
    feed_mm_s             requested feedrate (mm/s; along XYZ, or along E for E-only moves)
    dwell_s               > 0 for a dwell (G4): no motion, lasts dwell_s seconds
    accel_mm_s2           acceleration set by M204 / SET_VELOCITY_LIMIT (NaN: profile's)
    track                 ;TRACK label id, -1 outside labelled tracks
    line                  1-based source line number
    height_mm             commanded bead height from the ``h=`` labels (mm), NaN where
                          the G-code does not say (third-party G-code, outside tracks)
    """

    x0_mm: np.ndarray
    y0_mm: np.ndarray
    z0_mm: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    de_mm: np.ndarray
    feed_mm_s: np.ndarray
    dwell_s: np.ndarray
    accel_mm_s2: np.ndarray
    track: np.ndarray
    line: np.ndarray
    height_mm: np.ndarray | None = None

    def __post_init__(self):
        if self.height_mm is None:
            self.height_mm = np.full(np.shape(self.x_mm), np.nan)
        for name in MOVE_FIELDS:
            dt = np.int64 if name in ("track", "line") else float
            setattr(self, name, np.asarray(getattr(self, name), dtype=dt))

    def __len__(self) -> int:
        return len(self.x_mm)

    @property
    def xy_length_mm(self) -> np.ndarray:
        return np.hypot(self.x_mm - self.x0_mm, self.y_mm - self.y0_mm)

    @property
    def xyz_length_mm(self) -> np.ndarray:
        return np.sqrt((self.x_mm - self.x0_mm) ** 2 + (self.y_mm - self.y0_mm) ** 2
                       + (self.z_mm - self.z0_mm) ** 2)

    def subset(self, mask) -> "Moves":
        return Moves(**{n: getattr(self, n)[mask] for n in MOVE_FIELDS})


@dataclass
class PAEvent:
    """A firmware pressure-advance change, effective from move ``move_index`` on.

    k_s: new advance (s) or None if unchanged; smooth_time_s likewise (Klipper);
    t_s: program time of the change (filled by ``planner.plan_gcode``, NaN before).
    """

    move_index: int
    line: int
    command: str
    k_s: float | None = None
    smooth_time_s: float | None = None
    t_s: float = float("nan")


@dataclass
class ParseResult:
    moves: Moves
    track_kinds: dict = field(default_factory=dict)
    pa_events: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    unknown_commands: dict = field(default_factory=dict)
    n_lines: int = 0

    @property
    def labelled(self) -> bool:
        """True if the G-code carries our ;TRACK labels."""
        return bool(self.track_kinds)


def parse_gcode(text, profile=None, *, arc_tolerance_mm: float = 0.1) -> ParseResult:
    """Parse G-code text (str or bytes) into moves. ``profile`` supplies G10/G11 retraction
    and the bed for out-of-bed warnings. Raises UserError if the input is not G-code."""
    if isinstance(text, (bytes, bytearray)):
        if b"\x00" in text[:65536]:
            raise UserError("the input is a binary file, not G-code text")
        text = bytes(text).decode("utf-8", errors="replace")
    if "\x00" in text[:65536]:
        raise UserError("the input is a binary file, not G-code text")
    st = _State(profile, arc_tolerance_mm)
    lines = text.splitlines()
    n_cmd = 0
    for lineno, raw in enumerate(lines, start=1):
        n_cmd += st.feed_line(raw, lineno)
    if n_cmd == 0:
        raise UserError("the input has no G or M commands: it is not G-code")
    return st.result(len(lines))


class _State:
    """Modal parser state (private: one per parse)."""

    def __init__(self, profile, tol):
        self.profile = profile
        self.tol = float(tol)
        self.pos = [0.0, 0.0, 0.0]          # machine XYZ (mm)
        self.off = [0.0, 0.0, 0.0, 0.0]     # logical = machine - off (XYZ, E)
        self.e_logical = 0.0
        self.abs_xyz = True
        self.rel_e_m83 = False
        self.rel_g91 = False
        self.unit = 1.0                     # mm per input unit (G20: 25.4)
        self.feed = 25.0                    # mm/s, modal
        self.accel = math.nan
        self.track = -1
        self.h_mm = math.nan                # commanded bead height from ;TRACK h= / ;HEIGHT h=
        self.kinds: dict[int, str] = {}
        self.rows: list[tuple] = []
        self.pa: list[PAEvent] = []
        self.unknown: dict[str, int] = {}
        self.warnings: list[str] = []
        self.fw_retracted = False

    # -- per line -----------------------------------------------------------
    def feed_line(self, raw: str, lineno: int) -> int:
        s = raw.strip()
        if not s:
            return 0
        if s[0] == ";":
            m = _TRACK.match(s)
            if m:
                self._begin_track(int(m.group(1)), (m.group(2) or "test").lower(), lineno)
                self.h_mm = float(m.group(3)) if m.group(3) else math.nan
            elif _END_TRACK.match(s):
                self.track = -1
                self.h_mm = math.nan
            else:
                mh = _HEIGHT.match(s)
                if mh:
                    self.h_mm = float(mh.group(1))
            return 0
        code = s.split(";", 1)[0]
        if "(" in code:
            code = _PAREN.sub(" ", code)
        code = code.strip()
        if not code:
            return 0
        if code[0] in "Nn" and len(code) > 1 and code[1].isdigit():
            code = re.sub(r"^[Nn]\d+\s*", "", code)
            code = re.sub(r"\*\d+\s*$", "", code)
            if not code:        # a line number alone ("N0"): nothing to do
                return 0
        up = code.upper()
        head = up.split(None, 1)[0]
        if not re.match(r"^[GMT]\d", head):
            return self._extended(up, head, lineno)
        words = _WORD.findall(up)
        if not words:
            return 0
        letter, num = words[0]
        cmd = letter + (_canon(num) if num else "")
        args = {}
        for k, v in words[1:]:
            args[k] = _number(k, v, lineno, code) if v else None
        if cmd in MOTION and any(args[a] is None for a in "XYZEF" if a in args):
            raise UserError(f"line {lineno}: {cmd} has an axis word without a number: "
                            f"{code.strip()[:60]!r}")
        self._command(cmd, args, lineno)
        return 1

    def _begin_track(self, tid: int, kind: str, lineno: int):
        if kind not in TRACK_KINDS:
            self.warnings.append(f"line {lineno}: unknown track kind {kind!r}, using 'other'")
            kind = "other"
        self.track = tid
        self.kinds[tid] = kind

    def _extended(self, up: str, head: str, lineno: int) -> int:
        """Klipper-style extended commands (NAME KEY=VALUE ...)."""
        args = dict(_KLIPPER_ARG.findall(up))
        if head == "SET_PRESSURE_ADVANCE":
            k = _float_or_none(args.get("ADVANCE"))
            st = _float_or_none(args.get("SMOOTH_TIME"))
            self.pa.append(PAEvent(len(self.rows), lineno, head, k, st))
            return 1
        if head == "SET_VELOCITY_LIMIT":
            a = _float_or_none(args.get("ACCEL"))
            if a is not None and a > 0:
                self.accel = a
            return 1
        if head[:1].isalpha() and re.match(r"^[A-Z_][A-Z0-9_]*$", head):
            self.unknown[head] = self.unknown.get(head, 0) + 1
            return 1 if "_" in head else 0
        return 0

    def _command(self, cmd: str, a: dict, lineno: int):
        if cmd in ("G0", "G1"):
            self._linear(a, lineno)
        elif cmd in ("G2", "G3"):
            self._arc(a, lineno, clockwise=(cmd == "G2"))
        elif cmd == "G4":
            secs = 0.0
            if a.get("P") is not None:
                secs = a["P"] / 1000.0
            elif a.get("S") is not None:
                secs = a["S"]
            if secs > 0:
                self._row(self.pos, self.pos, 0.0, 0.0, secs, lineno)
        elif cmd == "G90":
            self.abs_xyz, self.rel_g91 = True, False
        elif cmd == "G91":
            self.abs_xyz, self.rel_g91 = False, True
        elif cmd == "M82":
            self.rel_e_m83 = False
        elif cmd == "M83":
            self.rel_e_m83 = True
        elif cmd == "G20":
            self.unit = 25.4
        elif cmd == "G21":
            self.unit = 1.0
        elif cmd == "G92":
            self._g92(a)
        elif cmd == "G28":
            axes = [i for i, k in enumerate("XYZ") if k in a] or [0, 1, 2]
            for i in axes:
                self.pos[i] = 0.0
                self.off[i] = 0.0
        elif cmd in ("G10", "G11"):
            if any(k in a for k in ("P", "L")):
                self._unknown(f"{cmd} (tool offsets)")
            else:
                self._fw_retract(cmd == "G10", lineno)
        elif cmd == "M900":
            k = a.get("K")
            if k is not None:
                self.pa.append(PAEvent(len(self.rows), lineno, cmd, k, None))
        elif cmd == "M572":
            k = a.get("S")
            if k is not None:
                self.pa.append(PAEvent(len(self.rows), lineno, cmd, k, None))
        elif cmd == "M204":
            v = a.get("P") if a.get("P") is not None else a.get("S")
            if v is not None and v > 0:
                self.accel = v
        elif cmd in HARMLESS or cmd[0] == "T":
            pass
        else:
            self._unknown(cmd)

    def _unknown(self, cmd: str):
        self.unknown[cmd] = self.unknown.get(cmd, 0) + 1

    # -- moves --------------------------------------------------------------
    def _targets(self, a: dict):
        """Machine XYZ target and filament step of a G0/G1/G2/G3."""
        tgt = list(self.pos)
        for i, k in enumerate("XYZ"):
            v = a.get(k)
            if v is None:
                continue
            v *= self.unit
            tgt[i] = (v + self.off[i]) if self.abs_xyz else (self.pos[i] + v)
        de = 0.0
        ev = a.get("E")
        if ev is not None:
            ev *= self.unit
            if self.rel_e_m83 or self.rel_g91:
                de = ev
            else:
                de = ev - self.e_logical
            self.e_logical += de
        if a.get("F") is not None and a["F"] > 0:
            self.feed = a["F"] * self.unit / 60.0
        return tgt, de

    def _linear(self, a: dict, lineno: int):
        tgt, de = self._targets(a)
        if tgt != self.pos or de != 0.0:
            self._row(self.pos, tgt, de, self.feed, 0.0, lineno)
            self.pos = tgt

    def _arc(self, a: dict, lineno: int, clockwise: bool):
        start = list(self.pos)
        tgt, de = self._targets(a)
        x0, y0 = start[0], start[1]
        x1, y1 = tgt[0], tgt[1]
        if a.get("R") is not None:
            r = a["R"] * self.unit
            dx, dy = x1 - x0, y1 - y0
            d = math.hypot(dx, dy)
            if d == 0 or abs(r) < d / 2 - 1e-9:
                self.warnings.append(f"line {lineno}: arc radius {abs(r):g} mm cannot join its end points; "
                                     "drawn as a straight line")
                self._row(start, tgt, de, self.feed, 0.0, lineno)
                self.pos = tgt
                return
            h = math.sqrt(max(r * r - d * d / 4, 0.0))
            # Centre on the left of the chord for CCW arcs of less than half a turn;
            # a negative R asks for the long way round.
            sgn = (1.0 if not clockwise else -1.0) * (1.0 if r > 0 else -1.0)
            cx = x0 + dx / 2 - sgn * h * dy / d
            cy = y0 + dy / 2 + sgn * h * dx / d
        else:
            i = (a.get("I") or 0.0) * self.unit
            j = (a.get("J") or 0.0) * self.unit
            if i == 0 and j == 0:
                self.warnings.append(f"line {lineno}: arc without I/J/R; drawn as a straight line")
                self._row(start, tgt, de, self.feed, 0.0, lineno)
                self.pos = tgt
                return
            cx, cy = x0 + i, y0 + j
        r = math.hypot(x0 - cx, y0 - cy)
        a0 = math.atan2(y0 - cy, x0 - cx)
        a1 = math.atan2(y1 - cy, x1 - cx)
        sweep = a1 - a0
        if clockwise:
            if sweep >= -1e-12:
                sweep -= 2 * math.pi
        else:
            if sweep <= 1e-12:
                sweep += 2 * math.pi
        if r <= self.tol:
            n = 1
        else:
            dth = 2.0 * math.acos(max(1.0 - self.tol / r, -1.0))
            n = max(1, math.ceil(abs(sweep) / dth - 1e-9))
        prev = start
        for k in range(1, n + 1):
            f = k / n
            if k == n:
                pt = list(tgt)
            else:
                ang = a0 + sweep * f
                pt = [cx + r * math.cos(ang), cy + r * math.sin(ang), start[2] + (tgt[2] - start[2]) * f]
            self._row(prev, pt, de / n, self.feed, 0.0, lineno)
            prev = pt
        self.pos = tgt

    def _g92(self, a: dict):
        if not any(k in a for k in "XYZE"):
            a = {"X": 0.0, "Y": 0.0, "Z": 0.0, "E": 0.0}
        for i, k in enumerate("XYZ"):
            if k in a:
                self.off[i] = self.pos[i] - (a[k] or 0.0) * self.unit
        if "E" in a:
            self.e_logical = (a["E"] or 0.0) * self.unit

    def _fw_retract(self, retract: bool, lineno: int):
        p = self.profile
        if p is None:
            length, speed = 1.0, 35.0
            if not any("G10/G11" in w for w in self.warnings):
                self.warnings.append("G10/G11 firmware retraction without a printer profile: "
                                     "assumed 1.0 mm at 35 mm/s")
        else:
            length, speed = p.retract_length_mm, p.retract_speed_mm_s
        if retract == self.fw_retracted:
            return  # firmware ignores a second G10 (or a G11 without G10)
        self.fw_retracted = retract
        self._row(self.pos, self.pos, -length if retract else length, speed, 0.0, lineno)

    def _row(self, p0, p1, de, feed, dwell, lineno):
        self.rows.append((p0[0], p0[1], p0[2], p1[0], p1[1], p1[2], de, feed, dwell,
                          self.accel, self.track, lineno, self.h_mm))

    def result(self, n_lines: int) -> ParseResult:
        if self.rows:
            cols = list(zip(*self.rows))
        else:
            cols = [[] for _ in MOVE_FIELDS]
        moves = Moves(**{n: np.asarray(c) for n, c in zip(MOVE_FIELDS, cols)})
        warnings = list(self.warnings)
        if self.unknown:
            total = sum(self.unknown.values())
            listing = ", ".join(f"{k} x{v}" for k, v in sorted(self.unknown.items()))
            warnings.append(f"skipped {total} unknown command(s): {listing}")
        if self.profile is not None and len(moves):
            inb = self.profile.in_bed(moves.x_mm, moves.y_mm, tol_mm=1e-3)
            if not inb.all():
                bad = int(np.argmin(inb))
                warnings.append(f"{int((~inb).sum())} move(s) end outside the bed of {self.profile.name}, "
                                f"first at line {int(moves.line[bad])}")
        return ParseResult(moves=moves, track_kinds=dict(self.kinds), pa_events=list(self.pa),
                           warnings=warnings, unknown_commands=dict(self.unknown), n_lines=n_lines)


def auto_tracks(moves: Moves, min_seg_mm: float = 1e-6) -> np.ndarray:
    """Track ids for unlabelled G-code: runs of consecutive extruding XY moves at one z.

    A move extrudes if it moves in XY and commands de > 0; any other move (travel,
    E-only, Z hop, dwell) ends the run. Returns (M,) int ids, -1 off tracks.
    """
    n = len(moves)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    ext = (moves.xy_length_mm > min_seg_mm) & (moves.de_mm > 0) & (moves.dwell_s <= 0)
    flat = np.abs(moves.z_mm - moves.z0_mm) < 1e-9
    ext &= flat
    prev_ext = np.concatenate([[False], ext[:-1]])
    same_z = np.concatenate([[False], np.abs(moves.z0_mm[1:] - moves.z_mm[:-1]) < 1e-9])
    start = ext & ~(prev_ext & same_z)
    ids = np.cumsum(start) - 1
    return np.where(ext, ids, -1).astype(np.int64)


#: commands whose X/Y/Z/E/F words must carry numbers (a bare 'X' or 'X NaN' is not 0)
MOTION = ("G0", "G1", "G2", "G3", "G92")
#: no printer is larger than this; beyond it a number is a typo or a corrupt file (mm)
MAX_ABS_COORD_MM = 1.0e5


def _number(letter: str, text: str, lineno: int, code: str) -> float:
    f = float(text)
    if not math.isfinite(f) or (letter in "XYZIJ" and abs(f) > MAX_ABS_COORD_MM):
        raise UserError(f"line {lineno}: {letter}{text} is not a usable number "
                        f"(|value| > {MAX_ABS_COORD_MM:g} or not finite): {code.strip()[:60]!r}")
    return f


def _canon(num: str) -> str:
    """'01' -> '1', '1.0' -> '1', '862.1' -> '862.1'."""
    try:
        f = float(num)
    except ValueError:
        return num
    return str(int(f)) if f.is_integer() else num


def _float_or_none(v):
    if v is None:
        return None
    try:
        return float(v)
    except ValueError:
        return None
