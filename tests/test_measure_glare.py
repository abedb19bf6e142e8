"""Where the scan's light is (measure/glare.py), the widths table's light_angle_deg column,
and the fit's ViewLight effect that reads it: known answers."""
import numpy as np
import pytest

from measure.glare import angle_to_light_deg, light_axis
from measure.table import WidthTable


def _normals(n=3000, seed=0):
    phi = np.random.default_rng(seed).uniform(0, 2 * np.pi, n)
    return np.cos(phi), np.sin(phi)


def test_the_lights_axis_comes_from_the_streak_stations_normals():
    nx, ny = _normals()
    # streaks where the flank faces a light along 100 deg (either way), plus 2 % stray ones
    a = angle_to_light_deg(nx, ny, np.radians(100.0))
    stray = np.random.default_rng(1).uniform(size=len(nx)) < 0.02
    axis = light_axis(nx, ny, (a < 20) | stray)
    assert axis is not None
    assert abs(np.degrees(np.angle(np.exp(2j * (axis - np.radians(100.0))))) / 2) < 2.0
    # edge misfit that looks like a streak picks any direction: no light
    assert light_axis(nx, ny, np.random.default_rng(2).uniform(size=len(nx)) < 0.1) is None
    assert light_axis(nx[:10], ny[:10], np.ones(10, bool)) is None


def test_angle_to_the_light_is_folded_to_0_90_deg():
    ang = np.radians([0.0, 30.0, 90.0, 150.0, 180.0, 270.0])
    got = angle_to_light_deg(np.cos(ang), np.sin(ang), 0.0)
    assert got == pytest.approx([0, 30, 90, 30, 0, 90], abs=1e-9)


def test_light_angle_column_round_trips_and_old_tables_read_as_unknown(tmp_path):
    n = 5
    t = WidthTable(track=np.zeros(n), s_mm=np.arange(n) * 0.25, x_mm=np.zeros(n), y_mm=np.zeros(n),
                   t_s=np.arange(n) * 0.01, width_mm=np.full(n, 0.45), width_sd_mm=np.full(n, 0.003),
                   valid=np.ones(n, bool), light_angle_deg=[0.0, 12.34, 45.0, 89.9, np.nan])
    back = WidthTable.load(t.save(tmp_path / "w.csv"))
    assert back.light_angle_deg[:4] == pytest.approx([0.0, 12.3, 45.0, 89.9], abs=0.051)
    assert np.isnan(back.light_angle_deg[4])
    old = tmp_path / "old.csv"
    old.write_text("track,s_mm,x_mm,y_mm,t_s,width_mm,width_sd_mm,valid,flag\n0,0,0,0,0,0.45,0.003,1,\n")
    assert np.isnan(WidthTable.load(old).light_angle_deg).all()


def test_view_light_adds_its_band_offset_and_nothing_where_the_light_is_unknown():
    from types import SimpleNamespace

    from fit.effects import ViewLight

    ctx = SimpleNamespace(s_light_deg=np.array([5.0, 20.0, 35.0, 50.0, 70.0, np.nan]), cache={})
    p = {"o0_mm": np.array([[0.004]]), "o1_mm": np.array([[0.003]]), "o2_mm": np.array([[0.002]]),
         "o3_mm": np.array([[0.001]])}
    w = np.full((1, 6), 0.5)
    got = ViewLight().width(ctx, w, p)
    assert got[0] == pytest.approx([0.504, 0.503, 0.502, 0.501, 0.5, 0.5])
    # a table without the column: the effect is absent
    assert ViewLight().width(SimpleNamespace(s_light_deg=None, cache={}), w, p) is w
