"""The foreign printer (bench/foreign_printer.py) against the library where their physics
coincide: two integrators written apart must agree there, or the discovery bench scores
the integrators instead of the effects."""
import numpy as np

import bench.foreign_printer as fp
from fit.context import SimContext
from fit.geometry import bead_width_mm
from fit.hidden import _theta, probe_manifest
from fit.model import build_model

TAU_S, BE_MM = 0.35, 0.8


def _widths(man, hidden, p, spec, values):
    """(foreign, library) widths in mm at the foreign printer's stations, the stop blobs out."""
    a, h, smp = fp.simulate(man, TAU_S, hidden, p)
    wf = np.asarray(bead_width_mm(np.maximum(a, 0.0), h))
    model = build_model(spec, man.printer)
    wl = np.asarray(model.predict(SimContext.build(man, smp), _theta(model, values)[None]))[0]
    stop = np.array([man.track(int(k)).params["stop_s_mm"] for k in smp.track])
    keep = np.abs(smp.s_mm - stop) > 1.0
    return wf[keep], wl[keep], smp.track[keep], smp.s_mm[keep]


def _median_apart_mm(wf, wl, trk):
    """The largest per-track median |foreign - library| (mm). Medians: the deposition is
    meant to differ (a Gaussian footprint against the library's window), which shows only
    where the width steps (up to 25 um at the slow-to-fast change of the 140 mm/s track)."""
    return max(np.median(np.abs(wf - wl)[trk == k]) for k in np.unique(trk))


def test_plain_spring_agrees_with_the_library_within_2_um():
    wf, wl, trk, _ = _widths(probe_manifest(n_tracks=4, length_mm=40.0), None, {}, "pa", {"pa.tau_s": TAU_S})
    assert _median_apart_mm(wf, wl, trk) < 0.002


def test_backlash_agrees_after_a_prime_line_and_not_without_one():
    """The play alone (elastic zone ~0): the same operator in both, started differently
    (library pushed forward, foreign in the middle of the band), so the first track's start
    differs by Be/2 of filament unless a prime line sets the state first."""
    p = {"be_mm": BE_MM, "lag_s": 1e-4}
    vals = {"pa.tau_s": TAU_S, "backlash.be_mm": BE_MM}
    for prime_mm, first_apart in ((0.0, True), (fp.PRIME_MM, False)):
        man = probe_manifest(n_tracks=4, length_mm=40.0, prime_mm=prime_mm)
        wf, wl, trk, s = _widths(man, "backlash", p, "pa+backlash", vals)
        start = np.max(np.abs(wf - wl)[(trk == 0) & (s < 2.0)])
        assert start > 0.3 if first_apart else start < 0.01
        rest = trk > 0 if first_apart else trk >= 0
        assert _median_apart_mm(wf[rest], wl[rest], trk[rest]) < 0.002


def test_probe_prints_the_width_reference_our_patterns_print():
    """``reference=True``: the probe's prime is the patterns' width reference (a serpentine
    of 2.5 and 1 nozzle sections at one volumetric flow), a track measure/calibrate.py reads
    sections from, printed before the tracks and clear of them; the tracks' own timeline
    is the default probe's, shifted by the reference's time."""
    from fit.geometry import bead_area_mm2, filament_area_mm2
    from measure.calibrate import reference_stations

    plain = probe_manifest(n_tracks=4, length_mm=40.0, prime_mm=20.0)
    man = probe_manifest(n_tracks=4, length_mm=40.0, prime_mm=20.0, reference=True)
    ref = man.tracks[-1]
    assert ref.kind == "prime" and ref.id == 4 and ref.params["role"] == "width_reference"
    smp, section, since, settle = reference_stations(man)
    widths = {round(float(w), 2) for w in smp.width_nominal_mm}
    assert widths == {0.4, 1.0} and len(np.unique(section)) == 4 and np.all(since >= 0)
    tl = man.timeline
    on = tl.track == ref.id
    af = filament_area_mm2(1.75)
    # one extruder rate, each section at the head speed that lays its width at that flow
    assert np.ptp(tl.ve_mm_s[on]) < 1e-9
    q = tl.ve_mm_s[on][0] * af
    for s0, s1, w in ref.params["sections_mm"]:
        mid = on & (tl.s_mm > s0 + 1.0) & (tl.s_mm < s1 - 1.0)
        assert np.allclose(tl.v_mm_s[mid] * bead_area_mm2(w, 0.2), q, rtol=1e-6)
    # before every track, and >= 5 mm from any of them
    first = min(np.min(tl.t_s[tl.track == k]) for k in range(4))
    assert np.max(tl.t_s[on]) < first
    test_xy = np.vstack([np.asarray(t.points_mm) for t in man.tracks[:4]])
    assert np.min(ref.points_mm[:, 1]) - np.max(test_xy[:, 1]) >= 5.0
    # the tracks as the default probe prints them, later by the reference's time
    for k in range(4):
        a, b = plain.timeline.track == k, tl.track == k
        assert np.allclose(np.diff(plain.timeline.t_s[a]), np.diff(tl.t_s[b]))
        assert np.allclose(plain.timeline.s_mm[a], tl.s_mm[b])


