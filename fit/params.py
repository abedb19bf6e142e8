"""Named model parameters with units, physical bounds and a default prior.

Every effect in :mod:`fit.effects` declares its parameters as :class:`Param` objects.
The fitter samples the free ones; fixed ones keep their value. The prior is always
truncated to ``[lower, upper]`` (log density -inf outside):

* ``"uniform"``          p(x) = 1 / (upper - lower)
* ``"loguniform"``       p(x) = 1 / (x * ln(upper / lower))   (needs lower > 0)
* ``("normal", mu, sd)`` N(mu, sd) truncated to the bounds (normalised on [lower, upper])

Bounds are chosen so that "effect absent" (an amplitude of 0, a gain of 1) lies inside
the prior: compare/diagnose can then add any effect to any model and fit it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from calib.errors import UserError


@dataclass(frozen=True)
class Param:
    """One scalar parameter.

    name     local name inside its effect (``tau_s``); the model prefixes the effect
             name (``pa.tau_s``)
    unit     unit text (``s``, ``mm``, ``mm/s``, ``1`` for dimensionless)
    default  value used when none is given (truth files, fixed parameters, start point)
    lower, upper   hard physical bounds
    prior    ``"uniform"``, ``"loguniform"`` or ``("normal", mu, sd)``
    fixed    not sampled by the fitter (value = default unless overridden)
    doc      one line: what it is, physically
    """

    name: str
    unit: str
    default: float
    lower: float
    upper: float
    prior: object = "uniform"
    fixed: bool = False
    doc: str = ""

    def __post_init__(self):
        if not (self.lower <= self.upper):
            raise ValueError(f"param {self.name}: lower {self.lower} > upper {self.upper}")
        kind = self.prior_kind
        if kind == "loguniform" and not self.lower > 0:
            raise ValueError(f"param {self.name}: loguniform prior needs lower > 0")
        if kind == "normal":
            _, mu, sd = self.prior
            if not sd > 0:
                raise ValueError(f"param {self.name}: normal prior needs sd > 0")
        elif kind not in ("uniform", "loguniform"):
            raise ValueError(f"param {self.name}: unknown prior {self.prior!r}")

    @property
    def prior_kind(self) -> str:
        if isinstance(self.prior, (tuple, list)):
            return str(self.prior[0])
        return str(self.prior)

    def with_default(self, value: float, fixed: bool | None = None) -> "Param":
        """A copy with a new default (and optionally a new fixed flag)."""
        return replace(self, default=float(value), fixed=self.fixed if fixed is None else fixed)

    def prefixed(self, effect_name: str) -> "Param":
        return replace(self, name=f"{effect_name}.{self.name}")

    def log_prior(self, x) -> np.ndarray:
        """Log prior density at ``x`` (any shape, vectorised); -inf outside the bounds."""
        x = np.asarray(x, dtype=float)
        inside = (x >= self.lower) & (x <= self.upper) & np.isfinite(x)
        kind = self.prior_kind
        if kind == "uniform":
            width = self.upper - self.lower
            val = np.full(x.shape, -math.log(width) if width > 0 else 0.0)
        elif kind == "loguniform":
            norm = math.log(self.upper / self.lower) if self.upper > self.lower else 1.0
            with np.errstate(divide="ignore", invalid="ignore"):
                val = -np.log(np.where(inside, x, 1.0)) - math.log(norm)
        else:
            _, mu, sd = self.prior
            mu, sd = float(mu), float(sd)
            # Truncation mass, so the density integrates to 1 on [lower, upper].
            z = lambda v: 0.5 * (1.0 + math.erf((v - mu) / (sd * math.sqrt(2.0))))
            mass = max(z(self.upper) - z(self.lower), 1e-300)
            val = (-0.5 * ((x - mu) / sd) ** 2 - math.log(sd * math.sqrt(2 * math.pi))
                   - math.log(mass))
        return np.where(inside, val, -np.inf)

    def check_value(self, value: float, where: str = "") -> float:
        """``value`` as float, or UserError if outside the bounds."""
        v = float(value)
        if not (self.lower <= v <= self.upper):
            raise UserError(f"{where}{self.name} = {v:g} {self.unit} is outside its bounds "
                            f"[{self.lower:g}, {self.upper:g}]")
        return v
