"""The printer's track placement against the registration's error (measure/placement.py).

Synthetic centre offsets with known per-track placements and known speed dependence:
the split recovers the within-track scatter, the placements' range and the slope, and
claims no speed dependence where there is none.
"""
import numpy as np
import pytest

from measure.placement import placement


def _stations(offsets_mm, normals, noise_mm, rng, n=40):
    track, c, nx, ny = [], [], [], []
    for k, (o, nrm) in enumerate(zip(offsets_mm, normals)):
        track.append(np.full(n, k))
        c.append(o + rng.normal(0.0, noise_mm, n))
        nx.append(np.full(n, nrm[0]))
        ny.append(np.full(n, nrm[1]))
    return (np.concatenate(track), np.concatenate(c), np.concatenate(nx), np.concatenate(ny),
            np.ones(n * len(offsets_mm), bool))


def test_speed_dependent_placement_of_parallel_tracks_is_recovered():
    rng = np.random.default_rng(1)
    v = np.linspace(20.0, 100.0, 12)                  # mm/s, one speed per track
    o = -0.08 + 0.0015 * v + rng.normal(0, 0.005, 12)  # 0.15 mm per 100 mm/s, as on StartStopTestPLA1
    track, c, nx, ny, ok = _stations(o, [(0.0, 1.0)] * 12, 0.02, rng)
    p = placement(track, c, nx, ny, ok, {k: float(v[k]) for k in range(12)})
    # median |N(0, s)| = 0.674 s
    assert abs(p.within_track_mm - 0.674 * 0.02) < 0.003
    assert p.tracks == 12 and p.track_offset_mm[0] < -0.03 and p.track_offset_mm[1] > 0.05 and p.notable
    assert abs(p.speed_mm_per_100mm_s - 0.15) < 0.02 and p.speed_p < 1e-3
    assert f"{p.speed_mm_per_100mm_s:.2f} mm further per 100 mm/s" in p.sentence()


def test_placement_unrelated_to_speed_claims_no_slope():
    rng = np.random.default_rng(2)
    v = np.linspace(20.0, 100.0, 12)
    o = rng.permutation(np.linspace(-0.1, 0.1, 12))   # large placements, in no order of speed
    nrm = [(0.0, 1.0), (1.0, 0.0)] * 6
    track, c, nx, ny, ok = _stations(o, nrm, 0.01, rng)
    p = placement(track, c, nx, ny, ok, {k: float(v[k]) for k in range(12)})
    assert p.notable and not np.isfinite(p.speed_mm_per_100mm_s) and p.speed_p > 1e-3
    assert "per 100 mm/s" not in p.sentence()


def test_slope_in_two_directions_and_tracks_on_their_lines():
    rng = np.random.default_rng(3)
    v = np.tile(np.linspace(20.0, 120.0, 8), 2)
    nrm = [(0.0, 1.0)] * 8 + [(1.0, 0.0)] * 8
    b = np.array([0.0005, 0.0010])                    # mm per mm/s along x and y
    o = np.array([np.dot(n, b) * vk for n, vk in zip(nrm, v)])
    track, c, nx, ny, ok = _stations(o, nrm, 0.005, rng)
    p = placement(track, c, nx, ny, ok, {k: float(v[k]) for k in range(16)})
    assert abs(p.speed_mm_per_100mm_s - 100 * np.hypot(*b)) < 0.01
    # tracks that lie on their commanded lines say nothing
    track, c, nx, ny, ok = _stations(np.zeros(16), nrm, 0.005, rng)
    q = placement(track, c, nx, ny, ok, {k: float(v[k]) for k in range(16)})
    assert not q.notable and q.sentence() == "" and q.within_track_mm < 0.005


def test_a_loose_along_track_place_is_said_with_its_figure_and_why_for_parallel_lines():
    """heading_resultant: 1 for lines one way (both directions of travel alike), ~0 on a
    spiral, 1 - 2f with a share f at right angles. The warning comes from the stations'
    along-track sd (>= ALONG_SD_WARN_MM), quotes it, and names parallel lines as the reason
    only for an automatic pose of lines that run one way."""
    from measure.placement import ALONG_SD_WARN_MM, along_track_warning, heading_resultant

    rng = np.random.default_rng(0)
    n = 2000
    th = np.where(rng.uniform(size=n) < 0.5, np.pi / 2, -np.pi / 2) + rng.normal(0, 0.02, n)
    nx, ny, ok = np.cos(th), np.sin(th), np.ones(n, bool)
    loose, tight = np.full(n, 0.46), np.full(n, 0.014)
    assert heading_resultant(nx, ny, ok) > 0.99
    w = along_track_warning(loose, nx, ny, ok, "auto+tracks+centres")
    assert "+/-0.46 mm" in w and "all run one way" in w
    assert along_track_warning(tight, nx, ny, ok, "auto+tracks+centres") is None
    assert along_track_warning(np.full(n, 0.99 * ALONG_SD_WARN_MM), nx, ny, ok, "auto") is None
    # a loose pose from markers or points is said, without the parallel-lines reason
    w = along_track_warning(loose, nx, ny, ok, "fiducials+tracks")
    assert "+/-0.46 mm" in w and "all run one way" not in w
    spiral = np.linspace(0, 8 * np.pi, n)
    assert heading_resultant(np.cos(spiral), np.sin(spiral), ok) < 0.05
    assert "all run one way" not in along_track_warning(loose, np.cos(spiral), np.sin(spiral), ok, "auto")
    across = th.copy()
    across[: n // 5] = 0.0                                    # a fifth of the stations across
    assert heading_resultant(np.cos(across), np.sin(across), ok) == pytest.approx(0.6, abs=0.02)
    assert along_track_warning(loose, nx, ny, ~ok, "auto") is None       # nothing valid: nothing said
    assert along_track_warning(None, nx, ny, ok, "auto") is None
