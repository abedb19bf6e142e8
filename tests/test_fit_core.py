"""Likelihood, priors, MAP/MCMC, joint fits and derived values on a tiny analytic model.

The toy model is a first-order step response (the linear PA law, seed 001): after a flow
step at the start of each track the width relaxes as
    w(t) = g * (w_lo + (w_hi - w_lo) * (1 - exp(-t / tau)))
with the same predict/params interface as fit.model.Model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.stats import multivariate_normal, t as student_t

from calib.errors import UserError
from fit.data import ScanData
from fit.derived import derived_values, firmware_commands, kalico_match, ve_s_from_tau
from fit.likelihood import JointProblem, NoiseOptions, ar1_phi, pointwise_loglik
from fit.params import Param
from fit.priors import Prior, apply_overrides, load_priors_file, prior_from_param
from fit.sampler import fit_map, fit_mcmc
from measure.table import WidthTable
from patterns.manifest import Samples


@dataclass
class ToyCtx:
    t_s: np.ndarray
    w_lo_mm: np.ndarray
    w_hi_mm: np.ndarray


class ToyModel:
    spec = "toy"

    def __init__(self, with_gain=True):
        self.params = [Param("pa.tau_s", "s", 0.2, 0.01, 3.0, "loguniform")]
        if with_gain:
            self.params.append(Param("flow_gain.gain", "1", 1.0, 0.8, 1.2))
        self.param_names = [p.name for p in self.params]

    def default_theta(self):
        return np.array([p.default for p in self.params])

    def predict(self, ctx, theta):
        th = np.atleast_2d(theta)
        tau = th[:, :1]
        g = th[:, 1:2] if th.shape[1] > 1 else 1.0
        return g * (ctx.w_lo_mm + (ctx.w_hi_mm - ctx.w_lo_mm) * (1 - np.exp(-ctx.t_s / tau)))


def make_scan(name="scan", tau=0.3, gain=1.0, sd=0.005, sig=0.015, ell=0.6, seed=0,
              n_tracks=6, n_per=120, v_mm_s=20.0, model=None, outliers=0):
    """Synthetic widths drawn *exactly* from the likelihood's noise model."""
    rng = np.random.default_rng(seed)
    model = model or ToyModel()
    s1 = 0.25 * np.arange(n_per)
    track = np.repeat(np.arange(n_tracks), n_per)
    s = np.tile(s1, n_tracks)
    t = s / v_mm_s
    lo = np.where(track % 2 == 0, 0.35, 0.6)
    hi = np.where(track % 2 == 0, 0.6, 0.35)
    ctx = ToyCtx(t, lo, hi)
    th = np.array([tau, gain])[: len(model.param_names)]
    w_true = model.predict(ctx, th)[0]
    phi = math.exp(-0.25 / ell)
    e = np.empty(len(s))       # the OU wobble (sig, ell), then white measurement noise (sd)
    for i in range(len(s)):
        if s[i] == 0:
            e[i] = rng.standard_normal()
        else:
            e[i] = phi * e[i - 1] + math.sqrt(1 - phi ** 2) * rng.standard_normal()
    y = w_true + sig * e + sd * rng.standard_normal(len(s))
    if outliers:
        k = rng.choice(len(y), outliers, replace=False)
        y[k] += 0.3
    n = len(s)
    table = WidthTable(track=track, s_mm=s, x_mm=s, y_mm=track * 3.0, t_s=t, width_mm=y,
                       width_sd_mm=np.full(n, sd), valid=np.ones(n, bool))
    samples = Samples(track=track, s_mm=s, x_mm=s, y_mm=track * 3.0, t_s=t, nx=np.zeros(n),
                      ny=np.ones(n), width_nominal_mm=hi, height_mm=np.full(n, 0.2))
    from fit.data import scan_from_table  # noqa: F401  (the real path needs a manifest)
    gap = np.where(s == 0, np.inf, 0.25)
    return ScanData(name=name, manifest=None, table=table, samples=samples,
                    order=np.arange(n), y_mm=y, sd_mm=np.full(n, sd), gap_mm=gap, ctx=ctx)


