"""Compare physical models on one set of measured widths: RMS, reduced chi-square, BIC, PSIS-LOO.

Likelihood (the one every number here refers to). Sample i has measured width y_i (mm)
with the measurement's one-sigma ``width_sd_mm`` s_i; the model predicts mu_i(theta).
Unmodelled physics shows up as extra scatter, so an extra noise term sigma_x (mm,
``noise.extra_mm``, one more fitted parameter) is added in quadrature:

    log L = sum_i  -1/2 [ (y_i - mu_i)^2 / v_i + ln(2 pi v_i) ],   v_i = s_i^2 + sigma_x^2

The maximum-likelihood fit (:func:`ml_fit`) gives

    BIC     = k ln n - 2 ln L_max             (Schwarz 1978; k = model params + 1)
    chi2_nu = sum_i (y_i - mu_i)^2 / s_i^2 / (n - k)   (against the measurement sd only,
              so it exceeds 1 exactly when the model leaves structure the scatter
              cannot explain; after adding the missing effect it returns to ~1)
    RMS     = sqrt(mean (y_i - mu_i)^2)  (mm)

Correlation along a track: samples every 0.25 mm are not independent when a model is
wrong, so BIC differences between wrong models are overconfident by about n / n_eff.
:func:`effective_n` estimates n_eff = n (1 - rho) / (1 + rho) from the lag-1
autocorrelation rho of standardised residuals along tracks (AR(1) variance inflation);
the comparison reports ``delta_bic_eff = delta_bic * n_eff / n`` beside the raw value.

The full fit (:func:`mcmc_fit`) samples the posterior with emcee (vectorised walkers)
from the ML point; PSIS-LOO (:func:`psis_loo`, Vehtari, Gelman & Gabry 2017, with the
Zhang & Stephens 2009 generalised-Pareto fit) turns the pointwise log-likelihood draws
into elpd_loo and its standard error.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.special import logsumexp

from patterns.manifest import Manifest, Samples
from measure.table import WidthTable
from calib.errors import UserError

LOG2PI = math.log(2.0 * math.pi)


# -- data ---------------------------------------------------------------------------------

@dataclass
class Observed:
    """The valid samples of a widths table, matched to the manifest, ready for the physics.

    width_mm, width_sd_mm: measured width and its one-sigma (mm), shape (n,)
    samples: the matching :class:`patterns.manifest.Samples` (track, s_mm, x, y, t_s, ...)
    ctx: the physics context (``fit.context.SimContext``) built for those samples
    """

    width_mm: np.ndarray
    width_sd_mm: np.ndarray
    samples: Samples
    ctx: object
    manifest: Manifest | None = None

    @property
    def n(self) -> int:
        return len(self.width_mm)


def samples_from_table(manifest: Manifest, table: WidthTable) -> Samples:
    """Stations of the table's rows, completed (normal, nominal width, height) from the manifest."""
    n = len(table)
    nx, ny, wn, hh = (np.empty(n) for _ in range(4))
    known = {tr.id: tr for tr in manifest.tracks}
    for tid in np.unique(table.track):
        if int(tid) not in known:
            raise UserError(f"the widths table names track {int(tid)}, which the manifest does not "
                            "have; pass the manifest the pattern was printed from")
        tr = known[int(tid)]
        m = table.track == tid
        _, tan = tr.at(table.s_mm[m])
        nx[m], ny[m] = -tan[:, 1], tan[:, 0]
        wn[m] = tr.interp("width_mm", table.s_mm[m])
        hh[m] = tr.interp("height_mm", table.s_mm[m])
    t = table.t_s.copy()
    if manifest.timeline is not None and not np.all(np.isfinite(t)):
        from fit.covariates import _first_passage
        t = _first_passage(manifest.timeline, table.track, table.s_mm, t)
    return Samples(track=table.track.copy(), s_mm=table.s_mm.copy(), x_mm=table.x_mm.copy(),
                   y_mm=table.y_mm.copy(), t_s=t, nx=nx, ny=ny, width_nominal_mm=wn, height_mm=hh)


