"""Everything parameter-independent the physics needs, precomputed once per print.

:class:`SimContext` turns a manifest's timeline and the measurement stations into flat
arrays: per timeline interval k (between nodes k and k+1) the duration dt, the commanded
extruder increment de (mm of filament), the head speed, the layer height and whether the
nozzle is laying a bead on a track; per station the deposit windows.

Deposit geometry (the bead width from flow): while the nozzle is on track T over
interval k it deposits dV_k = Af * out_k (mm^3) uniformly over the arc lengths
[s_k, s_k+1] (a stop, s_k == s_k+1, leaves a blob: a disc, fit/blobs.py). The
cumulative deposited volume V(s) along the track is evaluated at the window boundaries
s_i -+ d/2 (d = nozzle diameter, clipped to the printed part of the track) and

    A_i = (V(s_i + d/2) - V(s_i - d/2)) / L_i,   L_i = clipped window length (mm)
    (inside an interval the deposit follows the outflow, linear between its two nodes)
    w_i = bead_width_mm(A_i, h_i)                   (fit.geometry, rounded rectangle)

which conserves volume exactly. Flow while the nozzle is on no track is dribble.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from calib.errors import UserError
from fit.blobs import BlobMap, blob_map, still_intervals
from fit.geometry import filament_area_mm2
from patterns.manifest import Manifest, Samples, Timeline, sample_points, samples_at

#: Physics timeline coarsening (:func:`coarsen_nodes`): a merged interval lays at most
#: COARSE_DS_MM of bead (one nozzle diameter, the station window; the deposit inside an
#: interval follows the outflow at its nodes) and lasts at most COARSE_DT_S; the commanded extruder velocity
#: and head speed stay within COARSE_RTOL (relative) of the first merged interval; no
#: merging within COARSE_GUARD_S (longer for large jumps) after a change of command,
#: head speed, track or height by more than COARSE_GUARD_RTOL (fast transients of a
#: direct drive, tau ~0.02 s, keep the planner's resolution).
COARSE_DS_MM = 0.4
COARSE_DT_S = 0.05
COARSE_RTOL = 1e-3
COARSE_GUARD_S = 0.05
COARSE_GUARD_RTOL = 0.05
#: Timeline kept after the last deposit any station sees (:func:`last_needed_node`), s.
TRUNCATE_MARGIN_S = 1.0

PROFILE_KEYS = ("filament_diameter_mm", "nozzle_diameter_mm", "nozzle_land_length_mm",
                "bowden_length_mm")


def profile_dict(profile) -> dict:
    """A plain dict from a PrinterProfile, a dict, or None (empty dict)."""
    if profile is None:
        return {}
    if isinstance(profile, dict):
        return dict(profile)
    if hasattr(profile, "to_dict"):
        return dict(profile.to_dict())
    raise UserError(f"printer profile must be a dict or a PrinterProfile, not {type(profile).__name__}")


@dataclass
class SimContext:
    """Precomputed arrays of one print (timeline + stations). Units in the names.

    Intervals (n_int = n_t - 1): dt_s, de_mm, ve_mm_s (= de/dt), v_head_mm_s, h_mm (layer
    height of the bead being laid, 0 off-track), on_track (bool), track (id or -1).
    Stations (n_s): s_track, s_mm, s_x_mm, s_y_mm, s_t_s, s_height_mm, s_heading_rad,
    s_width_nominal_mm; deposit maps perm, lo_pos, lo_frac, hi_pos, hi_frac, win_mm,
    printed (station lies on a printed part of a track).
    """

    t_s: np.ndarray
    e_mm: np.ndarray
    ve_node_mm_s: np.ndarray
    dt_s: np.ndarray
    de_mm: np.ndarray
    ve_mm_s: np.ndarray
    v_head_mm_s: np.ndarray
    h_mm: np.ndarray
    on_track: np.ndarray
    track: np.ndarray
    filament_diameter_mm: float
    nozzle_diameter_mm: float
    filament_area_mm2: float
    profile: dict
    s_track: np.ndarray
    s_mm: np.ndarray
    s_x_mm: np.ndarray
    s_y_mm: np.ndarray
    s_t_s: np.ndarray
    s_height_mm: np.ndarray
    s_heading_rad: np.ndarray
    s_width_nominal_mm: np.ndarray
    perm: np.ndarray
    lo_pos: np.ndarray
    lo_frac: np.ndarray
    hi_pos: np.ndarray
    hi_frac: np.ndarray
    win_mm: np.ndarray
    printed: np.ndarray
    center_xy_mm: tuple[float, float] = (0.0, 0.0)
    firmware_pa_s: float = 0.0
    firmware_smooth_time_s: float = 0.0
    cache: dict = field(default_factory=dict, repr=False)
    #: (n_s,) the edge blur each station's width was measured with (mm; NaN unknown),
    #: from the widths table (fit/data.py scan_from_table); None: not given
    s_blur_mm: np.ndarray | None = None
    #: (n_s,) each station's angle between its flank normal and the scan's light axis
    #: (deg, 0-90; NaN unknown), from the widths table; None: not given
    s_light_deg: np.ndarray | None = None
    #: The same print on the coarsened physics timeline (:func:`coarsen_nodes`), cut
    #: after the last node any station's width depends on (:func:`last_needed_node`),
    #: used by ``Model.predict`` (widths only); None if that saves less than 10 %. The arrays above
    #: keep the planner's full timeline (``simulate``/``flow`` report on it).
    physics: "SimContext | None" = field(default=None, repr=False)
    #: On a coarsened context: index of each node in the full timeline.
    node_index: np.ndarray | None = field(default=None, repr=False)
    #: On :attr:`physics` when the widths came from the measurement: its along-track kernel
    #: (fit/observe.py); the stations are then its physics points (the sub-stations of the
    #: stations near a change of flow or speed, the other stations' centres), and
    #: ``Model.predict`` reads the widths through it. None: the stations are the table's,
    #: widths as laid.
    obs: "object | None" = field(default=None, repr=False)
    #: Where the head stands still on a track and the stations its blob can reach
    #: (fit/blobs.py); their volume is laid as a disc, not into the deposit windows.
    blobs: "BlobMap | None" = field(default=None, repr=False)

    @property
    def n_t(self) -> int:
        return len(self.t_s)

    @property
    def n_samples(self) -> int:
        return len(self.s_mm)

    @property
    def station_printed(self) -> np.ndarray:
        """(n_stations,) ``printed`` per station of the widths table: on a context of
        the kernel's physics points (:attr:`obs`), its station's centre's."""
        if self.obs is None:
            return self.printed
        return np.asarray(self.printed)[self.obs.centre_points]

    @property
    def deposit_map(self) -> tuple:
        """The deposit maps as the kernels take them (fit/kernels.py ``_deposit_row``):
        (perm, lo_pos, lo_frac, lo_int, hi_pos, hi_frac, hi_int, inv_win) with lo_int =
        perm[lo_pos], hi_int = perm[hi_pos] (timeline interval of each window edge) and
        inv_win = 1 / win_mm (0 where the window is empty), built once."""
        dm = self.cache.get("deposit_map")
        if dm is None:
            i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)      # noqa: E731
            f64 = lambda a: np.ascontiguousarray(a, dtype=float)          # noqa: E731
            perm = i64(self.perm)
            if len(perm):
                lo_int, hi_int = perm[self.lo_pos], perm[self.hi_pos]
            else:
                lo_int = hi_int = np.zeros(len(self.lo_pos), np.int64)
            win = f64(self.win_mm)
            inv = np.where(win > 1e-9, 1.0 / np.where(win > 1e-9, win, 1.0), 0.0)
            dm = (perm, i64(self.lo_pos), f64(self.lo_frac), i64(lo_int), i64(self.hi_pos),
                  f64(self.hi_frac), i64(hi_int), inv)
            self.cache["deposit_map"] = dm
        return dm

    @classmethod
    def build(cls, manifest, samples=None, profile=None, coarsen: bool = True,
              observe=None) -> "SimContext":
        """Precompute from a :class:`Manifest` (with timeline) and stations.

        ``samples``: a :class:`patterns.manifest.Samples`, a :class:`measure.table.WidthTable`
        (its track, s_mm), or None for ``sample_points(manifest)``. ``profile``: a
        PrinterProfile or dict with filament_diameter_mm and nozzle_diameter_mm (default:
        ``manifest.printer``). ``coarsen``: also build :attr:`physics`, the context on the
        coarsened timeline that ``predict`` integrates (see :func:`coarsen_nodes`).
        ``observe``: the measurement's kernel (fit/observe.py :class:`Observation`, one per
        station of ``samples``): :attr:`physics` is then built on its physics points (always,
        on the whole timeline where coarsening would not pay; sub-stations only within
        fit.observe.NEAR_MM of a change of flow or speed, :func:`fit.observe.near_changes`)
        and ``predict`` reads through it.
        """
        if isinstance(manifest, Timeline):
            manifest = Manifest(printer={}, pattern={}, tracks=[], timeline=manifest)
        if not isinstance(manifest, Manifest):
            raise UserError(f"expected a manifest, got {type(manifest).__name__}")
        tl = manifest.timeline
        if tl is None or len(tl) < 2:
            raise UserError("the manifest has no timeline; plan the G-code first (`calib plan`)")
        prof = profile_dict(manifest.printer)
        prof.update(profile_dict(profile))
        try:
            D = float(prof.get("filament_diameter_mm", 1.75))
            d = float(prof.get("nozzle_diameter_mm", 0.4))
        except (TypeError, ValueError):
            raise UserError("printer profile: filament_diameter_mm and nozzle_diameter_mm must be numbers") from None
        if not (D > 0 and d > 0):
            raise UserError("printer profile: filament_diameter_mm and nozzle_diameter_mm must be > 0")

        t = tl.t_s
        dt_raw = np.diff(t)
        if np.any(dt_raw < 0):
            raise UserError("timeline time t_s goes backwards; re-plan the G-code")
        # A zero-length interval carrying an E step is an instantaneous move: a tiny dt
        # keeps de exact and lets the exact/implicit step absorb it into P.
        dt = np.maximum(dt_raw, 1e-9)
        de = np.diff(tl.e_mm)
        trk = tl.track
        on = (trk[:-1] == trk[1:]) & (trk[:-1] >= 0)
        ds_xy = np.hypot(np.diff(tl.x_mm), np.diff(tl.y_mm))
        with np.errstate(invalid="ignore"):
            ds_tr = np.where(on, np.abs(np.diff(np.nan_to_num(tl.s_mm))), ds_xy)
        v_head = ds_tr / dt
        track_of = {tr.id: tr for tr in manifest.tracks}
        h_int = np.zeros(len(dt))
        s_mid = 0.5 * (np.nan_to_num(tl.s_mm[:-1]) + np.nan_to_num(tl.s_mm[1:]))
        for tid in np.unique(trk[:-1][on]):
            m = on & (trk[:-1] == tid)
            tr = track_of.get(int(tid))
            h_int[m] = tr.interp("height_mm", s_mid[m]) if tr is not None else 0.2

        if samples is None:
            if not manifest.tracks:
                raise UserError("no tracks to sample: pass samples or a manifest with tracks")
            samples = sample_points(manifest)
        st = _stations(manifest, samples, track_of)

        # what leaves the nozzle while the head stands still on a track is a blob: a disc
        # (fit/blobs.py), not bead in the deposit windows
        still = still_intervals(on, ds_tr)
        blobs = blob_map(still, trk[:-1], tl.s_mm, h_int, st["track"], st["s_mm"])
        perm, lo_pos, lo_frac, hi_pos, hi_frac, win, printed = _deposit_maps(
            trk, tl.s_mm, on & ~still, st["track"], st["s_mm"], d)

        pat = manifest.pattern or {}
        pparams = pat.get("params", {}) if isinstance(pat.get("params", {}), dict) else {}

        def _pget(*keys):
            for k in keys:
                for src in (pparams, pat):
                    if k in src:
                        try:
                            return float(src[k])
                        except (TypeError, ValueError):
                            pass
            return 0.0

        if len(st["x"]):
            center = (float(0.5 * (st["x"].min() + st["x"].max())),
                      float(0.5 * (st["y"].min() + st["y"].max())))
        else:
            center = (0.0, 0.0)
        ctx = cls(
            t_s=t, e_mm=tl.e_mm, ve_node_mm_s=tl.ve_mm_s, dt_s=dt, de_mm=de, ve_mm_s=de / dt,
            v_head_mm_s=v_head, h_mm=np.where(on, h_int, 0.0), on_track=on,
            track=np.where(on, trk[:-1], -1),
            filament_diameter_mm=D, nozzle_diameter_mm=d, filament_area_mm2=filament_area_mm2(D),
            profile=prof,
            s_track=st["track"], s_mm=st["s_mm"], s_x_mm=st["x"], s_y_mm=st["y"], s_t_s=st["t"],
            s_height_mm=st["h"], s_heading_rad=st["heading"], s_width_nominal_mm=st["w"],
            perm=perm, lo_pos=lo_pos, lo_frac=lo_frac, hi_pos=hi_pos, hi_frac=hi_frac,
            win_mm=win, printed=printed, center_xy_mm=center,
            firmware_pa_s=_pget("firmware_pa_s", "pressure_advance_s", "pa_s"),
            firmware_smooth_time_s=_pget("firmware_smooth_time_s", "pressure_advance_smooth_time_s",
                                         "smooth_time_s"),
            blobs=blobs,
        )
        keep = None
        if coarsen:
            keep = coarsen_nodes(ctx, trk)
            keep = keep[:np.searchsorted(keep, last_needed_node(ctx)) + 1]
            if len(keep) >= 0.9 * len(t):
                keep = None
        if keep is not None or observe is not None:
            sub = manifest if keep is None else replace(manifest, timeline=tl.slice(keep))
            phys_samples = samples
            if observe is not None:
                if observe.n_stations != len(st["track"]):
                    raise ValueError(f"observation for {observe.n_stations} stations, context has {len(st['track'])}")
                from fit.observe import near_changes

                observe = observe.focused(near_changes(manifest, st["track"], st["s_mm"]))
                trk_sub, s_sub = observe.points()
                # the measurement's lines stop at the track's ends (measure/widths.py)
                length = {tid: tr.length_mm for tid, tr in track_of.items()}
                s_sub = np.clip(s_sub, 0.0, np.array([length.get(int(k), np.inf) for k in trk_sub]))
                phys_samples = samples_at(manifest, trk_sub, s_sub)
            ctx.physics = cls.build(sub, phys_samples, profile, coarsen=False)
            ctx.physics.node_index = np.arange(len(t)) if keep is None else keep
            ctx.physics.obs = observe
        return ctx


