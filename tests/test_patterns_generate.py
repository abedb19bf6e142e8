"""The five test patterns: bed bounds, fiducials that decode, no overlaps, round trip
through the G-code parser/planner, spiral steps off the angle, exponential feed ramp."""
from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from calib.errors import UserError
from patterns import font, layout
from patterns.builder import PATTERNS
from patterns.plan import manifest_from_gcode
from patterns.profile import load_profile, profile_from_dict
from patterns.stop_mid_path import exp_feed_ramp

PROFILES = ("adventurer3", "long_bowden", "direct_drive")
NAMES = ("spiral-step", "stop-mid-path", "retract", "start-stop", "probe")


@functools.lru_cache(maxsize=None)
def generated(name, printer):
    return PATTERNS[name](load_profile(printer))


def _render_fiducials(manifest, px_mm=8.0):
    """Rasterise the fiducial tracks (beads at their commanded width) into a white-on-black image."""
    tr = [t for t in manifest.tracks if t.kind == "fiducial"]
    allp = np.concatenate([t.points_mm for t in tr])
    lo, hi = allp.min(0) - 10, allp.max(0) + 10
    w, h = np.ceil((hi - lo) * px_mm).astype(int)
    img = np.zeros((h, w), np.uint8)
    to_px = lambda p: ((p[:, 0] - lo[0]) * px_mm, (hi[1] - p[:, 1]) * px_mm)  # noqa: E731  v points down
    for t in tr:
        u, v = to_px(t.points_mm)
        for i in range(len(u) - 1):
            wi = max(t.width_mm[i], t.width_mm[i + 1])
            if wi > 0:
                cv2.line(img, (int(round(u[i] * 16)), int(round(v[i] * 16))),
                         (int(round(u[i + 1] * 16)), int(round(v[i + 1] * 16))), 255,
                         max(1, int(round(wi * px_mm))), cv2.LINE_AA, 4)
    return img, lo, hi


def _detect(img, inverted):
    params = cv2.aruco.DetectorParameters()
    params.detectInvertedMarker = inverted
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids, _ = det.detectMarkers(img)
    return corners, (ids.ravel().tolist() if ids is not None else [])


@pytest.mark.parametrize("printer", PROFILES)
@pytest.mark.parametrize("name", NAMES)
def test_pattern_in_bed_no_overlap_and_fiducials_decode(name, printer):
    gcode, m = generated(name, printer)
    prof = load_profile(printer)
    tl = m.timeline
    assert prof.in_bed(tl.x_mm, tl.y_mm).all(), "a planned move leaves the bed"
    assert all(prof.in_bed(t.points_mm[:, 0], t.points_mm[:, 1]).all() for t in m.tracks)
    kinds = {t.kind for t in m.tracks}
    assert {"test", "fiducial", "ruler", "label", "prime"} <= kinds
    assert m.pattern["name"] == name and m.pattern["params"]
    assert all(t.params for t in m.test_tracks())
    assert layout.overlapping_tracks(m.tracks) == []
    assert len(m.fiducials) >= 4
    img, lo, hi = _render_fiducials(m)
    for inverted, image in ((False, img), (True, 255 - img)):
        corners, ids = _detect(image, inverted)
        assert sorted(ids) == sorted(f.id for f in m.fiducials)
        for c, i in zip(corners, ids):
            c = c.reshape(4, 2)
            mm = np.column_stack([lo[0] + (c[:, 0] + 0.5) / 8.0, hi[1] - (c[:, 1] + 0.5) / 8.0])
            ref = np.asarray(next(f for f in m.fiducials if f.id == i).corners_mm)
            assert np.abs(mm - ref).max() < 0.35, (i, mm, ref)   # ~ 3 px at 8 px/mm


@pytest.mark.parametrize("name", NAMES)
def test_pattern_parses_back_to_its_manifest(name):
    gcode, m = generated(name, "adventurer3")
    again = manifest_from_gcode(gcode, "adventurer3")
    assert [t.id for t in again.tracks] == [t.id for t in m.tracks]
    assert [t.kind for t in again.tracks] == [t.kind for t in m.tracks]
    for a, b in zip(again.tracks, m.tracks):
        assert a.length_mm == pytest.approx(b.length_mm, abs=1e-6)
    np.testing.assert_allclose(again.timeline.t_s, m.timeline.t_s)
    np.testing.assert_allclose(again.timeline.e_mm, m.timeline.e_mm)


