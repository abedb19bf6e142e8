"""Global mode search (fit/modes.py) and the trust verdict (fit/trust.py).

Two-mode posterior: width = 0.4 + 0.05 x L^2 + c z L with L = ln(tau / 0.1 s). Data made
at L = +1.5 (tau = 0.448 s). With c = 0 the data cannot tell L = +1.5 from L = -1.5 (tau =
0.0223 s): two equally good modes, three decades of prior between them. With c > 0 the
mirror mode is a worse local optimum.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from fit.likelihood import JointProblem, NoiseOptions
from fit.params import Param
from fit.sampler import fit_map, fit_mcmc
from fit.trust import CHI2_NU_MAX, assess
from test_discover_compare import _scan

L_TRUE = 1.5
TAU_TRUE = 0.1 * math.exp(L_TRUE)
TAU_MIRROR = 0.1 * math.exp(-L_TRUE)


class MirrorModel:
    spec = "pa"

    def __init__(self, c):
        self.c = c
        self.params = (Param("pa.tau_s", "s", 0.2, 0.005, 5.0, "loguniform"),)
        self.param_names = ["pa.tau_s"]
        self.bounds = np.array([[0.005, 5.0]])

    def default_theta(self):
        return np.array([0.2])

    def log_prior(self, theta):
        return np.zeros(np.atleast_2d(theta).shape[0])

    def predict(self, ctx, theta):
        L = np.log(np.atleast_2d(theta)[:, :1] / 0.1)
        x, z = ctx
        return 0.4 + 0.05 * x[None, :] * L ** 2 + self.c * z[None, :] * L


def _problem(c, seed=0):
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 4, 200)
    z = np.where(np.arange(200) % 2 == 0, 1.0, -1.0) * 0.3
    y = 0.4 + 0.05 * x * L_TRUE ** 2 + c * z * L_TRUE + 0.002 * rng.standard_normal(200)
    sc = _scan(x, y, 0.002)
    sc.ctx = (x, z)
    return JointProblem([sc], [MirrorModel(c)], NoiseOptions(ar1=False))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_global_search_finds_both_modes_whatever_the_seed(seed):
    m = fit_map(_problem(0.0), seed=seed, global_search=True)
    taus = sorted(md["values"]["pa.tau_s"] for md in m.modes)
    assert len(taus) == 2
    assert taus[0] == pytest.approx(TAU_MIRROR, rel=0.01) and taus[1] == pytest.approx(TAU_TRUE, rel=0.01)
    assert abs(m.modes[1]["bic"] - m.modes[0]["bic"]) < 1.0


def test_the_better_mode_wins_and_the_map_does_not_depend_on_the_seed():
    maps = [fit_map(_problem(0.004), seed=s, global_search=True) for s in range(4)]
    assert all(m.values["pa.tau_s"] == pytest.approx(TAU_TRUE, rel=0.01) for m in maps)
    assert len({round(m.values["pa.tau_s"], 9) for m in maps}) == 1
    # the mirror is still listed, clearly worse
    mirror = [md for md in maps[0].modes if md["values"]["pa.tau_s"] < 0.1]
    assert mirror and mirror[0]["bic"] - maps[0].modes[0]["bic"] > 50


def test_rival_modes_make_the_fit_not_trustworthy():
    pb = _problem(0.0)
    m = fit_map(pb, global_search=True)
    r = fit_mcmc(pb, map_result=m, progress=False, max_steps=3000, n_loo_draws=50)
    doc = r.to_json()
    v = assess(doc)
    assert not v.trustworthy and v.checks["rival_modes"]
    assert any("second explanation" in p for p in v.problems)
    # the same scan with the mirror ruled out by the data is fine
    pb = _problem(0.004)
    r = fit_mcmc(pb, map_result=fit_map(pb, global_search=True), progress=False, max_steps=3000,
                 n_loo_draws=50)
    ok = assess(r.to_json())
    assert ok.trustworthy, ok.problems


def _doc(chi2=1.0, tau=(0.3, 0.31, 0.32), a=(0.0, 0.01, 0.03), converged=True, modes=()):
    def p(lo, med, hi):
        return {"median": med, "ci95": [lo, hi]}
    return {"converged": converged, "diagnostics": {},
            "information": {"chi2_nu": chi2, "rms_mm": 0.01, "n_obs": 1000,
                            "loo": {"n_pareto_k_gt_0.7": 0}},
            "params": {"pa.tau_s": p(*tau), "thermal.a": p(*a),
                       "noise.sigma_extra_mm": p(1e-4, 1e-4, 2e-4)},
            "priors": {"pa.tau_s": {"kind": "loguniform", "lower": 0.005, "upper": 5.0},
                       "thermal.a": {"kind": "uniform", "lower": 0.0, "upper": 1.0},
                       "noise.sigma_extra_mm": {"kind": "loguniform", "lower": 1e-4, "upper": 1.0}},
            "map": {"modes": list(modes)}}


def test_verdict_rules():
    assert assess(_doc()).trustworthy          # an absent effect (a = 0) and noise at its floor are fine
    v = assess(_doc(chi2=3.0))
    assert not v.trustworthy and "does not fit" in v.problems[0] and "diagnose" in v.advice
    assert assess(_doc(chi2=3.0), chi2_max=5.0).trustworthy
    assert CHI2_NU_MAX == 2.0
    v = assess(_doc(tau=(4.6, 4.9, 4.99)))     # the data want tau beyond the 5 s range limit
    assert not v.trustworthy and v.checks["at_bound"] == ["pa.tau_s"]
    v = assess(_doc(tau=(0.005, 0.0051, 0.0053)))
    assert v.checks["at_bound"] == ["pa.tau_s"]
    assert not assess(_doc(converged=False)).trustworthy
    best = {"values": {"pa.tau_s": 0.31}, "bic": 100.0}
    far_worse = {"values": {"pa.tau_s": 0.02}, "bic": 160.0}
    close = {"values": {"pa.tau_s": 0.02}, "bic": 104.0}
    inside = {"values": {"pa.tau_s": 0.305}, "bic": 101.0}
    assert assess(_doc(modes=[best, far_worse])).trustworthy
    assert assess(_doc(modes=[best, inside])).trustworthy
    assert not assess(_doc(modes=[best, close])).trustworthy


def test_a_view_shift_far_beyond_the_poses_along_track_sd_is_not_trusted():
    """view_shift's prior is the measurement's along-track sd (fit/measurement.py); a fit
    that puts the stations many of those sds away (StartStopTestPLA1: 2.9 mm for +-0.33)
    lets a missing effect pass for the picture's, and is not trustworthy; within 4 sd it is."""
    def with_shift(med, sd=0.33):
        d = _doc()
        d["params"]["view_shift.dx_mm"] = {"median": med, "ci95": [med - 0.05, med + 0.05]}
        d["priors"]["view_shift.dx_mm"] = {"kind": "normal", "mu": 0.0, "sd": sd, "lower": -3.0, "upper": 3.0}
        return d
    v = assess(with_shift(2.86))
    assert not v.trustworthy and v.checks["beyond_measured_prior"] == ["view_shift.dx_mm"]
    assert any("view_shift.dx_mm = 2.86 lies 9 sd" in p for p in v.problems)
    ok = assess(with_shift(0.4))
    assert ok.trustworthy and ok.checks["beyond_measured_prior"] == []
    assert not assess(with_shift(0.4, sd=0.05)).trustworthy      # 8 sd of a markers' pose


