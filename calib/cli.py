"""`calib`: the command line. A thin layer: every verb lives in calib/commands/<verb>.py
with ``add_parser(subparsers)`` and ``run(args) -> int``; the real work is in the
libraries (patterns, measure, fit).

Errors from bad input are :class:`calib.errors.UserError`: one line on stderr, exit 2.
"""
from __future__ import annotations

import argparse
import importlib
import re
import sys

from calib import __version__
from calib.errors import UserError

#: Verbs in the order `calib --help` lists them.
VERBS = ("pattern", "plan", "preview", "simulate", "measure", "fit", "batch", "compare",
         "diagnose", "report", "export", "wizard", "demo")


class _OneLineErrors(argparse.ArgumentParser):
    """argparse prints its usage block on a bad option; we print one line and exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineErrors(
        prog="calib",
        description="Calibrate extruder dynamics: print a test pattern, scan it, fit the physics.",
        epilog="Run `calib VERB --help` for the options of each verb.")
    parser.add_argument("--version", action="version", version=f"calib {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for verb in VERBS:
        try:
            mod = importlib.import_module(f"calib.commands.{verb}")
        except ModuleNotFoundError as exc:
            if exc.name == f"calib.commands.{verb}":
                continue  # verb not built yet
            raise
        p = mod.add_parser(sub)
        p.set_defaults(_run=mod.run)
    return parser




def _glue_negative_values(argv: list[str]) -> list[str]:
    """``--opt -70,0=...`` -> ``--opt=-70,0=...``. argparse takes a token that starts with
    '-' for an option unless it is a plain number, so point hints on a centre-origin bed
    ("-70,0=704,1478;...") were refused; no option of ours starts with '-' and a digit."""
    out: list[str] = []
    for a in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and re.match(r"-\.?\d", a):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def main(argv=None) -> int:
    parser = build_parser()
    argv = _glue_negative_values(list(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    from calib.parallel import single_blas

    single_blas()       # MAP fits 3-6x faster on 2 cores (calib/parallel.py)
    try:
        return int(args._run(args) or 0)
    except UserError as exc:
        print(f"calib {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"calib {args.verb}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
