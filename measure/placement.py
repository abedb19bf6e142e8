"""Where the printer put each track, against where the G-code told it to.

A registration maps the bed onto the picture; it cannot move one track against another.
When a printer lays its tracks off their commanded lines by different amounts (a gantry
that lags or racks with speed, backlash on a direction change), the bead centres sit off
the projected path track by track, and the registration residual (median |centre offset|,
measure/pipeline.py) counts that placement as misregistration. This module splits the two:

    c_i = o_k(i) + r_i                                                         (1)

c_i: the measured centre offset of station i along its track's normal (mm); o_k: the
median of c over track k's valid stations (its placement); r_i: what is left, the
registration's (and the edge fit's) own error. And, per track, the placement against the
head speed the track was printed at,

    o_k = n_k . (a + b v_k) + e_k                                              (2)

(n_k: the track's mean normal, v_k: its median head speed in mm/s, a and b 2-vectors in
mm and mm per mm/s, least squares over tracks): a significant b (F test of (2) against
b = 0) says the printer puts faster tracks elsewhere, which no picture can correct.

Measured on StartStopTestPLA1 (shared/realdata, a FlashForge Adventurer 3): residual
0.074 mm, median |r| 0.021 mm, o_k from -0.13 to +0.24 mm (5-95 %); in the block whose lines
step the speed from 20 to 100 mm/s, one G-code line's 1 mm/s section and its fast section
sit 0.05 -> 0.16 mm apart, growing with the speed (over the whole print (2) gives p = 0.15:
the other blocks' placements follow something else).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

#: A track needs this many valid stations for its placement o_k (1).
MIN_STATIONS = 8
#: The placements are worth a line to the user when their 5-95 % range exceeds this (mm):
#: a quarter of a 0.4 mm nozzle's bead, a tenth of the registration renders' residual.
NOTABLE_SPREAD_MM = 0.05
#: Speed dependence (2) is reported at this F-test p-value or below, with at least this
#: many tracks and a speed range of at least a factor of 1.5.
P_SPEED = 1e-3
MIN_TRACKS = 6


@dataclass
class Placement:
    """The split (1)-(2) of one measurement.

    within_track_mm        median |r| (mm): how far the beads stray from their own track's line
    track_offset_mm        (5th, 95th) percentile of the tracks' placements o_k (mm, along n_k)
    tracks                 tracks with a placement (>= MIN_STATIONS valid stations)
    speed_mm_per_100mm_s   |b| x 100 (mm of placement per 100 mm/s of head speed), NaN unless
                           (2) explains the placements at p <= P_SPEED
    speed_p                the F test's p-value (NaN when it could not be run)
    """

    within_track_mm: float
    track_offset_mm: tuple[float, float]
    tracks: int
    speed_mm_per_100mm_s: float = float("nan")
    speed_p: float = float("nan")

    def to_dict(self) -> dict:
        f = (lambda v: float(v) if np.isfinite(v) else None)
        return {"within_track_mm": f(self.within_track_mm),
                "track_offset_mm_p5_p95": [f(v) for v in self.track_offset_mm],
                "tracks": int(self.tracks),
                "speed_mm_per_100mm_s": f(self.speed_mm_per_100mm_s), "speed_p": f(self.speed_p)}

    @property
    def notable(self) -> bool:
        """The tracks' placements spread more than NOTABLE_SPREAD_MM."""
        lo, hi = self.track_offset_mm
        return bool(hi - lo > NOTABLE_SPREAD_MM)

    def sentence(self) -> str:
        """One clause for the user, or "" when the tracks lie where they were told."""
        if not (np.isfinite(self.within_track_mm) and self.notable):
            return ""
        lo, hi = self.track_offset_mm
        s = (f"each track's beads lie within {self.within_track_mm:.3f} mm of their own line; the tracks "
             f"sit {lo:+.2f} to {hi:+.2f} mm off their commanded lines (the printer's placement)")
        if np.isfinite(self.speed_mm_per_100mm_s):
            s += f", {self.speed_mm_per_100mm_s:.2f} mm further per 100 mm/s of head speed"
        return s