def test_spiral_steps_not_synchronised_with_angle():
    _, m = generated("spiral-step", "adventurer3")
    for tr in m.test_tracks():
        p = tr.params
        pos, _ = tr.at(np.asarray(p["step_boundaries_mm"]))
        ang = np.arctan2(pos[:, 1] - p["center_mm"][1], pos[:, 0] - p["center_mm"][0])
        assert layout.steps_angles_spread(ang) < 0.35          # far from all at one angle (R = 1)
        d = np.abs(np.angle(np.exp(1j * np.diff(ang))))
        assert np.median(d) > np.deg2rad(10)
        # The width really steps at those boundaries (commanded widths at both levels).
        w = tr.interp("width_mm", np.asarray(p["step_boundaries_mm"]) + 1.0)
        assert set(np.round(w, 3)) == set(np.round(p["widths_mm"], 3))


def test_spiral_steps_keep_the_head_speed_on_klipper():
    """A width step is a corner for Klipper's extruder (instantaneous_corner_velocity 1 mm/s):
    taken at once, 0.8 -> 0.35 mm at 40 mm/s slowed the head to 27 mm/s. The pattern takes it
    in sub-steps of at most 0.9 mm/s of extruder speed each, 0.05 mm apart: the head keeps
    40 mm/s through every step, and the width still steps within 0.15 mm."""
    from patterns import spiral_step
    from patterns.gcode_parser import parse_gcode
    from patterns.planner import plan_moves

    prof = load_profile("direct_drive")
    text, man = spiral_step.generate(prof, speeds_mm_s=(40.0,), n_steps=4, step_s=(2.0,),
                                     widths_mm=(0.35, 0.8))[:2]
    mv = parse_gcode(text, prof).moves
    mp = plan_moves(mv, prof)
    (tr,) = [t for t in man.tracks if t.kind == "test"]
    on = np.flatnonzero(mv.track == tr.id)
    r = mv.de_mm[on] / mv.xyz_length_mm[on]
    jumps = np.abs(np.diff(r)) * 40.0
    assert jumps.max() <= 0.9 + 1e-9 and (jumps > 0.5).sum() >= 3 * 2     # 3 steps, >= 2 sub-steps each
    # planned as if the extruder set no limit: the same speeds everywhere (the spiral's own
    # curvature slows its inner turns a little, 37 mm/s, either way)
    free = profile_from_dict({**prof.to_dict(), "instantaneous_corner_velocity_mm_s": 1e6})
    np.testing.assert_allclose(mp.v_start_mm_s[on], plan_moves(mv, free).v_start_mm_s[on], rtol=1e-12)
    # the width still steps: every move at a rate between the two levels is a 0.05 mm sub-step
    lo, hi = r.min(), r.max()
    between = (r > lo * 1.02) & (r < hi * 0.98)        # E is written to 5 decimals
    assert between.sum() >= 3 and np.all(mv.xyz_length_mm[on][between] <= 0.051)     # XY to 3 decimals


def test_stop_mid_path_feed_follows_exponential():
    v0, tau = 40.0, 0.3
    t, s, v = exp_feed_ramp(v0, tau)
    np.testing.assert_allclose(s, v0 * tau * (1 - np.exp(-t / tau)))
    _, m = generated("stop-mid-path", "adventurer3")
    tr = next(t for t in m.test_tracks() if t.params["variant"] == "exp"
              and t.params["speed_mm_s"] == 40.0 and t.params["tau_guess_s"] > 0.2)
    tau = tr.params["tau_guess_s"]
    tl = m.timeline
    on = (tl.track == tr.id) & (tl.s_mm >= tr.params["stop_s_mm"])
    t_stop = tl.t_s[on][0]
    t_rel, s_rel = tl.t_s[on] - t_stop, tl.s_mm[on] - tr.params["stop_s_mm"]
    assert np.all(tl.ve_mm_s[on][1:] == 0) or np.abs(tl.ve_mm_s[on][2:]).max() < 1e-9
    # Segment speeds are the ramp's means: position matches the exponential within a few %
    # of the coast length once the planner's finite deceleration has caught up.
    model = 40.0 * tau * (1 - np.exp(-t_rel / tau))
    late = t_rel > 0.5 * tau
    assert np.abs(s_rel[late] - model[late]).max() < 0.05 * 40.0 * tau


