"""Linear extruder model against analytic solutions; deposit geometry; conservation; API."""
from __future__ import annotations

import numpy as np
import pytest

from calib.errors import UserError
from fit.context import SimContext
from fit.effects import tau_from_ve_s, ve_from_tau_us
from fit.geometry import bead_area_mm2, filament_area_mm2
from fit.model import build_model
from fit.virtual import print_virtual
from patterns.manifest import Manifest, Timeline, Track

D_MM = 1.75
AF = filament_area_mm2(D_MM)
PROFILE = {"filament_diameter_mm": D_MM, "nozzle_diameter_mm": 0.4}


def straight_line(v=50.0, L=100.0, w1=0.4, w2=0.6, h=0.2, dt=0.002, s_step=None):
    """One straight test track at constant head speed, commanded width w1 then w2 after
    s_step (mm). E increments are exact: de = ds * A(w) / Af per interval."""
    s_step = L / 2 if s_step is None else s_step
    n = int(round(L / v / dt))
    t = np.arange(n + 1) * dt
    s = v * t
    a = np.where(s < s_step - 1e-9, bead_area_mm2(w1, h), bead_area_mm2(w2, h))
    de = np.diff(s) * a[:-1] / AF
    e = np.concatenate([[0.0], np.cumsum(de)])
    ve = np.concatenate([de / dt, [de[-1] / dt]])      # right-continuous node velocity
    tl = Timeline(t_s=t, x_mm=s, y_mm=0 * s, z_mm=0 * s + h, v_mm_s=0 * s + v, ve_mm_s=ve,
                  e_mm=e, track=np.zeros(n + 1, int), s_mm=s)
    tr = Track(id=0, kind="test", points_mm=[[0, 0], [s_step, 0], [L, 0]], width_mm=[w1, w2, w2],
               height_mm=h, flow_mm3_s=0.0)
    return Manifest(printer=dict(PROFILE), pattern={}, tracks=[tr], timeline=tl)


def step_vn(t, ve1, ve2, t1, tau):
    """Exact outflow of the linear model from rest: ve1 from t=0, ve2 from t1."""
    return ve1 * (1 - np.exp(-t / tau)) + (ve2 - ve1) * np.where(t >= t1, 1 - np.exp(-(t - t1) / tau), 0)


@pytest.mark.parametrize("tau,dt", [(0.3, 0.002), (0.02, 0.005)])
@pytest.mark.parametrize("spec", ["pa", "pa+bernoulli"])
def test_step_response_is_exact_exponential(tau, dt, spec):
    # "pa+bernoulli" with k = 0 runs the general (theta-scheme) kernel: it must be exact too.
    m = straight_line(dt=dt)
    ctx = SimContext.build(m)
    model = build_model(spec, fixed={"bernoulli.k_s2_mm3": 0.0} if "bernoulli" in spec else None)
    q = model.flow(ctx, [tau])[0]
    ve1, ve2 = ctx.de_mm[0] / dt, ctx.de_mm[-1] / dt
    exact = step_vn(ctx.t_s, ve1, ve2, 1.0, tau) * AF
    np.testing.assert_allclose(q, exact, rtol=0, atol=1e-9 * exact.max())


def test_step_widths_match_window_average_of_exact_flow():
    tau, v, d = 0.3, 50.0, 0.4
    m = straight_line(v=v)
    ctx = SimContext.build(m)
    w = build_model("pa").predict(ctx, [tau])[0]
    ve1, ve2 = ctx.de_mm[0] / 0.002, ctx.de_mm[-1] / 0.002

    def cum(t):  # integral of the exact outflow from 0 to t (mm of filament)
        c = ve1 * (t - tau * (1 - np.exp(-t / tau)))
        u = np.maximum(t - 1.0, 0)
        return c + (ve2 - ve1) * (u - tau * (1 - np.exp(-u / tau)))

    lo = np.clip(ctx.s_mm - d / 2, 0, 100) / v
    hi = np.clip(ctx.s_mm + d / 2, 0, 100) / v
    area = (cum(hi) - cum(lo)) * AF / ((hi - lo) * v)
    from fit.geometry import bead_width_mm
    np.testing.assert_allclose(w, bead_width_mm(area, 0.2), atol=2e-4)