def last_needed_node(ctx: "SimContext", margin_s: float = TRUNCATE_MARGIN_S) -> int:
    """Index of the last timeline node the predicted widths can depend on.

    The width at a station is the volume deposited inside its window, and the nozzle
    state is causal, so nothing printed after the last interval that deposits into any
    station's window (``perm[hi_pos]``) changes a predicted width: a pattern that prints
    its test tracks first and its fiducials, ruler and labels afterwards needs only the
    first part of its timeline (the spiral-step pattern: ~1/6). ``margin_s`` more of
    timeline is kept for command transforms that look ahead (firmware PA smoothing is a
    centred window of smooth_time ~0.04 s). The last node if no station is printed.
    """
    n_last = len(ctx.t_s) - 1
    if not np.any(ctx.printed):
        return n_last
    k = int(np.max(ctx.perm[ctx.hi_pos[ctx.printed]])) + 1
    k = int(np.searchsorted(ctx.t_s, ctx.t_s[k] + margin_s, side="right"))
    return min(k, n_last)


@njit(cache=True)
def _coarsen_kernel(dt, ve, vnode, vh, ds, h, on, trk_int, trk_node, ds_max, dt_max, rtol, guard_s, guard_rtol):
    n = dt.shape[0]
    keep = np.empty(n + 1, np.int64)
    keep[0] = 0
    m = 1
    g0 = 0
    tsum = dt[0]
    dsum = ds[0]
    until = 0.0            # no merging before this time (after a change)
    t = dt[0]
    for k in range(1, n):
        changed = (on[k] != on[k - 1] or trk_int[k] != trk_int[k - 1] or h[k] != h[k - 1]
                   or abs(ve[k] - ve[k - 1]) > guard_rtol * max(abs(ve[k - 1]), 1e-6)
                   or (on[k] and abs(vh[k] - vh[k - 1]) > guard_rtol * max(abs(vh[k - 1]), 1e-6)))
        if changed:
            # transients after a jump of relative size R last ~ tau ln(R): guard longer
            r = abs(ve[k] - ve[k - 1]) / max(abs(ve[k]), 0.1 * abs(ve[k - 1]), 1e-6)
            if on[k]:
                r = max(r, abs(vh[k] - vh[k - 1]) / max(abs(vh[k]), 0.1 * abs(vh[k - 1]), 1e-6))
            until = max(until, t + guard_s * (1.0 + math.log1p(min(r, 1e3))))
        ok = (not changed) and t >= until and on[k] == on[g0] and trk_int[k] == trk_int[g0] \
            and h[k] == h[g0] and tsum + dt[k] <= dt_max \
            and abs(ve[k] - ve[g0]) <= rtol * max(abs(ve[g0]), 1e-6) \
            and abs(vnode[k + 1] - vnode[g0]) <= rtol * max(abs(vnode[g0]), 1e-6)
        if ok and on[g0]:
            ok = dsum + ds[k] <= ds_max and abs(vh[k] - vh[g0]) <= rtol * max(abs(vh[g0]), 1e-6)
        if ok and not on[g0]:
            # merged travel must stay off-track: its end nodes on one track would make it a
            # track interval
            ok = not (trk_node[g0] == trk_node[k + 1] and trk_node[g0] >= 0)
        t += dt[k]
        if ok:
            tsum += dt[k]
            dsum += ds[k]
        else:
            keep[m] = k
            m += 1
            g0 = k
            tsum = dt[k]
            dsum = ds[k]
    keep[m] = n
    m += 1
    return keep[:m].copy()


