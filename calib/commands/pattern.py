"""`calib pattern NAME --printer P -o OUT.gcode`: write a test pattern and its manifest."""
from __future__ import annotations

import argparse
from pathlib import Path

from calib.argtypes import integer, number, numbers, positive
from calib.errors import UserError

_pos = numbers(0.0, lo_open=True)      # speeds, times, widths: > 0, finite


def _ints(text: str) -> list[int]:
    return [int(v) for v in numbers()(text)]


_COMMON = dict(help="printer profile: a .toml path or a shipped name (adventurer3, long_bowden, "
                    "direct_drive, ender3)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "pattern", help="write a calibration test pattern (G-code + manifest)",
        description="Write calibration G-code and, next to it, OUT.manifest.json and "
                    "OUT.timeline.npz (tracks, fiducials, labels, planned timeline) for the "
                    "measure and fit steps. Every pattern is one layer with four ArUco "
                    "fiducials, a 1 mm ruler, labels and a prime line.")
    sub = p.add_subparsers(dest="pattern", metavar="PATTERN", required=True)

    def common(sp):
        sp.add_argument("--printer", required=True, **_COMMON)
        sp.add_argument("-o", "--output", required=True, help="G-code path to write (OUT.gcode)")

    sp = sub.add_parser("spiral-step", help="Archimedean spirals, constant speed, stepped width (seed 004)",
                        description="Spirals at constant head speed whose commanded width steps between "
                                    "levels every --step-s seconds, not synchronised with the angle "
                                    "(Duet3D, seed 004). One spiral per speed x step duration.")
    common(sp)
    sp.add_argument("--speeds", type=_pos, default=[15.0, 30.0], help="head speeds, mm/s (default 15,30)")
    sp.add_argument("--step-s", type=_pos, default=[6.0], help="step durations, s (default 6)")
    sp.add_argument("--steps", type=integer(1), default=8, help="width levels per spiral (default 8)")
    sp.add_argument("--widths", type=_pos, default=[0.35, 0.8], help="width levels, mm (default 0.35,0.8)")
    sp.add_argument("--layer-height", type=positive, default=0.2, help="layer height, mm (default 0.2)")

    sp = sub.add_parser("stop-mid-path", help="extrusion stops mid-line, head coasts (seed 000)",
                        description="Straight lines whose extrusion stops mid-path while the head keeps "
                                    "moving: exponential feed ramp v0 exp(-t/tau), constant feed, and the "
                                    "KISSlicer wizard variant (stop, wiper, wait 3 s, retract).")
    common(sp)
    sp.add_argument("--speeds", type=_pos, default=[20.0, 40.0], help="head speeds v0, mm/s (default 20,40)")
    sp.add_argument("--tau", type=_pos, default=None,
                    help="tau guesses for the feed ramp, s (default: seed-000 estimate x 0.5,1,2)")
    sp.add_argument("--variants", default="exp,const,wizard", help="any of exp,const,wizard (default all)")
    sp.add_argument("--steady-s", type=positive, default=None, help="printing time before the stop, s")
    sp.add_argument("--wizard-wait-s", type=number(0.0), default=3.0,
                    help="wizard variant: wait after the wipe, s (default 3); the printer's display "
                         "says where to hold the wiper card (M117)")
    sp.add_argument("--width", type=_pos, default=None,
                    help="bead width, mm; several alternate over the lines (default 1.2 and 2 x "
                         "nozzle: the bead's back-pressure needs two widths)")
    sp.add_argument("--layer-height", type=positive, default=0.2, help="layer height, mm (default 0.2)")

    sp = sub.add_parser("retract", help="steady lines then a moving retraction (seed 001 RetractTest)",
                        description="Seed-001 RetractTest designs: prime/drain/restore, a steady line, then "
                                    "a 4 mm retraction while moving 40 mm at 10 mm/s; the smear length "
                                    "measures the pressure.")
    common(sp)
    sp.add_argument("--designs", type=_ints, default=[1, 2, 3, 4], help="seed-001 designs 1..4 (default all)")
    sp.add_argument("--steps", type=integer(1), default=6, help="lines per design (default 6)")
    sp.add_argument("--draw-mm", type=positive, default=40.0, help="steady line length, mm (default 40)")
    sp.add_argument("--restore-mm", type=number(0.0), default=None,
                    help="restore Re before the line, mm of filament (default: seed 001's 1 mm on the "
                         "Adventurer 3, scaled by the profile's Bowden length: 0.1 mm on a direct drive)")

    sp = sub.add_parser("start-stop", help="restore/retract sweep on concentric arcs (seed 001 StartStopTest)",
                        description="Seed-001 spiral StartStopTest: prime, drain, restore Re, draw, retract, "
                                    "drool check, restore, cooldown; sweeps Re within a ring group and w "
                                    "between groups.")
    common(sp)
    sp.add_argument("--re-mm", type=numbers(0.0), default=None,
                    help="restore distances, mm of filament (default: seed 001's 2-4 mm on the Adventurer 3, "
                         "scaled by the profile's Bowden length: 0.2-0.4 mm on a direct drive)")
    sp.add_argument("--widths", type=_pos, default=[0.3, 0.4, 0.8, 1.6], help="bead widths, mm")
    sp.add_argument("--ve", type=positive, default=1.0, help="extruder velocity while drawing, mm/s (default 1)")
    sp.add_argument("--layer-height", type=positive, default=0.3, help="layer height, mm (default 0.3)")
    sp.add_argument("--draw-s", type=positive, default=3.0, help="drawing time per test, s (default 3)")

    sp = sub.add_parser("probe", help="lines whose speed, width, stops and retractions vary apart (for "
                                      "calib diagnose)",
                        description="Straight lines, each slow then fast, with its own width and speed, a "
                                    "mid-line stop of 1.5, 3 or 6 s at half or three quarters of its length, "
                                    "a retraction at half of the stops, alternating direction: the causes a "
                                    "missing effect can have part, so `calib diagnose` can tell them apart "
                                    "(fit/hidden.py's discovery probe as G-code).")
    common(sp)
    sp.add_argument("--lines", type=integer(4), default=8, help="lines (default 8)")
    sp.add_argument("--length-mm", type=positive, default=60.0, help="line length, mm (default 60)")
    sp.add_argument("--speeds", type=_pos, default=[30.0, 60.0, 100.0, 140.0],
                    help="fast head speeds cycled over the lines, mm/s (default 30,60,100,140; capped by "
                         "the printer's max and --max-flow)")
    sp.add_argument("--stops-s", type=_pos, default=[1.5, 3.0, 6.0],
                    help="dwell at each line's stop cycled over the lines, s (default 1.5,3,6)")
    sp.add_argument("--max-flow", type=positive, default=10.0,
                    help="the hot end's melt rate, mm^3/s: no line is commanded more (default 10)")
    sp.add_argument("--layer-height", type=positive, default=0.2, help="layer height, mm (default 0.2)")
    return p


