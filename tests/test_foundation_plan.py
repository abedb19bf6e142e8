"""G-code -> manifest: labelled tracks from our writer, the realdata spiral test, the CLI."""
from pathlib import Path

import numpy as np
import pytest

from calib.cli import main
from fit.geometry import bead_area_mm2
from patterns.gcode_writer import GcodeWriter
from patterns.manifest import Manifest, sample_points
from patterns.plan import manifest_from_gcode

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
SPIRAL = REALDATA / "SpStartStopTest2_Te210Tp50Fe10Fc10Kf04Kb10Re15R.g"


def _labelled_program():
    w = GcodeWriter("direct_drive", layer_height_mm=0.25)
    w.header("plan test", {})
    w.set_z(0.25)
    w.travel(20, 20)
    w.begin_track(0, "prime")
    w.extrude_line(120, 20, 0.6, 30)
    w.end_track()
    w.travel(20, 40)
    w.begin_track(1, "test")
    w.extrude_line(70, 40, 0.45, 50)
    w.extrude_line(120, 40, 0.9, 50)
    w.move_with_e(140, 40, 0.0, 50)
    w.end_track()
    w.footer()
    return w.text()


def test_labelled_gcode_gives_commanded_widths_and_flows():
    man = manifest_from_gcode(_labelled_program(), "direct_drive")
    assert [(t.id, t.kind) for t in man.tracks] == [(0, "prime"), (1, "test")]
    tr = man.track(1)
    assert tr.length_mm == pytest.approx(120.0)
    # widths step (repeated vertex at x = 70), coasting part has width 0
    assert np.allclose(tr.interp("width_mm", [10, 40, 60, 90, 110]), [0.45, 0.45, 0.9, 0.9, 0.0], atol=2e-4)
    assert np.allclose(tr.height_mm, 0.25)
    q = tr.interp("flow_mm3_s", [25.0, 75.0])
    assert np.allclose(q, [bead_area_mm2(0.45, 0.25) * 50, bead_area_mm2(0.9, 0.25) * 50], rtol=1e-3)
    # stations get print times from the timeline, increasing along the track
    smp = sample_points(man)
    assert len(smp) == int(120 / 0.25) + 1 and np.all(np.isfinite(smp.t_s))
    assert np.all(np.diff(smp.t_s) > 0)


@pytest.mark.skipif(not SPIRAL.is_file(), reason="../shared/realdata not present")
def test_realdata_spiral_startstop_layout():
    """SpStartStopTest2: four test groups (w = 0.3, 0.4, 0.8, 1.6 mm at h = 0.3 mm, ve = 1 mm/s
    of filament for 3 s each), one spiral line per Re = 2.0, 2.4, ... 4.0 mm, so six lines per
    group in this G-code ("Test Line ... Re=" comments of the verbose file)."""
    man = manifest_from_gcode(SPIRAL.read_text(), "adventurer3")
    assert man.fiducials == []
    groups = {0.3: [], 0.4: [], 0.8: [], 1.6: []}   # the z = 0.2 prime line is not a test line
    for tr in man.test_tracks():
        # the author's bead model is a w x h rectangle: A / h is his nominal width
        w_rect = np.median(bead_area_mm2(tr.width_mm, tr.height_mm) / tr.height_mm)
        for w in groups:
            if abs(w_rect - w) < 0.02 * w and tr.length_mm > 12 and abs(tr.z_mm - 0.3) < 1e-6:
                groups[w].append(tr)
    assert {w: len(v) for w, v in groups.items()} == {0.3: 6, 0.4: 6, 0.8: 6, 1.6: 6}
    af = np.pi * 1.75 ** 2 / 4
    tl = man.timeline
    for w, trs in groups.items():
        for tr in trs:
            assert tr.height_mm[0] == pytest.approx(0.3) and tr.z_mm == pytest.approx(0.3)
            # 3 mm of filament per line: length * w * h = 3 * Af
            assert tr.length_mm * w * 0.3 == pytest.approx(3.0 * af, rel=0.01)
            assert np.median(tr.flow_mm3_s) == pytest.approx(1.0 * af, rel=0.01)
            on = tl.track == tr.id
            assert tl.t_s[on][-1] - tl.t_s[on][0] == pytest.approx(3.0, rel=0.03)
        # the six lines of a group are concentric spirals starting 2 mm apart in radius
        r0 = sorted(np.hypot(*tr.points_mm[0]) for tr in trs)
        assert np.allclose(np.diff(r0), 2.0, atol=0.15)
    # groups printed in order of width
    t_first = [min(tl.t_s[tl.track == tr.id][0] for tr in groups[w]) for w in (0.3, 0.4, 0.8, 1.6)]
    assert t_first == sorted(t_first)


