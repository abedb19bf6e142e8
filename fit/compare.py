"""Compare physical models on one set of measured widths: RMS, reduced chi-square, BIC, PSIS-LOO.

Every number here comes from the fit engine (:mod:`fit.sampler`, :mod:`fit.likelihood`);
this module only adds what is comparison-specific: several starts screened in one
vectorised call before the MAP polish, warm starts between nested models, the table with
differences to the best model, and the arrays the plots need.

Likelihood (``fit.likelihood``, the one ``calib fit`` uses). Samples are ordered along
each track; the residual y_i - mu_i is white measurement noise of sd width_sd_i plus an
Ornstein-Uhlenbeck wobble of sd sigma_extra and correlation exp(-gap_i / ell)
(ell = ``noise.corr_len_mm``, none across a track start); ln L is the exact Gaussian
density, summed from the Kalman filter's innovations v_i of variance F_i:

    ln L = sum_i -1/2 (v_i^2 / F_i + ln F_i + ln 2 pi)

The fit is the MAP (:func:`fit.sampler.fit_map`; with the engine's log-uniform priors on
the noise parameters and the optimisation in log space, the MAP of sigma_extra and ell
is their maximum-likelihood value). From it (:class:`fit.result.MapResult`):

    BIC     = k ln n - 2 ln L(theta_MAP)     (Schwarz 1978; k counts sigma_extra and ell)
    chi2_nu = sum_i (y_i - mu_i)^2 / width_sd_i^2 / (n - k_model)   (measurement sd only,
              so it exceeds 1 exactly when the model leaves structure that the measurement
              scatter cannot explain, even though sigma_extra absorbs it in ln L)
    RMS     = sqrt(mean (y_i - mu_i)^2)   (mm)

Residuals of a wrong model are correlated along a track; the AR(1) term carries that
correlation inside ln L, so BIC differences need no ad-hoc n_eff/n rescaling (the former
``delta_bic_eff`` key is kept equal to ``delta_bic`` for readers of old files). ``n_eff``
is reported as a diagnostic: sum_i (1 - phi_i) / (1 + phi_i) at the MAP, the AR(1)
effective number of independent samples of the wobble (an upper bound on its information).

The full fit (:func:`fit.sampler.fit_mcmc`) runs emcee to convergence (autocorrelation
time, split R-hat) and gives PSIS-LOO (:func:`fit.sampler.psis_loo`); the paired
difference of elpd_loo between two models and its standard error use the pointwise
elpd_i (Vehtari, Gelman & Gabry 2017).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from calib.errors import UserError
from fit.data import ScanData, scan_from_table
from fit.likelihood import CORR_NAME, SIGMA_NAME, JointProblem, NoiseOptions, ar1_phi, is_noise
from fit.result import FitResult, MapResult
from fit.sampler import fit_map, fit_mcmc, make_problem
from measure.table import WidthTable
from patterns.manifest import Manifest


def observe(manifest: Manifest, table: WidthTable, name: str = "widths") -> ScanData:
    """The valid samples of ``table`` matched to ``manifest`` (:func:`fit.data.scan_from_table`)."""
    if manifest.timeline is None:
        raise UserError("the manifest has no timeline (.timeline.npz); keep it next to the manifest")
    return scan_from_table(table, manifest, name)


# -- one model ------------------------------------------------------------------------------

@dataclass
class ModelFit:
    """A model fitted to one scan: the MAP (always) and the full posterior (``full``, optional).

    pred_mm, resid_mm: prediction and y - mu at the scan's valid samples, in the scan's
    order (``ScanData.order``: by track, then arc length), mm.
    """

    spec: str
    map: MapResult
    problem: JointProblem = field(repr=False)
    pred_mm: np.ndarray = field(repr=False)
    resid_mm: np.ndarray = field(repr=False)
    full: FitResult | None = field(default=None, repr=False)

    # numbers of the MAP fit
    n = property(lambda self: self.map.n_obs)
    k = property(lambda self: self.map.k)
    loglik = property(lambda self: self.map.loglik)
    bic = property(lambda self: self.map.bic)
    chi2_nu = property(lambda self: self.map.chi2_nu)
    #: the misfit the trust verdict judges (fit/result.py: the bead's own wobble allowed)
    chi2_nu_bead = property(lambda self: self.map.chi2_nu_bead)
    rms_mm = property(lambda self: self.map.rms_mm)
    names = property(lambda self: list(self.map.param_names))

    @property
    def extra_mm(self) -> float:
        return float(self.map.values.get(SIGMA_NAME, float("nan")))

    @property
    def corr_len_mm(self) -> float:
        return float(self.map.values.get(CORR_NAME, float("nan")))

    @property
    def n_eff(self) -> float:
        """AR(1) effective sample size at the MAP: sum_i (1 - phi_i) / (1 + phi_i) over the
        valid samples (the wobble; censored missing stations are not counted)."""
        if not np.isfinite(self.corr_len_mm):
            return float(sum(sc.n_valid for sc in self.problem.scans))
        phi = np.concatenate([ar1_phi(sc.gap_mm, self.corr_len_mm)[0] for sc in self.problem.scans])
        return float(np.sum((1 - phi) / (1 + phi)))

    def params(self) -> dict[str, float]:
        return self.map.values

    # numbers of the full fit (NaN without one)
    def _loo(self, key):
        return float(self.full.loo.get(key, float("nan"))) if self.full is not None else float("nan")

    elpd_loo = property(lambda self: self._loo("elpd_loo"))
    elpd_loo_se = property(lambda self: self._loo("se"))
    p_loo = property(lambda self: self._loo("p_loo"))
    pareto_k_max = property(lambda self: self._loo("pareto_k_max"))

    @property
    def elpd_i(self) -> np.ndarray | None:
        if self.full is None or "elpd_i" not in self.full.loo:
            return None
        return np.asarray(self.full.loo["elpd_i"], dtype=float)

    @property
    def converged(self) -> bool | None:
        return None if self.full is None else self.full.converged

    def intervals(self) -> dict[str, tuple[float, float, float]]:
        """Posterior 16/50/84 % quantiles per parameter (full fit only)."""
        if self.full is None:
            return {}
        return {n: (p.ci68[0], p.median, p.ci68[1]) for n, p in self.full.params.items()}


def _problem(model, scan: ScanData, noise: NoiseOptions | None = None,
             priors: dict | None = None) -> JointProblem:
    """The posterior of ``model`` on ``scan``; ``priors``: overrides (fit.priors format) of
    the parameters this model has (others are ignored: a search over models passes the
    same overrides to every model it tries)."""
    with np.errstate(divide="ignore"):
        pb = make_problem(model, scan, noise)
        mine = {k: v for k, v in (priors or {}).items() if k in pb.param_names}
        return make_problem(model, scan, noise, mine) if mine else pb


def _absent(prior, name: str, default: float) -> float:
    """Start value at which an added effect does nothing: 0 for amplitudes (0 inside the
    bounds), 1 for exponents and gains, else the default (a time constant, a scale)."""
    if prior.lower <= 0.0 <= prior.upper:
        return 0.0
    if (name.endswith(".n") or name.endswith(".gain")) and prior.lower <= 1.0 <= prior.upper:
        return 1.0
    return default


def warm_starts(problem: JointProblem, fits: list[ModelFit]) -> tuple[list[np.ndarray], np.ndarray]:
    """Starts taken from earlier fits, and the mask of the parameters they do not know.

    Every parameter an earlier fit has (the best fit that has it wins) is copied; the rest
    (the added effect) is set once to its 'absent' value (so the extended model starts
    exactly at the smaller model's optimum and cannot end worse) and once to its defaults.
    No starts (and all physical parameters unknown) if no earlier fit shares a physical
    parameter.
    """
    names = problem.param_names
    physical = np.array([not is_noise(n) for n in names])
    known = {}
    for f in sorted(fits, key=lambda f: f.bic, reverse=True):
        known.update(f.map.values)
    if not any(n in known for n, ph in zip(names, physical) if ph):
        return [], physical
    default = problem.default_theta()
    absent, dflt = default.copy(), default.copy()
    new = np.zeros(len(names), dtype=bool)
    for j, n in enumerate(names):
        if n in known:
            absent[j] = dflt[j] = known[n]
        else:
            new[j] = True
            absent[j] = _absent(problem.priors[j], n, default[j])
    lo, hi = problem.bounds.T
    return [np.clip(absent, lo, hi), np.clip(dflt, lo, hi)], new


def _zpost(problem: JointProblem, r: MapResult) -> float:
    """The log posterior fit_map maximises: in z = log(theta) for positive parameters, so
    it adds the log-Jacobian sum log(theta_j) of those (optima are compared on it)."""
    pos = np.array([p.positive for p in problem.priors])
    return float(r.log_post + np.sum(np.log(r.theta[pos])))


def fit_model(model, scan: ScanData, spec: str = "", warm: list[ModelFit] = (), n_random: int = 24,
              n_polish: int = 3, seed: int = 0, noise: NoiseOptions | None = None,
              problem: JointProblem | None = None, priors: dict | None = None) -> ModelFit:
    """MAP fit of ``model`` to ``scan`` by :func:`fit.sampler.fit_map`, from several starts.
    ``priors``: prior overrides of the parameters the model has (:func:`_problem`).

    Starts: warm starts from the earlier fits ``warm`` (:func:`warm_starts`; the first one
    is always polished) or the model defaults, plus ``n_random`` draws from the priors of
    the parameters the warm starts do not know (all physical parameters without warm
    starts; the noise parameters stay at the first start). All are evaluated in one
    vectorised call; the best ``n_polish`` are optimised by ``fit_map`` (L-BFGS-B) and the
    highest posterior wins, and is polished once more with the noise parameters reset to
    their defaults (see the comment in the code). With warm starts, another start is only optimised when it is
    already better than the warm start (the warm start is the smaller model's optimum, so
    a start that does not beat it rarely leads anywhere better; this keeps a candidate
    fit to about one optimisation).
    """
    problem = problem or _problem(model, scan, noise, priors)
    spec = spec or str(getattr(model, "spec", ""))
    starts, free = warm_starts(problem, list(warm))
    base = starts or [problem.default_theta()]
    noise = np.array([is_noise(n) for n in problem.param_names])
    rng = np.random.default_rng(seed)
    cand = list(base)
    lo, hi = problem.bounds.T
    for _ in range(n_random if free.any() else 0):
        th = base[0].copy()
        for j in np.flatnonzero(free):
            th[j] = problem.priors[j].sample(rng, 1)[0]
        cand.append(np.clip(th, lo, hi))
    cand = np.array(cand)
    lp = np.concatenate([problem.log_prob(cand[i:i + 64])[0] for i in range(0, len(cand), 64)])
    order = [0] + [i for i in np.argsort(-lp) if i != 0 and np.isfinite(lp[i])
                   and (not starts or lp[i] > lp[0])]
    best: MapResult | None = None
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore")
        for i in order[:max(1, n_polish)]:
            r = fit_map(problem, x0=cand[i], n_starts=1, seed=seed)
            if best is None or _zpost(problem, r) > _zpost(problem, best):
                best = r
        # Restart from the best optimum with the noise parameters reset to their defaults:
        # the posterior has a second basin where a large sigma_extra with a long AR(1)
        # correlation length absorbs the misfit, and a start warm from a smaller model sits
        # in it even when the added effect can explain the misfit down to the noise.
        # With the short wobble (NoiseOptions(short=True)) the wobble starts quiet (1 um):
        # from the default 10 um with the long length at its 2 mm floor, a user effect that
        # explains the misfit to the noise fell back into that basin (gear_slip example:
        # sigma_extra 19 um, slip at 10 mm/s 40 % off).
        # And once more with the wobble quiet (1 um): the defaults (10 um over 0.5 mm) are
        # themselves a basin where the wobble plays the white measurement noise; warm from
        # `pa`, the hidden bed tilt's fit stayed there on 2 of 10 seeds (bench_discover:
        # Delta BIC 88 and 94 where a cold start found 253, and bed_mesh, 210, was named).
        reset = best.theta.copy()
        reset[noise] = problem.default_theta()[noise]
        sig = [j for j, n in enumerate(problem.param_names) if n.startswith(SIGMA_NAME)]
        quiet = reset.copy()
        quiet[sig] = 0.001
        if problem.noise.short and problem.noise.ar1:
            reset = quiet
        n_ok = min(len(order), max(1, n_polish))
        tried = [best.theta]
        for x0 in (reset, quiet):
            if any(np.allclose(x0, t) for t in tried):
                continue
            tried.append(x0)
            r = fit_map(problem, x0=np.clip(x0, lo, hi), n_starts=1, seed=seed)
            n_ok += 1
            if _zpost(problem, r) > _zpost(problem, best):
                best = r
    best.model = spec
    best.n_starts = n_ok
    pred = problem.predict(best.theta, 0)[0, scan.order]
    return ModelFit(spec=spec, map=best, problem=problem, pred_mm=pred, resid_mm=scan.y_mm - pred)


def full_fit(fit: ModelFit, seed: int = 0, max_steps: int = 20000, progress: bool = False,
             **kw) -> ModelFit:
    """The posterior of an already MAP-fitted model (:func:`fit.sampler.fit_mcmc` from its MAP):
    emcee to convergence, PSIS-LOO."""
    with np.errstate(divide="ignore", invalid="ignore"):
        res = fit_mcmc(fit.problem, map_result=fit.map, seed=seed, max_steps=max_steps,
                       progress=progress, **kw)
    res.model = fit.spec
    return ModelFit(spec=fit.spec, map=fit.map, problem=fit.problem, pred_mm=fit.pred_mm,
                    resid_mm=fit.resid_mm, full=res)


def delta_elpd(f: ModelFit, ref: ModelFit | None) -> tuple[float, float]:
    """elpd_loo(f) - elpd_loo(ref) and its se from the paired pointwise differences."""
    if ref is None or f.elpd_i is None or ref.elpd_i is None or len(f.elpd_i) != len(ref.elpd_i):
        # (different observations, e.g. one fit ignored the missing stations: not paired)
        return float("nan"), float("nan")
    d = f.elpd_i - ref.elpd_i
    return float(np.sum(d)), float(math.sqrt(len(d) * np.var(d)))


# -- comparison -------------------------------------------------------------------------------

@dataclass
class Comparison:
    """Models fitted to one scan, best (lowest BIC) first, with differences to the best."""

    fits: list[ModelFit]
    scan: ScanData | None = field(default=None, repr=False)

    def _best_loo_fit(self):
        c = [f for f in self.fits if f.elpd_i is not None and np.isfinite(f.elpd_loo)]
        return max(c, key=lambda f: f.elpd_loo) if c else None

    def rows(self) -> list[dict]:
        best_bic = min(f.bic for f in self.fits)
        best_loo = self._best_loo_fit()
        rows = []
        for f in self.fits:
            d_bic = f.bic - best_bic
            d_elpd, d_se = delta_elpd(f, best_loo)
            rows.append({
                "model": f.spec, "n": f.n, "k": f.k, "rms_mm": f.rms_mm, "chi2_nu": f.chi2_nu,
                "loglik": f.loglik, "bic": f.bic, "delta_bic": d_bic,
                "delta_bic_eff": d_bic,  # the AR(1) likelihood already carries the correlation
                "n_eff": f.n_eff, "elpd_loo": f.elpd_loo, "elpd_loo_se": f.elpd_loo_se,
                "delta_elpd_loo": d_elpd, "delta_elpd_loo_se": d_se,
                "pareto_k_max": f.pareto_k_max, "params": f.params(),
                "intervals": {k: list(v) for k, v in f.intervals().items()},
                "extra_noise_mm": f.extra_mm, "corr_len_mm": f.corr_len_mm,
                "converged": f.converged,
            })
        return rows

    def to_json(self) -> dict:
        return {"schema": "calib.compare/1", "models": _clean(self.rows())}


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (bool, np.bool_)) or o is None:
        return None if o is None else bool(o)
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else float(o)
    if isinstance(o, np.integer):
        return int(o)
    return o


def compare_models(scan: ScanData, models: dict, full: bool = True, seed: int = 0,
                   max_steps: int = 20000, progress: bool = False,
                   noise: NoiseOptions | None = None, priors: dict | None = None) -> Comparison:
    """Fit each model (``{spec: Model}``) by MAP (and, if ``full``, by MCMC + PSIS-LOO).

    Models are warm-started from the earlier fits that share their parameters, so a model
    that extends another starts at that model's optimum and never fits worse than it.
    ``noise``: the engine's noise options (default: AR(1) along tracks, Gaussian);
    ``priors``: prior overrides (fit.priors format), each applied to the models that have
    the parameter.
    """
    from calib.progress import progress as bar

    fits: list[ModelFit] = []
    for spec, model in bar(list(models.items()), desc="compare", unit="model", disable=not progress):
        problem = _problem(model, scan, noise, priors)
        f = fit_model(model, scan, spec, warm=fits, seed=seed, problem=problem)
        fits.append(f)
    if full:
        fits = [full_fit(f, seed=seed, max_steps=max_steps, progress=progress) for f in fits]
    fits.sort(key=lambda f: f.bic)
    return Comparison(fits, scan)
