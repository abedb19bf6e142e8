"""The library of composable extrusion effects.

An :class:`Effect` is a small object: ``name``, ``params`` (tuple of :class:`Param`), a
docstring with its equation and source, and the stage(s) it acts in:

* ``command(ctx, ve, p) -> ve``  transforms the commanded extruder velocity per timeline
  interval, ve (n_sets, n_int) mm/s (firmware PA, backlash, flow gain, user effects).
* nozzle terms (built-ins only): ``nozzle(p, coef)`` writes columns of the compiled
  kernel's coefficient array (fit/kernels.py): pa, nonlinear, bernoulli, backpressure,
  offset, kalico_tanh, kalico_recip, thermal.
* ``height(ctx, h, p) -> h``     layer height (mm) at the stations (bed tilt).
* ``width(ctx, w, p) -> w``      width (mm) at the stations (heading-dependent width).

``p`` maps the effect's *local* parameter names (``tau_s``) to arrays of shape
(n_sets, 1). State P (mm of filament stored as compression, seed 001 ``pe``) obeys
dP/dt = ve - vn, with vn solving P = Preq(vn) (see fit/kernels.py for the full Preq).

Every parameter's bounds include "effect absent" (amplitude 0, gain 1) so any effect
can be added to any model and fitted (compare / diagnose).

User effects: a Python file defining subclasses of :class:`Effect` with ``command``,
``height`` or ``width`` in numpy, loaded with :func:`load_effects_file`.
"""
from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np

from calib.errors import UserError
from fit import kernels as K
from fit.params import Param

REGISTRY: dict[str, type] = {}


def _check_effect_class(cls, where: str) -> None:
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise UserError(f"{where}: {cls!r} is not a subclass of fit.effects.Effect")
    if not isinstance(cls.name, str) or not cls.name.isidentifier():
        raise UserError(f"{where}: effect class {cls.__name__} needs a `name` that is an identifier")
    if not all(isinstance(p, Param) for p in cls.params):
        raise UserError(f"{where}: effect {cls.name}: `params` must be a tuple of fit.params.Param")
    if not cls.stages():
        raise UserError(f"{where}: effect {cls.name} defines none of command(), height(), width()")


def register_effect(cls):
    """Class decorator: add an Effect subclass to :data:`REGISTRY` under ``cls.name``."""
    _check_effect_class(cls, where="register_effect")
    REGISTRY[cls.name] = cls
    return cls


class Effect:
    """Base class. Subclasses set ``name``, ``params`` and implement one or more stages."""

    name: str = ""
    params: tuple[Param, ...] = ()
    #: True for the built-in nozzle terms read by the compiled kernel.
    nozzle_term: bool = False

    def __init__(self, profile: dict | None = None):
        self.profile = dict(profile or {})

    def __repr__(self) -> str:
        return f"<effect {self.name}>"

    @classmethod
    def stages(cls) -> tuple[str, ...]:
        out = tuple(s for s in ("command", "height", "width") if callable(getattr(cls, s, None)))
        return (("nozzle",) if cls.nozzle_term else ()) + out


# -----------------------------------------------------------------------------------
# Seed 000 conversion between KISSlicer's viscoelasticity VE and the time constant tau.

def tau_from_ve_s(ve_us, D_mm, L_mm, l_mm, d_mm):
    """Spring/nozzle time constant tau (s) from KISSlicer's VE (us), seed 000:

        tau = 32 * D^2 * L * l / d^4 * VE

    D filament diameter, L Bowden length, l nozzle land length, d nozzle diameter (mm).
    (Hookean spring k = E Af / L against Poiseuille flow through the land: VE = mu / E.)
    D=2.85, L=150, l=0.6, d=0.4 mm, VE=0.65 us gives tau = 0.594 s (seed 000: ~0.6 s).
    """
    return 32.0 * np.asarray(D_mm, float) ** 2 * L_mm * l_mm / np.asarray(d_mm, float) ** 4 \
        * np.asarray(ve_us, float) * 1e-6


def ve_from_tau_us(tau_s, D_mm, L_mm, l_mm, d_mm):
    """Inverse of :func:`tau_from_ve_s`: VE (us) = tau * d^4 / (32 D^2 L l) * 1e6."""
    return np.asarray(tau_s, float) * np.asarray(d_mm, float) ** 4 / (
        32.0 * np.asarray(D_mm, float) ** 2 * L_mm * l_mm) * 1e6


# -----------------------------------------------------------------------------------
# Nozzle terms (compiled kernel)

@register_effect
class PA(Effect):
    """Linear pressure advance (seed 001 "Linear Advance" Kf; seed 000 tau).

    Filament + Bowden is a spring, the nozzle a linear resistance:
        dP/dt = ve - vn,   vn = P / tau   (Preq = tau * vn)
    A flow step relaxes as exp(-t/tau). Direct drive ~0.02-0.08 s, long Bowden ~1 s.
    """

    name = "pa"
    nozzle_term = True
    params = (Param("tau_s", "s", 0.5, 0.005, 5.0, "loguniform",
                    doc="spring/nozzle time constant (= ideal firmware PA K)"),)

    def nozzle(self, p, coef):
        coef[:, K.C_TAU] = p["tau_s"][:, 0]


