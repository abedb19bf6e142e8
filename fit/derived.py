"""Values a user types into a slicer or firmware, derived from posterior draws (with intervals).

* KISSlicer viscoelasticity (seed 000):  tau = 32 D^2 L l / d^4 * VE
      =>  VE = tau d^4 / (32 D^2 L l)      D filament dia, L Bowden length, l nozzle land
      length, d nozzle bore (all mm), tau (s), VE (s; reported in us). Seed 000 rig:
      D=2.85, L=150, l=0.6, d=0.4 mm, tau=0.594 s -> VE = 0.65 us. Undefined for a direct
      drive (L = 0).
* Linear pressure advance: the firmware constant equals the lag time constant tau (s)
  because Klipper/Marlin LA 1.5/RRF all advance the extruder by K * v_e (mm of filament
  per mm/s), which exactly cancels dP/dt = v_e - P/tau (REFERENCE.md "Physics"):
  Klipper ``SET_PRESSURE_ADVANCE ADVANCE=tau``, Marlin ``M900 K tau``, RRF ``M572 D0 S tau``.
* Kalico nonlinear PA (REFERENCE.md): advance(v) = LA v + off tanh(v / v_lin)  ("tanh")
  or LA v + off v / (v + v_lin)  ("recipr"), v the filament speed (mm/s). The nearest
  parameters are the least-squares match to the fitted steady-state advance Preq(v) over
  the fitted flow range (0 .. v_max).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

Q68, Q95 = (0.16, 0.84), (0.025, 0.975)


def ve_s_from_tau(tau_s, filament_diameter_mm, bowden_length_mm, nozzle_land_length_mm,
                  nozzle_diameter_mm):
    """KISSlicer VE (s) from the elastic time constant (seed 000, inverted)."""
    D, L, l, d = (float(x) for x in (filament_diameter_mm, bowden_length_mm,
                                     nozzle_land_length_mm, nozzle_diameter_mm))
    if L <= 0 or l <= 0:
        return np.full(np.shape(tau_s), np.nan)
    return np.asarray(tau_s, dtype=float) * d ** 4 / (32.0 * D * D * L * l)


def summarize(draws) -> dict:
    """Median, 68 % and 95 % intervals of draws (units of the draws)."""
    x = np.asarray(draws, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"median": math.nan, "ci68": [math.nan] * 2, "ci95": [math.nan] * 2}
    q = np.quantile(x, [Q95[0], Q68[0], 0.5, Q68[1], Q95[1]])
    return {"median": float(q[2]), "ci68": [float(q[1]), float(q[3])],
            "ci95": [float(q[0]), float(q[4])]}


def firmware_commands(pa_s: float) -> dict[str, str]:
    """One-line commands setting linear pressure advance to ``pa_s`` (s)."""
    k = f"{pa_s:.4f}"
    return {"klipper": f"SET_PRESSURE_ADVANCE ADVANCE={k}",
            "klipper_config": f"[extruder]\npressure_advance: {k}",
            "marlin": f"M900 K{k}",
            "rrf": f"M572 D0 S{k}"}


def _kalico_curve(kind, p, v):
    la, off, vl = p
    if kind == "tanh":
        return la * v + off * np.tanh(v / vl)
    return la * v + off * v / (v + vl)


def kalico_match(advance_mm, v_max_mm_s: float, kind: str = "tanh", n: int = 64) -> dict:
    """Nearest Kalico (LA s, offset mm, v_lin mm/s) to an advance curve ``advance_mm(v)``
    (mm of filament at filament speed v, mm/s) over 0 < v <= v_max, least squares."""
    v = np.linspace(v_max_mm_s / n, v_max_mm_s, n)
    a = np.asarray(advance_mm(v), dtype=float)
    a = a - float(np.asarray(advance_mm(np.array([0.0])), dtype=float).reshape(-1)[0])
    slope_hi = max((a[-1] - a[n // 2]) / (v[-1] - v[n // 2]), 0.0)
    x0 = [slope_hi, max(a[-1] - slope_hi * v[-1], 1e-4), v_max_mm_s / 10]
    res = least_squares(lambda p: _kalico_curve(kind, p, v) - a, x0,
                        bounds=([0, 0, 1e-3], [np.inf, np.inf, 10 * v_max_mm_s]))
    rms = float(np.sqrt(np.mean(res.fun ** 2)))
    return {"model": kind, "pressure_advance_s": float(res.x[0]), "offset_mm": float(res.x[1]),
            "linearization_velocity_mm_s": float(res.x[2]), "rms_mm": rms}


def kalico_config(kind: str, la_s: float, off_mm: float, v_lin_mm_s: float) -> str:
    """Kalico ``[extruder]`` lines for its nonlinear PA (Kalico docs, "Nonlinear pressure
    advance": ``pressure_advance_model``, ``linear_advance``, ``nonlinear_offset``,
    ``linearization_velocity``)."""
    return (f"[extruder]\npressure_advance_model: {kind}\nlinear_advance: {la_s:.4f}\n"
            f"nonlinear_offset: {off_mm:.4f}\nlinearization_velocity: {v_lin_mm_s:.4f}")


def problem_advance(problem, k: int = 0):
    """For a :class:`fit.likelihood.JointProblem` whose model has a nonlinear advance
    term: (advance_fn(theta_row, v) -> Preq mm, v_max_mm_s, width_mm) for
    :func:`derived_values`, else None. v_max is the 99.9 % time-weighted quantile of the
    commanded filament speed on the tracks of all scans (the fitted flow range); the
    bead width for a backpressure term is the median nominal width of the stations."""
    model = problem.models[k]
    if not getattr(model, "has_nonlinear_advance", False):
        return None
    vs, ws, ws_w = [], [], []
    for sc in problem.scans:
        c = sc.ctx
        m = np.asarray(c.on_track) & (np.asarray(c.dt_s) > 1e-6)
        vs.append(np.asarray(c.ve_mm_s)[m])
        ws_w.append(np.asarray(c.dt_s)[m])
        ws.append(np.asarray(c.s_width_nominal_mm, float))
    v, wt = np.concatenate(vs), np.concatenate(ws_w)
    if v.size == 0:
        return None
    o = np.argsort(v)
    cw = np.cumsum(wt[o]) / wt.sum()
    v_max = float(v[o][min(np.searchsorted(cw, 0.999), len(v) - 1)])
    w_all = np.concatenate(ws)
    width = float(np.nanmedian(w_all)) if np.any(np.isfinite(w_all)) else 1.125 * float(
        problem.scans[0].ctx.nozzle_diameter_mm)
    if not v_max > 0:
        return None

    def advance_fn(row, vn):
        return model.steady_advance_mm(problem.model_theta(row, k)[0], vn, width_mm=width)

    return advance_fn, v_max, width


def pa_vs_flow(advance_fn, rows, v_max_mm_s: float, profile: dict, n: int = 10) -> dict:
    """The linear PA that is right for a start or stop at each filament speed v of the
    fitted range: K(v) = Preq(v) / v (s), the secant of the steady advance curve (a line
    that starts from rest at speed v needs the advance Preq(v) = K v). With intervals over
    posterior draws; flows in mm^3/s = v Af. Used for Orca's adaptive PA table."""
    v = np.linspace(v_max_mm_s / n, v_max_mm_s, n)
    K = np.array([np.asarray(advance_fn(r, v), dtype=float) / v for r in rows])
    af = math.pi * float(profile.get("filament_diameter_mm", 1.75)) ** 2 / 4.0
    q = np.quantile(K, [0.025, 0.5, 0.975], axis=0)
    return {"v_mm_s": v.tolist(), "flow_mm3_s": (v * af).tolist(), "pa_s_median": q[1].tolist(),
            "pa_s_ci95": np.stack([q[0], q[2]], axis=1).tolist(), "v_max_mm_s": float(v_max_mm_s)}


