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