def coarsen_nodes(ctx: "SimContext", trk_node, ds_max_mm: float = COARSE_DS_MM,
                  dt_max_s: float = COARSE_DT_S, rtol: float = COARSE_RTOL,
                  guard_s: float = COARSE_GUARD_S, guard_rtol: float = COARSE_GUARD_RTOL) -> np.ndarray:
    """Indices of the timeline nodes kept on the physics timeline (first and last always).

    Consecutive intervals merge while nothing the physics needs changes: same track (or
    both off-track, and the merged travel does not start and end on one track), same layer
    height, commanded extruder velocity (per interval, and the planner's velocity at the
    nodes, which firmware PA differentiates) and (on a track) head speed within ``rtol`` of the
    first merged interval, at most ``ds_max_mm`` of bead and ``dt_max_s`` per merged
    interval, and not within guard_s * (1 + ln(1 + R)) after a change of relative size R
    (> ``guard_rtol``) of command or head speed (or of track / height): the transient of a
    fast extruder (tau ~0.02 s) after a jump by R decays like R exp(-t/tau). The e_mm increments add, so the
    commanded volume is conserved exactly; the deposit maps keep a spatial resolution of
    ``ds_max_mm`` (the planner's own bound). The exact linear step is exact on the merged
    intervals; the nonlinear theta step is second order in dt/tau_loc.

    On the realdata StartStopTestPLA1 (a 39-min third-party print, 482,007 intervals kept
    as 104,948), against the whole timeline under 32 prior draws (2026-11-28): `pa` and
    `pa+thermal` 99 % of stations within 0.05 um, `pa+nonlinear` / `+backpressure` /
    `+kalico_tanh` within 1.1-1.8 um; 5-30 of its 11,427 stations differ by 0.05-0.56 mm
    in some draw, on or beside the print's pre-pressure draws (1 mm at 1 mm/s, 15-51x
    over-extruded: nominal widths 12-25 mm), where the flow swings fastest. Merging further
    where no station is near (10 s before the next measured track, 1 s merges, no guard)
    kept 72,548 intervals (1.45x faster) but widened the nonlinear forms' 99th percentile
    to 1.5-2.0 um; not kept.
    """
    dt = np.ascontiguousarray(ctx.dt_s, dtype=float)
    ds = ctx.v_head_mm_s * dt
    return _coarsen_kernel(dt, np.ascontiguousarray(ctx.ve_mm_s, float),
                           np.ascontiguousarray(ctx.ve_node_mm_s, float),
                           np.ascontiguousarray(ctx.v_head_mm_s, float), ds,
                           np.ascontiguousarray(ctx.h_mm, float), np.ascontiguousarray(ctx.on_track),
                           np.ascontiguousarray(ctx.track, np.int64),
                           np.ascontiguousarray(trk_node, np.int64), float(ds_max_mm), float(dt_max_s),
                           float(rtol), float(guard_s), float(guard_rtol))