@pytest.mark.skipif(not SPIRAL.is_file(), reason="../shared/realdata not present")
def test_calib_plan_cli_writes_manifest_and_timeline(tmp_path, capsys):
    out = tmp_path / "sp.manifest.json"
    assert main(["plan", str(SPIRAL), "--printer", "adventurer3", "-o", str(out)]) == 0
    man = Manifest.load(out)
    assert (tmp_path / "sp.timeline.npz").is_file()
    assert len(man.tracks) > 100 and man.printer["name"] == "adventurer3"
    assert man.timeline.e_mm[-1] == pytest.approx(268.8143, abs=1e-6)


def test_calib_plan_cli_bad_input_is_one_line_exit_2(tmp_path, capsys):
    g = tmp_path / "x.gcode"
    g.write_text("G1 X10 Y10 E1\n")
    assert main(["plan", str(g), "--printer", "no_such_printer"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("calib plan: error: unknown printer 'no_such_printer'") and "\n" not in err
    assert main(["plan", str(tmp_path / "missing.gcode"), "--printer", "adventurer3"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_track_height_label_gives_commanded_width_and_height_off_z_spacing():
    """A bead 0.3 mm high printed at z = 0.2 (first layer): the z levels say h = 0.2, the
    ;TRACK h= label says 0.3; the manifest must return the commanded w and h."""
    w = GcodeWriter("adventurer3", layer_height_mm=0.2)
    w.header("h label", {})
    w.set_z(0.2)
    w.travel(-40, -20)
    w.begin_track(0, "test", height_mm=0.3)
    w.extrude_line(0, -20, 0.55, 20, height_mm=0.3)
    w.extrude_line(40, -20, 0.7, 20, height_mm=0.15)    # height change inside the track
    w.end_track()
    w.travel(-40, -10)
    w.begin_track(1, "test")                             # default: the writer's 0.2 mm
    w.extrude_line(0, -10, 0.5, 20)
    w.end_track()
    w.footer()
    text = w.text()
    assert ";TRACK id=0 kind=test h=0.3" in text and ";HEIGHT h=0.15" in text
    assert ";TRACK id=1 kind=test h=0.2" in text
    man = manifest_from_gcode(text, "adventurer3")
    tr = man.track(0)
    assert np.allclose(tr.interp("width_mm", [10.0, 30.0, 50.0, 70.0]), [0.55, 0.55, 0.7, 0.7], atol=1e-4)
    assert np.allclose(tr.interp("height_mm", [10.0, 30.0, 50.0, 70.0]), [0.3, 0.3, 0.15, 0.15])
    assert tr.z_mm == pytest.approx(0.2)
    assert np.allclose(man.track(1).width_mm, 0.5, atol=1e-4) and np.allclose(man.track(1).height_mm, 0.2)
    # the same G-code without the labels falls back to the z spacing: wrong width, as documented
    bare = "\n".join(ln for ln in text.splitlines() if not ln.startswith((";TRACK", ";HEIGHT", ";END")))
    man2 = manifest_from_gcode(bare, "adventurer3")
    first = max(man2.tracks, key=lambda t: t.length_mm)
    assert np.allclose(first.height_mm, 0.2) and first.width_mm[0] > 0.55 + 0.05


def test_retract_pattern_manifest_keeps_each_design_width_and_height():
    """RetractTest lines are printed at h = 0.1 .. 0.3 mm: every planned test track carries
    the design's commanded width and height."""
    from patterns.builder import PATTERNS
    _, man = PATTERNS["retract"]("adventurer3", designs=[1], n_steps=3)
    tests = man.test_tracks()
    assert len(tests) == 3
    for tr in tests:
        wide = tr.width_mm > 0
        h = tr.params["height_mm"]
        assert np.allclose(tr.height_mm[wide], h)
        # the drawn part (at least) is at the design width
        assert np.isclose(tr.width_mm[wide], tr.params["width_mm"], atol=1e-4).sum() >= 2


def test_heights_come_from_what_is_under_the_path():
    """Lines straight on the bed at different Z (a test that varies h line by line) keep
    their Z as height; a second layer gets the Z spacing; a strand with nothing below
    it high up is a bridge (round strand, h = nozzle) with a warning."""
    from fit.geometry import bead_area_mm2, filament_area_mm2
    from patterns.plan import manifest_from_gcode

    af = filament_area_mm2(1.75)
    lines = ["G21", "G90", "M83", "G28"]

    def line(y, z, w=0.45, h=None, x0=20.0, x1=60.0):
        e = float(bead_area_mm2(w, h if h is not None else z)) * (x1 - x0) / af
        lines.extend([f"G0 Z{z + 1:.3f} F600", f"G0 X{x0} Y{y} F6000", f"G0 Z{z:.3f}",
                      f"G1 X{x1} Y{y} E{e:.5f} F1200"])
    for k, z in enumerate((0.20, 0.24, 0.28, 0.32)):
        line(20 + 5 * k, z)                    # each on the bed
    line(60, 0.2)
    line(60, 0.4, h=0.2)                       # stacked on the line below
    line(100, 5.0, h=0.4)                      # 5 mm up over nothing: a bridge
    man = manifest_from_gcode("\n".join(lines) + "\n", "ender3")
    hs = [round(float(np.median(t.height_mm)), 3) for t in man.tracks]
    ws = [round(float(np.median(t.width_mm)), 3) for t in man.tracks]
    assert hs[:4] == [0.2, 0.24, 0.28, 0.32] and ws[:4] == [0.45] * 4
    assert hs[5] == 0.2 and ws[5] == 0.45
    assert hs[6] == 0.4
    assert any("bridges or prints in the air" in w for w in man.pattern["warnings"])


def test_plan_picks_the_test_tracks(tmp_path, capsys):
    """Third-party G-code: the prime line along the bed edge and a closed ring are not
    test tracks by default; --tracks and --z-range-mm choose explicitly."""
    from calib.cli import main
    from patterns.manifest import Manifest

    g = ["G21", "G90", "M83", "G28", "G0 Z0.2 F600",
         "G0 X5 Y20 F6000", "G1 X5 Y180 E8 F1500",                          # prime, x = 5 mm
         "G0 X50 Y50", "G1 X100 Y50 E2.5 F1200",                              # test line
         "G0 X50 Y60", "G1 X100 Y60 E2.5 F1200",                              # test line
         "G0 X120 Y100", "G1 X140 Y100 E1", "G1 X140 Y120 E1", "G1 X120 Y120 E1",
         "G1 X120 Y100 E1",                                                   # closed ring
         "G0 Z0.4", "G0 X50 Y70", "G1 X100 Y70 E2.5 F1200"]                   # line at z 0.4
    src = tmp_path / "third.gcode"
    src.write_text("\n".join(g) + "\n")
    out = tmp_path / "m.json"
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out)]) == 0
    kinds = {t.id: t.kind for t in Manifest.load(out).tracks}
    assert kinds == {0: "prime", 1: "test", 2: "test", 3: "other", 4: "test"}
    err = capsys.readouterr().err
    assert "prime line" in err and "closed loop" in err
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--tracks", "1,3-4"]) == 0
    kinds = {t.id: t.kind for t in Manifest.load(out).tracks}
    assert [k for k, v in kinds.items() if v == "test"] == [1, 3, 4]
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--z-range-mm", "0.3,0.5"]) == 0
    assert [t.id for t in Manifest.load(out).tracks if t.kind == "test"] == [4]
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--tracks", "x"]) == 2
    # a selection of no track is no manifest: one line, exit 2, nothing written
    capsys.readouterr()
    out.unlink()
    for sel in (["--tracks", "-1"], ["--tracks", "99"], ["--z-range-mm", "5,6"]):
        assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), *sel]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "no test track" in err[0] and sel[0] in err[0] and not out.exists()
    # an id no track has, beside ones that exist, is said
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--tracks", "4,99"]) == 0
    assert "--tracks names id no track has: 99" in capsys.readouterr().err


