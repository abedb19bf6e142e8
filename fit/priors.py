"""Priors of the fit: one :class:`Prior` per fitted parameter, from the effects' ``Param``
defaults, optionally overridden by a user's priors file (``--priors P.toml``).

Kinds (all truncated to ``[lower, upper]``, outside of which the log density is -inf):

* ``uniform``      p(x) = 1/(upper-lower)
* ``loguniform``   p(x) ~ 1/x  (scale-free: the physically honest choice for time
                   constants and gains whose order of magnitude is unknown, e.g. PA tau
                   from 0.005 s on a direct drive to 2 s on a long Bowden)
* ``normal``       N(mu, sd)   (a previous calibration, a datasheet value)
* ``lognormal``    log x ~ N(log mu, sd)   (sd is the relative spread)

Priors file (TOML), one table per parameter, keys as in ``calib fit --help``::

    ["pa.tau_s"]
    prior = "normal"      # uniform | loguniform | normal | lognormal
    mu = 0.45
    sd = 0.05
    lower = 0.05          # optional: new bounds
    upper = 1.5

An optional top-level ``[priors]`` table may hold the same tables.
"""
from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calib.errors import UserError

KINDS = ("uniform", "loguniform", "normal", "lognormal")
_ALIASES = {"log-uniform": "loguniform", "log_uniform": "loguniform", "jeffreys": "loguniform",
            "flat": "uniform", "gaussian": "normal", "log-normal": "lognormal",
            "log_normal": "lognormal"}


