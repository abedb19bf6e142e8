"""`make bench`: run every bench/bench_*.py and print one table of measured vs target.

Each module exposes ``run() -> list[Row]``. Speed and accuracy targets live here, not in
timed tests. A bench that raises is reported as a CRASHED row and the whole run exits 1
after the table (the other benches still run, so their figures are not lost).
"""
from __future__ import annotations

import importlib
import pkgutil
import sys
import time
import traceback

import bench
from bench.common import Row, print_table


def main(argv=None) -> int:
    from calib.parallel import single_blas

    single_blas()       # as the CLI runs: BLAS on one thread (calib/parallel.py)
    argv = sys.argv[1:] if argv is None else argv
    names = sorted(m.name for m in pkgutil.iter_modules(bench.__path__) if m.name.startswith("bench_"))
    if argv:
        names = [n for n in names if any(a in n for a in argv)]
    rows: list[Row] = []
    crashed: list[str] = []
    for name in names:
        t0 = time.perf_counter()
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        try:
            rows.extend(importlib.import_module(f"bench.{name}").run())
        except BaseException as exc:  # a broken bench must not hide the others' figures
            if isinstance(exc, KeyboardInterrupt):
                raise
            traceback.print_exc()
            crashed.append(name)
            rows.append(Row(name, "CRASHED (rows not measured)", float("nan"), "", "", False))
        print(f"[bench] {name} done in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    print_table(rows)
    if crashed:
        # a crashed bench is a failure of `make bench`, not a row to skim past
        print(f"[bench] FAILED: {', '.join(crashed)} crashed; see the tracebacks above",
              file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