# -- likelihood ------------------------------------------------------------------------
def test_loglik_equals_exact_multivariate_normal():
    """Sum of the pointwise terms is the exact density of an OU process (sigma_extra, ell)
    seen through white measurement noise of per-station sd: covariance
    diag(sd^2) + sig^2 exp(-|s_i - s_j| / ell), with a gap and two tracks; and with a
    second, short OU process added (the short wobble)."""
    rng = np.random.default_rng(1)
    n, sig, ell = 40, 0.02, 0.7
    sd = rng.uniform(0.005, 0.015, n)
    s = np.cumsum(np.r_[0.0, np.where(np.arange(1, n) == 17, 1.5, 0.25)])
    new_track = np.arange(n) == 25
    r = rng.normal(0, 0.02, n)
    track = np.cumsum(new_track)
    C = sig ** 2 * np.exp(-np.abs(np.subtract.outer(s, s)) / ell) * (track[:, None] == track[None, :])
    C += np.diag(sd ** 2)
    exact = multivariate_normal(np.zeros(n), C).logpdf(r)
    gap = np.r_[np.inf, np.diff(s)]
    gap[new_track] = np.inf
    ll = pointwise_loglik(r[None], sd, sig, ar1_phi(gap, np.array([[ell]])))
    assert ll.sum() == pytest.approx(exact, rel=1e-10)
    # the compiled kernel of the sampler gives the same terms
    from fit.likelihood import _AR1_SERIAL
    out = np.empty((1, n))
    _AR1_SERIAL(r[None] * 0 + 1.0, np.arange(n), 1.0 + r, sd ** 2, np.zeros(n), gap, np.array([sig]), np.zeros(1), 0.5,
                np.array([ell]), np.zeros(1), 0.4, np.zeros(1), -1.0, 0.0, out)
    assert np.allclose(out, ll, rtol=1e-12, atol=1e-12)
    # with the short wobble (sd sig_s, correlation length ell_s): the sum of two OU
    # processes, covariance diag(sd^2) + sig^2 exp(-|d| / ell) + sig_s^2 exp(-|d| / ell_s)
    sig_s, ell_s = 0.015, 0.4
    C2 = C + sig_s ** 2 * np.exp(-np.abs(np.subtract.outer(s, s)) / ell_s) * (track[:, None] == track[None, :])
    exact2 = multivariate_normal(np.zeros(n), C2).logpdf(r)
    ll2 = pointwise_loglik(r[None], sd, sig, ar1_phi(gap, np.array([[ell]])), sigma_short_mm=sig_s,
                           phi_short=ar1_phi(gap, np.array([[ell_s]])))
    assert ll2.sum() == pytest.approx(exact2, rel=1e-10)
    assert abs(exact2 - exact) > 1.0            # the short wobble changes the density
    _AR1_SERIAL(r[None] * 0 + 1.0, np.arange(n), 1.0 + r, sd ** 2, np.zeros(n), gap, np.array([sig]), np.zeros(1), 0.5,
                np.array([ell]), np.array([sig_s]), ell_s, np.zeros(1), -1.0, 0.0, out)
    assert np.allclose(out, ll2, rtol=1e-12, atol=1e-12)


def test_relative_wobble_is_exact_gaussian_loglik():
    """With the relative wobble the long wobble's sd at station i is h_i = sig sqrt(1 - f +
    f (m_i / w_ref)^2), m_i the model width: covariance diag(sd^2) + h_i h_j exp(-|d| / ell)
    within a track. The Kalman filter (reference and compiled) gives the dense Gaussian's
    log-density, and f = 0 gives the plain filter's terms."""
    from fit.likelihood import _AR1_SERIAL
    rng = np.random.default_rng(4)
    n, sig, f, w_ref, ell = 50, 0.008, 0.7, 0.6, 3.0
    sd = rng.uniform(0.002, 0.006, n)
    m = rng.uniform(0.3, 1.2, n)                     # model widths (mm)
    s = np.cumsum(rng.uniform(0.1, 0.6, n))
    track = (np.arange(n) >= 30).astype(int)
    gap = np.r_[np.inf, np.diff(s)]
    gap[30] = np.inf
    h = sig * np.sqrt(1 - f + f * (m / w_ref) ** 2)
    C = np.outer(h, h) * np.exp(-np.abs(np.subtract.outer(s, s)) / ell) * (track[:, None] == track[None, :])
    C += np.diag(sd ** 2)
    y = m + rng.multivariate_normal(np.zeros(n), C)
    exact = multivariate_normal(m, C).logpdf(y)
    # the reference: h^2 = fixed^2 + rel^2 (JointProblem.wobble_parts)
    ll = pointwise_loglik((y - m)[None], sd, sig * math.sqrt(1 - f), ar1_phi(gap, [[ell]]),
                          rel_mm=(sig * math.sqrt(f) * m / w_ref)[None])
    assert ll.sum() == pytest.approx(exact, rel=1e-10)
    out = np.empty((1, n))
    _AR1_SERIAL(m[None], np.arange(n), y, sd ** 2, np.zeros(n), gap, np.array([sig]), np.array([f]), w_ref,
                np.array([ell]), np.zeros(1), 0.4, np.zeros(1), -1.0, 0.0, out)
    assert np.allclose(out, ll, rtol=1e-12, atol=1e-12)
    _AR1_SERIAL(m[None], np.arange(n), y, sd ** 2, np.zeros(n), gap, np.array([sig]), np.zeros(1), w_ref,
                np.array([ell]), np.zeros(1), 0.4, np.zeros(1), -1.0, 0.0, out)
    assert np.allclose(out, pointwise_loglik((y - m)[None], sd, sig, ar1_phi(gap, [[ell]])), rtol=1e-12)