def derived_values(param_names, samples, profile: dict, advance_fn=None,
                   v_max_mm_s: float | None = None, n_kalico: int = 100) -> dict:
    """Derived values with intervals from posterior draws (samples (n, k)).

    ``advance_fn(theta_row, v_mm_s) -> advance_mm`` (steady-state Preq) enables the Kalico
    match for nonlinear models; ``v_max_mm_s`` is the largest filament speed in the data.
    """
    names = list(param_names)
    S = np.atleast_2d(np.asarray(samples, dtype=float))
    out: dict = {}
    tau_name = next((n for n in names if n.split("@")[0] in ("pa.tau_s", "pa.K_s", "pa.k_s")), None)
    ve_name = next((n for n in names if n.split("@")[0] == "pa_ve.ve_us"), None)
    tau = None
    if tau_name is not None:
        tau = S[:, names.index(tau_name)]
    elif ve_name is not None:
        # the pa_ve parameterisation: tau = 32 D^2 L l / d^4 * VE (seed 000), so every
        # firmware target gets the same time constant a pa fit would give
        one = ve_s_from_tau(1.0, *(profile.get(k, 0.0) for k in (
            "filament_diameter_mm", "bowden_length_mm", "nozzle_land_length_mm", "nozzle_diameter_mm")))
        if np.isfinite(one) and one > 0:
            tau = S[:, names.index(ve_name)] * 1e-6 / one
    if tau is not None:
        pa = summarize(tau)
        out["pressure_advance_s"] = pa
        out["firmware"] = firmware_commands(pa["median"])
        D = profile.get("filament_diameter_mm")
        L = profile.get("bowden_length_mm")
        l = profile.get("nozzle_land_length_mm")
        d = profile.get("nozzle_diameter_mm")
        if None not in (D, L, l, d) and float(L) > 0:
            out["kisslicer_ve_us"] = summarize(ve_s_from_tau(tau, D, L, l, d) * 1e6)
    if advance_fn is not None and v_max_mm_s:
        rng = np.random.default_rng(0)
        rows = S[rng.choice(len(S), min(n_kalico, len(S)), replace=False)]
        out["pa_vs_flow"] = pa_vs_flow(advance_fn, rows, v_max_mm_s, profile)
        for kind in ("tanh", "recipr"):
            fits = [kalico_match(lambda v, r=r: advance_fn(r, v), v_max_mm_s, kind) for r in rows]
            d = {k: summarize([f[k] for f in fits])
                 for k in ("pressure_advance_s", "offset_mm", "linearization_velocity_mm_s",
                           "rms_mm")}
            d["v_max_mm_s"] = float(v_max_mm_s)
            d["config"] = kalico_config(kind, d["pressure_advance_s"]["median"],
                                        d["offset_mm"]["median"],
                                        d["linearization_velocity_mm_s"]["median"])
            out[f"kalico_{kind}"] = d
    return out
