"""Compiled (numba) time-stepping kernels of the extruder ODE.

State P: filament "advance" (mm of filament stored as compression, seed 001 ``pe``);
X: thermal state (mm/s); vn: nozzle outflow (mm/s of filament).

    dP/dt = ve - vn + a_th * (X - vn)          (thermal source, seed 000)
    dX/dt = (vn - X) / tau_th
    vn solves P = Preq(vn) if P > Preq(0+), else vn = 0   (no back-flow)

    Preq(vn) = Kc                                         offset (seed 001 Kc)
             + (tau / n) * v_ref * (vn / v_ref)**n        pa; power law if n != 1
             + k_b * Af * vn**2                           Bernoulli (seed 002)
             + Kb * w_sat * tanh(w(vn) / w_sat)           bead back-pressure (seed 001)
             + off_t * tanh(vn / vl_t)                    Kalico "tanh" model
             + off_r * vn / (vn + vl_r)                   Kalico "recipr" model

with w(vn) = bead_width_mm(Af * vn / v_head, h) the width being laid (only on a track).

The commanded extruder velocity ``ve`` is piecewise constant over each timeline interval
(``de / dt``), so the commanded volume is integrated exactly. Two schemes:

* :func:`_linear_row` (pa + offset only): the exact solution of the piecewise-linear
  ODE, including the instant where P crosses Kc (flow stops / starts) inside an interval.
* :func:`_thermal_row` (pa + offset + thermal, all linear): the exact solution
  of the two-state linear system (q = P - Kc, X) over each interval,
      d/dt [q, X] = A [q, X] + [ve, 0],  A = [[-(1+a)/tau, a], [1/(tau tau_th), -1/tau_th]]
  (steady state q* = ve tau, X* = ve), [q, X](h) = y* + exp(A h) (y0 - y*) with the 2x2
  exponential in closed form (real eigenvalues, a >= 0); while q < 0 (no flow) q moves
  by ve t + a tau_th X0 (1 - exp(-t/tau_th)); the instants where q crosses 0 inside an
  interval are found by safeguarded Newton. Out per interval from the exact balance
  out = ve h - dq - a tau_th dX.
* :func:`_general_row`: an exponentially fitted theta scheme
  P1 = P0 + dt*ve + a' X0 - (dt + a') [(1-th) vn0 + th vn1],  P1 = Preq(vn1),
  th = 1/(1 - exp(-r)) - 1/r,  r = (dt + a') / tau_loc,  tau_loc = dPreq/dvn,
  a' = a * tau_th * (1 - exp(-dt/tau_th))  (~ a*dt; makes the thermal source exactly
  a*tau_th*(X0 - X1), so its total over a print is -a*tau_th*X_end).
  For a linear Preq this reproduces the exact exponential step (so direct drive tau =
  0.02 s with dt = 5 ms is exact and stable); for nonlinear Preq it is second order in
  dt/tau_loc and L-stable (th -> 1 as r -> inf). The implicit equation is monotone in
  vn1 and solved by safeguarded Newton (bisection fallback) on a bracket.

All three give the filament length that left the nozzle in every interval, so
sum(out) = sum(de) - (P_end - P_0) + thermal source, exactly (volume conservation).
"""
from __future__ import annotations

import math
import types

import numpy as np
from numba import njit, prange

# Column order of the coefficient array (n_sets, N_COEF) of the general kernel.
C_TAU, C_N, C_VREF, C_KBERN, C_KB, C_WSAT, C_KC, C_TOFF, C_TVL, C_ROFF, C_RVL, C_ATH, C_TAUTH = range(13)
N_COEF = 13

_PI4 = math.pi / 4.0
_TAU_MIN = 1e-6


MODE_LINEAR, MODE_THERMAL, MODE_GENERAL = 0, 1, 2


