"""G-code writer and parser: round trips, the E formula, modes, arcs, bounds, realdata."""
import math
import re
from pathlib import Path

import numpy as np
import pytest

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns.gcode_parser import auto_tracks, parse_gcode
from patterns.gcode_writer import GcodeWriter
from patterns.profile import load_profile

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


def _program(profile, relative_e):
    w = GcodeWriter(profile, relative_e=relative_e, layer_height_mm=0.2)
    w.header("round trip", {"speed_mm_s": 30})
    w.set_z(0.2)
    w.travel(10, 10)
    w.begin_track(1, "test")
    e1 = w.extrude_line(60, 10, 0.45, 30)
    w.move_with_e(60, 40, 0.0, 30)           # coasting inside the track
    w.extruder_move(-2.0, 40)
    w.dwell(0.25)
    w.extruder_move(2.0, 30)
    e2 = w.extrude_line(10, 40, 0.8, 20, height_mm=0.2)
    w.end_track()
    w.travel(20, 20)
    w.footer()
    return w, (e1, e2)


@pytest.mark.parametrize("relative_e", [True, False])
def test_writer_parser_round_trip(relative_e):
    prof = load_profile("direct_drive")
    w, (e1, e2) = _program(prof, relative_e)
    text = w.text()
    assert ("M83" in text) == relative_e and ("M82" in text) != relative_e
    af = math.pi * 1.75 ** 2 / 4
    assert e1 == pytest.approx(float(bead_area_mm2(0.45, 0.2)) * 50 / af, abs=1e-5)
    assert e2 == pytest.approx(float(bead_area_mm2(0.8, 0.2)) * 50 / af, abs=1e-5)
    pr = parse_gcode(text, prof)
    m = pr.moves
    assert m.de_mm.sum() == pytest.approx(w.e_total_mm, abs=1e-9)
    on = m.track == 1
    # track 1: extrude, coast, retract, dwell, restore, extrude -- in that order
    assert list(np.round(m.de_mm[on], 5)) == [round(e1, 5), 0.0, -2.0, 0.0, 2.0, round(e2, 5)]
    assert m.dwell_s[on][3] == pytest.approx(0.25)
    ends = np.column_stack([m.x_mm[on], m.y_mm[on]])
    assert np.allclose(ends[[0, 1, 5]], [[60, 10], [60, 40], [10, 40]])
    assert np.allclose(m.feed_mm_s[on][[0, 5]], [30, 20])
    assert pr.track_kinds == {1: "test"}
    assert w.position == (20.0, 20.0, 0.2)
    assert pr.pa_events[0].k_s == 0.0


def test_absolute_mode_g92_resets_register_not_total():
    prof = load_profile("adventurer3")           # no M83: absolute E
    w = GcodeWriter(prof, relative_e=True)
    w.header("abs", {})
    codes = [l.split(";")[0].strip() for l in w.text().splitlines()]
    assert "M82" in codes and "M83" not in codes
    w.set_z(0.3)
    w.travel(0, 0)
    w.extrude_line(50, 0, 0.5, 20, height_mm=0.3)
    text = w.text() + "G92 E0\nG1 X50 Y10 E0.5\nG1 E0.3\n"
    m = parse_gcode(text, prof).moves
    assert m.de_mm[-2] == pytest.approx(0.5) and m.de_mm[-1] == pytest.approx(-0.2)
    assert m.de_mm.sum() == pytest.approx(w.e_total_mm + 0.3)


def test_feedrate_only_written_when_it_changes():
    w = GcodeWriter("direct_drive")
    w.travel(0, 0, 100)
    for x in (10, 20, 30):
        w.extrude_line(x, 0, 0.4, 50)
    w.extrude_line(40, 0, 0.4, 25)
    g1 = [l for l in w.text().splitlines() if l.startswith("G1")]
    assert [("F" in l) for l in g1] == [True, False, False, True]
    assert "F3000" in g1[0] and "F1500" in g1[3]


def test_bed_bounds_raise_user_error_naming_the_move():
    w = GcodeWriter("adventurer3")
    w.travel(0, 0)
    w.extrude_line(10, 0, 0.4, 20)
    with pytest.raises(UserError) as ei:
        w.extrude_line(80, 0, 0.4, 20)
    assert str(ei.value) == ("move 3 (extrude_line to X80 Y0) is outside the bed of adventurer3: "
                             "x -75..75, y -75..75 mm")
    with pytest.raises(UserError, match="travel to X-76"):
        w.travel(-76, 0)


@pytest.mark.parametrize("name, line", [("adventurer3", "M900 K0"), ("direct_drive", "SET_PRESSURE_ADVANCE ADVANCE=0"),
                                        ("long_bowden", "M572 D0 S0")])
def test_pressure_advance_off_per_flavour_and_parsed(name, line):
    w = GcodeWriter(name)
    w.header("pa", {})
    assert line in w.text().splitlines()
    w2 = GcodeWriter(name, pressure_advance_s=0.35, smooth_time_s=0.04)
    w2.header("pa", {})
    ev = parse_gcode(w2.text()).pa_events
    assert len(ev) == 1 and ev[0].k_s == pytest.approx(0.35)
    if name == "direct_drive":
        assert ev[0].smooth_time_s == pytest.approx(0.04)


