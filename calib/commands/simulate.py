"""`calib simulate OUT.gcode --truth TRUTH.toml -o SCAN.png`: print on the virtual printer, scan it.

The virtual printer (fit/virtual.py) runs the pattern's timeline with the effects and
values of TRUTH.toml and gives the true bead width along every test track; the renderer
(measure/render.py) draws those widths as a flatbed scan or a phone photo through a
known camera. Writes SCAN.png (or .jpg) and SCAN.truth.json (measure/truth_io.py), and
with --plot SCAN.widths.png: true vs commanded width along each test track.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from calib.argtypes import number, positive, seed
from calib.errors import UserError

_IMAGE_EXT = {".png": ".png", ".jpg": ".jpg", ".jpeg": ".jpg", ".tif": ".tif", ".tiff": ".tif"}
#: Free border (mm) around the pattern in the picture.
REGION_MARGIN_MM = 6.0


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate", help="print a pattern on the virtual printer and write a synthetic scan/photo",
        description="Run the pattern's G-code on a virtual printer whose extruder obeys the effects "
                    "and values of TRUTH.toml, then render the print as a flatbed scan (--dpi) or a "
                    "12 MP phone photo (--tilt, lens distortion, uneven light, JPEG). Writes the "
                    "image and SCAN.truth.json (true camera homography, model, true width per "
                    "sample) so `calib measure` can be scored against it.")
    p.add_argument("gcode", help="G-code file; its NAME.manifest.json is used when present")
    p.add_argument("--truth", required=True, help="TRUTH.toml: [model] effects and [values] (see data/truths/)")
    p.add_argument("-o", "--output", default=None,
                   help="image path, .png/.tif (lossless) or .jpg (default: GCODE name + .scan.png, "
                        ".jpg for --camera phone)")
    p.add_argument("--printer", default=None,
                   help="printer profile (.toml or shipped name); needed when there is no manifest "
                        "next to the G-code")
    p.add_argument("--camera", choices=("flatbed", "phone"), default="flatbed", help="picture kind (default flatbed)")
    p.add_argument("--dpi", type=positive, default=600.0, help="flatbed resolution, 300-1200 (default 600)")
    p.add_argument("--tilt", type=number(), default=25.0, help="phone tilt from top-down, degrees 0-45 (default 25)")
    p.add_argument("--plate", choices=("dark", "light"), default="dark", help="build plate (default dark, textured)")
    p.add_argument("--plastic", choices=("opaque", "translucent"), default="opaque", help="filament (default opaque)")
    p.add_argument("--jpeg-quality", type=int, default=None,
                   help="JPEG quality for .jpg output (default 85 for phone photos, 95 otherwise)")
    p.add_argument("--no-clutter", action="store_true", help="no plate logos, scratches or cutting mat")
    p.add_argument("--realism", default="default", metavar="LIST",
                   help="what real prints and cameras do that the measurement does not assume: "
                        "'all', 'none', or a comma list of " + ", ".join(_phenomena()) +
                        " ('all,sparkle': all and a textured plate's specks; 'all,shadows': all and the "
                        "lamp's cast shadows; 'all' leaves both out; "
                        "measure/phenomena.py); default: all for --camera phone, none for flatbed")
    p.add_argument("--seed", type=seed, default=0, help="random seed for the picture (default 0)")
    p.add_argument("--light-seed", type=seed, default=None,
                   help="where the lamp stands, apart from --seed: pictures that differ only in it are "
                        "photos of one print from one camera with the lamp moved between them, which "
                        "`calib measure` takes together (default: drawn with --seed)")
    p.add_argument("--effects", default=None, help="Python file with user effects named in TRUTH.toml")
    p.add_argument("--plot", action="store_true", help="also write SCAN.widths.png: true vs commanded widths")
    return p


def _phenomena():
    from measure.phenomena import EXTRA_PHENOMENA, PHENOMENA
    return PHENOMENA + EXTRA_PHENOMENA


def camera_for(manifest, camera_kind: str, *, dpi: float = 600.0, tilt_deg: float = 25.0, seed: int = 0,
               margin_mm: float = REGION_MARGIN_MM):
    """The true camera for a picture of ``manifest``'s pattern (region = pattern + margin).

    Flatbed: the print lies on the glass turned by a few tenths of a degree to 2 deg
    (seeded), with the scanner's axis scale error. Phone: 12 MP, ``tilt_deg``, a seeded
    yaw of up to 8 deg and barrel distortion.
    """
    from measure.camera import Camera
    from measure.render import _pattern_rect

    rng = np.random.default_rng([int(seed), 7])
    r = _pattern_rect(manifest) + np.array([-margin_mm, -margin_mm, margin_mm, margin_mm])
    if camera_kind == "flatbed":
        return Camera.flatbed(r, dpi, rotation_deg=float(rng.uniform(-2, 2)),
                              scale_error=tuple(rng.uniform(-0.006, 0.006, 2)))
    if camera_kind == "phone":
        return Camera.phone(r, tilt_deg=tilt_deg, yaw_deg=float(rng.uniform(-8, 8)),
                            k1=float(rng.uniform(-0.08, -0.03)), k2=float(rng.uniform(0.0, 0.03)))
    raise UserError(f"unknown camera {camera_kind!r}: use flatbed or phone")


def simulate_scan(manifest, truth_spec: str, values: dict, camera_kind: str = "flatbed", *,
                  profile=None, extra_effects=(), dpi: float = 600.0, tilt_deg: float = 25.0,
                  plate: str = "dark", plastic: str = "opaque", seed: int = 0,
                  jpeg_quality: int | None = None, clutter: bool = True, progress: bool = False,
                  realism=None, **render_kw):
    """Print ``manifest`` on the virtual printer (``truth_spec`` + ``values``) and picture it.

    Returns (Rendered, VirtualPrint). ``jpeg_quality`` defaults to 85 for a phone and to
    lossless for a flatbed. ``realism``: :class:`measure.phenomena.Realism` or its text
    ("default": all phenomena for a phone, none for a flatbed). Extra keywords go to
    :func:`measure.render.render`.
    """
    from fit.model import build_model
    from fit.virtual import print_virtual
    from measure.render import render

    if camera_kind == "flatbed" and not 300 <= dpi <= 1200:
        raise UserError(f"--dpi {dpi:g} is outside 300-1200; flatbed scanners are used at 300-1200 dpi")
    model = build_model(truth_spec, profile if profile is not None else manifest.printer, extra_effects)
    vp = print_virtual(manifest, model, values)
    camera = camera_for(manifest, camera_kind, dpi=dpi, tilt_deg=tilt_deg, seed=seed)
    if jpeg_quality is None and camera_kind == "phone":
        jpeg_quality = 85
    from measure.phenomena import NEEDS_PHYSICS, Realism, deposit_pieces

    if not isinstance(realism, Realism):
        realism = Realism.parse(realism, camera_kind)
    # the beads are drawn as the moving head laid them and each dwell's blob as its disc
    # (fit/blobs.py); the truth is the width across the track, the discs' chords included
    t = vp.table
    blob_chord = np.where(t.width_mm > vp.bead_width_mm, t.width_mm, 0.0)
    t.width_mm[:] = vp.bead_width_mm
    if "irregular" in realism:
        from measure.phenomena import irregular_widths

        t.width_mm[:] = irregular_widths(t.track, t.s_mm, t.width_mm, np.random.default_rng([int(seed), 11]),
                                         rel=realism.irregular_rel, corr_mm=realism.irregular_corr_mm,
                                         abs_mm=realism.irregular_mm, short_mm=realism.irregular_short_mm)
    drawn = t.subset(np.ones(len(t), bool))
    t.width_mm[:] = np.maximum(t.width_mm, blob_chord)
    deposits = deposit_pieces(manifest, vp) if set(NEEDS_PHYSICS) & realism.enabled else None
    rendered = render(manifest, drawn, camera, plate=plate, plastic=plastic, seed=seed,
                      jpeg_quality=jpeg_quality, clutter=clutter, progress=progress,
                      model={"spec": truth_spec, "values": values}, realism=realism,
                      deposits=deposits, blobs=[(b.x_mm, b.y_mm, b.diameter_mm, b.h_mm) for b in vp.blobs],
                      truth_widths=t, **render_kw)
    rendered.truth.extras.update({"commanded_mm3": vp.commanded_mm3, "extruded_mm3": vp.extruded_mm3,
                                  "dribble_mm3": vp.dribble_mm3, "blobs": len(vp.blobs)})
    return rendered, vp


def run(args) -> int:
    from fit.truth import load_truth
    from measure.truth_io import save_scan_truth, truth_path_for
    from patterns.manifest import Manifest, manifest_path_for

    if args.camera == "flatbed" and not 300 <= args.dpi <= 1200:
        raise UserError(f"--dpi {args.dpi:g} is outside 300-1200; flatbed scanners are used at 300-1200 dpi")
    if args.camera == "phone" and not 0 <= args.tilt <= 45:
        raise UserError(f"--tilt {args.tilt:g} is outside 0-45 degrees")
    if args.jpeg_quality is not None and not 10 <= args.jpeg_quality <= 100:
        raise UserError(f"--jpeg-quality {args.jpeg_quality} is outside 10-100")
    src = Path(args.gcode)
    if not src.is_file():
        raise UserError(f"G-code {src} does not exist")
    default_ext = ".jpg" if args.camera == "phone" else ".png"
    out = Path(args.output) if args.output else src.with_name(src.stem + ".scan" + default_ext)
    ext = _IMAGE_EXT.get(out.suffix.lower())
    if ext is None:
        raise UserError(f"output {out.name}: use a .png, .tif or .jpg file name")
    profile = None
    if args.printer:
        from patterns.profile import load_profile
        profile = load_profile(args.printer)
    mpath = manifest_path_for(src)
    if mpath.is_file():
        manifest = Manifest.load(mpath)
    elif profile is not None:
        from patterns.plan import manifest_from_gcode
        manifest = manifest_from_gcode(src.read_text(errors="replace"), profile)
    else:
        raise UserError(f"no manifest {mpath.name} next to {src.name}: make the G-code with "
                        "`calib pattern`, or pass --printer to plan it")
    if manifest.timeline is None:
        raise UserError(f"manifest {mpath.name} has no timeline; re-create it with `calib pattern` or `calib plan`")
    extra = ()
    if args.effects:
        from fit.effects import load_effects_file
        extra = load_effects_file(args.effects)
    spec, values, _extras = load_truth(args.truth, profile if profile is not None else manifest.printer, extra)
    from measure.phenomena import Realism
    try:
        realism = Realism.parse(args.realism, args.camera)
    except ValueError as exc:
        raise UserError(f"--realism: {exc}") from None
    jq = args.jpeg_quality if args.jpeg_quality is not None else \
        (realism.jpeg_quality if "jpeg" in realism else 85 if args.camera == "phone" else 95)
    rendered, vp = simulate_scan(manifest, spec, values, args.camera, profile=profile, extra_effects=extra,
                                 dpi=args.dpi, tilt_deg=args.tilt, plate=args.plate, plastic=args.plastic,
                                 seed=args.seed, jpeg_quality=jq if ext == ".jpg" else None,
                                 clutter=not args.no_clutter, progress=True, realism=realism,
                                 light_seed=args.light_seed)
    write_image(out, rendered)
    rendered.truth.image = out.name
    tpath = save_scan_truth(truth_path_for(out), rendered.truth)
    print(f"wrote {out} ({rendered.image.shape[1]}x{rendered.image.shape[0]} px) and {tpath.name}")
    if args.plot:
        ppath = out.with_name(out.stem + ".widths.png")
        plot_widths(ppath, manifest, vp.table, title=f"{spec}: " + ", ".join(f"{k}={v:g}" for k, v in values.items()))
        print(f"wrote {ppath}")
    return 0


def write_image(path, rendered) -> Path:
    """Write the picture atomically: JPEG bytes as rendered (no re-encoding), else lossless."""
    import cv2

    from calib.fileio import atomic_write_bytes

    path = Path(path)
    ext = _IMAGE_EXT.get(path.suffix.lower(), ".png")
    if ext == ".jpg":
        data = rendered.encoded
        if data is None:
            ok, buf = cv2.imencode(".jpg", rendered.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            data = buf.tobytes()
    else:
        ok, buf = cv2.imencode(ext, rendered.image)
        data = buf.tobytes()
    return atomic_write_bytes(path, data)


def plot_widths(path, manifest, table, title: str = "", max_tracks: int = 48) -> Path:
    """SCAN.widths.png: true width (from the virtual printer) vs commanded along each test track."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calib.fileio import atomic_write_bytes

    tracks = manifest.test_tracks()[:max_tracks]
    n = max(1, len(tracks))
    ncol = int(np.ceil(np.sqrt(n)))
    nrow = int(np.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 2.2 * nrow), squeeze=False, sharey=True)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, tr in zip(axes.ravel(), tracks):
        sel = table.track == tr.id
        s = table.s_mm[sel]
        ax.plot(s, tr.interp("width_mm", s), color="0.5", ls="--", lw=1, label="commanded")
        ax.plot(s, table.width_mm[sel], color="C0", lw=1.2, label="true (virtual printer)")
        ax.set_title(f"track {tr.id} {tr.group}", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7)
    axes[0, 0].set_ylabel("width (mm)", fontsize=8)
    axes[-1, 0].set_xlabel("s along track (mm)", fontsize=8)
    if len(manifest.test_tracks()) > max_tracks:
        title += f"  (first {max_tracks} of {len(manifest.test_tracks())} test tracks)"
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())
