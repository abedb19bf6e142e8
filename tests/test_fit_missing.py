"""Stations flagged ``missing`` (no bead seen: width 0, valid 0) are censored data of the
fit (fit/likelihood.py, issue #10 item 5), not dropped samples:

    ln P(missing | theta) = ln Phi((w_min - m(theta)) / s),  s = sqrt(w_min^2 / 4 + sigma_extra^2)

The data: the spiral-step test track alone (as tests/test_fit_cli.py), printed on the
virtual printer by ``pa+offset`` (direct drive, tau 0.043 s, Kc 0.2 mm). The print starts
with no pressure, so no plastic flows until the advance reaches Kc: the first ~8 mm of the
track have no bead, and where the bead starts is set by Kc (delay Kc / ve)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

TRUTH = {"pa.tau_s": 0.043, "offset.kc_mm": 0.2}


@pytest.fixture(scope="module")
def vprint():
    """(model, manifest, true widths table) of the virtual print."""
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile("direct_drive")
    _, man = spiral_step.generate(prof, speeds_mm_s=(20.0,), n_steps=2, step_s=(2.0,),
                                  widths_mm=(0.35, 0.8))
    # no pad: the extruder starts from rest at the track (a pad would start it from rest
    # inside the prime line or before the restore that follows its retraction)
    man = man.cut_to_test_tracks(pad_s=0.0)
    model = build_model("pa+offset", prof)
    truth = print_virtual(man, model, TRUTH).table
    assert truth.valid.all()
    return model, man, truth


def _measured(truth, seed: int, noise_mm: float, px_mm: float):
    """What a scan with one pixel = ``px_mm`` (mm) and white width noise ``noise_mm`` (mm)
    reports: stations whose true bead is narrower than a pixel are ``missing`` (width 0,
    valid 0, width_sd = 1 px, as measure/widths.py writes them), the rest noisy widths."""
    t = truth.subset(np.ones(len(truth), bool))
    rng = np.random.default_rng(seed)
    t.width_mm = truth.width_mm + noise_mm * rng.standard_normal(len(t))
    t.width_sd_mm[:] = noise_mm
    miss = truth.width_mm < px_mm
    t.width_mm[miss] = 0.0
    t.width_sd_mm[miss] = px_mm
    t.valid[miss] = False
    t.flag[miss] = "missing"
    return t


def _scan(vprint, seed=0, noise_mm=0.01, px_mm=0.042):
    from fit.data import scan_from_table

    model, man, truth = vprint
    return scan_from_table(_measured(truth, seed, noise_mm, px_mm), man, f"s{seed}")


def _problem(model, sc, **kw):
    from fit.likelihood import NoiseOptions
    from fit.sampler import make_problem

    return make_problem(model, sc, NoiseOptions(**kw))


def _theta(problem, sigma_mm, kc_mm=TRUTH["offset.kc_mm"], tau_s=TRUTH["pa.tau_s"]):
    th = problem.default_theta()
    names = problem.param_names
    th[names.index("pa.tau_s")] = tau_s
    th[names.index("offset.kc_mm")] = kc_mm
    th[names.index("noise.sigma_extra_mm")] = sigma_mm
    if "noise.sigma_short_mm" in names:
        th[names.index("noise.sigma_short_mm")] = 0.0  # the censored term's s holds both wobbles
    return th


# -- (a) the censored term is the normal log-CDF ---------------------------------------

def test_censored_term_is_the_normal_log_cdf(vprint):
    model, _, _ = vprint
    sc = _scan(vprint)
    # no flow until the advance reaches Kc: a delay Kc / ve = 0.2 / 0.511 = 0.39 s, 7.8 mm
    # of track at 20 mm/s = 31 stations 0.25 mm apart (+ a few narrower than a pixel)
    assert 29 <= sc.n_missing <= 36
    assert np.all(sc.table.flag[sc.missing_idx] == "missing")
    pr, pr_off = _problem(model, sc), _problem(model, sc, missing=False)
    assert pr.n_missing == sc.n_missing and pr.n_obs == sc.n_valid + sc.n_missing
    assert pr_off.n_missing == 0 and pr_off.n_obs == sc.n_valid
    # measure wrote width_sd = 1 px = 0.042 mm: below the 0.05 mm floor
    np.testing.assert_allclose(pr.missing_w_min_mm[0], 0.05)
    # a Kc that starts the bead too early, and the truth, with two sigma_extra
    th = np.array([_theta(pr, 0.01, kc_mm=0.15), _theta(pr, 0.03)])
    ll = pr.pointwise(th)
    assert ll.shape == (2, pr.n_obs)
    # the valid terms (first n_valid columns) are exactly those of the fit without them
    np.testing.assert_array_equal(ll[:, :sc.n_valid], pr_off.pointwise(th))
    m = pr.predict(th, 0)[:, sc.missing_idx]
    for i, sig in enumerate((0.01, 0.03)):
        s = math.sqrt(0.05 ** 2 / 4 + sig ** 2)
        want = np.logaddexp(math.log(0.98) + stats.norm.logcdf((0.05 - m[i]) / s), math.log(0.02))
        np.testing.assert_allclose(ll[i, sc.n_valid:], want, rtol=1e-10, atol=1e-12)
    assert ll[0, sc.n_valid:].sum() < ll[1, sc.n_valid:].sum() - 20   # Kc 0.15 lays beads there
    # the short wobble widens the soft threshold as the long one does: s^2 adds both
    pr_s = _problem(model, sc, short=True)
    th_s = np.insert(th[1], len(th[1]), 0.02)         # the short wobble's sd is the last parameter
    assert pr_s.param_names[-1] == "noise.sigma_short_mm"
    s = math.sqrt(0.05 ** 2 / 4 + 0.03 ** 2 + 0.02 ** 2)
    want = np.logaddexp(math.log(0.98) + stats.norm.logcdf((0.05 - m[1]) / s), math.log(0.02))
    np.testing.assert_allclose(pr_s.pointwise(th_s)[0, sc.n_valid:], want, rtol=1e-10, atol=1e-12)
    # log posterior includes them
    lp, lp_off = pr.log_prob(th)[0], pr_off.log_prob(th)[0]
    np.testing.assert_allclose(lp - lp_off, ll[:, sc.n_valid:].sum(axis=1), rtol=1e-9)
    # Student-t noise: the Student-t CDF of the same standardised value
    pr_t = _problem(model, sc, student_nu=4.0)
    lt = pr_t.pointwise(th)[0, sc.n_valid:]
    np.testing.assert_allclose(lt, np.logaddexp(math.log(0.98) + stats.t.logcdf(
        (0.05 - m[0]) / math.sqrt(0.05 ** 2 / 4 + 0.01 ** 2), 4.0), math.log(0.02)), rtol=1e-9)


def test_only_printed_missing_stations_are_data(vprint):
    """Rows flagged otherwise, valid rows and stations the context never printed are not
    censored data; a wider pixel is its own w_min."""
    from fit.data import missing_rows
    from fit.likelihood import censored_rows

    model, man, truth = vprint
    t = _measured(truth, 0, 0.01, 0.17)
    first = np.flatnonzero(t.flag == "missing")
    t.flag[first[0]] = "glare"                       # another reason: not a missing bead
    from fit.data import scan_from_table

    sc = scan_from_table(t, man, "x")
    assert first[0] not in sc.missing_idx and len(sc.missing_idx) == len(first) - 1
    np.testing.assert_array_equal(missing_rows(t, sc.samples), sc.missing_idx)
    pr = _problem(model, sc)
    np.testing.assert_allclose(pr.missing_w_min_mm[0], 0.17)
    # a station the simulation never printed: its model width is NaN, it is dropped
    for c in (sc.ctx, sc.ctx.physics):
        if c is not None:
            c.printed = c.printed.copy()
            c.printed[sc.missing_idx[0]] = False
    assert len(censored_rows(sc)) == sc.n_missing - 1
    assert _problem(model, sc).n_missing == sc.n_missing - 1


# -- (b) the missing stations carry the onset ----------------------------------------

def test_missing_stations_narrow_the_flow_threshold(vprint):
    """A 150 dpi scan (one pixel = 0.17 mm, width noise 0.05 mm): the bead's onset ramp is
    half below a pixel, so the valid samples alone bound Kc from below only loosely (a
    smaller Kc starts the bead earlier, where nothing is valid); the missing stations say
    there was no bead there. MAP of (tau, Kc, sigma_extra) with and without them, then
    the posterior of Kc on a grid with the others at the MAP: with them it is narrower
    on every seed (measured, seeds 0-4: sd ratio 0.47, 0.83, 0.53, 0.52, 0.65) and holds the
    truth (it does not reliably move the mean: |error| 0.0027 vs 0.0026 mm on average)."""
    from fit.sampler import fit_map

    model = vprint[0]
    kcs = np.linspace(0.1, 0.3, 161)
    ratios = []
    for seed in range(5):
        sc = _scan(vprint, seed, noise_mm=0.05, px_mm=0.17)
        assert sc.n_missing >= 20
        sd, mean = {}, {}
        for use in (False, True):
            pr = _problem(model, sc, missing=use, ar1=False)
            r = fit_map(pr, n_starts=1, seed=0)
            th = np.tile(r.theta, (len(kcs), 1))
            th[:, pr.param_names.index("offset.kc_mm")] = kcs
            lp = pr.log_prob(th)[0]
            p = np.exp(lp - lp.max())
            p /= p.sum()
            mean[use] = float(np.sum(p * kcs))
            sd[use] = float(np.sqrt(np.sum(p * (kcs - mean[use]) ** 2)))
        ratios.append(sd[True] / sd[False])
        assert sd[True] < sd[False], (seed, sd)
        assert abs(mean[True] - TRUTH["offset.kc_mm"]) < 2.5 * sd[True], (seed, mean, sd)
    assert np.median(ratios) < 0.7, ratios


# -- (c) no bead where the model lays one: evidence against it, bounded by misdetection

def test_missing_where_the_model_lays_a_full_bead_costs_the_misdetection_floor(vprint):
    model, man, truth = vprint
    from fit.data import scan_from_table

    t = _measured(truth, 0, 0.01, 0.042)
    i = int(np.flatnonzero(truth.width_mm > 0.34)[40])       # steady 0.35 mm bead
    t.width_mm[i], t.width_sd_mm[i], t.valid[i], t.flag[i] = 0.0, 0.042, False, "missing"
    sc = scan_from_table(t, man, "c")
    pr = _problem(model, sc)
    th = _theta(pr, 0.01)
    ll = pr.pointwise(th)[0]
    j = sc.n_valid + int(np.flatnonzero(sc.missing_idx == i)[0])
    others = np.delete(ll[sc.n_valid:], j - sc.n_valid)
    # ln(0.98 Phi((0.05 - 0.35) / 0.027) + 0.02) = ln 0.02: the misdetection floor
    assert ll[j] == pytest.approx(math.log(0.02), abs=1e-6)
    # before the onset the model lays nothing (ln Phi(1.86) = -0.03) or a bead still under
    # a pixel (the last station before it: -0.1)
    assert np.all(others > -0.5) and np.median(others) > -0.05
    # ... and the fit without the missing data does not see it
    pr_off = _problem(model, sc, missing=False)
    assert pr.log_prob(th)[0][0] < pr_off.log_prob(th)[0][0] - 3.5


# -- the switch on the command line ---------------------------------------------------

def test_cli_reports_and_ignores_missing_stations(vprint, tmp_path, capsys, monkeypatch):
    from calib.cli import main

    _, man, truth = vprint
    mp = man.save(tmp_path / "a.manifest.json")
    w = _measured(truth, 0, 0.01, 0.042).save(tmp_path / "a.csv")
    n_miss = int(np.sum(truth.width_mm < 0.042))
    base = ["fit", str(w), "--manifest", str(mp), "--model", "pa", "--map-only", "--quiet"]
    assert main(base + ["-o", str(tmp_path / "f.json")]) == 0
    out = capsys.readouterr().out
    assert f"missing stations: {n_miss} fitted" in out
    assert main(base + ["--ignore-missing", "-o", str(tmp_path / "g.json")]) == 0
    out = capsys.readouterr().out
    assert f"missing stations: {n_miss} on printed tracks, ignored" in out
    import json
    f, g = (json.loads((tmp_path / n).read_text()) for n in ("f.json", "g.json"))
    assert f["n_missing"] == n_miss and g["n_missing"] == 0
    assert f["n_obs"] == g["n_obs"] + n_miss
    # --model auto searches on the same data: with --ignore-missing, without them
    import fit.auto
    seen = []

    def fake_auto(scan, *a, **k):
        seen.append(scan.n_missing)
        raise SystemExit(0)
    monkeypatch.setattr(fit.auto, "auto_model", fake_auto)
    for extra in ([], ["--ignore-missing"]):
        with pytest.raises(SystemExit):
            main(["fit", str(w), "--manifest", str(mp), "--model", "auto", "--quiet",
                  "-o", str(tmp_path / "h.json")] + extra)
    assert seen == [n_miss, 0]


def test_cli_short_wobble_fits_the_second_wobble(vprint, tmp_path):
    """`calib fit --short-wobble`: widths that wander over ~0.4 mm and over 15 mm (OU
    processes of sd 6 um each) besides 2 um of white noise: the MAP has
    noise.sigma_short_mm near 6 um and a lower BIC than the one-wobble fit, which has no
    such parameter."""
    import json

    from calib.cli import main

    _, man, truth = vprint
    mp = man.save(tmp_path / "a.manifest.json")
    t = _measured(truth, 1, 0.002, 0.0)
    rng = np.random.default_rng(5)
    for tid in np.unique(t.track):
        i = np.flatnonzero(t.track == tid)
        i = i[np.argsort(t.s_mm[i])]
        ds = np.diff(t.s_mm[i], prepend=t.s_mm[i][0] - 1e9)
        for ell in (0.4, 15.0):          # the short wobble and the long wander, 6 um each
            phi = np.exp(-ds / ell)
            z = np.zeros(len(i))
            for k in range(len(i)):
                z[k] = (phi[k] * z[k - 1] if k else 0.0) + 0.006 * np.sqrt(1 - phi[k] ** 2) * rng.standard_normal()
            t.width_mm[i] += z
    w = t.save(tmp_path / "a.csv")
    base = ["fit", str(w), "--manifest", str(mp), "--model", "pa+offset", "--map-only", "--quiet"]
    assert main(base + ["-o", str(tmp_path / "one.json")]) == 0
    assert main(base + ["--short-wobble", "-o", str(tmp_path / "two.json")]) == 0
    one, two = (json.loads((tmp_path / n).read_text()) for n in ("one.json", "two.json"))
    assert "noise.sigma_short_mm" not in one["theta"]
    assert 0.003 < two["theta"]["noise.sigma_short_mm"] < 0.010
    assert two["bic"] < one["bic"] - 10