@njit(cache=True)
def _linear_row(ve, iv, dt, tau, kc, p0, out, vn_node, want_vn):
    """Exact solution of dP/dt = ve - max(P - Kc, 0)/tau with piecewise-constant ve for
    one parameter set (row iv of ve). Writes out (n_int,) mm, vn_node (n_int+1,) mm/s if
    want_vn; returns P at the end (mm)."""
    n_int = dt.shape[0]
    ta = max(tau, _TAU_MIN)
    q = p0 - kc          # pressure above the flow threshold (mm)
    if want_vn:
        vn_node[0] = max(q, 0.0) / ta
    h_prev = -1.0
    ex = 1.0
    for k in range(n_int):
        h = dt[k]
        v = ve[iv, k]
        tgt = v * ta
        if q >= 0.0:
            if h != h_prev:
                ex = math.exp(-h / ta)
                h_prev = h
            if v >= 0.0:
                q1 = tgt + (q - tgt) * ex
            else:
                # Decays towards a negative target: flow stops when q reaches 0.
                t0 = ta * math.log1p(q / (-tgt))
                if t0 >= h:
                    q1 = tgt + (q - tgt) * ex
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
                    q1 = -tgt * math.expm1(-(h - t0) / ta)
        out[k] = v * h - (q1 - q)
        q = q1
        if want_vn:
            vn_node[k + 1] = max(q, 0.0) / ta
    return q + kc


@njit(cache=True)
def _th_c(h, s, dlt):
    """exp(A h) = c0 I + c1 (A - s I) for the 2x2 A with eigenvalues s +- dlt (real):
    c0 = exp(s h) cosh(dlt h), c1 = exp(s h) sinh(dlt h) / dlt."""
    x = dlt * h
    if x > 1e-3:
        e1 = math.exp((s + dlt) * h)
        e2 = math.exp((s - dlt) * h)
        return 0.5 * (e1 + e2), 0.5 * (e1 - e2) / dlt
    es = math.exp(s * h)
    x2 = x * x
    return es * (1.0 + x2 * (0.5 + x2 / 24.0)), es * h * (1.0 + x2 * (1.0 / 6.0 + x2 / 120.0))


@njit(cache=True)
def _th_state(t, flowing, q0, x0, v, ta, a, tth, s, dlt):
    """(q, X, dq/dt) after time t from (q0, X0) in one mode of the thermal-linear system."""
    if flowing:
        c0, c1 = _th_c(t, s, dlt)
        dq = q0 - v * ta
        dx = x0 - v
        m11 = -(1.0 + a) / ta - s
        q = v * ta + c0 * dq + c1 * (m11 * dq + a * dx)
        x = v + c0 * dx + c1 * (dq / (ta * tth) - m11 * dx)
        return q, x, v - (1.0 + a) * q / ta + a * x
    ex = math.exp(-t / tth)
    x = x0 * ex
    return q0 + v * t - a * tth * x0 * math.expm1(-t / tth), x, v + a * x


