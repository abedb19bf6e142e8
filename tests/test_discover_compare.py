"""Comparison numbers (BIC, chi2_nu, RMS, ln L, PSIS-LOO) against hand computation on tiny
cases, with the likelihood the fit engine really uses (fit/likelihood.py: Gaussian, or AR(1)
along a track, the default)."""
import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from fit.compare import compare_models, fit_model
from fit.data import ScanData
from fit.likelihood import NoiseOptions
from fit.params import Param
from measure.table import WidthTable
from patterns.manifest import Samples

GAUSS = NoiseOptions(ar1=False, relative=False)


class LineModel:
    """Stub with the Model API: width = a + b * x (x is the 'context'); only a if const."""

    def __init__(self, const=False):
        self.const = const
        self.params = tuple(Param(n, "mm", 0.5, -10.0, 10.0) for n in
                            (["line.a_mm"] if const else ["line.a_mm", "line.b_mm"]))
        self.param_names = [p.name for p in self.params]
        self.bounds = np.array([[p.lower, p.upper] for p in self.params])
        self.spec = "const" if const else "line"

    def default_theta(self):
        return np.full(len(self.params), 0.5)

    def log_prior(self, theta):
        return np.zeros(np.atleast_2d(theta).shape[0])

    def predict(self, ctx, theta):
        th = np.atleast_2d(theta)
        b = 0.0 if self.const else th[:, 1:2]
        return th[:, 0:1] + b * ctx[None, :]


X = np.arange(6.0)
Y = np.array([1.0, 1.1, 1.3, 1.2, 1.5, 1.4])


def _scan(x, y, sd):
    """One track, stations at s = x mm (so the AR(1) gaps are the x steps)."""
    n = len(x)
    z = np.zeros(n)
    t = WidthTable(track=np.zeros(n, int), s_mm=x, x_mm=x, y_mm=z, t_s=x, width_mm=y,
                   width_sd_mm=np.full(n, sd), valid=np.ones(n, bool))
    smp = Samples(track=np.zeros(n, int), s_mm=x, x_mm=x, y_mm=z, t_s=x, nx=z, ny=z + 1,
                  width_nominal_mm=z + 1, height_mm=z + 0.2)
    gap = np.concatenate([[np.inf], np.diff(x)])
    return ScanData(name="t", manifest=None, table=t, samples=smp, order=np.arange(n),
                    y_mm=np.asarray(y, float), sd_mm=np.full(n, sd), gap_mm=gap, ctx=x)


def test_line_fit_matches_hand_computed_bic_when_scatter_is_within_the_measurement_sd():
    # Gaussian likelihood (sigma_extra, no AR(1)). Hand computation: ybar = 1.25, Sxx = 17.5,
    # Sxy = 1.55 -> b = 0.0885714, a = 1.0285714, SSR = Syy - Sxy^2/Sxx = 0.0377143;
    # chi2 = SSR/0.2^2 = 0.942857 < n, so the ML extra noise is at its lower bound (1e-4 mm,
    # negligible against 0.2) and ln L = -1/2 (chi2 + 6 ln 0.04 + 6 ln 2pi) = 3.671568,
    # k = 3 (a, b, sigma_extra), BIC = 3 ln 6 - 2 ln L = -1.967858, chi2_nu = 0.942857 / (6 - 2)
    # (k_model = 2: the measurement-sd reduced chi-square), RMS = sqrt(SSR/6) = 0.0792825.
    f = fit_model(LineModel(), _scan(X, Y, 0.2), "line", noise=GAUSS).map
    assert f.theta[:2] == pytest.approx([1.0285714, 0.0885714], abs=1e-5)
    assert f.values["noise.sigma_extra_mm"] < 2e-4
    assert f.loglik == pytest.approx(3.671568, abs=1e-4)
    assert f.bic == pytest.approx(-1.967858, abs=2e-4)
    assert f.chi2_nu == pytest.approx(0.942857 / 4, abs=1e-5)
    assert f.rms_mm == pytest.approx(0.0792825, abs=1e-6)