def test_plan_picks_test_tracks_by_their_gcode_comments(tmp_path, capsys):
    """--tracks-comment REGEX: a slicer's ;TYPE: line before a track, or a comment on its
    moves, chooses the test tracks; a bad regex or one that matches nothing is one line."""
    from calib.cli import main
    from patterns.manifest import Manifest

    g = ["G21", "G90", "M83", "G28", "G0 Z0.2 F600",
         ";TYPE:Skirt", "G0 X40 Y40 F6000", "G1 X150 Y40 E5 F1500",
         ";TYPE:External perimeter", "G0 X50 Y50", "G1 X100 Y50 E2.5 F1200",
         ";TYPE:Solid infill", "G0 X50 Y60", "G1 X100 Y60 E2.5 F1200",
         "G0 X50 Y70", "G1 X100 Y70 E2.5 F1200 ; pa test line 7",
         ";TYPE:External perimeter", "G0 X50 Y80", "G1 X100 Y80 E2.5 F1200"]
    src = tmp_path / "sliced.gcode"
    src.write_text("\n".join(g) + "\n")
    out = tmp_path / "m.json"

    def tests(*extra):
        assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), *extra]) == 0
        return [t.id for t in Manifest.load(out).tracks if t.kind == "test"]

    assert tests("--tracks-comment", "type:external perimeter") == [1, 4]
    assert tests("--tracks-comment", r"test line \d+") == [3]
    assert tests("--tracks-comment", "perimeter|test line", "--tracks", "3-4") == [3, 4]
    capsys.readouterr()
    for bad, msg in (("[unclosed", "is not a regular expression"), ("TYPE:Bridge", "matches no track")):
        assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--tracks-comment", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0]


