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


def single_blas() -> None:
    """Run the BLAS library under numpy and scipy (OpenBLAS) on one thread in this process.

    Our linear algebra is small (3x3 poses, L-BFGS-B's vectors, a few hundred normal
    equations); OpenBLAS's extra threads only spin after each call, and on 2 cores they took
    the core the fit's own numba kernels run on: the same MAP fits (6 `calib diagnose`
    candidates on data/examples/gear_slip) took 5.9 s with OpenBLAS's default threads and
    0.97 s with one, L-BFGS-B's own time 1.57 -> ~0 s; a full `calib fit --model pa+thermal`
    30.5 -> 22.6 s (numbers identical). Every entry point calls it (the CLI, `make bench`,
    the test suite, the worker processes of :func:`process_pool`); a script that imports
    the libraries can call it too. threadpoolctl sets it at run time, whatever was loaded
    first (OPENBLAS_NUM_THREADS works only before numpy is imported)."""
    # threadpoolctl limits only the libraries loaded by then: numpy and scipy each bring
    # their own OpenBLAS, scipy's with scipy.linalg (L-BFGS-B's is that one)
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


def _start_worker(initializer, initargs) -> None:
    single_blas()
    if initializer is not None:
        initializer(*initargs)


def process_pool(max_workers: int, initializer=None, initargs=()) -> ProcessPoolExecutor:
    """A ProcessPoolExecutor whose workers are spawned, not forked (see module docstring),
    and run BLAS on one thread (:func:`single_blas`).

    ``initializer`` and the functions submitted must be importable (module level)."""
    return ProcessPoolExecutor(max_workers=max_workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_start_worker, initargs=(initializer, initargs))
