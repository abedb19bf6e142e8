"""The per-station sd, calibrated by the scan's own scatter (measure/station_sd.py calibrated_sd):
recovery of a known scale and floor, blind to steps, never below the edge fit's sd."""
import numpy as np
import pytest

from measure.station_sd import calibrated_sd


def _tracks(rng, n_tracks=40, n=200, ds=0.25):
    """Stations every ds mm on n_tracks tracks whose physical width steps 0.4 -> 0.6 mm halfway
    (a flow step) and drifts slowly; formal sds log-uniform over 1-12 um."""
    track = np.repeat(np.arange(n_tracks), n)
    s = np.tile(np.arange(n) * ds, n_tracks)
    true = np.where(s < n * ds / 2, 0.4, 0.6) + 0.01 * np.sin(s / 7.0)
    sd = np.exp(rng.uniform(np.log(1e-3), np.log(12e-3), len(s)))
    return track, s, true, sd


def _correlated(rng, n_tracks, n, m=3):
    """Unit-variance noise correlated over m stations (a moving average), track by track."""
    z = rng.normal(size=(n_tracks, n + m - 1))
    z = np.stack([np.convolve(r, np.ones(m), "valid") for r in z]) / np.sqrt(m)
    return z.ravel()


def test_scale_and_floor_are_recovered_and_the_sd_explains_the_errors():
    rng = np.random.default_rng(1)
    track, s, true, sd = _tracks(rng)
    # the truth: errors 1.5 x the formal sd plus a 3 um floor, correlated over 0.5 mm
    # (neighbours share texture), as on realistic renders
    sd_true = np.sqrt((1.5 * sd) ** 2 + 3e-3 ** 2)
    err = sd_true * _correlated(rng, 40, 200)
    valid = np.ones(len(s), bool)
    new, k, f = calibrated_sd(track, s, true + err, sd, valid)
    assert abs(k - 1.5) < 0.2 and abs(f - 3e-3) < 0.8e-3, (k, f)
    z = err / new
    lo, hi = np.quantile(new, [0.2, 0.8])
    for m in (new <= lo, new >= hi):
        assert 0.8 < np.sqrt(np.mean(z[m] ** 2)) < 1.25
    # the old rule's view: adjacent stations share the correlated part and see too little
    _, k1, f1 = calibrated_sd(track, s, true + err, sd, valid, lag_mm=0.25)
    assert np.hypot(k1 * 2e-3, f1) < 0.85 * np.hypot(k * 2e-3, f)


def test_honest_sds_are_left_alone_and_never_shrunk():
    rng = np.random.default_rng(2)
    track, s, true, sd = _tracks(rng)
    valid = rng.uniform(size=len(s)) > 0.1           # flags leave gaps in the grid
    new, k, f = calibrated_sd(track, s, true + sd * rng.normal(size=len(s)), sd, valid)
    assert k < 1.08 and f < 0.6e-3, (k, f)
    # errors half the formal sd: the edge fit's own sd stays
    new, k, f = calibrated_sd(track, s, true + 0.5 * sd * rng.normal(size=len(s)), sd, valid)
    assert (k, f) == (1.0, 0.0) and np.array_equal(new, sd)
    # too few stations to tell: unchanged
    few = track < 1
    new, k, f = calibrated_sd(track[few], s[few], true[few], sd[few], valid[few])
    assert (k, f) == (1.0, 0.0)


def test_the_fit_weighs_by_the_stations_own_sd_and_old_tables_still_read(tmp_path):
    from measure.table import WidthTable

    n = 4
    base = dict(track=np.zeros(n, int), s_mm=np.arange(n) * 0.25, x_mm=np.zeros(n), y_mm=np.zeros(n),
                t_s=np.arange(n) * 0.1, width_mm=np.full(n, 0.4), width_sd_mm=np.full(n, 0.004),
                valid=np.ones(n, bool))
    t = WidthTable(**base, width_sd_own_mm=np.array([0.002, 0.002, np.nan, 0.003]))
    back = WidthTable.load(t.save(tmp_path / "w.csv"))
    np.testing.assert_allclose(back.fit_sd_mm(), [0.002, 0.002, 0.004, 0.003])
    # a table written before the column: the fit takes width_sd_mm
    old = tmp_path / "old.csv"
    lines = WidthTable(**base).to_csv_text().splitlines()
    old.write_text("\n".join(",".join(r.split(",")[:9]) for r in lines) + "\n")
    np.testing.assert_allclose(WidthTable.load(old).fit_sd_mm(), 0.004)


def test_slope_term_is_the_slope_times_the_place_sd_and_nothing_on_a_flat_track():
    from measure.station_sd import slope_sd

    s = np.arange(0, 20, 0.25)
    track = np.zeros(len(s), int)
    # a ramp of 0.5 mm/mm, exact widths: slope x place sd everywhere
    w = 0.3 + 0.5 * s
    out = slope_sd(track, s, w, np.zeros(len(s)), np.ones(len(s), bool), np.full(len(s), 0.1))
    assert np.allclose(out, 0.05)
    # a flat track with noise of known sd: the debiased slope adds little on average
    rng = np.random.default_rng(1)
    sd = np.full(2000, 0.008)
    s2 = np.arange(2000) * 0.25
    w2 = 0.5 + sd * rng.standard_normal(2000)
    out2 = slope_sd(np.zeros(2000, int), s2, w2, sd, np.ones(2000, bool), np.full(2000, 0.2))
    # without the debiasing the RMS slope would be sqrt(2) 0.008 / 0.25 = 0.045 mm/mm, 9 um
    assert np.sqrt(np.mean(out2 ** 2)) < 0.004
    # a step: the corner stations carry it, the far ones not; invalid stations and an
    # unknown place (0) add nothing
    w3 = np.where(s < 10, 0.6, 0.3)
    valid = np.ones(len(s), bool)
    valid[3] = False
    out3 = slope_sd(track, s, w3, np.zeros(len(s)), valid, np.where(s < 15, 0.1, 0.0))
    i = int(np.searchsorted(s, 10.0))
    assert out3[i] == pytest.approx(0.1 * 0.3 / 0.25 / np.sqrt(2))
    assert out3[i - 1] == pytest.approx(out3[i])
    assert out3[i + 2] < 1e-9 and out3[3] == 0 and np.all(out3[s >= 15] == 0)
