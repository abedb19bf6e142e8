"""`calib measure`: bead widths from a flatbed scan or a photo of a printed pattern."""
from __future__ import annotations

import sys
from pathlib import Path

from calib.argtypes import positive


def add_parser(subparsers):
    p = subparsers.add_parser(
        "measure", help="measure bead widths along the test tracks in a scan or photo",
        description="Register the picture to the pattern (ArUco fiducials; without them the planned "
                    "path is found in the picture automatically, or --points gives the pose by hand), "
                    "measure the bead width every 0.25 mm along every test track with a "
                    "one-sigma uncertainty, and write the widths CSV (plus a QA overlay and a JSON "
                    "summary on request). Several pictures of the same print (the lamp moved between "
                    "them: a textured plate's specks move, the bead does not) are each measured and "
                    "their widths averaged station by station. Exit code 2 with one line on bad input; "
                    "no partial CSV.")
    p.add_argument("scan", nargs="+",
                   help="the picture: JPEG, PNG or TIFF (8/16 bit), up to 50 MP; or several pictures of the "
                        "same print, e.g. 3-5 photos with the lamp moved around the print between them "
                        "(measure/stack.py; the QA overlay shows the first)")
    p.add_argument("--manifest", required=True, help="NAME.manifest.json of the printed pattern")
    p.add_argument("-o", "--output", required=True, help="widths CSV to write")
    p.add_argument("--overlay", help="QA overlay PNG to write (tracks, measured edges, marker ids)")
    p.add_argument("--summary", help="JSON summary to write (residual, fraction valid, flags, warnings)")
    p.add_argument("--points", help='point hints "x_mm,y_mm=u_px,v_px;..." (>= 4) for prints without fiducials '
                   "(default: the pose is found automatically from the track layout; with several pictures, the same "
                   "points for each: one camera that did not move)")
    p.add_argument("--max-residual-mm", type=positive, default=0.1,
                   help="refuse a registration with a larger residual (mm; default 0.1)")
    return p


def run(args) -> int:
    from measure.pipeline import MeasureRefused, save_summary, summary_path_for
    from measure.stack import measure_pictures
    from patterns.manifest import Manifest
    from calib.errors import UserError

    man = Manifest.load(args.manifest)
    try:
        res = measure_pictures(args.scan, man, points=args.points, overlay_path=None,
                               max_residual_mm=args.max_residual_mm)
    except MeasureRefused as exc:
        # no widths CSV, but the overlay and summary that show why (the user's next step)
        shown = _write_qa(args, man, exc.result)
        raise UserError(str(exc) + (f" (see {', '.join(shown)})" if shown else
                                    " (add --overlay qa.png to see why)")) from None
    # the CSV only once every check passed; its summary sidecar tells `calib fit` whether
    # the widths are calibrated (measure/calibrate.py), whatever --summary says
    res.table.save(args.output)
    save_summary(summary_path_for(args.output), res.summary)
    _write_qa(args, man, res)
    s = res.summary
    print(f"{Path(args.output)}: {s['samples']} samples, {s['fraction_valid']:.0%} valid, "
          f"registration residual {res.registration.residual_mm:.3f} mm ({res.registration.method})",
          file=sys.stderr)
    st = s.get("stack")
    if st:
        shares = ", ".join(f"{p['fraction_valid']:.0%}" for p in st["per_picture"])
        print(f"calib measure: {len(st['per_picture'])} pictures measured (valid {shares}), each station the "
              f"mean of its valid readings ({st['readings_per_valid_station']:.1f} a station on average)",
              file=sys.stderr)
    rec = res.registration.recovered_markers
    if rec:
        print(f"calib measure: marker(s) {', '.join(map(str, rec))} read by their whole printed pattern where the "
              "others put them (the detector missed them or misread their corners: a logo, a string or glare "
              "across the border?)", file=sys.stderr)
    if res.placement is not None and res.placement.sentence():
        # the residual above then counts where the printer put its tracks, not only the pose
        print(f"calib measure: {res.placement.sentence()}", file=sys.stderr)
    on = s.get("measured_on", {})
    if on.get("channel") == "colour discriminant":
        print(f"calib measure: widths measured on the colour axis that tells bead from plate (scatter "
              f"{on['width_noise_um_colour']:.0f} um against {on['width_noise_um_grey']:.0f} in grey)", file=sys.stderr)
    if s.get("apparent_width", {}).get("note"):
        print(f"calib measure: {s['apparent_width']['note']}", file=sys.stderr)
    for w in s["warnings"]:
        print(f"calib measure: warning: {w}", file=sys.stderr)
    return 0


def _write_qa(args, man, res) -> list[str]:
    from measure.overlay import draw_overlay, save_overlay
    from measure.pipeline import save_summary

    out = []
    if args.overlay:
        save_overlay(args.overlay, draw_overlay(res.color, man, res.registration, res.measurement))
        out.append(str(args.overlay))
    if args.summary:
        save_summary(args.summary, res.summary)
        out.append(str(args.summary))
    return out
