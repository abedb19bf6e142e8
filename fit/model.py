"""A composition of effects: the object the fitters evaluate for many parameter sets.

``build_model("pa+thermal+backpressure", profile)`` -> :class:`Model`. Parameters are
named ``effect.local`` (``pa.tau_s``); theta is (n_sets, k) or (k,) over the free ones.

Pipeline of :meth:`Model.simulate` (one pass, all parameter sets at once):

1. command stage: ve = de/dt per timeline interval (mm/s), transformed by the command
   effects in spec order (firmware_pa, backlash, flow_gain, user effects);
2. nozzle: the compiled kernel integrates dP/dt = ve - vn (+ thermal) with
   P = Preq(vn) (fit/kernels.py) -> filament out of the nozzle per interval;
3. deposit: dV = Af * out on track intervals, V(s) per track, A_i over a window of one
   nozzle diameter around each station (fit/context.py), h_i from the height effects,
   w_i = bead_width_mm(A_i, h_i), then the width effects.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.errors import UserError
from fit import kernels as K
from fit.blobs import blob_volumes_mm3, with_footprints
from fit.context import SimContext, profile_dict
from fit.effects import REGISTRY, Effect
from fit.geometry import bead_width_mm, filament_area_mm2
from fit.params import Param

# Kernel defaults when an effect is absent: linear (n=1), no other term.
_COEF_DEFAULT = np.zeros(K.N_COEF)
_COEF_DEFAULT[K.C_TAU] = 1e-6
_COEF_DEFAULT[K.C_N] = 1.0
_COEF_DEFAULT[K.C_VREF] = 1.0
_COEF_DEFAULT[K.C_WSAT] = 1.0
_COEF_DEFAULT[K.C_TVL] = 1.0
_COEF_DEFAULT[K.C_RVL] = 1.0
_COEF_DEFAULT[K.C_TAUTH] = 1.0
_LINEAR_OK = {"pa", "pa_ve", "offset"}
_THERMAL_LINEAR_OK = _LINEAR_OK | {"thermal"}


@dataclass
class Simulation:
    """Full output of one simulation (n_sets parameter sets).

    out_mm        (n_sets, n_int) filament (mm) out of the nozzle per timeline interval
    vn_node_mm_s  (n_sets, n_t) nozzle outflow at the timeline nodes (mm/s of filament)
    ve_mm_s       (n_sets, n_int) commanded extruder velocity after the command effects
    p_end_mm      (n_sets,) advance P still stored at the end (mm of filament)
    x_end_mm_s    (n_sets,) thermal state at the end (mm/s)
    widths_mm     (n_sets, n_samples) bead width at the stations (mm), a dwell's blob
                  (fit/blobs.py) included
    height_mm     (n_sets, n_samples) layer height at the stations (mm)
    area_mm2      (n_sets, n_samples) deposited cross-section at the stations (mm^2)
    bead_widths_mm  (n_sets, n_samples) the width the moving head laid, without the blobs'
                  discs (mm; what ``predict`` returns; the renderer draws the discs apart,
                  fit/virtual.py ``Blob.diameter_mm``)
    blob_volume_mm3 (n_sets, n_blobs) volume of each of ``ctx.blobs`` (mm^3)
    """

    out_mm: np.ndarray
    vn_node_mm_s: np.ndarray
    ve_mm_s: np.ndarray
    p_end_mm: np.ndarray
    x_end_mm_s: np.ndarray
    widths_mm: np.ndarray
    height_mm: np.ndarray
    area_mm2: np.ndarray
    bead_widths_mm: np.ndarray | None = None
    blob_volume_mm3: np.ndarray | None = None


class Model:
    """A composition of effect instances with named free/fixed parameters."""

    def __init__(self, effects: list[Effect], fixed: dict | None = None, spec: str = ""):
        self.effects = list(effects)
        self.spec = spec or "+".join(e.name for e in self.effects)
        all_params: list[Param] = []
        for e in self.effects:
            all_params += [p.prefixed(e.name) for p in e.params]
        fixed = dict(fixed or {})
        names = [p.name for p in all_params]
        unknown = [k for k in fixed if k not in names]
        if unknown:
            raise UserError(f"cannot fix unknown parameter(s) {', '.join(unknown)} of model "
                            f"{self.spec}; its parameters are {', '.join(names)}")
        out = []
        for p in all_params:
            if p.name in fixed:
                v = float(fixed[p.name])
                if np.isfinite(v):
                    p.check_value(v, where="fixed value: ")
                p = p.with_default(v, fixed=True)
            out.append(p)
        self.all_params: tuple[Param, ...] = tuple(out)
        self.params: tuple[Param, ...] = tuple(p for p in out if not p.fixed)
        self.param_names: list[str] = [p.name for p in self.params]
        self.bounds = np.array([[p.lower, p.upper] for p in self.params], dtype=float).reshape(-1, 2)
        self._linear = all(e.name in _LINEAR_OK for e in self.effects if e.nozzle_term)
        # kernel: exact linear (pa/offset), exact two-state linear (+ thermal), or the
        # theta scheme for nonlinear Preq terms (fit/kernels.py)
        self._mode = K.MODE_LINEAR if self._linear else (
            K.MODE_THERMAL if all(e.name in _THERMAL_LINEAR_OK for e in self.effects if e.nozzle_term)
            else K.MODE_GENERAL)
        self._nozzle = [e for e in self.effects if e.nozzle_term]
        self._command = [e for e in self.effects if "command" in e.stages()]
        self._height = [e for e in self.effects if "height" in e.stages()]
        self._width = [e for e in self.effects if "width" in e.stages()]

    def __repr__(self) -> str:
        return f"Model({self.spec!r}, free={self.param_names})"

    # -- parameters ---------------------------------------------------------------
    def default_theta(self) -> np.ndarray:
        """Defaults of the free parameters, shape (k,)."""
        return np.array([p.default for p in self.params], dtype=float)

    def log_prior(self, theta) -> np.ndarray:
        """Sum of the parameters' log priors, shape (n_sets,); -inf outside the bounds."""
        th = self._theta2d(theta)
        lp = np.zeros(th.shape[0])
        for j, p in enumerate(self.params):
            lp = lp + p.log_prior(th[:, j])
        return lp

    def theta_from(self, values: dict) -> np.ndarray:
        """theta (k,) from a dict of free-parameter values; missing ones take defaults."""
        self._check_names(values)
        return np.array([float(values.get(p.name, p.default)) for p in self.params])

    def with_values(self, values: dict) -> "Model":
        """A copy whose defaults (free and fixed) are ``values`` (e.g. a TRUTH file):
        ``m = model.with_values(v); m.predict(ctx, m.default_theta())``."""
        self._check_names(values)
        new = Model.__new__(Model)
        new.__dict__.update(self.__dict__)
        ps = []
        for p in self.all_params:
            if p.name in values:
                p = p.with_default(p.check_value(values[p.name], where="value: "))
            ps.append(p)
        new.all_params = tuple(ps)
        new.params = tuple(p for p in ps if not p.fixed)
        return new

    def values(self, theta) -> dict:
        """All parameter values (free from theta (k,), fixed from defaults) as a dict."""
        th = self._theta2d(theta)[0]
        free = dict(zip(self.param_names, th))
        return {p.name: float(free.get(p.name, p.default)) for p in self.all_params}

    def _check_names(self, values: dict) -> None:
        names = {p.name for p in self.all_params}
        unknown = [k for k in values if k not in names]
        if unknown:
            raise UserError(f"unknown parameter(s) {', '.join(map(str, unknown))} for model "
                            f"{self.spec}; known: {', '.join(sorted(names))}")

    def _theta2d(self, theta) -> np.ndarray:
        th = np.asarray(theta, dtype=float)
        if th.ndim == 1:
            th = th[None, :]
        if th.ndim != 2 or th.shape[1] != len(self.params):
            raise ValueError(f"theta has shape {np.shape(theta)}, expected (n_sets, {len(self.params)})"
                             f" for parameters {self.param_names}")
        return th

    def _pdicts(self, theta) -> list[dict]:
        """Per effect: local name -> (n_sets, 1) array."""
        th = self._theta2d(theta)
        n = th.shape[0]
        col = {name: j for j, name in enumerate(self.param_names)}
        byname = {p.name: p for p in self.all_params}
        out = []
        for e in self.effects:
            d = {}
            for p in e.params:
                full = f"{e.name}.{p.name}"
                if full in col:
                    d[p.name] = th[:, col[full]][:, None]
                else:
                    d[p.name] = np.full((n, 1), byname[full].default)
            out.append(d)
        return out

    # -- physics ------------------------------------------------------------------
    def _nozzle_inputs(self, ctx: SimContext, theta, p0_mm=None):
        """Command stage and kernel coefficients: (n, pdicts, ve, ve_per_set, coef, p0)."""
        th = self._theta2d(theta)
        n = th.shape[0]
        pds = self._pdicts(th)
        n_int = len(ctx.dt_s)
        ve = ctx.ve_mm_s[None, :]
        for e, p in zip(self.effects, pds):
            if "command" in e.stages():
                ve = np.asarray(e.command(ctx, np.broadcast_to(ve, (n, n_int)), p), dtype=float)
                if ve.shape != (n, n_int):
                    raise UserError(f"effect {e.name}: command() returned shape {ve.shape}, "
                                    f"expected {(n, n_int)}")
        ve_per_set = int(ve.shape[0] == n and n > 1)
        ve = np.ascontiguousarray(ve if ve_per_set else ve[:1], dtype=float)
        coef = np.tile(_COEF_DEFAULT, (n, 1))
        for e, p in zip(self.effects, pds):
            if e.nozzle_term:
                e.nozzle(p, coef)
        p0 = np.zeros(n) if p0_mm is None else np.broadcast_to(np.asarray(p0_mm, float), (n,)).copy()
        return n, pds, ve, ve_per_set, coef, p0

    def _widths(self, ctx: SimContext, area, pds, n, observe=None, station_ctx: SimContext | None = None,
                blob_vol=None):
        """Height and width stages: (widths, heights) at the stations of ``ctx``.

        ``blob_vol`` (n_sets, n_blobs) mm^3: the volume of each of ``ctx.blobs``, laid as
        discs over the bead (fit/blobs.py) before the picture reads the widths.

        ``observe`` (fit/observe.py): ``ctx``'s stations are its physics points (sub-stations
        near changes of flow or speed, station centres elsewhere); the laid widths there are
        read through it onto the stations of ``station_ctx``, and the width stages (the
        bead's spreading, the picture's nuisances) act on those, which are then returned
        (heights stay at the physics points). A spreading applied after the
        despeckling rather than before differs only where a feature is shorter than the
        despeckling element, and at the sub-stations it would cost ~25x."""
        h = ctx.s_height_mm[None, :]
        for e, p in zip(self.effects, pds):
            if "height" in e.stages():
                h = np.asarray(e.height(ctx, np.broadcast_to(h, area.shape), p), dtype=float)
        h_per_set = int(h.shape[0] == n and n > 1)
        h = np.ascontiguousarray(np.broadcast_to(h, (n if h_per_set else 1, area.shape[1])), dtype=float)
        w = np.empty_like(area)
        K.kernel("bead_width", n)(area, h, h_per_set, ctx.printed, w)
        if blob_vol is not None and ctx.blobs is not None and ctx.blobs.n_blobs:
            w = with_footprints(w, blob_vol, ctx.blobs)
        if observe is not None:
            w, ctx = observe.apply(w), station_ctx
        if self._width:
            for e, p in zip(self.effects, pds):
                if "width" in e.stages():
                    w = np.asarray(e.width(ctx, w, p), dtype=float)
            w = np.maximum(w, 0.0)
        return w, h

    def simulate(self, ctx: SimContext, theta, p0_mm=None) -> Simulation:
        """Run command -> nozzle -> deposit for every parameter set in theta."""
        n, pds, ve, ve_per_set, coef, p0 = self._nozzle_inputs(ctx, theta, p0_mm)
        n_int = len(ctx.dt_s)
        out = np.empty((n, n_int))
        vn = np.empty((n, n_int + 1))
        p_end = np.empty(n)
        x_end = np.zeros(n)
        K.kernel("nozzle", n)(self._mode, ve, ve_per_set, ctx.dt_s, ctx.v_head_mm_s, ctx.h_mm,
                              ctx.on_track, coef, ctx.filament_area_mm2, p0, out, vn, p_end, x_end)
        area = self._deposit(ctx, out, vn)
        bm = ctx.blobs
        vol = blob_volumes_mm3(out, bm, ctx.filament_area_mm2) if bm is not None else None
        w_bead, h = self._widths(ctx, area, pds, n)
        w = self._widths(ctx, area, pds, n, blob_vol=vol)[0] if bm is not None and bm.n_blobs else w_bead
        return Simulation(out_mm=out, vn_node_mm_s=vn, ve_mm_s=np.broadcast_to(ve, (n, n_int)),
                          p_end_mm=p_end, x_end_mm_s=x_end,
                          widths_mm=w, height_mm=np.broadcast_to(h, area.shape), area_mm2=area,
                          bead_widths_mm=w_bead, blob_volume_mm3=vol)

    @staticmethod
    def _deposit(ctx: SimContext, out: np.ndarray, vn: np.ndarray) -> np.ndarray:
        """Cross-section A_i (mm^2) over the one-nozzle windows (fit/context.py)."""
        n = out.shape[0]
        if len(ctx.perm) == 0:
            return np.zeros((n, ctx.n_samples))
        area = np.empty((n, ctx.n_samples))
        K.kernel("deposit", n)(out, vn, ctx.deposit_map, ctx.filament_area_mm2, area)
        return area

    def predict(self, ctx: SimContext, theta) -> np.ndarray:
        """Bead widths (n_sets, n_samples) mm at the stations; NaN where never printed; as
        the measurement reads them where ``ctx.physics`` carries its kernel (fit/observe.py).
        The beads the moving head lays, without the dwells' blobs (``simulate``'s
        ``bead_widths_mm``): a blob's disc (fit/blobs.py) is our assumption of its shape (a
        real one domes higher and narrower), the picture shows it and the measurement flags
        the stations it covers (`blob`, `steep`); a fit through the disc's edge would trade
        the blob's volume, so the stored advance and tau, against where those flags end.

        Integrates on the coarsened physics timeline ``ctx.physics`` when there is one
        (fit/context.py :func:`coarsen_nodes`, same widths within ~1 um; cut after the last
        deposit a station sees, :func:`last_needed_node`, exact), with the fused
        nozzle + deposit kernel (no per-interval arrays kept; parallel over sets)."""
        c = ctx.physics or ctx
        n, pds, ve, ve_per_set, coef, p0 = self._nozzle_inputs(c, theta)
        area = np.empty((n, c.n_samples))
        K.kernel("predict", n)(self._mode, ve, ve_per_set, c.dt_s, c.v_head_mm_s, c.h_mm, c.on_track,
                               coef, c.filament_area_mm2, p0, c.deposit_map, area)
        return self._widths(c, area, pds, n, observe=c.obs, station_ctx=ctx)[0]

    #: nozzle terms whose steady advance is not linear in vn (Kalico match makes sense)
    NONLINEAR_TERMS = ("nonlinear", "bernoulli", "kalico_tanh", "kalico_recip")

    @property
    def has_nonlinear_advance(self) -> bool:
        return any(e.name in self.NONLINEAR_TERMS for e in self._nozzle)

    def steady_advance_mm(self, theta, vn_mm_s, width_mm=None, height_mm=None,
                          head_speed_mm_s=None) -> np.ndarray:
        """Steady-state advance Preq(vn) (mm of filament) at nozzle outflow vn (mm/s of
        filament), summed over the model's nozzle terms (same equations as the kernel,
        fit/kernels.py ``_preq``):

            Preq = (tau/n) v_ref (vn/v_ref)^n      pa / pa_ve (n = 1 without ``nonlinear``)
                 + k_b Af vn^2                     bernoulli (seed 002)
                 + Kb w_sat tanh(w / w_sat)        backpressure (seed 001)
                 + Kc                              offset (seed 001)
                 + off_t tanh(vn / vl_t)           kalico_tanh
                 + off_r vn / (vn + vl_r)          kalico_recip
        (thermal adds nothing at steady state: X = vn). At vn = 0 the value is the limit
        vn -> 0+ (the flow threshold). Backpressure needs the bead width w: ``width_mm``
        (scalar or broadcastable to vn; at steady state the commanded width), or the width
        the flow lays, w = bead_width_mm(Af vn / head_speed_mm_s, height_mm), as the kernel
        does. theta (k,) -> shape of vn; theta (n_sets, k) -> (n_sets,) + vn.shape.
        """
        th = self._theta2d(theta)
        n = th.shape[0]
        v = np.clip(np.asarray(vn_mm_s, dtype=float), 0.0, None)
        coef = np.tile(_COEF_DEFAULT, (n, 1))
        for e, p in zip(self.effects, self._pdicts(th)):
            if e.nozzle_term:
                e.nozzle(p, coef)
        c = coef.reshape((n, K.N_COEF) + (1,) * v.ndim)
        col = lambda j: c[:, j]          # noqa: E731  (n_sets, 1, ...) broadcast with v
        af = filament_area_mm2(self._profile().get("filament_diameter_mm", 1.75))
        tau = np.maximum(col(K.C_TAU), 1e-6)
        nexp, vref = col(K.C_N), col(K.C_VREF)
        with np.errstate(divide="ignore", invalid="ignore"):
            p_pa = np.where(nexp == 1.0, tau * v, tau / nexp * vref * (v / vref) ** nexp)
        out = p_pa + col(K.C_KC) + col(K.C_KBERN) * af * v * v
        out = out + col(K.C_TOFF) * np.tanh(v / col(K.C_TVL))
        out = out + col(K.C_ROFF) * v / (v + col(K.C_RVL))
        kb = col(K.C_KB)
        if np.any(kb != 0):
            if width_mm is not None:
                w = np.asarray(width_mm, dtype=float)
            elif height_mm is not None and head_speed_mm_s is not None:
                w = bead_width_mm(af * v / np.asarray(head_speed_mm_s, float), height_mm)
            else:
                raise ValueError("steady_advance_mm: the backpressure term needs width_mm "
                                 "(or height_mm and head_speed_mm_s)")
            ws = col(K.C_WSAT)
            out = out + kb * ws * np.tanh(w / ws)
        out = np.broadcast_to(out, (n,) + v.shape)
        return np.array(out[0] if np.ndim(theta) == 1 else out)

    def _profile(self) -> dict:
        for e in self.effects:
            if e.profile:
                return e.profile
        return {}

    def flow(self, ctx: SimContext, theta) -> np.ndarray:
        """Volumetric nozzle flow q (n_sets, n_t) mm^3/s at the timeline nodes."""
        return self.simulate(ctx, theta).vn_node_mm_s * ctx.filament_area_mm2