def test_neighbour_correlated_measurement_errors_are_exact_gaussian_loglik():
    """The despeckled stations' errors correlate with their predecessor's (the table links
    them: width_corr_prev; fit/likelihood.py "Neighbouring stations' errors"): within a
    linked run, corr(eps_i, eps_j) = rho^|i - j|, covariance sd_i sd_j rho^|i - j|, none
    across a break. The Kalman filter (reference and compiled, with both wobbles, with the
    relative wobble) gives the dense Gaussian's log-density; rho = 0 gives the independent
    filter's terms."""
    from fit.likelihood import _AR1_SERIAL
    rng = np.random.default_rng(7)
    n, sig, ell, sig_s, ell_s, rho = 60, 0.006, 2.0, 0.004, 0.4, 0.7
    sd = rng.uniform(0.002, 0.008, n)
    s = np.cumsum(np.full(n, 0.25))
    track = (np.arange(n) >= 35).astype(int)
    gap = np.r_[np.inf, np.diff(s)]
    gap[35] = np.inf
    link = np.ones(n)
    link[[0, 12, 35, 50]] = 0.0      # track starts, a station after an invalid one, an unfiltered one
    run = np.cumsum(link == 0)
    k = np.arange(n)
    meas = (np.outer(sd, sd) * rho ** np.abs(np.subtract.outer(k, k)) * (run[:, None] == run[None, :]))
    same = track[:, None] == track[None, :]
    d = np.abs(np.subtract.outer(s, s))
    wob = (sig ** 2 * np.exp(-d / ell) + sig_s ** 2 * np.exp(-d / ell_s)) * same
    m = rng.uniform(0.3, 0.8, n)
    y = m + rng.multivariate_normal(np.zeros(n), meas + wob)
    exact = multivariate_normal(m, meas + wob).logpdf(y)
    ll = pointwise_loglik((y - m)[None], sd, sig, ar1_phi(gap, [[ell]]), sigma_short_mm=sig_s,
                          phi_short=ar1_phi(gap, [[ell_s]]), link=link, rho_m=rho)
    assert ll.sum() == pytest.approx(exact, rel=1e-10)
    out = np.empty((1, n))
    _AR1_SERIAL(m[None], np.arange(n), y, sd ** 2, link, gap, np.array([sig]), np.zeros(1), 0.5,
                np.array([ell]), np.array([sig_s]), ell_s, np.array([rho]), -1.0, 0.0, out)
    assert np.allclose(out, ll, rtol=1e-12, atol=1e-12)
    # the relative wobble too: h_i = sig sqrt(1 - f + f (m_i / w_ref)^2)
    f, w_ref = 0.6, 0.5
    h = sig * np.sqrt(1 - f + f * (m / w_ref) ** 2)
    C3 = meas + (np.outer(h, h) * np.exp(-d / ell) + sig_s ** 2 * np.exp(-d / ell_s)) * same
    _AR1_SERIAL(m[None], np.arange(n), y, sd ** 2, link, gap, np.array([sig]), np.array([f]), w_ref,
                np.array([ell]), np.array([sig_s]), ell_s, np.array([rho]), -1.0, 0.0, out)
    assert out.sum() == pytest.approx(multivariate_normal(m, C3).logpdf(y), rel=1e-10)
    # the correlation matters, and 0 is the independent filter
    assert abs(multivariate_normal(m, np.diag(sd ** 2) + wob).logpdf(y) - exact) > 1.0
    ll0 = pointwise_loglik((y - m)[None], sd, sig, ar1_phi(gap, [[ell]]), link=link, rho_m=0.0)
    assert np.allclose(ll0, pointwise_loglik((y - m)[None], sd, sig, ar1_phi(gap, [[ell]])), rtol=1e-12)


