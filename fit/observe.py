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
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from measure.widths import SPECK_MM, STRIP_LINES, STRIP_MM

#: Steps of the laid width smaller than this (mm) count as flat when the despeckling looks
#: for the turns it can change (fit/kernels.py _observe_rows); what it then leaves is
#: smaller than them. The integration's own ripple is 1e-8 - 1e-7 mm (a back-pressure
#: spiral: 412 such turns against 49 above 1e-6), and each turn costs filtering.
EPS_MM = 1e-6


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
    n_stations number of stations (table rows)
    """

    lines: int
    strip_mm: float
    speck: int
    rows: np.ndarray
    starts: np.ndarray
    pad: int
    n_stations: int

    @property
    def offsets_mm(self) -> np.ndarray:
        """(lines,) each sub-station's place along the track from its station (mm)."""
        return ((np.arange(self.lines) + 0.5) / self.lines - 0.5) * self.strip_mm

    def substations(self, track, s_mm) -> tuple[np.ndarray, np.ndarray]:
        """(track ids, arc lengths mm) of the sub-stations, station-major: station i's are
        rows i * lines ... i * lines + lines - 1."""
        track = np.repeat(np.asarray(track, dtype=np.int64), self.lines)
        s = (np.asarray(s_mm, dtype=float)[:, None] + self.offsets_mm[None, :]).ravel()
        return track, s

    def apply(self, w_sub: np.ndarray) -> np.ndarray:
        """Widths (n_sets, n_stations) mm as the measurement reads them from the laid widths
        ``w_sub`` (n_sets, n_stations * lines) at the sub-stations (module docstring). A
        sub-station never printed (NaN) reads as its station's centre; a station whose centre
        was never printed stays NaN."""
        from fit.kernels import kernel

        w = np.ascontiguousarray(np.atleast_2d(np.asarray(w_sub, dtype=float)))
        out = np.empty((len(w), self.n_stations))
        kernel("observe", len(w))(w, self.lines, self.rows, self.starts, self.speck, self.pad, EPS_MM, out)
        return out


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
                       starts=np.cumsum([0] + [len(r) for r in rows]), pad=2 * k, n_stations=len(track))

