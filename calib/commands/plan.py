"""`calib plan OTHER.gcode --printer P.toml -o OTHER.manifest.json`: a manifest for any G-code."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from calib.commands.pattern import write_error
from calib.argtypes import number, positive
from calib.errors import UserError
from patterns.manifest import manifest_path_for, timeline_path_for


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "plan",
        help="build a manifest (tracks, widths, planned timeline) from any G-code",
        description="Parse G-code (ours or a slicer's / third party's), plan its motion with the "
                    "printer's firmware model (trapezoids, look-ahead, junction speeds) and write "
                    "NAME.manifest.json plus the sampled timeline NAME.timeline.npz, so the print "
                    "can be measured and fitted. Unlabelled G-code: every run of extruding moves "
                    "at one height becomes a track.")
    p.add_argument("gcode", help="G-code file to plan")
    p.add_argument("--printer", required=True,
                   help="printer profile: a .toml path or a shipped name (e.g. adventurer3, "
                        "long_bowden, direct_drive, ender3)")
    p.add_argument("-o", "--output", default=None,
                   help="manifest path (default: GCODE name with .manifest.json)")
    p.add_argument("--layer-height-mm", type=positive, default=None,
                   help="bead height (mm) for every track; default: from the z levels")
    p.add_argument("--min-test-length-mm", type=number(0.0), default=3.0,
                   help="unlabelled extrusion runs shorter than this (mm) are kind 'other' "
                        "(default 3.0)")
    p.add_argument("--tracks", metavar="IDS",
                   help="the test tracks by id, e.g. 3-8,12 (ids as in the preview); the rest "
                        "are 'other'. Default: every extruding run, minus the prime line, closed "
                        "loops (skirts, rings), label strokes and ruler/dial ticks when they can be "
                        "recognised")
    p.add_argument("--tracks-comment", metavar="REGEX",
                   help="the test tracks are those whose G-code comments match REGEX (case-insensitive; the "
                        "comment line before the track and those on its lines, e.g. 'TYPE:External perimeter' "
                        "or 'line [0-9]+'); combines with --tracks and --z-range-mm")
    p.add_argument("--z-range-mm", metavar="LO,HI",
                   help="only tracks printed at a z in [LO, HI] mm are test tracks")
    p.add_argument("--keep-all", action="store_true",
                   help="do not exclude the recognised prime line, closed loops, label strokes and ticks")
    return p


def run(args) -> int:
    from patterns.plan import manifest_from_gcode
    from patterns.profile import load_profile

    src = Path(args.gcode)
    if not src.is_file():
        raise UserError(f"G-code file {src} does not exist")
    if args.layer_height_mm is not None and not args.layer_height_mm > 0:
        raise UserError(f"--layer-height-mm must be > 0, got {args.layer_height_mm}")
    profile = load_profile(args.printer)
    try:
        data = src.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {src}: {exc}") from None
    man = manifest_from_gcode(data, profile, {"name": "gcode", "source": src.name},
                              layer_height_mm=args.layer_height_mm,
                              min_test_length_mm=args.min_test_length_mm)
    man.gcode = src.name
    from patterns.plan import parse_id_ranges, select_tracks

    zr = None
    if args.z_range_mm:
        try:
            lo, hi = (float(v) for v in args.z_range_mm.split(","))
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError
        except ValueError:
            raise UserError(f"--z-range-mm takes LO,HI in mm, not {args.z_range_mm!r}") from None
        zr = (min(lo, hi), max(lo, hi))
    ids = parse_id_ranges(args.tracks) if args.tracks else None
    if args.tracks_comment:
        from patterns.plan import tracks_matching_comment

        hit = tracks_matching_comment(man, data.decode("utf-8", errors="replace"), args.tracks_comment)
        if not hit:
            raise UserError(f"--tracks-comment {args.tracks_comment!r} matches no track's G-code comments")
        ids = hit if ids is None else ids & hit
    notes = select_tracks(man, ids, zr, auto_exclude=not (args.keep_all or man.pattern.get("labelled")))
    if not man.test_tracks():
        # a manifest without a test track can be neither measured nor fitted: say so now,
        # not two commands later
        chosen = [f for f, v in (("--tracks", args.tracks), ("--tracks-comment", args.tracks_comment),
                                 ("--z-range-mm", args.z_range_mm)) if v]
        why = (f"{' with '.join(chosen)} select{'s' if len(chosen) == 1 else ''} none of its "
               f"{len(man.tracks)} tracks" if chosen else
               f"each of its {len(man.tracks)} tracks was taken for a prime line, label, tick or loop"
               if man.tracks else "it extrudes no track")
        tail = next((n for n in notes if n.startswith("--tracks names")), None)
        raise UserError(f"no test track in {src.name}: {why}" + (f"; {tail}" if tail else "")
                        + "; `calib preview` shows the track ids, --keep-all keeps every track")
    man.pattern.setdefault("warnings", []).extend(notes)
    out = Path(args.output) if args.output else manifest_path_for(src)
    try:
        if out.is_dir():
            raise IsADirectoryError(21, "Is a directory", str(out))
        man.save(out)
    except OSError as exc:
        for f in (timeline_path_for(out), out):     # no timeline without its manifest
            try:
                if f.is_file():
                    f.unlink()
            except OSError:
                pass
        raise write_error(out, exc) from None
    for w in man.pattern.get("warnings", []):
        print(f"calib plan: warning: {w}", file=sys.stderr)
    n_test = len(man.test_tracks())
    print(f"{out}: {len(man.tracks)} tracks ({n_test} test), "
          f"{man.pattern['planned_duration_s']:.1f} s planned; timeline {timeline_path_for(out)}")
    return 0