def _kwargs(args) -> dict:
    if args.pattern == "spiral-step":
        return dict(speeds_mm_s=args.speeds, step_s=args.step_s, n_steps=args.steps, widths_mm=args.widths,
                    layer_height_mm=args.layer_height)
    if args.pattern == "stop-mid-path":
        return dict(speeds_mm_s=args.speeds, tau_s=args.tau, steady_s=args.steady_s,
                    variants=[v.strip() for v in args.variants.split(",") if v.strip()],
                    wizard_wait_s=args.wizard_wait_s, width_mm=args.width, layer_height_mm=args.layer_height)
    if args.pattern == "retract":
        return dict(designs=args.designs, n_steps=args.steps, draw_mm=args.draw_mm, restore_mm=args.restore_mm)
    if args.pattern == "probe":
        return dict(n_lines=args.lines, length_mm=args.length_mm, fast_mm_s=args.speeds, stops_s=args.stops_s,
                    max_flow_mm3_s=args.max_flow, layer_height_mm=args.layer_height)
    return dict(re_mm=args.re_mm, widths_mm=args.widths, ve_mm_s=args.ve, height_mm=args.layer_height,
                draw_s=args.draw_s)


def write_error(path, exc: OSError, what: str = "") -> UserError:
    """One-line UserError for an output that cannot be written (used by plan/preview too)."""
    path = Path(path)
    reason = exc.strerror or str(exc)
    for anc in path.parents:
        if anc.exists():
            if not anc.is_dir():
                reason = f"{anc} is a file, not a folder"
            break
    if path.is_dir():
        reason = "that is a folder"
    return UserError(f"cannot write {path}{what}: {reason}: choose a writable output path with -o")


def _write_all(out: Path, gcode: str, manifest) -> Path:
    """Write OUT.manifest.json, OUT.timeline.npz, then OUT.gcode (each atomically).

    The G-code goes last, so a printable file never exists without its manifest; if any
    write fails, the files this run wrote are removed and the failure becomes one
    UserError line.
    """
    from calib.fileio import atomic_write_text
    from patterns.manifest import manifest_path_for, timeline_path_for

    mpath = manifest_path_for(out)
    written = [timeline_path_for(mpath), mpath, out]
    try:
        if out.is_dir():
            raise IsADirectoryError(21, "Is a directory", str(out))
        manifest.save(mpath)
        atomic_write_text(out, gcode)
    except OSError as exc:
        for f in written:
            try:
                if f.is_file():
                    f.unlink()
            except OSError:
                pass
        raise write_error(out, exc, " and its manifest") from None
    return mpath


def run(args) -> int:
    from patterns.builder import PATTERNS
    from patterns.profile import load_profile

    out = Path(args.output)
    if out.suffix.lower() not in (".gcode", ".g", ".gco"):
        raise UserError(f"output {out} should end in .gcode")
    profile = load_profile(args.printer)
    h = getattr(args, "layer_height", None)
    if h is not None and h > profile.nozzle_diameter_mm:
        # a bead higher than the nozzle is wide is no bead the width model describes
        raise UserError(f"--layer-height {h:g} mm is more than the nozzle's diameter "
                        f"({profile.nozzle_diameter_mm:g} mm); a single layer is 0.1-0.75 nozzle diameters")
    gcode, manifest = PATTERNS[args.pattern](profile, **_kwargs(args))
    manifest.gcode = out.name
    mpath = _write_all(out, gcode, manifest)
    n = len(manifest.test_tracks())
    dur = manifest.timeline.duration_s / 60 if manifest.timeline is not None else float("nan")
    print(f"wrote {out} and {mpath}: {n} test tracks, {len(manifest.fiducials)} fiducials, ~{dur:.1f} min")
    return 0