@njit(cache=True)
def _thermal_row(ve, iv, dt, tau, kc, a, tauth, p0, out, vn_node, want_vn):
    """Exact solution of the linear pa + offset + thermal system (module docstring) for one
    parameter set. Returns (P_end mm, X_end mm/s)."""
    n_int = dt.shape[0]
    ta = max(tau, _TAU_MIN)
    tth = max(tauth, 1e-9)
    a = max(a, 0.0)
    # eigenvalues s +- dlt of A (real: discriminant >= a/(tau tau_th) >= 0)
    s = -0.5 * ((1.0 + a) / ta + 1.0 / tth)
    hd = 0.5 * ((1.0 + a) / ta - 1.0 / tth)
    dlt = math.sqrt(hd * hd + a / (ta * tth))
    m11 = -(1.0 + a) / ta - s
    q = p0 - kc
    x = 0.0
    if want_vn:
        vn_node[0] = max(q, 0.0) / ta
    h_prev = -1.0
    c0 = 1.0
    c1 = 0.0
    for k in range(n_int):
        h = dt[k]
        v = ve[iv, k]
        qs = q
        xs = x
        flowing = q > 0.0 or (q == 0.0 and v + a * x > 0.0)
        rem = h
        for _ in range(8):
            if flowing:
                if rem == h:
                    if h != h_prev:
                        c0, c1 = _th_c(h, s, dlt)
                        h_prev = h
                    dq = q - v * ta
                    dx = x - v
                    q1 = v * ta + c0 * dq + c1 * (m11 * dq + a * dx)
                    x1 = v + c0 * dx + c1 * (dq / (ta * tth) - m11 * dx)
                else:
                    q1, x1, _ = _th_state(rem, True, q, x, v, ta, a, tth, s, dlt)
                if q1 >= 0.0:
                    q, x = q1, x1
                    break
            else:
                q1, x1, _ = _th_state(rem, False, q, x, v, ta, a, tth, s, dlt)
                if q1 <= 0.0:
                    q, x = q1, x1
                    break
            # q crosses 0 inside the remaining time: safeguarded Newton on [0, rem]
            lo = 0.0
            hi = rem
            t = rem * q / (q - q1) if q != q1 else 0.5 * rem
            for _ in range(60):
                qt, xt, dqt = _th_state(t, flowing, q, x, v, ta, a, tth, s, dlt)
                if (qt > 0.0) == flowing:
                    lo = t
                else:
                    hi = t
                tn = t - qt / dqt if dqt != 0.0 else 0.5 * (lo + hi)
                if not (lo < tn < hi):
                    tn = 0.5 * (lo + hi)
                if abs(tn - t) <= 1e-15 * (1.0 + rem) or hi - lo <= 1e-15 * rem:
                    t = tn
                    break
                t = tn
            t = min(max(t, 0.0), rem)
            _, x, _ = _th_state(t, flowing, q, x, v, ta, a, tth, s, dlt)
            q = 0.0
            rem -= t
            flowing = not flowing
            if rem <= 0.0:
                break
        # exact balance: q1 - q0 = ve h - out - a tau_th (X1 - X0)
        out[k] = v * h - (q - qs) - a * tth * (x - xs)
        if want_vn:
            vn_node[k + 1] = max(q, 0.0) / ta
    return q + kc, x


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
        p = tau / n * vref * xn
        d = tau * xn / x if x > 0.0 else 1e30
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


