"""`calib export --to spoolman`: the PATCH body checked by Spoolman's own rules.

Re-implemented from Spoolman (github.com/Donkie/Spoolman, commit a9e50559bb11): the key rule of
spoolman/api/v1/field.py and ExtraField.key in spoolman/extra_field_registry.py (1-64
characters, ``^[a-z0-9_]+$``), ``SpoolParameters.extra: dict[str, str | None]`` in
spoolman/api/v1/spool.py, and ``validate_extra_field_value`` for a float field (the string
json.loads to an int or float that is not a bool); ``ExtraFieldParameters`` for the field
definition (name 1-128 chars, unit 1-16 chars, field_type one of Spoolman's types).
"""
from __future__ import annotations

import json
import re

import pytest

from calib.cli import main
from calib.spoolman import patch_body
from patterns.profile import load_profile
from test_export_match import fit_doc as match_fit_doc

PROF = load_profile("direct_drive")
TAU = 0.04
SPOOLMAN_FIELD_TYPES = ("text", "integer", "integer_range", "float", "float_range", "datetime",
                        "boolean", "choice")


def spoolman_key_ok(key) -> bool:
    return isinstance(key, str) and 1 <= len(key) <= 64 and re.fullmatch(r"[a-z0-9_]+", key) is not None


def spoolman_float_value(value) -> float:
    """Spoolman's validate_extra_field_value for field_type float; the float it stores."""
    assert isinstance(value, str) and len(value) <= 2**16 - 1
    data = json.loads(value)                       # "Value is not valid JSON."
    assert isinstance(data, (float, int)) and not isinstance(data, bool), "Value is not a float."
    return float(data)


def spoolman_patch_ok(body, key: str) -> float:
    """A PATCH /api/v1/spool/{id} body Spoolman accepts for a float field ``key``; its value."""
    assert isinstance(body, dict) and set(body) == {"extra"}
    extra = body["extra"]
    assert isinstance(extra, dict) and set(extra) == {key} and spoolman_key_ok(key)
    return spoolman_float_value(extra[key])


def fit_doc(values: dict, spec: str, n=12, **kw) -> dict:
    """test_export_match's trustworthy fit.json, with the tested flow range recorded."""
    return match_fit_doc(values, spec, n=n, derived={"tested_flow_mm3_s": {"lo": 0.5, "hi": 20.0}}, **kw)


@pytest.fixture
def fit(tmp_path):
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(fit_doc({"pa.tau_s": TAU}, "pa")))
    return str(p)


def klipper_pa(fit, capsys) -> str:
    assert main(["export", fit, "--to", "klipper"]) == 0
    out = capsys.readouterr().out
    return re.search(r"^pressure_advance: (\S+)$", out, re.MULTILINE).group(1)


def test_body_passes_spoolman_rules_and_holds_the_klipper_value(fit, capsys):
    k = klipper_pa(fit, capsys)
    assert main(["export", fit, "--to", "spoolman", "--spool-id", "7"]) == 0
    cap = capsys.readouterr()
    assert cap.out.count("\n") == 1                      # stdout: the body only
    body = json.loads(cap.out)
    assert spoolman_patch_ok(body, "pressure_advance") == float(k)
    assert body["extra"]["pressure_advance"] == k       # the same digits Klipper gets
    err = [ln for ln in cap.err.splitlines() if "curl" in ln]
    assert len(err) == 2
    define, patch = err
    m = re.search(r"curl -X POST (\S+)/api/v1/field/spool/(\S+) .* -d '(.*)'$", define)
    assert m and m.group(2) == "pressure_advance"
    d = json.loads(m.group(3))
    assert d["field_type"] == "float" and d["field_type"] in SPOOLMAN_FIELD_TYPES
    assert 1 <= len(d["name"]) <= 128 and 1 <= len(d["unit"]) <= 16
    assert set(d) <= {"name", "order", "unit", "field_type", "default_value", "choices", "multi_choice"}
    m = re.search(r"curl -X PATCH \S+/api/v1/spool/7 .* -d '(.*)'$", patch.split(" (")[0])
    assert m and json.loads(m.group(1)) == body


def test_nonlinear_fit_exports_klippers_width_matched_value(tmp_path, capsys):
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(fit_doc({"pa.tau_s": TAU, "nonlinear.n": 0.7}, "pa+nonlinear", n=6)))
    k = klipper_pa(str(p), capsys)
    assert abs(float(k) - TAU) > 0.002                  # the match moved it off tau
    assert main(["export", str(p), "--to", "spoolman", "--field-key", "pa_k"]) == 0
    cap = capsys.readouterr()
    body = json.loads(cap.out)
    assert spoolman_patch_ok(body, "pa_k") == float(k)
    assert "/api/v1/spool/<SPOOL_ID>" in cap.err and "smooth_time" in cap.err


@pytest.mark.parametrize("key", ["Pressure_Advance", "pressure-advance", "", "a" * 65, "pa k",
                                 "pa\n"])
def test_bad_key_is_one_line_exit_2(fit, capsys, key):
    assert not spoolman_key_ok(key)
    assert main(["export", fit, "--to", "spoolman", "--field-key", key]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.count("\n") == 1 and "field-key" in cap.err
    with pytest.raises(Exception):
        patch_body(0.04, key)


@pytest.mark.parametrize("key", ["pressure_advance", "a" * 64, "pa_2", "0"])
def test_good_keys_and_values_pass_spoolman(key):
    for k in (0.0, 0.04, 0.00004, 1.23456, -0.00001):
        v = spoolman_patch_ok(patch_body(k, key), key)
        assert v == pytest.approx(max(k, 0.0) if abs(k) < 5e-5 else k, abs=5e-5)


def test_profile_refused(fit, tmp_path, capsys):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[extruder]\npressure_advance: 0.5\n")
    assert main(["export", fit, "--to", "spoolman", "--profile", str(cfg)]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.count("\n") == 1 and "--profile" in cap.err
    assert cfg.read_text() == "[extruder]\npressure_advance: 0.5\n"


def test_untrustworthy_fit_refused_unless_forced(tmp_path, capsys):
    doc = fit_doc({"pa.tau_s": TAU}, "pa")
    doc["information"]["chi2_nu"] = 50.0
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(doc))
    assert main(["export", str(p), "--to", "spoolman"]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and "not trustworthy" in cap.err
    assert main(["export", str(p), "--to", "spoolman", "--force"]) == 0
    assert spoolman_patch_ok(json.loads(capsys.readouterr().out), "pressure_advance") > 0
