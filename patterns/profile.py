"""Printer profiles: the machine a pattern is printed on, read from TOML (tomllib).

A profile holds what the G-code writer needs (bed, temperatures, start/end code,
firmware flavour), what the motion planner needs (velocity/acceleration limits and the
cornering model) and what the physics needs (nozzle d and land length l, filament D,
Bowden length L: seed 000, tau = 32 D^2 L l / d^4 * VE).

Every key carries its unit in its name (``_mm``, ``_mm_s``, ``_mm_s2``, ``_c``).
Shipped profiles live in ``data/printers/NAME.toml``; ``load_profile("NAME")`` finds
them. Cornering model per firmware:

* klipper: ``square_corner_velocity_mm_s`` (klippy/toolhead.py; the junction deviation
  is derived as scv^2 (sqrt(2) - 1) / accel).
* marlin: ``junction_deviation_mm`` (Marlin planner.cpp, same junction formula; Marlin
  2.1 takes E into the unit vectors, so a change of extrusion rate is a corner), or
  ``max_jerk_mm_s`` for a build with CLASSIC_JERK (then as rrf below).
* rrf: RepRapFirmware limits the instantaneous speed change at a corner ("jerk", M566).
  We use ``max_jerk_mm_s``: the vector speed change at a junction may not exceed it,
  so v_j = jerk / |u1 - u2| (u = unit direction). RRF's jerk is per axis; using the
  vector norm is a documented approximation.

The extruder limits junctions too (patterns/planner.py ``_extruder_junction_v2``):
``instantaneous_corner_velocity_mm_s`` (Klipper, default 1 mm/s as Klipper's) and
``max_e_jerk_mm_s`` (RRF's M566 E, Marlin's classic-jerk M205 E).
"""
from __future__ import annotations

import math
import re
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from calib.errors import UserError

FIRMWARES = ("marlin", "klipper", "rrf")

#: Keys every profile must define (besides the firmware-specific cornering key).
REQUIRED_KEYS = (
    "name", "firmware", "bed_x_mm", "bed_y_mm", "max_z_mm",
    "nozzle_diameter_mm", "nozzle_land_length_mm", "filament_diameter_mm", "bowden_length_mm",
    "max_velocity_mm_s", "max_accel_mm_s2", "max_e_velocity_mm_s", "max_e_accel_mm_s2",
    "retract_length_mm", "retract_speed_mm_s", "nozzle_temp_c", "bed_temp_c",
    "start_gcode", "end_gcode",
)

#: Cornering key required per firmware flavour.
CORNER_KEY = {"klipper": "square_corner_velocity_mm_s", "marlin": "junction_deviation_mm",
              "rrf": "max_jerk_mm_s"}

_UNIT_SUFFIXES = ("_mm", "_mm_s", "_mm_s2", "_mm2", "_c", "_s")
_FOREIGN_UNIT = re.compile(r"_(in|inch|inches|cm|m|um|mm_min|in_s|f|k|deg_f|ms)$")


def data_dir() -> Path:
    """The repository's ``data/`` folder (next to the ``patterns`` package)."""
    return Path(__file__).resolve().parent.parent / "data"