def _stations(manifest: Manifest, samples, track_of: dict) -> dict:
    """Station arrays from Samples or a WidthTable (heights/headings from the tracks)."""
    trk = np.asarray(samples.track, dtype=np.int64)
    s = np.asarray(samples.s_mm, dtype=float)
    n = len(trk)
    x = np.asarray(getattr(samples, "x_mm", np.zeros(n)), dtype=float)
    y = np.asarray(getattr(samples, "y_mm", np.zeros(n)), dtype=float)
    tt = np.asarray(getattr(samples, "t_s", np.full(n, np.nan)), dtype=float)
    h = np.full(n, np.nan)
    w = np.full(n, np.nan)
    heading = np.zeros(n)
    if isinstance(samples, Samples):
        h = np.asarray(samples.height_mm, dtype=float).copy()
        w = np.asarray(samples.width_nominal_mm, dtype=float).copy()
        heading = np.arctan2(-np.asarray(samples.nx, float), np.asarray(samples.ny, float))
    else:
        for tid in np.unique(trk):
            m = trk == tid
            tr = track_of.get(int(tid))
            if tr is None:
                continue
            h[m] = tr.interp("height_mm", s[m])
            w[m] = tr.interp("width_mm", s[m])
            _, tan = tr.at(s[m])
            heading[m] = np.arctan2(tan[:, 1], tan[:, 0])
    missing = ~np.isfinite(h)
    if missing.any():
        if manifest.tracks:
            raise UserError(f"{int(missing.sum())} station(s) name track ids not in the manifest "
                            f"(first: track {int(trk[missing][0])}); use the manifest the widths were measured on")
        h[missing] = 0.2
    return dict(track=trk, s_mm=s, x=x, y=y, t=tt, h=h, w=w, heading=heading)


