"""`calib export fit.json --to klipper|marlin|rrf|orca|kisslicer|spoolman [--profile FILE]`.

A fit that fit/trust.py calls not trustworthy (misfit, a value on a prior bound, rival
modes, not converged) is refused with one line and exit 2 unless ``--force``; warnings go
to stderr, never into the snippet. Without --profile: print the snippet. With --profile:
update the file in place (calib.fileio.replace_user_file: timestamped backup, symlinks
followed, mode/owner/line endings kept, fsync, no write when nothing changes); a file of
another kind than the target edits is refused with one line:
  klipper  printer.cfg: the ``pressure_advance:`` Klipper actually reads (last one, in
           includes too), else added under the last [extruder] header; never in the
           SAVE_CONFIG block (calib/klipper_cfg.py); --section for extruder1, ...
  orca     filament JSON: "pressure_advance": ["K"] (string array) and
           "enable_pressure_advance": ["1"]
  marlin/rrf  a G-code/config file: the M900 / M572 line replaced or appended
  klipper-gcode  start G-code: SET_PRESSURE_ADVANCE [EXTRUDER=] ADVANCE= SMOOTH_TIME=
  prusa    PrusaSlicer/SuperSlicer filament ini: M572 S inside start_filament_gcode
  kisslicer   material .ini: ``matl_viscosity_over_elasticity_us=`` (KISSlicer 2's VE key,
              seed 000; a ``viscoelasticity_us=`` line from older calib versions is replaced)
  spoolman    no file: stdout is the JSON body of Spoolman's PATCH /api/v1/spool/{id} with the
              spool extra field (--field-key, default pressure_advance) set to the Klipper PA as
              a JSON-encoded float string; stderr: the once-only field definition and curl lines
              (calib/spoolman.py); --profile is refused

Width-optimal value (fit/firmware_match.py): for the pressure-advance targets the fitted
dynamics are simulated on a reference print (the standard move mix, or ``--on
FILE.gcode``) with the firmware's own compensation, per posterior draw; when the dynamics
are more than linear PA (shear thinning, back-pressure, offset, thermal ooze) the linear K
exported is the one that minimises the predicted width error (Klipper targets: with the
smooth time), with its 95 % interval; a plain pa fit keeps tau, the exact answer. A table
of the predicted width error at starts/stops/corners (no PA, linear, Kalico, adaptive
table) and a warning when the reference print's flows go beyond the tested ones go to
stderr.
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np

from calib.argtypes import integer
from calib.errors import UserError

TARGETS = ("klipper", "klipper-gcode", "kalico-tanh", "kalico-recipr", "marlin", "rrf", "orca",
           "orca-adaptive", "prusa", "kisslicer", "spoolman")


def add_parser(sub):
    p = sub.add_parser(
        "export", help="print or write the fitted pressure advance for a firmware or slicer",
        description="Turn fit.json into the firmware/slicer setting: Klipper pressure_advance, "
                    "Marlin M900 K, RRF M572 S, OrcaSlicer filament pressure_advance, KISSlicer "
                    "VE, a Spoolman spool extra field. With --profile the file is updated in place "
                    "after a timestamped backup.")
    p.add_argument("fit", help="fit.json from `calib fit`")
    p.add_argument("--to", required=True, choices=TARGETS, help="target firmware or slicer")
    p.add_argument("--profile", help="file to update in place (printer.cfg, filament .json, ...)")
    p.add_argument("--section", default="extruder",
                   help="Klipper: the extruder section to set (extruder1, ... for a tool changer, "
                        "'extruder_stepper NAME' for an extra stepper; default extruder)")
    p.add_argument("--tool", type=integer(0), default=0, metavar="N",
                   help="Marlin/RRF: the extruder (M900 T<N>) or drive (M572 D<N>) to set; other "
                        "tools' lines are left alone (default 0)")
    p.add_argument("--on", metavar="FILE.gcode",
                   help="choose the PA that minimises the predicted width error of this G-code "
                        "(a sliced print; its first 90 s of printing) instead of the standard move "
                        "mix (4 L-shaped lines with starts, stops and corners at 25-150 mm/s)")
    p.add_argument("--spool-id", type=int, metavar="N",
                   help="Spoolman: the spool's id, used in the curl example on stderr")
    p.add_argument("--field-key", default="pressure_advance", metavar="KEY",
                   help="Spoolman: the spool extra field's key (a-z, 0-9, _; default "
                        "pressure_advance)")
    p.add_argument("--force", action="store_true",
                   help="export a fit that is not trustworthy (misfit, value on a prior bound, "
                        "rival modes, not converged); the reasons still go to stderr")
    return p


FIRMWARE_TARGETS = ("klipper", "klipper-gcode", "kalico-tanh", "kalico-recipr", "marlin", "rrf",
                    "prusa")
#: Klipper's default pressure_advance_smooth_time (s), kept when no width match ran
KLIPPER_SMOOTH_TIME_S = 0.040
#: targets whose firmware value comes from (or is compared in) the width match
MATCH_TARGETS = ("klipper", "klipper-gcode", "kalico-tanh", "kalico-recipr", "marlin", "rrf",
                 "prusa", "orca", "orca-adaptive", "spoolman")
#: posterior draws simulated per export (each one optimised: ~0.01-0.3 s a draw); 32 gave
#: 95 % intervals of the optimal K that missed the truth's in 2 of 3 bench seeds by a hair
MATCH_DRAWS = 64
KISS_VE_KEY = "matl_viscosity_over_elasticity_us"
#: What the K interval holds and what it does not: measured by bench_export_foreign, the
#: foreign printer's best K lay outside every trusted 95 % interval (3-7 % below), and the
#: K exported lost at most 2.0 % of what linear advance gains there (docs/TRUST.md)
FORM_NOTE = ("the interval is this model's doubt, not the doubt of its form: on an independent "
             "printer's physics the best K lay 3-7 % from trusted intervals, and the K exported lost "
             "<= 2 % of what advance gains there (docs/TRUST.md, \"The number pasted\")")


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


def kalico_values(doc, target: str) -> dict:
    """Kalico's [extruder] options for its nonlinear PA (bleeding-edge-v2 branch,
    klippy/kinematics/extruder.py: pressure_advance_model tanh|recipr, linear_advance s,
    nonlinear_offset mm, linearization_velocity mm/s > 0), from the fit's Kalico match."""
    kind = target.split("-", 1)[1]
    d = doc.get("derived", {}).get(f"kalico_{kind}")
    if not d:
        raise UserError("this fit has no Kalico match: it needs a nonlinear advance term; fit "
                        "pa+nonlinear (or --model auto) for Kalico's nonlinear pressure advance")
    return {"pressure_advance_model": kind,
            "linear_advance": f"{d['pressure_advance_s']['median']:.4f}",
            "nonlinear_offset": f"{d['offset_mm']['median']:.4f}",
            "linearization_velocity": f"{max(d['linearization_velocity_mm_s']['median'], 1e-4):.4f}"}