@dataclass(frozen=True)
class Prior:
    """A truncated prior on one scalar parameter (units those of the parameter)."""

    kind: str
    lower: float
    upper: float
    mu: float = math.nan
    sd: float = math.nan

    def __post_init__(self):
        if self.kind not in KINDS:
            raise UserError(f"unknown prior kind {self.kind!r}; use one of {', '.join(KINDS)}")
        if not (self.lower < self.upper):
            raise UserError(f"prior bounds must satisfy lower < upper, got [{self.lower}, {self.upper}]")
        if self.kind == "loguniform" and self.lower <= 0:
            raise UserError(f"a loguniform prior needs lower > 0, got {self.lower}")
        if self.kind in ("normal", "lognormal") and not (self.sd > 0 and math.isfinite(self.mu)):
            raise UserError(f"a {self.kind} prior needs finite mu and sd > 0")
        if self.kind == "lognormal" and self.mu <= 0:
            raise UserError("a lognormal prior needs mu > 0 (its median)")

    @property
    def positive(self) -> bool:
        """True when the support is x > 0 (the optimiser then works in log x)."""
        return self.lower > 0

    def log_prob(self, x) -> np.ndarray:
        """Log density (up to a constant per kind), -inf outside ``[lower, upper]``."""
        x = np.asarray(x, dtype=float)
        inside = (x >= self.lower) & (x <= self.upper)
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.kind == "uniform":
                lp = np.full(x.shape, -math.log(self.upper - self.lower))
            elif self.kind == "loguniform":
                lp = -np.log(x) - math.log(math.log(self.upper / self.lower))
            elif self.kind == "normal":
                lp = -0.5 * ((x - self.mu) / self.sd) ** 2
            else:
                lp = -0.5 * ((np.log(x) - math.log(self.mu)) / self.sd) ** 2 - np.log(x)
        return np.where(inside, lp, -np.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws (rejection from the truncated distribution)."""
        out = np.empty(0)
        while out.size < n:
            m = 4 * n + 16
            if self.kind == "uniform":
                d = rng.uniform(self.lower, self.upper, m)
            elif self.kind == "loguniform":
                d = np.exp(rng.uniform(math.log(self.lower), math.log(self.upper), m))
            elif self.kind == "normal":
                d = rng.normal(self.mu, self.sd, m)
            else:
                d = self.mu * np.exp(rng.normal(0.0, self.sd, m))
            out = np.concatenate([out, d[(d >= self.lower) & (d <= self.upper)]])
        return out[:n]

    def to_json(self) -> dict:
        d = {"kind": self.kind, "lower": self.lower, "upper": self.upper}
        if self.kind in ("normal", "lognormal"):
            d.update(mu=self.mu, sd=self.sd)
        return d


def prior_from_param(param) -> Prior:
    """The default prior of an effect ``Param`` (fields ``lower``, ``upper``, ``prior``).

    ``param.prior`` may be a kind name ("loguniform"), a call-like string
    ("normal(0.5, 0.1)"), a dict ``{"kind":..., "mu":..., "sd":...}``, a :class:`Prior`,
    or empty (uniform within the bounds).
    """
    lo, hi = float(param.lower), float(param.upper)
    spec = getattr(param, "prior", None)
    if isinstance(spec, Prior):
        return spec
    if isinstance(spec, (tuple, list)):
        kind = _kind(spec[0])
        if kind in ("normal", "lognormal"):
            return Prior(kind, lo, hi, float(spec[1]), float(spec[2]))
        return Prior(kind, lo, hi)
    if isinstance(spec, dict):
        return Prior(_kind(spec.get("kind", spec.get("prior", "uniform"))),
                     float(spec.get("lower", lo)), float(spec.get("upper", hi)),
                     float(spec.get("mu", math.nan)), float(spec.get("sd", math.nan)))
    if not spec:
        return Prior("uniform", lo, hi)
    m = re.fullmatch(r"\s*([\w\-]+)\s*(?:\(([^)]*)\))?\s*", str(spec))
    if not m:
        raise ValueError(f"cannot parse prior {spec!r} of parameter {param.name}")
    kind = _kind(m.group(1))
    args = [float(a) for a in m.group(2).split(",")] if m.group(2) else []
    if kind in ("normal", "lognormal") and len(args) == 2:
        return Prior(kind, lo, hi, args[0], args[1])
    if kind in ("normal", "lognormal"):
        # No centre given: centre on the default, spread over the bounds.
        mu = float(getattr(param, "default", 0.5 * (lo + hi)))
        sd = (hi - lo) / 4 if kind == "normal" else 1.0
        return Prior(kind, lo, hi, mu, sd)
    return Prior(kind, lo, hi)


def _kind(name) -> str:
    k = str(name).strip().lower()
    k = _ALIASES.get(k, k)
    if k not in KINDS:
        raise UserError(f"unknown prior kind {name!r}; use one of {', '.join(KINDS)}")
    return k


def load_priors_file(path) -> dict[str, dict]:
    """Read a priors TOML file into ``{param_name: {prior, mu, sd, lower, upper}}``."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"priors file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise UserError(f"priors file {path} is not valid TOML: {exc}") from None
    if isinstance(doc.get("priors"), dict):
        doc = {**{k: v for k, v in doc.items() if k != "priors"}, **doc["priors"]}
    out = {}
    for name, spec in doc.items():
        if not isinstance(spec, dict):
            raise UserError(f"priors file {path}: entry {name!r} must be a table like "
                            f"[\"{name}\"] prior = \"normal\" mu = ... sd = ...")
        unknown = set(spec) - {"prior", "kind", "mu", "sd", "lower", "upper"}
        if unknown:
            raise UserError(f"priors file {path}: entry {name!r} has unknown key(s) "
                            f"{', '.join(sorted(unknown))}; allowed: prior, mu, sd, lower, upper")
        out[name] = spec
    return out


def apply_overrides(priors: dict[str, Prior], overrides: dict[str, dict]) -> dict[str, Prior]:
    """Return ``priors`` with the user's ``overrides`` (from :func:`load_priors_file`) applied.

    Unknown parameter names are a UserError listing the fitted names.
    """
    out = dict(priors)
    for name, spec in overrides.items():
        if name not in out:
            raise UserError(f"priors file names parameter {name!r}, which this model does not have; "
                            f"fitted parameters: {', '.join(out)}")
        base = out[name]
        kind = _kind(spec.get("prior", spec.get("kind", base.kind)))
        try:
            out[name] = replace(base, kind=kind, lower=float(spec.get("lower", base.lower)),
                                upper=float(spec.get("upper", base.upper)),
                                mu=float(spec.get("mu", base.mu)), sd=float(spec.get("sd", base.sd)))
        except (TypeError, ValueError) as exc:
            raise UserError(f"priors file: bad value for {name!r}: {exc}") from None
    return out