def test_ramp_response():
    # ve = alpha * t exactly in e (e = alpha t^2 / 2); vn = alpha (t - tau (1 - exp(-t/tau))).
    tau, alpha, dt = 0.2, 2.0, 0.002
    t = np.arange(0, 1.0 + 1e-12, dt)
    s = 20.0 * t
    e = 0.5 * alpha * t ** 2
    tl = Timeline(t_s=t, x_mm=s, y_mm=0 * s, z_mm=0 * s, v_mm_s=0 * s + 20, ve_mm_s=alpha * t, e_mm=e,
                  track=np.zeros(len(t), int), s_mm=s)
    tr = Track(id=0, kind="test", points_mm=[[0, 0], [20, 0]], width_mm=0.4, height_mm=0.2, flow_mm3_s=0)
    ctx = SimContext.build(Manifest(printer=dict(PROFILE), pattern={}, tracks=[tr], timeline=tl))
    vn = build_model("pa").flow(ctx, [tau])[0] / AF
    exact = alpha * (t - tau * (1 - np.exp(-t / tau)))
    # Piecewise-constant ve (midpoint of the ramp over each interval): O(dt^2) error.
    np.testing.assert_allclose(vn, exact, atol=alpha * dt ** 2 / tau)


def test_steady_state_width_equals_commanded():
    m = straight_line(w1=0.45, w2=0.45, L=100.0)
    ctx = SimContext.build(m)
    w = build_model("pa+offset").predict(ctx, [0.02, 0.3])[0]
    far = (ctx.s_mm > 50.0 * 0.02 * 40) & (ctx.s_mm < 99.0)   # > 40 tau after the start
    np.testing.assert_allclose(w[far], 0.45, atol=1e-9)


def _retract_travel_manifest(dt=0.002):
    """Track 0 (40 mm at 40 mm/s), retract 1 mm, travel 20 mm, unretract, track 1."""
    h, v, w = 0.2, 40.0, 0.5
    a = bead_area_mm2(w, h)
    rows = []  # (t, x, track, s, de)
    t = 0.0
    x = 0.0
    n1 = int(round(40 / v / dt))
    rows.append((0.0, 0.0, 0, 0.0, 0.0))
    for k in range(n1):
        t += dt; x += v * dt
        rows.append((t, x, 0, x, v * dt * a / AF))
    for k in range(25):  # retract 1 mm over 50 ms, head still, off track
        t += dt
        rows.append((t, x, -1, np.nan, -1.0 / 25))
    for k in range(int(round(20 / 100 / dt))):  # travel at 100 mm/s
        t += dt; x += 100 * dt
        rows.append((t, x, -1, np.nan, 0.0))
    for k in range(25):
        t += dt
        rows.append((t, x, -1, np.nan, 1.0 / 25))
    x0 = x
    rows.append((t + dt, x0, 1, 0.0, 0.0)); t += dt
    for k in range(n1):
        t += dt; x += v * dt
        rows.append((t, x, 1, x - x0, v * dt * a / AF))
    for k in range(500):  # dwell 1 s on the end of track 1: a blob
        t += dt
        rows.append((t, x, 1, x - x0, 0.0))
    r = np.array(rows, dtype=float)
    e = np.cumsum(r[:, 4])
    ve = np.concatenate([np.diff(e) / np.diff(r[:, 0]), [0.0]])
    tl = Timeline(t_s=r[:, 0], x_mm=r[:, 1], y_mm=0 * r[:, 1], z_mm=0 * r[:, 1] + h,
                  v_mm_s=np.zeros(len(r)), ve_mm_s=ve, e_mm=e, track=r[:, 2].astype(int), s_mm=r[:, 3])
    tracks = [Track(id=0, kind="test", points_mm=[[0, 0], [40, 0]], width_mm=w, height_mm=h, flow_mm3_s=0),
              Track(id=1, kind="test", points_mm=[[x0, 0], [x0 + 40, 0]], width_mm=w, height_mm=h,
                    flow_mm3_s=0)]
    return Manifest(printer=dict(PROFILE), pattern={}, tracks=tracks, timeline=tl)


