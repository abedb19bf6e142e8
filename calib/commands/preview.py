"""`calib preview OUT.gcode -o OUT.png`: top view coloured by commanded flow."""
from __future__ import annotations

import argparse
from pathlib import Path

from calib.commands.pattern import write_error
from calib.argtypes import integer
from calib.errors import UserError


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "preview", help="draw the top view of a G-code / pattern coloured by commanded flow",
        description="Draw a pattern's top view as PNG: every track coloured by its commanded "
                    "volumetric flow (mm^3/s, colour bar), coasting moves dotted red, fiducials "
                    "with their ids, label boxes and the bed outline. Uses OUT.manifest.json next "
                    "to the G-code; without one, plans the G-code with --printer.")
    p.add_argument("gcode", help="G-code file (its NAME.manifest.json is used when present)")
    p.add_argument("-o", "--output", default=None, help="PNG path (default: GCODE name with .png)")
    p.add_argument("--printer", default=None,
                   help="printer profile (.toml path or shipped name); needed when there is no "
                        "manifest next to the G-code, and draws the bed outline")
    p.add_argument("--dpi", type=integer(1), default=150, help="PNG resolution (default 150)")
    return p


def run(args) -> int:
    from calib.fileio import atomic_write_bytes
    from patterns.manifest import Manifest, manifest_path_for
    from patterns.preview import render_preview
    from patterns.profile import load_profile

    src = Path(args.gcode)
    if not src.is_file():
        raise UserError(f"G-code {src} does not exist")
    mpath = manifest_path_for(src)
    profile = load_profile(args.printer) if args.printer else None
    if mpath.is_file():
        manifest = Manifest.load(mpath)
        if profile is None and manifest.printer.get("name"):
            try:
                profile = load_profile(manifest.printer["name"])
            except UserError:
                profile = None
    elif profile is not None:
        from patterns.plan import manifest_from_gcode
        manifest = manifest_from_gcode(src.read_text(errors="replace"), profile)
    else:
        raise UserError(f"no manifest {mpath.name} next to {src.name}: pass --printer to plan the G-code")
    out = Path(args.output) if args.output else src.with_suffix(".png")
    if not 10 <= args.dpi <= 1200:
        raise UserError(f"--dpi must be between 10 and 1200, got {args.dpi}")
    png = render_preview(manifest, profile, dpi=args.dpi)
    try:
        if out.is_dir():
            raise IsADirectoryError(21, "Is a directory", str(out))
        atomic_write_bytes(out, png)
    except OSError as exc:
        raise write_error(out, exc) from None
    print(f"wrote {out}")
    return 0