def test_plan_leaves_printed_labels_out_of_the_test(tmp_path, capsys):
    """A third-party test labels its lines ("Kb 20", as the realdata prints do): the
    strokes turn sharply within a few mm (straight ones like "1" sit beside those) and are
    not test tracks; the lines stay. A spiral test (it turns, but over tens of mm) stays."""
    from calib.cli import main
    from patterns.font import place_strokes, text_strokes

    g = ["G21", "G90", "M83", "G28", "G0 Z0.2 F600"]
    for y in (50, 60):                                                       # test lines
        g += [f"G0 X50 Y{y}", f"G1 X100 Y{y} E2.5 F1200"]
    ang = np.linspace(0, 4 * np.pi, 80)                                     # a spiral test
    sp = np.column_stack([150 + (3 + 2 * ang) * np.cos(ang), 100 + (3 + 2 * ang) * np.sin(ang)])
    g += [f"G0 X{sp[0, 0]:.3f} Y{sp[0, 1]:.3f}"] + [f"G1 X{x:.3f} Y{y:.3f} E0.1" for x, y in sp[1:]]
    n_label = 0
    for stroke in place_strokes(text_strokes("Kb 20", 3.5), (105, 58)):  # label beside the lines
        g += [f"G0 X{stroke[0, 0]:.3f} Y{stroke[0, 1]:.3f}"]
        g += [f"G1 X{x:.3f} Y{y:.3f} E0.05" for x, y in stroke[1:]]
        n_label += 1
    src = tmp_path / "labelled.gcode"
    src.write_text("\n".join(g) + "\n")
    out = tmp_path / "m.json"
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out)]) == 0
    tracks = Manifest.load(out).tracks
    assert len(tracks) == 3 + n_label
    assert [t.id for t in tracks if t.kind == "test"] == [0, 1, 2]
    assert "tracks turn like letters or digits" in capsys.readouterr().err    # (strokes < 3 mm: "other" anyway)
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--keep-all"]) == 0
    assert sum(t.kind == "test" for t in Manifest.load(out).tracks) > 3


def _plan(tmp_path, capsys, lines):
    """`calib plan` of G-code ``lines`` on the ender3: (tracks, stderr, G-code path, manifest path)."""
    from calib.cli import main

    src, out = tmp_path / "test.gcode", tmp_path / "m.json"
    src.write_text("\n".join(lines) + "\n")
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out)]) == 0
    return Manifest.load(out).tracks, capsys.readouterr().err, src, out