def observe(manifest: Manifest, table: WidthTable, ctx=None) -> Observed:
    """Build :class:`Observed` from the valid rows of ``table`` (raises UserError if none)."""
    if manifest.timeline is None:
        raise UserError("the manifest has no timeline (.timeline.npz); keep it next to the manifest")
    valid = table.subset(table.valid)
    if len(valid) < 5:
        raise UserError(f"only {len(valid)} valid width samples; need at least 5 to fit anything")
    samples = samples_from_table(manifest, valid)
    if ctx is None:
        from fit.context import SimContext
        ctx = SimContext.build(manifest, samples)
    return Observed(width_mm=valid.width_mm, width_sd_mm=valid.width_sd_mm, samples=samples,
                    ctx=ctx, manifest=manifest)


# -- likelihood -----------------------------------------------------------------------------

def loglik_pointwise(y, sd, mu, extra_mm):
    """Pointwise Gaussian log-likelihood (see module docstring); broadcasts over leading axes."""
    v = np.asarray(sd) ** 2 + np.asarray(extra_mm) ** 2
    return -0.5 * ((y - mu) ** 2 / v + np.log(v) + LOG2PI)


def ml_extra_noise_mm(r, sd, iters: int = 60) -> float:
    """Maximum-likelihood sigma_x (mm) for residuals r: solves sum (r^2 - v)/v^2 = 0, or 0.

    The score d lnL / d(sigma_x^2) = 1/2 sum (r_i^2 - v_i) / v_i^2 is decreasing in
    sigma_x^2 wherever it crosses zero, so bisection on sigma_x^2 finds the maximum; if
    it is negative at sigma_x = 0 the maximum is on the boundary (sigma_x = 0).
    """
    r2 = np.asarray(r) ** 2
    s2 = np.asarray(sd) ** 2

    def score(x2):
        v = s2 + x2
        return float(np.sum((r2 - v) / v ** 2))

    if score(0.0) <= 0:
        return 0.0
    lo, hi = 0.0, max(float(np.max(r2)), 1e-12)
    while score(hi) > 0:
        hi *= 4
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if score(mid) > 0:
            lo = mid
        else:
            hi = mid
    return math.sqrt(0.5 * (lo + hi))


def effective_n(resid_std, track, t_s=None) -> float:
    """n_eff = n (1 - rho) / (1 + rho), rho = lag-1 autocorrelation of the standardised
    residuals along each track (pairs within a track only), clipped to [0, 0.99]."""
    r = np.asarray(resid_std, dtype=float)
    track = np.asarray(track)
    order = np.lexsort((np.zeros(len(r)) if t_s is None else np.asarray(t_s), track))
    r, tr = r[order], track[order]
    r = r - r.mean()
    same = tr[1:] == tr[:-1]
    den = float(np.sum(r * r))
    if den <= 0 or not same.any():
        return float(len(r))
    rho = float(np.sum(r[1:][same] * r[:-1][same]) / den * len(r) / same.sum())
    rho = min(max(rho, 0.0), 0.99)
    return len(r) * (1 - rho) / (1 + rho)


# -- maximum likelihood -------------------------------------------------------------------------

@dataclass
class FitSummary:
    """A fitted model on one dataset. Widths in mm.

    theta: best parameters (model order); names: ``model.param_names``
    extra_mm: fitted extra noise sigma_x; k: fitted parameters incl. sigma_x; n: samples
    loglik: ln L_max; bic; chi2_nu; rms_mm; pred_mm, resid_mm (n,): prediction and y - mu
    draws, loglik_draws, elpd_loo, elpd_loo_se, pareto_k_max: filled by a full fit
    """

    spec: str
    names: list[str]
    theta: np.ndarray
    extra_mm: float
    k: int
    n: int
    loglik: float
    bic: float
    chi2_nu: float
    rms_mm: float
    pred_mm: np.ndarray = field(repr=False)
    resid_mm: np.ndarray = field(repr=False)
    n_eff: float = float("nan")
    draws: np.ndarray | None = field(default=None, repr=False)
    loglik_draws: np.ndarray | None = field(default=None, repr=False)
    elpd_loo: float = float("nan")
    elpd_loo_se: float = float("nan")
    p_loo: float = float("nan")
    pareto_k_max: float = float("nan")
    elpd_i: np.ndarray | None = field(default=None, repr=False)
    autocorr_steps: float = float("nan")
    acceptance: float = float("nan")

    def params(self) -> dict[str, float]:
        d = {n: float(v) for n, v in zip(self.names, self.theta)}
        d["noise.extra_mm"] = float(self.extra_mm)
        return d

    def intervals(self) -> dict[str, tuple[float, float, float]]:
        """Posterior 16/50/84 % quantiles per parameter (full fit only)."""
        if self.draws is None:
            return {}
        q = np.quantile(self.draws, [0.16, 0.5, 0.84], axis=0)
        names = self.names + ["noise.extra_mm"]
        return {n: (float(q[0, i]), float(q[1, i]), float(q[2, i])) for i, n in enumerate(names)}


