"""Worker processes that are safe to start after numba has run.

numba's parallel kernels start a threading layer (GNU OpenMP, TBB or its own workqueue);
a process that forks after that inherits a half-copied thread pool, and GNU OpenMP aborts
the child ("fork() called from a process already using GNU OpenMP, this is unsafe").
Every process pool of the project therefore starts its workers with ``spawn``: a fresh
interpreter per worker, the same on Linux, macOS and Windows.
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor


def process_pool(max_workers: int, initializer=None, initargs=()) -> ProcessPoolExecutor:
    """A ProcessPoolExecutor whose workers are spawned, not forked (see module docstring).

    ``initializer`` and the functions submitted must be importable (module level)."""
    return ProcessPoolExecutor(max_workers=max_workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=initializer, initargs=initargs)