@njit(cache=True)
def _general_row(ve, iv, dt, vhead, hgt, on, c, af, p0, out, vn_node, want_vn):
    """Exponentially fitted theta scheme for the full nonlinear Preq and thermal ooze, one
    parameter set (row iv of ve, coefficients c). dt, vhead (mm/s), hgt (mm), on (bool)
    per interval; af filament area mm^2; p0 initial P (mm). Writes out (n_int,) mm of
    filament out of the nozzle per interval, vn_node (n_int+1,) mm/s if want_vn;
    returns (P_end, X_end).
    """
    n_int = dt.shape[0]
    a = c[C_ATH]
    tauth = max(c[C_TAUTH], 1e-9)
    p = p0
    vn0 = 0.0
    xth = 0.0
    if want_vn:
        vn_node[0] = 0.0
    # Preq and dPreq/dvn at vn0 as the previous interval's Newton solve left them, valid
    # while that interval had the same head speed, height and track state: most
    # intervals then cost one or two Preq evaluations instead of four.
    have = False
    p_at = 0.0
    d_at = 0.0
    vh_prev = -1.0
    h_prev = -1.0
    on_prev = False
    for k in range(n_int):
        h = dt[k]
        v = ve[iv, k]
        vh = vhead[k]
        hk = hgt[k]
        onk = on[k]
        # Thermal source over the step, a*(X - vn)*dt, written as a*tau_th*(X0 - X1)
        # with X updated exactly for the mean outflow: conserves volume exactly.
        eth = math.exp(-h / tauth) if a != 0.0 else 1.0
        ah = a * tauth * (1.0 - eth)
        hh = h + ah
        # Local time constant at a representative outflow (vn0, or the command at a start).
        vloc = vn0
        if vloc < 1e-6:
            vloc = max(0.5 * v, 1e-6)
        if have and vloc == vn0 and vh == vh_prev and hk == h_prev and onk == on_prev:
            ploc, dloc = p_at, d_at
        else:
            ploc, dloc = _preq(vloc, c, af, vh, hk, onk)
        vh_prev = vh
        h_prev = hk
        on_prev = onk
        r = hh / max(dloc, 1e-12)
        if r < 1e-4:
            th = 0.5 + r / 12.0
        elif r > 50.0:
            th = 1.0 - 1.0 / r
        else:
            th = 1.0 / (1.0 - math.exp(-r)) - 1.0 / r
        b = p + h * v + ah * xth - hh * (1.0 - th) * vn0
        cc = hh * th
        p00 = _preq0(c, vh, onk)
        if b <= p00:
            vn1 = 0.0
            p1 = b
            have = False
        else:
            # g(x) = Preq(x) + cc*x - b is increasing with g(0+) < 0 <= g(b/cc).
            # Newton from the linearised guess; a step leaving the bracket falls back to
            # an Illinois false-position step (bisection stalls near vn = 0 for the
            # concave power law, where Newton from the right overshoots below zero).
            lo = 0.0
            glo = p00 - b
            hi = b / cc
            ghi = -1.0          # g(hi) >= 0; evaluated only if a fallback step needs it
            v0 = max(vn0, 1e-12)
            if v0 == vloc:
                pv, dv = ploc, dloc
            else:
                pv, dv = _preq(v0, c, af, vh, hk, onk)
            x = (b - pv + dv * vn0) / (dv + cc)
            if not (lo < x < hi):
                x = min(max(vn0, 1e-12), 0.5 * hi)
            side = 0
            tol = 1e-13 * (1.0 + b)
            xe = x               # last point where Preq was evaluated, and its values
            pe = pv
            de = dv
            for _ in range(60):
                pe, de = _preq(x, c, af, vh, hk, onk)
                xe = x
                g = pe + cc * x - b
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
                        if ghi < 0.0:
                            ghi = _preq(hi, c, af, vh, hk, onk)[0] + cc * hi - b
                        ghi *= 0.5
                    side = -1
                xn = x - g / (de + cc)
                newton = lo < xn < hi
                if not newton:
                    if ghi < 0.0:
                        ghi = _preq(hi, c, af, vh, hk, onk)[0] + cc * hi - b
                    xn = (lo * ghi - hi * glo) / (ghi - glo)
                    if not (lo < xn < hi):
                        xn = 0.5 * (lo + hi)
                # A Newton step of relative size 1e-9 leaves an error ~1e-18 (quadratic
                # convergence): stop without another evaluation.
                if abs(xn - x) <= (1e-9 if newton else 1e-14) * (1.0 + x):
                    x = xn
                    break
                x = xn
            vn1 = x
            p1 = b - cc * vn1
            have = True
            p_at = pe + de * (x - xe)
            d_at = de
        vbar = (1.0 - th) * vn0 + th * vn1
        out[k] = vbar * h
        xth = vbar + (xth - vbar) * eth
        p = p1
        vn0 = vn1
        if want_vn:
            vn_node[k + 1] = vn1
    return p, xth