def test_a_misfit_on_uncalibrated_widths_first_asks_for_scan_bias():
    """Apparent widths (the width reference could not be calibrated) fitted without
    scan_bias: the edge offset is in every residual, so the advice names `MODEL+scan_bias`
    before `calib diagnose`; with scan_bias in the model the advice is diagnose again."""
    from fit.measurement import notes

    states = [{"scan": "scan", "calibration": {"applied": False, "note": "apparent-width calibration "
                                                "not applied: the width reference had not settled"}}]
    doc = _doc(chi2=12.0)
    doc["model"] = "pa+backpressure"
    doc["diagnostics"] = {"measurement": {"notes": notes(states, has_scan_bias=False)}}
    v = assess(doc)
    assert not v.trustworthy and "--model pa+backpressure+scan_bias" in v.advice
    assert v.checks["apparent_widths_without_scan_bias"]
    doc["diagnostics"] = {"measurement": {"notes": notes(states, has_scan_bias=True)}}
    v = assess(doc)
    assert "scan_bias" not in v.advice and "diagnose" in v.advice
    assert assess(_doc(chi2=12.0)).advice.startswith("run `calib diagnose`")


def test_a_misfit_the_scans_own_scatter_accounts_for_asks_for_a_better_scan():
    """Widths whose error neighbours share (sd 81 um against an own sd of 23 um, as on the
    sparkling-plate phone scans) give a right model chi2_nu_bead ~9 from the measurement
    alone: a misfit within 1.5x that asks for a better scan, still refused; a misfit far
    beyond it (the scan's scatter cannot make it) or a quiet scan asks for diagnose."""
    from types import SimpleNamespace

    from fit.measurement import scatter
    from measure.table import WidthTable

    n = 400
    y = np.full(n, 0.8)
    tab = WidthTable(track=np.zeros(n, int), s_mm=np.arange(n) * 0.25, x_mm=np.zeros(n), y_mm=np.zeros(n),
                     t_s=np.arange(n) * 0.01, width_mm=y, width_sd_mm=np.full(n, 0.084),
                     valid=np.ones(n, bool), width_sd_own_mm=np.full(n, 0.023))
    sc = scatter(SimpleNamespace(table=tab, order=np.arange(n), y_mm=y))
    assert sc["shared_sd_mm"] == pytest.approx(math.sqrt(0.084 ** 2 - 0.023 ** 2))
    assert sc["wobble_allowed_mm"] == pytest.approx(0.016)
    assert sc["chi2_nu_bead_expected"] == pytest.approx((0.084 ** 2 + 0.016 ** 2) / (0.023 ** 2 + 0.016 ** 2))

    def verdict(chi2, scat):
        doc = _doc(chi2=chi2)
        doc["diagnostics"] = {"measurement": {"scatter": [{"scan": "photo", **scat}]}}
        return assess(doc)

    v = verdict(3.0, sc)
    assert not v.trustworthy and "measure the print again" in v.advice
    assert v.checks["misfit_within_measurement_scatter"] == ["photo"]
    assert any("81 um beyond each station's own error" in c for c in v.cautions)
    assert "or the scan's own scatter" in v.problems[0]
    far = verdict(40.0, sc)
    assert far.advice.startswith("run `calib diagnose`") and not far.checks["misfit_within_measurement_scatter"]
    quiet = scatter(SimpleNamespace(table=tab.subset(np.ones(n, bool)), order=np.arange(n), y_mm=y))
    quiet.update(shared_sd_mm=0.004, chi2_nu_bead_expected=1.05)
    assert verdict(3.0, quiet).advice.startswith("run `calib diagnose`")
    assert verdict(1.0, sc).trustworthy


