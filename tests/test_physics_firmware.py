"""Firmware pressure advance (fit.effects.FirmwarePA) follows Klipper/Marlin: advance only on
moves that extrude while the head moves in XY; retract / prime (E-only) moves unchanged."""
from __future__ import annotations

import numpy as np
import pytest

from fit.context import SimContext
from fit.effects import FirmwarePA, pa_intervals
from fit.geometry import bead_area_mm2, filament_area_mm2
from patterns.manifest import Manifest, Timeline, Track

D_MM, H_MM, W_MM = 1.75, 0.2, 0.45
R = bead_area_mm2(W_MM, H_MM) / filament_area_mm2(D_MM)   # mm of filament per mm of track
DT = 0.001


def _trapezoid(dist, vmax, acc):
    """Positions and velocities (at DT) of a 0 -> vmax -> 0 move over dist."""
    t_acc = vmax / acc
    d_acc = 0.5 * acc * t_acc ** 2
    if 2 * d_acc > dist:
        t_acc = np.sqrt(dist / acc)
        vmax, d_acc = acc * t_acc, 0.5 * dist
    t_cru = (dist - 2 * d_acc) / vmax
    T = 2 * t_acc + t_cru
    t = np.linspace(0.0, T, int(np.ceil(T / DT)) + 1)
    v = np.minimum.reduce([acc * t, np.full_like(t, vmax), acc * (T - t)]).clip(0)
    s = np.where(t < t_acc, 0.5 * acc * t ** 2,
                 np.where(t < t_acc + t_cru, d_acc + vmax * (t - t_acc),
                          dist - 0.5 * acc * (T - t) ** 2))
    return t, s, v


def _manifest():
    """print 0->20 mm (track 0), retract 1 mm, travel to 30 mm, prime 1 mm, print 30->50
    (track 1); every move starts and ends at rest, as Klipper joins E-only and XY moves."""
    parts = []   # (t, x, e, v_head, ve, track, s)
    x0, e0, t0 = 0.0, 0.0, 0.0

    def add(t, x, e, vh, ve, trk, s):
        nonlocal x0, e0, t0
        sl = slice(1, None) if parts else slice(None)
        parts.append([a[sl] for a in (t + t0, x, e, vh, ve, np.full(len(t), trk), s)])
        t0, x0, e0 = t0 + t[-1], x[-1], e[-1]

    t, s, v = _trapezoid(20.0, 60.0, 3000.0)
    add(t, x0 + s, e0 + R * s, v, R * v, 0, s)
    t, s, v = _trapezoid(1.0, 35.0, 1500.0)                 # retract, head still
    add(t, np.full_like(t, x0), e0 - s, 0 * v, -v, 0, np.full_like(t, 20.0))
    t, s, v = _trapezoid(10.0, 150.0, 5000.0)               # travel, no E
    add(t, x0 + s, np.full_like(t, e0), v, 0 * v, -1, np.full_like(t, np.nan))
    t, s, v = _trapezoid(1.0, 35.0, 1500.0)                 # prime, head still
    add(t, np.full_like(t, x0), e0 + s, 0 * v, v, 1, np.zeros_like(t))
    t, s, v = _trapezoid(20.0, 60.0, 3000.0)
    add(t, x0 + s, e0 + R * s, v, R * v, 1, s)
    tt, x, e, vh, ve, trk, s = (np.concatenate(c) for c in zip(*parts))
    tl = Timeline(t_s=tt, x_mm=x, y_mm=0 * x, z_mm=0 * x + H_MM, v_mm_s=vh, ve_mm_s=ve,
                  e_mm=e, track=trk.astype(int), s_mm=s)
    tracks = [Track(id=i, kind="test", points_mm=[[xa, 0], [xa + 20, 0]], width_mm=[W_MM] * 2,
                    height_mm=[H_MM] * 2, flow_mm3_s=[0.0, 0.0]) for i, xa in ((0, 0.0), (1, 30.0))]
    return Manifest(printer={"filament_diameter_mm": D_MM, "nozzle_diameter_mm": 0.4},
                    pattern={}, tracks=tracks, timeline=tl)


def _command(ctx, k_s, smooth_s):
    p = {"k_s": np.array([[k_s]]), "smooth_time_s": np.array([[smooth_s]])}
    return FirmwarePA().command(ctx, ctx.ve_mm_s[None, :], p)[0]


@pytest.fixture(scope="module")
def ctx():
    return SimContext.build(_manifest(), coarsen=False)


def test_print_moves_flagged_retract_prime_travel_not(ctx):
    f = pa_intervals(ctx)
    e_only = (ctx.v_head_mm_s == 0) & (ctx.de_mm != 0)
    assert e_only.sum() > 50 and not np.any(f[e_only])
    assert not np.any(f[ctx.de_mm == 0])                         # travel
    assert np.all(f[(ctx.de_mm > 0) & (ctx.v_head_mm_s > 0)])


def test_marlin_la_retract_prime_unchanged_print_gets_pos_plus_k_vel(ctx):
    K = 0.08
    out = _command(ctx, K, 0.0)
    off = _command(ctx, 0.0, 0.0)
    np.testing.assert_array_equal(off, ctx.ve_mm_s)              # PA off: the raw command
    e_only = (ctx.v_head_mm_s == 0) & (ctx.de_mm != 0)
    # retract and prime: the same extruder motion as with PA off
    np.testing.assert_allclose(out[e_only], ctx.ve_mm_s[e_only], rtol=0, atol=1e-9)
    # extruder position with PA: pos + K * vel on printing moves, pos elsewhere
    e_pa = ctx.e_mm[0] + np.concatenate([[0.0], np.cumsum(out * ctx.dt_s)])
    f = pa_intervals(ctx)
    node_print = np.zeros(ctx.n_t, bool)
    node_print[:-1] |= f
    node_print[1:] |= f
    np.testing.assert_allclose(e_pa[node_print], (ctx.e_mm + K * ctx.ve_node_mm_s)[node_print],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(e_pa[~node_print], ctx.e_mm[~node_print], rtol=0, atol=1e-9)
    assert np.max(np.abs(K * ctx.ve_node_mm_s[node_print])) > 0.1    # the advance is visible


def test_klipper_smoothing_retract_prime_independent_of_k(ctx):
    # Klipper averages the whole extruder position (PA on), but adds K*v only on printing
    # moves: away (> smooth_time/2) from printing moves the motion does not depend on K.
    st = 0.04
    a, b = _command(ctx, 0.02, st), _command(ctx, 0.5, st)
    f = pa_intervals(ctx)
    t_mid = 0.5 * (ctx.t_s[:-1] + ctx.t_s[1:])
    t_print = t_mid[f]
    far = np.min(np.abs(t_mid[:, None] - t_print[None, :]), axis=1) > 0.6 * st
    e_only = (ctx.v_head_mm_s == 0) & (ctx.de_mm != 0)
    assert np.sum(far & e_only) > 30
    np.testing.assert_allclose(a[far], b[far], rtol=0, atol=1e-9)
    # mid-travel (at rest, far from any E motion) the extruder is where it was commanded:
    # the advance added while printing has been fully taken back
    trav = np.flatnonzero((ctx.track < 0) & (ctx.v_head_mm_s > 0))
    mid = trav[len(trav) // 2]
    assert np.sum(b[:mid] * ctx.dt_s[:mid]) == pytest.approx(ctx.e_mm[mid] - ctx.e_mm[0], abs=1e-9)
