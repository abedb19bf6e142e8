"""Motion planner against analytic trapezoids, published junction formulas, volume balance."""
import math

import numpy as np
import pytest

from patterns.gcode_parser import parse_gcode
from patterns.planner import junction_speed_klipper_mm_s, plan, plan_gcode, plan_moves
from patterns.profile import load_profile, profile_from_dict


def _prof(name="direct_drive", **kw):
    d = load_profile(name).to_dict()
    d.update(kw)
    return profile_from_dict(d)


def _analytic_s(t, v0, vc, v1, a, L):
    ta, td = (vc - v0) / a, (vc - v1) / a
    tc = (L - (vc**2 - v0**2) / (2 * a) - (vc**2 - v1**2) / (2 * a)) / vc
    t = np.asarray(t)
    s_acc = v0 * t + 0.5 * a * t**2
    da = v0 * ta + 0.5 * a * ta**2
    s_cru = da + vc * (t - ta)
    t1 = t - ta - tc
    s_dec = da + vc * tc + vc * t1 - 0.5 * a * t1**2
    return np.where(t < ta, s_acc, np.where(t1 > 0, s_dec, s_cru)), ta + tc + td


def test_trapezoid_matches_analytic_distance_and_time():
    prof = _prof(max_accel_mm_s2=1000.0)
    tl, pr = plan_gcode("G90\nG1 X10 Y20 F600\nG4 P1\nG1 X110 Y20 F6000\n", prof)
    mp = plan_moves(pr.moves, prof)
    # move 2: 100 mm at 100 mm/s, a = 1000: 0.1 s up (5 mm), 0.9 s cruise, 0.1 s down
    assert mp.duration_s[2] == pytest.approx(1.1, abs=1e-9)
    assert (mp.v_start_mm_s[2], mp.v_end_mm_s[2]) == (0.0, 0.0)   # straight from standstill
    on = (tl.t_s >= mp.t_start_s[2]) & (tl.y_mm == 20) & (tl.x_mm >= 10)
    t = tl.t_s[on] - mp.t_start_s[2]
    s_exp, T = _analytic_s(t, 0.0, 100.0, 0.0, 1000.0, 100.0)
    assert np.max(np.abs(tl.x_mm[on] - 10 - s_exp)) < 1e-6
    assert T == pytest.approx(1.1, abs=1e-12) and t[-1] == pytest.approx(1.1, abs=1e-9)
    assert tl.x_mm[-1] == 110.0
    v_exp = np.minimum.reduce([1000 * t, np.full_like(t, 100.0), 1000 * (1.1 - t)])
    assert np.max(np.abs(tl.v_mm_s[on] - v_exp)) < 1e-6


def test_triangle_profile_when_the_move_is_too_short_to_cruise():
    prof = _prof(max_accel_mm_s2=1000.0)
    tl, pr = plan_gcode("G1 X4 Y0 F6000\n", prof)
    mp = plan_moves(pr.moves, prof)
    vpeak = math.sqrt(1000.0 * 4.0)          # v^2 = a L for a symmetric triangle
    assert mp.v_cruise_mm_s[0] == pytest.approx(vpeak, abs=1e-9)
    assert mp.duration_s[0] == pytest.approx(2 * vpeak / 1000.0, abs=1e-9)
    s_exp, _ = _analytic_s(tl.t_s, 0.0, vpeak, 0.0, 1000.0, 4.0)
    assert np.max(np.abs(tl.x_mm - s_exp)) < 1e-6


def test_collinear_segments_plan_like_one_move():
    prof = _prof(max_accel_mm_s2=1000.0)
    one = plan_moves(parse_gcode("G1 X100 F6000\n").moves, prof).total_time_s
    many = "".join(f"G1 X{x} F6000\n" for x in range(1, 101))
    assert plan_moves(parse_gcode(many).moves, prof).total_time_s == pytest.approx(one, abs=1e-9)


