"""Sub-pixel bead edges from intensity profiles across the track.

The bead seen across its axis is a box of width ``w`` blurred by the optics (Gaussian of
sd ``s``) on a locally linear background (uneven light). With profile coordinate ``t``
(mm along the track normal, 0 at the nominal centre) the edge-pair model is

    f(t) = b0 + b1*t + A/2 * [erf((t - c + w/2)/(sqrt2 s)) - erf((t - c - w/2)/(sqrt2 s))]

(shared/REFERENCE.md "Measuring width in images": sd 2 um at 600 dpi with this model).
``A`` > 0 is light plastic on a dark plate, ``A`` < 0 dark plastic on a light plate.

Glare: glossy plastic lit from one side shows a specular streak on the flank facing the
light, a line narrower than the optics' blur inside that edge, where the flank's slope is
half the light's zenith angle (15-30 deg for a lamp or window 30-60 deg above the bed:
0.5-0.75 of the flank's radius h/2 from the edge on a round flank). It brightens the
edge's shoulder, and the plain model read the bead up to +12 um wide at the headings
facing the light (600 dpi flatbed render). :func:`fit_streak` adds it:

    f_g(t) = f(t) + G * exp(-(t - c_g)^2 / (2 s^2)),   c_g = c + side * (w/2 - d)

with G >= 0 (specular light only adds, whatever the polarity) and the depth d inside the
edge bounded to the outer flank, STREAK_FLANK x h/2 (mm). Both bounds matter: a free
position fits the crown's Lambert shading as a "streak" and shrank every bead by 15-20 um;
a streak allowed onto the edge itself is an edge shift, and with the blur free the
prime line's sections then disagreed by 18 um.

:func:`fit_profiles` fits many profiles at once with a batched Levenberg-Marquardt
(no Python loop over profiles; the model, its Jacobian and J^T J of every profile in one
compiled kernel, :func:`_normal_kernel`): the same least-squares problem that
``scipy.optimize.least_squares`` would solve one profile at a time, ~100x faster.
The covariance is ``inv(J^T J) * RSS / (M - p)`` (residual variance scaled).
"""
from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np
from numba import njit, prange
from scipy.special import erf

SQRT2 = np.sqrt(2.0)
_TWO_OVER_SQRTPI = 2.0 / np.sqrt(np.pi)

#: Parameter order of the edge-pair model.
PARAMS = ("b0", "b1", "A", "c", "w", "s")
#: Parameter order of the edge pair with a glare streak (:func:`fit_streak`).
STREAK_PARAMS = PARAMS + ("G", "d")
#: Where on the flank the streak may sit: depth d inside its edge, as fractions of the
#: flank radius h/2 (module docstring: 0.5-0.75 for light 30-60 deg above the bed). The
#: lower bound is active on strong streaks, and it matters: on 600 dpi flatbed renders
#: (glare from 45 deg, true depth 0.62) the prime line read -36 um with 0.4, -41 with 0.3,
#: -32 with 0.5 (the streak-free truth: -34 um).
STREAK_FLANK = (0.4, 1.0)
#: The LM stops when its step moves the fitted profile by less than this fraction of the
#: residual sd (:func:`_fit_chunk`): every parameter within this fraction of its sd.
OFFSET_TOL = 1e-3


@dataclass
class ProfileFit:
    """Fitted edge-pair parameters for N profiles (all lengths in the profile's unit, mm).

    params (N, 6) in PARAMS order; sd (N, 6) one-sigma from the scaled covariance;
    rms (N,) residual RMS (intensity); ok (N,) converged with finite, positive w and s.
    """

    params: np.ndarray
    sd: np.ndarray
    rms: np.ndarray
    ok: np.ndarray

    @property
    def width(self) -> np.ndarray:
        return self.params[:, 4]

    @property
    def width_sd(self) -> np.ndarray:
        return self.sd[:, 4]

    @property
    def centre(self) -> np.ndarray:
        return self.params[:, 3]

    @property
    def amplitude(self) -> np.ndarray:
        return self.params[:, 2]


