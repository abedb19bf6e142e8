"""MAP and MCMC fitting of a :class:`fit.likelihood.JointProblem`.

``fit_map``: multi-start L-BFGS-B on z = log(theta) for positive parameters (so time
constants spanning decades are searched evenly) and z = theta otherwise; gradients by
forward differences evaluated in *one* vectorised model call; the covariance is the
Laplace approximation (inverse Hessian of -log posterior by central differences, mapped
back to theta by the Jacobian of exp).

``fit_mcmc``: emcee 3 EnsembleSampler (vectorize=True; walkers in the same z as the MAP
search, with the log-Jacobian) with the mixture
[(DEMove, 0.8), (DESnookerMove, 0.2)] (ter Braak & Vrugt 2008; mixes 2-3x faster than the
stretch move on these correlated posteriors). Several *independent* ensembles (default
2), started from separate draws of the Laplace approximation around the MAP, so that the
rank-normalised split R-hat (Vehtari et al. 2021) compares chains that never exchanged
information (R-hat across walkers of one ensemble is not meaningful: the walkers are
coupled by the moves). Stopping rule (emcee docs, Goodman & Weare 2010; Vehtari et al. 2021): every
``check_every`` steps compute the integrated autocorrelation time tau of every parameter
in every ensemble; once the chain is longer than ``tau_factor`` x max tau and max tau
changed by less than ``tau_rtol`` since the last check, compute the split R-hat of the
post-burn-in chains and stop when it is below ``rhat_max`` for every parameter; otherwise
keep sampling. Burn-in 2 max tau is discarded and the chains thinned by tau/2. A run that
hits ``max_steps`` or ``max_time_s`` first is reported as *not converged*
(``FitResult.diagnostics["converged"] = False``; ``calib fit`` exits with code 3).
"""
from __future__ import annotations

import math
import time
import warnings

import emcee
import numpy as np
from scipy.optimize import minimize
from scipy.special import logsumexp

from calib.errors import UserError
from calib.progress import progress as progress_bar
from fit.likelihood import JointProblem, NoiseOptions, is_noise
from fit.result import WOBBLE_REL_MAX
from fit.modes import distinct_modes, global_starts, physical_mask
from fit.result import FitResult, MapResult, ParamSummary

EXIT_NOT_CONVERGED = 3
#: printer keys the physics reads (mm): seed 000's tau = 32 D^2 L l / d^4 VE and the nozzle area
PHYSICS_KEYS = ("filament_diameter_mm", "nozzle_diameter_mm", "nozzle_land_length_mm",
                "bowden_length_mm")


# -- problem construction ---------------------------------------------------------
def make_problem(model, data, noise: NoiseOptions | None = None, prior_overrides=None,
                 extra_effects=()) -> JointProblem:
    """Build the posterior of ``model`` on ``data`` (:class:`fit.data.FitData` or one ScanData).

    ``model``: a model spec string ("pa+thermal"; a model per scan is built with
    ``fit.model.build_model(spec, profile_of_that_scan)``), one Model object (shared by all
    scans) or a list of models (one per scan).
    """
    scans = getattr(data, "scans", None) or [data]
    if isinstance(model, str):
        from fit.model import build_model

        models = []
        for sc in scans:
            # The physics needs the nozzle and filament geometry, not the motion limits a
            # full profile also holds (manifests from `calib plan` and the shipped examples
            # carry only the geometry).
            prof = dict(sc.manifest.printer or {})
            bad = [k for k in PHYSICS_KEYS
                   if not isinstance(prof.get(k), (int, float)) or not prof[k] >= 0]
            if bad:
                raise UserError(f"{sc.name}: the manifest's printer block lacks a usable "
                                f"{bad[0]} (mm); regenerate the manifest with --printer")
            models.append(build_model(model, prof, extra_effects=tuple(extra_effects)))
        for sc, m in zip(scans, models):
            if sc.ctx is None:
                from fit.context import SimContext
                from fit.observe import observation_of
                sc.ctx = SimContext.build(sc.manifest, sc.samples, observe=observation_of(sc.table))
    elif isinstance(model, (list, tuple)):
        models = list(model)
    else:
        models = [model] * len(scans)
    return JointProblem(scans, models, noise or NoiseOptions(), prior_overrides)


def model_label(problem: JointProblem, model=None) -> str:
    if isinstance(model, str):
        return model
    m = problem.models[0]
    return str(getattr(m, "spec", getattr(m, "name", type(m).__name__)))