def test_extra_noise_and_bic_difference_between_nested_models_when_scatter_exceeds_sd():
    # sd = 0.02 mm: chi2 >> n, so sigma_x^2 = SSR/n - sd^2 (equal sd) and
    # ln L = -n/2 (1 + ln(SSR/n) + ln 2pi). Constant model: SSR0 = Syy = 0.175, k = 2.
    n = 6
    ssr1, ssr0 = 0.175 - 1.55 ** 2 / 17.5, 0.175
    ll1 = -n / 2 * (1 + math.log(ssr1 / n) + math.log(2 * math.pi))
    ll0 = -n / 2 * (1 + math.log(ssr0 / n) + math.log(2 * math.pi))
    bic1, bic0 = 3 * math.log(n) - 2 * ll1, 2 * math.log(n) - 2 * ll0
    comp = compare_models(_scan(X, Y, 0.02), {"const": LineModel(const=True), "line": LineModel()},
                          full=False, noise=GAUSS)
    rows = {r["model"]: r for r in comp.to_json()["models"]}
    assert rows["line"]["bic"] == pytest.approx(bic1, abs=1e-4)
    assert rows["const"]["bic"] == pytest.approx(bic0, abs=1e-4)
    assert rows["line"]["extra_noise_mm"] == pytest.approx(math.sqrt(ssr1 / n - 0.02 ** 2), abs=1e-5)
    assert comp.fits[0].spec == "line"  # lower BIC first
    assert rows["const"]["delta_bic"] == pytest.approx(bic0 - bic1, abs=1e-4)
    assert rows["line"]["delta_bic"] == 0.0


def _ar1_loglik_by_hand(x, y, sd, a, b, sig, ell):
    """The log-likelihood of fit/likelihood.py written out sample by sample: a Kalman
    filter for an OU wobble (sig, ell) under white measurement noise sd."""
    ll, m, P = 0.0, 0.0, sig ** 2
    for i in range(len(x)):
        phi = 0.0 if i == 0 else math.exp(-(x[i] - x[i - 1]) / ell)
        mp, Pp = phi * m, phi * phi * P + (1 - phi * phi) * sig ** 2
        F = Pp + sd ** 2
        v = y[i] - a - b * x[i] - mp
        ll += -0.5 * (v * v / F + math.log(F) + math.log(2 * math.pi))
        m, P = mp + Pp / F * v, Pp * sd ** 2 / F
    return ll


