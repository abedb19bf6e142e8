"""The firmware setting that minimises the *predicted width error* of a reference print.

``pa.tau_s`` is the right linear pressure advance only for a printer whose physics is
linear (seed 001 / REFERENCE "Physics": K v_e cancels dP/dt = v_e - P/tau exactly). With
shear thinning, bead back-pressure, a flow threshold or thermal ooze no single K cancels
the lag, and the best K depends on the moves printed. This module answers "which K (and
Klipper smooth_time) makes *this* print come out closest to the commanded widths" by
simulating a reference print with the fitted physics plus the firmware's own
compensation, per posterior draw:

    firmware extruder position (Klipper klippy/chelper/kin_extruder.c; Kalico
    bleeding-edge-v2 ``pressure_advance_*_model_func``):
        e_fw(t) = S[e](t) + A(S[v_pa](t))
    S[.]  the triangular smoothing window of total width smooth_time (0 = none: Marlin
          LA 1.5, RRF); v_pa the commanded extruder velocity on printing moves (0 on
          retract / travel, fit/effects.py FirmwarePA)
    A(v)  = K v                                   linear PA (Klipper, Marlin, RRF)
          = LA v + off tanh(v / v_lin)            Kalico "tanh"
          = LA v + off v / (v + v_lin)            Kalico "recipr"
          = K(q_move) v                           Orca adaptive PA: K from the table at
            the commanded flow q_move (mm^3/s) of the move being printed (PCHIP between
            rows, the end rows' K held outside; rounded to 0.001 s, as Orca does), kept
            over travels until the next printing move (Orca emits a PA command per move
            whose flow changes)

then the fitted nozzle physics (fit/kernels.py) and bead deposit (fit/context.py) give the
width at every station of the reference print. The width error of a station is the
predicted minus the commanded bead width (mm); it is summarised as RMS over

    starts   stations within ``WINDOW_MM`` of a track's start
    stops    stations within ``WINDOW_MM`` of a track's end
    corners  other stations within ``CORNER_MM`` of a vertex where the path turns by
             more than ``CORNER_DEG``
    steady   the rest;      all: every station

Only the printer's dynamics are simulated: station-stage nuisances of the fit
(scan_bias, heading, bed_tilt), its flow_gain (fixed by the extrusion multiplier, not by
PA) and a firmware_pa effect (the test print's own PA, a known input) are left out.

The linear optimum minimises the RMS over all stations, per posterior draw, with a
bounded Brent search on K (scipy.optimize.minimize_scalar) or, for Klipper with the
smooth time free, bounded Nelder-Mead on (K, smooth_time) (scipy.optimize.minimize);
its 95 % interval is the 2.5-97.5 % quantiles over the draws.

The standard reference print (:func:`standard_reference`) is four L-U shaped lines (a
start, two 90 degree corners, a stop, retract and travel in between) at 25, 50, 100 and
150 mm/s head speed (capped by the profile's speed and extruder limits), line width
1.2 x nozzle, layer 0.2 mm: the starts, stops and corners of perimeters and infill.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from calib.errors import UserError
from fit.effects import Effect, _pa_velocity, triangular_smooth
from fit.noise_envelope import _hull
from fit.nuisance import NOT_PASTED
from fit.params import Param

#: head speeds (mm/s) of the standard reference print's lines
STANDARD_SPEEDS_MM_S = (25.0, 50.0, 100.0, 150.0)
#: station classes: start / stop windows (mm of track), corner half-window (mm), turn (deg)
WINDOW_MM = 3.0
CORNER_MM = 1.5
CORNER_DEG = 20.0
CLASSES = ("starts", "stops", "corners", "steady", "all")
#: Klipper's default pressure_advance_smooth_time (s; klippy/kinematics/extruder.py)
KLIPPER_SMOOTH_TIME_S = 0.040
#: Bounds of the smooth time search (s). Klipper accepts 0 < smooth_time <= 0.2; the
#: model has no extruder motor (torque, step rate), so a shorter window never looks worse
#: to it: the floor is half Klipper's default, not 0, so the value stays one a real
#: extruder follows.
SMOOTH_MIN_S, SMOOTH_MAX_S = 0.020, 0.200
#: upper bound of the linear K search, as a multiple of the fitted tau (and at least 0.2 s);
#: an optimum on it doubles it, up to K_LIMIT_S
K_MAX_FACTOR = 4.0
#: the largest linear K (s) searched: Marlin's M900 takes K up to 10; Bowden printers measure
#: 0.3-1.5 s (REFERENCE), so an optimum at 5 s is no printer's but a fit's that says nothing there
K_LIMIT_S = 5.0
#: an optimum within this fraction of the search's upper bound is on it
EDGE_FRACTION = 0.01
#: at most this much printing time (s) of a user's G-code is simulated
MAX_REFERENCE_S = 90.0
#: a reference flow this much above the highest tested flow is an extrapolation
EXTRAPOLATION_MARGIN = 1.05
#: what is not the printer's extrusion dynamics: inputs, the bed's geometry, a static gain,
#: the bead's own spread and the picture's nuisances (fit/nuisance.py NOT_PASTED); a phone
#: fit of pa+scan_bias+view_light had been matched as "more than linear PA"
NOT_DYNAMICS = frozenset({"heading", "bed_tilt", "bed_mesh", "flow_gain", "firmware_pa", *NOT_PASTED})
#: adaptive table rows the compensation effect can hold
N_TABLE = 16
#: Draws of each envelope (fit.json ``envelope_samples``) the K interval is taken over.
ENVELOPE_MATCH_DRAWS = 32
#: What each envelope holds, for the note beside the interval.
ENVELOPE_WORDS = {"offset": "the width calibration's offset doubt",
                  "noise": "the short-wobble noise model's fit"}

MODE_LINEAR, MODE_TANH, MODE_RECIPR, MODE_TABLE = 0.0, 1.0, 2.0, 3.0


# ----------------------------------------------------------------------------------------
# the firmware's compensation as a command-stage effect (all parameter sets at once)

class FirmwareComp(Effect):
    """Firmware pressure advance of any kind applied to the command (module docstring):
    e_fw = S[e] + A(S[v_pa]) with A linear (mode 0), Kalico tanh (1), Kalico recipr (2)
    or an Orca adaptive table K(q_move) v (3). Parameters per set: ``mode``, ``k_s`` (K or
    Kalico LA, s), ``smooth_time_s`` (s), ``off_mm`` (Kalico offset, mm), ``vlin_mm_s``
    (Kalico linearization velocity, mm/s of filament), ``kt0..`` the table's K (s) at the
    flows ``self.table_flow_mm3_s`` (set on the instance; NaN rows unused)."""

    name = "fw_comp"
    params = (Param("mode", "1", 0.0, 0.0, 3.0, "uniform", doc="0 linear, 1 tanh, 2 recipr, 3 table"),
              Param("k_s", "s", 0.0, 0.0, 10.0, "uniform", doc="linear K or Kalico LA"),
              Param("smooth_time_s", "s", 0.0, 0.0, 0.2, "uniform", doc="smoothing window"),
              Param("off_mm", "mm", 0.0, 0.0, 100.0, "uniform", doc="Kalico offset"),
              Param("vlin_mm_s", "mm/s", 1.0, 1e-6, 1e4, "uniform", doc="Kalico velocity"),
              ) + tuple(Param(f"kt{i}", "s", 0.0, 0.0, 10.0, "uniform", doc="table K")
                        for i in range(N_TABLE))

    def __init__(self, profile=None):
        super().__init__(profile)
        self.table_flow_mm3_s = np.zeros(0)

    def command(self, ctx, ve, p):
        n = ve.shape[0]
        col = lambda k: np.broadcast_to(p[k][:, 0], (n,))        # noqa: E731
        mode, k, st = col("mode"), col("k_s"), col("smooth_time_s")
        off, vl = col("off_mm"), np.maximum(col("vlin_mm_s"), 1e-9)
        active = (k > 0) | (off > 0) | (mode == MODE_TABLE)
        if not np.any(active):
            return ve
        e = np.asarray(ctx.e_mm, float)
        v_pa = _pa_velocity(ctx)
        out = np.array(ve, dtype=float, copy=True)
        base = np.diff(e) / ctx.dt_s
        kq = None
        if np.any(active & (mode == MODE_TABLE)):
            kq = _table_k_nodes(ctx, self.table_flow_mm3_s,
                                np.stack([col(f"kt{i}") for i in range(N_TABLE)], axis=1))
        for st_val in np.unique(st[active]):
            rows = np.flatnonzero(active & (st == st_val))
            se = _smooth(ctx, "e", e, float(st_val))
            sv = _smooth(ctx, "v_pa", v_pa, float(st_val))
            adv = np.empty((len(rows), len(e)))
            adv_raw = np.empty((len(rows), 2))            # unsmoothed, at the two end nodes
            for j, r in enumerate(rows):
                adv[j] = _advance(mode[r], k[r], off[r], vl[r], sv, None if kq is None else kq[r])
                ends = v_pa[[0, -1]]
                adv_raw[j] = _advance(mode[r], k[r], off[r], vl[r], ends,
                                      None if kq is None else kq[r][[0, -1]])
            # as fit.effects.FirmwarePA: the end nodes keep the raw position, so the motion
            # the window spreads beyond the timeline is lumped into the end intervals
            pos = se[None, :] + adv
            pos[:, 0] = e[0] + adv_raw[:, 0]
            pos[:, -1] = e[-1] + adv_raw[:, 1]
            out[rows] = ve[rows] - base + np.diff(pos, axis=1) / ctx.dt_s
        return out


def _advance(mode, k, off, vl, v, k_nodes):
    """A(v) (mm of filament) of one parameter set at smoothed velocities v (mm/s)."""
    if mode == MODE_TANH:
        return k * v + off * np.tanh(v / vl)
    if mode == MODE_RECIPR:
        return k * v + off * v / (v + vl)
    if mode == MODE_TABLE:
        return k_nodes * v
    return k * v


def _smooth(ctx, key, f, smooth_s):
    """f at the nodes convolved with Klipper's triangular window of total width smooth_s
    (two boxes of smooth_s / 2), fit.effects.triangular_smooth; at most a
    few windows kept in ctx.cache, since the optimiser tries many."""
    if smooth_s <= 0:
        return np.asarray(f, float)
    cache = ctx.cache.setdefault("fw_comp_smooth", {})
    ck = (key, smooth_s)
    if ck in cache:
        return cache[ck]
    res = triangular_smooth(ctx.t_s, f, smooth_s)
    if len(cache) >= 8:
        cache.pop(next(iter(cache)))
    cache[ck] = res
    return res


def orca_table_k(flow_mm3_s, table_flow_mm3_s, table_k_s) -> np.ndarray:
    """K (s) Orca's adaptive PA uses at flows q (mm^3/s) from one acceleration's table rows
    (flows ascending), by Orca's own rules (OrcaSlicer src/libslic3r/PchipInterpolator.cpp,
    GCode/AdaptivePAInterpolator.cpp): PCHIP between rows with the weighted harmonic mean
    slopes inside and the end secants at the ends, the first/last row's K held outside
    the table (no extrapolation), rounded to 0.001 s."""
    q = np.asarray(flow_mm3_s, float)
    x, y = np.asarray(table_flow_mm3_s, float), np.asarray(table_k_s, float)
    if len(x) == 1:
        return np.round(np.full(q.shape, y[0]), 3)
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.empty(len(x))
    d[0], d[-1] = delta[0], delta[-1]
    for i in range(1, len(x) - 1):
        if delta[i - 1] * delta[i] > 0:
            w1, w2 = 2 * h[i] + h[i - 1], h[i] + 2 * h[i - 1]
            d[i] = (w1 + w2) / (w1 / delta[i - 1] + w2 / delta[i])
        else:
            d[i] = 0.0
    qc = np.clip(q, x[0], x[-1])
    i = np.clip(np.searchsorted(x, qc, side="left") - 1, 0, len(x) - 2)
    t = (qc - x[i]) / h[i]
    out = ((2 * t ** 3 - 3 * t ** 2 + 1) * y[i] + (t ** 3 - 2 * t ** 2 + t) * h[i] * d[i]
           + (-2 * t ** 3 + 3 * t ** 2) * y[i + 1] + (t ** 3 - t ** 2) * h[i] * d[i + 1])
    return np.round(out, 3)


def _table_k_nodes(ctx, table_flow, table_k) -> np.ndarray:
    """(n_sets, n_nodes) K of the adaptive table at each node's move flow; NaN rows of a
    table (fewer than N_TABLE rows) are ignored."""
    q = ctx.cache["fw_comp_move_flow"]            # move flow at the nodes, NaN off moves
    ok = np.isfinite(q)
    out = np.zeros((table_k.shape[0], len(q)))
    m = len(table_flow)
    for r in range(table_k.shape[0]):
        kq = np.full(len(q), np.nan)
        kq[ok] = orca_table_k(q[ok], table_flow, table_k[r, :m])
        out[r] = _fill_forward(kq)
    return out


def _fill_forward(a):
    """NaN entries take the last finite value before them (the first finite before any)."""
    ok = np.isfinite(a)
    if not ok.any():
        return np.zeros_like(a)
    idx = np.where(ok, np.arange(len(a)), 0)
    np.maximum.accumulate(idx, out=idx)
    out = a[idx]
    first = np.flatnonzero(ok)[0]
    out[:first] = a[first]
    return out


# ----------------------------------------------------------------------------------------
# reference prints

def standard_reference(profile, speeds_mm_s=STANDARD_SPEEDS_MM_S):
    """The standard move mix (module docstring) as a planned Manifest."""
    from patterns.builder import PatternBuilder
    from patterns.profile import load_profile

    prof = load_profile(profile)
    b = PatternBuilder(prof, "reference-move-mix", {"speeds_mm_s": list(speeds_mm_s)})
    b.set_z(b.layer_height_mm)
    w, h = b.line_width_mm, b.layer_height_mm
    # the head speed a flow the extruder can push allows (filament mm/s * Af = w h v)
    v_e_max = 0.9 * prof.max_e_velocity_mm_s * prof.filament_area_mm2 / (w * h)
    x0 = 0.5 * (prof.bed_x_mm[0] + prof.bed_x_mm[1]) - 20.0
    y0 = 0.5 * (prof.bed_y_mm[0] + prof.bed_y_mm[1]) - 25.0
    for i, v in enumerate(speeds_mm_s):
        v = float(min(v, prof.max_velocity_mm_s, v_e_max))
        y = y0 + 14.0 * i
        pts = np.array([[x0, y], [x0 + 40.0, y], [x0 + 40.0, y + 6.0], [x0 + 10.0, y + 6.0]])
        b.begin("test", pts[0], params={"speed_mm_s": v})
        b.extrude(pts, w, v)
        b.end()
    return b.build()[1]


def reference_from_gcode(text: str, profile, name: str = "G-code", max_print_s: float = MAX_REFERENCE_S):
    """A user's G-code as the reference print (patterns.plan.manifest_from_gcode). Bad
    G-code or G-code that prints no line: UserError naming the file."""
    from patterns.plan import manifest_from_gcode

    try:
        man = manifest_from_gcode(text, profile)
    except UserError as exc:
        raise UserError(f"--on {name}: {exc}") from None
    if man.timeline is None or not any(t.kind == "test" for t in man.tracks):
        raise UserError(f"--on {name}: no extruding line of at least 3 mm in it; give the G-code "
                        "of a print (sliced, with extrusion)")
    man.pattern = {**(man.pattern or {}), "max_print_s": float(max_print_s)}
    return man


@dataclass
class Reference:
    """A reference print ready to simulate.

    ctx           fit.context.SimContext of its stations
    classes       class name -> bool mask over the stations (CLASSES)
    nominal_mm    commanded width at the stations (mm)
    flow_mm3_s    (lo, hi): 0.1 and 99.9 % time-weighted quantiles of the commanded
                  flow while printing (mm^3/s)
    description   one line for the user
    """

    ctx: object
    classes: dict
    nominal_mm: np.ndarray
    flow_mm3_s: tuple
    description: str
    n_tracks: int = 0


def prepare_reference(manifest, description: str = "", max_print_s: float | None = None) -> Reference:
    """Stations (every 0.25 mm of the test tracks), their classes, the flow range."""
    from fit.context import SimContext
    from patterns.manifest import sample_points

    smp = sample_points(manifest, ds_mm=0.25)
    if max_print_s is None:
        max_print_s = float((manifest.pattern or {}).get("max_print_s", math.inf))
    keep = np.ones(len(smp), bool)
    note = ""
    if len(smp) and np.isfinite(max_print_s):
        t0 = float(np.nanmin(smp.t_s))
        keep = np.isfinite(smp.t_s) & (smp.t_s <= t0 + max_print_s)
        if not keep.all():
            note = f" (its first {max_print_s:g} s of printing)"
    if len(smp) and not keep.all():
        from dataclasses import fields as dfields

        smp = type(smp)(**{f.name: getattr(smp, f.name)[keep] for f in dfields(smp)})
    if len(smp) == 0:
        raise UserError("the reference print has no line to measure")
    ctx = SimContext.build(manifest, smp)
    tracks = {t.id: t for t in manifest.tracks}
    n = len(smp)
    start, stop, corner = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    for tid in np.unique(smp.track):
        tr = tracks[int(tid)]
        m = smp.track == tid
        s = smp.s_mm[m]
        start[m] = s <= WINDOW_MM
        stop[m] = s >= tr.length_mm - WINDOW_MM
        sc = _corner_arcs(tr)
        if len(sc):
            corner[m] = np.min(np.abs(s[:, None] - sc[None, :]), axis=1) <= CORNER_MM
    nominal = np.asarray(smp.width_nominal_mm, float)
    valid = np.asarray(ctx.printed, bool) & (nominal > 0)
    corner &= ~(start | stop)
    classes = {"starts": start & valid, "stops": stop & valid, "corners": corner & valid,
               "steady": valid & ~(start | stop | corner), "all": valid}
    # the flow each node's move commands (Orca's adaptive table is looked up with it)
    tl = manifest.timeline
    qn = np.full(len(tl), np.nan)
    for tid, tr in tracks.items():
        on = tl.track == tid
        if on.any():
            qn[on] = tr.interp("flow_mm3_s", tl.s_mm[on])
    qn[~(qn > 0)] = np.nan
    ctx.cache["fw_comp_move_flow"] = qn
    if ctx.physics is not None:
        ctx.physics.cache["fw_comp_move_flow"] = qn[ctx.physics.node_index]
    prt = (ctx.de_mm > 0) & (ctx.v_head_mm_s > 1e-6) & ctx.on_track
    q = ctx.ve_mm_s[prt] * ctx.filament_area_mm2
    lo, hi = _weighted_quantiles(q, ctx.dt_s[prt], (0.001, 0.999)) if q.size else (0.0, 0.0)
    return Reference(ctx=ctx, classes=classes, nominal_mm=nominal, flow_mm3_s=(lo, hi),
                     description=(description or "reference print") + note,
                     n_tracks=len(np.unique(smp.track)))


def _corner_arcs(tr) -> np.ndarray:
    """Arc lengths (mm) of the vertices where the path turns by more than CORNER_DEG."""
    p = tr.points_mm
    cl = tr.cumlen_mm
    seg = np.diff(p, axis=0)
    L = np.hypot(seg[:, 0], seg[:, 1])
    ok = L > 1e-6
    if ok.sum() < 2:
        return np.zeros(0)
    ang = np.arctan2(seg[ok, 1], seg[ok, 0])
    turn = np.abs((np.diff(ang) + np.pi) % (2 * np.pi) - np.pi)
    starts = cl[:-1][ok]                  # arc length where each non-empty segment begins
    return starts[1:][np.degrees(turn) > CORNER_DEG]


def _weighted_quantiles(x, w, qs):
    o = np.argsort(x)
    cw = np.cumsum(np.asarray(w, float)[o])
    cw /= cw[-1]
    return tuple(float(x[o][min(np.searchsorted(cw, q), len(x) - 1)]) for q in qs)


def tested_flow_range(problem) -> dict:
    """The commanded flows (mm^3/s) the test print covered: 0.1 and 99.9 % time-weighted
    quantiles of the commanded flow while printing on the tracks of all scans."""
    qs, ws = [], []
    for sc in problem.scans:
        c = sc.ctx
        m = np.asarray(c.on_track) & (np.asarray(c.de_mm) > 0) & (np.asarray(c.v_head_mm_s) > 1e-6)
        qs.append(np.asarray(c.ve_mm_s)[m] * c.filament_area_mm2)
        ws.append(np.asarray(c.dt_s)[m])
    q, w = np.concatenate(qs), np.concatenate(ws)
    if q.size == 0:
        return {}
    lo, hi = _weighted_quantiles(q, w, (0.001, 0.999))
    return {"lo": lo, "hi": hi}


# ----------------------------------------------------------------------------------------
# the fitted physics, per posterior draw

@dataclass
class Physics:
    """The fit's extrusion dynamics with the firmware compensation in front.

    model     fit.model.Model "fw_comp+<dynamics>"
    theta     (n_draws, k) physics columns of the chosen draws (compensation columns 0)
    spec      the dynamics spec; dropped: the effects left out (NOT_DYNAMICS)
    """

    model: object
    theta: np.ndarray
    spec: str
    dropped: list
    comp: FirmwareComp = field(repr=False, default=None)
    linear: bool = False
    tau_s: np.ndarray | None = None

    def col(self, name):
        return self.model.param_names.index(f"fw_comp.{name}")


def physics_from_fit(doc, n_draws: int = 64, seed: int = 0) -> Physics:
    """Rebuild the fit's dynamics from fit.json (model spec, param_names, samples,
    profile) with ``n_draws`` posterior draws (random subsample, fixed seed). UserError
    when the fit holds no draws or a model this version cannot rebuild."""
    from fit.model import build_model

    spec = str(doc.get("model") or "")
    names = list(doc.get("param_names") or [])
    S = np.asarray(doc.get("samples", []), float)
    if S.ndim != 2 or S.shape[0] == 0 or S.shape[1] != len(names):
        raise UserError("fit.json holds no posterior draws (a MAP-only fit?); run `calib fit` "
                        "without --map-only")
    parts = [p for p in spec.split("+") if p]
    dyn = [p for p in parts if p not in NOT_DYNAMICS]
    dropped = [p for p in parts if p in NOT_DYNAMICS]
    if not dyn:
        raise UserError(f"model {spec!r} has no extrusion dynamics to compensate")
    prof = dict(doc.get("profile") or {})
    try:
        model = build_model("fw_comp+" + "+".join(dyn), prof, extra_effects=(FirmwareComp,))
    except UserError as exc:
        raise UserError(f"cannot rebuild the fitted model for the width simulation: {exc}") from None
    rng = np.random.default_rng(seed)
    rows = S[rng.choice(len(S), min(n_draws, len(S)), replace=False)]
    base = [n.split("@")[0] for n in names]
    theta = np.tile(model.default_theta(), (len(rows), 1))
    for j, pn in enumerate(model.param_names):
        if pn.startswith("fw_comp."):
            continue
        if pn in base:                # per-scan copies (name@scan): the first scan's
            theta[:, j] = rows[:, base.index(pn)]
    comp = next(e for e in model.effects if e.name == "fw_comp")
    linear = set(dyn) <= {"pa", "pa_ve"}
    tau = None
    if "pa.tau_s" in base:
        tau = rows[:, base.index("pa.tau_s")]
    elif "pa_ve.ve_us" in base:          # seed 000: tau = 32 D^2 L l / d^4 VE
        from fit.effects import tau_from_ve_s

        tau = tau_from_ve_s(rows[:, base.index("pa_ve.ve_us")], *(float(prof.get(k, 0.0)) for k in (
            "filament_diameter_mm", "bowden_length_mm", "nozzle_land_length_mm", "nozzle_diameter_mm")))
    return Physics(model=model, theta=theta, spec="+".join(dyn), dropped=dropped, comp=comp,
                   linear=linear, tau_s=tau)


@dataclass
class Setting:
    """One firmware compensation: kind "none" | "linear" | "tanh" | "recipr" | "table"."""

    kind: str
    k_s: float = 0.0
    smooth_time_s: float = 0.0
    off_mm: float = 0.0
    vlin_mm_s: float = 1.0
    table_flow_mm3_s: tuple = ()
    table_k_s: tuple = ()

    def label(self) -> str:
        return {"none": "no PA", "linear": f"linear PA {self.k_s:.4f} s",
                "tanh": "Kalico tanh", "recipr": "Kalico recipr",
                "table": "adaptive table"}[self.kind]


def _theta_for(phys: Physics, settings: list[Setting]) -> np.ndarray:
    """(len(settings) * n_draws, k): every setting on every draw (setting-major)."""
    out = []
    tab = next((s for s in settings if s.kind == "table"), None)
    if tab is not None:
        if len(tab.table_flow_mm3_s) > N_TABLE:
            raise ValueError(f"adaptive table longer than {N_TABLE} rows")
        phys.comp.table_flow_mm3_s = np.asarray(tab.table_flow_mm3_s, float)
    for s in settings:
        th = phys.theta.copy()
        mode = {"none": MODE_LINEAR, "linear": MODE_LINEAR, "tanh": MODE_TANH,
                "recipr": MODE_RECIPR, "table": MODE_TABLE}[s.kind]
        th[:, phys.col("mode")] = mode
        th[:, phys.col("k_s")] = 0.0 if s.kind in ("none", "table") else s.k_s
        th[:, phys.col("smooth_time_s")] = 0.0 if s.kind == "none" else s.smooth_time_s
        th[:, phys.col("off_mm")] = s.off_mm if s.kind in ("tanh", "recipr") else 0.0
        th[:, phys.col("vlin_mm_s")] = s.vlin_mm_s
        if s.kind == "table":
            for i, k in enumerate(s.table_k_s):
                th[:, phys.col(f"kt{i}")] = k
        out.append(th)
    return np.concatenate(out, axis=0) if out else np.zeros((0, phys.theta.shape[1]))


def width_errors_mm(phys: Physics, ref: Reference, theta) -> dict:
    """RMS width error (mm) per class (CLASSES) for each row of theta: dict of (n,)."""
    w = phys.model.predict(ref.ctx, theta)
    err = w - ref.nominal_mm[None, :]
    out = {}
    for c, m in ref.classes.items():
        out[c] = (np.sqrt(np.mean(err[:, m] ** 2, axis=1)) if m.any()
                  else np.full(len(theta), np.nan))
    return out


def _rms_one(phys, ref, th_row):
    w = phys.model.predict(ref.ctx, th_row[None, :])[0]
    e = (w - ref.nominal_mm)[ref.classes["all"]]
    r = float(np.sqrt(np.mean(e * e)))
    return r if np.isfinite(r) else 1e3


def optimal_linear(phys: Physics, ref: Reference, *, smooth_time_s: float = 0.0,
                   free_smooth: bool = False, k_max_s: float | None = None,
                   on_draw=None) -> dict:
    """Per draw, the linear K (s) (and, with ``free_smooth``, the Klipper smooth time in
    [SMOOTH_MIN_S, SMOOTH_MAX_S]) that minimises the RMS width error over all stations.
    Returns arrays: k_s, smooth_time_s, rms_mm (at the optimum). ``on_draw()`` is called
    after each draw (a progress bar)."""
    n = len(phys.theta)
    if k_max_s is None:
        tau_hi = float(np.nanmax(phys.tau_s)) if phys.tau_s is not None else 0.05
        k_max_s = max(K_MAX_FACTOR * tau_hi, 0.2)
    ks, sts, rms = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        base = _theta_for(Physics(phys.model, phys.theta[i:i + 1], phys.spec, phys.dropped,
                                  phys.comp), [Setting("linear", 0.0, smooth_time_s)])[0]
        jk, js = phys.col("k_s"), phys.col("smooth_time_s")
        k0 = float(phys.tau_s[i]) if phys.tau_s is not None else 0.05 * k_max_s

        def f_k(k, st=smooth_time_s):
            th = base.copy()
            th[jk], th[js] = k, st
            return _rms_one(phys, ref, th)

        # The start bound comes from the fitted tau, which is not the whole advance when a
        # nonlinear term carries it: a foreign Bowden printer fitted as pa+kalico_recip (tau
        # 0.04 s, the reciprocal term the rest) had its optimum on the 0.2 s bound on every
        # draw, exported as 0.2000 [0.2000, 0.2000] (bench_export_foreign). An optimum on the
        # bound is no optimum: search again above it.
        hi = k_max_s
        while True:
            r = minimize_scalar(f_k, bounds=(0.0, hi), method="bounded",
                                options={"xatol": 1e-4 * max(k0, 1e-3)})
            if r.x < (1.0 - EDGE_FRACTION) * hi or hi >= K_LIMIT_S:
                break
            hi = min(2.0 * hi, K_LIMIT_S)
        k_best, st_best, f_best = float(r.x), smooth_time_s, float(r.fun)
        if free_smooth:
            sc = np.array([max(k_best, 1e-3), KLIPPER_SMOOTH_TIME_S])
            st0 = min(max(smooth_time_s or KLIPPER_SMOOTH_TIME_S, SMOOTH_MIN_S), SMOOTH_MAX_S)
            r2 = minimize(lambda z: f_k(z[0] * sc[0], z[1] * sc[1]),
                          x0=np.array([k_best / sc[0], st0 / sc[1]]), method="Nelder-Mead",
                          bounds=[(0.0, hi / sc[0]), (SMOOTH_MIN_S / sc[1], SMOOTH_MAX_S / sc[1])],
                          options={"xatol": 2e-3, "fatol": 1e-7, "maxfev": 80})
            if r2.fun < f_best or smooth_time_s < SMOOTH_MIN_S:
                k_best, st_best, f_best = float(r2.x[0] * sc[0]), float(r2.x[1] * sc[1]), float(r2.fun)
        ks[i], sts[i], rms[i] = k_best, st_best, f_best
        if on_draw is not None:
            on_draw()
    return {"k_s": ks, "smooth_time_s": sts, "rms_mm": rms}


# ----------------------------------------------------------------------------------------
# the whole comparison, as `calib export` shows it

#: what :func:`standard_reference` prints, in one line for the user
STANDARD_MIX = "the standard move mix (4 L-shaped lines, 25-150 mm/s)"


def envelope_sets(doc) -> list:
    """[(name, draws)] of fit.json's ``envelope_samples`` whose rows are laid out as its
    ``samples`` (older fits have none)."""
    k = len(doc.get("param_names") or [])
    out = []
    for name, E in (doc.get("envelope_samples") or {}).items():
        E = np.asarray(E, float)
        if E.ndim == 2 and E.shape[0] > 0 and E.shape[1] == k:
            out.append((name, E))
    return out


def envelope_draw_count(doc) -> int:
    """How many envelope draws :func:`match_firmware` simulates besides the posterior's."""
    return sum(min(ENVELOPE_MATCH_DRAWS, len(E)) for _, E in envelope_sets(doc))


