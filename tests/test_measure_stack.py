"""Several pictures of one print, one widths table (measure/stack.py): each picture measured
on its own, each station the mean of its valid readings."""
import json

import numpy as np
import pytest

from calib.cli import main
from measure.stack import combine_tables, combined_calibration
from measure.table import WidthTable


def _table(truth, noise_mm, rng, valid, offset_mm=0.0, flag_invalid="fit"):
    n = len(truth)
    w = truth + rng.normal(0.0, noise_mm, n) - offset_mm
    flag = np.where(valid, "", flag_invalid).astype(object)
    w = np.where(valid, w, np.where(flag == "missing", 0.0, np.nan))
    sd = np.where(valid, noise_mm, np.nan)
    return WidthTable(track=np.repeat([1, 2], n // 2), s_mm=np.tile(np.arange(n // 2) * 0.25, 2),
                      x_mm=np.zeros(n), y_mm=np.zeros(n), t_s=np.arange(n) * 0.01, width_mm=w,
                      width_sd_mm=sd, valid=valid, flag=flag, width_sd_own_mm=sd)


def test_a_station_is_the_mean_of_the_valid_readings_where_most_pictures_read_it():
    """Three pictures whose errors are independent (sd 30 um): where all three read a
    station its width is their mean and errs 30 / sqrt(3) um; a station read by one picture
    only is not valid; where most pictures saw no bead it is `missing`, width 0. The
    reported sds hold the combined errors (68 % within 1 sd)."""
    rng = np.random.default_rng(3)
    n = 4000
    truth = np.tile(np.linspace(0.3, 1.2, n // 2), 2)
    valid = np.ones((3, n), bool)
    valid[1:, :200] = False                 # read by one picture of three
    valid[2, 200:400] = False               # by two of three
    flags = ["fit", "fit", "fit"]
    tables = [_table(truth, 0.03, rng, valid[i], flag_invalid=flags[i]) for i in range(3)]
    tables[1].flag[100:200] = "missing"
    tables[2].flag[100:200] = "missing"
    comb, info = combine_tables(tables)
    assert not comb.valid[:200].any() and comb.valid[200:].all()
    assert (comb.flag[100:200] == "missing").all() and (comb.width_mm[100:200] == 0).all()
    assert (comb.flag[:100] == "fit").all()
    mean3 = np.mean([t.width_mm[400:] for t in tables], axis=0)
    np.testing.assert_allclose(comb.width_mm[400:], mean3)
    np.testing.assert_allclose(comb.width_mm[200:400], np.mean([t.width_mm[200:400] for t in tables[:2]], axis=0))
    err = comb.width_mm[400:] - truth[400:]
    assert np.std(err) == pytest.approx(0.03 / np.sqrt(3), rel=0.08)
    within = np.mean(np.abs(comb.width_mm[200:] - truth[200:]) <= comb.width_sd_mm[200:])
    assert 0.6 <= within <= 0.76
    # the stations read twice carry the larger sd
    assert np.median(comb.width_sd_mm[200:400]) > 1.15 * np.median(comb.width_sd_mm[400:])
    assert info["pictures"] == 3 and info["valid_per_picture"] == [n, n - 200, n - 400]


def test_what_the_pictures_share_does_not_average_out_and_the_sd_says_so():
    """Each reading errs by a part every picture shares (20 um: the plate's grain under the
    bead) and a part of its own (40 um: the specks), each sd the whole 44.7 um. The own
    share r = 0.8 is read from the readings' scatter about their mean, and the mean of 5
    errs sqrt(20^2 + 40^2 / 5) = 26.8 um, which its sd says (sqrt(mean sd^2 / 5) = 20 um
    would not)."""
    from measure.stack import own_share

    rng = np.random.default_rng(5)
    n = 4000
    truth = np.tile(np.linspace(0.3, 1.2, n // 2), 2)
    shared = rng.normal(0.0, 0.020, n)
    tables = [_table(truth + shared, 0.040, rng, np.ones(n, bool)) for _ in range(5)]
    for t in tables:
        t.width_sd_mm[:] = np.hypot(0.020, 0.040)
    W = np.array([t.width_mm for t in tables])
    S = np.array([t.width_sd_mm for t in tables])
    assert own_share(W, S, np.ones_like(W, bool)) == pytest.approx(0.8, abs=0.06)
    comb, info = combine_tables(tables)
    err = comb.width_mm - truth
    assert np.std(err) == pytest.approx(np.sqrt(0.02 ** 2 + 0.04 ** 2 / 5), rel=0.06)
    assert np.median(comb.width_sd_mm) == pytest.approx(np.sqrt(0.02 ** 2 + 0.04 ** 2 / 5), rel=0.1)
    assert 0.6 <= np.mean(np.abs(err) <= comb.width_sd_mm) <= 0.76


def test_pictures_of_different_patterns_are_not_combined():
    rng = np.random.default_rng(0)
    a = _table(np.full(100, 0.5), 0.01, rng, np.ones(100, bool))
    b = a.subset(np.arange(100) < 90)
    with pytest.raises(ValueError, match="same stations"):
        combine_tables([a, b])


def test_offsets_applied_in_every_picture_are_applied_once_to_the_mean():
    """Each picture's widths were corrected by its own reference's offset: the mean is taken
    of the apparent widths and corrected by the mean offset, whose sd is the pictures' RMS
    sd (their references are one print). Where a picture's offset was not applied none is,
    and the offsets said become the fit's prior."""
    rng = np.random.default_rng(1)
    truth = np.full(400, 0.6)
    apparent = truth - 0.04
    blocks = [{"applied": True, "prior_ok": False, "offset_mm": -0.040 + d, "offset_sd_mm": sd}
              for d, sd in ((0.002, 0.004), (-0.001, 0.006), (0.0, 0.005))]
    tables = [_table(apparent, 0.002, rng, np.ones(400, bool), offset_mm=b["offset_mm"]) for b in blocks]
    cal = combined_calibration(blocks)
    assert cal["applied"] and cal["offset_mm"] == pytest.approx(np.mean([b["offset_mm"] for b in blocks]))
    assert cal["offset_sd_mm"] == pytest.approx(np.sqrt(np.mean([0.004 ** 2, 0.006 ** 2, 0.005 ** 2])))
    comb, _ = combine_tables(tables, [b["offset_mm"] for b in blocks])
    # back to apparent widths: each picture's offset added back before the mean
    np.testing.assert_allclose(comb.width_mm, np.mean([t.width_mm + b["offset_mm"] for t, b in zip(tables, blocks)], 0))
    assert abs(np.mean(comb.width_mm) - 0.56) < 0.001
    blocks[1] = {"applied": False, "prior_ok": True, "offset_mm": -0.035, "offset_sd_mm": 0.015}
    mixed = combined_calibration(blocks)
    assert not mixed["applied"] and mixed["prior_ok"]
    assert mixed["offset_mm"] == pytest.approx(np.mean([-0.038, -0.035, -0.040]))
    none = combined_calibration([{"applied": False, "prior_ok": False, "offset_mm": None, "offset_sd_mm": None}] * 2)
    assert not none["applied"] and not none["prior_ok"]


@pytest.fixture(scope="module")
def lamp_moved(tmp_path_factory):
    """One print, one camera, three pictures with the lamp moved (render's light_seed)."""
    from calib.commands.simulate import simulate_scan, write_image
    from patterns import spiral_step
    from patterns.manifest import manifest_path_for

    d = tmp_path_factory.mktemp("stack")
    gcode, man = spiral_step.generate("direct_drive")[:2]
    (d / "p.gcode").write_text(gcode)
    man.save(manifest_path_for(d / "p.gcode"))
    paths, renders = [], []
    for ls in range(3):
        r, _ = simulate_scan(man, "pa", {"pa.tau_s": 0.04}, "flatbed", dpi=300.0, seed=0,
                             realism="grain,sparkle", light_seed=ls)
        paths.append(str(write_image(str(d / f"lamp{ls}.png"), r)))
        renders.append(r)
    return d, man, paths, renders


def test_moving_the_lamp_moves_the_specks_not_the_print(lamp_moved):
    _, _, _, renders = lamp_moved
    a, b = renders[0], renders[1]
    np.testing.assert_array_equal(a.truth.widths.width_mm, b.truth.widths.width_mm)
    np.testing.assert_allclose(a.truth.camera.H, b.truth.camera.H)
    assert a.truth.settings["plastic_bgr"] == b.truth.settings["plastic_bgr"]
    # the plate's specks moved: pixels change by far more than the sensor noise
    diff = np.abs(a.image.astype(float) - b.image.astype(float)).max(axis=2)
    assert np.mean(diff > 40) > 0.002


def test_three_pictures_with_the_lamp_moved_measure_tighter_than_one(lamp_moved, capsys):
    """The specks and the sensor noise are each picture's own: the mean of three readings
    errs ~1/sqrt(3) of one picture's (3.0 -> 1.8 um measured), and its sds stay honest."""
    d, man, paths, renders = lamp_moved
    truth = renders[0].truth.widths
    ok0 = np.isfinite(truth.width_mm) & (truth.width_mm > 0)
    mpath = str(d / "p.manifest.json")
    sds = []
    for name, pics in (("one", paths[:1]), ("three", paths)):
        out = d / f"{name}.csv"
        assert main(["measure", *pics, "--manifest", mpath, "-o", str(out)]) == 0
        t = WidthTable.load(out)
        ok = t.valid & ok0
        e = t.width_mm[ok] - truth.width_mm[ok]
        sds.append(np.std(e))
        if name == "three":
            assert t.valid[ok0].mean() >= 0.95
            assert 0.6 <= np.mean(np.abs(e - e.mean()) <= t.width_sd_mm[ok]) <= 0.8
    assert sds[1] < 0.75 * sds[0]
    err = capsys.readouterr().err
    assert "3 pictures measured" in err
    summary = json.loads((d / "three.summary.json").read_text())
    assert summary["stack"]["pictures"] == 3 and len(summary["images"]) == 3


def test_an_unreadable_picture_among_several_is_one_line_and_exit_2(lamp_moved, capsys):
    d, _, paths, _ = lamp_moved
    bad = d / "broken.jpg"
    bad.write_bytes(b"\xff\xd8\xff\xe0" + b"\x00" * 64)
    rc = main(["measure", paths[0], str(bad), "--manifest", str(d / "p.manifest.json"), "-o", str(d / "x.csv")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "broken.jpg" in err
    assert not (d / "x.csv").exists()


def test_a_picture_that_is_refused_is_left_out_and_said(lamp_moved, capsys):
    """A picture of something else among the pictures of the print: measured without it,
    with a warning that names it; the summary lists it."""
    import cv2

    d, _, paths, _ = lamp_moved
    other = d / "other.png"
    cv2.imwrite(str(other), np.random.default_rng(0).integers(0, 255, (900, 1200, 3), dtype=np.uint8))
    out = d / "two.csv"
    rc = main(["measure", paths[0], str(other), paths[1], "--manifest", str(d / "p.manifest.json"),
               "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0 and out.exists()
    assert "other.png: left out" in err and "2 pictures measured" in err
    summary = json.loads((d / "two.summary.json").read_text())
    assert [x["image"] for x in summary["stack"]["left_out"]] == [str(other)]


def test_pictures_of_two_prints_are_said_to_disagree(monkeypatch):
    """Two prints of one pattern (the second 50 um wider: another flow) photographed as if
    one: their readings of a station scatter far beyond each picture's sds (5 um), and the
    summary says so first. Pictures of one print read a ratio near or under 1."""
    import measure.pipeline
    from measure.pipeline import MeasureResult
    from measure.stack import DISAGREE_RATIO, measure_pictures, scatter_ratio

    rng = np.random.default_rng(2)
    n = 600
    truth = np.tile(np.linspace(0.3, 1.2, n // 2), 2)
    one = [_table(truth, 0.005, rng, np.ones(n, bool)) for _ in range(3)]
    W = np.array([t.width_mm for t in one])
    assert scatter_ratio(W, np.full_like(W, 0.005), np.ones_like(W, bool)) < 1.3
    two = one[:2] + [_table(truth + 0.05, 0.005, rng, np.ones(n, bool))]
    cal = {"applied": False, "prior_ok": False, "offset_mm": None, "offset_sd_mm": None}
    fake = iter(two)

    def measure_scan(path, manifest, points=None, overlay_path=None, *, max_residual_mm=None):
        t = next(fake)
        return MeasureResult(table=t, registration=type("R", (), {"residual_mm": 0.01})(),
                             summary={"apparent_width": dict(cal), "warnings": [], "fraction_valid": 1.0,
                                      "width_sd_mm_median": 0.005})
    monkeypatch.setattr(measure.pipeline, "measure_scan", measure_scan)
    res = measure_pictures(["a.jpg", "b.jpg", "c.jpg"], manifest=None)
    assert res.summary["stack"]["scatter_ratio"] > DISAGREE_RATIO
    assert "are they all of this one print" in res.summary["warnings"][0]