@register_effect
class PAVE(Effect):
    """Linear pressure advance parameterised by KISSlicer's viscoelasticity VE (seed 000).

        tau = 32 * D^2 * L * l / d^4 * VE      (profile: filament D, Bowden L,
                                                nozzle land l, nozzle bore d, all mm)
    then as ``pa``: Preq = tau * vn. Needs a Bowden printer profile (L > 0).
    """

    name = "pa_ve"
    nozzle_term = True
    params = (Param("ve_us", "us", 0.65, 0.01, 20.0, "loguniform",
                    doc="viscoelasticity mu/E of the filament (ABS ~0.65 us)"),)

    def __init__(self, profile=None):
        super().__init__(profile)
        try:
            self.geom = tuple(float(self.profile[k]) for k in (
                "filament_diameter_mm", "bowden_length_mm", "nozzle_land_length_mm",
                "nozzle_diameter_mm"))
        except (KeyError, TypeError, ValueError):
            raise UserError("effect pa_ve needs a printer profile with filament_diameter_mm, "
                            "bowden_length_mm, nozzle_land_length_mm and nozzle_diameter_mm") from None
        if self.geom[1] <= 0 or self.geom[2] <= 0:
            raise UserError("effect pa_ve needs bowden_length_mm > 0 and nozzle_land_length_mm > 0; "
                            "use `pa` (tau_s) for a direct drive")

    def nozzle(self, p, coef):
        coef[:, K.C_TAU] = tau_from_ve_s(p["ve_us"][:, 0], *self.geom)


@register_effect
class Nonlinear(Effect):
    """Power-law (shear-thinning) nozzle: the pa term becomes

        Preq_pa = (tau / n) * v_ref * (vn / v_ref)^n       (q ~ P^(1/n))

    n = 1 is linear pa (effect absent); melts have n ~0.3-0.5 (REFERENCE "Shear
    thinning"), so steady advance grows like v^n and the local time constant
    dPreq/dvn = tau * (vn/v_ref)^(n-1) falls with flow. tau is the time constant at
    v_ref = 1 mm/s of filament (fixed; ~2.4 mm^3/s of 1.75 mm filament, a typical
    printing flow), so pa.tau_s keeps its meaning (the linear pressure advance at that
    flow) whatever n is. Written as tau * v_ref * (vn/v_ref)^n instead, tau and n
    trade off along a curved ridge (the data fix tau * n), which samples ~10x slower.

    Firmware nonlinear PA maps onto steady-state Preq terms: Kalico's
    advance = LA*v + off*tanh(v/v_lin) is exactly Preq(vn) = LA*vn + off*tanh(vn/v_lin)
    (pa + ``kalico_tanh``), and its "recipr" model off*(1 - 1/(1 + v/v_lin)) is
    ``kalico_recip``. RRF's "advance ~ sqrt(v)" is this power law with n = 0.5.
    """

    name = "nonlinear"
    nozzle_term = True
    params = (Param("n", "1", 1.0, 0.2, 1.5, "uniform", doc="power-law index (1 = linear)"),
              Param("v_ref_mm_s", "mm/s", 1.0, 0.01, 100.0, "loguniform", fixed=True,
                    doc="reference filament speed of the power law"))

    def nozzle(self, p, coef):
        coef[:, K.C_N] = p["n"][:, 0]
        coef[:, K.C_VREF] = p["v_ref_mm_s"][:, 0]


@register_effect
class Bernoulli(Effect):
    """Bernoulli (orifice) advance, seed 002: advance volume = k * q^2, q in mm^3/s.

        Preq_b = k * q^2 / Af = k * Af * vn^2     (mm of filament; k in s^2/mm^3)

    Seed 002 uses k ~ 0.02 (0.1 from auto-priming numbers). k = 0: absent.
    """

    name = "bernoulli"
    nozzle_term = True
    params = (Param("k_s2_mm3", "s^2/mm^3", 0.02, 0.0, 0.5, "uniform",
                    doc="advance volume per squared volumetric flow"),)

    def nozzle(self, p, coef):
        coef[:, K.C_KBERN] = p["k_s2_mm3"][:, 0]


@register_effect
class Backpressure(Effect):
    """Bead back-pressure, seed 001 "Print Layer BackPressure": Pb = Kb * Db, Db = r*w.

    The bead being laid (width w = bead_width_mm(Af*vn/v_head, h)) pushes back on the
    nozzle. Later tests (realdata AUTHOR-NOTES, REFERENCE) show it flattens above ~0.8 mm
    for a 0.4 mm nozzle, so it saturates:

        Pb = Kb * w_sat * tanh(w / w_sat)        (mm of filament)

    Stopped on the track (v_head = 0) the bead is "infinitely wide": Pb = Kb * w_sat,
    a threshold the pressure must exceed before any flow. Off-track (travel): Pb = 0.
    At steady state it acts as a width-dependent offset Cf = Kb*Db (seed 001).
    """

    name = "backpressure"
    nozzle_term = True
    params = (Param("kb", "mm/mm", 1.0, 0.0, 5.0, "uniform",
                    doc="back-pressure per mm of bead width (seed 001 Kb)"),
              Param("w_sat_mm", "mm", 0.8, 0.2, 3.0, "uniform",
                    doc="bead width where back-pressure saturates (~2x nozzle)"))

    def nozzle(self, p, coef):
        coef[:, K.C_KB] = p["kb"][:, 0]
        coef[:, K.C_WSAT] = p["w_sat_mm"][:, 0]


@register_effect
class Offset(Effect):
    """Constant offset pressure Kc (mm of filament) that must be exceeded before any
    flow (seed 001 Kc): Preq = Kc + ... for vn > 0. Kc = 0: absent."""

    name = "offset"
    nozzle_term = True
    params = (Param("kc_mm", "mm", 0.2, 0.0, 3.0, "uniform", doc="flow threshold pressure"),)

    def nozzle(self, p, coef):
        coef[:, K.C_KC] = p["kc_mm"][:, 0]


