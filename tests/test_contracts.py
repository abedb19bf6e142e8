"""The shared contracts: bead geometry and the manifest/widths round trips."""
import numpy as np
import pytest

from calib.errors import UserError
from fit.geometry import bead_area_mm2, bead_width_mm
from measure.table import WidthTable
from patterns.manifest import Manifest, Timeline, Track, sample_points


def test_bead_geometry_round_trip_and_known_values():
    h = 0.2
    w = np.linspace(0.05, 2.0, 200)
    np.testing.assert_allclose(bead_width_mm(bead_area_mm2(w, h), h), w, rtol=1e-12)
    # rounded rectangle: 0.4 x 0.2 -> (0.4-0.2)*0.2 + pi*0.01 = 0.0714159...
    assert bead_area_mm2(0.4, 0.2) == pytest.approx(0.04 + np.pi * 0.01, rel=1e-12)
    # continuity at w = h
    assert bead_area_mm2(h - 1e-12, h) == pytest.approx(bead_area_mm2(h, h), rel=1e-9)
    assert bead_width_mm(-1.0, h) == 0.0


def _toy_manifest():
    tr = Track(id=3, kind="test", points_mm=[[0, 0], [10, 0], [10, 5]], width_mm=0.5,
               height_mm=0.2, flow_mm3_s=2.0)
    t = np.linspace(0, 1.5, 61)
    s = 10 * t  # 10 mm/s along the 15 mm track
    pos, _ = tr.at(s)
    tl = Timeline(t_s=t, x_mm=pos[:, 0], y_mm=pos[:, 1], z_mm=np.full_like(t, 0.2),
                  v_mm_s=np.full_like(t, 10.0), ve_mm_s=np.ones_like(t), e_mm=t,
                  track=np.full(len(t), 3), s_mm=s)
    return Manifest(printer={"name": "toy"}, pattern={"name": "toy"}, tracks=[tr], timeline=tl)


def test_manifest_round_trip_and_samples(tmp_path):
    m = _toy_manifest()
    path = m.save(tmp_path / "toy.manifest.json")
    m2 = Manifest.load(path)
    assert len(m2.timeline) == 61
    np.testing.assert_allclose(m2.tracks[0].points_mm, m.tracks[0].points_mm)
    smp = sample_points(m2, ds_mm=0.25)
    assert len(smp) == 61  # 0, 0.25, ..., 15.0
    # first-passage time equals s / (10 mm/s), and the corner at s=10 is at (10, 0)
    np.testing.assert_allclose(smp.t_s, smp.s_mm / 10.0, atol=1e-9)
    i = np.argmin(abs(smp.s_mm - 12.0))
    assert (smp.x_mm[i], smp.y_mm[i]) == pytest.approx((10.0, 2.0))
    assert (smp.nx[i], smp.ny[i]) == pytest.approx((-1.0, 0.0))


def test_manifest_load_rejects_non_manifest(tmp_path):
    p = tmp_path / "x.json"
    p.write_text('{"hello": 1}')
    with pytest.raises(UserError, match="not a calib manifest"):
        Manifest.load(p)


def test_width_table_round_trip_and_nan_rejected(tmp_path):
    n = 5
    t = WidthTable(track=[1] * n, s_mm=np.arange(n) * 0.25, x_mm=np.zeros(n), y_mm=np.zeros(n),
                   t_s=np.arange(n), width_mm=np.full(n, 0.45), width_sd_mm=np.full(n, 0.01),
                   valid=[1, 1, 0, 1, 1], flag=["", "", "label", "", ""])
    p = t.save(tmp_path / "w.csv")
    t2 = WidthTable.load(p)
    assert list(t2.valid) == [True, True, False, True, True]
    assert t2.flag[2] == "label"
    p.write_text(p.read_text().replace("0.45000", "nan", 1))
    with pytest.raises(UserError, match="NaN"):
        WidthTable.load(p)
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(UserError, match="empty"):
        WidthTable.load(tmp_path / "e.csv")


def test_atomic_write_keeps_mode_and_leaves_no_partial_file(tmp_path):
    import os
    import stat

    from calib.fileio import atomic_write, atomic_write_text, backup

    p = atomic_write_text(tmp_path / "a.txt", "hello")
    mode = stat.S_IMODE(p.stat().st_mode)
    assert mode & 0o044  # readable by group/others under a normal umask (not mkstemp's 0600)
    os.chmod(p, 0o640)
    atomic_write_text(p, "again")
    assert stat.S_IMODE(p.stat().st_mode) == 0o640 and p.read_text() == "again"

    def boom(f):
        f.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(p, boom)
    assert p.read_text() == "again"
    assert [q.name for q in tmp_path.iterdir()] == ["a.txt"]
    b = backup(p)
    assert b.read_text() == "again" and b != p
