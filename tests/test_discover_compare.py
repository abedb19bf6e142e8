"""Comparison numbers (BIC, chi2_nu, RMS, ln L, PSIS-LOO) against hand computation on tiny cases."""
import math

import numpy as np
import pytest

from fit.compare import (Observed, compare_models, ml_extra_noise_mm, ml_fit, mcmc_fit, psis_loo)
from patterns.manifest import Samples


class LineModel:
    """Stub with the Model API: width = a + b * x (x is the 'context'); b fixed to 0 if const."""

    def __init__(self, const=False):
        self.const = const
        self.param_names = ["line.a_mm"] if const else ["line.a_mm", "line.b_mm"]
        self.bounds = [(-10.0, 10.0)] * len(self.param_names)

    def default_theta(self):
        return np.zeros(len(self.param_names)) + 0.5

    def log_prior(self, theta):
        return np.zeros(np.atleast_2d(theta).shape[0])

    def predict(self, ctx, theta):
        th = np.atleast_2d(theta)
        b = 0.0 if self.const else th[:, 1:2]
        return th[:, 0:1] + b * ctx[None, :]


X = np.arange(6.0)
Y = np.array([1.0, 1.1, 1.3, 1.2, 1.5, 1.4])


def _obs(sd):
    n = len(X)
    z = np.zeros(n)
    smp = Samples(track=np.zeros(n, int), s_mm=X, x_mm=X, y_mm=z, t_s=X, nx=z, ny=z + 1,
                  width_nominal_mm=z + 1, height_mm=z + 0.2)
    return Observed(width_mm=Y.copy(), width_sd_mm=np.full(n, sd), samples=smp, ctx=X)


def test_line_fit_matches_hand_computed_bic_when_scatter_is_within_the_measurement_sd():
    # Hand computation: ybar = 1.25, Sxx = 17.5, Sxy = 1.55 -> b = 0.0885714, a = 1.0285714,
    # SSR = Syy - Sxy^2/Sxx = 0.175 - 2.4025/17.5 = 0.0377143; chi2 = SSR/0.2^2 = 0.942857 < n,
    # so the ML extra noise is 0 (score at 0 is negative) and
    # ln L = -1/2 (chi2 + 6 ln 0.04 + 6 ln 2pi) = 3.671568, k = 3 (a, b, sigma_x),
    # BIC = 3 ln 6 - 2 ln L = -1.967858, chi2_nu = 0.942857/3, RMS = sqrt(SSR/6) = 0.0792825.
    f = ml_fit(LineModel(), _obs(0.2), spec="line", n_random=4)
    assert f.theta == pytest.approx([1.0285714, 0.0885714], abs=1e-6)
    assert f.extra_mm == 0.0
    assert f.loglik == pytest.approx(3.671568, abs=1e-5)
    assert f.bic == pytest.approx(-1.967858, abs=1e-5)
    assert f.chi2_nu == pytest.approx(0.942857 / 3, abs=1e-6)
    assert f.rms_mm == pytest.approx(0.0792825, abs=1e-6)


def test_extra_noise_and_bic_difference_between_nested_models_when_scatter_exceeds_sd():
    # sd = 0.02 mm: chi2 >> n, so sigma_x^2 = SSR/n - sd^2 (equal sd) and
    # ln L = -n/2 (1 + ln(SSR/n) + ln 2pi). Constant model: SSR0 = Syy = 0.175, k = 2.
    n = 6
    ssr1, ssr0 = 0.175 - 1.55 ** 2 / 17.5, 0.175
    ll1 = -n / 2 * (1 + math.log(ssr1 / n) + math.log(2 * math.pi))
    ll0 = -n / 2 * (1 + math.log(ssr0 / n) + math.log(2 * math.pi))
    bic1, bic0 = 3 * math.log(n) - 2 * ll1, 2 * math.log(n) - 2 * ll0
    obs = _obs(0.02)
    comp = compare_models(obs, {"const": LineModel(const=True), "line": LineModel()}, full=False)
    rows = {r["model"]: r for r in comp.to_json()["models"]}
    assert rows["line"]["bic"] == pytest.approx(bic1, abs=1e-5)
    assert rows["const"]["bic"] == pytest.approx(bic0, abs=1e-5)
    assert rows["line"]["extra_noise_mm"] == pytest.approx(math.sqrt(ssr1 / n - 0.02 ** 2), abs=1e-6)
    assert comp.fits[0].spec == "line"  # lower BIC first
    assert rows["const"]["delta_bic"] == pytest.approx(bic0 - bic1, abs=1e-5)
    assert rows["line"]["delta_bic"] == 0.0


