"""TRUTH.toml: the effects and values of a virtual printer (``calib simulate --truth``).

    [model]
    effects = ["pa", "thermal", "backpressure"]

    [values]
    "pa.tau_s" = 0.8
    "thermal.a" = 0.05

Any other top-level table (e.g. ``[render]``, ``[notes]``) is returned as ``extras``
for the tools that use it. Values are checked against the effects' bounds.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from calib.errors import UserError
from fit.model import build_model


def load_truth(path, profile=None, extra_effects=()) -> tuple[str, dict, dict]:
    """Read a truth file -> (model_spec "pa+thermal", values {"pa.tau_s": 0.8}, extras)."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"truth file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read truth file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"truth file {path} is not valid TOML: {exc}") from None
    model = doc.get("model")
    effects = model.get("effects") if isinstance(model, dict) else None
    if not (isinstance(effects, list) and effects and all(isinstance(e, str) for e in effects)):
        raise UserError(f"truth file {path} needs [model] effects = [\"pa\", ...] (a list of effect names)")
    spec = "+".join(e.strip() for e in effects)
    values = doc.get("values", {})
    if not isinstance(values, dict):
        raise UserError(f"truth file {path}: [values] must be a table of \"effect.param\" = number")
    bad = [k for k, v in values.items() if isinstance(v, bool) or not isinstance(v, (int, float))]
    if bad:
        raise UserError(f"truth file {path}: value(s) {', '.join(bad)} are not numbers")
    values = {str(k): float(v) for k, v in values.items()}
    try:
        build_model(spec, profile, extra_effects).with_values(values)
    except UserError as exc:
        raise UserError(f"truth file {path}: {exc}") from None
    extras = {k: v for k, v in doc.items() if k not in ("model", "values")}
    return spec, values, extras
