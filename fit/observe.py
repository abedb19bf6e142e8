"""What the picture does to the width along the track, as the fit predicts it.

The model gives the width the printer laid (one nozzle window, fit/context.py). The
measurement (measure/widths.py) reads each station from the mean of STRIP_LINES profiles
spread over STRIP_MM of the track, each offset's sequence along the track despeckled first:
the mean of its open-close and its close-open with a flat element SPECK_MM long (Serra,
"Image Analysis and Mathematical Morphology", 1982). A feature of the bead shorter than
the element (the tail where a line stops extruding mid-path, a bulge where the head slows
for a moment) is flattened in the widths; a fit that predicts the laid bead there reads
the flat data as information. bench_observe (true parameters, flatbed renders): on
stop-mid-path lines the measured widths lie 9.6 um RMS from the laid prediction at the
stations the kernel moves and 3.0 um from this one (direct drive; Bowden 5.4 -> 2.4 um).
(It was not what misled session 40's back-pressure fits with Klipper's step slowdown:
docs/TRUST.md.)

Flat morphological filters commute with monotone functions. Across the track, the picture
at offset t is a monotone function of the width (a bead of one edge profile, centred on
its path: brighter or darker where it is wider), so despeckling the pixels is despeckling
the width (an increasing function maps open-close to open-close, a decreasing one to
close-open, and their mean is kept either way), and the mean of the lines' profiles reads,
to first order, the mean of their widths:

    w_seen(station i) = mean_j D[w](s_i + f_j STRIP_MM),   f_j = (j + 1/2) / L - 1/2
    D = (open o close + close o open) / 2 along each despeckled run   (mm)

with w the laid width at the L sub-stations of every station (STRIP_MM / L apart; those
of consecutive stations tile the track). The runs are the table's own: stations linked by
``width_corr_prev`` (measure/widths.py links the stations it filtered in one run).
Tables without links (truths, other tools) are predicted as laid.

Only stations within NEAR_MM of a change in the commanded flow or head speed (or where
the extrusion starts or stops) get their sub-stations from the physics; elsewhere the
laid width is smooth on the strip's scale and each sub-station is the quadratic through
its station's and the track neighbours' widths (one physics point per station). On the demo
spiral that leaves 6 % of its stations with sub-stations (stop-mid-path 18 %), and the
widths read move by at most 0.08 um against sub-stations everywhere (tau 0.005-2 s,
pa+nonlinear and pa+backpressure+thermal; tests/test_fit_observe.py).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from measure.widths import SPECK_MM, STRIP_LINES, STRIP_MM

#: Steps of the laid width smaller than this (mm) count as flat when the despeckling looks
#: for the turns it can change (fit/kernels.py _observe_rows); what it then leaves is
#: smaller than them. The integration's own ripple is 1e-8 - 1e-7 mm (a back-pressure
#: spiral: 412 such turns against 49 above 1e-6), and each turn costs filtering.
EPS_MM = 1e-6
#: Stations farther than this (mm of track) from every change in the commanded flow or head
#: speed read their sub-stations interpolated from the station widths. A response to a
#: change of length scale l (tau v) bends by ~dw / l^2 exp(-D / l) at D mm from it, at most
#: 4 e^-2 dw / D^2 over l; at 4 mm the despeckled widths moved <= 0.08 um (module docstring).
NEAR_MM = 4.0


@dataclass(frozen=True)
class Observation:
    """The measurement's along-track kernel for one widths table.

    lines      sub-stations per station (the measurement's lines per strip)
    strip_mm   length of track each station's lines span (mm)
    speck      the despeckling element (sub-stations, odd: SPECK_MM / (strip_mm / lines))
    rows       (T,) sub-station indices of the despeckled runs, concatenated
    starts     (runs + 1,) where each run begins in ``rows``, and T
    pad        end copies continuing each run on both sides (measure/widths.py filters a run
               with 2 ``speck`` copies of its end values)
    track, s_mm (n_stations,) the stations (the table's rows)
    near       (n_stations,) bool: the stations whose sub-stations the physics computes; the
               others' are interpolated (:meth:`focused`). None: all of them
    """

    lines: int
    strip_mm: float
    speck: int
    rows: np.ndarray
    starts: np.ndarray
    pad: int
    track: np.ndarray
    s_mm: np.ndarray
    near: np.ndarray | None = None

    @property
    def n_stations(self) -> int:
        return len(self.track)

    @property
    def offsets_mm(self) -> np.ndarray:
        """(lines,) each sub-station's place along the track from its station (mm)."""
        return ((np.arange(self.lines) + 0.5) / self.lines - 0.5) * self.strip_mm

    def focused(self, near) -> "Observation":
        """This kernel with only the stations ``near`` (n_stations,) bool computed at their
        sub-stations (see :func:`near_changes`)."""
        near = np.asarray(near, dtype=bool)
        if near.shape != (self.n_stations,):
            raise ValueError(f"near has shape {near.shape}, expected ({self.n_stations},)")
        return replace(self, near=near)

    @cached_property
    def _layout(self):
        """(points' station index and offset index; per station: the point of its centre,
        those of its track neighbours' centres STRIP_MM before and after it (-1: none) and
        whether its sub-stations are points of their own)."""
        n, L = self.n_stations, self.lines
        near = np.ones(n, bool) if self.near is None else self.near
        per = np.where(near, L, 1)
        first = np.concatenate([[0], np.cumsum(per)[:-1]])
        centre = first + np.where(near, L // 2, 0)
        pt_station = np.repeat(np.arange(n), per)
        pt_offset = np.where(near[pt_station], np.arange(per.sum()) - first[pt_station], L // 2)
        # track neighbours STRIP_MM apart (in or out of a run: the width is smooth there)
        order = np.lexsort((self.s_mm, self.track))
        tr, ss = np.asarray(self.track)[order], np.asarray(self.s_mm, dtype=float)[order]
        adj = (tr[1:] == tr[:-1]) & (np.abs(np.diff(ss) - self.strip_mm) < 1e-6)
        prev, nxt = np.full(n, -1), np.full(n, -1)
        prev[order[1:][adj]] = centre[order[:-1][adj]]
        nxt[order[:-1][adj]] = centre[order[1:][adj]]
        return pt_station, pt_offset, centre, prev, nxt, near.copy()

    @property
    def n_points(self) -> int:
        """Physics points the kernel reads (sub-stations of the near stations, centres of
        the rest)."""
        return len(self._layout[0])

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(track ids, arc lengths mm) of the physics points, station-major: a near
        station's ``lines`` sub-stations, another's centre."""
        st, off = self._layout[:2]
        return (np.asarray(self.track, dtype=np.int64)[st],
                np.asarray(self.s_mm, dtype=float)[st] + self.offsets_mm[off])

    @property
    def centre_points(self) -> np.ndarray:
        """(n_stations,) index of each station's centre among the physics points."""
        return self._layout[2]

    def apply(self, w_pts: np.ndarray) -> np.ndarray:
        """Widths (n_sets, n_stations) mm as the measurement reads them from the laid widths
        ``w_pts`` (n_sets, n_points) at the physics points (module docstring). A
        sub-station never printed (NaN) reads as its station's centre; a station whose
        centre was never printed stays NaN."""
        from fit.kernels import kernel

        w = np.ascontiguousarray(np.atleast_2d(np.asarray(w_pts, dtype=float)))
        if w.shape[1] != self.n_points:
            raise ValueError(f"{w.shape[1]} widths for {self.n_points} physics points")
        _, _, centre, prev, nxt, near = self._layout
        out = np.empty((len(w), self.n_stations))
        kernel("observe", len(w))(w, self.lines, self.offsets_mm / self.strip_mm, centre, prev, nxt, near,
                                  self.rows, self.starts, self.speck, self.pad, EPS_MM, out)
        return out


def near_changes(manifest, track, s_mm, reach_mm: float | None = None, rtol: float = 1e-3) -> np.ndarray:
    """(n,) bool: the stations (``track``, ``s_mm`` mm) within ``reach_mm`` (None: NEAR_MM) of a timeline
    node on their track where the extruder or head speed changes by more than ``rtol``
    (relative), or the head enters or leaves the track. A station on a track the head never
    travels is near (nothing to say it is smooth)."""
    reach_mm = NEAR_MM if reach_mm is None else float(reach_mm)
    tl = manifest.timeline
    track = np.asarray(track)
    s_mm = np.asarray(s_mm, dtype=float)
    dt = np.maximum(np.diff(tl.t_s), 1e-9)
    trk = np.asarray(tl.track)
    ss = np.nan_to_num(np.asarray(tl.s_mm, dtype=float))
    on = (trk[:-1] == trk[1:]) & (trk[:-1] >= 0)
    ve = np.diff(tl.e_mm) / dt
    vh = np.where(on, np.abs(np.diff(ss)), np.hypot(np.diff(tl.x_mm), np.diff(tl.y_mm))) / dt

    def changed(v):
        return np.abs(v[1:] - v[:-1]) > rtol * np.maximum(np.abs(v[1:]), np.abs(v[:-1])) + 1e-12

    node = np.flatnonzero(changed(ve) | changed(vh) | (on[1:] != on[:-1])) + 1
    node = node[trk[node] >= 0]
    near = np.ones(len(track), bool)
    for tid in np.unique(track):
        m = track == tid
        e = np.sort(ss[node][trk[node] == tid])
        if not np.any(trk == tid):
            continue
        if len(e) == 0:
            near[m] = False
            continue
        i = np.searchsorted(e, s_mm[m])
        d = np.minimum(np.abs(s_mm[m] - e[np.clip(i - 1, 0, len(e) - 1)]),
                       np.abs(e[np.clip(i, 0, len(e) - 1)] - s_mm[m]))
        near[m] = d <= reach_mm
    return near


def observation_of(table) -> Observation | None:
    """The kernel of the measurement that wrote ``table`` (measure.table.WidthTable), or
    None when no station is linked to its predecessor (``width_corr_prev`` 0 everywhere:
    a truth, another tool's widths, a table written before the links)."""
    rho = np.asarray(getattr(table, "width_corr_prev", None) if table is not None else None, dtype=float)
    if rho.ndim != 1 or not np.any(rho > 0):
        return None
    lines = STRIP_LINES
    k = int(round(SPECK_MM / (STRIP_MM / lines)))
    track = np.asarray(table.track)
    s = np.asarray(table.s_mm, dtype=float)
    order = np.lexsort((s, track))
    tr, ss, linked = track[order], s[order], rho[order] > 0
    # a link joins a station to the one STRIP_MM before it on its track (measure/widths.py
    # _despeckled_runs); anything else starts a new run
    join = np.zeros(len(order), bool)
    join[1:] = linked[1:] & (tr[1:] == tr[:-1]) & (np.abs(np.diff(ss) - STRIP_MM) < 1e-6)
    starts = np.flatnonzero(~join)
    rows = [(order[a:b, None] * lines + np.arange(lines)).ravel()
            for a, b in zip(starts, np.append(starts[1:], len(order))) if b - a >= 2]
    if not rows:
        return None
    return Observation(lines=lines, strip_mm=STRIP_MM, speck=k, rows=np.concatenate(rows),
                       starts=np.cumsum([0] + [len(r) for r in rows]), pad=2 * k, track=track.copy(),
                       s_mm=s.copy())

