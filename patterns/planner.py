"""Motion planner: parsed moves -> the firmware's timing, sampled into a Timeline.

Each move follows a trapezoidal velocity profile (accelerate at a, cruise at v_c,
decelerate at a). Speeds at the joints come from a look-ahead over the whole queue
(backward pass: v_start^2 <= v_end^2 + 2 a L; forward pass: v_end^2 <= v_start^2 + 2 a L),
capped by the cornering model of the profile's firmware:

* Klipper (klippy/toolhead.py ``Move.calc_junction``): with theta the angle between the
  reversed previous direction and the new one,
      jd = scv^2 (sqrt(2) - 1) / max_accel,
      v_j^2 = a jd sin(theta/2) / (1 - sin(theta/2)),
  also capped by the "centripetal" limits 2 L a * tan(theta/2) / 4 of both moves.
  A 90 degree corner gives v_j = scv exactly.
* Marlin (planner.cpp, junction deviation): the same v_j^2 formula with the profile's
  ``junction_deviation_mm``.
* RRF: the instantaneous speed change ("jerk", M566) limits |v u1 - v u2| <= jerk, so
  v_j = jerk / |u1 - u2| (vector approximation of RRF's per-axis jerk).

Extruder-only moves (retract, prime) use the extruder's own limits (max_e_velocity,
max_e_accel) and stop at both ends, as in Klipper and Marlin. Marlin and RRF also cap
XY+E moves so that the E axis keeps within its velocity/acceleration limits, Klipper only
the XY moves that retract (a wipe). The extruder limits junctions too: a change of
extrusion rate between two moves is a corner for it (Klipper's
``instantaneous_corner_velocity``, RRF's and classic Marlin's E jerk, current Marlin's
junction deviation over XYZE: ``_extruder_junction_v2``). Z moves are capped by
max_z_velocity / max_z_accel. Not modelled: Klipper's
``minimum_cruise_ratio`` smoothing, Marlin's small-segment arc limit, input shaping.

The Timeline (patterns/manifest.py) is sampled every <= 0.25 mm of head travel and
<= 5 ms, uniformly in time inside each move, and includes every move boundary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from calib.errors import UserError

from patterns.gcode_parser import Moves, ParseResult, auto_tracks, parse_gcode
from patterns.manifest import Timeline
from patterns.profile import PrinterProfile, load_profile

DS_MAX_MM = 0.25
DT_MAX_S = 0.005
_EPS_MM = 1e-9


@dataclass
class MovePlan:
    """Per-move plan, arrays (M,) aligned with ``Moves``.

    length_mm     path length used for kinematics (XYZ; |de| for E-only moves; 0 dwell)
    accel_mm_s2   acceleration along that path (mm/s^2)
    v_start_mm_s, v_cruise_mm_s, v_end_mm_s   trapezoid speeds along the path (mm/s)
    t_accel_s, t_cruise_s, t_decel_s          phase durations (s); a dwell is all cruise
    t_start_s     start time of the move (s)
    kind          0 XYZ(+E) motion, 1 E-only, 2 dwell
    """

    length_mm: np.ndarray
    accel_mm_s2: np.ndarray
    v_start_mm_s: np.ndarray
    v_cruise_mm_s: np.ndarray
    v_end_mm_s: np.ndarray
    t_accel_s: np.ndarray
    t_cruise_s: np.ndarray
    t_decel_s: np.ndarray
    t_start_s: np.ndarray
    kind: np.ndarray

    @property
    def duration_s(self) -> np.ndarray:
        return self.t_accel_s + self.t_cruise_s + self.t_decel_s

    @property
    def total_time_s(self) -> float:
        d = self.duration_s
        return float(self.t_start_s[-1] + d[-1]) if len(d) else 0.0



#: A timeline longer than this (samples every <= 5 ms: ~70 h of printing) is a corrupt program.
MAX_TIMELINE_SAMPLES = 5.0e7

def plan_moves(moves: Moves, profile: PrinterProfile) -> MovePlan:
    """Trapezoids with whole-queue look-ahead (see module docstring for the equations)."""
    p = load_profile(profile)
    n = len(moves)
    dx = moves.x_mm - moves.x0_mm
    dy = moves.y_mm - moves.y0_mm
    dz = moves.z_mm - moves.z0_mm
    de = moves.de_mm
    L3 = np.sqrt(dx * dx + dy * dy + dz * dz)
    dwell = moves.dwell_s > 0
    motion = (L3 > _EPS_MM) & ~dwell
    eonly = ~motion & ~dwell & (np.abs(de) > 0)
    kind = np.where(motion, 0, np.where(eonly, 1, 2)).astype(np.int64)
    # zero-length, zero-E rows (should not come from the parser) behave as 0 s dwells
    length = np.where(motion, L3, np.where(eonly, np.abs(de), 0.0))

    a_base = np.where(np.isfinite(moves.accel_mm_s2), moves.accel_mm_s2, p.max_accel_mm_s2)
    a_base = np.minimum(a_base, p.max_accel_mm_s2) if p.firmware != "klipper" else a_base
    vmax = np.minimum(moves.feed_mm_s, p.max_velocity_mm_s)
    acc = a_base.copy()
    safe_L = np.where(L3 > 0, L3, 1.0)
    zr = np.abs(dz) / safe_L
    with np.errstate(divide="ignore", invalid="ignore"):
        vmax = np.where(motion & (zr > 0), np.minimum(vmax, p.max_z_velocity_mm_s / zr), vmax)
        acc = np.where(motion & (zr > 0), np.minimum(acc, p.max_z_accel_mm_s2 / zr), acc)
        er = np.abs(de) / safe_L
        # Marlin and RRF cap every XY+E move; Klipper only the retracting ones (a wipe while
        # retracting: klippy/kinematics/extruder.py check_move, "axis_r < 0")
        capped = motion & (er > 0) & ((de < 0) if p.firmware == "klipper" else True)
        vmax = np.where(capped, np.minimum(vmax, p.max_e_velocity_mm_s / er), vmax)
        acc = np.where(capped, np.minimum(acc, p.max_e_accel_mm_s2 / er), acc)
    vmax = np.where(eonly, np.minimum(moves.feed_mm_s, p.max_e_velocity_mm_s), vmax)
    acc = np.where(eonly, p.max_e_accel_mm_s2, acc)
    vmax = np.where(dwell | ~(motion | eonly), 0.0, vmax)

    # junction limits (start of move i, joining move i-1)
    jmax2 = np.zeros(n)
    if n > 1:
        both = motion[1:] & motion[:-1]
        if p.firmware == "marlin" and p.junction_deviation_mm is not None and p.junction_deviation_with_e:
            # Marlin 2.1 planner.cpp: a block that moves E takes its unit vector over X, Y,
            # Z and E together, so a change of extrusion rate is a corner
            norm = np.where(de != 0, np.sqrt(L3 * L3 + de * de), safe_L)
            ux, uy, uz, ue = dx / norm, dy / norm, dz / norm, de / norm
            dot = ux[1:] * ux[:-1] + uy[1:] * uy[:-1] + uz[1:] * uz[:-1] + ue[1:] * ue[:-1]
        else:
            ux, uy, uz = dx / safe_L, dy / safe_L, dz / safe_L
            dot = ux[1:] * ux[:-1] + uy[1:] * uy[:-1] + uz[1:] * uz[:-1]
        cruise2 = np.minimum(vmax[1:], vmax[:-1]) ** 2
        j2 = _junction_v2(p, dot, acc[1:], acc[:-1], L3[1:], L3[:-1])
        j2 = np.minimum(j2, _extruder_junction_v2(p, np.where(motion, de / safe_L, 0.0)))
        jmax2[1:] = np.where(both, np.minimum(j2, cruise2), 0.0)

    start2, end2 = _lookahead(jmax2.tolist(), (2.0 * acc * length).tolist())
    start2 = np.asarray(start2)
    end2 = np.asarray(end2)
    with np.errstate(divide="ignore", invalid="ignore"):
        peak2 = np.where(length > 0, (2.0 * acc * length + start2 + end2) / 2.0, 0.0)
        vc2 = np.minimum(vmax ** 2, peak2)
        vc2 = np.maximum(vc2, np.maximum(start2, end2))
        v0 = np.sqrt(start2)
        v1 = np.sqrt(end2)
        vc = np.sqrt(vc2)
        moving = length > 0
        sa = np.where(moving, acc, 1.0)
        ta = np.where(moving, (vc - v0) / sa, 0.0)
        td = np.where(moving, (vc - v1) / sa, 0.0)
        da = np.where(moving, (vc2 - start2) / (2 * sa), 0.0)
        dd = np.where(moving, (vc2 - end2) / (2 * sa), 0.0)
        dc = np.maximum(length - da - dd, 0.0)
        tc = np.where(moving & (vc > 0), dc / np.where(vc > 0, vc, 1.0), 0.0)
    tc = np.where(dwell, moves.dwell_s, tc)
    dur = ta + tc + td
    t_start = np.concatenate([[0.0], np.cumsum(dur)[:-1]]) if n else np.zeros(0)
    return MovePlan(length_mm=length, accel_mm_s2=acc, v_start_mm_s=v0, v_cruise_mm_s=vc,
                    v_end_mm_s=v1, t_accel_s=ta, t_cruise_s=tc, t_decel_s=td,
                    t_start_s=t_start, kind=kind)


def klipper_refusals(moves: Moves, profile: PrinterProfile) -> list[tuple[int, str]]:
    """(G-code line, Klipper's error) for every move Klipper's extruder refuses, which stops
    the print there (klippy/kinematics/extruder.py ``check_move``): an XY move extruding
    more than ``max_extrude_cross_section`` (default 4 d^2 mm^2) per mm of path, unless it
    extrudes no more than d times that ratio in all; an extrude-only (or retracting) move
    longer than ``max_extrude_only_distance`` (default 50 mm). Empty for other firmware."""
    p = load_profile(profile)
    if p.firmware != "klipper" or len(moves) == 0:
        return []
    area = p.max_extrude_cross_section_mm2
    if area is None:
        area = 4.0 * p.nozzle_diameter_mm ** 2
    max_r = area / p.filament_area_mm2
    dxy = np.hypot(moves.x_mm - moves.x0_mm, moves.y_mm - moves.y0_mm)
    L3 = moves.xyz_length_mm
    de = moves.de_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(L3 > _EPS_MM, de / np.where(L3 > _EPS_MM, L3, 1.0), np.sign(de) * np.inf)
    e_only = (de != 0) & ((dxy <= 0) | (r < 0)) & (moves.dwell_s <= 0)
    out = []
    for i in np.flatnonzero(e_only & (np.abs(de) > p.max_extrude_only_distance_mm)):
        out.append((int(moves.line[i]), f"Extrude only move too long ({de[i]:.3f}mm vs "
                                        f"{p.max_extrude_only_distance_mm:.3f}mm)"))
    over = ~e_only & (dxy > 0) & (r > max_r) & (de > p.nozzle_diameter_mm * max_r)
    for i in np.flatnonzero(over):
        out.append((int(moves.line[i]), f"Move exceeds maximum extrusion ({r[i] * p.filament_area_mm2:.3f}mm^2 "
                                        f"vs {area:.3f}mm^2)"))
    return sorted(out)


def junction_speed_klipper_mm_s(angle_deg: float, scv_mm_s: float, accel_mm_s2: float) -> float:
    """Klipper's junction speed (mm/s) for a change of direction of ``angle_deg``
    (0 = straight on, 90 = square corner, 180 = reversal), ignoring the centripetal cap.

    jd = scv^2 (sqrt 2 - 1)/a;  v^2 = a jd sin(theta/2)/(1 - sin(theta/2)),
    theta = 180 deg - angle (klippy/toolhead.py).
    """
    jd = scv_mm_s ** 2 * (math.sqrt(2.0) - 1.0) / accel_mm_s2
    sin_t2 = math.sin(math.radians(180.0 - angle_deg) / 2.0)
    if sin_t2 >= 1.0:
        return math.inf
    return math.sqrt(accel_mm_s2 * jd * sin_t2 / (1.0 - sin_t2))


def _junction_v2(p: PrinterProfile, dot, a_cur, a_prev, L_cur, L_prev) -> np.ndarray:
    """Max junction speed^2 (mm^2/s^2) from unit-direction dot products (arrays)."""
    cos_theta = np.clip(-dot, -1.0, 1.0)
    sin_t2 = np.sqrt(np.maximum(0.5 * (1.0 - cos_theta), 0.0))
    cos_t2 = np.sqrt(np.maximum(0.5 * (1.0 + cos_theta), 0.0))
    one_minus = 1.0 - sin_t2
    with np.errstate(divide="ignore", invalid="ignore"):
        if p.firmware == "rrf" or p.junction_deviation_for_planner_mm is None:     # Marlin's classic jerk too
            du = np.sqrt(np.maximum(2.0 - 2.0 * dot, 0.0))
            v = np.where(du > 1e-12, p.max_jerk_mm_s / du, np.inf)
            return v * v
        jd = p.junction_deviation_for_planner_mm
        R = np.where(one_minus > 1e-12, sin_t2 / one_minus, np.inf)
        if p.firmware == "klipper":
            v2 = np.minimum(R * jd * a_cur, R * jd * a_prev)
            q = np.where(cos_t2 > 1e-12, 0.25 * sin_t2 / cos_t2, np.inf)
            cent = np.minimum(2.0 * L_cur * a_cur * q, 2.0 * L_prev * a_prev * q)
            v2 = np.minimum(v2, cent)
        else:
            v2 = R * jd * a_cur
    # a full reversal has sin(theta/2) = 0, hence R = 0 and v2 = 0: it stops
    return np.nan_to_num(v2, nan=0.0, posinf=np.inf)


def extruder_junction_limit_mm_s(profile) -> float | None:
    """The extruder speed change (mm/s of filament) the firmware allows at a junction
    without slowing the head (``_extruder_junction_v2``), or None where it sets none."""
    p = load_profile(profile)
    if p.firmware == "klipper":
        return p.instantaneous_corner_velocity_mm_s
    if p.max_e_jerk_mm_s is not None and (p.firmware == "rrf" or p.junction_deviation_mm is None):
        return p.max_e_jerk_mm_s
    return None


def _extruder_junction_v2(p: PrinterProfile, ratio) -> np.ndarray:
    """Max junction speed^2 (mm^2/s^2) from the extruder, per junction of consecutive
    moves, from ``ratio`` (M,): filament mm per mm of head path of each move (E / L).

    The extruder's own speed jumps at the junction by v |r2 - r1| at head speed v:
    * Klipper (klippy/kinematics/extruder.py ``calc_junction``): v^2 <= (icv / |r2 - r1|)^2,
      icv = ``instantaneous_corner_velocity_mm_s`` (Klipper's default 1 mm/s);
    * RRF (M566 E) and Marlin's classic jerk (M205 E): v <= e_jerk / |r2 - r1| with
      ``max_e_jerk_mm_s``; across a change of sign (extrude to retract) the jump is the
      larger speed, v max(|r1|, |r2|) (Marlin planner.cpp), as RRF's per-drive limit;
    * Marlin's junction deviation takes E into the corner's angle instead (plan_moves).
    A change of width along a straight line is then a corner: a line at 40 mm/s on Klipper
    slows to 1 / 0.042 = 24 mm/s where a 0.5 mm bead doubles (h 0.2 mm); the spiral-step
    pattern takes its steps in sub-steps to keep its speed (patterns/spiral_step.py)."""
    r1, r2 = ratio[:-1], ratio[1:]
    lim = extruder_junction_limit_mm_s(p)
    if lim is None:
        return np.full(len(r1), np.inf)
    if p.firmware == "klipper":
        jump = np.abs(r2 - r1)
    else:
        jump = np.where(r1 * r2 >= 0, np.abs(r2 - r1), np.maximum(np.abs(r1), np.abs(r2)))
    with np.errstate(divide="ignore"):
        return np.where(jump > 0, (lim / np.where(jump > 0, jump, 1.0)) ** 2, np.inf)


def _lookahead(jmax2: list, reach2: list) -> tuple[list, list]:
    """Whole-queue look-ahead on squared speeds. jmax2[i] caps the start of move i;
    reach2[i] = 2 a_i L_i. Returns (start^2, end^2) per move, end of the last move 0."""
    n = len(jmax2)
    start_b = [0.0] * n
    nxt = 0.0
    for i in range(n - 1, -1, -1):
        s = jmax2[i]
        r = nxt + reach2[i]
        start_b[i] = s if s < r else r
        nxt = start_b[i]
    start = [0.0] * n
    end = [0.0] * n
    prev_end = 0.0
    for i in range(n):
        s = start_b[i] if start_b[i] < prev_end else prev_end
        nb = start_b[i + 1] if i + 1 < n else 0.0
        r = s + reach2[i]
        e = nb if nb < r else r
        start[i] = s
        end[i] = e
        prev_end = e
    return start, end


def plan(parse_result_or_moves, profile, *, ds_max_mm: float = DS_MAX_MM,
         dt_max_s: float = DT_MAX_S) -> Timeline:
    """Plan and sample: ParseResult (or Moves) + profile -> Timeline.

    Track ids come from the ;TRACK labels, or for unlabelled G-code from
    :func:`patterns.gcode_parser.auto_tracks`.
    """
    tl, _ = _plan_with_details(parse_result_or_moves, profile, ds_max_mm, dt_max_s)
    return tl


def plan_gcode(text, profile) -> tuple[Timeline, ParseResult]:
    """Parse and plan G-code text. The ParseResult's PA events get their times t_s."""
    p = load_profile(profile)
    pr = parse_gcode(text, p)
    tl, mp = _plan_with_details(pr, p, DS_MAX_MM, DT_MAX_S)
    end_t = mp.total_time_s
    events = [replace(ev, t_s=float(mp.t_start_s[ev.move_index]) if ev.move_index < len(mp.t_start_s)
                      else end_t) for ev in pr.pa_events]
    return tl, replace(pr, pa_events=events)


def track_ids(pr_or_moves) -> np.ndarray:
    """Per-move track ids: labels if the G-code has them, else auto tracks."""
    if isinstance(pr_or_moves, ParseResult):
        return pr_or_moves.moves.track if pr_or_moves.labelled else auto_tracks(pr_or_moves.moves)
    mv = pr_or_moves
    return mv.track if (mv.track >= 0).any() else auto_tracks(mv)


def _plan_with_details(src, profile, ds_max_mm, dt_max_s) -> tuple[Timeline, MovePlan]:
    p = load_profile(profile)
    moves = src.moves if isinstance(src, ParseResult) else src
    track = track_ids(src)
    mp = plan_moves(moves, p)
    return sample_timeline(moves, mp, track, ds_max_mm, dt_max_s), mp


def sample_timeline(moves: Moves, mp: MovePlan, track: np.ndarray,
                    ds_max_mm: float = DS_MAX_MM, dt_max_s: float = DT_MAX_S) -> Timeline:
    """Sample the planned trapezoids uniformly in time inside each move (vectorised).

    Within a move, path distance s(tau) is the exact trapezoid: v0 tau + a tau^2/2 while
    accelerating, then cruise, then decelerating; position, E and track arc length are
    linear in s, so e increments between samples are exact.
    """
    n = len(moves)
    if n == 0:
        return Timeline(*(np.zeros(0) for _ in range(7)), np.zeros(0, np.int64), np.zeros(0))
    dur = mp.duration_s
    vc = mp.v_cruise_mm_s
    nseg_f = np.maximum.reduce([np.ones(n), np.ceil(dur / dt_max_s - 1e-9), np.ceil(vc * dur / ds_max_mm - 1e-9)])
    nseg_f = np.where(dur > 0, nseg_f, 0.0)
    total = float(np.sum(nseg_f))
    if not np.isfinite(total) or total > MAX_TIMELINE_SAMPLES:
        k = int(np.argmax(~np.isfinite(nseg_f) | (nseg_f > MAX_TIMELINE_SAMPLES / 10))) if n else 0
        raise UserError(f"the program is too long to plan (move {k + 1} alone would take {dur[k]:.3g} s): "
                        "a corrupt E or F value?")
    nseg = nseg_f.astype(np.int64)
    # a sample at the start of each move that begins a track, so s = 0 is on the track
    prev_track = np.concatenate([[-2], track[:-1]])
    starts_track = (track >= 0) & (track != prev_track)
    first = np.zeros(n, dtype=bool)
    first[0] = True
    with_start = starts_track | first
    counts = nseg + with_start
    idx = np.repeat(np.arange(n), counts)
    # k = 0 for the start sample, 1..nseg for the others
    offs = np.concatenate([[0], np.cumsum(counts)[:-1]])
    k = np.arange(len(idx)) - offs[idx] + (~with_start[idx]).astype(np.int64)
    safe_n = np.where(nseg[idx] > 0, nseg[idx], 1)
    tau = dur[idx] * k / safe_n
    ta = mp.t_accel_s[idx]
    tc = mp.t_cruise_s[idx]
    td = mp.t_decel_s[idx]
    a = mp.accel_mm_s2[idx]
    v0 = mp.v_start_mm_s[idx]
    vcs = vc[idx]
    L = mp.length_mm[idx]
    t1 = tau - ta - tc
    in_acc = tau < ta
    in_dec = t1 > 0
    da = (vcs + v0) * 0.5 * ta
    s = np.where(in_acc, v0 * tau + 0.5 * a * tau * tau,
                 np.where(in_dec, da + vcs * tc + vcs * t1 - 0.5 * a * t1 * t1, da + vcs * (tau - ta)))
    v = np.where(in_acc, v0 + a * tau, np.where(in_dec, vcs - a * t1, vcs))
    dwell_like = mp.kind[idx] == 2
    s = np.where(dwell_like, 0.0, s)
    v = np.where(dwell_like, 0.0, v)
    frac = np.where(L > 0, np.clip(s / np.where(L > 0, L, 1.0), 0.0, 1.0), 0.0)
    frac = np.where((k == nseg[idx]) & (nseg[idx] > 0) & ~dwell_like, 1.0, frac)

    x = moves.x0_mm[idx] + frac * (moves.x_mm[idx] - moves.x0_mm[idx])
    y = moves.y0_mm[idx] + frac * (moves.y_mm[idx] - moves.y0_mm[idx])
    z = moves.z0_mm[idx] + frac * (moves.z_mm[idx] - moves.z0_mm[idx])
    de = moves.de_mm
    e_before = np.concatenate([[0.0], np.cumsum(de)[:-1]])
    e = e_before[idx] + frac * de[idx]
    lxy = moves.xy_length_mm
    l_safe = np.where(L > 0, L, 1.0)
    motion = mp.kind[idx] == 0
    v_head = np.where(motion, v * lxy[idx] / l_safe, 0.0)
    ve = np.where(dwell_like, 0.0, v * de[idx] / l_safe)

    # arc length along each track: cumulative XY length of the track's earlier moves
    on = track >= 0
    s0 = np.zeros(n)
    if on.any():
        order = np.argsort(np.where(on, track, np.iinfo(np.int64).max), kind="stable")
        ls = np.where(on, lxy, 0.0)[order]
        cs = np.cumsum(ls) - ls
        tr_sorted = track[order]
        grp_start = np.concatenate([[True], tr_sorted[1:] != tr_sorted[:-1]])
        base = np.maximum.accumulate(np.where(grp_start, cs, 0.0))
        s0[order] = cs - base
    tr = track[idx]
    s_track = np.where(tr >= 0, s0[idx] + frac * lxy[idx], np.nan)
    t = mp.t_start_s[idx] + tau
    # A move boundary where an untracked move hands over to a track appears twice (end of
    # the untracked move, start sample of the track): keep only the track's copy.
    dup = np.zeros(len(idx), dtype=bool)
    dup[:-1] = (k[1:] == 0) & (idx[1:] > 0) & (tr[:-1] < 0)
    # zero-duration moves contribute no samples except possibly a start sample: nothing to drop
    keep = ~dup
    return Timeline(t_s=t[keep], x_mm=x[keep], y_mm=y[keep], z_mm=z[keep], v_mm_s=v_head[keep],
                    ve_mm_s=ve[keep], e_mm=e[keep], track=tr[keep], s_mm=s_track[keep])