@njit(cache=True)
def _nozzle_row(mode, ve, iv, dt, vhead, hgt, on, c, af, p0, out, vn_node, want_vn):
    """One parameter set through the kernel of ``mode``; returns (P_end, X_end)."""
    if mode == MODE_LINEAR:
        return _linear_row(ve, iv, dt, c[C_TAU], c[C_KC], p0, out, vn_node, want_vn), 0.0
    if mode == MODE_THERMAL:
        return _thermal_row(ve, iv, dt, c[C_TAU], c[C_KC], c[C_ATH], c[C_TAUTH], p0, out,
                            vn_node, want_vn)
    return _general_row(ve, iv, dt, vhead, hgt, on, c, af, p0, out, vn_node, want_vn)


def nozzle_kernel(mode, ve, ve_per_set, dt, vhead, hgt, on, coef, af, p0, out, vn_node, p_end, x_end):
    """All parameter sets through the nozzle: ve (n_sets or 1, n_int) mm/s, coef
    (n_sets, N_COEF), p0 (n_sets,). Writes out (n_sets, n_int) mm, vn_node (n_sets,
    n_int+1) mm/s, p_end, x_end (n_sets,)."""
    n_sets = coef.shape[0]
    for i in prange(n_sets):
        pe, xe = _nozzle_row(mode, ve, i * ve_per_set, dt, vhead, hgt, on, coef[i], af, p0[i],
                             out[i], vn_node[i], True)
        p_end[i] = pe
        x_end[i] = xe


def predict_kernel(mode, ve, ve_per_set, dt, vhead, hgt, on, coef, af, p0, dmap, area):
    """Nozzle then deposit (:func:`deposit_kernel`) per parameter set, without keeping the
    per-interval outflow: writes only the station cross-sections area (n_sets, n_s) mm^2."""
    n_sets = coef.shape[0]
    n_int = dt.shape[0]
    for i in prange(n_sets):
        out = np.empty(n_int)
        vn = np.empty(n_int + 1)
        cbuf = np.empty(max(dmap[0].shape[0], 1))
        _nozzle_row(mode, ve, i * ve_per_set, dt, vhead, hgt, on, coef[i], af, p0[i], out, vn, True)
        _deposit_row(out, vn, dmap, af, area[i], cbuf)


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


@njit(cache=True)
def _placed(f, r0, r1):
    """Fraction of an interval's deposit laid before fraction f of its arc length when
    the outflow varies linearly from r0 to r1 over it (head speed constant within the
    interval): F(f) = (r0 f + (r1 - r0) f^2 / 2) / ((r0 + r1) / 2); f if no flow."""
    sm = r0 + r1
    if sm <= 0.0 or r0 == r1:
        return f
    return f * (2.0 * r0 + (r1 - r0) * f) / sm


@njit(cache=True)
def _deposit_row(out, vn, dmap, af, area, c):
    """One parameter set of :func:`deposit_kernel`; vn (n_int+1,) outflow at the nodes,
    c a scratch array (len(perm),)."""
    perm, lo_pos, lo_frac, lo_int, hi_pos, hi_frac, hi_int, inv_win = dmap
    m = perm.shape[0]
    n_s = lo_pos.shape[0]
    if m == 0:
        for k in range(n_s):
            area[k] = 0.0
        return
    acc = 0.0
    for j in range(m):
        acc += out[perm[j]]
        c[j] = acc
    for k in range(n_s):
        iw = inv_win[k]
        if iw > 0.0:
            ia = lo_int[k]
            ib = hi_int[k]
            v_lo = c[lo_pos[k]] - (1.0 - _placed(lo_frac[k], vn[ia], vn[ia + 1])) * out[ia]
            v_hi = c[hi_pos[k]] - (1.0 - _placed(hi_frac[k], vn[ib], vn[ib + 1])) * out[ib]
            area[k] = (v_hi - v_lo) * af * iw
        else:
            area[k] = 0.0


