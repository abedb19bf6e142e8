"""Steady-state advance of a model (Model.steady_advance_mm) and the Kalico nonlinear-PA
match (fit.derived.kalico_match / derived_values / problem_advance) used by `calib fit`."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from calib.commands.fit import summary_text  # noqa: F401  (import check of the wiring)
from fit.context import SimContext
from fit.derived import _kalico_curve, derived_values, kalico_match, problem_advance
from fit.geometry import bead_area_mm2, filament_area_mm2
from fit.model import build_model
from patterns.manifest import Manifest, Timeline, Track

PROFILE = {"filament_diameter_mm": 1.75, "nozzle_diameter_mm": 0.4}
V = np.linspace(0.0, 8.0, 81)


@pytest.mark.parametrize("tau", [0.02, 0.5, 1.7])
def test_pa_alone_is_tau_times_vn(tau):
    m = build_model("pa", PROFILE)
    np.testing.assert_array_equal(m.steady_advance_mm([tau], V), tau * V)
    both = m.steady_advance_mm(np.array([[tau], [2 * tau]]), V)
    assert both.shape == (2, V.size)
    np.testing.assert_allclose(both[1], 2 * tau * V, rtol=1e-15)


def test_sum_of_terms_matches_the_kernel_equations():
    m = build_model("pa+nonlinear+bernoulli+offset+kalico_recip+backpressure", PROFILE)
    vals = {"pa.tau_s": 0.2, "nonlinear.n": 0.5, "bernoulli.k_s2_mm3": 0.03, "offset.kc_mm": 0.1,
            "kalico_recip.off_mm": 0.2, "kalico_recip.v_lin_mm_s": 0.7, "backpressure.kb": 0.5,
            "backpressure.w_sat_mm": 0.8}
    th = m.theta_from(vals)
    af = filament_area_mm2(1.75)
    w = 0.45
    exp = (0.2 / 0.5 * V ** 0.5 + 0.03 * af * V ** 2 + 0.1 + 0.2 * V / (V + 0.7)
           + 0.5 * 0.8 * np.tanh(w / 0.8))
    np.testing.assert_allclose(m.steady_advance_mm(th, V, width_mm=w), exp, rtol=1e-12)
    with pytest.raises(ValueError):
        m.steady_advance_mm(th, V)                 # backpressure needs a width


@pytest.mark.parametrize("la,off,vl,vmax", [(0.017, 0.12, 1.0, 8.0), (0.3, 0.8, 0.3, 3.0),
                                             (0.04, 0.3, 2.0, 10.0)])
def test_kalico_match_recovers_kalico_tanh_truth(la, off, vl, vmax):
    m = build_model("pa+kalico_tanh", PROFILE)
    th = m.theta_from({"pa.tau_s": la, "kalico_tanh.off_mm": off, "kalico_tanh.v_lin_mm_s": vl})
    r = kalico_match(lambda v: m.steady_advance_mm(th, v), vmax, "tanh")
    assert r["pressure_advance_s"] == pytest.approx(la, rel=1e-6)
    assert r["offset_mm"] == pytest.approx(off, rel=1e-6)
    assert r["linearization_velocity_mm_s"] == pytest.approx(vl, rel=1e-6)


def test_power_law_posterior_matched_kalico_within_tolerance():
    """Shear-thinning power law (n = 0.4): the matched Kalico curves (medians over posterior
    draws) stay within 4 % rms and 15 % max of the advance at v_max over 0 < v <= v_max
    (the misfit is at v -> 0 where the power law's slope is unbounded)."""
    m = build_model("pa+nonlinear", PROFILE)
    rng = np.random.default_rng(3)
    draws = np.column_stack([0.3 * np.exp(0.03 * rng.standard_normal(200)),
                             0.4 + 0.01 * rng.standard_normal(200)])
    vmax = 5.0
    d = derived_values(m.param_names, draws, PROFILE,
                       advance_fn=lambda row, v: m.steady_advance_mm(row, v), v_max_mm_s=vmax,
                       n_kalico=60)
    truth = m.theta_from({"pa.tau_s": 0.3, "nonlinear.n": 0.4})
    v = np.linspace(vmax / 200, vmax, 200)
    a = m.steady_advance_mm(truth, v)
    for kind in ("tanh", "recipr"):
        kd = d[f"kalico_{kind}"]
        p = [kd[k]["median"] for k in ("pressure_advance_s", "offset_mm",
                                       "linearization_velocity_mm_s")]
        err = _kalico_curve(kind, p, v) - a
        assert np.sqrt(np.mean(err ** 2)) < 0.04 * a[-1]
        assert np.max(np.abs(err)) < 0.15 * a[-1]
        lo, hi = kd["pressure_advance_s"]["ci95"]
        assert lo < kd["pressure_advance_s"]["median"] < hi      # intervals from the draws
        assert f"pressure_advance_model: {kind}" in kd["config"]


def _line_ctx(v_head=50.0, w=0.45, h=0.2, dt=0.002, L=60.0):
    n = int(round(L / v_head / dt))
    t = np.arange(n + 1) * dt
    s = v_head * t
    de = np.diff(s) * bead_area_mm2(w, h) / filament_area_mm2(1.75)
    e = np.concatenate([[0.0], np.cumsum(de)])
    ve = np.concatenate([de / dt, [de[-1] / dt]])
    tl = Timeline(t_s=t, x_mm=s, y_mm=0 * s, z_mm=0 * s + h, v_mm_s=0 * s + v_head, ve_mm_s=ve,
                  e_mm=e, track=np.zeros(n + 1, int), s_mm=s)
    tr = Track(id=0, kind="test", points_mm=[[0, 0], [L, 0]], width_mm=[w, w], height_mm=h,
               flow_mm3_s=0.0)
    return SimContext.build(Manifest(printer=dict(PROFILE), pattern={}, tracks=[tr], timeline=tl))


def test_problem_advance_only_for_nonlinear_models_and_uses_the_data_range():
    ctx = _line_ctx()
    lin = SimpleNamespace(models=[build_model("pa", PROFILE)], scans=[SimpleNamespace(ctx=ctx)],
                          model_theta=lambda th, k: np.atleast_2d(th))
    assert problem_advance(lin) is None
    m = build_model("pa+bernoulli+backpressure", PROFILE)
    nl = SimpleNamespace(models=[m], scans=[SimpleNamespace(ctx=ctx)],
                         model_theta=lambda th, k: np.atleast_2d(th)[:, :4])
    fn, vmax, width = problem_advance(nl)
    assert vmax == pytest.approx(50.0 * bead_area_mm2(0.45, 0.2) / filament_area_mm2(1.75), rel=1e-9)
    assert width == pytest.approx(0.45)
    row = np.array([0.2, 0.03, 0.0, 0.8, 0.01, 0.5])      # model params + noise params
    np.testing.assert_allclose(fn(row, V), 0.2 * V + 0.03 * filament_area_mm2(1.75) * V ** 2)


def test_pa_ve_fits_export_the_same_time_constant_as_pa():
    """A pa_ve fit (VE in us) yields the firmware PA through tau = 32 D^2 L l / d^4 VE
    (seed 000: VE 0.65 us with D 2.85, L 150, l 0.6, d 0.4 mm is tau 0.594 s)."""
    from fit.derived import derived_values

    prof = {"filament_diameter_mm": 2.85, "bowden_length_mm": 150, "nozzle_land_length_mm": 0.6,
            "nozzle_diameter_mm": 0.4}
    d = derived_values(["pa_ve.ve_us"], np.full((20, 1), 0.65), prof)
    assert d["pressure_advance_s"]["median"] == pytest.approx(0.594, abs=0.002)
    assert d["kisslicer_ve_us"]["median"] == pytest.approx(0.65, abs=1e-9)
    assert d["firmware"]["marlin"].startswith("M900 K0.59")


def test_pa_vs_flow_is_the_secant_of_the_advance_curve():
    """Power law Preq = (tau/n) v_ref (v/v_ref)^n (fit/effects.py nonlinear, v_ref 1 mm/s):
    K(v) = Preq/v = (tau/n) v^(n-1), falling with flow for n < 1; flows are v * pi D^2/4."""
    from fit.derived import pa_vs_flow

    tau, n = 0.05, 0.6
    rows = np.array([[tau], [tau * 1.01], [tau * 0.99]])
    d = pa_vs_flow(lambda r, v: (r[0] / n) * v ** n, rows, 2.0, {"filament_diameter_mm": 1.75})
    v = np.array(d["v_mm_s"])
    assert v[-1] == pytest.approx(2.0)
    assert np.allclose(d["pa_s_median"], (tau / n) * v ** (n - 1), rtol=1e-9)
    assert np.all(np.diff(d["pa_s_median"]) < 0)
    assert d["flow_mm3_s"][-1] == pytest.approx(2.0 * np.pi * 1.75 ** 2 / 4)
    lo, hi = np.array(d["pa_s_ci95"]).T
    assert np.all(lo < np.array(d["pa_s_median"])) and np.all(np.array(d["pa_s_median"]) < hi)