# -- transforms ---------------------------------------------------------------------
class _Transform:
    """theta <-> z: log for parameters with a positive lower bound."""

    def __init__(self, problem: JointProblem):
        self.log = np.array([p.positive for p in problem.priors])
        lo, hi = problem.bounds.T
        # log only where the parameter is log-transformed: other bounds may be 0 or < 0
        self.zlo = np.where(self.log, np.log(np.where(self.log, lo, 1.0)), lo)
        self.zhi = np.where(self.log, np.log(np.where(self.log, hi, 1.0)), hi)

    def to_theta(self, z):
        z = np.asarray(z, dtype=float)
        return np.where(self.log, np.exp(z), z)

    def to_z(self, th):
        th = np.asarray(th, dtype=float)
        return np.where(self.log, np.log(np.where(self.log, th, 1.0)), th)


def _logpost_z(problem, tr, z):
    """log posterior density in z (includes the log-Jacobian of exp for log parameters)."""
    th = tr.to_theta(np.atleast_2d(z))
    lp, _ = problem.log_prob(th)
    return lp + (np.atleast_2d(z) * tr.log).sum(axis=1)


def _hessian_z(problem, tr, z0, h=1e-3, free=None):
    """Central-difference Hessian of -log posterior in z, all points in one call; over the
    parameters where ``free`` (bool mask) is True only, the others held at z0."""
    idx = np.arange(len(z0)) if free is None else np.flatnonzero(free)
    d = len(idx)
    pts, keys = [z0], []
    for i in range(d):
        for j in range(i, d):
            for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                p = z0.copy()
                p[idx[i]] += si * h
                p[idx[j]] += sj * h
                pts.append(p)
                keys.append((i, j, si * sj))
    f = -_logpost_z(problem, tr, np.array(pts))
    if not np.all(np.isfinite(f)):
        # a stencil point left the support (a parameter at its bound): no Laplace curvature
        raise np.linalg.LinAlgError("Hessian stencil outside the prior support")
    H = np.zeros((d, d))
    for (i, j, sgn), fv in zip(keys, f[1:]):
        H[i, j] += sgn * fv / (4 * h * h)
    H = H + np.triu(H, 1).T
    return H


def _laplace_cov_z(problem, tr, z, h: float = 1e-3) -> np.ndarray:
    """Laplace covariance in z at the MAP z. Parameters within 2 h of a bound (a wobble's
    sd at its floor, an effect at its "absent" 0) have no two-sided curvature: the
    Hessian is taken over the others, and those get a small variance (1e-4 in z), the
    same as every parameter gets when the Hessian fails altogether. Before, one such
    parameter cost every other one its Laplace sd (and the sampler its start ball)."""
    d = len(z)
    free = (z - tr.zlo > 2 * h) & (tr.zhi - z > 2 * h)
    cov_z = np.diag(np.full(d, 1e-4))
    # a noise parameter the data hardly hold (a wobble's sd near its floor, below the
    # measurement's own) has a curvature of either sign: then the print's parameters get
    # their curvature with the noise held at the MAP (linked measurement errors took the
    # wobble to its 0.1 um floor on 3 of 10 demo-setup seeds, and every sd fell back)
    physical = np.array([not is_noise(n) for n in problem.param_names])
    for mask in (free, free & physical):
        if not mask.any():
            continue
        try:
            Hz = _hessian_z(problem, tr, z, h=h, free=mask)
            sub = np.linalg.inv(Hz)
            if not np.all(np.isfinite(sub)) or np.any(np.linalg.eigvalsh(0.5 * (sub + sub.T)) <= 0):
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            continue
        cov_z[np.ix_(mask, mask)] = sub
        return cov_z
    return cov_z