def _bounds(model) -> tuple[np.ndarray, np.ndarray]:
    b = np.asarray(model.bounds, dtype=float)
    p = len(model.param_names)
    if b.shape == (p, 2):
        return b[:, 0].copy(), b[:, 1].copy()
    if b.shape == (2, p):
        return b[0].copy(), b[1].copy()
    raise ValueError(f"model.bounds has shape {b.shape}, expected ({p}, 2)")


def _predict(model, ctx, thetas: np.ndarray, chunk: int = 64) -> np.ndarray:
    thetas = np.atleast_2d(thetas)
    outs = [np.asarray(model.predict(ctx, thetas[i:i + chunk]), dtype=float).reshape(
        len(thetas[i:i + chunk]), -1) for i in range(0, len(thetas), chunk)]
    return np.concatenate(outs, axis=0)


def _random_starts(lo, hi, n, rng):
    u = rng.random((n, len(lo)))
    logscale = (lo > 0) & (hi / np.where(lo > 0, lo, 1) >= 20)
    out = lo + u * (hi - lo)
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.exp(np.log(np.where(logscale, lo, 1)) + u * np.log(np.where(logscale, hi / np.where(lo > 0, lo, 1), 1)))
    return np.where(logscale, lg, out)


def ml_fit(model, obs: Observed, spec: str = "", theta0=None, n_random: int = 32,
           n_polish: int = 2, seed: int = 0, max_nfev: int = 60) -> FitSummary:
    """Maximum-likelihood fit of ``model`` to ``obs`` (see module docstring for the likelihood).

    Global stage: ``n_random`` parameter sets drawn over the bounds (log-uniform for
    bounds spanning >= 20x) plus ``theta0`` and the model's defaults, evaluated in one
    vectorised call; the best ``n_polish`` are refined by bounded least squares
    (scipy ``least_squares``, trust-region reflective) on whitened residuals with a
    forward-difference Jacobian evaluated as one batch of parameter sets. sigma_x is
    then set to its ML value and the weights updated (two rounds).
    """
    y, sd, ctx = obs.width_mm, obs.width_sd_mm, obs.ctx
    lo, hi = _bounds(model)
    p = len(lo)
    rng = np.random.default_rng(seed)
    starts = [np.asarray(model.default_theta(), dtype=float).reshape(p)]
    if theta0 is not None:
        starts.insert(0, np.clip(np.asarray(theta0, dtype=float).reshape(p), lo, hi))
    if n_random:
        starts.extend(_random_starts(lo, hi, n_random, rng))
    starts = np.array(starts)
    span = hi - lo

    def chi2_of(pred, v):
        r = (pred - y[None, :]) ** 2 / v[None, :]
        r[~np.isfinite(r)] = 1e6
        return r.sum(axis=1)

    v = sd ** 2
    chis = chi2_of(_predict(model, ctx, starts), v)
    best_idx = np.argsort(chis)[:max(1, n_polish)]
    if theta0 is not None and 0 not in best_idx:
        best_idx = np.concatenate([[0], best_idx])

    def polish(x0, v):
        w = 1.0 / np.sqrt(v)
        h = 1e-4 * np.maximum(span, 1e-9)

        def fun(x):
            r = (_predict(model, ctx, x[None, :])[0] - y) * w
            return np.where(np.isfinite(r), r, 1e3)

        def jac(x):
            step = np.where(x + h <= hi, h, -h)
            X = np.repeat(x[None, :], p + 1, axis=0)
            X[np.arange(1, p + 1), np.arange(p)] += step
            P = _predict(model, ctx, X)
            P = np.where(np.isfinite(P), P, P[0][None, :])
            return ((P[1:] - P[0][None, :]) * w[None, :] / step[:, None]).T

        x0 = np.clip(x0, lo + 1e-12 * span, hi - 1e-12 * span)
        res = least_squares(fun, x0, jac=jac, bounds=(lo, hi), x_scale="jac", max_nfev=max_nfev,
                            method="trf")
        return res.x, float(np.sum(res.fun ** 2))

    cands = [polish(starts[i], v) for i in best_idx]
    theta = min(cands, key=lambda c: c[1])[0]
    extra = 0.0
    for _ in range(2):
        mu = _predict(model, ctx, theta[None, :])[0]
        extra = ml_extra_noise_mm(y - mu, sd)
        if extra == 0.0:
            break
        theta, _ = polish(theta, sd ** 2 + extra ** 2)
    mu = _predict(model, ctx, theta[None, :])[0]
    extra = ml_extra_noise_mm(y - mu, sd)
    return summarize(spec, list(model.param_names), theta, extra, y, sd, mu, obs.samples)


