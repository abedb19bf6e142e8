"""Compiled (numba) time-stepping kernels of the extruder ODE.

State P: filament "advance" (mm of filament stored as compression, seed 001 ``pe``);
X: thermal state (mm/s); vn: nozzle outflow (mm/s of filament).

    dP/dt = ve - vn + a_th * (X - vn)          (thermal source, seed 000)
    dX/dt = (vn - X) / tau_th
    vn solves P = Preq(vn) if P > Preq(0+), else vn = 0   (no back-flow)

    Preq(vn) = Kc                                         offset (seed 001 Kc)
             + tau * v_ref * (vn / v_ref)**n              pa; power law if n != 1
             + k_b * Af * vn**2                           Bernoulli (seed 002)
             + Kb * w_sat * tanh(w(vn) / w_sat)           bead back-pressure (seed 001)
             + off_t * tanh(vn / vl_t)                    Kalico "tanh" model
             + off_r * vn / (vn + vl_r)                   Kalico "recipr" model

with w(vn) = bead_width_mm(Af * vn / v_head, h) the width being laid (only on a track).

The commanded extruder velocity ``ve`` is piecewise constant over each timeline interval
(``de / dt``), so the commanded volume is integrated exactly. Two schemes:

* :func:`linear_kernel` (pa + offset only): the exact solution of the piecewise-linear
  ODE, including the instant where P crosses Kc (flow stops / starts) inside an interval.
* :func:`general_kernel`: an exponentially fitted theta scheme
  P1 = P0 + dt*ve + a' X0 - (dt + a') [(1-th) vn0 + th vn1],  P1 = Preq(vn1),
  th = 1/(1 - exp(-r)) - 1/r,  r = (dt + a') / tau_loc,  tau_loc = dPreq/dvn,
  a' = a * tau_th * (1 - exp(-dt/tau_th))  (~ a*dt; makes the thermal source exactly
  a*tau_th*(X0 - X1), so its total over a print is -a*tau_th*X_end).
  For a linear Preq this reproduces the exact exponential step (so direct drive tau =
  0.02 s with dt = 5 ms is exact and stable); for nonlinear Preq it is second order in
  dt/tau_loc and L-stable (th -> 1 as r -> inf). The implicit equation is monotone in
  vn1 and solved by safeguarded Newton (bisection fallback) on a bracket.

Both return the filament length that left the nozzle in every interval, so
sum(out) = sum(de) - (P_end - P_0) + thermal source, exactly (volume conservation).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# Column order of the coefficient array (n_sets, N_COEF) of the general kernel.
C_TAU, C_N, C_VREF, C_KBERN, C_KB, C_WSAT, C_KC, C_TOFF, C_TVL, C_ROFF, C_RVL, C_ATH, C_TAUTH = range(13)
N_COEF = 13

_PI4 = math.pi / 4.0
_TAU_MIN = 1e-6


def linear_kernel(ve, ve_per_set, dt, tau, kc, p0, out, vn_node, p_end):
    """Exact solution of dP/dt = ve - max(P - Kc, 0)/tau with piecewise-constant ve.

    ve (n_sets, n_int) mm/s, or (1, n_int) shared if ve_per_set == 0; dt (n_int,) s;
    tau, kc, p0 (n_sets,) s, mm, mm.
    Writes out (n_sets, n_int) mm of filament through the nozzle per interval,
    vn_node (n_sets, n_int+1) outflow at the nodes (mm/s), p_end (n_sets,) mm.
    """
    n_sets = tau.shape[0]
    n_int = ve.shape[1]
    for i in prange(n_sets):
        iv = i * ve_per_set
        ta = max(tau[i], _TAU_MIN)
        q = p0[i] - kc[i]          # pressure above the flow threshold (mm)
        vn_node[i, 0] = max(q, 0.0) / ta
        for k in range(n_int):
            h = dt[k]
            v = ve[iv, k]
            tgt = v * ta
            if q >= 0.0:
                if v >= 0.0:
                    q1 = tgt + (q - tgt) * math.exp(-h / ta)
                else:
                    # Decays towards a negative target: flow stops when q reaches 0.
                    t0 = ta * math.log1p(q / (-tgt))
                    if t0 >= h:
                        q1 = tgt + (q - tgt) * math.exp(-h / ta)
                    else:
                        q1 = v * (h - t0)
            else:
                if v <= 0.0:
                    q1 = q + v * h
                else:
                    t0 = -q / v
                    if t0 >= h:
                        q1 = q + v * h
                    else:
                        q1 = tgt - tgt * math.exp(-(h - t0) / ta)
            out[i, k] = v * h - (q1 - q)
            q = q1
            vn_node[i, k + 1] = max(q, 0.0) / ta
        p_end[i] = q + kc[i]


@njit(cache=True)
def _bead_width(area, h):
    if area <= 0.0 or h <= 0.0:
        return 0.0, 0.0
    a0 = _PI4 * h * h
    if area >= a0:
        return (area - a0) / h + h, 1.0 / h
    return area / (_PI4 * h), 1.0 / (_PI4 * h)


@njit(cache=True)
def _preq(vn, c, af, vhead, h, on):
    """Preq(vn) (mm) and dPreq/dvn (s) for vn > 0."""
    tau = max(c[C_TAU], _TAU_MIN)
    n = c[C_N]
    vref = c[C_VREF]
    if n == 1.0:
        p = tau * vn
        d = tau
    else:
        x = vn / vref
        xn = x ** n
        p = tau * vref * xn
        d = tau * n * xn / x if x > 0.0 else 1e30
    p += c[C_KC]
    if c[C_KBERN] != 0.0:
        p += c[C_KBERN] * af * vn * vn
        d += 2.0 * c[C_KBERN] * af * vn
    if c[C_KB] != 0.0 and on:
        ws = c[C_WSAT]
        if vhead <= 1e-9:
            p += c[C_KB] * ws          # stopped on the bead: saturated back-pressure
        else:
            w, dwda = _bead_width(af * vn / vhead, h)
            th = math.tanh(w / ws)
            p += c[C_KB] * ws * th
            d += c[C_KB] * (1.0 - th * th) * dwda * af / vhead
    if c[C_TOFF] != 0.0:
        th = math.tanh(vn / c[C_TVL])
        p += c[C_TOFF] * th
        d += c[C_TOFF] * (1.0 - th * th) / c[C_TVL]
    if c[C_ROFF] != 0.0:
        s = vn + c[C_RVL]
        p += c[C_ROFF] * vn / s
        d += c[C_ROFF] * c[C_RVL] / (s * s)
    return p, d


@njit(cache=True)
def _preq0(c, vhead, on):
    """Preq(0+): the pressure that must be exceeded before any flow (mm)."""
    p = c[C_KC]
    if c[C_KB] != 0.0 and on and vhead <= 1e-9:
        p += c[C_KB] * c[C_WSAT]
    return p


def general_kernel(ve, ve_per_set, dt, vhead, hgt, on, coef, af, p0, out, vn_node, p_end, x_end):
    """Exponentially fitted theta scheme for the full nonlinear Preq and thermal ooze.

    ve (n_sets, n_int) mm/s; dt, vhead (mm/s), hgt (mm), on (bool) per interval;
    coef (n_sets, N_COEF); af filament area mm^2; p0 (n_sets,) initial P (mm).
    Writes out (n_sets, n_int) mm of filament out of the nozzle per interval,
    vn_node (n_sets, n_int+1) mm/s, p_end, x_end (n_sets,).
    """
    n_sets = coef.shape[0]
    n_int = ve.shape[1]
    for i in prange(n_sets):
        iv = i * ve_per_set
        c = coef[i]
        a = c[C_ATH]
        tauth = max(c[C_TAUTH], 1e-9)
        p = p0[i]
        vn0 = 0.0
        xth = 0.0
        vn_node[i, 0] = 0.0
        for k in range(n_int):
            h = dt[k]
            v = ve[iv, k]
            vh = vhead[k]
            onk = on[k]
            # Thermal source over the step, a*(X - vn)*dt, written as a*tau_th*(X0 - X1)
            # with X updated exactly for the mean outflow: conserves volume exactly.
            eth = math.exp(-h / tauth)
            ah = a * tauth * (1.0 - eth)
            hh = h + ah
            # Local time constant at a representative outflow (vn0, or the command at a start).
            vloc = vn0
            if vloc < 1e-6:
                vloc = max(0.5 * v, 1e-6)
            _, dloc = _preq(vloc, c, af, vh, hgt[k], onk)
            r = hh / max(dloc, 1e-12)
            if r < 1e-4:
                th = 0.5 + r / 12.0
            elif r > 50.0:
                th = 1.0 - 1.0 / r
            else:
                th = 1.0 / (1.0 - math.exp(-r)) - 1.0 / r
            b = p + h * v + ah * xth - hh * (1.0 - th) * vn0
            cc = hh * th
            if b <= _preq0(c, vh, onk):
                vn1 = 0.0
                p1 = b
            else:
                # g(x) = Preq(x) + cc*x - b is increasing with g(0+) < 0 <= g(b/cc).
                # Newton from the linearised guess; a step leaving the bracket falls back to
                # an Illinois false-position step (bisection stalls near vn = 0 for the
                # concave power law, where Newton from the right overshoots below zero).
                lo = 0.0
                glo = _preq0(c, vh, onk) - b
                hi = b / cc
                ghi = _preq(hi, c, af, vh, hgt[k], onk)[0]
                pv, dv = _preq(max(vn0, 1e-12), c, af, vh, hgt[k], onk)
                x = (b - pv + dv * vn0) / (dv + cc)
                if not (lo < x < hi):
                    x = min(max(vn0, 1e-12), 0.5 * hi)
                side = 0
                tol = 1e-13 * (1.0 + b)
                for _ in range(60):
                    g, dg = _preq(x, c, af, vh, hgt[k], onk)
                    g += cc * x - b
                    if abs(g) <= tol:
                        break
                    if g > 0.0:
                        hi = x
                        ghi = g
                        if side == 1:
                            glo *= 0.5
                        side = 1
                    else:
                        lo = x
                        glo = g
                        if side == -1:
                            ghi *= 0.5
                        side = -1
                    xn = x - g / (dg + cc)
                    if not (lo < xn < hi):
                        xn = (lo * ghi - hi * glo) / (ghi - glo)
                        if not (lo < xn < hi):
                            xn = 0.5 * (lo + hi)
                    if abs(xn - x) <= 1e-14 * (1.0 + x):
                        x = xn
                        break
                    x = xn
                vn1 = x
                p1 = b - cc * vn1
            vbar = (1.0 - th) * vn0 + th * vn1
            out[i, k] = vbar * h
            xth = vbar + (xth - vbar) * eth
            p = p1
            vn0 = vn1
            vn_node[i, k + 1] = vn1
        p_end[i] = p
        x_end[i] = xth


@njit(cache=True)
def play_operator(e, width, out):
    """Backlash (play / dead band) on the cumulative commanded E (seed 001 Be).

    e (n_sets, n_t) mm commanded position; width (n_sets,) mm. The filament follows
    y = max(e - Be, min(y_prev, e)): it moves only once the gear has taken up the
    dead band after a reversal. Starts pushed forward (y0 = e0 - Be).
    """
    n_sets, n_t = e.shape
    for i in range(n_sets):
        b = width[i]
        y = e[i, 0] - b
        out[i, 0] = y
        for k in range(1, n_t):
            x = e[i, k]
            y = max(x - b, min(y, x))
            out[i, k] = y


def deposit_kernel(out, perm, lo_pos, lo_frac, hi_pos, hi_frac, win, af, area):
    """Cross-section A_i (mm^2) over the station windows (fit/context.py):
    V(s_b) = C[pos] - (1 - frac) * dV[perm[pos]],  C = cumsum(dV[perm]),  dV = Af * out,
    A_i = (V(hi_i) - V(lo_i)) / win_i."""
    n_sets = out.shape[0]
    m = perm.shape[0]
    n_s = lo_pos.shape[0]
    for i in prange(n_sets):
        c = np.empty(m)
        acc = 0.0
        for j in range(m):
            acc += out[i, perm[j]] * af
            c[j] = acc
        for k in range(n_s):
            if win[k] > 1e-9:
                a = lo_pos[k]
                b = hi_pos[k]
                v_lo = c[a] - (1.0 - lo_frac[k]) * out[i, perm[a]] * af
                v_hi = c[b] - (1.0 - hi_frac[k]) * out[i, perm[b]] * af
                area[i, k] = (v_hi - v_lo) / win[k]
            else:
                area[i, k] = 0.0


def bead_width_kernel(area, h, h_per_set, printed, out):
    """fit.geometry.bead_width_mm for (n_sets, n_s) areas; heights h (mm) of shape
    (n_sets, n_s) if h_per_set else (1, n_s); NaN at stations never printed."""
    n_sets, n_s = area.shape
    for i in prange(n_sets):
        ih = i * h_per_set
        for k in range(n_s):
            if printed[k]:
                w, _ = _bead_width(area[i, k], max(h[ih, k], 1e-6))
                out[i, k] = w
            else:
                out[i, k] = np.nan


# Each kernel twice: serial (one or a few parameter sets: no thread start-up cost) and
# parallel over parameter sets (prange; emcee ensembles, 64+ sets).
_PY = {"linear": linear_kernel, "general": general_kernel, "deposit": deposit_kernel,
       "bead_width": bead_width_kernel}
SERIAL = {k: njit(cache=True)(f) for k, f in _PY.items()}
PARALLEL = {k: njit(cache=True, parallel=True)(f) for k, f in _PY.items()}
#: Parameter sets from which the parallel kernels pay off.
PARALLEL_MIN_SETS = 8


def kernel(name: str, n_sets: int):
    """The compiled kernel ``name`` suited to ``n_sets`` parameter sets."""
    return (PARALLEL if n_sets >= PARALLEL_MIN_SETS else SERIAL)[name]
