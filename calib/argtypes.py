"""argparse types for numbers that must be finite and within a range: a bad value is
argparse's one usage line (exit 2), never a NaN that reaches the generators (``--speeds
nan`` was a ValueError traceback deep in the pattern builder) or a negative seed numpy
refuses with a traceback."""
from __future__ import annotations

import argparse
import math


def _check(v: float, text: str, lo, hi, lo_open: bool) -> None:
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise argparse.ArgumentTypeError(f"expected a number {'>' if lo_open else '>='} {lo:g}, got {text!r}")
    if hi is not None and v > hi:
        raise argparse.ArgumentTypeError(f"expected a number <= {hi:g}, got {text!r}")


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False):
    """A finite float in [lo, hi] ((lo, hi] with ``lo_open``)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        _check(v, text, lo, hi, lo_open)
        return v
    return parse


def positive(text: str) -> float:
    """A finite float > 0."""
    return number(0.0, lo_open=True)(text)


def integer(lo: int | None = None, hi: int | None = None):
    """An int in [lo, hi]."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f">= {lo}" if hi is None else f"{lo}-{hi}" if lo is not None else f"<= {hi}"
            raise argparse.ArgumentTypeError(f"expected a whole number {rng}, got {text!r}")
        return v
    return parse


#: a random seed: numpy takes only non-negative integers
seed = integer(0)


def numbers(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False):
    """Comma-separated finite floats, each in [lo, hi] ((lo, hi] with ``lo_open``); at least one."""
    def parse(text: str) -> list[float]:
        try:
            vals = [float(v) for v in str(text).split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
        if not vals:
            raise argparse.ArgumentTypeError("expected at least one number")
        for v in vals:
            _check(v, text, lo, hi, lo_open)
        return vals
    return parse
