"""The width calibration's doubt carried into the intervals (fit/offset_envelope.py) and the
MAP's response to a common width offset (fit/influence.py offset_response), on a model
whose answer is known: a constant width, which an offset of every width moves one for one."""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from fit.data import ScanData
from fit.influence import influence, offset_response
from fit.likelihood import JointProblem, NoiseOptions
from fit.offset_envelope import offset_doubts, widen_offset
from fit.params import Param
from fit.result import ParamSummary
from fit.sampler import fit_map
from measure.table import WidthTable
from patterns.manifest import Samples


@dataclass
class _Ctx:
    n: int


class ConstModel:
    """w = c at every station (mm)."""
    spec = "const"

    def __init__(self):
        self.params = [Param("flow.w_mm", "mm", 0.5, 0.1, 1.0)]
        self.param_names = ["flow.w_mm"]

    def default_theta(self):
        return np.array([0.5])

    def predict(self, ctx, theta):
        th = np.atleast_2d(theta)
        return np.repeat(th[:, :1], ctx.n, axis=1)


def _scan(n=400, sd=0.005, seed=0):
    rng = np.random.default_rng(seed)
    track = np.repeat([0, 1], n // 2)
    s = np.tile(0.25 * np.arange(n // 2), 2)
    y = 0.45 + sd * rng.standard_normal(n)
    table = WidthTable(track=track, s_mm=s, x_mm=s, y_mm=track * 3.0, t_s=s / 20, width_mm=y,
                       width_sd_mm=np.full(n, sd), valid=np.ones(n, bool))
    smp = Samples(track=track, s_mm=s, x_mm=s, y_mm=track * 3.0, t_s=s / 20, nx=np.zeros(n), ny=np.ones(n),
                  width_nominal_mm=np.full(n, 0.45), height_mm=np.full(n, 0.2))
    gap = np.where(s == 0, np.inf, 0.25)
    return ScanData(name="scan", manifest=None, table=table, samples=smp, order=np.arange(n), y_mm=y,
                    sd_mm=np.full(n, sd), gap_mm=gap, ctx=_Ctx(n))


def _problem(sc):
    return JointProblem([sc], [ConstModel()], NoiseOptions(ar1=False, relative=False))


def test_a_constant_width_follows_a_common_offset_one_for_one():
    """d c / d offset = 1: the vector-whitened response equals the influence matrix's, with
    the wobble of the default noise model too."""
    sc = _scan()
    pb = _problem(sc)
    m = fit_map(pb)
    names, R = offset_response(pb, m.theta)
    assert names == ["flow.w_mm"]
    assert R[0, 0] == pytest.approx(1.0, rel=1e-6)
    pb2 = JointProblem([sc], [ConstModel()])
    m2 = fit_map(pb2)
    _, R2 = offset_response(pb2, m2.theta)
    inf = influence(pb2, m2.theta)
    assert R2[0, 0] == pytest.approx(inf.shift(np.ones(len(sc.order)))["flow.w_mm"], rel=1e-9)
    assert R2[0, 0] == pytest.approx(1.0, rel=1e-3)


class ConstAndDeadModel(ConstModel):
    """w = c, plus a parameter that moves nothing (spread's sigma at 0 under a flat prior)."""
    spec = "const+dead"

    def __init__(self):
        self.params = [Param("flow.w_mm", "mm", 0.5, 0.1, 1.0), Param("dead.x", "-", 0.0, 0.0, 1.0)]
        self.param_names = ["flow.w_mm", "dead.x"]

    def default_theta(self):
        return np.array([0.5, 0.0])


def test_a_parameter_the_widths_do_not_move_has_no_response_and_no_error():
    """bench_e2e seed 1, `pa+spread` with sigma at 0: the information matrix was singular and
    the fit chain raised "Singular matrix". The width still follows the offset one for one;
    the dead parameter does not respond."""
    pb = JointProblem([_scan()], [ConstAndDeadModel()], NoiseOptions(ar1=False, relative=False))
    theta = np.array(fit_map(pb).theta, dtype=float)
    theta[pb.param_names.index("dead.x")] = 0.0
    names, R = offset_response(pb, theta)
    assert names == ["flow.w_mm", "dead.x"]
    assert R[0, 0] == pytest.approx(1.0, rel=1e-6) and R[0, 1] == 0.0


def test_the_interval_carries_the_calibrations_offset_doubt():
    """Posterior sd s_post of c, the calibration knows the offset to s_b (2 um): the widened
    95 % interval's half-width is 1.96 sqrt(s_post^2 + s_b^2) (a Gaussian convolved with the
    offset's doubt); the median stays; widths without a calibration, or a model that fits
    the offset (scan_bias), are not widened."""
    sc = _scan()
    pb = _problem(sc)
    m = fit_map(pb)
    s_post = math.sqrt(m.cov[0, 0])
    rng = np.random.default_rng(1)
    draws = m.theta[0] + s_post * rng.standard_normal((40000, 1))
    q = np.quantile(draws[:, 0], [0.16, 0.84, 0.05, 0.95, 0.025, 0.975])
    ps = ParamSummary(name="flow.w_mm", median=float(np.median(draws)), mean=float(draws.mean()), sd=s_post,
                      ci68=tuple(q[0:2]), ci90=tuple(q[2:4]), ci95=tuple(q[4:6]), map=float(m.theta[0]))
    res = SimpleNamespace(map=m, samples=draws, param_names=list(pb.param_names), params={"flow.w_mm": ps},
                          derived={}, diagnostics={}, envelope_samples={})
    s_b = 0.002
    states = [{"scan": "scan", "calibration": {"applied": True, "offset_sd_mm": s_b}}]
    info = widen_offset(pb, res, states, seed=0)
    lo, hi = res.params["flow.w_mm"].ci95
    assert (hi - lo) / 2 == pytest.approx(1.96 * math.hypot(s_post, s_b), rel=0.03)
    assert res.params["flow.w_mm"].median == ps.median
    assert info["widened"]["flow.w_mm"]["ci95_posterior"] == pytest.approx(list(ps.ci95))
    assert (hi - lo) / (ps.ci95[1] - ps.ci95[0]) > 2.0          # s_b = 2 um against s_post ~0.25 um
    kept = res.envelope_samples["offset"][:, 0]                 # fit.json keeps the shifted draws
    assert len(kept) == 256 and np.std(kept) == pytest.approx(math.hypot(s_post, s_b), rel=0.15)
    assert offset_doubts(pb, [{"scan": "scan", "calibration": {"applied": False}}]) == [None]
    assert widen_offset(pb, res, [{"scan": "scan", "calibration": None}]) is None


def test_a_model_with_scan_bias_carries_the_offset_itself():
    sc = _scan()
    pb = SimpleNamespace(param_names=["pa.tau_s", "scan_bias.b0_mm"], scans=[sc])
    states = [{"scan": "scan", "calibration": {"applied": True, "offset_sd_mm": 0.002}}]
    assert offset_doubts(pb, states) == [None]
    pb.param_names = ["pa.tau_s"]
    assert offset_doubts(pb, states) == [pytest.approx(0.002)]


def test_a_map_fit_carries_the_doubt_in_its_covariance():
    """The Laplace form: var(c) grows by s_b^2 (R = 1), and nothing without a calibration."""
    from fit.offset_envelope import widen_map_offset

    sc = _scan()
    pb = _problem(sc)
    m = fit_map(pb)
    v0 = m.cov[0, 0]
    assert widen_map_offset(pb, m, [{"scan": "scan", "calibration": {"applied": False}}]) is None
    assert m.cov[0, 0] == v0
    info = widen_map_offset(pb, m, [{"scan": "scan", "calibration": {"applied": True, "offset_sd_mm": 0.002}}])
    assert m.cov[0, 0] == pytest.approx(v0 + 0.002 ** 2, rel=1e-6)
    assert info["sd_before"]["flow.w_mm"] == pytest.approx(math.sqrt(v0))


def _two_heights(offset_mm=0.0, sd=0.005, n=400):
    """Track 0 printed at 0.2 mm (the reference's height), track 1 at 0.1 mm whose widths
    read ``offset_mm`` wide of the truth, 0.45 mm (the reference's offset does not hold there)."""
    sc = _scan(n=n, sd=sd)
    h = np.where(sc.table.track == 0, 0.2, 0.1)
    sc.samples.height_mm[:] = h
    sc.y_mm = sc.y_mm + np.where(h == 0.1, offset_mm, 0.0)
    return sc


def _calibration(offset_mm=-0.040, sd_mm=0.002, height_mm=0.2):
    from measure.calibrate import calibrate

    rng = np.random.default_rng(3)
    nominal = np.repeat([1.0, 0.4, 1.0, 0.4], 40)
    phys = nominal + (1 - 1.0) * height_mm * (1 - np.pi / 4)
    width = phys + offset_mm + rng.normal(0, 0.002, len(nominal))
    cal = calibrate(width, np.ones(len(nominal), bool), nominal, np.repeat(np.arange(4), 40),
                    height_mm=height_mm).to_dict()
    cal["offset_sd_mm"] = sd_mm
    return cal


def test_a_track_at_another_height_carries_its_own_offset_doubt():
    """The calibration records its reference's layer height; a track printed at half of it
    gets s_g = (|b0| + 2 sd) ln 2, none at the reference's own height; the constant width
    responds to that track's offset by its share of the information (1/2 here: equal
    stations and sds), so var(c) grows by s_b^2 + (s_g / 2)^2 (Laplace)."""
    from fit.offset_envelope import height_doubts, widen_map_offset

    cal = _calibration()
    assert cal["height_mm"] == pytest.approx(0.2)
    assert abs(cal["offset_mm"] + 0.040) < 0.002
    sc = _two_heights()
    pb = _problem(sc)
    (groups,) = height_doubts(pb, [{"scan": "scan", "calibration": cal}])
    assert len(groups) == 1
    h, mask, s_g = groups[0]
    assert h == pytest.approx(0.1) and mask.sum() == 200 and np.all(sc.table.track[sc.order][mask] == 1)
    assert s_g == pytest.approx((abs(cal["offset_mm"]) + 2 * 0.002) * math.log(2.0))
    m = fit_map(pb)
    v0 = m.cov[0, 0]
    info = widen_map_offset(pb, m, [{"scan": "scan", "calibration": cal}])
    assert m.cov[0, 0] == pytest.approx(v0 + 0.002 ** 2 + (s_g / 2) ** 2, rel=1e-3)
    assert info["height_sd_mm"] == {"scan": {"0.1": pytest.approx(s_g)}}
    # all at the reference's height, or a calibration that does not say its height: no doubt
    one = _problem(_scan())
    assert height_doubts(one, [{"scan": "scan", "calibration": cal}]) == [[]]
    assert height_doubts(pb, [{"scan": "scan", "calibration": {**cal, "height_mm": None}}]) == [[]]


def test_the_widened_interval_holds_a_track_read_wide_at_another_height():
    """The 0.1 mm track reads 25 um wide (the reference's offset, -40 um, is -15 there): the
    posterior's interval of c misses the truth 0.45 by ~50 of its sds; the interval that
    carries the height doubt holds it."""
    from fit.offset_envelope import widen_map_offset

    cal = _calibration()
    pb = _problem(_two_heights(offset_mm=0.025))
    m = fit_map(pb)
    c, sd0 = m.theta[0], math.sqrt(m.cov[0, 0])
    assert abs(c - 0.45) > 1.96 * sd0
    widen_map_offset(pb, m, [{"scan": "scan", "calibration": cal}])
    assert abs(c - 0.45) < 1.96 * math.sqrt(m.cov[0, 0])