def test_linked_measurement_errors_recover_their_correlation():
    """Toy scan whose measurement errors (sd 5 um) correlate 0.7 between linked neighbours
    (rho^k at k stations) and whose wobble is negligible: the fit with the links reads
    noise.meas_corr 0.7 +- 0.1, tau within 3 of its sds of the truth, and describes the
    data better than the fit that takes the errors as independent (ln L higher by more
    than 20). That one's wobble takes most of the correlation (its length free down to
    0.02 mm): its sd of tau is within 30 % of the linked fit's, not the 2.4x smaller an
    independent white term alone would give."""
    from fit.likelihood import MEAS_NAME
    rho, sd = 0.7, 0.005
    sc = make_scan(seed=3, sd=0.0, sig=1e-4, tau=0.3)
    rng = np.random.default_rng(11)
    n = len(sc.y_mm)
    first = sc.gap_mm == np.inf
    e = np.empty(n)
    for i in range(n):
        e[i] = rng.standard_normal() if first[i] else rho * e[i - 1] + math.sqrt(1 - rho ** 2) * rng.standard_normal()
    sc.y_mm = sc.y_mm + sd * e
    sc.sd_mm = np.full(n, sd)
    sc.corr_prev = np.where(first, 0.0, 0.45)
    linked = fit_map(JointProblem([sc], [ToyModel()]))
    names = linked.param_names
    assert linked.theta[names.index(MEAS_NAME)] == pytest.approx(rho, abs=0.1)
    sd_linked = math.sqrt(linked.cov[0, 0])
    assert abs(linked.theta[0] - 0.3) < 3 * sd_linked
    indep = fit_map(JointProblem([sc], [ToyModel()], NoiseOptions(meas_corr=False)))
    assert MEAS_NAME not in indep.param_names
    assert linked.loglik > indep.loglik + 20.0
    assert 0.7 * sd_linked < math.sqrt(indep.cov[0, 0]) < 1.3 * sd_linked


def test_ar1_gap_uses_rho_to_the_power_of_the_gap():
    """Two samples 1 mm apart: correlation exp(-1/ell), as an OU process."""
    ell, sd, sig = 0.5, 0.004, 0.01
    r = np.array([0.012, -0.004])
    rho = math.exp(-1.0 / ell)
    exact = multivariate_normal(np.zeros(2), sig ** 2 * np.array([[1, rho], [rho, 1]])
                                + sd ** 2 * np.eye(2)).logpdf(r)
    ll = pointwise_loglik(r[None], np.full(2, sd), sig, ar1_phi(np.array([np.inf, 1.0]), [[ell]]))
    assert ll.sum() == pytest.approx(exact, rel=1e-10)


def test_long_wobble_is_bounded_by_a_quarter_of_the_track():
    """A wobble longer than the tracks is a free offset per track (fit/likelihood.py, "Why
    the long wobble is shorter than a track"): its length's prior ends at a quarter of the
    typical track's span, never below twice its start, and a long track keeps 50 mm."""
    from fit.likelihood import CORR_NAME, corr_prior_of, track_span_mm

    def upper(n_per, **kw):
        sc = make_scan(n_per=n_per)
        noise = NoiseOptions(**kw)
        pb = JointProblem([sc], [ToyModel()], noise)
        p = pb.priors[pb.param_names.index(CORR_NAME)]
        assert p == corr_prior_of(sc, noise)
        return track_span_mm(sc), p.lower, p.upper

    assert upper(241) == pytest.approx((60.0, 0.02, 15.0))
    assert upper(241, corr_max_track_share=None)[2] == 50.0
    assert upper(241, short=True)[1:] == pytest.approx((2.0, 15.0))
    assert upper(1201)[2] == 50.0                       # 300 mm: the prior's own bound
    assert upper(20)[2] == pytest.approx(4.75 / 4)
    assert upper(20, short=True)[1:] == pytest.approx((2.0, 4.0))


def test_student_t_pointwise_matches_scipy():
    r = np.array([0.01, -0.3, 0.002])
    ll = pointwise_loglik(r[None], np.full(3, 0.02), 0.0, None, student_nu=4)
    assert np.allclose(ll[0], student_t(4, scale=0.02).logpdf(r))


# -- priors ------------------------------------------------------------------------------
def test_loguniform_prior_density_normalised_and_truncated():
    p = Prior("loguniform", 0.01, 1.0)
    x = np.geomspace(0.01, 1.0, 20001)
    assert np.trapezoid(np.exp(p.log_prob(x)), x) == pytest.approx(1.0, rel=1e-3)
    assert p.log_prob(1.5) == -np.inf