def placement(track, centre_mm, nx, ny, valid, speed_mm_s: dict | None = None) -> Placement:
    """Split the centre offsets ``centre_mm`` (N,) of stations on tracks ``track`` (N,), with
    normals (nx, ny) (N,) and ``valid`` (N,) bool, into (1); ``speed_mm_s`` maps a track id to
    its head speed (mm/s) for (2)."""
    track, c = np.asarray(track), np.asarray(centre_mm, float)
    ok = np.asarray(valid, bool) & np.isfinite(c)
    ids, o, n, r = [], [], [], []
    for k in np.unique(track[ok]):
        q = ok & (track == k)
        if q.sum() < MIN_STATIONS:
            continue
        ok_k = float(np.median(c[q]))
        ids.append(k)
        o.append(ok_k)
        nk = np.array([np.mean(np.asarray(nx)[q]), np.mean(np.asarray(ny)[q])])
        n.append(nk / (np.linalg.norm(nk) + 1e-12))
        r.append(c[q] - ok_k)
    if not ids:
        return Placement(float("nan"), (float("nan"), float("nan")), 0)
    o = np.asarray(o)
    res = Placement(float(np.median(np.abs(np.concatenate(r)))),
                    (float(np.percentile(o, 5)), float(np.percentile(o, 95))), len(ids))
    if speed_mm_s is None:
        return res
    v = np.array([speed_mm_s.get(int(k), np.nan) for k in ids], float)
    use = np.isfinite(v) & (v > 0)
    if use.sum() < MIN_TRACKS or not np.nanmax(v[use]) >= 1.5 * np.nanmin(v[use]):
        return res
    N, ov, vv = np.asarray(n)[use], o[use], v[use]
    X0 = N                                    # o = n . a
    X1 = np.column_stack([N, N * vv[:, None]])  # o = n . (a + b v)
    rss = []
    coef1 = None
    for X in (X0, X1):
        coef, *_ = np.linalg.lstsq(X, ov, rcond=None)
        rss.append(float(np.sum((ov - X @ coef) ** 2)))
        coef1 = coef
    p0, p1 = np.linalg.matrix_rank(X0), np.linalg.matrix_rank(X1)
    dof = len(ov) - p1
    if p1 <= p0 or dof < 2 or rss[1] <= 0:
        return res
    F = ((rss[0] - rss[1]) / (p1 - p0)) / (rss[1] / dof)
    res.speed_p = float(stats.f.sf(F, p1 - p0, dof))
    if res.speed_p <= P_SPEED:
        res.speed_mm_per_100mm_s = float(np.linalg.norm(coef1[2:]) * 100.0)
    return res


def track_speeds(manifest) -> dict:
    """{track id: median head speed (mm/s) while the nozzle was on it} from the manifest's timeline."""
    tl = getattr(manifest, "timeline", None)
    if tl is None:
        return {}
    tr, v = np.asarray(tl.track), np.asarray(tl.v_mm_s, float)
    on = (tr >= 0) & (v > 0)
    out = {}
    for k in np.unique(tr[on]):
        out[int(k)] = float(np.median(v[on & (tr == k)]))
    return out


#: Test lines whose normals' doubled-angle resultant is at least this run (nearly) one way:
#: 1 - 2f for a share f of stations at right angles to the rest, so 0.9 is under 5 % across.
PARALLEL_RESULTANT = 0.9
#: The user hears about the pose's along-track uncertainty when the valid stations' median
#: place sd reaches this (mm): a 0.05 mm shift moves a width by 5 um where it changes by
#: 0.1 mm per mm of track, and a station's time by 2.5 ms on a 20 mm/s line.
ALONG_SD_WARN_MM = 0.05


def heading_resultant(nx, ny, valid) -> float:
    """Length (0..1) of the mean of (cos 2 theta, sin 2 theta) over the valid stations,
    theta the angle of each station's normal (nx, ny): 1 when every test line runs the same
    way (a track's two directions count alike), ~0 on a spiral.

    Why it matters: without markers the picture holds the pose across the lines only. On
    StartStopTestPLA1 (straight parallel lines, resultant ~1) the same photo with 1 LSB of
    noise on 2 % of its pixels moved its stations 0.1-0.24 mm along their lines (median;
    up to 0.5 mm); on the spiral of SpStartStopTest2 they moved 2-5 um (docs/MEASUREMENT.md)."""
    ok = np.asarray(valid, bool) & np.isfinite(nx) & np.isfinite(ny)
    if not ok.any():
        return float("nan")
    th = np.arctan2(np.asarray(ny, float)[ok], np.asarray(nx, float)[ok])
    return float(np.hypot(np.mean(np.cos(2 * th)), np.mean(np.sin(2 * th))))


def along_track_warning(place_sd_mm, nx, ny, valid, method: str) -> str | None:
    """The line `calib measure` prints when the registration places the valid stations
    along their tracks no better than ALONG_SD_WARN_MM (median of ``place_sd_mm``, the
    along-track sd of each station, measure/register.py), with the reason when it is an
    automatic pose of lines that all run one way (:func:`heading_resultant`), else None."""
    ok = np.asarray(valid, bool)
    if place_sd_mm is None or not ok.any():
        return None
    sd = float(np.median(np.asarray(place_sd_mm, float)[ok]))
    if not sd >= ALONG_SD_WARN_MM:
        return None
    head = (f"the pose places the stations along their lines only to +/-{sd:.2f} mm (median sd), and so "
            "the times they were printed; width_sd_mm carries it where the width changes along a line")
    if method.startswith("auto") and heading_resultant(nx, ny, valid) >= PARALLEL_RESULTANT:
        return (head + ": the test lines all run one way and no markers were found, so the picture fixes "
                "the pose across them, and along them only through the few tracks that cross them; print "
                "the pattern's markers, or give --points at the lines' ends")
    return head + "; print the pattern's markers, or give --points spread over the print"