@register_effect
class KalicoTanh(Effect):
    """Kalico ``pressure_advance_model: tanh`` read as a steady-state Preq term
    (REFERENCE "Nonlinear PA in the wild"):

        Preq += off * tanh(vn / v_lin)      (mm; vn mm/s of filament)

    Example (direct drive PLA): LA = pa.tau_s = 0.017 s, off = 0.12 mm, v_lin = 1 mm/s.
    off = 0: absent.
    """

    name = "kalico_tanh"
    nozzle_term = True
    params = (Param("off_mm", "mm", 0.1, 0.0, 3.0, "uniform", doc="saturating advance offset"),
              Param("v_lin_mm_s", "mm/s", 1.0, 0.02, 20.0, "loguniform",
                    doc="filament speed where the offset saturates"))

    def nozzle(self, p, coef):
        coef[:, K.C_TOFF] = p["off_mm"][:, 0]
        coef[:, K.C_TVL] = p["v_lin_mm_s"][:, 0]


@register_effect
class KalicoRecip(Effect):
    """Kalico ``pressure_advance_model: recipr`` as a Preq term (REFERENCE):

        Preq += off * (1 - 1/(1 + vn/v_lin)) = off * vn / (vn + v_lin)     (mm)
    """

    name = "kalico_recip"
    nozzle_term = True
    params = (Param("off_mm", "mm", 0.1, 0.0, 3.0, "uniform", doc="saturating advance offset"),
              Param("v_lin_mm_s", "mm/s", 1.0, 0.02, 20.0, "loguniform",
                    doc="filament speed of half saturation"))

    def nozzle(self, p, coef):
        coef[:, K.C_ROFF] = p["off_mm"][:, 0]
        coef[:, K.C_RVL] = p["v_lin_mm_s"][:, 0]


@register_effect
class Thermal(Effect):
    """Thermal ooze, seed 000: a second, slower exponential process.

        dX/dt = (vn - X) / tau_th          (X: recent outflow, mm/s)
        dP/dt = ve - vn + a * (X - vn)     (thermal expansion source)

    At steady state X = vn and nothing changes; after a stop from flow v0 an extra ooze
    ~ a * v0 * exp(-t / tau_th) lasts tens of seconds (seed 000: starts 10-30x smaller
    than the elastic ooze). The net volume over a start-stop cycle is zero
    (integral of a*(X - vn) dt = -a*tau_th*dX). a = 0: absent.
    """

    name = "thermal"
    nozzle_term = True
    params = (Param("a", "1", 0.05, 0.0, 1.0, "uniform", doc="thermal ooze amplitude"),
              Param("tau_s", "s", 20.0, 1.0, 300.0, "loguniform", doc="thermal time constant"))

    def nozzle(self, p, coef):
        coef[:, K.C_ATH] = p["a"][:, 0]
        coef[:, K.C_TAUTH] = p["tau_s"][:, 0]


# -----------------------------------------------------------------------------------
# Command-stage effects

@register_effect
class FirmwarePA(Effect):
    """The firmware's own pressure advance, applied to the command (a known input).

    Klipper: pa_pos = pos + K * vel * f, smoothed by a triangular window of total width
    smooth_time (klippy/chelper/kin_extruder.c; REFERENCE: default 0.040 s); Marlin LA:
    pos + K * vel * f (smooth_time = 0). f is the per-move "can pressure advance" flag:
    Klipper (klippy/kinematics/extruder.py, ``process_move``/``move``) sets it only when
    ``axis_r > 0 and (move.axes_d[0] or move.axes_d[1])``, i.e. the move extrudes
    (positive E) while the head moves in XY; Marlin LA 1.5 (planner.cpp) sets
    ``use_advance_lead = esteps && K && de > 0`` on XY moves ("Extruder is running
    forward"). So retract / prime (E-only) moves and wipe-while-retracting moves get no
    advance; Klipper still smooths them when PA is on (the whole extruder position is
    averaged), and sets smooth_time to 0 when K = 0.

    Here f is 1 on timeline intervals with de > 0 and head speed > 1e-6 mm/s and 0
    elsewhere; the advance term at a node uses the planner's velocity there when either
    adjacent interval is a printing one (junctions of E-only moves with XY moves have
    zero extruder velocity in Klipper, so the choice only places a print-to-travel
    release of K * v within one interval).

    Both parameters are fixed by default; NaN means "take them from the manifest's
    pattern parameters" (``firmware_pa_s``, ``firmware_smooth_time_s``), so patterns
    printed with PA on are simulated right.
    """

    name = "firmware_pa"
    params = (Param("k_s", "s", float("nan"), 0.0, 2.0, "uniform", fixed=True,
                    doc="firmware PA constant K (NaN: from the manifest)"),
              Param("smooth_time_s", "s", float("nan"), 0.0, 0.2, "uniform", fixed=True,
                    doc="firmware PA smoothing window (NaN: from the manifest)"))

    def command(self, ctx, ve, p):
        k = _nan_to(p["k_s"], ctx.firmware_pa_s)
        st = _nan_to(p["smooth_time_s"], ctx.firmware_smooth_time_s)
        if not np.any(k):
            return ve
        e = ctx.e_mm
        v_pa = _pa_velocity(ctx)
        out = np.empty_like(ve)
        for st_val in np.unique(st):
            rows = (st == st_val)[:, 0]
            se = _smoothed(ctx, "e", e, float(st_val))
            sv = _smoothed(ctx, "v_pa", v_pa, float(st_val))
            # firmware extruder position at the nodes; the first and last node keep the raw
            # position so the motion the window spreads beyond the timeline's ends is
            # lumped into the first/last interval (commanded volume conserved)
            pos = se[None, :] + k[rows] * sv[None, :]
            pos[:, 0] = e[0] + k[rows, 0] * v_pa[0]
            pos[:, -1] = e[-1] + k[rows, 0] * v_pa[-1]
            out[rows] = ve[rows] - np.diff(e) / ctx.dt_s + np.diff(pos, axis=1) / ctx.dt_s
        return out


