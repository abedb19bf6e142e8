"""The sandwich (HAC) widening of the intervals (fit/sandwich_envelope.py), on a model whose
answer is known: a constant width c, whose MAP is the widths' mean. Under AR(1) errors of
correlation rho that a white noise model ignores, the mean's variance is the white one times
1 + 2 sum_l rho^l; the Bartlett-weighted estimate the module uses converges to
1 + 2 sum_{l<=L} (1 - l / (L + 1)) rho^l."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from fit.data import ScanData
from fit.likelihood import JointProblem, NoiseOptions
from fit.result import ParamSummary
from fit.sampler import fit_map
from fit.sandwich_envelope import (MAX_LAGS, MAX_RATIO, bandwidths, newey_west_lags, sandwich_estimate,
                                   sandwich_line, sandwich_ratios, widen_sandwich)
from measure.table import WidthTable
from patterns.manifest import Samples
from tests.test_offset_envelope import ConstModel, _Ctx


def _scan(rho: float, n=8000, sd=0.003, seed=0, tracks=4):
    """Widths 0.45 mm plus AR(1) errors of sd ``sd`` and lag-one correlation ``rho`` along
    each of ``tracks`` tracks (stations 0.25 mm apart); the table states sd as white."""
    rng = np.random.default_rng(seed)
    per = n // tracks
    track = np.repeat(np.arange(tracks), per)
    s = np.tile(0.25 * np.arange(per), tracks)
    e = np.empty(n)
    w = rng.standard_normal(n)
    for j in range(n):
        e[j] = w[j] if s[j] == 0 else rho * e[j - 1] + math.sqrt(1 - rho * rho) * w[j]
    y = 0.45 + sd * e
    table = WidthTable(track=track, s_mm=s, x_mm=s, y_mm=track * 3.0, t_s=s / 20, width_mm=y,
                       width_sd_mm=np.full(n, sd), valid=np.ones(n, bool))
    smp = Samples(track=track, s_mm=s, x_mm=s, y_mm=track * 3.0, t_s=s / 20, nx=np.zeros(n), ny=np.ones(n),
                  width_nominal_mm=np.full(n, 0.45), height_mm=np.full(n, 0.2))
    gap = np.where(s == 0, np.inf, 0.25)
    return ScanData(name="scan", manifest=None, table=table, samples=smp, order=np.arange(n), y_mm=y,
                    sd_mm=np.full(n, sd), gap_mm=gap, ctx=_Ctx(n))


def _white(sc):
    return JointProblem([sc], [ConstModel()], NoiseOptions(ar1=False, relative=False))


def _bartlett(rho: float, L: int) -> float:
    return math.sqrt(1 + 2 * sum((1 - l / (L + 1)) * rho ** l for l in range(1, L + 1)))


def test_the_ratio_is_the_variance_the_ignored_correlation_adds():
    n = 8000
    assert newey_west_lags(n) == 10               # floor(4 (80)^(2/9)) = floor(10.6)
    for rho in (0.5, 0.7):
        pb = _white(_scan(rho, n=n, seed=3))
        theta = fit_map(pb).theta
        r, lags = sandwich_estimate(pb, theta)
        # a constant is read alike all along its tracks: the longest bandwidth
        assert lags["flow.w_mm"] == MAX_LAGS
        assert r["flow.w_mm"] == pytest.approx(_bartlett(rho, MAX_LAGS), rel=0.12)
        assert r["flow.w_mm"] > 1.6               # the white model's interval is that much too narrow
        # Newey-West's own bandwidth reads the same here: rho^10 is already small
        r10 = sandwich_ratios(pb, theta, lags=10)["flow.w_mm"]
        assert r10 == pytest.approx(_bartlett(rho, 10), rel=0.12)
    pb = _white(_scan(0.0, n=n, seed=3))
    assert sandwich_ratios(pb, fit_map(pb).theta)["flow.w_mm"] == pytest.approx(1.0, abs=0.1)


def test_the_bandwidth_is_how_far_a_parameters_response_reaches_along_the_track():
    """A column that decays over 40 stations (a slow transient: a Bowden's tau at 20-40
    mm/s) is read with its autocorrelation's half-width (exp(-l / 40) = 1/2 at l = 28),
    one that lives on a single station (a direct drive's tau) with Newey-West's bandwidth,
    and no bandwidth crosses a track or exceeds MAX_LAGS."""
    n_per, tracks = 1000, 4
    j = np.tile(np.arange(n_per), tracks)
    seg = np.repeat(np.arange(tracks), n_per)
    slow = np.where(j % 200 >= 100, np.exp(-(j % 200 - 100) / 40.0), 0.0)
    spike = np.where(j % 200 == 100, 1.0, 0.0)
    const = np.ones(len(j))
    L = bandwidths(np.column_stack([slow, spike, const]), seg, len(j))
    assert L[0] == pytest.approx(round(40 * math.log(2)) + 1, abs=2)
    assert L[1] == newey_west_lags(len(j))
    assert L[2] == min(MAX_LAGS, len(j) // 8)


def test_the_noise_model_that_has_the_correlation_needs_no_widening():
    """The default noise model (an OU wobble beside the white error) takes AR(1) errors as
    its own: no widening (ratio <= 1 within the estimate's noise), where the white model's
    is ~2. At Newey-West's bandwidth the ratio is ~1; at the constant's own (256 lags on
    2,000-station tracks) the long-run variance of scores that sum to zero at the MAP reads
    low (Bartlett's bias, ~2 L / n of it), which only leaves the interval as it is."""
    sc = _scan(0.6, seed=5)
    pb = JointProblem([sc], [ConstModel()], NoiseOptions(relative=False))
    theta = fit_map(pb).theta
    assert sandwich_ratios(pb, theta)["flow.w_mm"] < 1.1
    assert sandwich_ratios(pb, theta, lags=newey_west_lags(8000))["flow.w_mm"] == pytest.approx(1.0, abs=0.15)
    pbw = _white(sc)
    assert sandwich_ratios(pbw, fit_map(pbw).theta)["flow.w_mm"] > 1.5


def _result(pb, m, n_draws=40000, seed=1):
    s_post = math.sqrt(m.cov[0, 0])
    draws = m.theta[0] + s_post * np.random.default_rng(seed).standard_normal((n_draws, 1))
    q = np.quantile(draws[:, 0], [0.16, 0.84, 0.05, 0.95, 0.025, 0.975])
    ps = ParamSummary(name="flow.w_mm", median=float(np.median(draws)), mean=float(draws.mean()), sd=s_post,
                      ci68=tuple(q[0:2]), ci90=tuple(q[2:4]), ci95=tuple(q[4:6]), map=float(m.theta[0]))
    return SimpleNamespace(map=m, samples=draws, param_names=list(pb.param_names), params={"flow.w_mm": ps},
                           derived={}, diagnostics={}, envelope_samples={})


def test_the_interval_grows_by_the_ratio_and_never_shrinks():
    pb = _white(_scan(0.6, seed=7))
    m = fit_map(pb)
    res = _result(pb, m)
    before = res.params["flow.w_mm"]
    info = widen_sandwich(pb, res, seed=0)
    r = info["ratio"]["flow.w_mm"]
    assert info["applied"] and r > 1.5
    lo, hi = res.params["flow.w_mm"].ci95
    assert (hi - lo) == pytest.approx(r * (before.ci95[1] - before.ci95[0]), rel=0.03)
    assert res.params["flow.w_mm"].median == before.median
    assert res.diagnostics["sandwich"] is info and len(res.envelope_samples["sandwich"]) == 256
    assert "flow.w_mm 95 %" in sandwich_line(info) and f"x{r:.2f}" in sandwich_line(info)
    # white errors under a white model: a ratio under 1 leaves the posterior as it was
    pb0 = _white(_scan(0.0, seed=8))
    m0 = fit_map(pb0)
    res0 = _result(pb0, m0)
    ci0 = res0.params["flow.w_mm"].ci95
    info0 = widen_sandwich(pb0, res0, seed=0)
    if info0["ratio"]["flow.w_mm"] <= 1.0:
        assert not info0["applied"] and res0.params["flow.w_mm"].ci95 == ci0 and sandwich_line(info0) is None
    else:
        assert res0.params["flow.w_mm"].ci95[1] - res0.params["flow.w_mm"].ci95[0] < 1.1 * (ci0[1] - ci0[0])


def test_the_widening_stops_at_its_cap(monkeypatch):
    """A ratio beyond MAX_RATIO (a noise model too far from the residuals for a linear
    correction) widens by MAX_RATIO, no more: here the cap set to 1.2 under a ratio ~1.8."""
    import fit.sandwich_envelope as se

    monkeypatch.setattr(se, "MAX_RATIO", 1.2)
    pb = _white(_scan(0.6, seed=9))
    m = fit_map(pb)
    res = _result(pb, m)
    w0 = res.params["flow.w_mm"].ci95[1] - res.params["flow.w_mm"].ci95[0]
    info = se.widen_sandwich(pb, res, seed=0)
    assert info["ratio"]["flow.w_mm"] > 1.5
    w1 = res.params["flow.w_mm"].ci95[1] - res.params["flow.w_mm"].ci95[0]
    assert w1 == pytest.approx(1.2 * w0, rel=0.03)
    assert "(x1.20, the cap; the residuals ask x" in se.sandwich_line(info)
    assert MAX_RATIO == 3.0


def test_a_map_fit_carries_the_ratio_in_its_covariance():
    """`calib fit --map-only`: the Laplace sd grows by the ratio, the noise parameters' stay."""
    from fit.sandwich_envelope import widen_map_sandwich

    pb = _white(_scan(0.6, seed=7))
    m = fit_map(pb)
    C = np.array(m.cov, dtype=float)
    info = widen_map_sandwich(pb, m)
    i = pb.param_names.index("flow.w_mm")
    r = info["ratio"]["flow.w_mm"]
    assert info["applied"] and r > 1.5
    assert math.sqrt(m.cov[i, i]) == pytest.approx(r * math.sqrt(C[i, i]), rel=1e-9)
    for j, n in enumerate(pb.param_names):
        if n != "flow.w_mm":
            assert m.cov[j, j] == C[j, j]