def test_stop_mid_path_widths_alternate_over_the_lines():
    """Two widths (mm) alternate over the lines in print order; each line's commanded width,
    E per mm (bead area A(w, h) / filament area) and flow (A v0, mm^3/s) are its own."""
    from fit.geometry import bead_area_mm2

    prof = load_profile("adventurer3")
    _, m = PATTERNS["stop-mid-path"](prof, width_mm=(0.48, 1.0))
    tests = m.test_tracks()
    assert len(tests) == 10 and m.pattern["params"]["widths_mm"] == [0.48, 1.0]
    assert [t.params["width_mm"] for t in tests] == [0.48, 1.0] * 5
    tl = m.timeline
    af = np.pi * prof.filament_diameter_mm ** 2 / 4
    for t in tests[:2]:
        w = t.params["width_mm"]
        assert t.params["flow_mm3_s"] == pytest.approx(bead_area_mm2(w, 0.2) * t.params["speed_mm_s"])
        on = (tl.track == t.id) & (tl.s_mm > 5.0) & (tl.s_mm < t.params["stop_s_mm"] - 5.0)
        assert np.median(tl.ve_mm_s[on] / tl.v_mm_s[on]) * af == pytest.approx(bead_area_mm2(w, 0.2), rel=1e-3)
    with pytest.raises(UserError, match="--width must be > 0"):
        PATTERNS["stop-mid-path"](prof, width_mm=(0.48, float("nan")))


def test_start_stop_restores_scale_with_the_filament_path():
    # seed 001's own sweep on the author's Adventurer 3; the advance is pressure times the
    # path's compliance, which grows with the Bowden length (seed 000: tau ~ L)
    from patterns.start_stop import SEED_RE_MM, default_re_mm

    adv3 = default_re_mm(load_profile("adventurer3"))
    assert adv3 == SEED_RE_MM
    assert np.allclose(default_re_mm(load_profile("ender3")), 2 * np.asarray(SEED_RE_MM))   # 400 mm tube
    # a direct drive's advance at 1 mm/s is tenths of a mm: restoring 2-4 mm buries the rings
    dd = default_re_mm(load_profile("direct_drive"))
    assert 0.1 <= min(dd) < max(dd) <= 0.5
    _, man = PATTERNS["start-stop"]("direct_drive")
    assert man.pattern["params"]["re_mm"] == list(dd)
    restores = sorted({t.params["restore_mm"] for t in man.test_tracks()})
    assert restores == list(dd)
    # RetractTest's 1 mm restore likewise
    for name, re_mm in (("adventurer3", 1.0), ("direct_drive", 0.1), ("ender3", 2.0)):
        _, man = PATTERNS["retract"](name, designs=[1], n_steps=2)
        assert {t.params["restore_mm"] for t in man.test_tracks()} == {re_mm}


def test_overflow_is_a_user_error_naming_pattern_and_size():
    with pytest.raises(UserError, match=r"spiral-step needs \d+ mm in y but the bed is 150 mm: reduce --speeds"):
        PATTERNS["spiral-step"](load_profile("adventurer3"), speeds_mm_s=(20, 40, 60))


