"""`calib batch DIR`: fit every scan in a folder, in parallel, and write a summary table.

A scan is ``NAME.csv`` (widths) with ``NAME.manifest.json`` beside it (or the folder's
only manifest). Each fit writes ``NAME.fit.json``; the summary (CSV and printed) has one
row per scan. ``--scheduler ADDRESS`` sends the fits to a Dask cluster (print farms);
otherwise ``--jobs N`` local processes. Exit code 3 if any fit did not converge.
"""
from __future__ import annotations

import csv
import io
import os
import sys
from concurrent.futures import as_completed
from pathlib import Path

from calib.argtypes import integer, seed
from calib.errors import UserError
from calib.fileio import atomic_write_text
from calib.parallel import process_pool
from calib.progress import progress as progress_bar


def add_parser(sub):
    p = sub.add_parser(
        "batch", help="fit every scan in a folder (parallel, optional Dask cluster)",
        description="Fit each NAME.csv with its NAME.manifest.json in DIR independently, in "
                    "parallel processes or on a Dask cluster (--scheduler), write NAME.fit.json "
                    "per scan and a summary CSV. Exit code 3 if any fit did not converge.")
    p.add_argument("dir", help="folder with widths CSVs and manifests")
    p.add_argument("--model", default="pa", help="effects joined by '+' (default pa)")
    p.add_argument("--priors", help="priors TOML for every fit")
    p.add_argument("--jobs", type=integer(1), default=2, help="local worker processes (default 2)")
    p.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786)")
    p.add_argument("--max-steps", type=integer(1), default=20000, help="MCMC step cap per fit")
    p.add_argument("--seed", type=seed, default=0, help="random seed")
    p.add_argument("-o", "--out", help="summary CSV (default DIR/batch_summary.csv)")
    return p


def find_scans(folder) -> list[tuple[str, str, str]]:
    """(name, widths csv, manifest) of every scan in ``folder``."""
    d = Path(folder)
    if not d.is_dir():
        raise UserError(f"{d} is not a folder")
    manifests = sorted(d.glob("*.manifest.json"))
    out = []
    for w in sorted(d.glob("*.csv")):
        if w.name.startswith("batch_summary"):
            continue
        m = d / f"{w.stem}.manifest.json"
        if not m.exists():
            if len(manifests) != 1:
                continue
            m = manifests[0]
        out.append((w.stem, str(w), str(m)))
    if not out:
        raise UserError(f"no scans in {d}: expected NAME.csv with NAME.manifest.json")
    return out


def fit_one(name, widths, manifest, model, priors=None, max_steps=20000, seed=0) -> dict:
    """Fit one scan, write NAME.fit.json next to it, return its summary row."""
    from calib.commands.fit import run_fit
    from calib.parallel import single_blas

    single_blas()       # a Dask worker is no process of ours: BLAS on one thread there too
    row = {"scan": name, "model": model}
    try:
        res, _ = run_fit([(widths, manifest)], model, priors=priors, max_steps=max_steps,
                         seed=seed, progress=False)
    except UserError as exc:
        return {**row, "converged": False, "trustworthy": False, "error": str(exc)}
    out = Path(widths).with_name(f"{name}.fit.json")
    res.save(out)
    row.update(converged=res.converged, trustworthy=bool(res.trust.get("trustworthy")),
               problems="; ".join(res.trust.get("problems", [])),
               rms_um=round(res.map.rms_mm * 1000, 2),
               chi2_nu=round(res.map.chi2_nu, 3), n_steps=res.diagnostics["n_steps"],
               fit_json=str(out), error="")
    for n, p in res.params.items():
        row[f"{n}"] = p.median
        row[f"{n}_lo95"] = p.ci95[0]
        row[f"{n}_hi95"] = p.ci95[1]
    return row


def _worker_threads(n: int) -> None:
    from fit.kernels import set_threads

    set_threads(n)


def run_batch(folder, model="pa", priors=None, jobs=2, scheduler=None, max_steps=20000,
              seed=0, progress=True) -> list[dict]:
    scans = find_scans(folder)
    rows = []
    bar = progress_bar(total=len(scans), desc="batch", unit="scan", disable=not progress)
    if scheduler:
        try:
            from dask.distributed import Client, as_completed as dask_completed
        except ImportError:
            raise UserError("--scheduler needs dask[distributed] installed") from None
        try:
            client = Client(scheduler, timeout="10s") if isinstance(scheduler, str) else Client(scheduler)
        except (OSError, TimeoutError) as exc:
            raise UserError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from None
        try:
            futs = [client.submit(fit_one, n, w, m, model, priors, max_steps, seed, pure=False)
                    for n, w, m in scans]
            for f in dask_completed(futs):
                rows.append(f.result())
                bar.update(1)
        finally:
            client.close()
    elif jobs <= 1:
        for n, w, m in scans:
            rows.append(fit_one(n, w, m, model, priors, max_steps, seed))
            bar.update(1)
    else:
        threads = max(1, (os.cpu_count() or 1) // jobs)
        with process_pool(jobs, initializer=_worker_threads, initargs=(threads,)) as ex:
            futs = [ex.submit(fit_one, n, w, m, model, priors, max_steps, seed) for n, w, m in scans]
            for f in as_completed(futs):
                rows.append(f.result())
                bar.update(1)
    bar.close()
    return sorted(rows, key=lambda r: r["scan"])


def summary_csv(rows) -> str:
    cols = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    w = csv.DictWriter(buf, cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


def run(args) -> int:
    rows = run_batch(args.dir, args.model, args.priors, args.jobs, args.scheduler,
                     args.max_steps, args.seed)
    out = Path(args.out) if args.out else Path(args.dir) / "batch_summary.csv"
    atomic_write_text(out, summary_csv(rows))
    for r in rows:
        pa = r.get("pa.tau_s")
        txt = (f"tau {pa:.4f} s [{r['pa.tau_s_lo95']:.4f}, {r['pa.tau_s_hi95']:.4f}]"
               if pa is not None else r.get("error", ""))
        state = ("ok" if r.get("trustworthy") else "NOT TRUSTWORTHY") if r.get("converged") \
            else "NOT CONVERGED"
        print(f"{r['scan']:24s} {state:15s} {txt}")
        if r.get("converged") and not r.get("trustworthy"):
            print(f"{'':24s} {r.get('problems', '')}", file=sys.stderr)
    print(f"wrote {out}")
    return 0 if all(r.get("converged") for r in rows) else 3
