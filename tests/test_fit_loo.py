"""Vectorised PSIS-LOO (fit.sampler.psis_loo / psis_log_weights) against arviz_stats'
per-observation PSIS and against exact leave-one-out of a conjugate model."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.stats import norm

from fit.sampler import psis_log_weights, psis_loo, psis_tail_length


def _arviz_psislw(log_lik_obs_draws):
    from arviz_stats.base import array_stats

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lw, k = array_stats.psislw(log_lik_obs_draws, r_eff=1.0, axis=-1)
    return np.asarray(lw), np.asarray(k, dtype=float)


@pytest.mark.parametrize("n_draws", [60, 400, 1000])
def test_matches_arviz_stats_psislw(n_draws):
    # heavy-tailed pointwise log-likelihoods: Pareto k from ~0 to > 1 across observations
    rng = np.random.default_rng(n_draws)
    n_obs = 150
    ll = (rng.standard_normal((n_draws, n_obs)) * rng.uniform(0.05, 3.0, n_obs)
          + rng.uniform(0.0, 0.5, n_obs) * rng.standard_t(2, (n_draws, n_obs)))
    lw_ref, k_ref = _arviz_psislw(ll.T)           # arviz_stats negates: weights ~ 1/p
    lw, k = psis_log_weights(-ll.T)
    assert k.min() < 0.5 < 0.7 < k.max()          # the test spans good and bad tails
    np.testing.assert_allclose(k, k_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lw, lw_ref, rtol=0, atol=1e-10)


def test_tail_length_is_min_of_fifth_and_three_root_s():
    for s in (25, 100, 225, 226, 400, 4000):
        assert psis_tail_length(s) == int(np.floor(min(0.2 * s, 3 * np.sqrt(s))))


def test_elpd_loo_equals_exact_loo_of_conjugate_normal_mean():
    # y_i ~ N(mu, 1), mu ~ N(0, 10^2): exact posterior draws and exact
    # p(y_i | y_-i) = N(y_i; m_-i, 1 + 1/P_-i), P_-i = 1/100 + (n - 1), m_-i = sum_-i y / P_-i
    rng = np.random.default_rng(7)
    n, S = 40, 4000
    y = 1.3 + rng.standard_normal(n)
    y[0] = 4.5                                     # one influential point
    P = 1 / 100 + n
    mu = y.sum() / P + rng.standard_normal(S) / np.sqrt(P)
    ll = norm.logpdf(y[None, :], mu[:, None], 1.0)
    P_i = 1 / 100 + (n - 1)
    m_i = (y.sum() - y) / P_i
    exact_i = norm.logpdf(y, m_i, np.sqrt(1 + 1 / P_i))
    res = psis_loo(ll)
    # Monte Carlo error of elpd_i with 4000 draws and k < 0.5 is ~1e-3 per point
    assert max(res["pareto_k"]) < 0.5
    np.testing.assert_allclose(res["elpd_i"], exact_i, atol=0.01)
    assert abs(res["elpd_loo"] - exact_i.sum()) < 0.05
    # p_loo ~ 1 (one parameter, weak prior); se from the pointwise spread
    assert 0.7 < res["p_loo"] < 1.5
    assert res["se"] == pytest.approx(np.sqrt(n * np.var(res["elpd_i"])))


def test_degenerate_rows_do_not_fail():
    rng = np.random.default_rng(0)
    ll = rng.standard_normal((30, 5))
    ll[:, 2] = -1.0                                # an observation that does not depend on theta
    res = psis_loo(ll)
    assert np.isfinite(res["elpd_loo"])
    assert res["elpd_i"][2] == pytest.approx(-1.0)