@pytest.mark.parametrize("spec,values", [
    ("pa", {"pa.tau_s": 0.4}),
    ("pa+offset", {"pa.tau_s": 0.4, "offset.kc_mm": 0.3}),
    ("pa+backpressure+nonlinear", {"pa.tau_s": 0.4, "nonlinear.n": 0.6}),
])
def test_volume_conservation_with_retraction_travel_and_blob(spec, values):
    m = _retract_travel_manifest()
    vp = print_virtual(m, build_model(spec), values)
    assert vp.extruded_mm3 == pytest.approx(vp.commanded_mm3 - vp.stored_mm3, rel=1e-12, abs=1e-9)
    assert vp.deposited_mm3 + vp.dribble_mm3 == pytest.approx(vp.extruded_mm3, rel=1e-12)
    assert vp.dribble_mm3 > 0.01  # flow continues while retracting and travelling
    assert len(vp.blobs) == 1 and vp.blobs[0].track == 1


def test_blob_volume_at_a_dwell_is_the_stored_advance():
    # Linear model, dwell of T = 1 s after steady flow ve: ooze = tau*ve*(1 - exp(-T/tau)) * Af.
    m = _retract_travel_manifest()
    tau = 0.1
    vp = print_virtual(m, build_model("pa"), {"pa.tau_s": tau})
    ve = 40.0 * bead_area_mm2(0.5, 0.2) / AF
    assert vp.blobs[0].volume_mm3 == pytest.approx(tau * ve * (1 - np.exp(-1.0 / tau)) * AF, rel=1e-3)
    # The blob sits at the end of track 1 and widens the last station.
    s1, w1 = vp.widths[1]
    assert w1[-1] > 1.5 * np.median(w1)
    # every station printed; those the blob's disc covers are flagged as a picture shows them
    assert (vp.table.valid | (vp.table.flag == "blob")).all() and (vp.table.flag == "blob").sum() >= 3


def test_a_dwells_blob_is_a_disc_of_its_volume_at_the_layer_height():
    # fit/blobs.py: the blob of volume V at the end of track 1 is a disc of radius
    # r = sqrt(V / (pi h)); the stations within r read its chord 2 sqrt(r^2 - u^2) where
    # that is wider than the bead, the others the bead alone (the blob's volume is not in
    # their deposit windows: before, all of it went into the last station's 0.4 mm window)
    m = _retract_travel_manifest()
    tau, h = 0.1, 0.2
    vp = print_virtual(m, build_model("pa"), {"pa.tau_s": tau})
    V = vp.blobs[0].volume_mm3
    r = np.sqrt(V / (np.pi * h))
    assert vp.blobs[0].diameter_mm == pytest.approx(2 * r, rel=1e-12)
    assert 1.4 < 2 * r < 1.7                            # ~0.37 mm^3 at h 0.2 mm
    s1, w1 = vp.widths[1]
    t = vp.table
    bead = vp.bead_width_mm[t.track == 1]
    u = s1 - vp.blobs[0].s_mm
    chord = 2 * np.sqrt(np.clip(r * r - u * u, 0.0, None))
    np.testing.assert_allclose(w1, np.maximum(bead, chord), rtol=0, atol=1e-12)
    assert np.sum(chord > bead) >= 3                    # the disc spans several stations
    assert w1[-1] == pytest.approx(2 * r, rel=1e-9)
    # the bead under it is the steady bead: no blob volume in the windows
    assert np.max(np.abs(bead[-8:] - 0.5)) < 0.01
    # the fitter predicts the beads, not the disc (Model.predict: the measurement flags it)
    ctx = SimContext.build(m)
    w_pred = build_model("pa").predict(ctx, [tau])[0]
    ok = np.isfinite(w_pred)
    np.testing.assert_allclose(w_pred[ok], vp.bead_width_mm[ok], atol=1e-3)