def deposit_kernel(out, vn_node, dmap, af, area):
    """Cross-section A_i (mm^2) over the station windows (fit/context.py):
    V(s_b) = C[pos] - (1 - F(frac)) * dV[perm[pos]],  C = cumsum(dV[perm]),  dV = Af * out,
    A_i = (V(hi_i) - V(lo_i)) / win_i, with F (:func:`_placed`) placing each interval's
    deposit along its arc length by the outflow at its two nodes (linear in between:
    second order in dt/tau, where a uniform placement is first order). dmap:
    :attr:`fit.context.SimContext.deposit_map`."""
    n_sets = out.shape[0]
    m = dmap[0].shape[0]
    for i in prange(n_sets):
        c = np.empty(max(m, 1))
        _deposit_row(out[i], vn_node[i], dmap, af, area[i], c)


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


def _spread_rows(w, order, s, starts, sig, out):
    """Gaussian smoothing of the widths w (n_sets, n) along each track (fit.effects.Spread):
    ``order`` sorts the stations by (track, s), ``starts`` the track boundaries in it,
    ``sig`` (n_sets,) the sd (mm); NaN widths neither contribute nor change."""
    n_sets = w.shape[0]
    for i in prange(n_sets):
        sg = sig[i]
        if not sg > 0.0:
            for k in range(w.shape[1]):
                out[i, k] = w[i, k]
            continue
        reach = 4.0 * sg
        for t in range(len(starts) - 1):
            a, b = starts[t], starts[t + 1]
            lo = a
            for k in range(a, b):
                ik = order[k]
                sk = s[ik]
                if w[i, ik] != w[i, ik]:
                    out[i, ik] = w[i, ik]
                    continue
                while s[order[lo]] < sk - reach:
                    lo += 1
                acc = 0.0
                tot = 0.0
                m = lo
                while m < b and s[order[m]] <= sk + reach:
                    v = w[i, order[m]]
                    if v == v:
                        d = (s[order[m]] - sk) / sg
                        g = math.exp(-0.5 * d * d)
                        acc += g * v
                        tot += g
                    m += 1
                out[i, ik] = acc / tot


