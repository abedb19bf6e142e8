"""`calib wizard`: a guided print -> photo -> fit session, one question at a time."""
from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "wizard", help="guided session: pattern, (send to printer), photo, measure, fit, firmware line",
        description="Asks one question at a time (printer, test, folder), writes the test pattern, "
                    "optionally streams it to the printer over USB serial, measures your photo or "
                    "scan (or a virtual one), fits, diagnoses and prints the firmware line. Answers "
                    "can be piped on stdin, one per line; an empty line takes the default.")
    p.add_argument("--port", default=None,
                   help="serial device of the printer (e.g. /dev/ttyUSB0) to send the G-code to")
    p.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    return p


def run(args) -> int:
    from calib.wizard import run_wizard

    run_wizard(port=args.port, baud=args.baud)
    return 0