def test_klipper_square_corner_velocity_published_formula():
    # Klipper docs: square_corner_velocity is the speed through a 90 degree corner.
    assert junction_speed_klipper_mm_s(90.0, 5.0, 3000.0) == pytest.approx(5.0, rel=1e-12)
    assert junction_speed_klipper_mm_s(90.0, 5.0, 500.0) == pytest.approx(5.0, rel=1e-12)
    assert junction_speed_klipper_mm_s(180.0, 5.0, 3000.0) == 0.0
    # 45 degree turn: v^2 = a jd s/(1-s), s = sin(67.5 deg)
    s = math.sin(math.radians(67.5))
    jd = 25 * (math.sqrt(2) - 1) / 3000
    assert junction_speed_klipper_mm_s(45.0, 5.0, 3000.0) == pytest.approx(math.sqrt(3000 * jd * s / (1 - s)))
    prof = _prof(square_corner_velocity_mm_s=5.0, max_accel_mm_s2=3000.0)
    mp = plan_moves(parse_gcode("G1 X50 Y0 F6000\nG1 X50 Y50\n").moves, prof)
    assert mp.v_end_mm_s[0] == pytest.approx(5.0, abs=1e-9)
    assert mp.v_start_mm_s[1] == pytest.approx(5.0, abs=1e-9)


def test_marlin_junction_deviation_and_rrf_jerk_corners():
    marlin = _prof("adventurer3", junction_deviation_mm=0.05, max_accel_mm_s2=500.0)
    mp = plan_moves(parse_gcode("G1 X50 Y0 F6000\nG1 X50 Y50\n").moves, marlin)
    s = math.sin(math.radians(45))
    assert mp.v_end_mm_s[0] == pytest.approx(math.sqrt(500 * 0.05 * s / (1 - s)), abs=1e-9)
    rrf = _prof("long_bowden", max_jerk_mm_s=10.0)
    mp = plan_moves(parse_gcode("G1 X50 Y0 F6000\nG1 X50 Y50\n").moves, rrf)
    assert mp.v_end_mm_s[0] == pytest.approx(10.0 / math.sqrt(2), abs=1e-9)
    # a reversal always stops
    mp = plan_moves(parse_gcode("G1 X50 Y0 F6000\nG1 X0 Y0\n").moves, marlin)
    assert mp.v_end_mm_s[0] == 0.0


def test_a_change_of_extrusion_rate_is_a_corner_for_the_extruder():
    """A straight line whose width steps: the extruder's speed jumps by v |r2 - r1| (r = E
    per mm of path), which each firmware limits its own way (patterns/planner.py)."""
    r1, r2 = 0.04, 0.10                              # filament mm per head mm
    gcode = f"M83\nG1 X50 Y0 E{50 * r1:.4f} F6000\nG1 X100 Y0 E{50 * r2:.4f}\n"
    # Klipper, klippy/kinematics/extruder.py calc_junction: v = icv / |dr|
    klipper = _prof("direct_drive", max_accel_mm_s2=3000.0, instantaneous_corner_velocity_mm_s=1.0)
    mp = plan_moves(parse_gcode(gcode).moves, klipper)
    assert mp.v_end_mm_s[0] == pytest.approx(1.0 / (r2 - r1), rel=1e-9)     # 16.7 mm/s, not 100
    assert mp.v_start_mm_s[1] == pytest.approx(1.0 / (r2 - r1), rel=1e-9)
    # the same line without the step goes straight through at full speed
    flat = f"M83\nG1 X50 Y0 E{50 * r1:.4f} F6000\nG1 X100 Y0 E{50 * r1:.4f}\n"
    assert plan_moves(parse_gcode(flat).moves, klipper).v_end_mm_s[0] == pytest.approx(100.0)
    # RRF (M566 E): v = e_jerk / |dr|; a retracting move across the junction: the larger speed
    rrf = _prof("long_bowden", max_jerk_mm_s=10.0, max_e_jerk_mm_s=2.0, max_accel_mm_s2=3000.0)
    assert plan_moves(parse_gcode(gcode).moves, rrf).v_end_mm_s[0] == pytest.approx(2.0 / (r2 - r1), rel=1e-9)
    wipe = f"M83\nG1 X50 Y0 E{50 * r1:.4f} F6000\nG1 X100 Y0 E-{50 * r2:.4f}\n"
    assert plan_moves(parse_gcode(wipe).moves, rrf).v_end_mm_s[0] == pytest.approx(2.0 / r2, rel=1e-9)
    # Marlin 2.1 junction deviation over X, Y, Z and E: the angle between (1, r1) and (1, r3);
    # a small step is nearly straight (v ~ 300 mm/s), a pre-pressure draw (r3 0.8) is not
    r3 = 0.8
    draw = f"M83\nG1 X50 Y0 E{50 * r1:.4f} F6000\nG1 X100 Y0 E{50 * r3:.4f}\n"
    marlin = _prof("ender3", junction_deviation_mm=0.08, max_accel_mm_s2=500.0, max_e_velocity_mm_s=200.0)
    cos_theta = -(1 + r1 * r3) / math.sqrt((1 + r1 ** 2) * (1 + r3 ** 2))
    sin_t2 = math.sqrt(0.5 * (1 - cos_theta))
    v = math.sqrt(500.0 * 0.08 * sin_t2 / (1 - sin_t2))
    assert v < 30.0
    assert plan_moves(parse_gcode(draw).moves, marlin).v_end_mm_s[0] == pytest.approx(v, rel=1e-9)
    # ... and a Marlin built with classic jerk (M205 X Y E) limits it like RRF
    d = load_profile("ender3").to_dict()
    del d["junction_deviation_mm"]
    d.update(max_jerk_mm_s=10.0, max_e_jerk_mm_s=5.0, max_e_velocity_mm_s=100.0)
    classic = profile_from_dict(d)
    assert plan_moves(parse_gcode(gcode).moves, classic).v_end_mm_s[0] == pytest.approx(5.0 / (r2 - r1), rel=1e-9)