@njit(cache=True)
def _flat_filter(a, n, k, take_max, out):
    """Grey erosion (take_max False) or dilation of ``a[:n]`` with a flat element of ``k``
    samples into ``out[:n]``, window [j - k//2, j + (k-1)//2] clipped to ``a[:n]`` (ends
    continued by their own values)."""
    for j in range(n):
        lo, hi = max(j - k // 2, 0), min(j + (k - 1) // 2, n - 1)
        v = a[lo]
        for q in range(lo + 1, hi + 1):
            if (a[q] > v) if take_max else (a[q] < v):
                v = a[q]
        out[j] = v


@njit(cache=True)
def _sub_station(w, i, f, j, h, st, centre, prev, nxt, own):
    """Laid width (mm) at sub-station j of station st for set i (see :func:`_observe_rows`)."""
    c = w[i, centre[st]]
    if own[st]:
        v = w[i, centre[st] - h + j]
        return v if v == v else c
    a = w[i, prev[st]] if prev[st] >= 0 else np.nan
    b = w[i, nxt[st]] if nxt[st] >= 0 else np.nan
    fj = f[j]
    if a == a and b == b:
        return c + 0.5 * fj * (b - a) + 0.5 * fj * fj * (a - 2.0 * c + b)
    if a == a:
        return c + fj * (c - a)
    if b == b:
        return c + fj * (b - c)
    return c


def _observe_rows(w, lines, f, centre, prev, nxt, own, rows, starts, k, pad, eps, out):
    """fit/observe.py's measurement kernel: the laid widths w (n_sets, m) at the physics
    points read as the stations' widths out (n_sets, n) mm.

    The sub-stations (``f`` (lines,) their offsets in station spacings): a station that
    ``own``s them has them as the points from ``centre[st] - lines // 2`` on; another has
    the quadratic through the centres of its track neighbours (points ``prev``/``nxt``, -1:
    none) and its own at f (Lagrange at -1, 0, 1: f (f - 1) / 2, 1 - f^2, f (f + 1) / 2),
    the line through two where one neighbour is missing, its centre where both are. A NaN
    sub-station takes its station's centre; each station reads the mean of its
    sub-stations, NaN where its centre is.

    Along each despeckled run (the sub-stations ``rows[starts[r]:starts[r + 1]]``,
    station-major, continued by ``pad`` copies of its end values on both sides as the
    measurement filters it; NaN read as 0) the sub-stations then read the mean of the
    run's open-close and close-open (flat element ``k`` samples). Only the places j whose
    reach [j - R, j + R], R = 4 (k // 2) <= pad, holds a turn of the run (a rise and a fall
    by more than ``eps`` mm, in either order) are filtered: the four filters reach R
    samples, and all of them leave a sequence that is monotone over [j - R, j + R] as it is
    at j, so the rest is exact as it stands. The end copies are flat, so a turn lies inside
    a run; a place is filtered on a stretch reaching R beyond it, its entries past the run's
    ends read the end values, as in the padded run. A run of interpolated stations whose
    centres (with the neighbours they are interpolated from) do not turn is not filtered:
    the quadratics through monotone centres are monotone over |f| <= 0.4, so what turns is
    only where one station's quadratic meets the next's, by the interpolation's own error."""
    n_sets = w.shape[0]
    n = out.shape[1]
    n_runs = len(starts) - 1
    R = 4 * (k // 2)
    h = lines // 2
    l_max = 0
    for r in range(n_runs):
        l_max = max(l_max, starts[r + 1] - starts[r])
    m2 = 0.0
    for j in range(lines):
        m2 += f[j] * f[j] / lines
    for i in prange(n_sets):
        for st in range(n):
            c = w[i, centre[st]]
            if c != c:
                out[i, st] = np.nan
            elif own[st]:
                acc = 0.0
                for q in range(centre[st] - h, centre[st] - h + lines):
                    v = w[i, q]
                    acc += v if v == v else c
                out[i, st] = acc / lines
            else:
                a = w[i, prev[st]] if prev[st] >= 0 else np.nan
                b = w[i, nxt[st]] if nxt[st] >= 0 else np.nan
                # the quadratic's mean over the symmetric offsets; a line's is c
                out[i, st] = c + 0.5 * m2 * (a - 2.0 * c + b) if (a == a and b == b) else c
        seq = np.empty(l_max)
        mark = np.empty(l_max, np.bool_)
        # the filters' work space: a stretch is at most a run and R + pad each side
        seg = np.empty(l_max + 2 * (R + pad))
        t1 = np.empty_like(seg)
        t2 = np.empty_like(seg)
        oc = np.empty_like(seg)
        co = np.empty_like(seg)
        for r in range(n_runs):
            r0 = starts[r]
            L = starts[r + 1] - r0
            # interpolated stations only, and their centres do not turn: nothing to filter
            needed = False
            last_sign = 0
            prev_v = 0.0
            first = True
            for jj in range(0, L, lines):
                st = rows[r0 + jj] // lines
                if own[st]:
                    needed = True
                    break
                for which in range(3):
                    if which == 0:
                        if jj != 0 or prev[st] < 0:
                            continue
                        v = w[i, prev[st]]
                    elif which == 1:
                        v = w[i, centre[st]]
                    else:
                        if jj != L - lines or nxt[st] < 0:
                            continue
                        v = w[i, nxt[st]]
                    v = v if v == v else 0.0
                    if not first:
                        d = v - prev_v
                        sg = 1 if d > eps else (-1 if d < -eps else 0)
                        if sg != 0:
                            if last_sign != 0 and sg != last_sign:
                                needed = True
                            last_sign = sg
                    first = False
                    prev_v = v
                if needed:
                    break
            if not needed:
                continue
            for j in range(L):
                q = rows[r0 + j]
                st = q // lines
                c = w[i, centre[st]]
                v = _sub_station(w, i, f, q - st * lines, h, st, centre, prev, nxt, own) if c == c else np.nan
                seq[j] = v if v == v else 0.0
            any_mark = False
            last_sign = 0
            last_j = 0
            for j in range(L):
                mark[j] = False
            for j in range(1, L):
                d = seq[j] - seq[j - 1]
                sg = 1 if d > eps else (-1 if d < -eps else 0)
                if sg != 0:
                    # a rise at last_j and a fall at j (or the reverse), nothing between: the
                    # places whose reach holds both
                    if last_sign != 0 and sg != last_sign:
                        for q in range(max(j - R, 0), min(last_j - 1 + R, L - 1) + 1):
                            mark[q] = True
                        any_mark = True
                    last_sign = sg
                    last_j = j
            if not any_mark:
                continue
            j = 0
            while j < L:
                if not mark[j]:
                    j += 1
                    continue
                a = j
                while j < L and mark[j]:
                    j += 1
                sa, sb = max(a - R, -pad), min(j + R, L + pad)
                m = sb - sa
                for p in range(sa, sb):
                    seg[p - sa] = seq[min(max(p, 0), L - 1)]
                _flat_filter(seg, m, k, False, t1)           # open, then close: oc
                _flat_filter(t1, m, k, True, t2)
                _flat_filter(t2, m, k, True, t1)
                _flat_filter(t1, m, k, False, oc)
                _flat_filter(seg, m, k, True, t1)            # close, then open: co
                _flat_filter(t1, m, k, False, t2)
                _flat_filter(t2, m, k, False, t1)
                _flat_filter(t1, m, k, True, co)
                for q in range(a, j):
                    sub = rows[r0 + q]
                    st = sub // lines
                    if out[i, st] == out[i, st]:
                        out[i, st] += (0.5 * (oc[q - sa] + co[q - sa]) - seq[q]) / lines


# Each kernel twice: serial (one or a few parameter sets: no thread start-up cost) and
# parallel over parameter sets (prange; emcee ensembles, 64+ sets).
_PY = {"nozzle": nozzle_kernel, "predict": predict_kernel, "deposit": deposit_kernel,
       "bead_width": bead_width_kernel, "spread": _spread_rows, "observe": _observe_rows}


def _renamed(f, suffix: str):
    """A copy of f with its own __qualname__. numba names its on-disk cache by the
    function's qualified name and line, not by the compile flags: compiling the same
    function serial and parallel=True with cache=True made the two share one cache entry,
    so whichever compiled first was loaded for both (the parallel kernels ran serial)."""
    g = types.FunctionType(f.__code__, f.__globals__, f.__name__ + suffix, f.__defaults__,
                           f.__closure__)
    g.__qualname__ = f.__qualname__ + suffix
    g.__doc__ = f.__doc__
    return g


def serial_and_parallel(f):
    """(serial, parallel=True) numba builds of the prange function f, cached apart."""
    return (njit(cache=True)(_renamed(f, "_serial")),
            njit(cache=True, parallel=True)(_renamed(f, "_parallel")))


_BUILDS = {k: serial_and_parallel(f) for k, f in _PY.items()}
SERIAL = {k: b[0] for k, b in _BUILDS.items()}
PARALLEL = {k: b[1] for k, b in _BUILDS.items()}
#: Parameter sets from which the parallel kernels pay off.
PARALLEL_MIN_SETS = 4


def set_threads(n: int | None) -> int:
    """Threads the parallel kernels use (None: every core numba sees); returns the count.
    Worker processes of a batch each take their share, so that jobs x threads does not
    oversubscribe the cores."""
    import numba

    n = numba.config.NUMBA_NUM_THREADS if n is None else max(1, min(int(n), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


def kernel(name: str, n_sets: int):
    """The compiled kernel ``name`` suited to ``n_sets`` parameter sets."""
    return (PARALLEL if n_sets >= PARALLEL_MIN_SETS else SERIAL)[name]