def test_prior_from_param_tuple_and_overrides_file(tmp_path):
    pr = prior_from_param(Param("a", "s", 0.5, 0.0, 1.0, ("normal", 0.4, 0.1)))
    assert (pr.kind, pr.mu, pr.sd) == ("normal", 0.4, 0.1)
    f = tmp_path / "p.toml"
    f.write_text('["pa.tau_s"]\nprior = "normal"\nmu = 0.3\nsd = 0.01\n')
    out = apply_overrides({"pa.tau_s": Prior("loguniform", 0.01, 3)}, load_priors_file(f))
    assert out["pa.tau_s"].kind == "normal" and out["pa.tau_s"].mu == 0.3
    f.write_text('["pa.nope"]\nprior = "uniform"\n')
    with pytest.raises(UserError, match="does not have"):
        apply_overrides({"pa.tau_s": Prior("loguniform", 0.01, 3)}, load_priors_file(f))


def test_strong_prior_override_pulls_the_posterior():
    sc = make_scan(tau=0.3, seed=3)
    pb = JointProblem([sc], [ToyModel()], prior_overrides={"pa.tau_s": {"prior": "normal", "mu": 0.5,
                                                                         "sd": 0.001}})
    m = fit_map(pb)
    assert m.values["pa.tau_s"] == pytest.approx(0.5, abs=0.005)


# -- MAP / MCMC --------------------------------------------------------------------------
def test_map_recovers_tau_and_gain_and_reports_information():
    sc = make_scan(tau=0.3, gain=1.05, seed=2)
    m = fit_map(ToyModel(), sc)
    assert m.values["pa.tau_s"] == pytest.approx(0.3, rel=0.05)
    assert m.values["flow_gain.gain"] == pytest.approx(1.05, rel=0.01)
    n = sc.n_valid
    assert m.bic == pytest.approx(m.k * math.log(n) - 2 * m.loglik)
    assert m.pointwise.shape == (n,) and m.pointwise.sum() == pytest.approx(m.loglik)
    # widths scatter ~0.016 mm around the truth; the residual RMS must show it
    assert 0.010 < m.rms_mm < 0.025
    assert m.k == 5 and m.k_model == 2        # noise: the wobble's sd, its relative share, its length


def test_mcmc_recovers_tau_with_honest_diagnostics():
    sc = make_scan(tau=0.3, gain=1.0, seed=6)
    r = fit_mcmc(ToyModel(), sc, seed=1, progress=False, max_steps=6000)
    assert r.converged, r.diagnostics.get("warning")
    p = r.params["pa.tau_s"]
    assert p.ci95[0] < 0.3 < p.ci95[1]
    assert p.ci95[1] - p.ci95[0] < 0.1
    assert all(v < 1.01 for v in r.diagnostics["rhat"].values())
    assert 0.1 < r.diagnostics["acceptance_fraction"] < 0.9
    assert r.diagnostics["n_steps"] >= 50 * max(r.diagnostics["tau_steps"].values())
    assert r.loo["pareto_k_max"] < 0.7
    # p_loo ~ number of effectively free parameters (4 here)
    assert 1.5 < r.loo["p_loo"] < 10


def test_interval_coverage_small_seed_set():
    """90 % intervals contain the truth in most of 10 datasets (binomial 90 %: 7..10)."""
    hits = 0
    for seed in range(10):
        sc = make_scan(tau=0.25, gain=0.95, seed=100 + seed, n_tracks=4, n_per=100)
        # short chains (30 tau, no tau-stability wait) keep the test fast; intervals are
        # still from >= 30 tau x 32 walkers, i.e. hundreds of independent draws
        r = fit_mcmc(ToyModel(), sc, seed=seed, progress=False, max_steps=1500, tau_factor=30,
                     tau_rtol=1.0, n_loo_draws=30)
        lo, hi = r.params["pa.tau_s"].ci90
        hits += lo < 0.25 < hi
    assert 7 <= hits <= 10


def test_non_convergence_is_reported():
    sc = make_scan(seed=7)
    r = fit_mcmc(ToyModel(), sc, seed=0, progress=False, max_steps=60, check_every=20,
                 n_loo_draws=50)
    assert not r.converged
    assert r.diagnostics["stop_reason"] == "max_steps"
    assert "NOT CONVERGED" in r.diagnostics["warning"]


def test_no_loo_draws_gives_map_predictions_and_no_loo():
    """n_loo_draws=0 skips LOO (NaN, said so) and the prediction band collapses onto the
    MAP prediction instead of failing on an empty set of draws."""
    sc = make_scan(seed=7)
    r = fit_mcmc(ToyModel(), sc, seed=0, progress=False, max_steps=60, check_every=20,
                 n_loo_draws=0)
    assert np.isnan(r.loo["elpd_loo"]) and "too few" in r.loo["warning"]
    p = r.predictions[0]
    assert p["pred_lo68_mm"] == p["pred_map_mm"] == p["pred_hi68_mm"]
    assert len(p["pred_map_mm"]) == len(p["width_mm"])


