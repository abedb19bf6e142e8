"""Blobs: what a head standing still on a track leaves, as the footprint it makes.

A dwell on a track (a stop mid path, a G4, an unretract before the head moves, the
ooze while it waits) puts the volume V that leaves the nozzle meanwhile at one point of
the track. Squeezed between the nozzle face and the plate (the gap is the layer height
h), the plastic spreads as a disc (squeeze flow; our assumption, no seed gives the form):

    r = sqrt(V / (pi h))                         (mm; V mm^3, h mm)

and the bead at arc offset u (mm) from the blob's centre is at least the disc's chord wide:

    w(u) = max(w_bead(u), 2 sqrt(r^2 - u^2))     for |u| < r

where w_bead is the width the flow lays while the head moves (fit/context.py). Before
this the blob's volume went into the one-nozzle window of the station it stood on (A =
V / d): the stop-mid-path print's 2.45 mm^3 dwell on the Bowden truth read 35 mm wide at
one station and the renderer drew a 35 mm disc over the neighbouring lines, where a real
one of that volume is ~4 mm across; the start-stop rings' 0.1-0.2 mm^3 restore blobs read
2-4 mm at one station, ~1 mm as discs.

The virtual printer's truth and picture carry the disc; the fit predicts the bead under it
(fit/model.py ``Model.predict``) and leaves its stations to the measurement's flags
(measure/widths.py ``_at_dwell``, ``_at_end``, ``steep``).

Only the stations of the blob's own track are widened (a disc reaching a neighbouring
track is rare on our patterns, whose lines are 5-8 mm apart, and the measurement flags
such a station as ``blob`` or ``neighbour`` either way).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Stations farther than this from a blob's centre (mm of track) are never widened by it:
#: a disc of this radius at h 0.2 mm holds 10 mm^3, ten times the largest dwell of our
#: patterns on a Bowden printer.
REACH_MM = 4.0


@dataclass(frozen=True)
class BlobMap:
    """Where a print's blobs are, parameter-independent (built once per SimContext).

    interval_blob  (n_int,) int64: blob index of each timeline interval, -1 where the head
                   moves or is on no track
    track          (n_blobs,) track id of each blob
    s_mm           (n_blobs,) arc length of its centre on that track (mm)
    h_mm           (n_blobs,) gap under the nozzle there (the layer height, mm)
    station        (m,) int64 stations within REACH_MM of a blob on its track
    blob           (m,) int64 the blob each of them is near
    u_mm           (m,) their arc offset from the blob's centre (mm)
    """

    interval_blob: np.ndarray
    track: np.ndarray
    s_mm: np.ndarray
    h_mm: np.ndarray
    station: np.ndarray
    blob: np.ndarray
    u_mm: np.ndarray

    @property
    def n_blobs(self) -> int:
        return len(self.track)


def still_intervals(on_track: np.ndarray, ds_mm: np.ndarray) -> np.ndarray:
    """(n_int,) bool: intervals on a track over which the head does not advance (mm)."""
    return np.asarray(on_track, bool) & (np.abs(np.asarray(ds_mm, float)) < 1e-6)


def blob_map(still: np.ndarray, interval_track: np.ndarray, s_node_mm: np.ndarray, h_mm: np.ndarray,
             station_track: np.ndarray, station_s_mm: np.ndarray, reach_mm: float = REACH_MM) -> BlobMap:
    """Group consecutive still intervals of one track into blobs and find the stations
    each can reach. ``s_node_mm``: arc length at the timeline nodes (n_int + 1)."""
    still = np.asarray(still, bool)
    n = len(still)
    interval_blob = np.full(n, -1, np.int64)
    idx = np.flatnonzero(still)
    if len(idx) == 0:
        e = np.zeros(0, np.int64)
        return BlobMap(interval_blob, e, np.zeros(0), np.zeros(0), e, e, np.zeros(0))
    trk = np.asarray(interval_track)[idx]
    new = np.r_[True, (np.diff(idx) > 1) | (trk[1:] != trk[:-1])]
    bid = np.cumsum(new) - 1
    interval_blob[idx] = bid
    first = idx[new]
    b_track = trk[new].astype(np.int64)
    b_s = np.nan_to_num(np.asarray(s_node_mm, float)[first])
    b_h = np.maximum(np.asarray(h_mm, float)[first], 0.02)
    st_track = np.asarray(station_track)
    st_s = np.asarray(station_s_mm, float)
    stations, blobs, us = [], [], []
    for b, (t, s0) in enumerate(zip(b_track, b_s)):
        k = np.flatnonzero((st_track == t) & (np.abs(st_s - s0) <= reach_mm))
        stations.append(k)
        blobs.append(np.full(len(k), b, np.int64))
        us.append(st_s[k] - s0)
    return BlobMap(interval_blob, b_track, b_s, b_h, np.concatenate(stations).astype(np.int64),
                   np.concatenate(blobs), np.concatenate(us))


def blob_volumes_mm3(out_mm: np.ndarray, bm: BlobMap, filament_area_mm2: float) -> np.ndarray:
    """(n_sets, n_blobs) volume out of the nozzle over each blob's intervals (mm^3) from
    the per-interval filament outflow ``out_mm`` (n_sets, n_int) mm."""
    out = np.atleast_2d(out_mm)
    vol = np.zeros((out.shape[0], bm.n_blobs))
    m = bm.interval_blob >= 0
    if bm.n_blobs and m.any():
        for i in range(out.shape[0]):
            vol[i] = np.bincount(bm.interval_blob[m], weights=out[i, m], minlength=bm.n_blobs)
    return vol * filament_area_mm2


def disc_radius_mm(volume_mm3, h_mm):
    """Radius of the disc of height ``h_mm`` that holds ``volume_mm3``: sqrt(V / (pi h))."""
    return np.sqrt(np.maximum(volume_mm3, 0.0) / (np.pi * h_mm))


def with_footprints(w_mm: np.ndarray, volume_mm3: np.ndarray, bm: BlobMap) -> np.ndarray:
    """Widths (n_sets, n_s) mm with every blob's disc chord where it is wider than the bead
    (module docstring); stations never printed (NaN) stay so."""
    if not bm.n_blobs or not len(bm.station):
        return w_mm
    r = disc_radius_mm(volume_mm3, bm.h_mm[None, :])[:, bm.blob]            # (n_sets, m)
    chord = 2.0 * np.sqrt(np.maximum(r * r - bm.u_mm[None, :] ** 2, 0.0))
    w = np.array(w_mm, dtype=float, copy=True)
    cols = w[:, bm.station]
    # several blobs can reach one station: np.maximum.at takes the widest of them
    np.maximum.at(w, (slice(None), bm.station), np.where(np.isnan(cols), np.nan, chord))
    return w


def under_blobs(bm: BlobMap | None, volume_mm3: np.ndarray, n_stations: int, margin_mm: float = 0.5) -> np.ndarray:
    """(n_stations,) bool: stations within a blob's disc radius + ``margin_mm`` of its
    centre on its track (``volume_mm3``: (n_blobs,) one parameter set), where a picture
    shows the blob, not the bead (a measurement flags them `blob` or `steep`)."""
    out = np.zeros(n_stations, bool)
    if bm is None or not bm.n_blobs or not len(bm.station):
        return out
    r = disc_radius_mm(np.asarray(volume_mm3, float).reshape(-1)[bm.blob], bm.h_mm[bm.blob])
    near = (r > 0) & (np.abs(bm.u_mm) <= r + margin_mm)
    out[bm.station[near]] = True
    return out