def test_arcs_are_chords_within_tolerance_and_ij_equals_r():
    base = "G21\nG90\nM83\nG1 X10 Y0 F600\n"
    ij = parse_gcode(base + "G3 X0 Y10 I-10 J0 E1.0\n").moves
    r = parse_gcode(base + "G3 X0 Y10 R10 E1.0\n").moves
    assert len(ij) == len(r) > 2
    assert np.allclose(ij.x_mm, r.x_mm) and np.allclose(ij.y_mm, r.y_mm)
    # all vertices on the circle, chord sagitta <= 0.1 mm, E spread over the arc
    arc = slice(1, None)
    assert np.allclose(np.hypot(ij.x_mm[arc], ij.y_mm[arc]), 10.0)
    chord = np.hypot(ij.x_mm[arc] - ij.x0_mm[arc], ij.y_mm[arc] - ij.y0_mm[arc])
    sagitta = 10 - np.sqrt(100 - (chord / 2) ** 2)
    assert sagitta.max() <= 0.1 + 1e-12
    assert ij.de_mm[arc].sum() == pytest.approx(1.0)
    assert (ij.x_mm[-1], ij.y_mm[-1]) == (0.0, 10.0)
    # G2 goes clockwise: the long way round from (10,0) to (0,10), 3/4 of a turn
    cw = parse_gcode(base + "G2 X0 Y10 I-10 J0\n").moves
    n = len(cw) - 1
    polygon = n * 2 * 10 * math.sin(1.5 * math.pi / n / 2)
    assert cw.xy_length_mm[1:].sum() == pytest.approx(polygon, rel=1e-9)
    assert polygon == pytest.approx(2 * math.pi * 10 * 0.75, rel=5e-3)


def test_units_relative_offsets_dwell_and_firmware_retraction():
    prof = load_profile("ender3")
    text = """; comment line
G20 (inches from here)
G90
G1 X1 Y1 F600 ; 25.4 mm, 10 in/min
G21
G91
G1 X10
G90
G92 X0 Y0
G1 X5 Y5
G4 P500
G4 S2
G10
G11
M999 ; unknown
FOO_BAR X=1
"""
    pr = parse_gcode(text, prof)
    m = pr.moves
    assert (m.x_mm[0], m.y_mm[0]) == pytest.approx((25.4, 25.4))
    assert m.feed_mm_s[0] == pytest.approx(600 * 25.4 / 60)
    assert m.x_mm[1] == pytest.approx(35.4)
    assert (m.x_mm[2], m.y_mm[2]) == pytest.approx((40.4, 30.4))   # G92 shifted the origin only
    assert list(m.dwell_s[3:5]) == [0.5, 2.0]
    assert list(m.de_mm[5:7]) == [-5.0, 5.0]                        # profile retract length
    assert m.feed_mm_s[5] == prof.retract_speed_mm_s
    assert any("skipped 2 unknown command(s): FOO_BAR x1, M999 x1" in w for w in pr.warnings)


def test_not_gcode_is_a_user_error():
    with pytest.raises(UserError, match="binary file"):
        parse_gcode(b"\x7fELF\x00\x00\x01")
    with pytest.raises(UserError, match="no G or M commands"):
        parse_gcode("Dear printer,\nplease print nicely.\n")


def test_auto_tracks_are_runs_of_extruding_moves_at_one_z():
    text = """M83
G1 Z0.2
G1 X0 Y0
G1 X10 Y0 E1
G1 X10 Y10 E1
G1 E-1
G1 X20 Y10
G1 E1
G1 X30 Y10 E1
G1 Z0.4
G1 X40 Y10 E1
"""
    m = parse_gcode(text).moves
    ids = auto_tracks(m)
    # "G1 X0 Y0" from the origin is no move at all: not in the table
    assert list(ids) == [-1, 0, 0, -1, -1, -1, 1, -1, 2]


@pytest.mark.skipif(not REALDATA.is_dir(), reason="../shared/realdata not present")
def test_realdata_gcode_parses_with_flashforge_commands_counted():
    prof = load_profile("adventurer3")
    for path in sorted(REALDATA.glob("*.g")):
        text = path.read_text()
        pr = parse_gcode(text, prof)
        last_e = float(re.findall(r"E([-\d.]+)", text)[-1])
        # absolute E, never reset: the sum of steps is the last E word
        assert pr.moves.de_mm.sum() == pytest.approx(last_e, abs=1e-6)
        assert len(pr.moves) > 2500
        assert pr.unknown_commands.get("M132") == 2 and pr.unknown_commands.get("G161") == 1
        assert not any("outside the bed" in w for w in pr.warnings)


def test_line_numbers_checksums_and_lowercase():
    m = parse_gcode("N10 G1 X5 Y2 F600*35\nn11 g1 x7 y2 e0.5\n").moves
    assert list(m.x_mm) == [5.0, 7.0] and m.de_mm[1] == pytest.approx(0.5)
