"""Progress that reads well in a terminal and in a log.

On a terminal: a tqdm bar on stderr. Anywhere else (CI, ``2> log.txt``, a pipe): one line
when the work ends, so a log holds one line per task instead of every refresh of the bar,
and for long work one line at most every HEARTBEAT_S while it runs (after the item that
crosses it), so a log shows how far a 50-minute `calib diagnose` or `--model auto` has got.
"""
from __future__ import annotations

import sys
import time

from tqdm import tqdm

#: Seconds between the running lines OneLine writes (none for work that ends sooner).
HEARTBEAT_S = 60.0


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):      # closed or replaced streams (pytest capture)
        return False


def progress(iterable=None, *, total=None, desc: str = "", unit: str = "it",
             disable: bool = False, leave: bool = True, file=None):
    """A tqdm-like bar: ``update(n)``, ``set_postfix(**kw)``, ``close()``, a context
    manager and, given ``iterable``, an iterator over it."""
    stream = file if file is not None else sys.stderr
    if disable:
        return tqdm(iterable, total=total, disable=True)
    if _is_terminal(stream):
        return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, file=stream,
                    mininterval=0.5)
    return OneLine(iterable, total=total, desc=desc, unit=unit, file=stream)


class OneLine:
    """Counts like a tqdm bar and writes one line on close: ``desc: n/total unit in T s (k=v)``,
    and, while it runs, ``desc: n/total unit, T s so far`` after an update at least
    ``heartbeat_s`` after the last line."""

    def __init__(self, iterable=None, *, total=None, desc="", unit="it", file=None,
                 heartbeat_s: float = HEARTBEAT_S):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.desc, self.unit = total, desc, unit
        self.file = file if file is not None else sys.stderr
        self.n = 0
        self.postfix: dict = {}
        self.t0 = time.perf_counter()
        self.last = self.t0
        self.heartbeat_s = heartbeat_s
        self.closed = False

    def __iter__(self):
        try:
            for x in self.iterable:
                yield x
                self.update(1)
        finally:
            self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if now - self.last >= self.heartbeat_s and not self.closed:
            self.last = now
            of = f"/{self.total}" if self.total is not None else ""
            self._write(f"{self.desc}: {self.n}{of} {self.unit}, {now - self.t0:.0f} s so far")

    def _write(self, line: str) -> None:
        try:
            print(line, file=self.file, flush=True)
        except (OSError, ValueError):
            pass

    def set_postfix(self, ordered_dict=None, refresh=True, **kw) -> None:
        self.postfix = dict(ordered_dict or {}, **kw)

    def set_description(self, desc: str, refresh=True) -> None:
        self.desc = desc

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        of = f"/{self.total}" if self.total is not None else ""
        extra = ", ".join(f"{k}={v}" for k, v in self.postfix.items())
        self._write(f"{self.desc}: {self.n}{of} {self.unit} in {time.perf_counter() - self.t0:.1f} s"
                    + (f" ({extra})" if extra else ""))