def _deposit_maps(trk, s_tl, on, st_track, st_s, d_mm):
    """Index maps so that V(s_b) = C[pos] - (1 - frac) * dV[perm[pos]] for every boundary.

    perm lists the on-track intervals grouped by track, in time order; C is the cumulative
    sum of the deposited volume along perm (restarting per track is unnecessary: only
    differences between boundaries of one track are used).
    """
    idx = np.flatnonzero(on)
    t_of = trk[:-1][idx]
    order = np.argsort(t_of, kind="stable")
    perm = idx[order]
    ptrack = trk[:-1][perm]
    sa = np.nan_to_num(s_tl[:-1][perm])
    sb = np.nan_to_num(s_tl[1:][perm])
    n = len(st_s)
    lo_pos = np.zeros(n, np.int64)
    hi_pos = np.zeros(n, np.int64)
    lo_frac = np.zeros(n)
    hi_frac = np.zeros(n)
    win = np.zeros(n)
    printed = np.zeros(n, bool)
    if len(perm) == 0:
        return perm, lo_pos, lo_frac, hi_pos, hi_frac, win, printed
    starts = np.searchsorted(ptrack, np.unique(ptrack), side="left")
    ends = np.searchsorted(ptrack, np.unique(ptrack), side="right")
    for tid, a, b in zip(np.unique(ptrack), starts, ends):
        m = st_track == tid
        if not m.any():
            continue
        s_lo_tr, s_hi_tr = float(sa[a:b].min()), float(sb[a:b].max())
        # s along one track must advance with time for V(s) to be a function of s.
        sb_run = np.maximum.accumulate(sb[a:b])
        ss = st_s[m]
        inside = (ss >= s_lo_tr - 1e-9) & (ss <= s_hi_tr + 1e-9)
        lo = np.clip(ss - 0.5 * d_mm, s_lo_tr, s_hi_tr)
        hi = np.clip(ss + 0.5 * d_mm, s_lo_tr, s_hi_tr)
        win[m] = hi - lo
        printed[m] = inside & (hi - lo > 1e-9)
        for bnd, pos_out, frac_out in ((lo, lo_pos, lo_frac), (hi, hi_pos, hi_frac)):
            j = np.clip(np.searchsorted(sb_run, bnd, side="left"), 0, b - a - 1)
            s0 = sa[a:b][j]
            L = sb[a:b][j] - s0
            frac = np.where(L > 1e-12, (bnd - s0) / np.where(L > 1e-12, L, 1.0), 1.0)
            frac = np.clip(frac, 0.0, 1.0)
            # Window edges at the ends of the printed part take in everything deposited
            # there (a dwell's blob is not: it is a disc, fit/blobs.py).
            at_start = bnd <= s_lo_tr + 1e-12
            at_end = bnd >= s_hi_tr - 1e-12
            j = np.where(at_start, 0, np.where(at_end, b - a - 1, j))
            frac = np.where(at_start, 0.0, np.where(at_end, 1.0, frac))
            pos_out[m] = a + j
            frac_out[m] = frac
    return perm, lo_pos, lo_frac, hi_pos, hi_frac, win, printed
