"""`calib export fit.json --to klipper|marlin|rrf|orca|kisslicer [--profile FILE]`.

Without --profile: print the snippet. With --profile: update the file in place, after a
timestamped backup (calib.fileio.backup), with an atomic write:
  klipper  printer.cfg: ``pressure_advance:`` in the [extruder] section (added if missing)
  orca     filament JSON: "pressure_advance": ["K"] (string array) and
           "enable_pressure_advance": ["1"]
  marlin/rrf  a G-code/config file: the M900 / M572 line replaced or appended
  kisslicer   .ini: ``viscoelasticity_us=`` (KISSlicer VE, seed 000)
"""
from __future__ import annotations

import json
import re
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
    return p


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
        return f"viscoelasticity_us={ve_value(doc):.3f}"
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
        line, pat = snippet(doc, target), r"^\s*viscoelasticity_us\s*=.*$"
    elif target == "marlin":
        line, pat = snippet(doc, target), r"^\s*M900\b.*$"
    else:
        line, pat = snippet(doc, target), r"^\s*M572\b.*$"
    new, n = re.subn(pat, line, text, flags=re.MULTILINE)
    return new if n else text.rstrip("\n") + "\n" + line + "\n"


def run(args) -> int:
    from fit.result import load_fit_json

    doc = load_fit_json(args.fit)
    if not doc.get("converged", False):
        print("calib export: warning: this fit did not converge; the value may be unreliable")
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