def _wobbly_line(missing_um, seed=0):
    """A bead 0.6 mm wide whose own width wanders by 1.2 % (OU, 20 mm), measured with a
    2 um sd; plus, if asked, an effect the line model lacks (a 60 mm-period ripple)."""
    from fit.likelihood import JointProblem, NoiseOptions
    from test_discover_compare import LineModel

    rng = np.random.default_rng(seed)
    x = np.arange(0.0, 400.0, 0.25)
    phi = math.exp(-0.25 / 20.0)
    ou = np.zeros(len(x))
    ou[0] = rng.standard_normal()
    for i in range(1, len(x)):
        ou[i] = phi * ou[i - 1] + math.sqrt(1 - phi * phi) * rng.standard_normal()
    y = (0.6 + 1e-4 * x + 0.012 * 0.6 * ou + 1e-3 * missing_um * np.sin(2 * np.pi * x / 60.0)
         + 0.002 * rng.standard_normal(len(x)))
    return JointProblem([_scan(x, y, 0.002)], [LineModel()], NoiseOptions())


def test_the_beads_own_wobble_is_not_a_misfit_but_a_missing_effect_still_is():
    """Realistic renders (issue #11): the right model had chi2_nu 5.4 against the measurement
    sd alone, because a real bead wanders; chi2_nu_bead allows that wobble up to 2 % of the
    width, so the right model passes and a missing 40 um ripple does not."""
    for seed in range(3):
        right = fit_map(_wobbly_line(0.0, seed), seed=seed)
        assert right.chi2_nu > 4 * CHI2_NU_MAX                 # the old statistic called it a misfit
        assert right.chi2_nu_bead < CHI2_NU_MAX
        doc = {"converged": True, "information": {"chi2_nu": right.chi2_nu, "chi2_nu_bead": right.chi2_nu_bead,
                                                  "rms_mm": right.rms_mm, "n_obs": right.n_obs},
               "params": {}, "priors": {}}
        assert assess(doc).trustworthy
        wrong = fit_map(_wobbly_line(40.0, seed), seed=seed)
        assert wrong.chi2_nu_bead > CHI2_NU_MAX
        doc["information"].update(chi2_nu=wrong.chi2_nu, chi2_nu_bead=wrong.chi2_nu_bead)
        assert not assess(doc).trustworthy