def test_ar1_bic_matches_the_hand_computed_likelihood_of_correlated_residuals():
    # Default engine likelihood: AR(1) along the track. y = line + an Ornstein-Uhlenbeck
    # wobble (ell = 1 mm, 20 um) + 5 um measurement noise, stations every 0.25 mm.
    rng = np.random.default_rng(2)
    x = np.arange(0, 30, 0.25)
    n = len(x)
    rho = math.exp(-0.25 / 1.0)
    w = np.empty(n)
    w[0] = rng.standard_normal()
    for i in range(1, n):
        w[i] = rho * w[i - 1] + math.sqrt(1 - rho ** 2) * rng.standard_normal()
    y = 0.45 + 0.004 * x + 0.02 * w + 0.005 * rng.standard_normal(n)
    sd = 0.005
    # one wobble of constant sd (the default adds a share that grows with the commanded
    # width, a constant here); the optional second, short wobble is checked at the end
    comp = compare_models(_scan(x, y, sd), {"const": LineModel(const=True), "line": LineModel()},
                          full=False, noise=NoiseOptions(relative=False))
    fits = {f.spec: f for f in comp.fits}
    f = fits["line"]
    a, b = f.map.theta[:2]
    sig, ell = f.extra_mm, f.corr_len_mm
    assert 0.2 < ell < 5.0 and 0.01 < sig < 0.04  # the wobble is found, not absorbed by a, b
    # 1. ln L is the AR(1) likelihood written out by hand ...
    ll = _ar1_loglik_by_hand(x, y, sd, a, b, sig, ell)
    assert f.loglik == pytest.approx(ll, abs=1e-8)
    # ... which is the exact joint density of the stationary process: a multivariate normal
    # with covariance sig^2 exp(-|x_i - x_j| / ell) + sd^2 I
    C = sig ** 2 * np.exp(-np.abs(x[:, None] - x[None, :]) / ell) + sd ** 2 * np.eye(n)
    assert ll == pytest.approx(multivariate_normal(a + b * x, C).logpdf(y), abs=1e-6)
    # 2. BIC = k ln n - 2 ln L with k = 4 (a, b, sigma_extra, ell)
    assert f.k == 4 and f.bic == pytest.approx(4 * math.log(n) - 2 * ll, abs=1e-8)
    # 3. it is the optimum: (a, b) are the generalised least squares estimate at (sigma, ell)
    A = np.stack([np.ones(n), x], axis=1)
    Ci = np.linalg.inv(C)
    F = A.T @ Ci @ A
    gls = np.linalg.solve(F, A.T @ Ci @ y)
    se = np.sqrt(np.diag(np.linalg.inv(F)))  # to within 2 % of their standard errors
    assert np.all(np.abs(np.array([a, b]) - gls) < 0.02 * se)
    # and neither noise parameter can be moved to raise ln L
    for ds, dl in ((1.01, 1), (0.99, 1), (1, 1.01), (1, 0.99)):
        assert _ar1_loglik_by_hand(x, y, sd, a, b, sig * ds, ell * dl) <= ll + 1e-6
    # 4. chi2_nu against the measurement sd only, k_model = 2; RMS
    r = y - a - b * x
    assert f.chi2_nu == pytest.approx(np.sum((r / sd) ** 2) / (n - 2), rel=1e-9)
    assert f.rms_mm == pytest.approx(math.sqrt(np.mean(r ** 2)), rel=1e-9)
    rows = {r["model"]: r for r in comp.rows()}
    assert rows["const"]["delta_bic"] == pytest.approx(fits["const"].bic - f.bic, abs=1e-9)
    assert rows["const"]["delta_bic"] > 10
    # 5. NoiseOptions(short=True) adds a short wobble (fixed length SHORT_CORR_MM, the long
    # one then >= LONG_MIN_FACTOR x that): k = 5 and ln L is the density of the sum of the
    # two OU processes under the white noise
    from fit.likelihood import LONG_MIN_FACTOR, SHORT_CORR_MM
    f2 = {g.spec: g for g in compare_models(_scan(x, y, sd), {"line": LineModel()}, full=False,
                                            noise=NoiseOptions(short=True, relative=False)).fits}["line"]
    v2 = f2.map.values
    ell2, sig_s = v2["noise.corr_len_mm"], v2["noise.sigma_short_mm"]
    assert f2.k == 5 and ell2 >= LONG_MIN_FACTOR * SHORT_CORR_MM
    d = np.abs(x[:, None] - x[None, :])
    C2 = (f2.extra_mm ** 2 * np.exp(-d / ell2) + sig_s ** 2 * np.exp(-d / SHORT_CORR_MM) + sd ** 2 * np.eye(n))
    a2, b2 = f2.map.theta[:2]
    assert f2.loglik == pytest.approx(multivariate_normal(a2 + b2 * x, C2).logpdf(y), abs=1e-6)
    # a 1 mm wobble lies between the two lengths: the short one takes most of it
    assert sig_s > 0.01


def test_full_fit_gives_elpd_and_prefers_the_true_model():
    rng = np.random.default_rng(5)
    x = np.linspace(0, 20, 80)
    y = 0.4 + 0.005 * x + 0.01 * rng.standard_normal(len(x))
    comp = compare_models(_scan(x, y, 0.01), {"const": LineModel(const=True), "line": LineModel()},
                          full=True, max_steps=6000)
    rows = {r["model"]: r for r in comp.rows()}
    assert rows["line"]["converged"] and rows["const"]["converged"]  # tau and split R-hat
    assert rows["line"]["delta_elpd_loo"] == 0.0
    # (the OU wobble under white measurement noise absorbs part of the missing slope as a
    # long-correlated wander, so the margin is ~3 SE, 16 nats, on this 80-sample line)
    assert rows["const"]["delta_elpd_loo"] < -2.5 * rows["const"]["delta_elpd_loo_se"]
    assert rows["const"]["delta_elpd_loo"] < -10
    lo, med, hi = rows["line"]["intervals"]["line.b_mm"]
    assert lo < 0.005 < hi