def pa_intervals(ctx) -> np.ndarray:
    """Timeline intervals where firmware applies pressure advance (bool, n_int): the
    extruder moves forward while the head moves in XY (Klipper ``can_pressure_advance``,
    Marlin ``use_advance_lead``; see :class:`FirmwarePA`)."""
    return (np.asarray(ctx.de_mm) > 0.0) & (np.asarray(ctx.v_head_mm_s) > 1e-6)


def _pa_velocity(ctx) -> np.ndarray:
    """Extruder velocity at the nodes that firmware PA multiplies by K: the planner's node
    velocity where an adjacent interval is a printing move, 0 inside E-only / travel runs."""
    ck = ("fw_pa_velocity",)
    if ck in ctx.cache:
        return ctx.cache[ck]
    f = pa_intervals(ctx)
    node = np.zeros(len(f) + 1, dtype=bool)
    node[:-1] |= f
    node[1:] |= f
    res = np.where(node, np.asarray(ctx.ve_node_mm_s, float), 0.0)
    ctx.cache[ck] = res
    return res


def _nan_to(arr, value):
    a = np.asarray(arr, float)
    return np.where(np.isfinite(a), a, value)


def triangular_smooth(t_s, f, smooth_s: float) -> np.ndarray:
    """f(t) convolved with Klipper's pressure-advance smoothing window: a triangle of
    total width smooth_s (s), i.e. two boxes of smooth_s/2, on a <= 0.5 ms grid."""
    if smooth_s <= 0:
        return np.asarray(f, float)
    t = np.asarray(t_s, float)
    step = min(5e-4, smooth_s / 20)
    grid = np.arange(t[0] - smooth_s, t[-1] + smooth_s + step, step)
    g = np.interp(grid, t, f)
    nb = max(int(round(0.5 * smooth_s / step)), 1)
    box = np.ones(nb) / nb
    g = np.convolve(np.convolve(g, box, mode="same"), box, mode="same")
    return np.interp(t, grid, g)


def _smoothed(ctx, key, f, smooth_s):
    """:func:`triangular_smooth` of f at the timeline nodes, cached in ctx."""
    ck = ("fw_smooth", key, smooth_s)
    if ck not in ctx.cache:
        ctx.cache[ck] = triangular_smooth(ctx.t_s, f, smooth_s)
    return ctx.cache[ck]


@register_effect
class Backlash(Effect):
    """Extruder dead band Be (mm) on direction reversal (seed 001 logs: Be ~0.4-1.2 mm).

    A play operator on the cumulative commanded E:
        y_k = max(e_k - Be, min(y_{k-1}, e_k))
    after a retraction the filament does not move until the gear has taken up Be.
    Be = 0: absent.
    """

    name = "backlash"
    params = (Param("be_mm", "mm", 0.0, 0.0, 3.0, "uniform", doc="dead band on reversal"),)

    def command(self, ctx, ve, p):
        be = np.broadcast_to(p["be_mm"][:, 0], (ve.shape[0],)).astype(float)
        if not np.any(be):
            return ve
        e = np.concatenate([np.zeros((ve.shape[0], 1)), np.cumsum(ve * ctx.dt_s, axis=1)], axis=1)
        y = np.empty_like(e)
        K.play_operator(e, np.ascontiguousarray(be), y)
        return np.diff(y, axis=1) / ctx.dt_s


@register_effect
class FlowGain(Effect):
    """Static flow gain g: extruded = g * commanded (extrusion multiplier, filament
    diameter error: g = (D_true/D_assumed)^2, e-steps). g = 1: absent."""

    name = "flow_gain"
    params = (Param("gain", "1", 1.0, 0.7, 1.3, "uniform", doc="extrusion multiplier error"),)

    def command(self, ctx, ve, p):
        return ve * p["gain"]


# -----------------------------------------------------------------------------------
# Station-stage nuisances

@register_effect
class BedTilt(Effect):
    """Layer height varying as a plane over the bed (bed tilt / mesh error):

        h = h0 + gx * (x - xc) + gy * (y - yc)       (xc, yc: centre of the stations)

    The deposited area is unchanged, so the width follows from the same area at the new
    height (width ~ 1/h, REFERENCE "Width from flow"). gx = gy = 0: absent.
    """

    name = "bed_tilt"
    params = (Param("gx", "mm/mm", 0.0, -0.005, 0.005, "uniform", doc="height slope along x"),
              Param("gy", "mm/mm", 0.0, -0.005, 0.005, "uniform", doc="height slope along y"))

    def height(self, ctx, h, p):
        xc, yc = ctx.center_xy_mm
        return h + p["gx"] * (ctx.s_x_mm - xc) + p["gy"] * (ctx.s_y_mm - yc)


