"""`calib export --profile` on real-world printer.cfg layouts, loaded back by Klipper's rules.

``klipper_reads`` follows klippy/configfile.py read_main_config step by step: CRLF -> LF,
split at the SAVE_CONFIG header, refuse the autosave block if anything in it lacks the
'#*# ' prefix or the regular part contains one ("Can't read autosave"), drop text after
'#', expand [include] in place, RawConfigParser(strict=False, inline_comment_prefixes=
(';', '#')) fed chunk by chunk, autosave options that the regular part also sets dropped.
"""
from __future__ import annotations

import configparser
import glob
import json
import os
from pathlib import Path

import pytest

from calib.cli import main

AUTOSAVE = ("\n#*# <---------------------- SAVE_CONFIG ---------------------->\n"
            "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n")
SAVE_BLOCK = AUTOSAVE + "#*# [stepper_z]\n#*# position_endstop = 0.512\n#*#\n#*# [extruder]\n#*# pid_kp = 22.1\n"


def klipper_reads(main_cfg: Path) -> configparser.RawConfigParser:
    data = main_cfg.read_text().replace("\r\n", "\n")
    pos = data.find(AUTOSAVE)
    regular, auto = (data[:pos], data[pos + len(AUTOSAVE):].strip()) if pos >= 0 else (data, "")
    assert "\n#*# " not in regular, "Klipper: autosave state corrupted"
    for line in auto.split("\n") if auto else []:
        assert line.startswith("#*#") and (len(line) < 4 or line.startswith("#*# ")), \
            "Klipper: modifications after header"
    auto = "\n".join(line[4:] for line in auto.split("\n")) if auto else ""

    def parse(text, filename, cp):
        buf = []
        for line in text.split("\n"):
            if "#" in line:
                line = line[:line.find("#")]
            mo = configparser.RawConfigParser.SECTCRE.match(line)
            header = mo and mo.group("header")
            if header and header.startswith("include "):
                cp.read_string("\n".join(buf))
                buf = []
                for inc in sorted(glob.glob(os.path.join(os.path.dirname(filename), header[8:].strip()))):
                    parse(Path(inc).read_text().replace("\r\n", "\n"), inc, cp)
            else:
                buf.append(line)
        cp.read_string("\n".join(buf))

    def new():
        return configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))

    reg = new()
    parse(regular, str(main_cfg), reg)
    if auto:
        a = new()
        a.read_string(auto)
        for s in a.sections():
            if not reg.has_section(s):
                reg.add_section(s)
            for o in a.options(s):
                if not reg.has_option(s, o):
                    reg.set(s, o, a.get(s, o))
    return reg


@pytest.fixture
def fit_json(tmp_path):
    doc = {"schema": "calib.fit/1", "model": "pa", "converged": True,
           "information": {"chi2_nu": 1.0, "rms_mm": 0.01, "n_obs": 500, "loo": {}},
           "params": {"pa.tau_s": {"median": 0.0412, "ci95": [0.04, 0.042]}},
           "priors": {"pa.tau_s": {"kind": "loguniform", "lower": 0.005, "upper": 5.0}},
           "derived": {"pressure_advance_s": {"median": 0.0412}},
           "profile": {"name": "direct_drive"}, "samples": []}
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(doc))
    return str(p)


def _export(fit, cfg, *extra):
    return main(["export", fit, "--to", "klipper", "--profile", str(cfg), *extra])


def test_extruder_in_an_include_with_a_save_config_block(tmp_path, fit_json):
    (tmp_path / "hw").mkdir()
    inc = tmp_path / "hw" / "extruder.cfg"
    inc.write_text("[extruder]   # E3D V6\nstep_pin: PB3\nrotation_distance: 22.6\n"
                   "pressure_advance: 0.5  ; old\n")
    cfg = tmp_path / "printer.cfg"
    main_text = "[include hw/*.cfg]\n[printer]\nkinematics: cartesian\n" + SAVE_BLOCK
    cfg.write_text(main_text)
    assert _export(fit_json, cfg) == 0
    assert cfg.read_text() == main_text                   # main file and SAVE_CONFIG untouched
    k = klipper_reads(cfg)
    assert k.getfloat("extruder", "pressure_advance") == 0.0412
    assert k.get("stepper_z", "position_endstop") == "0.512"   # autosave still read
    assert "; old" in inc.read_text() and "# E3D V6" in inc.read_text()
    assert len(list((tmp_path / "hw").glob("extruder.cfg.bak-*"))) == 1