#: accelerations (mm/s^2) of the adaptive table's rows; the physics has no acceleration
#: term, so every row of one flow carries the same PA (said on stderr)
ORCA_ACCELS = (1000, 5000, 10000)


def orca_adaptive_table(doc) -> tuple[str, str]:
    """Orca's adaptive_pressure_advance_model text ("PA,flow_mm3_s,accel_mm_s2" lines) from
    the fit's K(v) = Preq(v)/v curve (fit.derived.pa_vs_flow), and a note on its range."""
    d = doc.get("derived", {}).get("pa_vs_flow")
    if not d:
        raise UserError("this fit has no flow-dependent PA: it needs a nonlinear advance term; "
                        "fit pa+nonlinear (or --model auto); a linear fit is one value: --to orca")
    rows = [f"{k:.4f},{q:.2f},{a}" for k, q in zip(d["pa_s_median"], d["flow_mm3_s"])
            for a in ORCA_ACCELS]
    note = (f"the table covers flows {d['flow_mm3_s'][0]:.2f}-{d['flow_mm3_s'][-1]:.2f} mm^3/s, the "
            f"range the test print had; Orca extrapolates outside it, so print a faster test before "
            f"trusting faster prints. The fit has no acceleration term: the PA is the same at "
            f"{', '.join(map(str, ORCA_ACCELS))} mm/s^2")
    return "\n".join(rows), note


def smooth_time_s(doc) -> float:
    """The Klipper smooth time to print: the width match's (``derived.klipper_smooth_time_s``,
    set by :func:`with_match`) or Klipper's default."""
    return float((doc.get("derived") or {}).get("klipper_smooth_time_s", KLIPPER_SMOOTH_TIME_S))