def test_sum_of_station_areas_recovers_deposited_volume():
    m = straight_line(L=60.0)
    ctx = SimContext.build(m)
    sim = build_model("pa").simulate(ctx, [0.2])
    # Stations every 0.25 mm with 0.4 mm windows: integrate A(s) ds with the trapezoid rule.
    a = sim.area_mm2[0]
    vol = np.trapezoid(a, ctx.s_mm)
    deposited = sim.out_mm[0].sum() * AF
    assert vol == pytest.approx(deposited, rel=5e-3)


def test_ve_of_seed_000():
    tau = tau_from_ve_s(0.65, 2.85, 150.0, 0.6, 0.4)
    assert tau == pytest.approx(0.594, abs=0.001)     # seed 000: "tau ~ 0.6 s"
    assert ve_from_tau_us(tau, 2.85, 150.0, 0.6, 0.4) == pytest.approx(0.65, rel=1e-12)
    prof = {"filament_diameter_mm": 2.85, "bowden_length_mm": 150.0, "nozzle_land_length_mm": 0.6,
            "nozzle_diameter_mm": 0.4}
    m = straight_line()
    ctx = SimContext.build(m)
    w_ve = build_model("pa_ve", prof).predict(ctx, [0.65])
    w_tau = build_model("pa").predict(ctx, [float(tau)])
    np.testing.assert_allclose(w_ve, w_tau, atol=1e-12)


def test_vectorised_predict_equals_looped():
    m = _retract_travel_manifest()
    ctx = SimContext.build(m)
    model = build_model("pa+thermal+backpressure+bernoulli+nonlinear+offset+kalico_tanh+flow_gain"
                        "+bed_tilt+heading+backlash+spread")
    rng = np.random.default_rng(1)
    lo, hi = model.bounds.T
    lo = np.where(np.array([p.prior_kind == "loguniform" for p in model.params]), lo, lo)
    theta = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(6, len(lo)))
    theta[:, model.param_names.index("pa.tau_s")] = rng.uniform(0.02, 1.0, 6)
    theta[:, model.param_names.index("thermal.tau_s")] = rng.uniform(5, 50, 6)
    many = model.predict(ctx, theta)
    one = np.vstack([model.predict(ctx, th) for th in theta])
    np.testing.assert_allclose(many, one, rtol=0, atol=1e-12)
    assert model.log_prior(theta).shape == (6,) and np.isfinite(model.log_prior(theta)).all()


def test_model_api_names_bounds_prior():
    model = build_model("pa+thermal")
    assert model.param_names == ["pa.tau_s", "thermal.a", "thermal.tau_s"]
    assert model.bounds.shape == (3, 2)
    th = model.default_theta()
    assert np.isfinite(model.log_prior(th)).all()
    bad = th.copy(); bad[0] = 10.0
    assert model.log_prior(np.vstack([th, bad]))[1] == -np.inf
    # loguniform density on [0.005, 5]: -log(x) - log(log(1000))
    assert model.params[0].log_prior(0.5) == pytest.approx(-np.log(0.5) - np.log(np.log(1000.0)))
    m2 = model.with_values({"pa.tau_s": 0.8})
    assert m2.default_theta()[0] == 0.8 and model.default_theta()[0] == 0.5
    fixed = build_model("pa+thermal", fixed={"thermal.tau_s": 30.0})
    assert fixed.param_names == ["pa.tau_s", "thermal.a"]