def test_a_rival_mode_that_differs_only_in_the_bead_or_the_picture_is_not_a_second_printer():
    """fit/nuisance.py NOT_PASTED: spread 0 against 0.2 with the same tau (phone seed 19 of
    bench_e2e) is not two printers; the same rival with another tau is."""
    doc = _doc()
    doc["params"]["spread.sigma_mm"] = {"median": 0.2, "ci95": [0.17, 0.23]}
    doc["priors"]["spread.sigma_mm"] = {"kind": "uniform", "lower": 0.0, "upper": 1.0}
    best = {"values": {"pa.tau_s": 0.31, "spread.sigma_mm": 0.2}, "bic": 100.0}
    bead = {"values": {"pa.tau_s": 0.31, "spread.sigma_mm": 1e-9}, "bic": 104.0}
    printer = {"values": {"pa.tau_s": 0.02, "spread.sigma_mm": 1e-9}, "bic": 104.0}
    doc["map"] = {"modes": [best, bead]}
    assert assess(doc).trustworthy
    doc["map"] = {"modes": [best, printer]}
    v = assess(doc)
    assert not v.trustworthy and "pa.tau_s = 0.02" in v.problems[0] and "spread" not in v.problems[0]


def _riding_doc(beta, b0_prior_sd=0.03, n=4000, seed=0, rider="thermal.tau_s"):
    """Posterior draws where ln(rider) = ln(c) + beta (b0 - b0_med) + eps, eps sd 0.1, c =
    30 s (thermal) or 0.8 s (pa), and pa.tau_s is independent of b0 when it is not the
    rider (known answer of offset_riders: the ends are c exp(-+beta x OFFSET_DOUBT_MM))."""
    rng = np.random.default_rng(seed)
    b0 = -0.045 + 0.004 * rng.standard_normal(n)
    eps = 0.1 * rng.standard_normal(n)
    centre = 0.8 if rider == "pa.tau_s" else 30.0
    ride = np.exp(np.log(centre) + beta * (b0 + 0.045) + eps)
    other = 0.3 + 0.003 * rng.standard_normal(n) if rider != "pa.tau_s" else None
    doc = _doc()
    cols = {"scan_bias.b0_mm": b0, rider: ride}
    if other is not None:
        cols["pa.tau_s"] = other
    doc["param_names"] = list(cols)
    doc["samples"] = np.column_stack(list(cols.values()))
    for name, x in cols.items():
        lo, med, hi = np.quantile(x, [0.025, 0.5, 0.975])
        doc["params"][name] = {"median": float(med), "ci95": [float(lo), float(hi)]}
    doc["priors"]["scan_bias.b0_mm"] = {"kind": "normal", "mu": 0.0, "sd": b0_prior_sd,
                                        "lower": -0.3, "upper": 0.3}
    doc["priors"][rider] = ({"kind": "loguniform", "lower": 0.005, "upper": 5.0} if rider == "pa.tau_s"
                            else {"kind": "loguniform", "lower": 1.0, "upper": 300.0})
    return doc