@dataclass(frozen=True)
class PrinterProfile:
    """One printer. Lengths in mm, speeds in mm/s, accelerations in mm/s^2, temperatures in C.

    Physics: nozzle bore ``nozzle_diameter_mm`` (d) with land length
    ``nozzle_land_length_mm`` (l); filament ``filament_diameter_mm`` (D); Bowden tube
    ``bowden_length_mm`` (L, 0 = direct drive). Seed 000: tau = 32 D^2 L l / d^4 * VE.
    """

    name: str
    firmware: str
    bed_x_mm: tuple[float, float]
    bed_y_mm: tuple[float, float]
    max_z_mm: float
    nozzle_diameter_mm: float
    nozzle_land_length_mm: float
    filament_diameter_mm: float
    bowden_length_mm: float
    max_velocity_mm_s: float
    max_accel_mm_s2: float
    max_e_velocity_mm_s: float
    max_e_accel_mm_s2: float
    retract_length_mm: float
    retract_speed_mm_s: float
    nozzle_temp_c: float
    bed_temp_c: float
    start_gcode: str
    end_gcode: str
    square_corner_velocity_mm_s: float | None = None
    junction_deviation_mm: float | None = None
    max_jerk_mm_s: float | None = None
    #: Marlin's junction deviation over X, Y, Z and E (current Marlin, 2.1: a block that moves E
    #: normalises its unit vector with E in it, so a change of extrusion rate is a corner);
    #: false for older builds and forks, where E's share is too small to matter.
    junction_deviation_with_e: bool = True
    #: The extruder at a junction (patterns/planner.py ``_extruder_junction_v2``): Klipper's
    #: ``instantaneous_corner_velocity`` (its default 1 mm/s) ...
    instantaneous_corner_velocity_mm_s: float = 1.0
    #: ... and the E jerk of RRF (M566 E) and of Marlin's classic jerk (M205 E); None: not
    #: limited (Marlin's junction deviation takes E into the corner's angle instead).
    max_e_jerk_mm_s: float | None = None
    #: Klipper's [extruder] limits whose breach stops the print with an error
    #: (klippy/kinematics/extruder.py ``check_move``): the bead cross-section of an XY move
    #: (None: Klipper's default 4 d^2) and the length of an extrude-only move.
    max_extrude_cross_section_mm2: float | None = None
    max_extrude_only_distance_mm: float = 50.0
    max_z_velocity_mm_s: float = 10.0
    max_z_accel_mm_s2: float = 100.0
    #: Klipper's minimum_cruise_ratio is not modelled (see planner docstring).
    supports_relative_e: bool = True
    #: Does the firmware honour its pressure-advance command (Marlin M900 K, RRF M572,
    #: Klipper SET_PRESSURE_ADVANCE)? False where it is known to ignore it; `calib export`
    #: then says so and points at the slicer-side route (KISSlicer VE).
    firmware_pressure_advance: bool = True
    travel_speed_mm_s: float | None = None
    description: str = ""
    extra: dict = field(default_factory=dict)

    # -- derived ------------------------------------------------------------
    @property
    def filament_area_mm2(self) -> float:
        """Af = pi D^2 / 4 (mm^2)."""
        return math.pi / 4.0 * self.filament_diameter_mm ** 2

    @property
    def junction_deviation_for_planner_mm(self) -> float | None:
        """Junction deviation (mm) used by the cornering formula.

        Klipper (klippy/toolhead.py): jd = scv^2 (sqrt(2) - 1) / max_accel.
        Marlin: the profile's ``junction_deviation_mm``. RRF: None (jerk model).
        """
        if self.firmware == "klipper":
            return self.square_corner_velocity_mm_s ** 2 * (math.sqrt(2.0) - 1.0) / self.max_accel_mm_s2
        if self.firmware == "marlin":
            return self.junction_deviation_mm
        return None

    @property
    def travel_speed(self) -> float:
        """Default travel speed (mm/s): ``travel_speed_mm_s`` or the max velocity."""
        return float(self.travel_speed_mm_s or self.max_velocity_mm_s)

    def in_bed(self, x_mm, y_mm, tol_mm: float = 1e-6):
        """True where (x, y) lies on the bed (works on arrays)."""
        import numpy as np
        x = np.asarray(x_mm, dtype=float)
        y = np.asarray(y_mm, dtype=float)
        return ((x >= self.bed_x_mm[0] - tol_mm) & (x <= self.bed_x_mm[1] + tol_mm)
                & (y >= self.bed_y_mm[0] - tol_mm) & (y <= self.bed_y_mm[1] + tol_mm))

    def to_dict(self) -> dict:
        """Plain dict (JSON/TOML-able) for the manifest; ``profile_from_dict`` inverts it."""
        d = asdict(self)
        d["bed_x_mm"] = list(self.bed_x_mm)
        d["bed_y_mm"] = list(self.bed_y_mm)
        extra = d.pop("extra")
        d = {k: v for k, v in d.items() if v is not None}
        d.update(extra)
        return d


def load_profile(path_or_name) -> PrinterProfile:
    """Read and validate a profile: a path to a ``.toml`` file or a shipped name ("adventurer3")."""
    if isinstance(path_or_name, PrinterProfile):
        return path_or_name
    s = str(path_or_name)
    path = Path(s)
    if not path.exists() and not s.endswith(".toml") and "/" not in s and "\\" not in s:
        path = data_dir() / "printers" / f"{s}.toml"
        if not path.exists():
            raise UserError(f"unknown printer {s!r}: give a profile .toml path or one of "
                            f"{', '.join(shipped_profiles())}")
    if not path.exists():
        raise UserError(f"printer profile {s} does not exist")
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"printer profile {path} is not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read printer profile {path}: {exc}") from None
    doc.setdefault("name", path.stem)
    return profile_from_dict(doc, source=str(path))


def shipped_profiles() -> list[str]:
    """Names of the profiles in ``data/printers``."""
    return sorted(p.stem for p in (data_dir() / "printers").glob("*.toml"))