def match_smoothing(doc, target: str) -> tuple[float, bool, float]:
    """(smooth time of the linear search s, smooth time free?, smooth time of the Orca
    table's firmware s) for ``target``: Klipper/Kalico targets search the smooth time too
    (SET_PRESSURE_ADVANCE SMOOTH_TIME= / pressure_advance_smooth_time); Marlin LA, RRF and
    Prusa firmware do not smooth (0); a slicer target (orca) runs on the profile's firmware,
    whose smooth time it cannot set (Klipper: its default)."""
    fw = str((doc.get("profile") or {}).get("firmware", "")).lower()
    fw_st = KLIPPER_SMOOTH_TIME_S if fw == "klipper" else 0.0
    if target in ("klipper", "klipper-gcode", "kalico-tanh", "kalico-recipr"):
        return KLIPPER_SMOOTH_TIME_S, True, fw_st
    if target in ("orca", "orca-adaptive"):
        return fw_st, False, fw_st
    return 0.0, False, fw_st


def width_match(doc, target: str, on: str | None = None, n_draws: int = MATCH_DRAWS,
                force: bool = False):
    """The width match (fit.firmware_match.match_firmware) of ``target`` on the standard
    move mix or the G-code file ``on``; None (with a note on stderr) when the fit cannot
    be simulated and no ``--on`` was asked for; UserError for a bad ``--on`` file, and
    (unless ``force``) for dynamics more than linear PA whose move mix cannot be planned:
    tau is then only the linear part of the advance (a probe print's partial printer dict
    made `calib export` write tau 0.047 s where the printer's best K was 0.201 s)."""
    from calib.progress import progress
    from fit import firmware_match as fm
    from patterns.profile import profile_from_dict

    phys = None
    try:
        phys = fm.physics_from_fit(doc, n_draws=n_draws)
        prof = profile_from_dict(dict(doc.get("profile") or {}), source="fit.json profile")
    except UserError as exc:
        if on:
            raise UserError(f"--on {on}: cannot simulate this fit: {exc}") from None
        if phys is not None and not phys.linear and not force:
            raise UserError(f"not exporting: the fitted dynamics ({phys.spec}) are more than linear "
                            f"PA and the width match cannot plan the move mix ({exc}), so tau is only "
                            "the linear part of the advance; fit a manifest from `calib pattern` or "
                            "`calib plan` with a whole printer profile (--force exports tau anyway)")
        print(f"calib export: note: no width-error check ({exc}); the value is tau", file=sys.stderr)
        return None
    if on:
        path = Path(on)
        try:
            text = path.read_text(encoding="utf-8", errors="strict")
        except FileNotFoundError:
            raise UserError(f"--on {on}: no such file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"--on {on}: cannot read it as G-code text: {exc}") from None
        man = fm.reference_from_gcode(text, prof, name=on)
        ref = fm.prepare_reference(man, path.name)
    else:
        ref = fm.prepare_reference(fm.standard_reference(prof), fm.STANDARD_MIX)
    st, free, table_st = match_smoothing(doc, target)
    bar = progress(total=0 if phys.linear else len(phys.theta) + fm.envelope_draw_count(doc),
                   desc="width match", unit="draw",
                   disable=phys.linear)
    try:
        return fm.match_firmware(doc, ref, smooth_time_s=st, smooth_free=free,
                                 kalico_smooth_time_s=KLIPPER_SMOOTH_TIME_S,
                                 table_smooth_time_s=table_st, physics=phys,
                                 on_draw=lambda: bar.update(1))
    finally:
        bar.close()


def with_match(doc, m) -> dict:
    """A copy of ``doc`` whose exported PA (and Klipper smooth time) are the width match's."""
    if m is None or not m.optimised:
        return doc
    out = dict(doc)
    d = dict(out.get("derived") or {})
    d["pressure_advance_s"] = {**dict(d.get("pressure_advance_s") or {}), **m.k_s}
    if m.smooth_free:
        d["klipper_smooth_time_s"] = float(m.smooth_time_s["median"])
    out["derived"] = d
    return out


def report_match(m, target: str) -> None:
    """The width match on stderr: the value with its interval, the table, the warnings."""
    from fit.firmware_match import SMOOTH_MIN_S

    say = lambda t: print(f"calib export: {t}", file=sys.stderr)      # noqa: E731
    k, st = m.k_s, m.smooth_time_s
    env = f" (and {m.n_envelope_draws} of the fit's envelopes)" if m.n_envelope_draws else ""
    say(f"width check on {m.reference}, {m.n_draws} posterior draws{env}:")
    if m.optimised:
        line = (f"  linear PA that minimises the predicted width error: {k['median']:.4f} s "
                f"(95 % {k['ci95'][0]:.4f}-{k['ci95'][1]:.4f})")
        if m.smooth_free:
            line += (f", smooth time {st['median']:.3f} s (95 % {st['ci95'][0]:.3f}-"
                     f"{st['ci95'][1]:.3f})")
        say(line)
    else:
        say(f"  the fitted physics is linear PA: the exported value is tau = {k['median']:.4f} s "
            f"(95 % {k['ci95'][0]:.4f}-{k['ci95'][1]:.4f}), which cancels it exactly")
    say(f"  {FORM_NOTE}")
    r = m.rms_opt_um
    say(f"  predicted residual width error with it: {r['median']:.1f} um RMS "
        f"(95 % {r['ci95'][0]:.1f}-{r['ci95'][1]:.1f})")
    for ln in m.table_lines():
        say("  " + ln)
    if m.smooth_free and st["median"] <= 1.05 * SMOOTH_MIN_S:
        say(f"note: the shortest smooth time searched ({SMOOTH_MIN_S:.3f} s, half Klipper's default) "
            "is best for the widths; the model has no extruder motor, so it never sees what a "
            "shorter window costs (jerk, skipped steps)")
    for n in m.notes:
        say(f"note: {n}")
    w = m.extrapolation_warning()
    if w:
        say(("warning: " if m.flow_tested_mm3_s is not None else "note: ") + w)


#: the config sections that hold a pressure advance (klippy/kinematics/extruder.py)
KLIPPER_SECTION = re.compile(r"extruder\d*|extruder_stepper\s+\S+")


def klipper_name(section: str) -> str:
    """What SET_PRESSURE_ADVANCE's EXTRUDER= names for a config section: its last word
    (Klipper's ExtruderStepper: ``config.get_name().split()[-1]``), so [extruder_stepper
    belt] is EXTRUDER=belt and [extruder1] is EXTRUDER=extruder1."""
    return section.split()[-1]


#: the targets that set one extruder among several by --tool (the others: by --section, or none)
TOOL_TARGETS = ("marlin", "rrf", "orca", "orca-adaptive", "prusa")


def check_targeting(target: str, tool: int, section: str) -> None:
    """A UserError where ``--tool`` or ``--section`` names an extruder the target does not
    choose that way: ignored, the value would go to extruder 0 (a fuzzed ``--tool 99 --to
    klipper`` printed [extruder])."""
    klipper = target.startswith(("klipper", "kalico"))
    if tool != 0 and target not in TOOL_TARGETS:
        how = (f"Klipper chooses the extruder by section: --section extruder{tool}" if klipper else
               f"--to {target} sets one value for the filament or spool; drop --tool")
        raise UserError(f"--tool {tool}: --tool chooses the extruder for {', '.join(TOOL_TARGETS)}; {how}")
    if section != "extruder" and not klipper:
        how = (f"choose the extruder with --tool N" if target in TOOL_TARGETS else "drop --section")
        raise UserError(f"--section {section!r}: --section names a Klipper config section; for --to {target} {how}")


def snippet(doc, target: str, section: str = "extruder", tool: int = 0) -> str:
    if target == "orca-adaptive":
        return orca_adaptive_table(doc)[0]
    if target.startswith("kalico-"):
        v = kalico_values(doc, target)
        return (f"[{section}]\n" + "\n".join(f"{k}: {x}" for k, x in v.items())
                + f"\n# at run time: SET_PRESSURE_ADVANCE ADVANCE={v['linear_advance']} "
                  f"OFFSET={v['nonlinear_offset']} VELOCITY={v['linearization_velocity']}")
    if target == "kisslicer":
        return f"{KISS_VE_KEY}={ve_value(doc):.3f}"
    k = f"{pa_value(doc):.4f}"
    extruder = "" if section == "extruder" else f" EXTRUDER={klipper_name(section)}"
    st = (f"\npressure_advance_smooth_time: {smooth_time_s(doc):.3f}"
          if "klipper_smooth_time_s" in (doc.get("derived") or {}) else "")
    return {"klipper": f"[{section}]\npressure_advance: {k}{st}",
            "klipper-gcode": f"SET_PRESSURE_ADVANCE{extruder} ADVANCE={k} "
                             f"SMOOTH_TIME={smooth_time_s(doc):.3f}",
            "prusa": f"M572 S{k}",
            "marlin": tool_line("marlin", k, tool),
            "rrf": tool_line("rrf", k, tool),
            "orca": json.dumps({"enable_pressure_advance": ["1"], "pressure_advance": [k]})}[target]


def profile_kind(text: str) -> str:
    """What a profile file is: 'json', 'klipper' (has [section] headers or a SAVE_CONFIG
    block), 'ini' (key = value lines) or 'gcode'."""
    body = text.lstrip("\ufeff \t\r\n")
    if body.startswith("{"):
        return "json"
    lines = [ln.strip() for ln in text.splitlines()]
    if any(re.match(r"\[[^\]]+\]", ln) for ln in lines) or "#*# <---" in text:
        return "klipper"
    if any(re.match(r"^[GMT]\d+\b", ln, re.IGNORECASE) for ln in lines):
        return "gcode"
    if any(re.match(r"^[A-Za-z_][A-Za-z0-9_]*\s*=", ln) for ln in lines):
        return "ini"
    # Klipper's "option: value" without a readable header ("[extruder" cut short): not a
    # start G-code to append an M900 to
    if any(re.match(r"^[A-Za-z_][A-Za-z0-9_]*\s*:", ln) for ln in lines):
        return "klipper"
    return "gcode"


#: the file kinds each target may edit, and what to use instead
ACCEPTS = {"orca-adaptive": ("json",), "klipper": ("klipper",), "kalico-tanh": ("klipper",), "kalico-recipr": ("klipper",), "orca": ("json",), "kisslicer": ("ini",), "prusa": ("ini",),
           "marlin": ("gcode",), "rrf": ("gcode",), "klipper-gcode": ("gcode",)}
USE_INSTEAD = {"json": "--to orca", "klipper": "--to klipper", "ini": "--to prusa or --to kisslicer",
               "gcode": "--to marlin, rrf or klipper-gcode"}


def check_kind(path, text: str, target: str) -> None:
    kind = profile_kind(text)
    if kind not in ACCEPTS[target]:
        raise UserError(f"{path} looks like a {kind} file, which --to {target} does not edit "
                        f"(use {USE_INSTEAD[kind]}); nothing was changed")


def update_text(text: str, doc, target: str, tool: int = 0, section: str = "extruder") -> str:
    """The profile text with the setting replaced (or added); not for Klipper configs
    (:func:`calib.klipper_cfg.set_option` follows includes and SAVE_CONFIG)."""
    if target == "orca":
        return update_orca(text, pa_value(doc), tool)
    if target == "orca-adaptive":
        return update_orca(text, pa_value(doc), tool, adaptive_model=orca_adaptive_table(doc)[0])
    if target == "prusa":
        return update_prusa(text, f"{pa_value(doc):.4f}", tool)
    if target == "klipper-gcode":
        st = (f"{smooth_time_s(doc):.3f}" if "klipper_smooth_time_s" in (doc.get("derived") or {})
              else None)
        return update_klipper_macro(text, snippet(doc, target, section), f"{pa_value(doc):.4f}",
                                    section, smooth=st)
    if target == "kisslicer":
        line, pat = snippet(doc, target), rf"^\s*(?:{KISS_VE_KEY}|viscoelasticity_us)\s*=.*$"
        new, n = re.subn(pat, line, text, flags=re.MULTILINE)
        return new if n else text.rstrip("\n") + "\n" + line + "\n"
    return set_pa_gcode(text, target, f"{pa_value(doc):.4f}", tool)


ORCA_PA_MAX = 2.0      # PrintConfig.cpp: pressure_advance, coFloats, max 2


def update_orca(text: str, k: float, tool: int = 0, adaptive_model: str | None = None) -> str:
    """An OrcaSlicer filament preset (JSON, string arrays, one entry per extruder) with
    pressure_advance[tool] = k and enable_pressure_advance[tool] = 1. Adaptive PA, which
    makes Orca ignore pressure_advance, is switched off for that extruder (said on stderr).
    Refused: not JSON, not a filament preset, a system preset (replaced on update)."""
    try:
        prof = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UserError(f"the Orca filament preset is not valid JSON: {exc}") from None
    if not isinstance(prof, dict):
        raise UserError("the Orca filament preset must be a JSON object")
    kind = prof.get("type")
    if kind not in (None, "filament") or (kind is None and "pressure_advance" not in prof
                                          and not any(key.startswith("filament_") for key in prof)):
        raise UserError(f"this is not an Orca filament preset (type {kind!r}); pressure advance "
                        "lives in the filament preset")
    if str(prof.get("from", "")).lower() == "system":
        raise UserError("this is an Orca system preset (from: system), replaced on every update; "
                        "save it as a user preset in Orca and export into that")
    if not 0 <= k <= ORCA_PA_MAX:
        raise UserError(f"pressure advance {k:.4f} s is outside what Orca accepts (0-{ORCA_PA_MAX:g})")

    def put(key, value):
        cur = prof.get(key)
        arr = [str(x) for x in cur] if isinstance(cur, list) else ([str(cur)] if cur is not None else [])
        n = max(len(arr), len(prof.get("pressure_advance") or []) or 1, tool + 1)
        fill = arr[-1] if arr else value
        arr += [fill] * (n - len(arr))
        arr[tool] = value
        prof[key] = arr

    n_ext = len(prof["pressure_advance"]) if isinstance(prof.get("pressure_advance"), list) else 1
    if tool >= n_ext and "pressure_advance" in prof:
        raise UserError(f"the preset holds pressure advance for {n_ext} extruder(s); --tool {tool} "
                        "is not one of them")
    put("pressure_advance", f"{k:.4f}")
    put("enable_pressure_advance", "1")
    adaptive = prof.get("adaptive_pressure_advance")
    if adaptive_model is not None:        # the table, switched on for this extruder
        put("adaptive_pressure_advance_model", adaptive_model)
        put("adaptive_pressure_advance", "1")
    elif isinstance(adaptive, list) and tool < len(adaptive) and str(adaptive[tool]) == "1":
        put("adaptive_pressure_advance", "0")
        print("calib export: note: adaptive pressure advance was on in this preset, and Orca "
              "then ignores pressure_advance; it is now off for this extruder", file=sys.stderr)
    m = re.search(r"\n([ \t]+)\S", text)
    indent = m.group(1) if m else "    "
    eol = "\r\n" if "\r\n" in text else "\n"
    out = json.dumps(prof, indent=indent, ensure_ascii=False)
    return out.replace("\n", eol) + eol


# after an escaped newline ("...\\nM572 S0.04") there is no word boundary: the escape ends in 'n'
PA_IN_GCODE = re.compile(r"(?:(?<=\\n)|(?<=\\r)|(?<![A-Za-z0-9]))(M572|M900)\b([^\\;\"\n]*?)\b([SK])(-?[0-9.]+)",
                         re.IGNORECASE)


def update_prusa(text: str, k: str, tool: int = 0) -> str:
    """A PrusaSlicer/SuperSlicer filament ini with the PA command inside
    ``start_filament_gcode`` (a per-extruder list of C-style escaped strings, "a";"b")
    set to ``k`` for extruder ``tool``. The escaped text is edited in place (a PA command
    holds none of the escaped characters); a missing command is appended as ``M572 S``
    (Prusa firmware, REFERENCE). Refused when the extruder's G-code sets PA more than
    once (per-printer or per-nozzle conditionals): one value for all would be wrong."""
    m = re.search(r"(?m)^(start_filament_gcode\s*=\s*)(.*?)(\r?)$", text)
    if not m:
        raise UserError("no start_filament_gcode line: is this a PrusaSlicer/SuperSlicer filament "
                        "preset (exported with File > Export > Export Config)?")
    value = m.group(2)
    strings = list(re.finditer(r'"((?:[^"\\]|\\.)*)"', value))
    spans = [(s.start(1), s.end(1)) for s in strings] or [(0, len(value))]
    if tool >= len(spans):
        raise UserError(f"start_filament_gcode has {len(spans)} extruder entries; --tool {tool} is "
                        "not one of them")
    a, b = spans[tool]
    part = value[a:b]
    hits = list(PA_IN_GCODE.finditer(part))
    if len(hits) > 1:
        raise UserError(f"this preset sets pressure advance {len(hits)} times in start_filament_gcode ("
                        + ", ".join(h.group(0).strip() for h in hits) + "), probably per printer or "
                        "nozzle; set the one for your printer by hand to " + k)
    if hits:
        h = hits[0]
        part = part[:h.start(4)] + k + part[h.end(4):]
    else:
        sep = "" if part.endswith("\\n") or not part else "\\n"
        part = part + f"{sep}M572 S{k}\\n"
    value = value[:a] + part + value[b:]
    return text[:m.start(2)] + value + text[m.end(2):]


def update_klipper_macro(text: str, line: str, k: str, section: str, smooth: str | None = None) -> str:
    """Slicer start G-code: the ADVANCE= of the SET_PRESSURE_ADVANCE lines for this
    extruder (no EXTRUDER= means the active one, taken as ``extruder``) replaced, else the
    line appended; with ``smooth`` (a width-matched smooth time) their SMOOTH_TIME= too."""
    eol = "\r\n" if "\r\n" in text else "\n"
    lines = text.replace("\r\n", "\n").split("\n")
    hit = False
    for i, ln in enumerate(lines):
        if not re.match(r"\s*SET_PRESSURE_ADVANCE\b", ln, re.IGNORECASE):
            continue
        ex = re.search(r"\bEXTRUDER=(\S+)", ln, re.IGNORECASE)
        if (ex.group(1) if ex else "extruder") != klipper_name(section):
            continue
        hit = True
        if re.search(r"\bADVANCE=", ln, re.IGNORECASE):
            lines[i] = re.sub(r"(\bADVANCE=)[-+0-9.]+", rf"\g<1>{k}", ln, flags=re.IGNORECASE)
        else:
            lines[i] = ln.rstrip() + f" ADVANCE={k}"
        if smooth is not None:
            if re.search(r"\bSMOOTH_TIME=", lines[i], re.IGNORECASE):
                lines[i] = re.sub(r"(\bSMOOTH_TIME=)[-+0-9.]+", rf"\g<1>{smooth}", lines[i],
                                  flags=re.IGNORECASE)
            else:
                lines[i] = lines[i].rstrip() + f" SMOOTH_TIME={smooth}"
    if not hit:
        while lines and lines[-1] == "":
            lines.pop()
        lines += [line, ""]
    return eol.join(lines)


def _tool_matches(target: str, code: str, tool: int) -> bool:
    """Does this M900 (Marlin, T<tool>, none = tool 0) / M572 (RRF, D<d>[:<d>...], none =
    drive 0) line set the advance of ``tool``?"""
    if target == "marlin":
        m = re.search(r"\bT(\d+)", code, re.IGNORECASE)
        return (int(m.group(1)) if m else 0) == tool
    m = re.search(r"\bD([\d:]+)", code, re.IGNORECASE)
    return tool in ([int(x) for x in m.group(1).split(":") if x] if m else [0])


def set_pa_gcode(text: str, target: str, k: str, tool: int = 0) -> str:
    """Set the advance of ``tool`` in every M900 (K) / M572 (S) line that addresses it,
    leaving other tools' lines, other parameters and comments alone; append a line when
    none does. Line endings are kept."""
    cmd, letter = ("M900", "K") if target == "marlin" else ("M572", "S")
    eol = "\r\n" if "\r\n" in text else "\n"
    lines = text.replace("\r\n", "\n").split("\n")
    hit = False
    for i, ln in enumerate(lines):
        code, sep, comment = ln.partition(";")
        if not re.match(rf"\s*{cmd}\b", code, re.IGNORECASE) or not _tool_matches(target, code, tool):
            continue
        hit = True
        if re.search(rf"\b{letter}[-+0-9.]+", code, re.IGNORECASE):
            code = re.sub(rf"\b{letter}[-+0-9.]+", f"{letter}{k}", code, flags=re.IGNORECASE)
        else:
            code = code.rstrip() + f" {letter}{k}" + (" " if sep else "")
        lines[i] = code + sep + comment
    if not hit:
        while lines and lines[-1] == "":
            lines.pop()
        lines += [tool_line(target, k, tool), ""]
    return eol.join(lines)


def tool_line(target: str, k: str, tool: int = 0) -> str:
    if target == "marlin":
        return f"M900 T{tool} K{k}" if tool else f"M900 K{k}"
    return f"M572 D{tool} S{k}"


def run(args) -> int:
    from calib.fileio import replace_user_file
    from fit.result import load_fit_json

    doc = load_fit_json(args.fit)
    spool = args.to == "spoolman"
    if spool:                 # argument errors before the fit is judged or simulated
        from calib import spoolman

        if args.profile:
            raise UserError("--profile: --to spoolman edits no file; it prints the body of "
                            "Spoolman's PATCH /api/v1/spool/{id} (drop --profile)")
        spoolman.check_key(args.field_key)
        if args.spool_id is not None and args.spool_id < 1:
            raise UserError(f"--spool-id {args.spool_id}: Spoolman spool ids start at 1")
    if args.to.startswith(("klipper", "kalico")) and not KLIPPER_SECTION.fullmatch(args.section.strip()):
        raise UserError(f"--section {args.section!r}: Klipper keeps pressure advance in [extruder], "
                        "[extruder1], ... or [extruder_stepper NAME]; give the name without brackets")
    args.section = " ".join(args.section.split())
    check_targeting(args.to, args.tool, args.section)
    check_trust(doc, args.force)
    if args.on and args.to not in MATCH_TARGETS:
        raise UserError(f"--on chooses a pressure-advance value; --to {args.to} has none "
                        f"(use one of {', '.join(MATCH_TARGETS)})")
    # what the target needs from the fit, checked before seconds of simulation
    if args.to.startswith("kalico-"):
        kalico_values(doc, args.to)
    elif args.to == "orca-adaptive":
        orca_adaptive_table(doc)
    elif args.to in MATCH_TARGETS:
        pa_value(doc)
    path = text = None
    if args.profile:          # a missing or wrong file is refused before any simulation
        path = Path(args.profile)
        if not path.exists():
            raise UserError(f"profile {path} does not exist")
        try:
            from calib.klipper_cfg import read_exact

            text = read_exact(path)      # line endings kept
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"cannot read profile {path}: {exc}") from None
        check_kind(path, text, args.to)
    if args.to in MATCH_TARGETS:
        # the spool field holds the value Klipper macros apply: Klipper's width match
        as_target = "klipper" if spool else args.to
        m = width_match(doc, as_target, args.on, force=args.force)
        if m is not None:
            report_match(m, as_target)
            if m.n_at_limit and not args.force:
                raise UserError(f"the width-optimal K of {m.n_at_limit} of {m.n_draws + m.n_envelope_draws} draws "
                                f"lies at the search's limit: nothing to paste (--force exports it anyway)")
            doc = with_match(doc, m)
    warn = firmware_warning(doc, args.to)
    if warn:
        print(f"calib export: warning: {warn}", file=sys.stderr)
    if args.to == "kisslicer":
        print(f"calib export: note: {kisslicer_geometry_note(doc)}", file=sys.stderr)
    if args.to == "orca-adaptive":
        print(f"calib export: note: {orca_adaptive_table(doc)[1]}", file=sys.stderr)
    if args.to.startswith("kalico-"):
        print("calib export: note: pressure_advance_model is in Kalico's bleeding-edge-v2 branch, "
              "not in its main branch (checked 2026-11); stock Klipper rejects these options",
              file=sys.stderr)
    if spool:
        k = pa_value(doc)
        define, patch = spoolman.curl_lines(k, args.field_key, args.spool_id)
        print(json.dumps(spoolman.patch_body(k, args.field_key)))
        print(f"calib export: once per Spoolman, define the float spool field: {define}",
              file=sys.stderr)
        note = ("" if "klipper_smooth_time_s" not in (doc.get("derived") or {}) else
                f" (the value is for pressure_advance_smooth_time {smooth_time_s(doc):.3f} s)")
        print(f"calib export: then set it on the spool: {patch}{note}", file=sys.stderr)
        return 0
    if not args.profile:
        print(snippet(doc, args.to, args.section, args.tool))
        if args.to == "marlin":
            print("calib export: note: send M500 after it to keep the value over a reboot "
                  "(Marlin stores it in EEPROM; needs LIN_ADVANCE in the firmware)", file=sys.stderr)
        return 0
    if args.to == "klipper" and "klipper_smooth_time_s" in (doc.get("derived") or {}):
        from calib.klipper_cfg import set_options

        changes = set_options(path, args.section, {
            "pressure_advance": f"{pa_value(doc):.4f}",
            "pressure_advance_smooth_time": f"{smooth_time_s(doc):.3f}"})
    elif args.to == "klipper":
        from calib.klipper_cfg import set_option

        changes = set_option(path, args.section, "pressure_advance", f"{pa_value(doc):.4f}")
    elif args.to.startswith("kalico-"):
        from calib.klipper_cfg import set_options

        changes = set_options(path, args.section, kalico_values(doc, args.to))
    else:
        new = update_text(text, doc, args.to, args.tool, args.section)
        changes = {path: new} if new != text else {}
    if not changes:
        print(f"{path} already has this value; nothing written")
        return 0
    for f, new in changes.items():
        bak = replace_user_file(f, new.encode("utf-8"))
        print(f"updated {f} (backup {bak})")
    return 0