def summarize(spec, names, theta, extra_mm, y, sd, mu, samples=None) -> FitSummary:
    """Numbers of a fit at (theta, sigma_x): ln L, BIC, chi2_nu, RMS, n_eff."""
    n = len(y)
    k = len(names) + 1
    r = y - mu
    ll = float(np.sum(loglik_pointwise(y, sd, mu, extra_mm)))
    bic = k * math.log(n) - 2.0 * ll
    chi2_nu = float(np.sum(r ** 2 / sd ** 2) / max(1, n - k))
    rms = float(np.sqrt(np.mean(r ** 2)))
    n_eff = float("nan")
    if samples is not None:
        n_eff = effective_n(r / np.sqrt(sd ** 2 + extra_mm ** 2), samples.track, samples.t_s)
    return FitSummary(spec=spec, names=list(names), theta=np.asarray(theta, dtype=float),
                      extra_mm=float(extra_mm), k=k, n=n, loglik=ll, bic=bic, chi2_nu=chi2_nu,
                      rms_mm=rms, pred_mm=mu, resid_mm=r, n_eff=n_eff)


# -- full fit ---------------------------------------------------------------------------------

def mcmc_fit(model, obs: Observed, ml: FitSummary, n_steps: int = 600, n_burn: int = 200,
             n_walkers: int | None = None, max_draws: int = 1000, seed: int = 0,
             progress: bool = False) -> FitSummary:
    """Posterior draws by emcee from a ball around the ML point, then PSIS-LOO.

    Log posterior: ``model.log_prior(theta)`` + a uniform prior on sigma_x in [0, 0.5] mm +
    log L (module docstring). Walkers: max(16, 2 (p+1) + 2), vectorised. This is a fixed-
    length run for model comparison (elpd_loo); the integrated autocorrelation time is
    reported so a short chain is visible, and ``calib fit`` is the place for a fit run to
    convergence.
    """
    import emcee

    y, sd, ctx = obs.width_mm, obs.width_sd_mm, obs.ctx
    lo, hi = _bounds(model)
    lo = np.append(lo, 0.0)
    hi = np.append(hi, 0.5)
    ndim = len(lo)
    nw = n_walkers or max(16, 2 * ndim + 2)
    nw += nw % 2
    rng = np.random.default_rng(seed)
    x0 = np.append(ml.theta, max(ml.extra_mm, 1e-4))
    scale = np.maximum(1e-3 * (hi - lo), 1e-3 * np.abs(x0))
    p0 = np.clip(x0 + scale * rng.standard_normal((nw, ndim)), lo + 1e-12, hi - 1e-12)

    def log_prob(X):
        X = np.atleast_2d(X)
        out = np.full(len(X), -np.inf)
        inb = np.all((X >= lo) & (X <= hi), axis=1)
        if not inb.any():
            return out
        th = X[inb, :-1]
        lp = np.asarray(model.log_prior(th), dtype=float).reshape(-1)
        mu = _predict(model, ctx, th)
        ll = loglik_pointwise(y[None, :], sd[None, :], mu, X[inb, -1:]).sum(axis=1)
        out[inb] = np.where(np.isfinite(ll), lp + ll, -np.inf)
        return out

    sampler = emcee.EnsembleSampler(nw, ndim, log_prob, vectorize=True,
                                    moves=[(emcee.moves.DEMove(), 0.8),
                                           (emcee.moves.DESnookerMove(), 0.2)])
    sampler.random_state = np.random.RandomState(int(rng.integers(2 ** 31))).get_state()
    sampler.run_mcmc(p0, n_steps + n_burn, progress=progress)
    chain = sampler.get_chain(discard=n_burn, flat=True)
    try:
        tau = float(np.max(sampler.get_autocorr_time(discard=n_burn, tol=0)))
    except Exception:  # emcee raises on degenerate chains; the number is diagnostic only
        tau = float("nan")
    if len(chain) > max_draws:
        chain = chain[np.linspace(0, len(chain) - 1, max_draws).astype(int)]
    mu = _predict(model, ctx, chain[:, :-1])
    lld = loglik_pointwise(y[None, :], sd[None, :], mu, chain[:, -1:])
    elpd, se, ks, p_loo, elpd_i = psis_loo(lld)
    out = FitSummary(**{**ml.__dict__})
    out.draws = chain
    out.loglik_draws = lld
    out.elpd_loo, out.elpd_loo_se, out.p_loo, out.elpd_i = elpd, se, p_loo, elpd_i
    out.pareto_k_max = float(np.max(ks)) if len(ks) else float("nan")
    out.autocorr_steps = tau
    out.acceptance = float(np.mean(sampler.acceptance_fraction))
    return out


