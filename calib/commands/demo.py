"""`calib demo`: the whole print -> scan -> measure -> fit -> diagnose loop on the virtual printer."""
from __future__ import annotations

import argparse

from calib.argtypes import integer, seed


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="run the whole loop on the built-in virtual printer",
        description="Generate a spiral step test, print it on the virtual printer (whose extruder "
                    "hides effects the base model lacks), scan it, measure it, fit the base model, "
                    "diagnose what is missing, fit the extended model and show the error falling, "
                    "then export the firmware value and write an HTML report.")
    p.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    p.add_argument("--printer", default="adventurer3", help="printer profile name or TOML path")
    p.add_argument("--truth", default=None,
                   help="TRUTH.toml of the virtual printer (default: data/truths/bowden.toml)")
    p.add_argument("--camera", choices=("flatbed", "phone"), default="flatbed",
                   help="synthetic flatbed scan (600 dpi) or 12 MP phone photo")
    p.add_argument("--model", default=None,
                   help="base model to start from (default: where `calib fit --model auto` starts: "
                        "pa, or pa+scan_bias on apparent widths such as a phone's)")
    p.add_argument("--rounds", type=integer(0), default=2, help="diagnose/extend rounds (default: 2)")
    p.add_argument("--seed", type=seed, default=1, help="random seed")
    return p


def run(args) -> int:
    from calib.demo import run_demo

    run_demo(args.out, printer=args.printer, truth=args.truth, camera=args.camera,
             base_model=args.model, seed=args.seed, rounds=args.rounds)
    return 0
