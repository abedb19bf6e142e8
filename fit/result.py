"""Results of a fit: :class:`MapResult` (fast point estimate) and :class:`FitResult` (the
posterior), with ``fit.json`` read/write (schema ``calib.fit/1``).

Information criteria (Schwarz 1978; Vehtari, Gelman & Gabry 2017):

    BIC  = k ln n - 2 ln L(theta_MAP)        k all fitted parameters incl. noise, n samples
    AIC  = 2 k - 2 ln L(theta_MAP)
    elpd_loo = sum_i log( sum_s w_is p(y_i | theta_s) )   PSIS weights w (Pareto-smoothed)
    chi2_nu  = sum_i (r_i / width_sd_i)^2 / (n - k_model)  measurement sd only, so a model
               that misses an effect shows chi2_nu >> 1 even though sigma_extra absorbs it
    chi2_nu_bead = sum_i r_i^2 / (width_sd_i^2 + a^2) / (n - k_model),
               a = min(sigma_extra, WOBBLE_REL_MAX x median width)   (per scan)
               the same, allowing the bead's own width wobble up to a physical size: a real
               bead is not a constant of the model (filament diameter tolerance +-0.02-0.05 mm
               on 1.75 mm is +-2.3-5.7 % of area, i.e. of width at a fixed height; read as
               about 2 sd). On realistic renders whose beads wander by 1.2 % (measure/
               phenomena.py ``irregular``) the right model has chi2_nu 5.4 and chi2_nu_bead ~1;
               a missing effect that the fitted sigma_extra absorbs beyond 2 % still shows.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from calib.fileio import read_json_doc, write_json

SCHEMA = "calib.fit/1"
#: Rows of each envelope's draws fit.json keeps (FitResult.envelope_samples).
ENVELOPE_KEEP = 256
#: Largest bead wobble (sd, fraction of the width) that chi2_nu_bead accepts as the bead's own.
WOBBLE_REL_MAX = 0.02


@dataclass
class MapResult:
    """Maximum a posteriori fit.

    theta        (k,) MAP parameters (units as ``param_names``)
    cov          (k, k) Laplace covariance (inverse Hessian of -log posterior)
    loglik       ln L at the MAP;  pointwise (n,) its per-sample terms
    n_obs        terms of ln L: valid samples + censored missing stations (n_missing,
                 fit/likelihood.py), the n of BIC
    rms_mm       residual RMS over valid samples (mm)
    chi2_nu      reduced chi-square with the measurement sd only (see module docstring)
    chi2_nu_bead the same allowing the bead's own wobble (module docstring)
    """

    model: str
    param_names: list[str]
    theta: np.ndarray
    cov: np.ndarray
    log_post: float
    loglik: float
    pointwise: np.ndarray
    n_obs: int
    k: int
    k_model: int
    rms_mm: float
    chi2_nu: float
    success: bool
    n_starts: int = 1
    message: str = ""
    modes: list = field(default_factory=list)   # distinct optima, best first (fit.modes)
    n_missing: int = 0                           # of n_obs: stations with no bead seen (censored)
    chi2_nu_bead: float = float("nan")

    @property
    def bic(self) -> float:
        return float(self.k * np.log(self.n_obs) - 2.0 * self.loglik)

    @property
    def aic(self) -> float:
        return float(2 * self.k - 2.0 * self.loglik)

    @property
    def values(self) -> dict[str, float]:
        return dict(zip(self.param_names, map(float, self.theta)))

    def to_json(self) -> dict:
        sd = np.sqrt(np.clip(np.diag(self.cov), 0, None))
        return {"model": self.model, "theta": self.values,
                "sd": dict(zip(self.param_names, map(float, sd))),
                "log_post": self.log_post, "loglik": self.loglik, "bic": self.bic,
                "aic": self.aic, "n_obs": self.n_obs, "n_missing": self.n_missing, "k": self.k,
                "rms_mm": self.rms_mm,
                "chi2_nu": self.chi2_nu, "chi2_nu_bead": self.chi2_nu_bead,
                "success": self.success, "message": self.message,
                "modes": self.modes}


@dataclass
class ParamSummary:
    """Posterior summary of one parameter (units of the parameter)."""

    name: str
    median: float
    mean: float
    sd: float
    ci68: tuple[float, float]
    ci90: tuple[float, float]
    ci95: tuple[float, float]
    map: float
    tau: float = float("nan")     # integrated autocorrelation time (steps)
    ess: float = float("nan")     # effective sample size
    rhat: float = float("nan")    # rank-normalised split R-hat over independent ensembles

    @classmethod
    def from_draws(cls, name, draws, map_value, **kw) -> "ParamSummary":
        q = np.quantile(draws, [0.025, 0.05, 0.16, 0.5, 0.84, 0.95, 0.975])
        return cls(name, float(q[3]), float(np.mean(draws)), float(np.std(draws, ddof=1)),
                   (float(q[2]), float(q[4])), (float(q[1]), float(q[5])),
                   (float(q[0]), float(q[6])), float(map_value), **kw)


@dataclass
class FitResult:
    """A full posterior fit (what ``fit.json`` holds)."""

    model: str
    param_names: list[str]
    params: dict[str, ParamSummary]
    map: MapResult
    cov: np.ndarray
    samples: np.ndarray                      # (n_draws, k) thinned posterior draws
    diagnostics: dict
    loo: dict
    predictions: list[dict] = field(default_factory=list)   # per scan
    derived: dict = field(default_factory=dict)
    profile: dict = field(default_factory=dict)
    priors: dict = field(default_factory=dict)
    seed: int | None = None
    trust: dict = field(default_factory=dict)     # fit.trust.Verdict.to_json()
    #: draws (rows as ``samples``) of the envelopes that widened the intervals (fit/
    #: offset_envelope.py "offset", fit/noise_envelope.py "noise"): `calib export`'s width
    #: match takes its K interval over them too, as `calib fit`'s intervals do
    envelope_samples: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return bool(self.diagnostics.get("converged", False))

    def median(self, name: str) -> float:
        return self.params[name].median

    def draws(self, name: str) -> np.ndarray:
        return self.samples[:, self.param_names.index(name)]

    def to_json(self) -> dict:
        return {
            "schema": SCHEMA, "model": self.model, "converged": self.converged,
            "param_names": self.param_names,
            "params": {k: asdict(v) for k, v in self.params.items()},
            "map": self.map.to_json(), "covariance": self.cov.tolist(),
            "diagnostics": self.diagnostics,
            "information": {"loglik_map": self.map.loglik, "bic": self.map.bic, "aic": self.map.aic,
                            "n_obs": self.map.n_obs, "n_missing": self.map.n_missing,
                            "k": self.map.k, "rms_mm": self.map.rms_mm,
                            "chi2_nu": self.map.chi2_nu, "chi2_nu_bead": self.map.chi2_nu_bead,
                            "loo": self.loo},
            "derived": self.derived, "profile": self.profile, "priors": self.priors,
            "seed": self.seed, "trust": self.trust,
            "samples": np.round(self.samples, 7).tolist(),
            "envelope_samples": {k: np.round(v, 7).tolist() for k, v in self.envelope_samples.items()},
            "predictions": self.predictions,
        }

    def save(self, path) -> Path:
        return write_json(path, self.to_json())


def envelope_rows(draws, seed: int = 0) -> np.ndarray:
    """Up to ENVELOPE_KEEP rows of an envelope's ``draws`` (random, fixed seed), in order:
    what FitResult.envelope_samples keeps."""
    draws = np.asarray(draws, dtype=float)
    rows = np.random.default_rng(seed).choice(len(draws), min(ENVELOPE_KEEP, len(draws)), replace=False)
    return draws[np.sort(rows)]


def load_fit_json(path) -> dict:
    """Read ``fit.json`` as a dict (checked schema); ``samples`` as an array."""
    from calib.errors import UserError

    doc = read_json_doc(path, "calib.fit/", "fit", "run `calib fit` first",
                        near={"calib.fit-map/": "is a MAP-only fit (`calib fit --map-only`): a best value "
                              "without its interval, which cannot be judged or exported; run `calib fit` "
                              "without --map-only"})
    env = doc.get("envelope_samples")
    try:
        doc["samples"] = np.asarray(doc.get("samples", []), dtype=float)
        doc["envelope_samples"] = ({k: np.asarray(v, dtype=float) for k, v in env.items()}
                                   if isinstance(env, dict) else {})
    except (TypeError, ValueError) as exc:
        raise UserError(f"{path}: its posterior draws are not a table of numbers ({exc}); "
                        "run `calib fit` again") from None
    return doc