def _gpdfit(x: np.ndarray) -> tuple[float, float]:
    """Generalised Pareto fit (Zhang & Stephens 2009, with the weak prior on k of Vehtari
    et al. 2017) to sorted positive exceedances x. Returns (k, sigma)."""
    n = len(x)
    m = 30 + int(math.sqrt(n))
    b = 1.0 - np.sqrt(m / (np.arange(1, m + 1) - 0.5))
    b /= 3.0 * x[int(n / 4 + 0.5) - 1]
    b += 1.0 / x[-1]
    k = np.log1p(-b[:, None] * x[None, :]).mean(axis=1)
    L = n * (np.log(-(b / k)) - k - 1.0)
    w = 1.0 / np.exp(L - L[:, None]).sum(axis=1)
    keep = w >= 10 * np.finfo(float).eps
    w, b = w[keep] / w[keep].sum(), b[keep]
    bp = float(np.sum(b * w))
    kp = float(np.log1p(-bp * x).mean())
    sigma = -kp / bp
    kp = (n * kp + 10 * 0.5) / (n + 10)
    return kp, sigma


def psis_loo(loglik_draws: np.ndarray) -> tuple[float, float, np.ndarray, float, np.ndarray]:
    """PSIS-LOO (Vehtari, Gelman & Gabry 2017) from pointwise log-likelihood draws (S, n).

    Importance ratios 1/p(y_i|theta_s); the largest M = ceil(min(S/5, 3 sqrt(S))) are
    replaced by expected order statistics of a generalised Pareto fit, truncated at the
    largest raw ratio. elpd_i = log sum_s w_is p(y_i|theta_s); se = sqrt(n var(elpd_i)).
    Returns (elpd_loo, se, pareto_k per sample, p_loo, elpd_i per sample). k > 0.7 flags
    unreliable samples.
    """
    ll = np.asarray(loglik_draws, dtype=float)
    S, n = ll.shape
    M = int(math.ceil(min(0.2 * S, 3 * math.sqrt(S))))
    lw_all = -ll - np.max(-ll, axis=0, keepdims=True)
    order = np.argsort(lw_all, axis=0)
    ks = np.full(n, np.inf)
    probs = (np.arange(M) + 0.5) / M
    lw_out = lw_all.copy()
    for i in range(n):
        lw = lw_all[:, i]
        idx = order[:, i]
        cut = lw[idx[S - M - 1]]
        tail_idx = idx[S - M:]
        tail = np.exp(lw[tail_idx]) - math.exp(cut)
        if M <= 4 or tail[-1] <= 0:
            continue
        k, sig = _gpdfit(np.maximum(tail, 1e-300))
        ks[i] = k
        if not np.isfinite(k) or sig <= 0:
            continue
        q = sig * (np.expm1(-k * np.log1p(-probs)) / k if abs(k) > 1e-12 else -np.log1p(-probs))
        col = lw.copy()
        col[tail_idx] = np.log(q + math.exp(cut))
        lw_out[:, i] = np.minimum(col, 0.0)
    lw_out -= logsumexp(lw_out, axis=0, keepdims=True)
    elpd_i = logsumexp(lw_out + ll, axis=0)
    lpd_i = logsumexp(ll, axis=0) - math.log(S)
    elpd = float(np.sum(elpd_i))
    se = float(math.sqrt(n * np.var(elpd_i)))
    return elpd, se, ks, float(np.sum(lpd_i - elpd_i)), elpd_i