def known_effects(extra_effects=()) -> dict[str, type]:
    reg = dict(REGISTRY)
    for cls in extra_effects:
        reg[cls.name] = cls
    return reg


def build_model(spec: str, profile=None, extra_effects=(), fixed: dict | None = None) -> Model:
    """Compose a model from ``spec`` ("pa+thermal+backpressure").

    ``profile``: PrinterProfile or dict (needed by ``pa_ve``); ``extra_effects``: user
    Effect classes (:func:`fit.effects.load_effects_file`); ``fixed``: full parameter
    name -> value to hold fixed. Unknown effect name -> UserError listing the known ones.
    """
    reg = known_effects(extra_effects)
    if not isinstance(spec, str) or not spec.strip():
        raise UserError(f"empty model spec; name effects joined by '+', from: {', '.join(sorted(reg))}")
    names = [s.strip() for s in spec.split("+")]
    bad = [s for s in names if s not in reg]
    if bad:
        raise UserError(f"unknown effect(s) {', '.join(repr(b) for b in bad)} in model {spec!r}; "
                        f"known effects: {', '.join(sorted(reg))}")
    dup = sorted({s for s in names if names.count(s) > 1})
    if dup:
        raise UserError(f"effect(s) {', '.join(dup)} appear twice in model {spec!r}")
    if "pa" in names and "pa_ve" in names:
        raise UserError("model uses both pa and pa_ve: they are the same term; keep one")
    prof = profile_dict(profile)
    effects = [reg[s](prof) for s in names]
    return Model(effects, fixed=fixed, spec="+".join(names))