def test_every_effect_can_be_absent_inside_its_prior():
    # compare/diagnose add any effect to any model: the "absent" value must be allowed.
    absent = {"nonlinear.n": 1.0, "bernoulli.k_s2_mm3": 0.0, "backpressure.kb": 0.0,
              "offset.kc_mm": 0.0, "kalico_tanh.off_mm": 0.0, "kalico_recip.off_mm": 0.0,
              "thermal.a": 0.0, "backlash.be_mm": 0.0, "flow_gain.gain": 1.0, "bed_tilt.gx": 0.0,
              "bed_tilt.gy": 0.0, "heading.a_mm": 0.0, "heading.b_mm": 0.0, "spread.sigma_mm": 0.0}
    spec = "pa+" + "+".join(sorted({k.split(".")[0] for k in absent}))
    model = build_model(spec)
    th = model.theta_from(absent)
    assert np.isfinite(model.log_prior(th)).all()
    m = straight_line(L=40.0)
    ctx = SimContext.build(m)
    w_all = model.predict(ctx, th)
    w_pa = build_model("pa").predict(ctx, [model.default_theta()[0]])
    np.testing.assert_allclose(w_all, w_pa, atol=1e-9)


def test_bad_names_raise_user_error():
    with pytest.raises(UserError, match=r"unknown effect\(s\) 'pressure' in model 'pa\+pressure'; known effects: .*backpressure"):
        build_model("pa+pressure")
    with pytest.raises(UserError, match="appear twice"):
        build_model("pa+pa")
    with pytest.raises(UserError, match=r"unknown parameter\(s\) pa.k_s"):
        build_model("pa").with_values({"pa.k_s": 0.1})
    with pytest.raises(UserError, match="outside its bounds"):
        build_model("pa").with_values({"pa.tau_s": 50.0})
    with pytest.raises(UserError, match="pa_ve needs a printer profile"):
        build_model("pa_ve")


def test_spread_is_a_gaussian_smoothing_along_each_track():
    """fit.effects.Spread against its equation computed directly: a width step becomes
    lo + (hi - lo) Phi(d / sigma) in the interior of a track, a ramp stays a ramp, two
    tracks never mix, NaN (never printed) stays NaN, sigma = 0 is the identity; several
    parameter sets at once (the parallel kernel) equal one at a time."""
    from types import SimpleNamespace

    from scipy.stats import norm

    from fit.effects import Spread

    s1 = np.arange(0.0, 20.0, 0.05)
    n = len(s1)
    s = np.r_[s1, s1]
    track = np.r_[np.zeros(n, int), np.ones(n, int)]
    w = np.r_[np.where(s1 < 10.0, 0.4, 0.8), 0.3 + 0.01 * s1]
    w[n + 50] = np.nan
    perm = np.random.default_rng(0).permutation(2 * n)       # stations in any order
    ctx = SimpleNamespace(s_mm=s[perm], s_track=track[perm], cache={})
    eff = Spread()
    sig = np.array([[0.3], [0.0], [0.15]])
    out = eff.width(ctx, w[perm][None, :], {"sigma_mm": sig})
    back = np.empty_like(out)
    back[:, perm] = out
    step = back[0, :n]
    mid = (s1 > 5) & (s1 < 15)
    np.testing.assert_allclose(step[mid], 0.4 + 0.4 * norm.cdf((s1[mid] - 10.0 + 0.025) / 0.3), atol=2e-3)
    assert step[0] == pytest.approx(0.4) and step[-1] == pytest.approx(0.8)   # no mixing with track 1
    ramp = back[0, n:]
    inner = (s1 > 2) & (s1 < 18) & (np.abs(s1 - 2.5) > 1.3)                  # away from the NaN
    np.testing.assert_allclose(ramp[inner], (0.3 + 0.01 * s1)[inner], atol=1e-6)  # 4-sigma cut
    assert np.isnan(ramp[50]) and np.isfinite(np.delete(ramp, 50)).all()
    np.testing.assert_array_equal(back[1], np.where(np.isnan(w), np.nan, w))
    one = eff.width(ctx, w[perm][None, :], {"sigma_mm": sig[2:3]})
    np.testing.assert_allclose(out[2], one[0], rtol=0, atol=1e-15)
