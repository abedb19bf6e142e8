"""What the fitter fits: measured widths matched to the manifest that printed them.

A :class:`ScanData` is one widths table (``measure``) with its manifest: the stations
become :class:`patterns.manifest.Samples` (positions, normals, commanded width and
height from the manifest's tracks, pass times from its timeline), the simulation
context ``ctx`` is built on them, and the valid samples are ordered along each track
(track, then arc length) for the AR(1) noise model of :mod:`fit.likelihood`.

Stations the measurement flagged ``missing`` (no bead seen: width 0, valid 0) are data
too, not dropped samples: where the nozzle passed over a printed part of a test track
and the scan saw nothing, the bead was narrower than the scan's detection limit. Their
rows are kept in ``missing_idx``; :class:`fit.likelihood.JointProblem` adds one
censored term P(w < w_min | theta) per station (see its docstring). A station is "on a
printed part" when the nozzle passed it on that track: finite pass time t_s and, when
the simulation context is built, ``ctx.printed`` (the deposit window lies inside the
part of the track the timeline covers); elsewhere (a station past the printed end, a
track the timeline never reached) nothing could be seen under any model, so it carries
no information and is not kept.

A :class:`FitData` is one or more ScanData of the same printer (a joint fit).

Checks (each a one-line :class:`calib.errors.UserError`): the table has valid samples;
every track id exists in the manifest; stations lie on their tracks (arc length within
the track, x/y within ``POS_TOL_MM`` of the manifest's polyline), so a widths file paired
with the wrong manifest is caught before any fitting.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.errors import UserError
from measure.table import WidthTable
from patterns.manifest import Manifest, Samples, samples_at

#: Largest allowed distance (mm) between a station's x/y in the widths file and the
#: manifest's track at the same arc length (the registration error is ~0.01 mm; a wrong
#: manifest is off by millimetres).
POS_TOL_MM = 1.0
#: Stations further apart than this along a track (mm) are treated as independent
#: (a long run of invalid samples), besides the AR(1) decay.
MAX_GAP_MM = 5.0


@dataclass
class ScanData:
    """One scan. Arrays over all table rows unless named ``*_valid``/ordered.

    name        label of the scan (file stem), used for per-scan parameters
    manifest    the manifest that printed it
    table       the widths table (all rows)
    samples     stations of all rows (patterns.manifest.Samples)
    ctx         simulation context on ``samples`` (model-specific; None until built)
    order       (n_valid,) row indices of the valid samples, sorted by (track, s_mm)
    y_mm, sd_mm (n_valid,) measured width and its sd at ``order`` (mm)
    gap_mm      (n_valid,) arc length to the previous valid sample of the same track
                (mm; inf at the first sample of each track)
    corr_prev   (n_valid,) correlation of the measurement error of each valid sample with
                the previous valid sample's (the table's ``width_corr_prev`` where that
                sample is the station just before it on the track, else 0; None: all 0)
    missing_idx (n_missing,) row indices of the stations flagged ``missing`` (no bead seen)
                that lie on a printed part of a test track, sorted by (track, s_mm); the
                censored data of the fit (their ``width_sd_mm`` is the scan's detection
                scale, ~1 px = 1/ppm mm)
    """

    name: str
    manifest: Manifest
    table: WidthTable
    samples: Samples
    order: np.ndarray
    y_mm: np.ndarray
    sd_mm: np.ndarray
    gap_mm: np.ndarray
    ctx: object = None
    source: dict = field(default_factory=dict)
    missing_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    corr_prev: np.ndarray | None = None

    @property
    def n_valid(self) -> int:
        return len(self.order)

    @property
    def n_missing(self) -> int:
        return len(self.missing_idx)

    @property
    def track_valid(self) -> np.ndarray:
        return self.table.track[self.order]

    @property
    def s_valid_mm(self) -> np.ndarray:
        return self.table.s_mm[self.order]


@dataclass
class FitData:
    scans: list[ScanData]

    @property
    def n_valid(self) -> int:
        return sum(s.n_valid for s in self.scans)

    @property
    def n_missing(self) -> int:
        return sum(s.n_missing for s in self.scans)

    @classmethod
    def load(cls, pairs, build_ctx: bool = True) -> "FitData":
        """``pairs``: iterable of (widths CSV path, manifest path). Names from the CSV stems
        (made unique)."""
        scans = []
        names: set[str] = set()
        for widths, manifest in pairs:
            table = WidthTable.load(widths)
            man = Manifest.load(manifest)
            name = Path(widths).stem
            base, n = name, 2
            while name in names:
                name, n = f"{base}_{n}", n + 1
            names.add(name)
            sc = scan_from_table(table, man, name, build_ctx=build_ctx)
            sc.source = {"widths": str(widths), "manifest": str(manifest)}
            scans.append(sc)
        if not scans:
            raise UserError("no widths/manifest pair given")
        return cls(scans)


def samples_for_table(table: WidthTable, manifest: Manifest, name: str = "widths") -> Samples:
    """Stations of the table rows, checked against the manifest (see module docstring)."""
    ids = {tr.id: tr for tr in manifest.tracks}
    unknown = sorted(set(np.unique(table.track).tolist()) - set(ids))
    if unknown:
        raise UserError(f"{name}: track id(s) {', '.join(map(str, unknown[:5]))} are not in the "
                        "manifest; pair each widths file with the manifest it was measured against")
    if manifest.timeline is None:
        raise UserError(f"{name}: the manifest has no timeline (.timeline.npz); the fit needs it, "
                        "regenerate the pattern with `calib pattern`")
    for tid in np.unique(table.track):
        tr = ids[int(tid)]
        rows = np.flatnonzero(table.track == tid)
        s = table.s_mm[rows]
        if np.any(s < -0.5) or np.any(s > tr.length_mm + 0.5):
            raise UserError(f"{name}: track {tid} has stations at s up to {s.max():.1f} mm but the "
                            f"manifest's track is {tr.length_mm:.1f} mm long; wrong manifest?")
        pos, _ = tr.at(np.clip(s, 0, tr.length_mm))
        d = np.hypot(pos[:, 0] - table.x_mm[rows], pos[:, 1] - table.y_mm[rows])
        d = d[np.isfinite(d)]
        if d.size and np.median(d) > POS_TOL_MM:
            raise UserError(f"{name}: track {tid} stations are {np.median(d):.1f} mm (median) away "
                            "from the manifest's track; the widths were measured against a "
                            "different manifest")
    return samples_at(manifest, table.track, table.s_mm)


def scan_from_table(table: WidthTable, manifest: Manifest, name: str = "scan",
                    build_ctx: bool = True, ctx=None) -> ScanData:
    """Match a widths table to its manifest; build the simulation context unless given."""
    if len(table) == 0:
        raise UserError(f"{name}: the widths table is empty; run `calib measure` first")
    samples = samples_for_table(table, manifest, name)
    sd = table.fit_sd_mm()
    valid = table.valid & np.isfinite(table.width_mm) & np.isfinite(sd) & (sd > 0) & np.isfinite(samples.t_s)
    if table.valid.any() and (table.valid & ~np.isfinite(table.width_mm)).any():
        raise UserError(f"{name}: {int((table.valid & ~np.isfinite(table.width_mm)).sum())} valid "
                        "sample(s) have NaN width; mark them valid=0 or re-measure")
    if valid.sum() < 3:
        raise UserError(f"{name}: only {int(valid.sum())} valid width sample(s); nothing to fit "
                        "(check the scan's QA overlay)")
    idx = np.flatnonzero(valid)
    idx = idx[np.lexsort((table.s_mm[idx], table.track[idx]))]
    tr, s = table.track[idx], table.s_mm[idx]
    gap = np.concatenate([[np.inf], np.diff(s)])
    new = np.concatenate([[True], tr[1:] != tr[:-1]]) | (gap > MAX_GAP_MM) | (gap <= 0)
    gap = np.where(new, np.inf, gap)
    corr_prev = linked_corr(table, idx, new)
    if ctx is None and build_ctx:
        from fit.context import SimContext
        from fit.observe import observation_of
        ctx = SimContext.build(manifest, samples, observe=observation_of(table))
    # the measurement's blur per station (fit/effects.py ViewBlur), on the context and on
    # the coarsened one that predicts the widths (not on one of physics points, fit/observe.py:
    # the width stages act on the widths as read, at the context's own stations)
    for c in (ctx, getattr(ctx, "physics", None)):
        if c is None or getattr(c, "obs", None) is not None:
            continue
        if hasattr(c, "s_blur_mm"):
            c.s_blur_mm = np.asarray(table.blur_mm, dtype=float)
        if hasattr(c, "s_light_deg"):
            c.s_light_deg = np.asarray(table.light_angle_deg, dtype=float)
    return ScanData(name=name, manifest=manifest, table=table, samples=samples, order=idx,
                    y_mm=table.width_mm[idx].copy(), sd_mm=sd[idx].copy(),
                    gap_mm=gap, ctx=ctx, missing_idx=missing_rows(table, samples, ctx), corr_prev=corr_prev)


def linked_corr(table: WidthTable, idx, new) -> np.ndarray:
    """(len(idx),) the table's ``width_corr_prev`` at the valid rows ``idx`` (sorted by
    track, s), kept only where the previous valid row is the station just before it on the
    same track (``new``: a track start or a gap): one with an invalid station between them
    shares no filtered pixels with it. 0 elsewhere."""
    idx = np.asarray(idx, dtype=np.int64)
    rank = np.empty(len(table), np.int64)
    rank[np.lexsort((table.s_mm, table.track))] = np.arange(len(table))
    adjacent = np.concatenate([[False], np.diff(rank[idx]) == 1]) & ~np.asarray(new, bool)
    return np.where(adjacent, table.width_corr_prev[idx], 0.0)


def missing_rows(table: WidthTable, samples, ctx=None) -> np.ndarray:
    """Rows flagged ``missing`` on a printed part of a test track (module docstring),
    sorted by (track, s_mm): flag "missing", valid 0, finite pass time t_s (s), and
    ``ctx.printed`` when a context is given."""
    miss = (np.asarray(table.flag, dtype=object) == "missing") & ~table.valid
    miss &= np.isfinite(np.asarray(samples.t_s, dtype=float))
    printed = getattr(ctx, "printed", None)
    if printed is not None and len(printed) == len(table):
        miss &= np.asarray(printed, dtype=bool)
    idx = np.flatnonzero(miss)
    return idx[np.lexsort((table.s_mm[idx], table.track[idx]))].astype(np.int64)