def edge_pair(t, p) -> np.ndarray:
    """Model f(t) for profiles t (N, M) and parameters p (N, 6); see module docstring."""
    b0, b1, A, c, w, s = (p[:, k:k + 1] for k in range(6))
    z1 = (t - c + w / 2) / (SQRT2 * s)
    z2 = (t - c - w / 2) / (SQRT2 * s)
    return b0 + b1 * t + 0.5 * A * (erf(z1) - erf(z2))


def width_per_blur(t, p, weights=None, h: float = 1e-4, chunk: int = 2000, amp_lam=None) -> np.ndarray:
    """dw/ds (mm per mm) of a fit with the blur held at s: how far the fitted width moves
    when the blur it was held at is off, the other parameters (b0, b1, A, c) refitting.

    Linearised least squares: with J the Jacobian of :func:`edge_pair` in (b0, b1, A, c, w)
    and g = df/ds at p, the fit's parameters move by -(J'WJ)^-1 J'W g per unit of s (W the
    weights), and dw/ds is that move's w component. For a box of width w and blur s it is
    a function of w / s and the window: with 0.5 mm + 3 s beyond each edge about -0.5 at
    w = 6 s, -1.4 at 4 s, -2.5 at 3 s, -4.8 at 2 s and -7.1 at 1.5 s (a narrow bead's
    profile is the blur's: its width and height trade, its area A w stays).
    ``amp_lam`` (N,): the fit's prior on A (:func:`fit_profiles` ``amp_prior``'s lam), in
    J'WJ as in the fit: with the contrast known, a narrow bead's width is its area's and
    hardly moves with the blur.
    t (N, M) mm, p (N, 6), weights (N, M) 0/1; NaN where singular.
    """
    t = np.asarray(t, float)
    p = np.asarray(p, float)
    wts = np.ones_like(t) if weights is None else np.asarray(weights, float)
    lam = np.zeros(len(p)) if amp_lam is None else np.broadcast_to(np.asarray(amp_lam, float), (len(p),))
    if len(p) > chunk:
        return np.concatenate([width_per_blur(t[i:i + chunk], p[i:i + chunk], wts[i:i + chunk], h, chunk,
                                              lam[i:i + chunk]) for i in range(0, len(p), chunk)])
    f0 = edge_pair(t, p)
    cols = []
    for k in range(6):
        dp = np.zeros_like(p)
        dp[:, k] = h
        cols.append((edge_pair(t, p + dp) - f0) / h)
    J = np.stack(cols[:5], axis=-1) * np.sqrt(wts)[..., None]          # (N, M, 5)
    g = cols[5] * np.sqrt(wts)
    JTJ = np.einsum("nmi,nmj->nij", J, J)
    JTJ[:, 2, 2] += lam
    JTg = np.einsum("nmi,nm->ni", J, g)
    out = np.full(len(p), np.nan)
    ok = np.isfinite(JTJ).all(axis=(1, 2)) & np.isfinite(JTg).all(axis=1) & (np.abs(np.linalg.det(JTJ)) > 0)
    if ok.any():
        out[ok] = -np.linalg.solve(JTJ[ok], JTg[ok][..., None])[:, 4, 0]
    return out


#: Beyond |z| = 6, erf(z) is +-1 in double precision (erfc(6) = 2e-17) and the Gaussian
#: 2/sqrt(pi) exp(-z^2) under 3e-16: the kernel skips them for the samples that far from
#: both edges (the fitted widths of a 12 MP photo's profiles move by 0.02 um at most).
_ERF_CUT = 6.0
#: The same for the streak's exp(-u^2 / 2): under 2.3e-16 beyond u^2 = 72.
_GAUSS_CUT2 = 72.0


@njit(cache=True, inline="always")
def _erf_gauss(z):  # pragma: no cover - numba
    """(erf(z), 2/sqrt(pi) exp(-z^2)), exact to double precision, cheap far from 0."""
    if z > _ERF_CUT:
        return 1.0, 0.0
    if z < -_ERF_CUT:
        return -1.0, 0.0
    return math.erf(z), _TWO_OVER_SQRTPI * math.exp(-z * z)


