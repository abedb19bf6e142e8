"""Shared bench helpers: a row type, a timer and the table printer."""
from __future__ import annotations

import time
from dataclasses import dataclass


@dataclass
class Row:
    area: str        # e.g. "planner", "physics", "measure", "fit", "diagnose"
    metric: str      # what was measured, with its conditions
    value: float     # the measured figure
    unit: str        # unit of value
    target: str      # the target as text, e.g. "<= 5"
    passed: bool | None  # None where there is no target


def best_time_s(fn, repeat: int = 5, number: int = 1) -> float:
    """Best wall time (s) of ``number`` calls of ``fn`` over ``repeat`` tries."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def print_table(rows: list[Row]) -> None:
    headers = ("area", "metric", "value", "unit", "target", "ok")
    cells = [(r.area, r.metric, _fmt(r.value), r.unit, r.target,
              "-" if r.passed is None else ("yes" if r.passed else "NO")) for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) if cells else len(h) for i, h in enumerate(headers)]
    line = "  ".join(h.ljust(w) for h, w in zip(headers, widths))
    print(line)
    print("-" * len(line))
    for c in cells:
        print("  ".join(x.ljust(w) for x, w in zip(c, widths)))


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if v != v:  # NaN
        return "nan"
    if v == 0 or 1e-3 <= abs(v) < 1e5:
        return f"{v:.4g}"
    return f"{v:.3e}"