def profile_from_dict(doc: dict, source: str = "profile") -> PrinterProfile:
    """Validate a dict (from TOML or a manifest) and build the profile.

    Raises UserError naming the first problem: a missing key, a key or value with the
    wrong unit, or an impossible value.
    """
    if not isinstance(doc, dict):
        raise UserError(f"{source}: a printer profile must be a TOML table of keys")
    known = {f.name for f in fields(PrinterProfile)} - {"extra"}
    for key in doc:
        if key not in known and _FOREIGN_UNIT.search(key):
            base = _FOREIGN_UNIT.sub("", key)
            raise UserError(f"{source}: key {key!r} has the wrong unit; use SI-mm keys "
                            f"(e.g. {base}_mm, {base}_mm_s), see data/printers/adventurer3.toml")
    missing = [k for k in REQUIRED_KEYS if k not in doc]
    if missing:
        raise UserError(f"{source}: missing key {missing[0]!r}"
                        + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    fw = str(doc["firmware"]).strip().lower()
    if fw not in FIRMWARES:
        raise UserError(f"{source}: unknown firmware {doc['firmware']!r}; use one of {', '.join(FIRMWARES)}")
    ck = CORNER_KEY[fw]
    if fw == "marlin" and doc.get(ck) is None and doc.get("max_jerk_mm_s") is not None:
        ck = "max_jerk_mm_s"            # Marlin built with CLASSIC_JERK (M205 X Y)
    if doc.get(ck) is None:
        raise UserError(f"{source}: missing key {ck!r} (required for firmware {fw})")

    vals: dict = {"name": str(doc["name"]), "firmware": fw}
    for key in ("bed_x_mm", "bed_y_mm"):
        v = doc[key]
        if not isinstance(v, (list, tuple)) or len(v) != 2:
            raise UserError(f"{source}: {key} must be [min, max] in mm, got {v!r}")
        lo, hi = (_number(source, key, x) for x in v)
        if lo >= hi:
            raise UserError(f"{source}: {key} min {lo} must be below max {hi}")
        vals[key] = (lo, hi)
    float_keys = [f.name for f in fields(PrinterProfile)
                  if f.name.endswith(_UNIT_SUFFIXES) and f.name not in ("bed_x_mm", "bed_y_mm")]
    for key in float_keys:
        if key in doc and doc[key] is not None:
            vals[key] = _number(source, key, doc[key])
    positive = ("max_z_mm", "nozzle_diameter_mm", "nozzle_land_length_mm", "filament_diameter_mm",
                "max_velocity_mm_s", "max_accel_mm_s2", "max_e_velocity_mm_s", "max_e_accel_mm_s2",
                "retract_speed_mm_s", "max_z_velocity_mm_s", "max_z_accel_mm_s2", "instantaneous_corner_velocity_mm_s",
                "max_e_jerk_mm_s", "max_extrude_cross_section_mm2", "max_extrude_only_distance_mm", ck)
    for key in positive:
        if key in vals and not vals[key] > 0:
            raise UserError(f"{source}: {key} must be > 0, got {vals[key]}")
    for key in ("bowden_length_mm", "retract_length_mm", "nozzle_temp_c", "bed_temp_c"):
        if vals[key] < 0:
            raise UserError(f"{source}: {key} must be >= 0, got {vals[key]}")
    if vals["nozzle_diameter_mm"] >= vals["filament_diameter_mm"]:
        raise UserError(f"{source}: nozzle_diameter_mm {vals['nozzle_diameter_mm']} must be smaller "
                        f"than filament_diameter_mm {vals['filament_diameter_mm']}")
    if vals["nozzle_temp_c"] > 500:
        raise UserError(f"{source}: nozzle_temp_c {vals['nozzle_temp_c']} is impossible (> 500 C)")
    for key in ("start_gcode", "end_gcode", "description"):
        if key in doc:
            if not isinstance(doc[key], str):
                raise UserError(f"{source}: {key} must be a string")
            vals[key] = doc[key]
    for key in ("supports_relative_e", "firmware_pressure_advance", "junction_deviation_with_e"):
        if key in doc:
            if not isinstance(doc[key], bool):
                raise UserError(f"{source}: {key} must be true or false")
            vals[key] = doc[key]
    extra = {k: v for k, v in doc.items() if k not in known}
    prof = PrinterProfile(**vals, extra=extra)
    for key in ("start_gcode", "end_gcode"):
        try:
            format_gcode_template(getattr(prof, key), prof)
        except UserError as exc:
            raise UserError(f"{source}: {key}: {exc}") from None
    return prof


def format_gcode_template(template: str, profile: PrinterProfile, **extra) -> str:
    """Fill ``{nozzle_temp_c}``-style placeholders from the profile (and ``extra``)."""
    values = profile.to_dict() if not isinstance(profile, dict) else dict(profile)
    values.update(extra)
    for k in ("nozzle_temp_c", "bed_temp_c"):
        if k in values and float(values[k]).is_integer():
            values[k] = int(values[k])
    try:
        return template.format_map(values)
    except KeyError as exc:
        raise UserError(f"unknown placeholder {{{exc.args[0]}}}; use profile keys like "
                        "{nozzle_temp_c}") from None
    except (ValueError, IndexError) as exc:
        raise UserError(f"bad placeholder syntax ({exc}); write literal braces as {{{{ }}}}") from None


def _number(source: str, key: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        if isinstance(v, str):
            raise UserError(f"{source}: {key} must be a plain number in the key's unit "
                            f"({_unit_of(key)}), got the string {v!r}")
        raise UserError(f"{source}: {key} must be a number ({_unit_of(key)}), got {v!r}")
    if not math.isfinite(v):
        raise UserError(f"{source}: {key} must be finite, got {v}")
    return float(v)


def _unit_of(key: str) -> str:
    for suf, unit in (("_mm_s2", "mm/s^2"), ("_mm_s", "mm/s"), ("_mm", "mm"), ("_c", "deg C"), ("_s", "s")):
        if key.endswith(suf):
            return unit
    return "see the key name"