def test_sampler_keeps_going_until_the_ensembles_agree():
    """The autocorrelation rule alone is not convergence: with an R-hat bar no finite chain
    reaches (1.00001), the sampler must not stop at ~50 tau and call it done, but run to
    its cap and say that R-hat, not the chain length, is what was missing."""
    sc = make_scan(seed=7, n_tracks=2, n_per=80)
    r = fit_mcmc(ToyModel(), sc, seed=0, progress=False, max_steps=900, check_every=50,
                 tau_factor=10, tau_rtol=1.0, rhat_max=1.00001, n_loo_draws=30)
    d = r.diagnostics
    assert d["stop_reason"] == "max_steps" and d["n_steps"] == 900
    assert d["n_steps"] > 10 * max(d["tau_steps"].values())   # long enough by the tau rule
    assert "R-hat" in d["warning"] and not r.converged
    # a reachable bar on the same data stops on both criteria, well before the cap
    ok = fit_mcmc(ToyModel(), sc, seed=0, progress=False, max_steps=6000, n_loo_draws=30)
    assert ok.converged and ok.diagnostics["stop_reason"] == "converged"
    assert max(ok.diagnostics["rhat"].values()) < 1.01
    assert ok.diagnostics["n_steps"] > 50 * max(ok.diagnostics["tau_steps"].values())


def test_joint_fit_shares_tau_and_keeps_per_scan_gains():
    a = make_scan("a", tau=0.4, gain=0.95, seed=11, n_tracks=4)
    b = make_scan("b", tau=0.4, gain=1.08, seed=12, n_tracks=4)
    pb = JointProblem([a, b], [ToyModel(), ToyModel()])
    assert pb.param_names[:3] == ["pa.tau_s", "flow_gain.gain@a", "flow_gain.gain@b"]
    m = fit_map(pb)
    v = m.values
    assert v["pa.tau_s"] == pytest.approx(0.4, rel=0.06)
    assert v["flow_gain.gain@a"] == pytest.approx(0.95, rel=0.01)
    assert v["flow_gain.gain@b"] == pytest.approx(1.08, rel=0.01)
    # a joint fit is more precise than either scan alone
    sa = math.sqrt(fit_map(ToyModel(), a).cov[0, 0])
    assert math.sqrt(m.cov[0, 0]) < sa


def test_student_t_resists_outliers():
    sc = make_scan(tau=0.3, seed=21, outliers=25, sig=0.005)
    g = fit_map(JointProblem([sc], [ToyModel()], NoiseOptions(ar1=False)))
    t = fit_map(JointProblem([sc], [ToyModel()], NoiseOptions(ar1=False, student_nu=3)))
    assert abs(t.values["flow_gain.gain"] - 1) < abs(g.values["flow_gain.gain"] - 1)
    assert t.values["pa.tau_s"] == pytest.approx(0.3, rel=0.05)


# -- derived -------------------------------------------------------------------------------
def test_kisslicer_ve_seed000_example():
    """Seed 000: D=2.85, L=150, l=0.6, d=0.4 mm, tau 0.594 s -> VE 0.65 us."""
    ve = ve_s_from_tau(0.594, 2.85, 150, 0.6, 0.4)
    assert ve * 1e6 == pytest.approx(0.65, abs=0.005)
    d = derived_values(["pa.tau_s"], np.full((10, 1), 0.594),
                       {"filament_diameter_mm": 2.85, "bowden_length_mm": 150,
                        "nozzle_land_length_mm": 0.6, "nozzle_diameter_mm": 0.4})
    assert d["kisslicer_ve_us"]["median"] == pytest.approx(0.65, abs=0.005)
    assert d["firmware"]["marlin"] == "M900 K0.5940"
    assert d["firmware"]["rrf"] == "M572 D0 S0.5940"
    assert d["firmware"]["klipper"] == "SET_PRESSURE_ADVANCE ADVANCE=0.5940"


def test_kalico_match_recovers_its_own_curve():
    """A curve that *is* Kalico tanh (REFERENCE example LA=0.017, off=0.12, v_lin=1) is matched."""
    fit = kalico_match(lambda v: 0.017 * v + 0.12 * np.tanh(v / 1.0), 20.0, "tanh", n=200)
    assert fit["pressure_advance_s"] == pytest.approx(0.017, rel=0.02)
    assert fit["offset_mm"] == pytest.approx(0.12, rel=0.05)
    assert fit["rms_mm"] < 1e-4
    assert firmware_commands(0.04)["klipper_config"].endswith("pressure_advance: 0.0400")