def test_plan_leaves_ruler_and_dial_ticks_out_of_the_test(tmp_path, capsys):
    """A third-party test with a ruler (9 ticks of 4 mm and 3 of 6 mm, as StartStopTestPLA1
    has 44 + 44) and a dial (10 radial ticks of 3.5 mm, as SpStartStopTest2 has 24 of 3): the ticks
    are "other"; the test lines stay, and so do short strokes of varying length (the
    warm-up strokes beside SpStartStopTest2's lines) and a family too small to be a ruler."""
    from calib.cli import main

    g = ["G21", "G90", "M83", "G28", "G0 Z0.2 F600"]
    for y in (50, 60):                                                       # test lines
        g += [f"G0 X50 Y{y}", f"G1 X100 Y{y} E2.5 F1200"]
    for k in range(12):                                                      # ruler
        x = 50 + 5 * k
        g += [f"G0 X{x} Y30", f"G1 X{x} Y{34 if k % 5 else 36} E0.2 F1200"]
    for k in range(10):                                                      # dial
        a = 2 * np.pi * k / 10
        p, q = (150 + 20 * np.cos(a), 100 + 20 * np.sin(a)), (150 + 23.5 * np.cos(a), 100 + 23.5 * np.sin(a))
        g += [f"G0 X{p[0]:.3f} Y{p[1]:.3f}", f"G1 X{q[0]:.3f} Y{q[1]:.3f} E0.175 F1200"]
    for k, length in enumerate((3.9, 4.3, 4.7, 5.1, 5.5, 5.9)):            # warm-up strokes
        g += [f"G0 X{60 + 10 * k} Y80", f"G1 X{60 + 10 * k + length:.2f} Y80 E{0.05 * length:.3f} F300"]
    tracks, err, src, out = _plan(tmp_path, capsys, g)
    test = [t.id for t in tracks if t.kind == "test"]
    # 0, 1 the lines; 2-13 the ruler (two of its 6 mm ticks, a family of 3, stay); 14-23
    # the dial; 24-29 the warm-up strokes
    assert test == [0, 1, 2, 7, 12] + list(range(24, 30))
    assert "19 tracks are ruler or dial ticks" in err
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--keep-all"]) == 0
    assert sum(t.kind == "test" for t in Manifest.load(out).tracks) == 30


def test_plan_leaves_a_rulers_base_line_out_and_reads_a_lines_width_over_its_length(tmp_path, capsys):
    """StartStopTestPLA1 draws each ruler as a 90 mm line with its ticks standing on it: the
    line is the ruler's, not a test line (1180 of the print's 2200 `crossing` stations were
    on four of them). A test line whose first 1 mm restores the pressure at 30x the flow
    (the same print) has the commanded width of the rest; over-wide lines all through get
    one warning line for all of them."""
    from calib.cli import main

    g = ["G21", "G90", "M83", "G28", "G0 Z0.2 F600"]
    g += ["G0 X45 Y30", "G1 X105 Y30 E3 F1200"]                          # 0: the ruler's line
    for k in range(12):                                                   # 1-12: ticks on it
        g += [f"G0 X{50 + 5 * k} Y30", f"G1 X{50 + 5 * k} Y34 E0.2 F1200"]
    g += ["G0 X45 Y36", "G1 X105 Y36 E3 F1200"]                           # 13: tick ends 2 mm off
    g += ["G0 X50 Y50", "G1 X51 Y50 E1.5 F60", "G1 X65 Y50 E0.7 F1200"]  # 14: restore blob, then the line
    for y in (70, 80):                                                    # 15, 16: 9 mm "beads"
        g += [f"G0 X50 Y{y}", f"G1 X100 Y{y} E40 F1200"]
    tracks, err, src, out = _plan(tmp_path, capsys, g)
    assert [t.id for t in tracks if t.kind == "test"] == [13, 14, 15, 16]
    assert "track 0 is the line ruler ticks stand on (>= 8 ticks touch each), not test lines: 0;" in err
    assert "track 14" not in err                                          # 0.42 mm over 14 of its 15 mm
    lines = [ln for ln in err.splitlines() if "implausible" in ln]
    assert len(lines) == 1 and lines[0].count("2 tracks have commanded widths") == 1 and "15-16" in lines[0]
    assert main(["plan", str(src), "--printer", "ender3", "-o", str(out), "--tracks", "0,13"]) == 0
    assert [t.id for t in Manifest.load(out).tracks if t.kind == "test"] == [0, 13]