def summarize_draws(x) -> dict:
    """median and 95 % interval (2.5-97.5 % quantiles) of per-draw values."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"median": math.nan, "ci95": [math.nan, math.nan]}
    q = np.quantile(x, [0.025, 0.5, 0.975])
    return {"median": float(q[1]), "ci95": [float(q[0]), float(q[2])]}


@dataclass
class MatchResult:
    """What :func:`match_firmware` found (lengths mm, times s, width errors um).

    k_s, smooth_time_s   the exported linear setting: median over draws of the per-draw
                         optimum, with its 95 % interval (``optimised`` False: tau, the
                         exact answer for linear physics, and the firmware's smooth time)
    rms_opt_um           RMS width error over all stations at each draw's own optimum
    rows                 label -> class -> {"median", "ci95"} (um) of each compared
                         setting, evaluated on every draw
    flow_reference_mm3_s, flow_tested_mm3_s   (lo, hi) of each; tested None if unknown
    """

    reference: str
    optimised: bool
    k_s: dict
    smooth_time_s: dict
    smooth_free: bool
    rms_opt_um: dict
    rows: dict
    settings: list
    n_draws: int
    flow_reference_mm3_s: tuple
    flow_tested_mm3_s: tuple | None
    notes: list = field(default_factory=list)
    #: draws whose width-optimal K lies at the search's limit K_LIMIT_S (not a measurement)
    n_at_limit: int = 0
    #: draws of the envelopes (fit.json ``envelope_samples``) the intervals also hold
    n_envelope_draws: int = 0

    @property
    def extrapolates(self) -> bool:
        return (self.flow_tested_mm3_s is not None
                and self.flow_reference_mm3_s[1] > EXTRAPOLATION_MARGIN * self.flow_tested_mm3_s[1])

    def extrapolation_warning(self) -> str | None:
        if self.flow_tested_mm3_s is None:
            return ("fit.json does not say which flows the test print covered (fitted by an older "
                    "calib); re-run `calib fit` to have the extrapolation checked")
        if not self.extrapolates:
            return None
        lo, hi = self.flow_tested_mm3_s
        return (f"the reference print reaches {self.flow_reference_mm3_s[1]:.1f} mm^3/s but the test "
                f"print covered {lo:.1f}-{hi:.1f} mm^3/s: the predicted widths above {hi:.1f} mm^3/s "
                f"extrapolate the fitted physics (and an adaptive table beyond its last row); print a "
                f"faster test before trusting them")

    def table_lines(self) -> list[str]:
        """The width-error table (um, median over draws) as text lines."""
        cols = ("starts", "stops", "corners", "steady", "all")
        wl = max(len(k) for k in self.rows) if self.rows else 10
        out = [f"{'predicted width error (um RMS)':<{wl}}  " + "  ".join(f"{c:>7}" for c in cols)]
        for label, r in self.rows.items():
            out.append(f"{label:<{wl}}  " + "  ".join(f"{r[c]['median']:7.1f}" for c in cols))
        return out

    def to_json(self) -> dict:
        return {"reference": self.reference, "optimised": self.optimised, "k_s": self.k_s,
                "smooth_time_s": self.smooth_time_s, "smooth_free": self.smooth_free,
                "rms_opt_um": self.rms_opt_um, "rows": self.rows, "n_draws": self.n_draws,
                "flow_reference_mm3_s": list(self.flow_reference_mm3_s),
                "flow_tested_mm3_s": None if self.flow_tested_mm3_s is None else list(self.flow_tested_mm3_s),
                "extrapolates": self.extrapolates, "notes": self.notes}


def tested_flow_of(doc) -> tuple | None:
    """(lo, hi) mm^3/s the fit's test print covered: ``derived.tested_flow_mm3_s`` (written
    by `calib fit`), else the range of a nonlinear fit's pa_vs_flow table, else None."""
    d = doc.get("derived") or {}
    t = d.get("tested_flow_mm3_s")
    if t and "hi" in t:
        return float(t["lo"]), float(t["hi"])
    pv = d.get("pa_vs_flow")
    if pv and pv.get("flow_mm3_s"):
        return 0.0, float(pv["flow_mm3_s"][-1])
    return None