def test_moves_klipper_refuses_are_found_with_their_line():
    """klippy/kinematics/extruder.py check_move: an XY move over max_extrude_cross_section
    (default 4 d^2 = 0.64 mm^2 for 0.4 mm) stops the print, unless it extrudes no more than
    d times the ratio; an extrude-only move over max_extrude_only_distance (50 mm) too."""
    from patterns.planner import klipper_refusals
    klipper = _prof("direct_drive")
    af = klipper.filament_area_mm2
    ratio = 0.64 / af                                  # filament mm per mm at the limit
    text = ("M83\nG1 X10 Y0 F3000\n"
            f"G1 X20 Y0 E{10 * 0.5 / af:.5f}\n"           # line 3: 0.5 mm^2, fine
            f"G1 X30 Y0 E{10 * 1.0 / af:.5f}\n"           # line 4: 1.0 mm^2: refused
            f"G1 X30.1 Y0 E{0.9 * 0.4 * ratio:.5f}\n"     # line 5: over the ratio but tiny: permitted
            "G1 E60 F300\n"                                # line 6: a 60 mm extrude-only move
            "G1 E-5\n")                                    # line 7: a retraction, fine
    got = klipper_refusals(parse_gcode(text, klipper).moves, klipper)
    assert [ln for ln, _ in got] == [4, 6]
    assert got[0][1] == "Move exceeds maximum extrusion (1.000mm^2 vs 0.640mm^2)"
    assert got[1][1] == "Extrude only move too long (60.000mm vs 50.000mm)"
    wider = _prof("direct_drive", max_extrude_cross_section_mm2=1.2, max_extrude_only_distance_mm=100.0)
    assert klipper_refusals(parse_gcode(text, wider).moves, wider) == []
    marlin = _prof("ender3")
    assert klipper_refusals(parse_gcode(text, marlin).moves, marlin) == []


def test_extruder_only_move_uses_extruder_limits_and_dwell_time():
    prof = _prof("adventurer3", max_e_velocity_mm_s=40.0, max_e_accel_mm_s2=1000.0)
    mp = plan_moves(parse_gcode("M83\nG1 E-2 F6000\nG4 P500\nG4 S1.5\n").moves, prof)
    # 2 mm at <= 40 mm/s, a = 1000: 0.04 s up (0.8 mm), 0.4 mm cruise (0.01 s), 0.04 s down
    assert mp.duration_s[0] == pytest.approx(0.09, abs=1e-9)
    assert list(mp.duration_s[1:]) == pytest.approx([0.5, 1.5])
    assert mp.total_time_s == pytest.approx(2.09)