@register_effect
class BedMesh(Effect):
    """Layer height over a bed that is not flat: a 3 x 3 grid of height offsets over the
    stations' extent, interpolated bilinearly between its nodes (as Marlin's
    AUTO_BED_LEVELING_BILINEAR applies a probed 3 x 3 grid):

        h = h0 + sum_ij dz_ij * B_i(x) * B_j(y)

    B: the piecewise-linear hat functions of the nodes at the lowest, middle and highest
    station x (resp. y). A warped, domed or bowl-shaped bed (a heated plate bulges) that a
    plane (bed_tilt) cannot follow; the width follows from the same area at the new height,
    as for bed_tilt. Nine parameters: in `calib diagnose` it must explain far more than a
    plane to be named over it. dz = 0: absent.
    """

    name = "bed_mesh"
    params = tuple(Param(f"dz{i}{j}_mm", "mm", 0.0, -0.1, 0.1, "uniform",
                         doc=f"height offset at grid node x{i} y{j} (0: lowest station x/y, 2: highest)")
                   for j in range(3) for i in range(3))

    def height(self, ctx, h, p):
        if "bed_mesh_basis" not in ctx.cache:
            def hats(v):
                lo, hi = float(np.min(v)), float(np.max(v))
                u = np.clip((v - lo) / max(hi - lo, 1e-9) * 2.0, 0.0, 2.0)
                return np.stack([np.clip(1.0 - np.abs(u - k), 0.0, 1.0) for k in range(3)], axis=1)
            bx, by = hats(ctx.s_x_mm), hats(ctx.s_y_mm)
            ctx.cache["bed_mesh_basis"] = np.einsum("si,sj->sji", bx, by).reshape(len(bx), 9)
        dz = np.concatenate([p[q.name] for q in self.params], axis=1)      # (n_sets, 9)
        return h + dz @ ctx.cache["bed_mesh_basis"].T


@register_effect
class Spread(Effect):
    """The bead smooths its own width along the track (surface tension rounds what the
    nozzle lays, the nozzle's flat land irons it):

        w_seen(s) = sum_j g(s_j - s) w(s_j) / sum_j g(s_j - s),   g(d) = exp(-d^2 / (2 sigma^2))

    over the stations s_j of the same track within 4 sigma (mm). The deposit model
    (fit/context.py) already averages the flow over one nozzle diameter; this is the
    spreading beyond it, which shows where the width changes fast (the first 1-2 mm
    after a flow step): the measured width leads the laid one before a rise and lags it
    after. Found on realistic renders (bench_e2e): without it `pa` read tau 8-13 % high
    with a 90 % interval of +-2 %, because the whitened residual keeps exactly those
    stations; with it sigma ~0.18 mm and tau unbiased. sigma = 0: absent.
    """

    name = "spread"
    params = (Param("sigma_mm", "mm", 0.0, 0.0, 1.0, "uniform", doc="along-track smoothing sd of the bead"),)

    def width(self, ctx, w, p):
        from fit.kernels import kernel

        key = "spread_order"
        if key not in ctx.cache:
            order = np.lexsort((ctx.s_mm, ctx.s_track)).astype(np.int64)
            tr = ctx.s_track[order]
            starts = np.flatnonzero(np.r_[True, tr[1:] != tr[:-1], True]).astype(np.int64)
            ctx.cache[key] = (order, starts, np.ascontiguousarray(ctx.s_mm, dtype=float))
        order, starts, s = ctx.cache[key]
        sig = np.asarray(p["sigma_mm"], dtype=float).reshape(-1)
        w2 = np.atleast_2d(np.asarray(w, dtype=float))
        n_sets = max(w2.shape[0], len(sig))
        w2 = np.ascontiguousarray(np.broadcast_to(w2, (n_sets, len(s))))
        sig = np.ascontiguousarray(np.broadcast_to(sig, (n_sets,)))
        out = np.empty_like(w2)
        kernel("spread", w2.shape[0])(w2, order, s, starts, sig, out)
        return out


@register_effect
class Heading(Effect):
    """Width depending on the direction of travel theta (Duet3D spiral, seed 004):

        w = w0 + a * cos(theta) + b * sin(theta)     (mm)

    e.g. a nozzle wiping one side, a tilted nozzle, a fan from one side. a = b = 0: absent.
    """

    name = "heading"
    params = (Param("a_mm", "mm", 0.0, -0.2, 0.2, "uniform", doc="cos(heading) width term"),
              Param("b_mm", "mm", 0.0, -0.2, 0.2, "uniform", doc="sin(heading) width term"))

    def width(self, ctx, w, p):
        th = ctx.s_heading_rad
        return w + p["a_mm"] * np.cos(th) + p["b_mm"] * np.sin(th)