@njit(cache=True, inline="always")
def _norm_cdf_pdf(z):  # pragma: no cover - numba
    """(Phi(z), phi(z)) of the standard normal, exact to double precision."""
    if z > 2 * _ERF_CUT:
        return 1.0, 0.0
    if z < -2 * _ERF_CUT:
        return 0.0, 0.0
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0))), math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


@njit(cache=True, parallel=True)
def _normal_kernel(t, y, wts, p, rows, fixed_s, side, shade, cost, JTJ, JTr):  # pragma: no cover - numba
    """For profiles ``rows``: the weighted residual sum of squares ``cost`` and the normal
    equations J^T W J, J^T W r of the edge pair (plus the streak when ``side`` != 0, the
    shadow's shelf when ``shade`` != 0) at parameters p[rows], written into row ii of the
    outputs for profile rows[ii].

    Fused and compiled: evaluating the model and Jacobian as (N, M, k) numpy arrays and
    multiplying them was 90 % of a 12 MP photo's measurement (erf, exp and copies)."""
    k = JTJ.shape[1]
    m = t.shape[1]
    for ii in prange(len(rows)):
        i = rows[ii]
        b0, b1, A, c, w, s = p[i, 0], p[i, 1], p[i, 2], p[i, 3], p[i, 4], p[i, 5]
        kk = 1.0 / (math.sqrt(2.0) * s)
        G = p[i, 6] if side != 0.0 else 0.0
        cg = c + side * (w / 2 - p[i, 7]) if side != 0.0 else 0.0
        D = p[i, 8] if shade != 0.0 else 0.0
        ea = c + shade * w / 2                   # the shadow from the edge, full out to L,
        L = p[i, 9] if shade != 0.0 else 0.0
        P = p[i, 10] if shade != 0.0 else 1.0    # then fading over the penumbra P
        col = np.empty(k)
        a_ = np.zeros((k, k))
        v = np.zeros(k)
        cst = 0.0
        for j in range(m):
            wt = wts[i, j]
            if wt == 0.0:
                continue
            tt = t[i, j]
            z1 = (tt - c + w / 2) * kk
            z2 = (tt - c - w / 2) * kk
            e1, g1 = _erf_gauss(z1)
            e2, g2 = _erf_gauss(z2)
            half = 0.5 * (e1 - e2)
            f = b0 + b1 * tt + A * half
            col[0] = 1.0
            col[1] = tt
            col[2] = half
            col[3] = 0.5 * A * kk * (g2 - g1)
            col[4] = 0.25 * A * kk * (g1 + g2)
            q = 5
            g = 0.0
            if not fixed_s:
                col[5] = 0.5 * A / s * (z2 * g2 - z1 * g1)
                q = 6
            if side != 0.0:
                d = tt - cg
                u2 = (d / s) ** 2
                g = math.exp(-0.5 * u2) if u2 < _GAUSS_CUT2 else 0.0
                f += G * g
                dg = G * g * d / (s * s)        # d f / d c_g
                col[3] += dg
                col[4] += 0.5 * side * dg
                if not fixed_s:                 # the streak is as wide as the blur
                    col[5] += dg * d / s
                col[q] = g
                col[q + 1] = -side * dg
                q += 2
            box = 0.0
            if shade != 0.0:
                # u outward from the edge; shape = Phi(u/s) - R(u - L), R the unit ramp over
                # P blurred: (psi(x) - psi(x - P)) / P, psi(x) = x Phi(x/s) + s phi(x/s)
                uu = shade * (tt - ea)
                x0 = uu - L
                x1 = x0 - P
                pa, na_ = _norm_cdf_pdf(uu / s)
                p0_, n0 = _norm_cdf_pdf(x0 / s)
                p1, n1 = _norm_cdf_pdf(x1 / s)
                ramp = (x0 * p0_ + s * n0 - x1 * p1 - s * n1) / P
                box = pa - ramp                      # ~1 on the full shadow, 0 beyond it
                f -= D * box
                dsu = D * (na_ / s - (p0_ - p1) / P)   # d S / d u
                col[3] += shade * dsu
                col[4] += 0.5 * dsu
                if not fixed_s:
                    col[5] -= D * (-uu * na_ / (s * s) - (n0 - n1) / P)
                col[q] = -box
                col[q + 1] = -D * (p0_ - p1) / P
                col[q + 2] = D * (p1 / P - ramp / P)
            r = (y[i, j] - f) * wt
            cst += r * r
            # far from both edges and the streak only b0, b1 and A act (the other columns
            # are exactly 0): 6 of the 28 sums of a streak fit
            nz = k if (g1 != 0.0 or g2 != 0.0 or (side != 0.0 and g != 0.0) or box != 0.0) else 3
            for u in range(nz):
                cu = col[u] * wt
                v[u] += cu * r
                for x in range(u, nz):
                    a_[u, x] += cu * col[x] * wt
        for u in range(k):
            JTr[ii, u] = v[u]
            for x in range(u, k):
                JTJ[ii, u, x] = a_[u, x]
                JTJ[ii, x, u] = a_[u, x]
        cost[ii] = cst


