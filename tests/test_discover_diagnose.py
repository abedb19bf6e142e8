"""Diagnosis finds a hidden effect (fast configuration: 4 short tracks, MAP only)."""
import numpy as np
import pytest

from fit.compare import observe
from fit.covariates import compute_covariates, score_covariates
from fit.diagnose import candidate_names, diagnose
from fit.effects import REGISTRY
from fit.hidden import make_case
from fit.model import build_model

FAST = dict(n_tracks=4, length_mm=40.0, ds_mm=0.5)


def _diagnose(hidden, seed=3):
    c = make_case(hidden, seed=seed, **FAST)
    obs = observe(c.manifest, c.table)
    d = diagnose(obs, "pa", lambda s: build_model(s, c.manifest.printer, c.extra_effects),
                 list(REGISTRY), [e.name for e in c.extra_effects], n_null=50)
    return c, d


@pytest.mark.parametrize("hidden", ["thermal", "backpressure", "backlash", "nonlinear"])
def test_diagnosis_ranks_the_hidden_library_effect_first_and_the_error_falls_to_noise(hidden):
    c, d = _diagnose(hidden)
    assert c.effect_rms_mm > c.noise_mm
    assert d.candidates[0].effect == hidden
    assert d.best == hidden
    assert d.candidates[0].delta_bic > 30     # decisive is >= 10; backlash on 4 short tracks: 66
    assert d.base.chi2_nu > 2.0
    assert d.candidates[0].chi2_nu_after < 1.2
    assert d.candidates[0].rms_mm_after < 1.2 * c.noise_mm
    assert f"--model pa+{hidden}" in d.command
    j = d.to_json()
    assert j["candidates"][0]["effect"] == hidden
    assert [x["delta_bic"] for x in j["candidates"]] == sorted(
        [x["delta_bic"] for x in j["candidates"]], reverse=True)
    assert set(j) >= {"model", "rms_mm", "chi2_nu", "candidates", "covariates"}


def test_no_effect_is_called_missing_when_the_model_is_the_truth():
    c = make_case("thermal", seed=4, **FAST)
    obs = observe(c.manifest, c.table)
    d = diagnose(obs, "pa+thermal", lambda s: build_model(s, c.manifest.printer), list(REGISTRY),
                 n_null=50)
    assert d.best is None
    assert "No missing effect is supported" in d.verdict
    assert d.base.chi2_nu < 1.2


def test_candidates_exclude_effects_in_the_model_and_the_other_pa_parameterisation():
    names = candidate_names("pa+thermal", ["pa", "pa_ve", "thermal", "backlash", "firmware_pa"], ["gear_slip"])
    assert names == ["backlash", "gear_slip"]


def test_covariate_score_finds_the_driving_covariate_and_not_an_autocorrelated_bystander():
    c = make_case("bed_tilt", seed=1, **FAST)
    smp_ok = c.table.valid
    cov = compute_covariates(c.manifest, c.table.track[smp_ok], c.table.s_mm[smp_ok],
                             c.table.t_s[smp_ok], c.table.x_mm[smp_ok], c.table.y_mm[smp_ok])
    rng = np.random.default_rng(0)
    x = cov["x_mm"]
    resid = 0.02 * (x - x.mean()) / x.std() + 0.005 * rng.standard_normal(len(x))
    scores = score_covariates(resid, cov, n_null=100)
    assert scores[0].name == "x_mm"
    assert scores[0].score > 0.8
    by = {s.name: s for s in scores}
    # heading and time_since_stop are unrelated to x here: near-zero excess over the null
    assert by["time_since_stop_s"].score < 0.2


def test_time_since_stop_is_hand_checkable_on_the_probe_print():
    c = make_case("thermal", seed=0, **FAST)
    tr = c.manifest.track(0)
    stop = tr.params["stop_s_mm"]
    s = np.array([stop + 5.0])
    cov = compute_covariates(c.manifest, np.array([0]), s)
    # after the stop the head accelerates at 1500 mm/s^2 to 30 mm/s (0.3 mm in 0.02 s)
    # and then cruises: 5 mm takes 0.02 + (5 - 0.3)/30 s after the end of the stop
    assert cov["time_since_stop_s"][0] == pytest.approx(0.02 + 4.7 / 30, abs=0.01)
    assert cov["last_stop_duration_s"][0] == pytest.approx(3.0, abs=0.02)
    assert cov["speed_mm_s"][0] == pytest.approx(30.0, abs=0.5)
