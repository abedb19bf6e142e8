"""The fit reads its predicted widths through the measurement's along-track kernel
(fit/observe.py): the mean of STRIP_LINES sub-stations over STRIP_MM, each offset's
sequence despeckled (open-close / close-open, SPECK_MM) first.

Known answers: flat morphological filters commute with monotone functions (Serra 1982),
so despeckling the pictures of a bead (measure/widths.py ``_despeckle``, on pixels) and
despeckling its width (the fit's kernel) give the same width; the compiled kernel, which
filters only near turns of the sequence, equals filtering everything."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.special import expit, logit

from measure.table import WidthTable
from measure.widths import SPECK_MM, STRIP_LINES, STRIP_MM, _despeckle, neighbour_corr
from patterns.manifest import Samples


def _bead(s):
    """A laid width (mm) along one track with what the despeckling must remove (a 0.3 mm
    bulge, a 0.2 mm neck: shorter than SPECK_MM) and keep (a 0.4 mm ramp up, a 1 mm bump)."""
    w = np.full_like(s, 0.45)
    w += 0.12 * np.clip(1 - np.abs(s - 3.0) / 0.15, 0, 1)
    w -= 0.10 * np.clip(1 - np.abs(s - 6.0) / 0.10, 0, 1)
    w += 0.25 * np.clip((s - 9.0) / 0.4, 0, 1)
    w += 0.08 * ((s > 12.0) & (s < 13.0))
    return w


def _stations(n=64):
    s = STRIP_MM * np.arange(n)
    z = np.zeros(n)
    return Samples(track=np.zeros(n, np.int64), s_mm=s, x_mm=s, y_mm=z, t_s=s, nx=z, ny=z + 1.0,
                   width_nominal_mm=z + 0.45, height_mm=z + 0.2)


def _table(smp, rho):
    n = len(smp.track)
    return WidthTable(track=smp.track, s_mm=smp.s_mm, x_mm=smp.x_mm, y_mm=smp.y_mm, t_s=smp.t_s,
                      width_mm=np.full(n, 0.45), width_sd_mm=np.full(n, 0.01), valid=np.ones(n, bool),
                      flag=np.full(n, "", dtype=object), width_corr_prev=rho)


@pytest.mark.parametrize("bright_bead", [True, False])
def test_despeckled_picture_reads_the_despeckled_width(bright_bead):
    from fit.observe import observation_of

    smp = _stations()
    n, blur = len(smp.track), 0.03
    t = np.tile(np.linspace(-0.5, 0.5, 41), (n, 1))                     # mm across the track
    f = (np.arange(STRIP_LINES) + 0.5) / STRIP_LINES - 0.5
    w_sub = _bead(smp.s_mm[:, None] + f[None, :] * STRIP_MM)             # (n, lines) laid
    # each line's profile across the track: a blurred edge at +-w/2, monotone in w at any t
    prof = expit((w_sub.T[:, :, None] / 2 - np.abs(t)[None]) / blur)     # (lines, n, m)
    stack = (prof if bright_bead else 1.0 - prof).astype(np.float64)
    out = _despeckle(stack, smp, t)
    p = out if bright_bead else 1.0 - out
    # invert the edge at the offset nearest half height: the width each line now shows
    m = np.argmin(np.abs(p - 0.5), axis=2)
    pm = np.take_along_axis(p, m[..., None], 2)[..., 0]
    w_seen = 2 * (np.abs(np.take_along_axis(np.broadcast_to(t, p.shape), m[..., None], 2)[..., 0])
                  + blur * logit(pm))
    picture = w_seen.mean(axis=0)                                        # (n,) the station's width

    obs = observation_of(_table(smp, neighbour_corr(smp, t)))
    assert obs is not None and obs.lines == STRIP_LINES
    model = obs.apply(w_sub.reshape(1, -1))[0]
    np.testing.assert_allclose(model, picture, atol=1e-6)
    # and the kernel did something: the short bulge and neck are gone, the long bump kept
    laid = w_sub.mean(axis=1)
    s = smp.s_mm
    assert laid[np.argmin(np.abs(s - 3.0))] - model[np.argmin(np.abs(s - 3.0))] > 0.04
    assert model[np.argmin(np.abs(s - 6.0))] - laid[np.argmin(np.abs(s - 6.0))] > 0.02
    np.testing.assert_allclose(model[(s > 12.4) & (s < 12.6)], laid[(s > 12.4) & (s < 12.6)], atol=1e-9)


def _filter_everything(obs, w):
    """The reference: despeckle every run in full (scipy), each continued by its end
    values, then the strip mean."""
    k = obs.speck

    def op(a):
        return ndimage.maximum_filter1d(ndimage.minimum_filter1d(a, k, axis=1, mode="nearest"), k, axis=1,
                                        mode="nearest")

    def cl(a):
        return ndimage.minimum_filter1d(ndimage.maximum_filter1d(a, k, axis=1, mode="nearest"), k, axis=1,
                                        mode="nearest")

    out = w.copy()
    for a, b in zip(obs.starts[:-1], obs.starts[1:]):
        r = obs.rows[a:b]
        seq = np.pad(w[:, r], ((0, 0), (obs.pad, obs.pad)), mode="edge")
        out[:, r] = (0.5 * (cl(op(seq)) + op(cl(seq))))[:, obs.pad:-obs.pad]
    return out.reshape(len(w), -1, obs.lines).mean(axis=2)


def test_kernel_filtering_near_turns_equals_filtering_everything():
    from fit.observe import observation_of

    rng = np.random.default_rng(3)
    smp = _stations(200)
    rho = np.full(200, 0.45)
    rho[[0, 37, 38, 120]] = 0.0                                 # four runs (one of a single station)
    obs = observation_of(_table(smp, rho))
    # plateaus, ramps, short spikes and dips, and fine ripple, for 8 parameter sets
    s = np.repeat(smp.s_mm, STRIP_LINES) + np.tile(obs.offsets_mm, 200)
    w = np.stack([0.4 + 0.1 * np.round(np.sin(s / (1 + i)) * 3) / 3
                  + 0.05 * (rng.random(len(s)) < 0.02) * rng.standard_normal(len(s))
                  + (1e-3 * rng.standard_normal(len(s)) if i % 2 else 0.0) for i in range(8)])
    got = obs.apply(w)
    np.testing.assert_allclose(got, _filter_everything(obs, w), atol=2e-6)
    assert obs.apply(w[:1]).shape == (1, 200)
    np.testing.assert_allclose(obs.apply(w[:1])[0], got[0], atol=1e-12)        # serial = parallel
    # a station never printed stays NaN; a sub-station never printed reads as its centre
    w2 = w[:1].copy()
    w2[0, 5 * STRIP_LINES + STRIP_LINES // 2] = np.nan
    w2[0, 9 * STRIP_LINES] = np.nan
    r = obs.apply(w2)[0]
    assert np.isnan(r[5]) and np.isfinite(r[9]) and np.isfinite(r).sum() == 199


def test_tables_without_links_are_read_as_laid():
    from fit.observe import observation_of

    smp = _stations()
    assert observation_of(_table(smp, np.zeros(len(smp.track)))) is None
    # a link to a station that is not STRIP_MM before it joins nothing
    t = _table(smp, np.full(len(smp.track), 0.45))
    t.s_mm = t.s_mm * 2
    assert observation_of(t) is None


def test_fit_context_predicts_through_the_measurement():
    """A widths table the measurement linked: the fit's context holds the kernel on its
    physics, predicts at the table's stations, equals the laid widths where the bead is
    steady and reads less than the laid width on a short bulge."""
    from fit.context import SimContext
    from fit.data import scan_from_table
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile("direct_drive")
    _, man = spiral_step.generate(prof, speeds_mm_s=(20.0,), n_steps=2, step_s=(2.0,), widths_mm=(0.35, 0.8))
    man = man.cut_to_test_tracks(pad_s=1.0)
    model = build_model("pa", prof)
    truth = print_virtual(man, model, {"pa.tau_s": 0.043}).table
    table = truth.subset(np.ones(len(truth), bool))
    table.width_sd_mm[:] = 0.005
    first = np.r_[True, np.diff(table.track) != 0]
    table.width_corr_prev = np.where(first, 0.0, 0.45)
    sc = scan_from_table(table, man, "linked")
    assert sc.ctx.physics is not None and sc.ctx.physics.obs is not None
    obs = sc.ctx.physics.obs
    # sub-stations only near the steps and the ends; the rest one point per station
    assert sc.ctx.physics.n_samples == obs.n_points
    assert len(table) < obs.n_points < 0.6 * STRIP_LINES * len(table)
    th = model.theta_from({"pa.tau_s": 0.043})[None]
    seen = model.predict(sc.ctx, th)[0]
    laid = model.predict(SimContext.build(man, sc.samples), th)[0]
    assert seen.shape == laid.shape == (len(table),)
    ok = np.isfinite(laid)
    assert np.array_equal(np.isfinite(seen), ok)
    d = seen[ok] - laid[ok]
    # steady: the laid width moves < 10 nm per station over +-2 stations (0.5 mm)
    steady = ndimage.maximum_filter1d(np.abs(np.gradient(laid[ok])), 5) < 1e-5
    assert steady.sum() > 100 and np.max(np.abs(d[steady])) < 1e-5
    # the kernel moves the widths only where they change, and never by more than the change
    assert 1e-4 < np.max(np.abs(d)) < np.ptp(laid[ok])
    # without links the same table is predicted as laid
    table.width_corr_prev = np.zeros(len(table))
    sc0 = scan_from_table(table, man, "unlinked")
    assert sc0.ctx.physics is None or sc0.ctx.physics.obs is None
    np.testing.assert_allclose(model.predict(sc0.ctx, th)[0], laid, atol=2e-6, equal_nan=True)


@pytest.mark.parametrize("pattern,printer", [("stop-mid-path", "direct_drive"), ("spiral-step", "adventurer3")])
def test_sub_stations_only_near_changes_read_as_sub_stations_everywhere(monkeypatch, pattern, printer):
    """Stations NEAR_MM from any change of flow or speed take their sub-stations from the
    station widths; over time constants 0.005-2 s and three nozzle models the widths read
    stay within 0.2 um of sub-stations computed everywhere (0.10 um at worst on the
    stop-mid-path print: tau 0.005 s, a 0.2 mm ooze tail)."""
    import fit.observe as fo
    from fit.data import scan_from_table
    from fit.model import build_model
    from patterns.builder import PATTERNS
    from patterns.manifest import sample_points

    _, man = PATTERNS[pattern](printer)
    man = man.cut_to_test_tracks(pad_s=1.0)
    smp = sample_points(man)
    n = len(smp.track)
    first = np.r_[True, np.diff(smp.track) != 0]
    rho = np.where(first | (np.arange(n) % 4 == 0), 0.0, 0.45)      # ~1 mm runs, as measured
    table = _table(smp, rho)
    focused = scan_from_table(table, man, "focused").ctx
    monkeypatch.setattr(fo, "NEAR_MM", np.inf)
    full = scan_from_table(table, man, "full").ctx
    assert full.physics.obs.n_points == STRIP_LINES * n
    assert focused.physics.obs.n_points < 0.5 * STRIP_LINES * n
    for spec in ("pa", "pa+nonlinear", "pa+backpressure+thermal"):
        model = build_model(spec)
        th = np.repeat(model.default_theta()[None], 8, axis=0)
        th[:, 0] = np.geomspace(0.005, 2.0, 8)
        a, b = model.predict(focused, th), model.predict(full, th)
        assert np.array_equal(np.isfinite(a), np.isfinite(b))
        assert np.nanmax(np.abs(a - b)) < 2e-4, spec


def test_constants_match_the_measurement():
    from fit.observe import observation_of

    smp = _stations()
    obs = observation_of(_table(smp, np.r_[0.0, np.full(len(smp.track) - 1, 0.45)]))
    assert obs.speck == int(round(SPECK_MM / (STRIP_MM / STRIP_LINES)))
    assert obs.strip_mm == STRIP_MM
    np.testing.assert_allclose(np.diff(obs.offsets_mm), STRIP_MM / STRIP_LINES)