def _normal_equations(t, y, wts, p, rows, fixed_s: bool, side: float, shade: float = 0.0):
    """(cost (R,), J^T W J (R, k, k), J^T W r (R, k)) of profiles ``rows`` at parameters p:
    the free parameters are PARAMS (without s when fixed_s), then G, d when ``side`` is
    -1 or +1 (the streak on the low-t or high-t edge), then D, L when ``shade`` is -1 or +1
    (the shadow's shelf outside the low-t or high-t edge)."""
    k = len(_free_columns(fixed_s, side, shade))
    n = len(rows)
    cost, JTJ, JTr = np.empty(n), np.empty((n, k, k)), np.empty((n, k))
    _normal_kernel(t, y, wts, p, rows, bool(fixed_s), float(side), float(shade), cost, JTJ, JTr)
    return cost, JTJ, JTr


def _with_amp_prior(normal, p, rows, amp_prior):
    """The normal equations ``normal`` (cost, J^T W J, J^T W r) of profiles ``rows`` with the
    prior term lam (A - A_ref)^2 on the contrast (:func:`fit_profiles`' ``amp_prior``, (N, 2)
    columns A_ref, lam): a pseudo-observation of A, whose Jacobian is sqrt(lam) on A's
    column (the third free one in every model)."""
    if amp_prior is None:
        return normal
    cost, JTJ, JTr = normal
    a_ref, lam = amp_prior[rows, 0], amp_prior[rows, 1]
    d = a_ref - p[rows, 2]
    JTJ[:, 2, 2] += lam
    JTr[:, 2] += lam * d
    return cost + lam * d * d, JTJ, JTr


def _free_columns(fixed_s: bool, side: float, shade: float = 0.0) -> list[int]:
    cols = [0, 1, 2, 3, 4] + ([] if fixed_s else [5])
    return cols + ([6, 7] if side else []) + ([8, 9, 10] if shade else [])


