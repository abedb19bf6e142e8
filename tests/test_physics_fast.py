"""The fast paths of the physics: exact two-state kernel for pa+thermal (against
solve_ivp, with flow stops/starts inside intervals), the coarsened physics timeline that
predict integrates on (same widths within 1 um), the fused parallel predict kernel (same
numbers as simulate, set by set)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fit import kernels as K
from fit.context import SimContext
from fit.geometry import bead_area_mm2, filament_area_mm2
from fit.model import build_model
from patterns.manifest import Manifest, Timeline, Track

AF = filament_area_mm2(1.75)
H, V = 0.2, 40.0


def retract_track(dt=0.004):
    """Print 0.5 s, retract 1 mm in 0.05 s (travel off-track), dwell, unretract, print."""
    segs = [(0.5, bead_area_mm2(0.45, H) * V / AF, V, 0),       # print
            (0.05, -1.0 / 0.05, 0.0, -1),                       # retract
            (0.3, 0.0, 0.0, -1),                                # dwell
            (0.05, 1.0 / 0.05, 0.0, 0),                         # unretract
            (0.6, bead_area_mm2(0.6, H) * V / AF, V, 0)]        # print wider
    ve, vh, trk = [], [], []
    for T, v, sp, tr in segs:
        n = int(round(T / dt))
        ve += [v] * n
        vh += [sp] * n
        trk += [tr] * n
    ve, vh = np.array(ve), np.array(vh)
    t = np.arange(len(ve) + 1) * dt
    s = np.concatenate([[0.0], np.cumsum(vh * dt)])
    e = np.concatenate([[0.0], np.cumsum(ve * dt)])
    track = np.array(trk + [0])
    tl = Timeline(t_s=t, x_mm=s, y_mm=0 * s, z_mm=0 * s + H, v_mm_s=np.append(vh, 0.0),
                  ve_mm_s=np.append(ve, 0.0), e_mm=e, track=track, s_mm=np.where(track >= 0, s, np.nan))
    tr = Track(id=0, kind="test", points_mm=[[0, 0], [s[-1], 0]], width_mm=0.45, height_mm=H, flow_mm3_s=0)
    return Manifest(printer={"filament_diameter_mm": 1.75, "nozzle_diameter_mm": 0.4}, pattern={},
                    tracks=[tr], timeline=tl)


def reference_vn(ctx, tau, kc, a, tth):
    """solve_ivp (Radau, tight) of dP/dt = ve - vn + a(X - vn), dX/dt = (vn - X)/tau_th,
    vn = max(P - Kc, 0)/tau, piece by piece where ve is constant."""
    ve = ctx.ve_mm_s
    edges = np.flatnonzero(np.abs(np.diff(ve)) > 1e-12) + 1
    bounds = np.concatenate([[0], edges, [len(ve)]])
    y = np.array([0.0, 0.0])
    out = [0.0]
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        vi = ve[i0]

        def rhs(_, yy):
            q = max(yy[0] - kc, 0.0) / tau
            return [vi - q + a * (yy[1] - q), (q - yy[1]) / tth]

        sol = solve_ivp(rhs, (ctx.t_s[i0], ctx.t_s[i1]), y, method="Radau", rtol=1e-11, atol=1e-13,
                        t_eval=ctx.t_s[i0 + 1:i1 + 1])
        out += [max(P - kc, 0.0) / tau for P in sol.y[0]]
        y = sol.y[:, -1]
    return np.array(out)


@pytest.mark.parametrize("tau,kc,a,tth", [(0.05, 0.0, 0.3, 2.0), (0.02, 0.2, 0.8, 1.0), (0.6, 0.1, 0.05, 25.0)])
def test_thermal_exact_kernel_matches_solve_ivp(tau, kc, a, tth):
    ctx = SimContext.build(retract_track(), coarsen=False)
    model = build_model("pa+offset+thermal").with_values(
        {"pa.tau_s": tau, "offset.kc_mm": kc, "thermal.a": a, "thermal.tau_s": tth})
    assert model._mode == K.MODE_THERMAL
    sim = model.simulate(ctx, model.default_theta())
    ref = reference_vn(ctx, tau, kc, a, tth)
    scale = ctx.ve_mm_s[ctx.ve_mm_s > 0].min()
    # exact in time (flow stop/start located inside the interval): far inside the 1 %
    # the theta scheme is held to
    assert np.max(np.abs(sim.vn_node_mm_s[0] - ref)) < 1e-5 * scale
    # exact balance: out = commanded - stored - a tau_th X_end
    assert sim.out_mm.sum() == pytest.approx(ctx.de_mm.sum() - sim.p_end_mm[0] - a * tth * sim.x_end_mm_s[0],
                                             abs=1e-12)
    # the theta scheme of the general kernel is less accurate where flow stops/starts
    # inside an interval: the exact kernel is at least as close to the reference
    model._mode = K.MODE_GENERAL
    gen = model.simulate(ctx, model.default_theta())
    assert np.max(np.abs(sim.vn_node_mm_s[0] - ref)) <= np.max(np.abs(gen.vn_node_mm_s[0] - ref))


@pytest.fixture(scope="module")
def planned_manifest():
    builder = pytest.importorskip("patterns.builder")
    _, man = builder.PATTERNS["start-stop"]("direct_drive")
    return man


@pytest.fixture(scope="module")
def spiral_manifest():
    builder = pytest.importorskip("patterns.builder")
    _, man = builder.PATTERNS["spiral-step"]("adventurer3")
    return man


@pytest.mark.parametrize("spec,values", [
    ("pa", {"pa.tau_s": 0.02}),
    ("pa", {"pa.tau_s": 0.8}),
    ("pa+thermal", {"pa.tau_s": 0.3, "thermal.a": 0.2, "thermal.tau_s": 5.0}),
    ("pa+thermal+backpressure", {"pa.tau_s": 0.02}),
    ("pa+nonlinear+backpressure+thermal", {"pa.tau_s": 0.8, "nonlinear.n": 0.5}),
])
def test_predict_on_coarse_timeline_matches_full(planned_manifest, spiral_manifest, spec, values):
    # the demo spiral (what calib fits): within 1 um everywhere
    ctx = SimContext.build(spiral_manifest)
    model = build_model(spec).with_values(values)
    th = model.default_theta()
    full = model.simulate(ctx, th).bead_widths_mm[0]
    coarse = model.predict(ctx, th)[0]
    ok = np.isfinite(full)
    assert np.array_equal(ok, np.isfinite(coarse))
    assert np.max(np.abs(full[ok] - coarse[ok])) < 1e-3       # mm: 1 um
    # start-stop (dwells with blobs several mm wide, ooze tails): the deposit placement
    # inside a merged interval is first order in dt/tau: within 1 um + 0.25 %
    ctx = SimContext.build(planned_manifest)
    assert ctx.physics is not None and ctx.physics.n_t < 0.9 * ctx.n_t
    assert np.array_equal(ctx.physics.t_s, ctx.t_s[ctx.physics.node_index])
    model = build_model(spec).with_values(values)
    th = model.default_theta()
    full = model.simulate(ctx, th).bead_widths_mm[0]
    coarse = model.predict(ctx, th)[0]
    ok = np.isfinite(full)
    assert np.array_equal(ok, np.isfinite(coarse))
    assert np.all(np.abs(full[ok] - coarse[ok]) < 1e-3 + 2.5e-3 * full[ok])


def test_batched_parallel_predict_equals_set_by_set(planned_manifest):
    ctx = SimContext.build(planned_manifest)
    for spec in ("pa", "pa+thermal", "pa+thermal+backpressure+flow_gain+bed_tilt"):
        model = build_model(spec)
        th = np.tile(model.default_theta(), (9, 1))
        th[:, 0] = np.geomspace(0.01, 2.0, 9)
        batch = model.predict(ctx, th)          # >= PARALLEL_MIN_SETS: parallel kernel
        one = np.vstack([model.predict(ctx, t) for t in th])
        np.testing.assert_array_equal(np.isfinite(batch), np.isfinite(one))
        ok = np.isfinite(one)
        assert np.max(np.abs(batch[ok] - one[ok])) < 1e-12
        # without coarsening predict is exactly simulate's widths
        ctx_full = SimContext.build(planned_manifest, coarsen=False)
        w_sim = model.simulate(ctx_full, th[:2]).bead_widths_mm
        w_pred = model.predict(ctx_full, th[:2])
        assert np.max(np.abs(w_sim[ok[:2]] - w_pred[ok[:2]])) < 1e-12


def test_serial_and_parallel_kernels_have_separate_compile_caches():
    """numba keys its on-disk cache by qualified name and line, not by parallel=True: the
    serial and parallel builds of one kernel must not share a cache entry, or whichever
    compiled first is loaded for both (the parallel kernels then ran on one core)."""
    from fit import kernels as K
    from fit import likelihood as L

    pairs = [(K.SERIAL[k], K.PARALLEL[k]) for k in K.SERIAL] + [(L._AR1_SERIAL, L._AR1_PARALLEL)]
    for ser, par in pairs:
        assert ser.py_func.__code__ is par.py_func.__code__
        assert ser._cache._cache_file._index_name != par._cache._cache_file._index_name
        assert par.targetoptions.get("parallel") is True
        assert not ser.targetoptions.get("parallel")


def test_physics_timeline_is_cut_after_the_last_deposit_a_station_sees(spiral_manifest, monkeypatch):
    """Widths are causal: with stations on the test tracks only (as a measured scan has),
    the fiducials, ruler and labels printed after the spiral cannot change a predicted
    width. The cut timeline gives the same widths as the uncut one to rounding, and is
    much shorter."""
    import fit.context as C
    from patterns.manifest import sample_points

    man = spiral_manifest
    test_ids = [t.id for t in man.tracks if t.kind == "test"]
    st = sample_points(man)
    keep = np.isin(st.track, test_ids)
    stations = type(st)(**{f: np.asarray(getattr(st, f))[keep] for f in st.__dataclass_fields__})
    cut = SimContext.build(man, stations)
    monkeypatch.setattr(C, "last_needed_node", lambda ctx, margin_s=0.0: len(ctx.t_s) - 1)
    whole = SimContext.build(man, stations)
    assert cut.physics.t_s[-1] < 0.5 * whole.physics.t_s[-1]
    for spec in ("pa+thermal", "pa+backpressure+nonlinear"):
        model = build_model(spec, man.printer)
        th = np.tile(model.default_theta(), (4, 1))
        th[:, 0] = [0.02, 0.1, 0.5, 1.5]
        a, b = model.predict(cut, th), model.predict(whole, th)
        np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
        ok = np.isfinite(a)
        assert ok.sum() > 0.9 * ok.size
        assert np.max(np.abs(a[ok] - b[ok])) < 1e-12