def fit_map(model, data=None, *, n_starts: int = 4, seed: int = 0, noise=None,
            prior_overrides=None, extra_effects=(), x0=None, maxiter: int = 400,
            global_search: bool = False) -> MapResult:
    """Maximum a posteriori fit. ``fit_map(problem)`` or ``fit_map(model, data)`` (see
    :func:`make_problem`). Starts: ``x0`` (or the model defaults) and ``n_starts - 1`` prior
    draws; the best optimum wins.

    ``global_search``: instead of prior draws, start from the distinct basins a
    differential evolution over the whole prior support finds (:mod:`fit.modes`, fixed
    seed: the MAP then does not depend on ``seed``); every distinct optimum is kept in
    ``MapResult.modes`` (best first, with BIC)."""
    problem = model if isinstance(model, JointProblem) else make_problem(
        model, data, noise, prior_overrides, extra_effects)
    tr = _Transform(problem)
    rng = np.random.default_rng(seed)
    starts = [problem.default_theta() if x0 is None else np.asarray(x0, dtype=float)]
    lo, hi = problem.bounds.T
    # a small step inside the bounds keeps finite differences legal
    zlo, zhi = tr.zlo + 1e-9, tr.zhi - 1e-9
    d = problem.ndim
    phys = physical_mask(problem.param_names)
    if global_search:
        z_def = np.clip(tr.to_z(np.clip(starts[0], lo, hi)), zlo, zhi)
        starts += [tr.to_theta(z) for z in global_starts(
            lambda Z: -_logpost_z(problem, tr, Z), zlo, zhi, phys, z_def)]
    else:
        for _ in range(max(0, n_starts - 1)):
            th = np.array([p.sample(rng, 1)[0] for p in problem.priors])
            # noise parameters start at a typical scale; prior draws of those are wasteful
            th[~phys] = starts[0][~phys]
            starts.append(np.clip(th, lo, hi))

    def fun_grad(z):
        h = 1e-6 * np.maximum(1.0, np.abs(z))
        pts = np.vstack([z, z + np.diag(h)])
        pts = np.clip(pts, zlo - 1e-9, zhi + 1e-9)
        f = -_logpost_z(problem, tr, pts)
        if not np.isfinite(f[0]):
            return 1e300, np.zeros(d)
        g = np.where(np.isfinite(f[1:]), (f[1:] - f[0]) / h, 0.0)
        return float(f[0]), g

    optima = []
    for s in starts:
        z0 = np.clip(tr.to_z(np.clip(s, lo, hi)), zlo, zhi)
        f0, _ = fun_grad(z0)
        if not np.isfinite(f0) or f0 >= 1e300:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = minimize(fun_grad, z0, jac=True, method="L-BFGS-B",
                           bounds=list(zip(zlo, zhi)), options={"maxiter": maxiter})
        optima.append((res.x, res))
    if not optima:
        raise UserError("the model cannot reproduce these widths at any starting point "
                        "(log-likelihood is -inf everywhere); check the manifest and the model")
    optima.sort(key=lambda o: o[1].fun)
    best = optima[0][1]
    z = best.x
    theta = tr.to_theta(z)
    cov_z = _laplace_cov_z(problem, tr, z)
    J = np.where(tr.log, theta, 1.0)
    cov = cov_z * np.outer(J, J)
    out = _map_result(problem, theta, cov, best, len(optima), model_label(problem, model))
    if global_search:
        out.modes = _mode_table(problem, tr, distinct_modes(optima, phys))
    return out


def _mode_table(problem, tr, modes) -> list[dict]:
    """Every distinct optimum, best first: parameter values, ln posterior, ln L and BIC."""
    th = np.array([tr.to_theta(z) for z, _ in modes])
    lp, ll = problem.log_prob(th)
    n, k = problem.n_obs, problem.ndim
    return [{"values": dict(zip(problem.param_names, map(float, t))), "log_post": float(lp[i]),
             "loglik": float(ll[i].sum()), "bic": float(k * math.log(n) - 2.0 * ll[i].sum())}
            for i, t in enumerate(th)]


def _map_result(problem, theta, cov, res, n_ok, label) -> MapResult:
    lp, ll = problem.log_prob(theta)
    resid = np.concatenate(problem.residuals(theta))
    sd = np.concatenate([sc.sd_mm for sc in problem.scans])
    k_model = sum(1 for n in problem.param_names if not is_noise(n))
    n = problem.n_obs
    n_valid = len(resid)          # chi2_nu and RMS: valid samples (missing ones have no residual)
    # the bead's own wobble, allowed up to WOBBLE_REL_MAX of the width (fit/result.py)
    # (long and short wobble together)
    # (long and short wobble together; the long one's sd is sigma_extra at the scan's
    # median width whatever its relative share)
    allow = np.concatenate([np.full(len(sc.y_mm), min(
        math.hypot(float(theta[i_sig]), 0.0 if i_short is None else float(theta[i_short])),
        WOBBLE_REL_MAX * float(np.median(np.abs(sc.y_mm))) if len(sc.y_mm) else 0.0))
        for sc, (i_sig, _, i_short) in zip(problem.scans, problem.noise_index)])
    return MapResult(model=label, param_names=list(problem.param_names), theta=theta, cov=cov,
                     log_post=float(lp[0]), loglik=float(ll[0].sum()), pointwise=ll[0],
                     n_obs=n, k=problem.ndim, k_model=k_model,
                     rms_mm=float(np.sqrt(np.mean(resid ** 2))),
                     chi2_nu=float(np.sum((resid / sd) ** 2) / max(1, n_valid - k_model)),
                     chi2_nu_bead=float(np.sum(resid ** 2 / (sd ** 2 + allow ** 2)) / max(1, n_valid - k_model)),
                     n_missing=int(getattr(problem, "n_missing", 0)),
                     success=bool(getattr(res, "success", True)), n_starts=n_ok,
                     message=str(getattr(res, "message", "")))


