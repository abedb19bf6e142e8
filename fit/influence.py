"""Which widths move which parameter: the fit's linear response to a change in the data.

At the MAP theta of a fit, a small change e (mm) of the measured widths moves the
parameters by (Gauss-Newton, noise parameters held at the MAP):

    d theta = A e,   A = (Jw^T Jw + P)^-1 Jw^T M,   Jw = M J                         (1)

J (n, p): d(model width)/d(theta) at the stations (mm per parameter unit, central
differences); M (n, n): the noise model's whitening (the Kalman innovations v / sqrt(F)
of fit/likelihood.py, linear in the residual), so Jw^T Jw is the Fisher information of
the widths; P: the curvature of the log prior (normal priors such as `scan_bias`'s).

Why: a measurement error that is small against the noise can still move a parameter by
several of its sd when it sits where that parameter's information is. Given the
measurement's error against a known truth (a render), A e says how far each parameter
moves and ``attribute`` says which stations do it, so a bias can be traced to the part of
the picture that causes it (bench/bench_e2e.py, issue #11: the back-pressure fits' Kb bias
traced to glare, the beads whose flanks do not face the scanner's lamp reading ~2.5 um
narrower than the rest, which pulls Kb through the first 0.25 s after each flow change).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fit.likelihood import _kalman, ar1_phi, is_noise

#: stations whitened per batch when building M (memory: batch x n doubles)
_BATCH = 512


@dataclass
class Influence:
    """Linear response of the MAP to the widths of one scan (eq. 1).

    names    the parameters that respond (the noise parameters are held fixed)
    A        (p, n) d theta / d y (parameter unit per mm of width), columns in ``rows`` order
    rows     (n,) the widths table rows of the scan's valid stations (ScanData.order)
    theta    the MAP the response is taken at (all parameters of the problem)
    """

    names: list
    A: np.ndarray
    rows: np.ndarray
    theta: np.ndarray

    def shift(self, error_mm) -> dict:
        """Parameter shifts (eq. 1) caused by a width error per station (mm, ``rows`` order;
        NaN counts as 0)."""
        e = np.nan_to_num(np.asarray(error_mm, dtype=float))
        return dict(zip(self.names, (self.A @ e).tolist()))

    def attribute(self, name: str, error_mm, groups) -> dict:
        """The shift of parameter ``name`` caused by ``error_mm``, summed per group label
        (``groups``: one label per station, ``rows`` order): the parts add up to the whole."""
        e = np.nan_to_num(np.asarray(error_mm, dtype=float))
        c = self.A[self.names.index(name)] * e
        groups = np.asarray(groups)
        return {g: float(c[groups == g].sum()) for g in np.unique(groups)}


def whitening_matrix(sc, sigma_extra_mm: float, corr_len_mm: float | None, sigma_short_mm: float = 0.0,
                     short_corr_mm: float = 0.4, rel_mm=None, link=None, rho_m: float = 0.0) -> np.ndarray:
    """M (n, n) with M @ x = fit.likelihood.whiten(x, ...) for the scan's valid stations
    (its sd_mm and gap_mm; ``link``, ``rho_m``: its linked measurement errors,
    JointProblem.meas_parts; ``rel_mm`` (n,) the relative wobble's sd at each, mm, or None):
    the whitening is linear in x, so M is it applied to the unit vectors."""
    n = len(sc.y_mm)
    cols = []
    for k0 in range(0, n, _BATCH):
        eye = np.zeros((min(_BATCH, n - k0), n))
        eye[np.arange(len(eye)), k0 + np.arange(len(eye))] = 1.0
        cols.append(_whiten_rows(sc, eye, sigma_extra_mm, corr_len_mm, sigma_short_mm, short_corr_mm, rel_mm,
                                 link, rho_m))
    return np.vstack(cols).T


def _whiten_rows(sc, X, sigma_extra_mm, corr_len_mm, sigma_short_mm, short_corr_mm, rel_mm, link, rho_m):
    """Each row of X (m, n) whitened by scan ``sc``'s noise model (as :func:`whitening_matrix`)."""
    sd2 = np.asarray(sc.sd_mm, dtype=float) ** 2
    g = np.asarray(sc.gap_mm, dtype=float)
    phi = None if corr_len_mm is None else ar1_phi(g, [[corr_len_mm]])
    short = phi is not None and sigma_short_mm > 0
    m = X.shape[0]
    v, F = _kalman(X, sd2, np.full(m, sigma_extra_mm ** 2),
                   None if phi is None else np.broadcast_to(phi, X.shape),
                   np.full(m, sigma_short_mm ** 2) if short else None,
                   np.broadcast_to(ar1_phi(g, [[short_corr_mm]]), X.shape) if short else None,
                   None if rel_mm is None else np.broadcast_to(np.asarray(rel_mm, dtype=float), X.shape),
                   link, np.full(m, float(rho_m)))
    return v / np.sqrt(F)


def _scan_noise(problem, theta, k: int, pred_mm) -> tuple:
    """The whitening arguments of scan ``k`` at ``theta`` (after ``sc``, ``X``)."""
    i_sig, i_cor, i_short = problem.noise_index[k]
    fixed, rel = problem.wobble_parts(theta, k, pred_mm)
    return (fixed, None if i_cor is None else float(theta[i_cor]),
            0.0 if i_short is None else float(theta[i_short]), problem.noise.short_corr_mm, rel,
            *problem.meas_parts(theta, k))


def _jacobian(problem, theta, k: int, free, rel_step: float) -> np.ndarray:
    """d(model width)/d(theta) (n_valid, len(free)) at scan ``k``'s valid stations (mm per
    parameter unit; central differences, one-sided at a bound)."""
    sc = problem.scans[k]
    lo, hi = problem.bounds.T
    J = np.empty((len(sc.order), len(free)))
    for j, i in enumerate(free):
        h = rel_step * max(abs(theta[i]), 1e-3)
        # a one-sided difference at a bound (a parameter at 0 with a lower bound of 0)
        up, dn = min(theta[i] + h, hi[i]), max(theta[i] - h, lo[i])
        tp, tm = theta.copy(), theta.copy()
        tp[i], tm[i] = up, dn
        J[:, j] = (problem.predict(tp[None], k)[0, sc.order] - problem.predict(tm[None], k)[0, sc.order]) / (up - dn)
    return J


def _prior_curvature(problem, theta, free, rel_step: float) -> np.ndarray:
    """P (len(free), len(free)): minus the log prior's second derivative on the diagonal."""
    lo, hi = problem.bounds.T
    P = np.zeros((len(free), len(free)))
    for j, i in enumerate(free):
        h = rel_step * max(abs(theta[i]), 1e-3)
        up, dn = min(theta[i] + h, hi[i]), max(theta[i] - h, lo[i])
        lp = [float(problem.priors[i].log_prob(np.array([x]))[0]) for x in (dn, theta[i], up)]
        if all(np.isfinite(lp)) and up - theta[i] > 0 and theta[i] - dn > 0:
            P[j, j] = max(0.0, -(lp[2] - 2 * lp[1] + lp[0]) / ((up - dn) / 2) ** 2)
    return P


def influence(problem, theta, k: int = 0, rel_step: float = 1e-4) -> Influence:
    """The MAP's linear response (eq. 1) to the widths of scan ``k`` of ``problem``
    (fit.likelihood.JointProblem) at ``theta`` (its MAP)."""
    theta = np.asarray(theta, dtype=float)
    sc = problem.scans[k]
    free = [i for i, name in enumerate(problem.param_names) if not is_noise(name)]
    J = _jacobian(problem, theta, k, free, rel_step)
    P = _prior_curvature(problem, theta, free, rel_step)
    M = whitening_matrix(sc, *_scan_noise(problem, theta, k, problem.predict(theta[None], k)[0, sc.order]))
    Jw = M @ J
    # least squares for the reason given in offset_response: a parameter at a flat-prior
    # bound where the widths do not move it (spread's sigma at 0) has no response
    A = np.linalg.lstsq(Jw.T @ Jw + P, Jw.T @ M, rcond=None)[0]
    return Influence(names=[problem.param_names[i] for i in free], A=A, rows=np.asarray(sc.order), theta=theta)


def offset_response(problem, theta, rel_step: float = 1e-4) -> tuple[list, np.ndarray]:
    """How the MAP moves when every width of one scan is off by the same amount: (names of
    the parameters that respond, R (n_scans, len(names)) in parameter units per mm of
    offset). Eq. 1 with e = 1 at every valid station of scan k and 0 elsewhere, the
    information summed over all scans (a shared parameter is held by the others too):
    R_k = (sum_j Jw_j^T Jw_j + P)^-1 Jw_k^T (M_k 1). Each whitening is one pass of the
    Kalman filter over a vector, so no (n, n) matrix is formed."""
    return direction_response(problem, theta, [(k, np.ones(len(sc.order))) for k, sc in enumerate(problem.scans)],
                              rel_step)


def direction_response(problem, theta, directions, rel_step: float = 1e-4) -> tuple[list, np.ndarray]:
    """:func:`offset_response` for width errors of any shape: ``directions`` [(k, e)], e
    (n_valid of scan k,) the error of each valid station (``ScanData.order`` order, mm per
    unit); returns (names, R (len(directions), len(names))), parameter units per unit."""
    theta = np.asarray(theta, dtype=float)
    free = [i for i, name in enumerate(problem.param_names) if not is_noise(name)]
    info = _prior_curvature(problem, theta, free, rel_step)
    rhs = np.zeros((len(directions), len(free)))
    for k, sc in enumerate(problem.scans):
        mine = [i for i, (kk, _) in enumerate(directions) if kk == k]
        J = _jacobian(problem, theta, k, free, rel_step)
        E = np.array([np.asarray(directions[i][1], dtype=float) for i in mine]).reshape(len(mine), len(sc.order))
        W = _whiten_rows(sc, np.vstack([J.T, E]),
                         *_scan_noise(problem, theta, k, problem.predict(theta[None], k)[0, sc.order]))
        Jw = W[:len(free)].T
        info = info + Jw.T @ Jw
        if mine:
            rhs[mine] = (Jw.T @ W[len(free):].T).T
    # least squares, not solve: a parameter the widths do not move where it sits (spread's
    # sigma at 0, flat prior) leaves info singular and has no response (bench_e2e seed 1:
    # `pa+spread` raised "Singular matrix")
    R = np.linalg.lstsq(info, rhs.T, rcond=None)[0].T
    return [problem.param_names[i] for i in free], R