def initial_guess(t, y, polarity: float, s0) -> np.ndarray:
    """Moment-based start values (N, 6) for :func:`fit_profiles`.

    Background from medians of the outer fifth on each side (robust to a neighbour's
    edge), amplitude from the extreme of the detrended profile, centre and width from
    the samples above half amplitude (their count times the step and their mean).
    """
    n, m = y.shape
    q = max(2, m // 5)
    left, right = np.median(y[:, :q], axis=1), np.median(y[:, -q:], axis=1)
    tl, tr = np.median(t[:, :q], axis=1), np.median(t[:, -q:], axis=1)
    b1 = (right - left) / (tr - tl)
    b0 = 0.5 * (left + right) - b1 * 0.5 * (tl + tr)
    a = polarity * (y - b0[:, None] - b1[:, None] * t)
    amp = np.percentile(a, 95, axis=1)
    above = a > 0.5 * np.maximum(amp, 1e-6)[:, None]
    dt = t[:, 1] - t[:, 0]
    w0 = np.maximum(above.sum(axis=1) * dt, 2 * dt)
    c0 = np.where(above.any(axis=1), (t * above).sum(axis=1) / np.maximum(above.sum(axis=1), 1), 0.0)
    s0 = np.broadcast_to(np.asarray(s0, dtype=float), (n,))
    return np.column_stack([b0, b1, polarity * amp, c0, w0, s0])


def fit_profiles(t, y, p0, fixed_s: bool = False, weights=None, n_iter: int = 30,
                 chunk: int = 4000, amp_prior=None) -> ProfileFit:
    """Least-squares fit of the edge-pair model to N profiles at once (batched LM).

    t, y       (N, M) profile coordinate (mm) and intensity
    p0         (N, 6) start values (see :func:`initial_guess`)
    fixed_s    keep the blur ``s`` at p0's value (5-parameter fit): use it once the blur is
               known from wide beads, because for narrow beads (w < ~4 s) w, s and A are
               nearly degenerate.
    weights    (N, M) 0/1 mask of usable samples (e.g. inside the image); default all.
    amp_prior  (A_ref, lam), each (N,): a Gaussian prior on the contrast A, the term
               lam (A - A_ref)^2 added to the weighted sum of squares (lam = the profile's
               noise variance over the prior's, sigma_y^2 / sigma_A^2): the MAP of the
               edge pair under that prior. A bead under ~3 blurs shows its area A w more
               than either (module docstring: the profile tends to A w / (sqrt(2 pi) s)
               exp(-t^2 / 2 s^2)), and the plastic's contrast read on the scan's wide beads
               tells A (measure/widths.py :func:`~measure.widths.scan_contrast`).
    """
    return _fit_all(t, y, p0, fixed_s, weights, n_iter, chunk, side=0.0, amp_prior=amp_prior)


def fit_streak(t, y, p_plain, side: float, height_mm, fixed_s: bool = True, weights=None,
               n_iter: int = 30, chunk: int = 4000, flank: tuple[float, float] = STREAK_FLANK,
               shade: float = 0.0, shelf=None) -> ProfileFit:
    """The edge pair plus a glare streak on one flank (module docstring), started from a
    plain fit ``p_plain`` (N, 6); the blur is held at its value unless ``fixed_s`` is False.
    ``side`` -1: the streak is on the low-t edge, +1 on the high-t edge. ``height_mm``
    (scalar or (N,)) the bead height, which bounds the streak's depth to the flank:
    ``flank`` (fractions of h/2; equal ends hold the depth there). Returns
    params (N, 8) in STREAK_PARAMS order. Compare its ``rms`` with the plain fit's to
    decide whether a streak is there. With ``shade`` -1 / +1 the lamp's shadow outside that
    edge is in the model too (:func:`fit_shadow`), held at ``shelf`` (N, 3) = (D, L, P);
    params are then (N, 11)."""
    p_plain = np.asarray(p_plain, float)[:, :6]
    n = len(p_plain)
    r = 0.5 * np.broadcast_to(np.asarray(height_mm, float), (n,))
    lo, hi = flank[0] * r, flank[1] * r
    amp = np.abs(p_plain[:, 2:3])
    p0 = np.column_stack([p_plain, 0.05 * amp, 0.5 * (lo + hi)])
    if not shade:
        return _fit_all(t, y, p0, fixed_s, weights, n_iter, chunk, side=float(side),
                        depth_bounds=np.column_stack([lo, hi]))
    shelf = np.asarray(shelf, float).reshape(n, 3)
    p0 = np.column_stack([p0, shelf])
    return _fit_all(t, y, p0, fixed_s, weights, n_iter, chunk, side=float(side),
                    depth_bounds=np.column_stack([lo, hi]), shade=float(shade),
                    **{k: np.column_stack([shelf[:, j], shelf[:, j]])
                       for j, k in enumerate(("dark_bounds", "reach_bounds", "fade_bounds"))})


def fit_shadow(t, y, p_start, shade: float, reach_mm, fixed_s: bool = True, weights=None, n_iter: int = 30,
               chunk: int = 4000, dark=None, reach_held=None, fade_held=None, glare_height_mm=None) -> ProfileFit:
    """The edge pair plus the lamp's cast shadow outside one edge, started from a plain fit
    ``p_start`` (N, 6). A bead lit from one side shades the plate beside its other edge,
    darkening it by D (intensity, 0 <= D <= the plate's brightness there, whatever the
    polarity) out to L, and a lamp of some size (a scanner's tube, a window) hides less and
    less of itself further out: the shadow fades linearly over a penumbra P
    (measure/phenomena.py cast_shadow). With u =
    shade (t - e_a) the distance outward from the edge e_a = c + shade w/2, all blurred by s:

        f_s(t) = f(t) - D [Phi(u/s) - (psi(u - L) - psi(u - L - P)) / P],
        psi(x) = x Phi(x/s) + s phi(x/s)      (the blurred unit ramp's integral)

    (P -> 0 is a box from the edge to L; a box with the penumbra's mean darkness read the
    beads 7-10 um wide on a flatbed render with a 6 deg lamp: docs/MEASUREMENT.md "The
    lamp's shadow"). ``shade`` -1: outside the low-t edge, +1 the high-t edge; ``reach_mm``
    (scalar or (N,)) bounds L and P to [0, reach] (P >= 0.05 s); ``dark``, ``reach_held``,
    ``fade_held`` (N,) hold D, L, P (one lamp leaves one share of the light in its shadows,
    one elevation and one size: a shelf narrower than the blur tells only their product).
    ``glare_height_mm`` (scalar or (N,), the bead height): the lamp's glare streak on the
    flank facing it (the other edge) is fitted too, as in :func:`fit_streak` (the lamp that
    casts the shadow lights that flank: fitted without it, its streak pulled the edge in and
    the shelf took 0.11 of the plate's light for 0.5). Returns params (N, 11): PARAMS, G, d
    (0: no streak), D, L, P."""
    p_start = np.asarray(p_start, float)
    n = len(p_start)
    p0 = np.zeros((n, 11))
    p0[:, :6] = p_start[:, :6]
    reach = np.broadcast_to(np.asarray(reach_mm, float), (n,))
    s_lo = 0.05 * p0[:, 5]
    # a shadow takes at most all of the plate's light beside the edge
    plate = np.abs(p0[:, 0] + p0[:, 1] * (p0[:, 3] + shade * p0[:, 4] / 2))
    p0[:, 8] = np.minimum(0.1 * np.abs(p_start[:, 2]), 0.5 * plate) if dark is None else dark
    p0[:, 9] = 0.2 * reach if reach_held is None else reach_held
    p0[:, 10] = np.maximum(0.1 * reach, s_lo) if fade_held is None else fade_held

    side, depth = 0.0, None
    if glare_height_mm is not None:
        r = 0.5 * np.broadcast_to(np.asarray(glare_height_mm, float), (n,))
        side, depth = -float(shade), np.column_stack([STREAK_FLANK[0] * r, STREAK_FLANK[1] * r])
        p0[:, 6], p0[:, 7] = 0.05 * np.abs(p_start[:, 2]), depth.mean(axis=1)

    def held(v, free):
        return free if v is None else np.column_stack([v, v]).astype(float)

    return _fit_all(t, y, p0, fixed_s, weights, n_iter, chunk, side=side, depth_bounds=depth, shade=float(shade),
                    reach_bounds=held(reach_held, np.column_stack([np.zeros(n), reach])),
                    dark_bounds=held(dark, np.column_stack([np.zeros(n), plate])),
                    fade_bounds=held(fade_held, np.column_stack([s_lo, np.maximum(reach, s_lo)])))


def _fit_all(t, y, p0, fixed_s, weights, n_iter, chunk, side, depth_bounds=None, shade=0.0, reach_bounds=None,
             dark_bounds=None, fade_bounds=None, amp_prior=None):
    # one compiled signature: C-contiguous float64 (a broadcast t would compile another)
    t = np.ascontiguousarray(t, dtype=float)
    y = np.ascontiguousarray(y, dtype=float)
    p0 = np.asarray(p0, float)
    wts = np.ones_like(y) if weights is None else np.ascontiguousarray(weights, dtype=float)
    db = np.zeros((len(t), 2)) if depth_bounds is None else depth_bounds
    rb = np.zeros((len(t), 2)) if reach_bounds is None else reach_bounds
    kb = np.column_stack([np.zeros(len(t)), np.full(len(t), np.inf)]) if dark_bounds is None else dark_bounds
    fb = rb if fade_bounds is None else fade_bounds
    ap = None if amp_prior is None else np.column_stack([np.broadcast_to(np.asarray(v, float), (len(t),))
                                                         for v in amp_prior])
    out = [_fit_chunk(t[i:i + chunk], y[i:i + chunk], p0[i:i + chunk], fixed_s, wts[i:i + chunk], n_iter, side,
                      db[i:i + chunk], shade, rb[i:i + chunk], kb[i:i + chunk], fb[i:i + chunk],
                      None if ap is None else ap[i:i + chunk])
           for i in range(0, len(t), chunk)]
    if not out:
        z = np.zeros((0, p0.shape[1] if p0.ndim == 2 else 6))
        return ProfileFit(z, z.copy(), np.zeros(0), np.zeros(0, bool))
    return ProfileFit(*(np.concatenate(parts) for parts in zip(*out)))


def _fit_chunk(t, y, p, fixed_s, wts, n_iter, side=0.0, depth_bounds=None, shade=0.0, reach_bounds=None,
               dark_bounds=None, fade_bounds=None, amp_prior=None):
    n = len(t)
    free = _free_columns(fixed_s, side, shade)
    npar = len(free)
    p = np.array(p, dtype=float, order="C")       # a copy: the caller keeps its start values
    span = t[:, -1] - t[:, 0]
    step = np.abs(t[:, 1] - t[:, 0])
    lam = np.full(n, 1e-2)
    act = np.arange(n)
    m_eff = wts.sum(axis=1)
    # the normal equations at the accepted point are all the iteration needs of the Jacobian
    cost, JTJ, JTr = _with_amp_prior(_normal_equations(t, y, wts, p, act, fixed_s, side, shade), p, act, amp_prior)
    eye = np.eye(npar)
    trial_p = p.copy()
    # Keep the geometry physical: positive width and blur, centre inside the window, the
    # streak bright and on its flank.
    lo, hi = np.full(p.shape, -np.inf), np.full(p.shape, np.inf)
    lo[:, 3], hi[:, 3] = t[:, 0], t[:, -1]
    lo[:, 4], hi[:, 4] = 0.2 * step, 2 * span
    if not fixed_s:
        lo[:, 5], hi[:, 5] = 0.1 * step, 0.5 * span
    if side:
        lo[:, 6] = 0.0
        lo[:, 7], hi[:, 7] = depth_bounds[:, 0], depth_bounds[:, 1]
    if shade:                                     # a shadow darkens, out to the lamp's reach
        lo[:, 8], hi[:, 8] = dark_bounds[:, 0], dark_bounds[:, 1]
        lo[:, 9], hi[:, 9] = reach_bounds[:, 0], reach_bounds[:, 1]
        lo[:, 10], hi[:, 10] = fade_bounds[:, 0], fade_bounds[:, 1]
    lo, hi = lo[:, free], hi[:, free]
    # Profiles drop out of the iteration once converged: on a 12 MP photo the plain fits
    # take 7 steps on average, the streak fits 17.
    for _ in range(n_iter):
        if len(act) == 0:
            break
        pa = p[act]
        A_ = JTJ[act]
        diag = np.einsum("nii->ni", A_)
        A = A_ + lam[act, None, None] * (diag[:, :, None] * eye + 1e-12 * eye)
        b = JTr[act]
        delta = _solve(A, b)
        # A parameter on its bound that the step pushes outwards is held there and the step
        # solved for the others (projected LM). Clipping the full step instead left the rest
        # of it aimed for a move the bound never allows: with the streak's depth on the
        # flank's end (most streak fits), 2 in 3 of a photo's profiles crept on for all 30
        # iterations, a micron per step.
        pf = pa[:, free]
        pinned = ((pf <= lo[act]) & (delta < 0)) | ((pf >= hi[act]) & (delta > 0))
        if pinned.any():
            r = np.flatnonzero(pinned.any(axis=1))
            keep = ~pinned[r]
            A2 = A[r] * (keep[:, :, None] & keep[:, None, :]) + pinned[r][:, :, None] * eye
            delta[r] = _solve(A2, b[r] * keep)
        trial = pa.copy()
        trial[:, free] = np.clip(pf + delta, lo[act], hi[act])
        trial_p[act] = trial
        cost_t, JTJ_t, JTr_t = _with_amp_prior(_normal_equations(t, y, wts, trial_p, act, fixed_s, side, shade),
                                               trial_p, act, amp_prior)
        better = cost_t < cost[act]
        ib = act[better]
        step_f = trial[:, free] - pf
        small = (np.abs(step_f) <= 1e-6 * (np.abs(pf) + 1e-3 * span[act, None])).all(axis=1)
        rel_gain = (cost[act] - cost_t) / np.maximum(cost[act], 1e-300)
        # Bates & Watts' relative offset (Technometrics 23, 179, 1981): the step, as the
        # change of the fitted profile, against the residual sd; below OFFSET_TOL every
        # parameter is within OFFSET_TOL of its own sd from the optimum. On a photo's
        # profiles (misfit, not noise, dominates the residual) Gauss-Newton converges only
        # linearly, and the parameters' own relative 1e-6 took 30 steps and more.
        offset2 = np.einsum("ni,nij,nj->n", step_f, A_, step_f)
        near = (lam[act] <= 0.1) & (offset2 <= OFFSET_TOL ** 2 * cost[act] / np.maximum(m_eff[act] - npar, 1))
        p[ib], cost[ib], JTJ[ib], JTr[ib] = trial[better], cost_t[better], JTJ_t[better], JTr_t[better]
        lam[act] = np.where(better, lam[act] * 0.3, lam[act] * 10.0)
        done = (better & (small | near | (rel_gain < 1e-9))) | (lam[act] > 1e8)
        act = act[~done]
    # a parameter whose bounds meet (the streak's depth held for the whole scan) is held in
    # the covariance too: with it free there the width's sd read a trade the fit never made
    # (phone renders: 15x its peers'). A free parameter that merely ended on a bound keeps
    # its trade in the sd: on a flatbed the streaks' depth rests on its lower bound where
    # the true one is deeper, and the sd then covers the error that leaves (glare render,
    # largest-sd fifth of the stations: error / sd 1.06; 1.52 with the bound held).
    tol = 1e-9 * (np.abs(hi) + span[:, None])
    held = np.isfinite(hi) & (hi - lo <= tol)
    var = cost / np.maximum(m_eff - npar + held.sum(axis=1), 1)
    A = JTJ * (~held[:, :, None] & ~held[:, None, :]) + held[:, :, None] * eye
    cov = _safe_inv(A) * var[:, None, None] * ~held[:, :, None]
    sd = np.full(p.shape, np.nan)
    sd[:, free] = np.sqrt(np.clip(np.einsum("nii->ni", cov), 0, None))
    if fixed_s:
        sd[:, 5] = 0.0
    ok = (np.isfinite(p).all(axis=1) & np.isfinite(sd[:, 4]) & (p[:, 4] > 0.25 * step)
          & (p[:, 5] > 0) & (m_eff > npar + 2))
    return p, sd, np.sqrt(var), ok


def _solve(A, b):
    try:
        return np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return _safe_solve(A, b)


def _safe_inv(A):
    out = np.full_like(A, np.nan)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):     # singular: said by det_ok
        det_ok = np.abs(np.linalg.det(A)) > 1e-300
    if det_ok.any():
        try:
            out[det_ok] = np.linalg.inv(A[det_ok])
        except np.linalg.LinAlgError:
            for i in np.flatnonzero(det_ok):
                try:
                    out[i] = np.linalg.inv(A[i])
                except np.linalg.LinAlgError:
                    pass
    return out


def _safe_solve(A, b):
    out = np.zeros_like(b)
    for i in range(len(A)):
        try:
            out[i] = np.linalg.solve(A[i], b[i])
        except np.linalg.LinAlgError:
            pass
    return out