# -- comparison -------------------------------------------------------------------------------

@dataclass
class Comparison:
    """Models fitted to one dataset, best (lowest BIC) first, with differences to the best."""

    fits: list[FitSummary]

    def rows(self) -> list[dict]:
        best_bic = min(f.bic for f in self.fits)
        loo = [f.elpd_loo for f in self.fits if np.isfinite(f.elpd_loo)]
        best_loo = max(loo) if loo else float("nan")
        rows = []
        for f in self.fits:
            d_bic = f.bic - best_bic
            rows.append({
                "model": f.spec, "n": f.n, "k": f.k, "rms_mm": f.rms_mm, "chi2_nu": f.chi2_nu,
                "loglik": f.loglik, "bic": f.bic, "delta_bic": d_bic,
                "delta_bic_eff": d_bic * (f.n_eff / f.n if np.isfinite(f.n_eff) else 1.0),
                "n_eff": f.n_eff, "elpd_loo": f.elpd_loo, "elpd_loo_se": f.elpd_loo_se,
                "delta_elpd_loo": (f.elpd_loo - best_loo) if np.isfinite(f.elpd_loo) else float("nan"),
                "delta_elpd_loo_se": _delta_se(f, self._best_loo_fit()),
                "pareto_k_max": f.pareto_k_max, "params": f.params(),
                "intervals": {k: list(v) for k, v in f.intervals().items()},
                "extra_noise_mm": f.extra_mm,
            })
        return rows

    def _best_loo_fit(self):
        c = [f for f in self.fits if f.loglik_draws is not None and np.isfinite(f.elpd_loo)]
        return max(c, key=lambda f: f.elpd_loo) if c else None

    def to_json(self) -> dict:
        return {"schema": "calib.compare/1", "models": _clean(self.rows())}


def _delta_se(f: FitSummary, best: FitSummary | None) -> float:
    """SE of the elpd difference from the paired pointwise differences (Vehtari et al. 2017)."""
    if best is None or f.elpd_i is None:
        return float("nan")
    if f is best:
        return 0.0
    d = f.elpd_i - best.elpd_i
    return float(math.sqrt(len(d) * np.var(d)))


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else float(o)
    if isinstance(o, np.integer):
        return int(o)
    return o


def compare_models(obs: Observed, models: dict, full: bool = True, seed: int = 0,
                   n_steps: int = 600, progress: bool = False) -> Comparison:
    """Fit each model (``{spec: Model}``) by ML (and, if ``full``, by MCMC + PSIS-LOO).

    Nested models are warm-started from the best fit of a model whose parameters they
    contain, so adding an effect never fits worse than the model without it.
    """
    from tqdm import tqdm

    fits: list[FitSummary] = []
    for spec, model in tqdm(models.items(), desc="compare", disable=not progress, file=None):
        theta0 = _warm_start(model, fits)
        f = ml_fit(model, obs, spec=spec, theta0=theta0, seed=seed)
        if full:
            f = mcmc_fit(model, obs, f, n_steps=n_steps, seed=seed)
        fits.append(f)
    fits.sort(key=lambda f: f.bic)
    return Comparison(fits)


def _warm_start(model, fits: list[FitSummary]):
    """Start values: each parameter from the best earlier fit that has it, else the default."""
    if not fits:
        return None
    theta = np.asarray(model.default_theta(), dtype=float).reshape(-1).copy()
    names = list(model.param_names)
    found = False
    for f in sorted(fits, key=lambda f: f.bic, reverse=True):
        for j, nm in enumerate(names):
            if nm in f.names:
                theta[j] = f.theta[f.names.index(nm)]
                found = True
    return theta if found else None
