"""Printer profiles: shipped files load, validation names the problem, derived values."""
import math

import pytest

from calib.errors import UserError
from patterns.profile import load_profile, profile_from_dict, shipped_profiles


def test_shipped_profiles_load_and_adventurer3_matches_realdata_printer():
    names = shipped_profiles()
    assert {"adventurer3", "long_bowden", "direct_drive"} <= set(names)
    p = load_profile("adventurer3")
    assert (p.firmware, p.nozzle_diameter_mm, p.filament_diameter_mm) == ("marlin", 0.4, 1.75)
    assert p.bed_x_mm[1] - p.bed_x_mm[0] == 150.0 and p.bowden_length_mm > 0
    assert "M132" in p.start_gcode and "G161" in p.start_gcode
    assert load_profile("direct_drive").bowden_length_mm == 0.0
    assert load_profile("long_bowden").bowden_length_mm >= 600.0


def test_to_dict_round_trip_is_identity():
    for name in shipped_profiles():
        p = load_profile(name)
        assert profile_from_dict(p.to_dict()) == p


def test_klipper_junction_deviation_from_square_corner_velocity():
    p = load_profile("direct_drive")
    jd = p.square_corner_velocity_mm_s ** 2 * (math.sqrt(2) - 1) / p.max_accel_mm_s2
    assert p.junction_deviation_for_planner_mm == pytest.approx(jd, rel=1e-12)


def test_filament_area():
    assert load_profile("adventurer3").filament_area_mm2 == pytest.approx(math.pi * 1.75 ** 2 / 4)


def _base():
    return load_profile("adventurer3").to_dict()


@pytest.mark.parametrize("change, message", [
    ({"nozzle_diameter_mm": None}, "missing key 'nozzle_diameter_mm'"),
    ({"nozzle_diameter_mm": "0.4in"}, "nozzle_diameter_mm must be a plain number in the key's unit (mm), got the string '0.4in'"),
    ({"nozzle_diameter_in": 0.016}, "key 'nozzle_diameter_in' has the wrong unit"),
    ({"max_accel_mm_s2": -5.0}, "max_accel_mm_s2 must be > 0, got -5.0"),
    ({"bowden_length_mm": -1.0}, "bowden_length_mm must be >= 0, got -1.0"),
    ({"nozzle_diameter_mm": 2.0}, "nozzle_diameter_mm 2.0 must be smaller than filament_diameter_mm 1.75"),
    ({"bed_x_mm": [100.0, 0.0]}, "bed_x_mm min 100.0 must be below max 0.0"),
    ({"firmware": "sailfish"}, "unknown firmware 'sailfish'; use one of marlin, klipper, rrf"),
    ({"firmware": "klipper"}, "missing key 'square_corner_velocity_mm_s' (required for firmware klipper)"),
    ({"start_gcode": "M104 S{hotend_temp}"}, "unknown placeholder {hotend_temp}"),
])
def test_validation_messages(change, message):
    d = _base()
    for k, v in change.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    with pytest.raises(UserError) as ei:
        profile_from_dict(d, source="p.toml")
    assert message in str(ei.value)
    assert str(ei.value).startswith("p.toml: ")
    assert "\n" not in str(ei.value)


def test_file_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed\n")
    with pytest.raises(UserError, match="is not valid TOML"):
        load_profile(bad)
    with pytest.raises(UserError, match="unknown printer 'nosuch'"):
        load_profile("nosuch")
    with pytest.raises(UserError, match="does not exist"):
        load_profile(tmp_path / "missing.toml")