def match_firmware(doc, ref: Reference, *, smooth_time_s: float = 0.0, smooth_free: bool = False,
                   kalico_smooth_time_s: float = KLIPPER_SMOOTH_TIME_S,
                   table_smooth_time_s: float = 0.0, n_draws: int = 64, seed: int = 0,
                   physics: Physics | None = None, on_draw=None,
                   envelopes: bool = True) -> MatchResult:
    """Simulate ``ref`` with the fit's dynamics (``n_draws`` posterior draws) under: no PA;
    linear PA at tau; the width-optimal linear PA (per draw, exported as the median with a
    95 % interval; Klipper: with the smooth time free when ``smooth_free``); the fit's
    Kalico tanh / recipr match and Orca adaptive table (fit.json ``derived``, when the fit
    has a nonlinear term). For dynamics that are linear PA alone (pa, pa_ve) the optimum
    is tau (exact cancellation, module docstring) and is not searched: the export keeps
    tau and the firmware's smooth time. With ``envelopes``, the 95 % intervals of K and
    the smooth time are hulled with those over each envelope's draws in fit.json
    (``envelope_samples``: the width offset's doubt, the short-wobble noise model), the
    median staying the posterior's; their draws at the search's limit count in n_at_limit.
    """
    phys = physics or physics_from_fit(doc, n_draws=n_draws, seed=seed)
    n = len(phys.theta)
    notes = []
    if phys.dropped:
        notes.append(f"simulated without {', '.join(phys.dropped)} (not extrusion dynamics PA acts on)")
    tau = phys.tau_s
    st_fixed = 0.0 if smooth_time_s is None else float(smooth_time_s)
    if phys.linear and tau is not None:
        opt = {"k_s": np.asarray(tau, float), "smooth_time_s": np.full(n, st_fixed), "rms_mm": None}
        optimised = False
    else:
        opt = optimal_linear(phys, ref, smooth_time_s=st_fixed, free_smooth=smooth_free,
                             on_draw=on_draw)
        optimised = True
    n_lim = int(np.sum(opt["k_s"] >= (1.0 - EDGE_FRACTION) * K_LIMIT_S)) if optimised else 0
    n_env = 0
    k_sum, st_sum = summarize_draws(opt["k_s"]), summarize_draws(opt["smooth_time_s"])
    if envelopes:
        # The posterior's interval alone holds neither doubt `calib fit` widens its own
        # intervals by: the demo's export read K 0.8862-0.8881 s where the fit's firmware K
        # (the same match, no smoothing) read 0.8592-0.8691 with them.
        for name, E in envelope_sets(doc):
            ph = physics_from_fit({**doc, "samples": E}, n_draws=ENVELOPE_MATCH_DRAWS, seed=seed)
            if phys.linear and ph.tau_s is not None:
                ks, sts = np.asarray(ph.tau_s, float), np.full(len(ph.theta), st_fixed)
            else:
                o = optimal_linear(ph, ref, smooth_time_s=st_fixed, free_smooth=smooth_free,
                                   on_draw=on_draw)
                ks, sts = o["k_s"], o["smooth_time_s"]
                n_lim += int(np.sum(ks >= (1.0 - EDGE_FRACTION) * K_LIMIT_S))
            k_sum["ci95"] = _hull(k_sum["ci95"], summarize_draws(ks)["ci95"])
            st_sum["ci95"] = _hull(st_sum["ci95"], summarize_draws(sts)["ci95"])
            n_env += len(ks)
            notes.append(f"the 95 % interval of K holds {ENVELOPE_WORDS.get(name, name)} "
                         f"({len(ks)} draws), as `calib fit`'s intervals do")
    if n_lim:
        notes.append(f"the width-optimal K of {n_lim} of {n + n_env} draws lies at the search's limit "
                     f"({K_LIMIT_S:g} s): the fitted physics wants more advance than any printer "
                     f"takes, so the value is not a measurement; do not paste it, check the fit "
                     f"with `calib diagnose`")
    k_exp = k_sum["median"]
    st_exp = st_sum["median"] if optimised and smooth_free else st_fixed
    settings = [Setting("none")]
    labels = ["no PA"]
    if tau is not None and optimised:
        settings.append(Setting("linear", float(np.median(tau)), st_fixed))
        labels.append(f"linear PA = tau {np.median(tau):.4f} s"
                      + (f", smooth {st_fixed:.3f} s" if st_fixed > 0 else ""))
    settings.append(Setting("linear", k_exp, st_exp))
    labels.append(f"linear PA {k_exp:.4f} s" + (f", smooth {st_exp:.3f} s" if st_exp > 0 else "")
                  + (" (exported)" if optimised else " (= tau, exported)"))
    d = doc.get("derived") or {}
    for kind in ("tanh", "recipr"):
        km = d.get(f"kalico_{kind}")
        if km:
            settings.append(Setting(kind, float(km["pressure_advance_s"]["median"]), kalico_smooth_time_s,
                                    float(km["offset_mm"]["median"]),
                                    max(float(km["linearization_velocity_mm_s"]["median"]), 1e-4)))
            labels.append(f"Kalico {kind}" + (f", smooth {kalico_smooth_time_s:.3f} s"
                                               if kalico_smooth_time_s > 0 else ""))
    pv = d.get("pa_vs_flow")
    if pv and pv.get("flow_mm3_s"):
        fq = [float(x) for x in pv["flow_mm3_s"]][:N_TABLE]
        kk = [float(x) for x in pv["pa_s_median"]][:N_TABLE]
        settings.append(Setting("table", smooth_time_s=table_smooth_time_s,
                                table_flow_mm3_s=tuple(fq), table_k_s=tuple(kk)))
        labels.append("Orca adaptive table" + (f", smooth {table_smooth_time_s:.3f} s"
                                               if table_smooth_time_s > 0 else ""))
    errs = width_errors_mm(phys, ref, _theta_for(phys, settings))
    rows = {}
    for i, lab in enumerate(labels):
        rows[lab] = {c: summarize_draws(1e3 * errs[c][i * n:(i + 1) * n]) for c in CLASSES}
    exp_label = labels[settings.index(next(s for s in settings[1:] if s.kind == "linear"
                                           and s.k_s == k_exp))]
    rms_opt = (summarize_draws(1e3 * opt["rms_mm"]) if opt["rms_mm"] is not None
               else rows[exp_label]["all"])
    return MatchResult(reference=ref.description, optimised=optimised, k_s=k_sum,
                       smooth_time_s=st_sum if (optimised and smooth_free) else
                       {"median": st_fixed, "ci95": [st_fixed, st_fixed]},
                       smooth_free=bool(optimised and smooth_free), rms_opt_um=rms_opt, rows=rows,
                       settings=settings, n_draws=n, flow_reference_mm3_s=ref.flow_mm3_s,
                       flow_tested_mm3_s=tested_flow_of(doc), notes=notes, n_at_limit=n_lim,
                       n_envelope_draws=n_env)


