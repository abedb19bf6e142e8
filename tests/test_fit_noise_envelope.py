"""The noise-model envelope (fit/noise_envelope.py): when the widths carry a short wobble
the default noise model cannot hold, `calib fit` widens every interval to the hull of its
posterior and the short-wobble fit's Laplace approximation; otherwise it changes nothing.

The data: the spiral-step test track printed by ``pa`` on the virtual printer (direct
drive, tau 0.043 s), with 2 um of white measurement noise and Ornstein-Uhlenbeck wobbles:
one of 6 um over 30 mm (the long wander) and, in the first case, one of 6 um over 0.4 mm
(the bead's short wobble: BIC 37-51 lower with it on seeds 1-3)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

TAU_S = 0.043
LONG = ((30.0, 0.006),)
SHORT_AND_LONG = ((0.4, 0.006), (30.0, 0.006))


@pytest.fixture(scope="module")
def vprint():
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile("direct_drive")
    _, man = spiral_step.generate(prof, speeds_mm_s=(20.0,), n_steps=6, step_s=(2.0,),
                                  widths_mm=(0.35, 0.8))
    man = man.cut_to_test_tracks(pad_s=0.0)
    truth = print_virtual(man, build_model("pa", prof), {"pa.tau_s": TAU_S}).table
    return man, truth


def _widths(truth, wobbles_mm, seed=1):
    """The true widths + 2 um white noise + an OU wobble per (correlation length, sd) in
    ``wobbles_mm`` (mm)."""
    t = truth.subset(np.ones(len(truth), bool))
    rng = np.random.default_rng(seed)
    t.width_mm = truth.width_mm + 0.002 * rng.standard_normal(len(t))
    t.width_sd_mm[:] = 0.002
    for tid in np.unique(t.track):
        i = np.flatnonzero(t.track == tid)
        i = i[np.argsort(t.s_mm[i])]
        ds = np.diff(t.s_mm[i], prepend=t.s_mm[i][0] - 1e9)
        for ell, sd in wobbles_mm:
            phi = np.exp(-ds / ell)
            z = np.zeros(len(i))
            for k in range(len(i)):
                z[k] = (phi[k] * z[k - 1] if k else 0.0) + sd * np.sqrt(1 - phi[k] ** 2) * rng.standard_normal()
            t.width_mm[i] += z
    return t


def _fit(vprint, tmp_path, wobbles_mm, extra=(), seed=2):
    from calib.cli import main

    man, truth = vprint
    mp = man.save(tmp_path / "a.manifest.json")
    w = _widths(truth, wobbles_mm, seed).save(tmp_path / "a.csv")
    out = tmp_path / f"fit{len(extra)}.json"
    code = main(["fit", str(w), "--manifest", str(mp), "--model", "pa", "--quiet", "--seed", "3",
                 "-o", str(out), *extra])
    assert code in (0, 3)
    return json.loads(out.read_text())


def test_short_wobble_widens_every_interval_to_the_hull(vprint, tmp_path, capsys):
    """With a 0.4 mm wobble in the widths (seed 2: BIC 37 lower with it, and the short
    wobble's MAP tau 0.0428 s against 0.0421, one Laplace sd): applied, every 95 % interval
    is exactly the hull of the posterior's (the same fit with --no-noise-envelope) and the
    short fit's, tau's grew, the median is the posterior's, and the firmware number
    (derived from the draws of tau) is widened alike."""
    doc = _fit(vprint, tmp_path, SHORT_AND_LONG)
    env = doc["diagnostics"]["noise_envelope"]
    assert env["applied"] and env["bic_short"] < env["bic_default"] - 10
    assert 0.004 < env["sigma_short_mm"] < 0.009
    assert "noise model: the widths also carry a short wobble" in capsys.readouterr().out
    off = _fit(vprint, tmp_path, SHORT_AND_LONG, ("--no-noise-envelope",))
    assert "noise_envelope" not in off["diagnostics"]
    for n, short in env["short_ci95"].items():
        p, q = doc["params"][n], off["params"][n]
        assert p["median"] == q["median"]
        assert p["ci95"] == pytest.approx([min(q["ci95"][0], short[0]), max(q["ci95"][1], short[1])])
        grew = p["ci95"][0] < q["ci95"][0] or p["ci95"][1] > q["ci95"][1]
        assert grew == (n in env["widened"])
    assert "pa.tau_s" in env["widened"] and "noise.sigma_extra_mm" not in env["short_ci95"]
    lo, hi = doc["derived"]["pressure_advance_s"]["ci95"]
    s_lo, s_hi = env["widened"]["pa.tau_s"]["ci95_short"]
    assert lo <= s_lo * 1.001 and hi >= s_hi * 0.999
    # fit.json keeps the short fit's draws, for `calib export`'s interval of K
    E = np.asarray(doc["envelope_samples"]["noise"])
    assert E.shape == (256, len(doc["param_names"]))
    t = E[:, doc["param_names"].index("pa.tau_s")]
    assert s_lo * 0.95 < np.quantile(t, 0.025) and np.quantile(t, 0.975) < s_hi * 1.05
    assert off["envelope_samples"].get("noise") is None


def test_no_short_wobble_changes_nothing(vprint, tmp_path):
    """Widths with only the long wander: the short wobble is not worth 10 in BIC, so
    nothing is widened and the intervals are those of --no-noise-envelope to the last bit."""
    doc = _fit(vprint, tmp_path, LONG)
    env = doc["diagnostics"]["noise_envelope"]
    assert not env["applied"] and env["widened"] == {}
    assert "noise" not in doc["envelope_samples"]
    off = _fit(vprint, tmp_path, LONG, ("--no-noise-envelope",))
    assert doc["params"] == off["params"]
    assert doc["derived"]["pressure_advance_s"] == off["derived"]["pressure_advance_s"]


def test_laplace_draws_follow_the_laplace_approximation(vprint):
    """Draws of a MAP's Laplace approximation are Gaussian in the sampler's coordinates:
    log tau for the positive tau (a log-normal in theta), with the MAP's covariance."""
    from dataclasses import replace

    from fit.data import scan_from_table
    from fit.noise_envelope import laplace_draws
    from fit.sampler import fit_map, make_problem

    man, truth = vprint
    pb = make_problem("pa", scan_from_table(_widths(truth, LONG), man, "a"))
    m = fit_map(pb, seed=0)
    i = pb.param_names.index("pa.tau_s")
    cov = np.diag(np.full(pb.ndim, 1e-12))
    cov[i, i] = (0.1 * TAU_S) ** 2            # sd 10 % of tau: 0.1 in log tau
    th = m.theta.copy()
    th[i] = TAU_S
    d = laplace_draws(pb, replace(m, theta=th, cov=cov), 20000, np.random.default_rng(0))
    z = np.log(d[:, i] / TAU_S) / 0.1
    assert abs(z.mean()) < 0.03 and abs(z.std() - 1) < 0.03
    assert stats.kstest(z, "norm").pvalue > 0.01