def test_a_value_that_rides_an_uncalibrated_offset_is_named():
    """The Bowden scene's thermal.tau_s (README): an offset error of 15 um moves it by 2.8
    posterior sds. Known answer: with ln(tau_s) = ln 30 + beta (b0 - b0_med) + noise the
    ends are 30 exp(-+beta OFFSET_DOUBT_MM)."""
    from fit.trust import OFFSET_DOUBT_MM, offset_riders

    beta = 60.0                      # per mm: 15 um -> 0.9 in ln, against a posterior sd of ~0.26
    doc = _riding_doc(beta)
    r = offset_riders(doc)
    assert [x["param"] for x in r] == ["thermal.tau_s"]        # pa.tau_s is independent of b0
    assert r[0]["low"] == pytest.approx(30 * math.exp(-beta * OFFSET_DOUBT_MM), rel=0.05)
    assert r[0]["high"] == pytest.approx(30 * math.exp(beta * OFFSET_DOUBT_MM), rel=0.05)
    v = assess(doc)
    # thermal is not what export pastes: a caution naming it, the fit stays usable
    assert v.trustworthy and any("thermal.tau_s rides the width offset" in c for c in v.cautions)
    # a weak ride (15 um moves it by ~1.6 sd) is not named
    assert offset_riders(_riding_doc(12.0)) == []
    # calibrated widths (b0's prior from the width reference, sd 2 um): the doubt is 2 prior
    # sds, 4 um, which moves it by 0.9 sd; with a prior sd of 5 um, 10 um moves it by 2.3
    assert offset_riders(_riding_doc(beta, b0_prior_sd=0.002)) == []
    r = offset_riders(_riding_doc(beta, b0_prior_sd=0.005))
    assert [x["param"] for x in r] == ["thermal.tau_s"] and r[0]["doubt_mm"] == pytest.approx(0.010)
    assert r[0]["calibrated"] and "the width reference knows the offset to +-5.0 um" in " ".join(
        assess(_riding_doc(beta, b0_prior_sd=0.005)).cautions)


def test_an_exported_value_that_rides_the_offset_is_refused():
    doc = _riding_doc(60.0, rider="pa.tau_s")
    v = assess(doc)
    assert not v.trustworthy and "pa.tau_s rides the width offset" in v.problems[0]
    assert "calibrate the widths" in v.advice


def test_a_value_riding_calibrated_widths_is_told_what_spoiled_the_reference():
    """Calibrated widths (reference sd 5 um: doubt 10 um, which moves tau by ~2.3 sd) whose
    exported value still rides the offset: the advice is not "calibrate" (they are) but what
    the calibration block says spoiled the reference's reading."""
    doc = _riding_doc(60.0, rider="pa.tau_s", b0_prior_sd=0.005)
    cal = {"applied": True, "glare_bracket_mm": [-0.040, -0.048],
           "warnings": ["width reference 1.00 mm still changes by +10 um beyond the end of its "
                        "section (its settling time constant 1.6 s): the flow had not settled"]}
    doc["diagnostics"]["measurement"] = {"scans": [{"scan": "scan0", "calibration": cal}]}
    v = assess(doc)
    assert not v.trustworthy and "pa.tau_s rides the width offset" in v.problems[0]
    assert "calibrate the widths" not in v.advice and "+-5.0 um" in v.advice
    assert "glare" in v.advice and "had not settled" in v.advice
    # nothing named in the block: the generic way to a closer reading, and neither cause
    doc["diagnostics"]["measurement"] = {"scans": [{"scan": "scan0", "calibration": {"applied": True}}]}
    v = assess(doc)
    assert "1200 dpi" in v.advice and "glare" not in v.advice and "settled" not in v.advice