def fit_linear_k(doc, n_draws: int = 64) -> MatchResult | None:
    """The linear K that prints the standard move mix best with the fit's dynamics, no
    firmware smoothing (Marlin LA, RRF): what `calib fit` gives as its firmware line when
    the dynamics are more than linear PA. None when they are linear PA (tau then cancels
    them exactly) or hold nothing to simulate; UserError when they are more than linear PA
    and the move mix cannot be planned (a printer profile without the planner's limits).

    Why not tau: with a nonlinear term tau is only the linear part of the advance. A
    foreign Bowden print fitted as pa+kalico_recip read tau 0.036 s [0.028, 0.046] while the
    linear K that printed the move mix best on that printer was 0.201 s (bench_export_foreign);
    `calib fit` had printed the 0.036 as "SET_PRESSURE_ADVANCE ADVANCE=0.0360", trusted."""
    from patterns.profile import profile_from_dict

    try:
        phys = physics_from_fit(doc, n_draws=n_draws)
    except UserError:
        return None
    if phys.linear:
        return None
    prof = profile_from_dict(dict(doc.get("profile") or {}), source="fit.json profile")
    return match_firmware(doc, prepare_reference(standard_reference(prof), STANDARD_MIX),
                          smooth_time_s=0.0, physics=phys)