def test_rendered_probe_is_measured_as_the_foreign_printer_laid_it():
    """render_foreign_case pictures the foreign widths with every phenomenon and measures
    them with our pipeline: the widths read back calibrated by the probe's width reference
    (the edge offset of every phenomenon, -40 to -50 um, taken off within its sd; session
    60: the reference's glare check no longer counts a run the head slowed through) with
    the scatter of a realistic flatbed, the pressure peaks at the track starts (1.2-1.4 mm
    on 0.4-0.85 mm lines) drawn as laid (a cap meant for the stop blobs once clipped them
    to twice the commanded width: 1.36 -> 0.8 mm, and the fit read a misfit the printer did
    not make)."""
    c = fp.render_foreign_case("bed", 0)
    t, tru = c.table, c.truth_mm
    ok = t.valid & (tru > 0)
    err = t.width_mm[ok] - tru[ok]
    off = np.median(err)
    cal = c.calibration
    assert c.figures["valid"] > 0.7 and not c.figures["apparent"] and cal["applied"]
    assert -0.06 < cal["offset_mm"] < -0.03                      # the edge offset of every phenomenon
    assert abs(off) < max(3 * cal["offset_sd_mm"], 0.005) and cal["offset_sd_mm"] < 0.012
    assert np.percentile(np.abs(err - off), 90) < 0.025
    # away from the stops every width is the one laid (the bead's own wobble aside)
    _, man, tau, p = fp._draw("bed", 0, fp.REFERENCE)
    a, h, smp = fp.simulate(man, tau, "bed", p, ds_mm=0.25, margin_mm=0.0)
    laid = dict(zip(zip(smp.track, np.round(smp.s_mm, 3)), bead_width_mm(np.maximum(a, 0.0), h)))
    stop = np.array([man.track(int(k)).params["stop_s_mm"] for k in t.track])
    away = (np.abs(t.s_mm - stop) > 1.0) & (tru > 0.3)
    ratio = tru[away] / np.array([laid[(k, s)] for k, s in zip(t.track[away], np.round(t.s_mm[away], 3))])
    assert np.all(np.abs(ratio - 1.0) < 0.1)


def test_linear_advance_at_tau_cancels_the_plain_springs_lag():
    """Marlin's LA on this printer (``with_linear_advance``): E + K ve gives the spring
    P = tau ve at K = tau, so the nozzle's outflow is the commanded flow (dP/dt = ve + K dve/dt
    - P / tau; P = tau ve solves it): within 1 % of the commanded peak while printing, where
    without advance it lags by the spring's whole response. No retractions: an un-retraction
    fills the spring itself, which no advance is meant to cancel."""
    man = probe_manifest(n_tracks=2, length_mm=40.0, retract_mm=0.0)
    af = np.pi * 1.75 ** 2 / 4

    def lag(k_s):
        rec = {}
        fp.simulate(fp.with_linear_advance(man, k_s), TAU_S, None, {}, record=rec)
        t, q = rec["t_s"], rec["q_mm3_s"]
        tl = man.timeline
        ve = np.interp(t, tl.t_s, tl.ve_mm_s)
        on = np.interp(t, tl.t_s, ((tl.ve_mm_s > 0) & (tl.v_mm_s > 1e-6)).astype(float)) > 0.999
        return np.max(np.abs(q[on] - ve[on] * af)) / np.max(ve[on] * af)

    assert lag(TAU_S) < 0.01 < 0.5 < lag(0.0)


def test_the_foreign_printers_best_advance_is_near_tau_and_beats_none():
    from fit import firmware_match as fm
    from patterns.profile import load_profile

    ref = fm.standard_reference(load_profile("adventurer3"))
    k, e = fp.optimal_advance(ref, TAU_S, None, {})
    # not tau exactly: the Gaussian footprint rounds each line's ends whatever the flow
    assert 0.85 * TAU_S < k < TAU_S
    assert e < fp.width_error_mm(ref, TAU_S, None, {}, TAU_S) < 0.2 * fp.width_error_mm(ref, TAU_S, None, {}, 0.0)