def test_duet3d_peer_recovers_pa_from_exponential_steps():
    """Seed 004: steps every 30 mm at R = 20 mm/s with tau = 0.3 s -> PA = 1/(C R) = 0.3 s."""
    from fit.peers import duet3d_pa

    s = np.arange(0, 240, 0.25)
    x = s % 30
    up = (s // 30) % 2 == 0
    rise = 1 - np.exp(-x / (0.3 * 20))
    w = np.where(up, 0.35 + 0.25 * rise, 0.6 - 0.25 * rise) + 0.01 * np.sin(s / 7)
    assert duet3d_pa(s, w, 30.0, 20.0) == pytest.approx(0.3, rel=0.05)


# -- influence: the MAP's linear response to the data (fit/influence.py) ---------------
def test_influence_predicts_how_far_a_width_error_moves_the_map():
    """Known answer: refit the MAP after adding a known width error; eq. (1) must predict the
    shift of each parameter, and its attribution must add up to it."""
    from dataclasses import replace

    from fit.influence import influence
    from fit.sampler import make_problem

    sc = make_scan(tau=0.3, gain=1.05, seed=2)
    m0 = fit_map(ToyModel(), sc)
    infl = influence(make_problem(ToyModel(), sc), m0.theta)
    assert infl.names == ["pa.tau_s", "flow_gain.gain"] and infl.A.shape == (2, sc.n_valid)
    t = sc.table.t_s[infl.rows]
    rising = sc.table.track[infl.rows] % 2 == 0          # make_scan: even tracks step 0.35 -> 0.6 mm
    # 4 um narrower in the first 0.2 s of every rising step: reads as a slower rise (tau up)
    e = np.where(rising & (t < 0.2), -0.004, 0.0)
    pred = infl.shift(e)
    m1 = fit_map(ToyModel(), replace(sc, y_mm=sc.y_mm + e), x0=m0.theta)
    for name in infl.names:
        actual = m1.values[name] - m0.values[name]
        assert abs(actual) > 1e-4
        assert pred[name] == pytest.approx(actual, rel=0.15), name
    assert pred["pa.tau_s"] > 0
    parts = infl.attribute("pa.tau_s", e, np.where(t < 0.1, "early", "late"))
    assert sum(parts.values()) == pytest.approx(pred["pa.tau_s"])
    # widths 1 % wider everywhere is exactly a gain 1 % higher (w = g w_c): tau stays
    w = ToyModel().predict(sc.ctx, m0.theta[:2])[0]
    scaled = infl.shift(0.01 * w)
    assert scaled["flow_gain.gain"] == pytest.approx(0.01 * m0.values["flow_gain.gain"], rel=0.02)
    assert abs(scaled["pa.tau_s"]) < 0.02 * abs(pred["pa.tau_s"])


def _two_width_track(rel, add, seed):
    """400 mm of bead alternating 0.3 and 0.9 mm every 40 mm (model: a + b z, z the block
    indicator), its width wandering along an OU process of 20 mm by ``rel`` x the width plus
    ``add`` mm, measured with a 2 um sd."""
    from test_discover_compare import LineModel, _scan

    rng = np.random.default_rng(seed)
    s = np.arange(0.0, 400.0, 0.25)
    z = (s // 40.0) % 2
    w = 0.3 + 0.6 * z
    phi = math.exp(-0.25 / 20.0)
    ou = np.zeros((2, len(s)))
    ou[:, 0] = rng.standard_normal(2)
    for i in range(1, len(s)):
        ou[:, i] = phi * ou[:, i - 1] + math.sqrt(1 - phi * phi) * rng.standard_normal(2)
    y = w + rel * w * ou[0] + add * ou[1] + 0.002 * rng.standard_normal(len(s))
    sc = _scan(s, y, 0.002)
    sc.ctx = z
    sc.samples.width_nominal_mm = w          # the commanded width the relative wobble grows with
    return sc, LineModel()


@pytest.mark.parametrize("seed", [0, 1])
def test_relative_wobble_is_told_from_an_additive_one(seed):
    """The wobble's form recovered from data made with a known one (beads of 0.3 and 0.9
    mm): a 2 % wobble of the width reads a
    relative share near 1 and the width-independent fit is worse by far in ln L (150-170);
    a 9 um additive wobble reads a share near 0, sigma_extra ~9 um, and gains nothing."""
    from fit.likelihood import JointProblem, NoiseOptions, REL_NAME

    sc, model = _two_width_track(0.02, 0.0, seed)
    pb = JointProblem([sc], [model], NoiseOptions())
    m = fit_map(pb, seed=seed)
    v = dict(zip(m.param_names, m.theta))
    assert v[REL_NAME] > 0.9
    # sigma_extra is the wobble's sd at the median commanded width: 2 % of it
    assert v["noise.sigma_extra_mm"] == pytest.approx(0.02 * float(np.median(sc.samples.width_nominal_mm)), rel=0.3)
    plain = fit_map(JointProblem([sc], [model], NoiseOptions(relative=False)), seed=seed)
    assert m.loglik - plain.loglik > 20.0
    sc, model = _two_width_track(0.0, 0.009, seed)
    m = fit_map(JointProblem([sc], [model], NoiseOptions()), seed=seed)
    v = dict(zip(m.param_names, m.theta))
    assert v[REL_NAME] < 0.3
    assert 0.006 < v["noise.sigma_extra_mm"] < 0.012
    plain = fit_map(JointProblem([sc], [model], NoiseOptions(relative=False)), seed=seed)
    assert m.loglik - plain.loglik < 5.0


def test_laplace_sds_survive_a_parameter_at_its_bound():
    """Ordinary least squares, known answer: y = a + b x with a known sd of 0.2 mm, scatter
    within it, so the extra noise sits at its floor (1e-4 mm). The Laplace sds of a and b
    are the OLS ones, sd_b = 0.2 / sqrt(Sxx), sd_a = 0.2 sqrt(1/n + xbar^2 / Sxx); before,
    the one parameter at its bound cost both of them their curvature (every sd 0.01)."""
    from test_discover_compare import X, Y, LineModel, _scan

    m = fit_map(JointProblem([_scan(X, Y, 0.2)], [LineModel()], NoiseOptions(ar1=False, relative=False)))
    sd = dict(zip(m.param_names, np.sqrt(np.diag(m.cov))))
    assert m.theta[m.param_names.index("noise.sigma_extra_mm")] < 2e-4
    sxx = float(np.sum((X - X.mean()) ** 2))
    assert sd["line.b_mm"] == pytest.approx(0.2 / math.sqrt(sxx), rel=0.02)
    assert sd["line.a_mm"] == pytest.approx(0.2 * math.sqrt(1 / len(X) + X.mean() ** 2 / sxx), rel=0.02)


def test_grouped_move_frees_a_walker_started_outside_the_support_without_warnings():
    """A walker at log p = -inf (an initial ball's fallback at a bound) takes the first
    proposal inside the support (inf > log u), and inf - inf for a proposal outside too is
    a rejection, not a RuntimeWarning printed to the user."""
    import warnings

    import emcee

    from fit.sampler import GroupedMove

    def logp(x):
        x = np.atleast_2d(x)
        return np.where(np.all(np.abs(x) < 1.0, axis=1), -0.5 * np.sum(x ** 2, axis=1), -np.inf)

    rng = np.random.default_rng(3)
    p0 = rng.uniform(-0.5, 0.5, (16, 2))
    p0[0] = [5.0, 5.0]      # outside: log p = -inf
    s = emcee.EnsembleSampler(16, 2, logp, vectorize=True,
                              moves=[(GroupedMove(emcee.moves.DEMove(), 2), 0.8),
                                     (GroupedMove(emcee.moves.DESnookerMove(), 2), 0.2)])
    s._random = np.random.mtrand.RandomState(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        s.run_mcmc(p0, 200)
    last = s.get_chain()[-1]
    assert np.all(np.abs(last) < 1.0)
    assert np.all(np.isfinite(s.get_log_prob()[-1]))


def test_laplace_sds_of_the_print_survive_a_noise_parameter_without_curvature(monkeypatch):
    """When the Hessian over every free parameter fails (a wobble's sd near its floor, below
    the measurement's own, has a curvature of either sign), the print's parameters still
    get theirs with the noise held at the MAP: a constant width's sd is sd / sqrt(n), not
    the 1 % fallback every parameter got before."""
    import fit.sampler as fs
    from test_offset_envelope import ConstModel, _scan

    real = fs._hessian_z

    def fails_with_noise(problem, tr, z0, h=1e-3, free=None):
        if free is None or any(free[i] and n.startswith("noise.") for i, n in enumerate(problem.param_names)):
            raise np.linalg.LinAlgError("no curvature")
        return real(problem, tr, z0, h=h, free=free)

    monkeypatch.setattr(fs, "_hessian_z", fails_with_noise)
    sc = _scan(n=400, sd=0.005)
    m = fit_map(JointProblem([sc], [ConstModel()]))
    assert math.sqrt(m.cov[0, 0]) == pytest.approx(0.005 / math.sqrt(400), rel=0.05)