@register_effect
class ScanBias(Effect):
    """Calibration error of the width measurement itself, not of the printer:

        w_measured = w + b0 + b1 * (w - w_ref)      (mm), w_ref = 0.5 mm

    b0: an offset (edge threshold against the plate, blur, translucent edges); b1: a
    relative error growing with width (scan scale, dpi, registration scale, edge bias
    that depends on the bead's profile). The measure bench sees ~1 um of width-dependent
    bias on a flatbed, more on phone photos and real plastics; with thousands of
    samples that is several posterior sd of a back-pressure or thermal parameter, so a
    fit that should not trust the scan's absolute scale adds this effect and its
    intervals widen accordingly. Priors normal(0, 5 um) and normal(0, 0.02). A per-scan
    nuisance in joint fits. b0 = b1 = 0: absent. The bounds on b0 are far outside the
    priors: apparent widths of a realistic render read -48 um (bench_realism, flatbed,
    Bowden), and a bound at +-50 um stopped the fit there (-50.0 in 2 of 6 MAP fits), a
    posterior "against a bound" caused by the bound alone.
    """

    name = "scan_bias"
    W_REF_MM = 0.5
    params = (Param("b0_mm", "mm", 0.0, -0.3, 0.3, ("normal", 0.0, 0.005),
                    doc="measured minus true width at w_ref"),
              Param("b1", "1", 0.0, -0.2, 0.2, ("normal", 0.0, 0.02),
                    doc="relative width scale error of the measurement"))

    def width(self, ctx, w, p):
        return w + p["b0_mm"] + p["b1"] * (w - self.W_REF_MM)


@register_effect
class ScanCurve(Effect):
    """The measurement's apparent width bent with the width, a measurement nuisance (never
    proposed by ``diagnose``; scan_bias holds the straight part):

        w_measured = w + c2 (w - w_ref)^2 + c3 (w - w_ref)^3        (mm, w_ref = 0.5 mm)

    A rounded, translucent bead's edge is read where its flank's shading crosses the
    plate's, a depth that depends on how high and how wide the bead is, so the apparent
    width is not a straight function of the true one. On the foreign printer's probe
    rendered on a 600 dpi flatbed with every phenomenon (bench_discover_foreign, a right
    `pa` print and a bowl-shaped bed, seeds 0-1) it gained 9-23 BIC over `pa+scan_bias`,
    with c2 -0.06 to -0.12 /mm and c3 0.07-0.14 /mm^2 on all four; on the right print it
    took all that `bed_mesh` had taken (Delta BIC 25 -> -1.9 after it), on the bowls not
    (96 -> 60, 33 -> 16). ``calib diagnose`` fits it beside a bed effect it names
    (fit/diagnose.py CURVE_TWINS). All zero: absent.
    """

    name = "scan_curve"
    W_REF_MM = 0.5
    params = (Param("c2_per_mm", "1/mm", 0.0, -2.0, 2.0, "uniform", doc="apparent width's quadratic term"),
              Param("c3_per_mm2", "1/mm^2", 0.0, -5.0, 5.0, "uniform", doc="apparent width's cubic term"))

    def width(self, ctx, w, p):
        d = w - self.W_REF_MM
        return w + p["c2_per_mm"] * d * d + p["c3_per_mm2"] * d * d * d


def _bed_uv(ctx):
    """Station positions scaled to [-1, 1] about the stations' centre: (x - xc, y - yc) / R,
    R = half the larger extent of the stations (mm / mm)."""
    xc, yc = ctx.center_xy_mm
    dx, dy = ctx.s_x_mm - xc, ctx.s_y_mm - yc
    r = max(float(np.max(np.abs(dx), initial=0.0)), float(np.max(np.abs(dy), initial=0.0)), 1e-9)
    return dx / r, dy / r


@register_effect
class ViewXY(Effect):
    """The picture's apparent width varying over the bed, a measurement nuisance (not
    physics, never proposed by ``diagnose``): on a phone photo taken at an angle the
    resolution and the blur change across the picture, and with them the edge offset of a
    rounded, translucent bead:

        w_measured = w + ax u + ay v + axx u^2 + ayy v^2 + axy u v        (mm)

    u, v: :func:`_bed_uv`. The trust verdict's structure check (fit/nuisance.py) adds it
    to ask whether the values depend on a width pattern over x, y or r; all zero: absent.
    """

    name = "view_xy"
    params = tuple(Param(n, "mm", 0.0, -0.1, 0.1, "uniform", doc=f"apparent width term in {t}")
                   for n, t in (("ax_mm", "u"), ("ay_mm", "v"), ("axx_mm", "u^2"), ("ayy_mm", "v^2"),
                                ("axy_mm", "u v")))

    def width(self, ctx, w, p):
        u, v = _bed_uv(ctx)
        return (w + p["ax_mm"] * u + p["ay_mm"] * v + p["axx_mm"] * u * u + p["ayy_mm"] * v * v
                + p["axy_mm"] * u * v)


@register_effect
class ViewHeading(Effect):
    """The picture's apparent width depending on the bead's direction, a measurement
    nuisance (never proposed by ``diagnose``): a photo at an angle foreshortens one bed
    direction (blur and resolution differ along and across it: second harmonic of the
    heading theta), and light from one side shades one flank (first harmonic):

        w_measured = w + a1 cos(theta) + b1 sin(theta) + a2 cos(2 theta) + b2 sin(2 theta)   (mm)

    The physical ``heading`` effect has the first harmonic only. All zero: absent.
    """

    name = "view_heading"
    params = tuple(Param(n, "mm", 0.0, -0.1, 0.1, "uniform", doc=f"apparent width term in {t}")
                   for n, t in (("a1_mm", "cos theta"), ("b1_mm", "sin theta"), ("a2_mm", "cos 2 theta"),
                                ("b2_mm", "sin 2 theta")))

    def width(self, ctx, w, p):
        th = ctx.s_heading_rad
        return (w + p["a1_mm"] * np.cos(th) + p["b1_mm"] * np.sin(th) + p["a2_mm"] * np.cos(2 * th)
                + p["b2_mm"] * np.sin(2 * th))