def test_marlin_caps_xy_speed_by_extruder_speed():
    prof = _prof("ender3", max_e_velocity_mm_s=1.0)
    mp = plan_moves(parse_gcode("M83\nG1 X100 E10 F6000\n").moves, prof)
    assert mp.v_cruise_mm_s[0] == pytest.approx(10.0)     # E at 1 mm/s -> head 10 mm/s
    # Klipper caps only a move that retracts while it travels (a wipe), not one that extrudes
    klipper = _prof("direct_drive", max_e_velocity_mm_s=1.0)
    assert plan_moves(parse_gcode("M83\nG1 X100 E10 F6000\n").moves, klipper).v_cruise_mm_s[0] == pytest.approx(100.0)
    assert plan_moves(parse_gcode("M83\nG1 X100 E-10 F6000\n").moves, klipper).v_cruise_mm_s[0] == pytest.approx(10.0)


def test_timeline_sampling_and_commanded_volume_is_conserved():
    prof = load_profile("direct_drive")
    text = "M83\nG1 Z0.2 F600\nG1 X10 Y10 F9000\n" + "".join(
        f"G1 X{10 + 30 * math.cos(a):.3f} Y{10 + 30 * math.sin(a):.3f} E{0.03 + 0.02 * (i % 3):.4f} F{1200 + 600 * (i % 4)}\n"
        for i, a in enumerate(np.linspace(0, 6, 80))) + "G1 E-0.8 F2100\nG4 P200\nG1 X0 Y0 F9000\nG1 E0.8 F1800\n"
    tl, pr = plan_gcode(text, prof)
    assert np.all(np.diff(tl.t_s) <= 0.005 + 1e-12)
    step = np.sqrt(np.diff(tl.x_mm) ** 2 + np.diff(tl.y_mm) ** 2 + np.diff(tl.z_mm) ** 2)
    assert step.max() <= 0.25 + 1e-9
    assert np.all(np.diff(tl.t_s) > 0)
    # increments sum exactly to the commanded filament
    assert tl.e_mm[-1] - tl.e_mm[0] == pytest.approx(pr.moves.de_mm.sum(), abs=1e-12)
    # and the commanded flow integrates to the same volume (trapezoid rule on samples)
    af = prof.filament_area_mm2
    vol = np.trapezoid(tl.ve_mm_s * af, tl.t_s)
    assert vol == pytest.approx(pr.moves.de_mm.sum() * af, rel=2e-3)
    # every move boundary is a sample
    mp = plan_moves(pr.moves, prof)
    bounds = mp.t_start_s + mp.duration_s
    assert np.all(np.min(np.abs(tl.t_s[None, :] - bounds[:, None]), axis=1) < 1e-9)


def test_track_arc_length_and_labels():
    text = """M83
G1 X0 Y0 Z0.2 F3000
;TRACK id=7 kind=test
G1 X20 Y0 E1
G1 X20 Y0 E-0.5
G1 X20 Y10 E0
;END_TRACK
G1 X40 Y40
"""
    tl = plan(parse_gcode(text), load_profile("direct_drive"))
    on = tl.track == 7
    assert tl.s_mm[on][0] == 0.0 and tl.s_mm[on][-1] == pytest.approx(30.0)
    assert np.all(np.diff(tl.s_mm[on]) >= 0)
    assert np.all(np.isnan(tl.s_mm[~on]))
    # the retraction happens at s = 20 while the head is still
    retr = on & (tl.ve_mm_s < 0)
    assert np.allclose(tl.s_mm[retr], 20.0) and np.allclose(tl.v_mm_s[retr], 0.0)


def test_pa_events_get_program_times():
    prof = _prof(max_accel_mm_s2=1000.0)
    text = "M83\nG1 X100 F6000\nSET_PRESSURE_ADVANCE ADVANCE=0.04 SMOOTH_TIME=0.02\nG4 P250\nM900 K0.1\n"
    tl, pr = plan_gcode(text, prof)
    assert [(e.k_s, e.smooth_time_s) for e in pr.pa_events] == [(0.04, 0.02), (0.1, None)]
    assert [e.t_s for e in pr.pa_events] == pytest.approx([1.1, 1.35])
    assert tl.t_s[-1] == pytest.approx(1.35)
