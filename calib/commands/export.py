"""`calib export fit.json --to klipper|marlin|rrf|orca|kisslicer [--profile FILE]`.

A fit that fit/trust.py calls not trustworthy (misfit, a value on a prior bound, rival
modes, not converged) is refused with one line and exit 2 unless ``--force``; warnings go
to stderr, never into the snippet. Without --profile: print the snippet. With --profile: update the file in place, after a
timestamped backup (calib.fileio.backup), with an atomic write:
  klipper  printer.cfg: ``pressure_advance:`` in the [extruder] section (added if missing)
  orca     filament JSON: "pressure_advance": ["K"] (string array) and
           "enable_pressure_advance": ["1"]
  marlin/rrf  a G-code/config file: the M900 / M572 line replaced or appended
  kisslicer   material .ini: ``matl_viscosity_over_elasticity_us=`` (KISSlicer 2's VE key,
              seed 000; a ``viscoelasticity_us=`` line from older calib versions is replaced)
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np

from calib.errors import UserError
from calib.fileio import atomic_write_text, backup

TARGETS = ("klipper", "marlin", "rrf", "orca", "kisslicer")


def add_parser(sub):
    p = sub.add_parser(
        "export", help="print or write the fitted pressure advance for a firmware or slicer",
        description="Turn fit.json into the firmware/slicer setting: Klipper pressure_advance, "
                    "Marlin M900 K, RRF M572 S, OrcaSlicer filament pressure_advance, KISSlicer "
                    "VE. With --profile the file is updated in place after a timestamped backup.")
    p.add_argument("fit", help="fit.json from `calib fit`")
    p.add_argument("--to", required=True, choices=TARGETS, help="target firmware or slicer")
    p.add_argument("--profile", help="file to update in place (printer.cfg, filament .json, ...)")
    p.add_argument("--force", action="store_true",
                   help="export a fit that is not trustworthy (misfit, value on a prior bound, "
                        "rival modes, not converged); the reasons still go to stderr")
    return p


FIRMWARE_TARGETS = ("klipper", "marlin", "rrf")
KISS_VE_KEY = "matl_viscosity_over_elasticity_us"


def kisslicer_geometry_note(doc) -> str:
    """VE = tau d^4 / (32 D^2 L l) (seed 000) holds only for the geometry it was computed
    with; KISSlicer computes tau back from its own printer keys, so they must match."""
    p = doc.get("profile") or {}
    return (f"VE was computed for Bowden L = {p.get('bowden_length_mm')} mm, nozzle land "
            f"l = {p.get('nozzle_land_length_mm')} mm, nozzle d = {p.get('nozzle_diameter_mm')} mm, "
            f"filament D = {p.get('filament_diameter_mm')} mm; set KISSlicer's drive_len_1, "
            f"nozzle_len_1 and nozzle_dia_1 to the same values or the delay it applies is wrong")


def check_trust(doc, force: bool) -> None:
    """Refuse (UserError, exit 2) a fit that fit.trust calls not trustworthy, unless forced.

    The verdict is recomputed from the fit itself, so fit.json files written before the
    verdict existed are judged too; the chi-square threshold the fit was run with is kept."""
    from fit.trust import CHI2_NU_MAX, assess

    chi2_max = (doc.get("trust") or {}).get("checks", {}).get("chi2_nu_max", CHI2_NU_MAX)
    v = assess(doc, chi2_max=chi2_max)
    if v.trustworthy:
        return
    why = v.problems[0] + (f" (and {len(v.problems) - 1} more problem(s))" if len(v.problems) > 1 else "")
    if not force:
        raise UserError(f"not exporting: this fit is not trustworthy: {why}; {v.advice} "
                        "(--force exports it anyway)")
    for line in v.lines():
        print(f"calib export: {line}", file=sys.stderr)


def firmware_warning(doc, target: str) -> str | None:
    """One line when the printer profile says its firmware ignores the PA command."""
    prof = doc.get("profile") or {}
    if target in FIRMWARE_TARGETS and prof.get("firmware_pressure_advance", True) is False:
        return (f"the printer profile '{prof.get('name', '?')}' says its firmware ignores the "
                f"pressure-advance command, so this line will change nothing on that printer; the "
                f"slicer-side route is KISSlicer VE (`calib export FIT --to kisslicer`), which the "
                f"slicer applies in the G-code itself")
    return None


def pa_value(doc) -> float:
    d = doc.get("derived", {})
    if "pressure_advance_s" in d:
        return float(d["pressure_advance_s"]["median"])
    for name, p in doc.get("params", {}).items():
        if name.split("@")[0] == "pa.tau_s":
            return float(p["median"])
    raise UserError("this fit has no pressure advance (pa.tau_s); fit a model with 'pa'")


def ve_value(doc) -> float:
    d = doc.get("derived", {}).get("kisslicer_ve_us")
    if not d:
        raise UserError("this fit has no KISSlicer VE (needs pa and a Bowden length > 0 in the profile)")
    return float(d["median"])


def snippet(doc, target: str) -> str:
    if target == "kisslicer":
        return f"{KISS_VE_KEY}={ve_value(doc):.3f}"
    k = f"{pa_value(doc):.4f}"
    return {"klipper": f"[extruder]\npressure_advance: {k}",
            "marlin": f"M900 K{k}",
            "rrf": f"M572 D0 S{k}",
            "orca": json.dumps({"enable_pressure_advance": ["1"], "pressure_advance": [k]})}[target]


def update_text(text: str, doc, target: str) -> str:
    """The profile text with the setting replaced (or added)."""
    if target == "orca":
        try:
            prof = json.loads(text)
        except json.JSONDecodeError as exc:
            raise UserError(f"the Orca filament profile is not valid JSON: {exc}") from None
        if not isinstance(prof, dict):
            raise UserError("the Orca filament profile must be a JSON object")
        prof["pressure_advance"] = [f"{pa_value(doc):.4f}"]
        prof["enable_pressure_advance"] = ["1"]
        return json.dumps(prof, indent=4) + "\n"
    if target == "klipper":
        k = f"{pa_value(doc):.4f}"
        lines = text.splitlines()
        sec = next((i for i, l in enumerate(lines) if l.strip().lower() == "[extruder]"), None)
        if sec is None:
            return text.rstrip("\n") + f"\n\n[extruder]\npressure_advance: {k}\n"
        end = next((i for i in range(sec + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines))
        for i in range(sec + 1, end):
            if re.match(r"\s*pressure_advance\s*[:=]", lines[i]):
                lines[i] = f"pressure_advance: {k}"
                break
        else:
            lines.insert(sec + 1, f"pressure_advance: {k}")
        return "\n".join(lines) + "\n"
    if target == "kisslicer":
        line, pat = snippet(doc, target), rf"^\s*(?:{KISS_VE_KEY}|viscoelasticity_us)\s*=.*$"
    elif target == "marlin":
        line, pat = snippet(doc, target), r"^\s*M900\b.*$"
    else:
        line, pat = snippet(doc, target), r"^\s*M572\b.*$"
    new, n = re.subn(pat, line, text, flags=re.MULTILINE)
    return new if n else text.rstrip("\n") + "\n" + line + "\n"


def run(args) -> int:
    from fit.result import load_fit_json

    doc = load_fit_json(args.fit)
    check_trust(doc, args.force)
    warn = firmware_warning(doc, args.to)
    if warn:
        print(f"calib export: warning: {warn}", file=sys.stderr)
    if args.to == "kisslicer":
        print(f"calib export: note: {kisslicer_geometry_note(doc)}", file=sys.stderr)
    if not args.profile:
        print(snippet(doc, args.to))
        return 0
    path = Path(args.profile)
    if not path.exists():
        raise UserError(f"profile {path} does not exist")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read profile {path}: {exc}") from None
    new = update_text(text, doc, args.to)
    bak = backup(path)
    atomic_write_text(path, new)
    print(f"updated {path} (backup {bak})")
    return 0