def test_commented_header_gets_the_option_before_the_save_config_block(tmp_path, fit_json):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: corexy\n\n[extruder]   # E3D\nstep_pin: PB3\n\n"
                   "[heater_bed]\nheater_pin: PA1\n" + SAVE_BLOCK)
    assert _export(fit_json, cfg) == 0
    k = klipper_reads(cfg)
    assert k.getfloat("extruder", "pressure_advance") == 0.0412
    assert k.get("extruder", "step_pin") == "PB3" and k.get("stepper_z", "position_endstop") == "0.512"
    assert cfg.read_text().index("pressure_advance") < cfg.read_text().index("#*# <---")


def test_the_value_klipper_reads_is_the_one_edited(tmp_path, fit_json):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[extruder]\nstep_pin: PB3\npressure_advance: 0.1\n\n[fan]\npin: PA8\n\n"
                   "[extruder]\npressure_advance = 0.2\n")
    assert _export(fit_json, cfg) == 0
    text = cfg.read_text()
    assert "pressure_advance: 0.1\n" in text and "pressure_advance = 0.0412\n" in text
    assert klipper_reads(cfg).getfloat("extruder", "pressure_advance") == 0.0412


def test_second_extruder_crlf_symlink_mode_and_no_write_when_unchanged(tmp_path, fit_json, capsys):
    real = tmp_path / "config-repo" / "printer.cfg"
    real.parent.mkdir()
    real.write_bytes(b"[extruder]\r\nstep_pin: PB3\r\n\r\n[extruder1]\r\nstep_pin: PB4\r\n")
    os.chmod(real, 0o640)
    link = tmp_path / "printer.cfg"
    link.symlink_to(real)
    assert _export(fit_json, link, "--section", "extruder1") == 0
    assert link.is_symlink() and os.readlink(link) == str(real)
    data = real.read_bytes()
    assert b"\r\npressure_advance: 0.0412\r\n" in data and b"\n" not in data.replace(b"\r\n", b"")
    assert (real.stat().st_mode & 0o777) == 0o640
    k = klipper_reads(link)
    assert k.getfloat("extruder1", "pressure_advance") == 0.0412
    assert not k.has_option("extruder", "pressure_advance")
    before = sorted(real.parent.iterdir())
    capsys.readouterr()
    assert _export(fit_json, link, "--section", "extruder1") == 0
    assert "nothing written" in capsys.readouterr().out
    assert sorted(real.parent.iterdir()) == before       # no second backup
    assert _export(fit_json, link, "--section", "extruder2") == 2
    assert "found: extruder, extruder1" in capsys.readouterr().err


@pytest.mark.parametrize("target,content,hint", [
    ("klipper", '{"name": "PLA", "pressure_advance": ["0.02"]}', "--to orca"),
    ("marlin", "[extruder]\nstep_pin: PB3\n", "--to klipper"),
    ("orca", "[extruder]\nstep_pin: PB3\n", "--to klipper"),
    ("klipper", "G28\nM900 K0\n", "--to marlin"),
    # a printer.cfg whose header was cut short is still not a start G-code to append M900 to
    ("marlin", "[extruder\npressure_advance: 0.1\n", "--to klipper"),
])
def test_a_file_of_another_kind_is_refused_untouched(tmp_path, fit_json, capsys, target, content, hint):
    f = tmp_path / "profile.x"
    f.write_text(content)
    assert main(["export", fit_json, "--to", target, "--profile", str(f)]) == 2
    err = capsys.readouterr().err
    assert hint in err and err.count("\n") == 1
    assert f.read_text() == content and not list(tmp_path.glob("profile.x.bak-*"))