@register_effect
class ViewGlare(Effect):
    """The picture's apparent width where the bead catches the light, a measurement
    nuisance (never proposed by ``diagnose``): glossy plastic reflects the light
    specularly off the flank whose normal halves the light and camera directions, so a
    streak lies along beads of one direction only (measure/phenomena.py ``glare``), and
    a streak on a flank moves the edge the width is read at. A bead printed either way
    along a line is the same cylinder to the light, so the pattern has period pi in the
    heading theta, one bump about the direction theta0 that catches the light:

        w_measured = w + A exp(kappa (cos 2 (theta - theta0) - 1))           (mm)

    (a von Mises bump on the doubled angle; kappa ~ 1 / (2 x its half width in rad)^2).
    Harmonics would need many terms for a bump this narrow: on a 35 deg phone render whose
    residuals followed heading (bench_e2e phone seed 10: two bumps +8 and +15 um, 170 deg
    apart, 20-30 deg wide) this form took Delta BIC 39 with 3 parameters, the heading's
    harmonics -7 with 2 (view_heading) and 30 with 4, and tau moved by 0.1 %. A = 0: absent.
    """

    name = "view_glare"
    params = (Param("amp_mm", "mm", 0.0, -0.1, 0.1, "uniform", doc="apparent width added at theta0"),
              Param("theta0_rad", "rad", 0.0, -0.5 * np.pi, 0.5 * np.pi, "uniform",
                    doc="bead direction (mod pi) that catches the light"),
              Param("kappa", "1", 2.0, 0.3, 50.0, "loguniform", doc="sharpness of the bump in heading"))

    def width(self, ctx, w, p):
        th = ctx.s_heading_rad
        return w + p["amp_mm"] * np.exp(p["kappa"] * (np.cos(2.0 * (th - p["theta0_rad"])) - 1.0))


def _station_column(ctx, attr: str, key: str, derive):
    """A per-station column the measurement gave the context (``s_blur_mm``, ``s_light_deg``;
    None when the widths table had none), transformed by ``derive`` once per context."""
    v = getattr(ctx, attr, None)
    if v is None:
        return None
    if key not in ctx.cache:
        ctx.cache[key] = derive(np.asarray(v, dtype=float))
    return ctx.cache[key]


def _about_median(s):
    """s minus its median over the finite values; 0 where s is not finite."""
    ok = np.isfinite(s)
    return np.where(ok, s - (np.median(s[ok]) if ok.any() else 0.0), 0.0)


@register_effect
class ViewBlur(Effect):
    """The picture's apparent width depending on the blur each width was read with, a
    measurement nuisance (never proposed by ``diagnose``). The edge-pair fit reads a
    rounded, translucent bead's edge where the blurred flank crosses half the contrast,
    and that point moves inwards as the blur grows; on a photo at an angle the blur across
    the bead changes with its place and its direction (foreshortening, depth of field):

        w_measured = w + k (s - s_med)                                          (mm)

    s: the station's edge blur (Gaussian sd across the track, mm; the widths CSV's
    ``blur_mm``), s_med its median over the scan; stations without a blur are left as
    they are. k (mm of width per mm of blur) is the offset's slope: -0.46 on a 12 MP
    phone render at 35 deg (blur 0.10-0.13 mm), where it explained 22 % of the width
    error's variance (the heading's two harmonics, 4 parameters: 26 %). k = 0: absent.
    """

    name = "view_blur"
    params = (Param("k", "mm/mm", 0.0, -3.0, 3.0, "uniform", doc="apparent width per mm of edge blur"),)

    def width(self, ctx, w, p):
        ds = _station_column(ctx, "s_blur_mm", "view_blur_ds", _about_median)
        return w if ds is None else w + p["k"] * ds


@register_effect
class ViewLight(Effect):
    """The picture's apparent width depending on the flank's angle to the scan's light, a
    measurement nuisance (never proposed by ``diagnose``): beads whose glossy flank faces the
    light read wider than beads that run along it, by a step rather than a smooth function
    of the heading, and one offset for all beads (``scan_bias``) cannot take it:

        w_measured = w + o_k   for a station whose angle a lies in band k = [15 k, 15 k + 15) deg,
                               k = 0..3; nothing for a >= 60 deg or unknown               (mm)

    a: the angle between the station's flank normal and the light's axis (deg, the widths
    CSV's ``light_angle_deg``, measure/glare.py; 0 = the flank faces the light). Measured on
    bench_e2e's back-pressure flatbed renders: beads whose flank faces the lamp read ~2.5 um
    wider than the rest and pulled Kb 7 % high (fit/influence.py). With this effect the MAP
    Kb moved 0.004 towards the truth on 7 of 7 seeds with the axis given (a heading-based
    prototype), and 0.0008 and 0.005 on seeds 0 and 1 with the measured axis (89.1 and 88.9
    deg, truth 90); on 40 seeds the posterior Kb fell on 39 (+6.7 % -> +4.9 % against the
    truth) and its 90 % coverage rose from 85 to 90 %. `--model auto` starts with it where
    the angle spans its bands (fit/measurement.py); the trust verdict's structure check asks
    it when the residuals follow the heading and the widths carry the angle
    (fit/nuisance.py), as the other view effects. Priors normal(0, 5 um). All zero: absent.
    """

    name = "view_light"
    BAND_DEG = 15.0
    params = tuple(Param(f"o{k}_mm", "mm", 0.0, -0.05, 0.05, ("normal", 0.0, 0.005),
                         doc=f"apparent width offset where the flank is {15 * k}-{15 * k + 15} deg from the light")
                   for k in range(4))

    def width(self, ctx, w, p):
        band = _station_column(ctx, "s_light_deg", "view_light_band",
                               lambda a: np.floor(np.nan_to_num(a, nan=99.0) / self.BAND_DEG))
        if band is None:
            return w
        out = w
        for k in range(4):
            out = out + p[f"o{k}_mm"] * (band == k)
        return out