def test_font_covers_labels_and_fiducial_bits():
    for ch in "0123456789abcdefghijklmnopqrstuvwxyz.=-/:":
        assert font.supported(ch)
    assert font.text_width_mm("10", 6.0) == pytest.approx(4 + 5.5)
    from patterns.fiducials import plan_fiducial, printed_bits
    bits = printed_bits(7)
    assert bits.shape == (8, 8) and bits[0].all() and bits[1, 1:7].sum() == 0
    fp = plan_fiducial(7, (10.0, 20.0), 2.0, 0.5)
    assert fp.fiducial.corners_mm[0] == [12.0, 34.0]          # TL = (x0, y0 + size)
    # The serpentines cover every white cell and never put plastic on a black one: sample the
    # cells on a fine grid; a point is covered when a chain's centre line is within w/2.
    segs = np.vstack([np.hstack([c[:-1], c[1:]]) for c in fp.chains_mm])
    g = np.stack(np.meshgrid(np.arange(10.02, 26.0, 0.07), np.arange(20.02, 36.0, 0.07)), -1).reshape(-1, 2)
    a, b = segs[:, :2], segs[:, 2:]
    ab = b - a
    t = np.clip(np.einsum("pkd,kd->pk", g[:, None] - a[None], ab) / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
    dist = np.linalg.norm(g[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1)
    def is_white(p):
        inside = (p[:, 0] > 10.0) & (p[:, 0] < 26.0) & (p[:, 1] > 20.0) & (p[:, 1] < 36.0)
        col = np.clip(((p[:, 0] - 10.0) // 2).astype(int), 0, 7)
        row = 7 - np.clip(((p[:, 1] - 20.0) // 2).astype(int), 0, 7)
        return inside & (bits[row, col] == 1)

    white = is_white(g)
    # round bead ends leave notches at a white region's edge (as on a real print): every
    # white point >= 0.2 mm from the region's edge must be under a bead
    interior = white.copy()
    for d in ((0.2, 0), (-0.2, 0), (0, 0.2), (0, -0.2), (0.2, 0.2), (-0.2, -0.2), (0.2, -0.2), (-0.2, 0.2)):
        interior &= is_white(g + np.array(d))
    assert dist[interior].max() <= 0.26, g[interior][np.argmax(dist[interior])]   # 0.25 + cap notch
    assert np.all(dist[~white] >= 0.25 - 1e-6)                 # no bead reaches into a black cell
    # neighbouring lines of a cell row overlap by >= 10 % of the width; chains turn only in white
    ys = np.unique(np.round(np.concatenate([c[:, 1] for c in fp.chains_mm]), 6))
    in_row = np.diff(ys)[np.diff(ys) < 0.5 - 1e-6]
    assert len(in_row) and in_row.max() <= 0.9 * 0.5 + 1e-9
    assert len(fp.chains_mm) < 10                               # few starts, not one per run


@pytest.mark.parametrize("printer", ["adventurer3", "direct_drive"])
def test_stop_mid_path_wizard_tells_where_to_hold_the_card(printer):
    """Before each wizard line: M117 'Hold card at X Y' naming the middle of the wipe move
    (5 mm past the stop), a WIPER comment right before that wipe move, and 'Remove card'
    after the retraction; the G-code still parses back to the same tracks."""
    gcode, m = PATTERNS["stop-mid-path"](load_profile(printer), speeds_mm_s=[20.0], variants=["wizard"])
    lines = gcode.splitlines()
    holds = [i for i, ln in enumerate(lines) if ln.startswith("M117 Hold card at X")]
    tests = m.test_tracks()
    assert len(holds) == len(tests) == 1
    tr = tests[0]
    x, y = (float(v[1:]) for v in lines[holds[0]].split()[-2:])
    assert [x, y] == tr.params["card_xy_mm"]
    x_stop = tr.points_mm[0, 0] + tr.params["stop_s_mm"]
    assert x == pytest.approx(x_stop + 5.0, abs=0.06) and y == pytest.approx(tr.points_mm[0, 1], abs=0.06)
    # order: message, track label, ... WIPER comment, the zero-E wipe through (x, y), dwell, remove card
    i_track = next(i for i, ln in enumerate(lines) if ln.startswith(f";TRACK id={tr.id} "))
    i_wiper = next(i for i, ln in enumerate(lines) if ln.startswith("; WIPER"))
    i_remove = next(i for i, ln in enumerate(lines) if ln == "M117 Remove card")
    assert holds[0] < i_track < i_wiper < i_remove
    wipe = lines[i_wiper + 1]
    assert wipe.startswith("G1 X") and float(wipe.split("X")[1].split()[0]) > x
    assert any(ln.startswith("G4 P3000") for ln in lines[i_wiper:i_remove])
    m2 = manifest_from_gcode(gcode, printer)
    assert np.allclose(m2.track(tr.id).points_mm, tr.points_mm)