def test_ml_extra_noise_solves_the_score_equation_for_unequal_sd():
    rng = np.random.default_rng(1)
    sd = rng.uniform(0.01, 0.05, 400)
    r = rng.standard_normal(400) * np.sqrt(sd ** 2 + 0.03 ** 2)
    s = ml_extra_noise_mm(r, sd)
    v = sd ** 2 + s ** 2
    assert abs(np.sum((r ** 2 - v) / v ** 2)) < 1e-6 * np.sum(1 / v)
    assert 0.02 < s < 0.04


def test_psis_loo_matches_exact_leave_one_out_for_a_conjugate_normal_mean():
    # y_i ~ N(mu, 1), flat prior: posterior mu ~ N(ybar, 1/n); exact LOO predictive
    # y_i | y_-i ~ N(ybar_-i, 1 + 1/(n-1)).
    rng = np.random.default_rng(3)
    n, S = 30, 4000
    y = rng.standard_normal(n) + 2.0
    mu = y.mean() + rng.standard_normal(S) / math.sqrt(n)
    ll = -0.5 * ((y[None, :] - mu[:, None]) ** 2 + math.log(2 * math.pi))
    elpd, se, ks, p_loo, _ = psis_loo(ll)
    ybar_m = (y.sum() - y) / (n - 1)
    var = 1 + 1 / (n - 1)
    exact = float(np.sum(-0.5 * ((y - ybar_m) ** 2 / var + math.log(2 * math.pi * var))))
    assert elpd == pytest.approx(exact, abs=0.1)
    # exact p_loo = lpd - elpd_loo with lpd_i = log N(y_i; ybar, 1 + 1/n)
    v1 = 1 + 1 / n
    lpd = float(np.sum(-0.5 * ((y - y.mean()) ** 2 / v1 + math.log(2 * math.pi * v1))))
    assert p_loo == pytest.approx(lpd - exact, abs=0.1)
    assert np.max(ks) < 0.5


def test_full_fit_gives_elpd_and_prefers_the_true_model():
    rng = np.random.default_rng(5)
    x = np.linspace(0, 10, 80)
    n = len(x)
    z = np.zeros(n)
    smp = Samples(track=np.zeros(n, int), s_mm=x, x_mm=x, y_mm=z, t_s=x, nx=z, ny=z + 1,
                  width_nominal_mm=z + 1, height_mm=z + 0.2)
    y = 0.4 + 0.01 * x + 0.01 * rng.standard_normal(n)
    obs = Observed(width_mm=y, width_sd_mm=np.full(n, 0.01), samples=smp, ctx=x)
    comp = compare_models(obs, {"const": LineModel(const=True), "line": LineModel()}, full=True,
                          n_steps=300)
    rows = {r["model"]: r for r in comp.rows()}
    assert rows["line"]["delta_elpd_loo"] == 0.0
    assert rows["const"]["delta_elpd_loo"] < -10 * rows["const"]["delta_elpd_loo_se"] / 10
    assert rows["const"]["delta_elpd_loo"] < -20
    lo, med, hi = rows["line"]["intervals"]["line.b_mm"]
    assert lo < 0.01 < hi