# -- MCMC -----------------------------------------------------------------------------
def _initial_ball(problem, tr, map_res, n, rng):
    """Walkers from the Laplace approximation in z shrunk by 0.3 (inside the support)."""
    z0 = tr.to_z(map_res.theta)
    J = np.where(tr.log, map_res.theta, 1.0)
    cov_z = map_res.cov / np.outer(J, J)
    try:
        L = np.linalg.cholesky(0.5 * (cov_z + cov_z.T))
    except np.linalg.LinAlgError:
        L = np.diag(np.full(len(z0), 1e-3))
    out = []
    tries = 0
    while len(out) < n:
        tries += 1
        scale = 0.3 if tries < 50 * n else 0.01
        z = z0 + scale * L @ rng.standard_normal(len(z0))
        th = tr.to_theta(z)
        if np.isfinite(problem.log_prob(th)[0][0]):
            out.append(th)
        elif tries > 200 * n:
            out.append(map_res.theta * (1 + 1e-6 * rng.standard_normal(len(z0))))
    return np.array(out)


def fit_mcmc(model, data=None, *, map_result: MapResult | None = None, n_walkers: int | None = None,
             n_ensembles: int = 2, max_steps: int = 20000, min_steps: int = 200,
             check_every: int = 100, tau_factor: float = 50.0, tau_rtol: float = 0.01,
             rhat_max: float = 1.01, max_time_s: float | None = None, seed: int = 0,
             progress: bool = True, n_loo_draws: int = 400, noise=None, prior_overrides=None,
             extra_effects=(), n_starts: int = 4) -> FitResult:
    """Full posterior of ``model`` on ``data`` (or of a JointProblem), see module docstring."""
    problem = model if isinstance(model, JointProblem) else make_problem(
        model, data, noise, prior_overrides, extra_effects)
    label = model_label(problem, model)
    t0 = time.perf_counter()
    if map_result is None:
        map_result = fit_map(problem, n_starts=n_starts, seed=seed)
    t_map = time.perf_counter() - t0
    d = problem.ndim
    nw = n_walkers or max(12, 2 * d + 4)
    nw += nw % 2
    tr = _Transform(problem)
    rng = np.random.default_rng(seed)

    # The walkers move in z (log theta for positive parameters, as the MAP search): the
    # posterior is then closer to Gaussian, and products that the data pin down (Kb*w_sat
    # of a saturated back-pressure, a*tau_th of thermal ooze) become linear combinations
    # of the coordinates, which the affine-invariant DE moves sample efficiently; in theta
    # they are curved ridges. The log-Jacobian keeps the target the same posterior.
    def logp(z):
        return _logpost_z(problem, tr, z)

    groups = [np.arange(e * nw, (e + 1) * nw) for e in range(n_ensembles)]
    sampler = emcee.EnsembleSampler(
        nw * n_ensembles, d, logp, vectorize=True,
        moves=[(GroupedMove(emcee.moves.DEMove(), n_ensembles), 0.8),
               (GroupedMove(emcee.moves.DESnookerMove(), n_ensembles), 0.2)])
    sampler._random = np.random.mtrand.RandomState(int(rng.integers(2 ** 31)))
    p0 = tr.to_z(np.concatenate([_initial_ball(problem, tr, map_result, nw, rng)
                                 for _ in range(n_ensembles)]))
    gen = sampler.sample(p0, iterations=max_steps, store=True)
    tau_prev = None
    tau = np.full(d, np.nan)
    stop_reason = "max_steps"
    steps = 0
    bar = progress_bar(total=max_steps, desc=f"fit {label}", unit="step", disable=not progress,
                       leave=False)
    history = []

    def group_tau():
        ch = sampler.get_chain()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # the ACF averaged over all walkers of all ensembles (same target) is a less
            # noisy estimate than per ensemble, so the 1 % stability test is not dominated
            # by estimator noise
            return emcee.autocorr.integrated_time(ch, tol=0)

    def posterior(tau_now):
        """Post-burn-in, thinned chains (n, walkers, d) per ensemble and their split R-hat."""
        tau_now = np.where(np.isfinite(tau_now), tau_now, steps / 2.0)
        burn = int(min(2 * np.max(tau_now), steps // 2))
        thin = max(1, int(0.5 * np.min(tau_now)))
        full = tr.to_theta(sampler.get_chain(discard=burn, thin=thin))
        return full, [full[:, g, :] for g in groups], burn, thin

    rhat = np.full(d, np.inf)
    try:
        for steps in range(1, max_steps + 1):
            next(gen)
            bar.update(1)
            if steps % check_every == 0:
                tau = group_tau()
                history.append([steps, float(np.max(tau))])
                # The chain-length rule is N > tau_factor * max(tau); what must be stable is
                # that max. Requiring every parameter's noisy tau estimate to move < 1 %
                # between checks at once almost never happens with 5+ parameters.
                stable = tau_prev is not None and \
                    abs(np.max(tau) - np.max(tau_prev)) / np.max(tau) < tau_rtol
                long_enough = steps >= min_steps and np.all(np.isfinite(tau)) and \
                    steps > tau_factor * np.max(tau) and stable
                if long_enough:
                    # Only then is R-hat worth computing; a chain that is long enough but
                    # whose ensembles still disagree (a noise parameter at its bound mixes
                    # slowly) keeps sampling instead of stopping "not converged".
                    rhat = _split_rhat(posterior(tau)[1])
                    history[-1].append(float(np.max(rhat)))
                    if np.all(rhat < rhat_max):
                        stop_reason = "converged"
                        bar.set_postfix(tau=f"{np.max(tau):.1f}", rhat=f"{np.max(rhat):.4f}")
                        break
                bar.set_postfix(tau=f"{np.max(tau):.1f}", need=int(tau_factor * np.max(tau)),
                                rhat=f"{np.max(rhat):.3f}")
                tau_prev = tau
                if max_time_s is not None and time.perf_counter() - t0 > max_time_s:
                    stop_reason = "max_time"
                    break
    finally:
        bar.close()
        gen.close()
    if not np.all(np.isfinite(tau)) or steps % check_every:
        tau = group_tau()
    tau = np.where(np.isfinite(tau), tau, steps / 2.0)
    full, chains, burn, thin = posterior(tau)
    flat = full.reshape(-1, d)
    rhat = _split_rhat(chains)
    n_post = steps - burn
    ess = n_ensembles * nw * n_post / tau
    acc = float(np.mean(sampler.acceptance_fraction))
    converged = stop_reason == "converged" and bool(np.all(rhat < rhat_max))
    diag = {
        "converged": converged, "stop_reason": stop_reason, "n_steps": steps,
        "n_walkers": nw, "n_ensembles": n_ensembles, "burn_in": burn, "thin": thin,
        "tau_steps": dict(zip(problem.param_names, map(float, tau))),
        "ess": dict(zip(problem.param_names, map(float, ess))),
        "rhat": dict(zip(problem.param_names, map(float, rhat))),
        "acceptance_fraction": acc, "tau_factor": tau_factor, "tau_rtol": tau_rtol,
        "rhat_max": rhat_max, "max_steps": max_steps,
        "wall_time_s": time.perf_counter() - t0, "map_time_s": t_map,
        "tau_history": history,
    }
    if not converged:
        long_enough = steps > tau_factor * np.max(tau)
        why = {"max_steps": f"hit the cap of {max_steps} steps before "
                            + (f"the independent ensembles agreed (R-hat {np.max(rhat):.3f} > {rhat_max})"
                               if long_enough else
                               f"the chain was {tau_factor:g} tau long with a stable tau"),
               "max_time": f"hit the time cap of {max_time_s} s"}.get(stop_reason, "")
        diag["warning"] = "NOT CONVERGED: " + why + "; raise --max-steps or --max-time"
    params = {n: ParamSummary.from_draws(n, flat[:, j], map_result.theta[j], tau=float(tau[j]),
                                         ess=float(ess[j]), rhat=float(rhat[j]))
              for j, n in enumerate(problem.param_names)}
    cov = np.cov(flat.T).reshape(d, d)
    loo, preds = _loo_and_predictions(problem, flat, map_result, n_loo_draws, rng)
    return FitResult(model=label, param_names=list(problem.param_names), params=params,
                     map=map_result, cov=cov, samples=_subsample(flat, 4000, rng),
                     diagnostics=diag, loo=loo, predictions=preds,
                     priors={n: p.to_json() for n, p in zip(problem.param_names, problem.priors)},
                     profile=dict(problem.scans[0].manifest.printer) if problem.scans[0].manifest else {},
                     seed=seed)


class GroupedMove(emcee.moves.Move):
    """Run a red-blue ``inner`` move (DEMove, DESnookerMove) independently inside each of
    ``n_groups`` equal groups of walkers: a walker's proposal only uses walkers of its own
    group, so the groups are independent ensembles (for R-hat), while the log-probability
    of all groups' proposals is computed in one vectorised model call per half-step (the
    physics kernel has a fixed cost per call; batching halves the wall time for two
    ensembles). Same acceptance rule as emcee's RedBlueMove.propose."""

    def __init__(self, inner, n_groups: int):
        self.inner, self.n_groups = inner, int(n_groups)

    def propose(self, model, state):
        nw_tot, d = state.coords.shape
        m = nw_tot // self.n_groups
        group = np.arange(nw_tot) // m
        self.inner.setup(state.coords[:m])
        ns = self.inner.nsplits
        half = np.empty(nw_tot, dtype=int)
        for g in range(self.n_groups):
            h = np.arange(m) % ns
            model.random.shuffle(h)
            half[group == g] = h
        accepted = np.zeros(nw_tot, dtype=bool)
        for split in range(ns):
            qs, fs, idx = [], [], []
            for g in range(self.n_groups):
                mine = (group == g) & (half == split)
                others = [state.coords[(group == g) & (half == j)] for j in range(ns) if j != split]
                q, f = self.inner.get_proposal(state.coords[mine], others, model.random)
                qs.append(q)
                fs.append(np.asarray(f, dtype=float))
                idx.append(np.flatnonzero(mine))
            idx = np.concatenate(idx)
            order = np.argsort(idx)
            idx, q, f = idx[order], np.concatenate(qs)[order], np.concatenate(fs)[order]
            nlp, blobs = model.compute_log_prob_fn(q)
            # a proposal outside the support (-inf) from a walker still there, or a snooker
            # factor of a degenerate pair, gives inf - inf: NaN, never accepted, as in emcee
            with np.errstate(invalid="ignore"):
                acc = f + nlp - state.log_prob[idx] > np.log(model.random.rand(len(idx)))
            accepted[idx[acc]] = True
            subset = np.zeros(nw_tot, dtype=bool)
            subset[idx] = True
            state = self.update(state, emcee.State(q, log_prob=nlp, blobs=blobs), accepted, subset)
        return state, accepted


def _subsample(flat, n, rng):
    if len(flat) <= n:
        return flat
    return flat[np.sort(rng.choice(len(flat), n, replace=False))]


def _split_rhat(chains) -> np.ndarray:
    """Rank-normalised split R-hat: each ensemble's post-burn chain is split in two halves in
    time; each half (all its walkers) is one chain."""
    from arviz_stats.base import array_stats

    d = chains[0].shape[2]
    half = chains[0].shape[0] // 2
    if half < 2:
        return np.full(d, np.inf)
    parts = []
    for c in chains:
        parts.append(c[:half].reshape(-1, d))
        parts.append(c[half:2 * half].reshape(-1, d))
    arr = np.stack(parts)             # (n_chains, n_draws, d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = np.array([array_stats.rhat(arr[:, :, j], chain_axis=0, draw_axis=1) for j in range(d)],
                     dtype=float)
    return np.where(np.isfinite(r), r, np.inf)


def psis_tail_length(n_draws: int, r_eff: float = 1.0) -> int:
    """Tail length M = min(0.2 S, 3 sqrt(S / r_eff)) (Vehtari et al. 2024, sec. 3; rounded
    down, as arviz_stats does)."""
    if n_draws * r_eff > 225:
        return int(math.floor(3.0 * math.sqrt(n_draws / r_eff)))
    return int(math.floor(n_draws / 5))


def _gpd_fit_rows(x: np.ndarray, chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Generalized Pareto (k, sigma) of every row of ``x`` (n, M), each row the sorted
    (ascending) exceedances of one observation over its threshold.

    Zhang & Stephens (2009) profile estimator: a grid of m = 30 + floor(sqrt(M)) values

        b_j = 1/x_(M) + (1 - sqrt(m / (j - 1/2))) / (3 x_(floor(M/4 + 1/2))),

    k(b) = mean_i log(1 - b x_i), profile log-likelihood l(b) = M (log(-b/k) - k - 1),
    b_hat = sum_j b_j w_j with w = softmax(l) (weights < 10 eps dropped), k = mean log(1 -
    b_hat x), sigma = -k / b_hat; then the weakly informative prior of PSIS (Vehtari et
    al. 2024, eq. 17 / loo: normal around 0.5 worth 10 observations):
    k <- (M k + 10 * 0.5) / (M + 10). Rows of equal values give k = sigma = NaN.
    """
    n, M = x.shape
    m = 30 + int(math.sqrt(M))
    j = np.arange(1, m + 1, dtype=float)
    base = 1.0 - np.sqrt(m / (j - 0.5))
    q = x[:, int(M / 4 + 0.5) - 1]
    xmax = x[:, -1]
    k_out = np.full(n, np.nan)
    s_out = np.full(n, np.nan)
    ok = (xmax > 0) & (q > 0) & np.all(np.isfinite(x), axis=1)
    idx = np.flatnonzero(ok)
    tiny = 10 * np.finfo(float).eps
    for a in range(0, len(idx), chunk):
        r = idx[a:a + chunk]
        xr = x[r]
        b = base[None, :] / (3.0 * q[r, None]) + 1.0 / xmax[r, None]          # (c, m)
        kb = np.log1p(-b[:, :, None] * xr[:, None, :]).mean(axis=2)          # (c, m)
        with np.errstate(divide="ignore", invalid="ignore"):
            ls = M * (np.log(-b / kb) - kb - 1.0)
        ls = np.where(np.isfinite(ls), ls, -np.inf)
        w = np.exp(ls - logsumexp(ls, axis=1, keepdims=True))
        w = np.where(w >= tiny, w, 0.0)
        w /= w.sum(axis=1, keepdims=True)
        b_post = (b * w).sum(axis=1)
        k = np.log1p(-b_post[:, None] * xr).mean(axis=1)
        s_out[r] = -k / b_post
        k_out[r] = (M * k + 10 * 0.5) / (M + 10)
    return k_out, s_out


def psis_log_weights(log_ratios, r_eff: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Pareto smoothed importance sampling (Vehtari, Simpson, Gelman, Yao & Gabry 2024,
    JMLR 25(72)) for all rows of ``log_ratios`` (n_obs, S) at once.

    Per row: the M = :func:`psis_tail_length` largest raw weights r = exp(lr - max lr) are
    replaced by the expected order statistics of a generalized Pareto fitted to their
    exceedances over the (M+1)-th largest weight u (:func:`_gpd_fit_rows`),

        r_(S-M+z) = u + sigma/k ((1 - p_z)^(-k) - 1),   p_z = (z - 1/2)/M,  z = 1..M,

    truncated at the largest raw weight; returned normalised (logsumexp 0 per row) with
    the Pareto k per row. Rows whose tail cannot be fitted (M < 5, all tail values equal)
    keep their raw weights and get k = NaN. Same numbers as arviz_stats' per-observation
    ``psislw`` (tests/test_fit_loo.py), ~50x faster on 8,000 x 400.
    """
    lr = np.asarray(log_ratios, dtype=float)
    lr = lr - lr.max(axis=1, keepdims=True)
    n, S = lr.shape
    M = psis_tail_length(S, r_eff)
    khat = np.full(n, np.nan)
    if M >= 5 and S > M:
        part = np.argpartition(lr, S - M - 1, axis=1)
        cut_idx = part[:, S - M - 1]
        tail_idx = part[:, S - M:]
        tail = np.take_along_axis(lr, tail_idx, axis=1)
        order = np.argsort(tail, axis=1, kind="stable")
        tail_idx = np.take_along_axis(tail_idx, order, axis=1)
        tail = np.take_along_axis(tail, order, axis=1)                        # ascending
        cutoff = np.exp(lr[np.arange(n), cut_idx])
        k, sigma = _gpd_fit_rows(np.exp(tail) - cutoff[:, None])
        khat = k
        smooth = np.isfinite(k) & (sigma > 0)
        if np.any(smooth):
            p = (np.arange(M) + 0.5) / M
            ks, ss = k[smooth, None], sigma[smooth, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                q = np.where(ks == 0, -ss * np.log1p(-p)[None, :],
                             ss * np.expm1(-ks * np.log1p(-p)[None, :]) / np.where(ks == 0, 1.0, ks))
                sm = np.log(cutoff[smooth, None] + q)
            sm = np.minimum(sm, tail[smooth, -1:])          # truncate at the max raw weight
            rows = np.flatnonzero(smooth)
            lr[rows[:, None], tail_idx[smooth]] = sm
    lr = lr - logsumexp(lr, axis=1, keepdims=True)
    return lr, khat


def psis_loo(ll: np.ndarray) -> dict:
    """PSIS-LOO (Vehtari, Gelman & Gabry 2017) from pointwise log-likelihoods (n_draws, n_obs)
    of (nearly) independent posterior draws: elpd_loo, its standard error, p_loo, Pareto k.

    Raw LOO weights are 1/p(y_i | theta_s) (log ratio -ll), smoothed for all observations
    at once by :func:`psis_log_weights`; elpd_i = log sum_s w_is p(y_i | theta_s),
    p_loo = sum_i (lpd_i - elpd_i), se = sqrt(n var(elpd_i)).
    """
    ll = np.asarray(ll, dtype=float)
    llT = np.ascontiguousarray(ll.T)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lw, k = psis_log_weights(-llT)
    elpd_i = logsumexp(lw + llT, axis=1)
    lpd_i = logsumexp(llT, axis=1) - math.log(ll.shape[0])
    n = ll.shape[1]
    k = np.asarray(k, dtype=float)
    kmax = float(np.nanmax(k)) if np.any(np.isfinite(k)) else float("nan")
    return {"elpd_loo": float(elpd_i.sum()), "se": float(math.sqrt(n * np.var(elpd_i))),
            "p_loo": float((lpd_i - elpd_i).sum()), "n_draws": int(ll.shape[0]),
            "pareto_k_max": kmax, "n_pareto_k_gt_0.7": int(np.sum(k > 0.7)),
            "elpd_i": elpd_i.tolist(), "pareto_k": np.round(k, 4).tolist()}


def _loo_and_predictions(problem, flat, map_res, n_draws, rng):
    idx = rng.choice(len(flat), min(n_draws, len(flat)), replace=False)
    draws = flat[idx]
    lls, preds = [], [[] for _ in problem.scans]
    for i in range(0, len(draws), 64):
        chunk = draws[i:i + 64]
        lp, ll = problem.log_prob(chunk)
        lls.append(ll)
        for k in range(len(problem.scans)):
            preds[k].append(problem.predict(chunk, k))
    if lls:
        ll = np.concatenate(lls)
        ll = ll[np.all(np.isfinite(ll), axis=1)]
    else:       # n_draws = 0: no LOO, and the band collapses onto the MAP prediction
        ll = np.empty((0, 0))
        preds = [[problem.predict(map_res.theta, k)] for k in range(len(problem.scans))]
    loo = psis_loo(ll) if len(ll) >= 20 else {"elpd_loo": float("nan"), "warning": "too few draws"}
    out = []
    for k, sc in enumerate(problem.scans):
        P = np.concatenate(preds[k])
        q = np.quantile(P, [0.16, 0.5, 0.84], axis=0)
        pm = problem.predict(map_res.theta, k)[0]
        t = sc.table
        out.append({"scan": sc.name, **sc.source,
                    "track": t.track.tolist(), "s_mm": np.round(t.s_mm, 4).tolist(),
                    "width_mm": np.round(t.width_mm, 5).tolist(),
                    "width_sd_mm": np.round(t.width_sd_mm, 5).tolist(),
                    "valid": t.valid.astype(int).tolist(),
                    "pred_map_mm": np.round(pm, 5).tolist(),
                    "pred_median_mm": np.round(q[1], 5).tolist(),
                    "pred_lo68_mm": np.round(q[0], 5).tolist(),
                    "pred_hi68_mm": np.round(q[2], 5).tolist()})
    return loo, out