def test_marlin_and_rrf_lines_of_other_tools_are_left_alone(tmp_path, fit_json, capsys):
    start = tmp_path / "start.gcode"
    start.write_bytes(b"M104 S210\r\nM900 K0.02 L0 ; tool 0\r\nM900 T1 K0.08\r\nG28\r\n")
    assert main(["export", fit_json, "--to", "marlin", "--profile", str(start), "--tool", "1"]) == 0
    assert start.read_bytes() == b"M104 S210\r\nM900 K0.02 L0 ; tool 0\r\nM900 T1 K0.0412\r\nG28\r\n"
    assert main(["export", fit_json, "--to", "marlin", "--profile", str(start)]) == 0
    assert b"M900 K0.0412 L0 ; tool 0\r\n" in start.read_bytes()
    rrf = tmp_path / "config.g"
    rrf.write_text("M572 D0:1 S0.05 ; both drives\nM572 D2 S0.2\n")
    assert main(["export", fit_json, "--to", "rrf", "--profile", str(rrf), "--tool", "2"]) == 0
    assert rrf.read_text() == "M572 D0:1 S0.05 ; both drives\nM572 D2 S0.0412\n"
    assert main(["export", fit_json, "--to", "rrf", "--profile", str(rrf), "--tool", "3"]) == 0
    assert rrf.read_text().endswith("M572 D2 S0.0412\nM572 D3 S0.0412\n")
    capsys.readouterr()
    assert main(["export", fit_json, "--to", "marlin", "--tool", "1"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "M900 T1 K0.0412\n" and "M500" in cap.err


def test_orca_filament_presets_only_arrays_kept_adaptive_pa_off(tmp_path, fit_json, capsys):
    preset = {"name": "My PLA", "from": "User", "inherits": "Generic PLA", "filament_type": ["PLA"],
              "pressure_advance": ["0.02", "0.03"], "enable_pressure_advance": ["0", "0"],
              "adaptive_pressure_advance": ["1", "1"], "filament_settings_id": ["My PLA"]}
    f = tmp_path / "My PLA.json"
    f.write_text(json.dumps(preset, indent=2))
    assert main(["export", fit_json, "--to", "orca", "--profile", str(f), "--tool", "1"]) == 0
    out = json.loads(f.read_text())
    # Orca's types: string arrays, one entry per extruder; the other extruder untouched
    assert out["pressure_advance"] == ["0.02", "0.0412"]
    assert out["enable_pressure_advance"] == ["0", "1"]
    assert out["adaptive_pressure_advance"] == ["1", "0"]
    assert all(isinstance(v, str) for key in ("pressure_advance", "enable_pressure_advance")
               for v in out[key])
    assert f.read_text().startswith('{\n  "name"')                # indent kept
    assert "adaptive pressure advance was on" in capsys.readouterr().err
    for bad, msg in (({"type": "machine", "name": "X1C"}, "not an Orca filament preset"),
                     ({"type": "filament", "from": "system", "pressure_advance": ["0.02"]}, "system preset")):
        g = tmp_path / "bad.json"
        g.write_text(json.dumps(bad))
        assert main(["export", fit_json, "--to", "orca", "--profile", str(g)]) == 2
        assert msg in capsys.readouterr().err and json.loads(g.read_text()) == bad


def _prusa_unescape(s: str) -> str:
    """PrusaSlicer's unescape_string_cstyle for one quoted value: \\n, \\r, \\\\, \\"."""
    out, i = [], 0
    while i < len(s):
        if s[i] == "\\" and i + 1 < len(s):
            out.append({"n": "\n", "r": "\r"}.get(s[i + 1], s[i + 1]))
            i += 2
        else:
            out.append(s[i])
            i += 1
    return "".join(out)


def test_prusa_filament_ini_edits_inside_start_filament_gcode(tmp_path, fit_json, capsys):
    f = tmp_path / "PLA.ini"
    f.write_text('filament_type = PLA\nstart_filament_gcode = "; Filament gcode\\nM572 S0.05 ; PA\\n"\n'
                 'temperature = 215\n')
    assert main(["export", fit_json, "--to", "prusa", "--profile", str(f)]) == 0
    line = [ln for ln in f.read_text().splitlines() if ln.startswith("start_filament_gcode")][0]
    value = line.split("=", 1)[1].strip()
    assert value.startswith('"') and value.endswith('"')
    assert _prusa_unescape(value[1:-1]) == "; Filament gcode\nM572 S0.0412 ; PA\n"
    assert "temperature = 215" in f.read_text()
    # two extruders, no PA yet in the second: appended inside its own string only
    g = tmp_path / "MMU.ini"
    g.write_text('start_filament_gcode = "M572 S0.03\\n";"; second\\n"\n')
    assert main(["export", fit_json, "--to", "prusa", "--profile", str(g), "--tool", "1"]) == 0
    assert g.read_text() == 'start_filament_gcode = "M572 S0.03\\n";"; second\\nM572 S0.0412\\n"\n'
    # per-nozzle conditionals: refused, untouched
    h = tmp_path / "cond.ini"
    cond = ('start_filament_gcode = "{if nozzle_diameter[0]==0.4}M572 S0.05{elsif '
            'nozzle_diameter[0]==0.6}M572 S0.03{endif}\\n"\n')
    h.write_text(cond)
    capsys.readouterr()
    assert main(["export", fit_json, "--to", "prusa", "--profile", str(h)]) == 2
    assert "sets pressure advance 2 times" in capsys.readouterr().err and h.read_text() == cond


def test_klipper_start_gcode_line_with_smooth_time(tmp_path, fit_json, capsys):
    assert main(["export", fit_json, "--to", "klipper-gcode", "--section", "extruder1"]) == 0
    assert capsys.readouterr().out == "SET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.0412 SMOOTH_TIME=0.040\n"
    start = tmp_path / "start.gcode"
    start.write_text("PRINT_START\nSET_PRESSURE_ADVANCE ADVANCE=0.02 SMOOTH_TIME=0.03\n"
                     "SET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.05\nG28\n")
    assert main(["export", fit_json, "--to", "klipper-gcode", "--profile", str(start)]) == 0
    assert start.read_text() == ("PRINT_START\nSET_PRESSURE_ADVANCE ADVANCE=0.0412 SMOOTH_TIME=0.03\n"
                                 "SET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.05\nG28\n")


def test_kalico_nonlinear_pa_into_printer_cfg(tmp_path, fit_json, capsys):
    doc = json.loads(Path(fit_json).read_text())
    doc["derived"]["kalico_tanh"] = {"pressure_advance_s": {"median": 0.017},
                                     "offset_mm": {"median": 0.12},
                                     "linearization_velocity_mm_s": {"median": 1.3}}
    fit = tmp_path / "nl.json"
    fit.write_text(json.dumps(doc))
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[extruder]\nstep_pin: PB3\npressure_advance: 0.04\n" + SAVE_BLOCK)
    assert main(["export", str(fit), "--to", "kalico-tanh", "--profile", str(cfg)]) == 0
    k = klipper_reads(cfg)
    assert k.get("extruder", "pressure_advance_model") == "tanh"
    assert k.getfloat("extruder", "linear_advance") == 0.017
    assert k.getfloat("extruder", "nonlinear_offset") == 0.12
    assert k.getfloat("extruder", "linearization_velocity") == 1.3
    assert k.get("stepper_z", "position_endstop") == "0.512"
    assert len(list(tmp_path.glob("printer.cfg.bak-*"))) == 1          # one backup, one write
    assert "bleeding-edge-v2" in capsys.readouterr().err
    assert main(["export", str(fit), "--to", "kalico-tanh"]) == 0
    assert "SET_PRESSURE_ADVANCE ADVANCE=0.0170 OFFSET=0.1200 VELOCITY=1.3000" in capsys.readouterr().out
    assert main(["export", fit_json, "--to", "kalico-recipr"]) == 2      # a linear fit: no match
    assert "needs a nonlinear advance term" in capsys.readouterr().err


def test_orca_adaptive_table_from_a_nonlinear_fit(tmp_path, fit_json, capsys):
    doc = json.loads(Path(fit_json).read_text())
    doc["derived"]["pa_vs_flow"] = {"flow_mm3_s": [1.0, 5.0], "pa_s_median": [0.06, 0.04],
                                    "v_mm_s": [0.4, 2.1], "pa_s_ci95": [[0.05, 0.07], [0.03, 0.05]],
                                    "v_max_mm_s": 2.1}
    fit = tmp_path / "nl.json"
    fit.write_text(json.dumps(doc))
    assert main(["export", str(fit), "--to", "orca-adaptive"]) == 0
    cap = capsys.readouterr()
    lines = cap.out.strip().splitlines()
    assert lines[0] == "0.0600,1.00,1000" and lines[-1] == "0.0400,5.00,10000" and len(lines) == 6
    assert "covers flows 1.00-5.00 mm^3/s" in cap.err and "no acceleration term" in cap.err
    preset = tmp_path / "PLA.json"
    preset.write_text(json.dumps({"type": "filament", "pressure_advance": ["0.02"],
                                  "adaptive_pressure_advance": ["0"],
                                  "adaptive_pressure_advance_model": ["0,0,0\n0,0,0"]}))
    assert main(["export", str(fit), "--to", "orca-adaptive", "--profile", str(preset)]) == 0
    out = json.loads(preset.read_text())
    assert out["adaptive_pressure_advance"] == ["1"]
    rows = [r.split(",") for r in out["adaptive_pressure_advance_model"][0].split("\n")]
    assert all(len(r) == 3 for r in rows) and float(rows[0][0]) == 0.06     # PA,flow,accel
    assert main(["export", fit_json, "--to", "orca-adaptive"]) == 2       # a linear fit


def test_an_extruder_stepper_section_is_named_as_klipper_names_it(tmp_path, fit_json, capsys):
    """[extruder_stepper belt] is SET_PRESSURE_ADVANCE EXTRUDER=belt (Klipper's
    ExtruderStepper: the section name's last word); a bracketed or empty --section is
    refused in one line."""
    assert main(["export", fit_json, "--to", "klipper-gcode", "--section", "extruder_stepper belt"]) == 0
    assert capsys.readouterr().out.startswith("SET_PRESSURE_ADVANCE EXTRUDER=belt ADVANCE=0.0412")
    start = tmp_path / "start.gcode"
    start.write_text("SET_PRESSURE_ADVANCE EXTRUDER=belt ADVANCE=0.1\nSET_PRESSURE_ADVANCE ADVANCE=0.2\n")
    assert main(["export", fit_json, "--to", "klipper-gcode", "--section", "extruder_stepper belt",
                 "--profile", str(start)]) == 0
    assert start.read_text().startswith("SET_PRESSURE_ADVANCE EXTRUDER=belt ADVANCE=0.0412")
    assert "SET_PRESSURE_ADVANCE ADVANCE=0.2\n" in start.read_text()
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[extruder]\nstep_pin: PB3\n\n[extruder_stepper belt]\nextruder: extruder\n")
    assert main(["export", fit_json, "--to", "klipper", "--section", "extruder_stepper belt",
                 "--profile", str(cfg)]) == 0
    assert "[extruder_stepper belt]\npressure_advance: 0.0412\n" in cfg.read_text()
    capsys.readouterr()
    for bad in ("[extruder1]", "", "extruder x"):
        assert main(["export", fit_json, "--to", "klipper", "--section", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--section" in err[0]


def test_tool_and_section_go_only_where_the_target_chooses_extruders_that_way(fit_json, capsys):
    """--tool was ignored by Klipper's targets (a fuzzed `--tool 99 --to klipper` printed
    [extruder]) and --section by the others: either would set extruder 0 where the user
    asked for another. Now one line naming the option the target does take."""
    for argv, hint in ((["--to", "klipper", "--tool", "1"], "--section extruder1"),
                       (["--to", "klipper-gcode", "--tool", "2"], "--section extruder2"),
                       (["--to", "kisslicer", "--tool", "1"], "drop --tool"),
                       (["--to", "marlin", "--section", "extruder1"], "--tool N"),
                       (["--to", "spoolman", "--section", "extruder1"], "drop --section")):
        assert main(["export", fit_json, *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and hint in err[0], (argv, err)
    assert main(["export", fit_json, "--to", "marlin", "--tool", "1"]) == 0
    assert "T1" in capsys.readouterr().out