def _track_coordinate(ctx):
    """One increasing coordinate for all stations, track after track: g = rank(track) K + s
    (mm; K longer than any track), sorted; each station's g and the g range of its track."""
    key = "track_coordinate"
    if key not in ctx.cache:
        s = np.asarray(ctx.s_mm, dtype=float)
        _, rank = np.unique(np.asarray(ctx.s_track), return_inverse=True)
        K = float(np.ptp(s)) + 10.0 if len(s) else 1.0
        g = rank * K + s
        order = np.argsort(g, kind="stable")
        gs = g[order]
        lo = np.full(rank.max() + 1 if len(s) else 0, np.inf)
        hi = np.full(len(lo), -np.inf)
        np.minimum.at(lo, rank, g)
        np.maximum.at(hi, rank, g)
        first = np.searchsorted(gs, lo[rank], side="left")
        last = np.searchsorted(gs, hi[rank], side="right") - 1
        ctx.cache[key] = (order, gs, g, lo[rank], hi[rank], first, last)
    return ctx.cache[key]


@register_effect
class ViewShift(Effect):
    """The picture's stations sitting off along their tracks, a measurement nuisance (never
    proposed by ``diagnose``): a pose held across the test lines but loosely along them (a
    markerless photo of lines that all run one way: `calib measure` prints its along-track
    sd) puts every station's bed point a shift d = (dx, dy) mm from where the bead it shows
    was laid, so the measured width is the laid width a little further along the track,

        w_measured(s) = w(s + dx cos theta + dy sin theta)                          (mm)

    theta: the station's heading; w between the track's own stations linearly interpolated,
    held at its first and last. One shift for all stations, not the per-station sd the
    measurement already widens each width by: on a print of one-way lines a shared shift
    moves every line's start alike, which the fit would otherwise read as a change of tau
    (0.33 mm on StartStopTestPLA1 is 3-16 ms at 20-100 mm/s). The prior is the
    measurement's along-track sd (fit/measurement.py); default normal(0, 0.05 mm). All
    zero: absent.
    """

    name = "view_shift"
    params = (Param("dx_mm", "mm", 0.0, -3.0, 3.0, ("normal", 0.0, 0.05), doc="stations' shift along bed x"),
              Param("dy_mm", "mm", 0.0, -3.0, 3.0, ("normal", 0.0, 0.05), doc="stations' shift along bed y"))

    def width(self, ctx, w, p):
        order, gs, g, lo, hi, first, last = _track_coordinate(ctx)
        th = ctx.s_heading_rad
        target = np.atleast_2d(np.clip(g + p["dx_mm"] * np.cos(th) + p["dy_mm"] * np.sin(th), lo, hi))
        w = np.atleast_2d(np.asarray(w, dtype=float))
        shape = (max(w.shape[0], target.shape[0]), len(g))
        w, target = np.broadcast_to(w, shape), np.broadcast_to(target, shape)
        j = np.searchsorted(gs, target, side="right") - 1
        j = np.maximum(np.minimum(j, last - 1), first)       # the interval within the track
        j1 = np.minimum(j + 1, last)
        span = gs[j1] - gs[j]
        frac = np.where(span > 0, (target - gs[j]) / np.where(span > 0, span, 1.0), 0.0)
        ws, rows = w[:, order], np.arange(shape[0])[:, None]
        return ws[rows, j] * (1.0 - frac) + ws[rows, j1] * frac


# -----------------------------------------------------------------------------------
# User effects

def load_effects_file(path) -> list[type]:
    """Effect classes defined in a user's Python file (``--effects my_effects.py``).

    The file subclasses :class:`Effect` and implements ``command``, ``height`` or
    ``width`` in numpy. Any problem (missing file, syntax error, exception on import,
    malformed class, name clash with a built-in) -> UserError.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"effects file {path} does not exist")
    modname = f"calib_user_effects_{abs(hash(str(path.resolve())))}"
    try:
        spec = importlib.util.spec_from_file_location(modname, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[modname] = mod
        spec.loader.exec_module(mod)
    except UserError:
        raise
    except SyntaxError as exc:
        raise UserError(f"effects file {path}: syntax error at line {exc.lineno}: {exc.msg}") from None
    except Exception as exc:  # the user's code: report it on one line
        raise UserError(f"effects file {path} failed to load: {type(exc).__name__}: {exc}") from None
    finally:
        sys.modules.pop(modname, None)
    classes = [obj for obj in vars(mod).values()
               if isinstance(obj, type) and issubclass(obj, Effect) and obj is not Effect
               and obj.__module__ == modname]
    if not classes:
        raise UserError(f"effects file {path} defines no subclass of fit.effects.Effect")
    for cls in classes:
        _check_effect_class(cls, where=f"effects file {path}")
        if cls.nozzle_term:
            raise UserError(f"effects file {path}: effect {cls.name}: nozzle terms are built-in only; "
                            "implement command(), height() or width()")
        if cls.name in REGISTRY and REGISTRY[cls.name] is not cls:
            raise UserError(f"effects file {path}: effect name {cls.name!r} clashes with a built-in effect")
    return classes
