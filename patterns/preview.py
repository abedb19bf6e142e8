"""Top-view preview of a pattern: tracks coloured by commanded volumetric flow (mm^3/s),
fiducial outlines with their ids, labels and the bed outline. matplotlib, Agg backend."""
from __future__ import annotations

import io

import numpy as np


def render_preview(manifest, profile=None, *, dpi: int = 150) -> bytes:
    """PNG bytes of the top view. Bead widths are drawn to scale (mm) where possible."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon, Rectangle

    fig, ax = plt.subplots(figsize=(8, 8))
    if profile is not None:
        bx, by = profile.bed_x_mm, profile.bed_y_mm
        ax.add_patch(Rectangle((bx[0], by[0]), bx[1] - bx[0], by[1] - by[0], fill=False, lw=1.5,
                               ec="0.3", ls="--", label="bed"))
        ax.set_xlim(bx[0] - 5, bx[1] + 5)
        ax.set_ylim(by[0] - 5, by[1] + 5)
    segs, flows, lws, coast = [], [], [], []
    for tr in manifest.tracks:
        p = tr.points_mm
        for i in range(len(p) - 1):
            w = max(tr.width_mm[i], tr.width_mm[i + 1])
            if w > 0:
                segs.append(p[i:i + 2])
                flows.append(max(tr.flow_mm3_s[i], tr.flow_mm3_s[i + 1]))
                lws.append(w)
            else:
                coast.append(p[i:i + 2])
    qmax = max(flows) if flows else 1.0
    lc = LineCollection(segs, array=np.asarray(flows), cmap="viridis", linewidths=np.asarray(lws) * 2.0)
    lc.set_clim(0.0, qmax)
    ax.add_collection(lc)
    if coast:
        ax.add_collection(LineCollection(coast, colors="tab:red", linewidths=0.4, linestyles=":",
                                         label="no extrusion (ooze measured)"))
    for f in manifest.fiducials:
        ax.add_patch(Polygon(np.asarray(f.corners_mm), closed=True, fill=False, ec="tab:orange", lw=1.0))
        ax.text(*f.center_mm, str(f.id), color="tab:orange", ha="center", va="center", fontsize=8)
    for lab in manifest.labels:
        x0, y0, x1, y1 = lab["bbox_mm"]
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="tab:blue", lw=0.4))
    fig.colorbar(lc, ax=ax, label="commanded flow (mm$^3$/s)", shrink=0.8)
    name = manifest.pattern.get("name", "gcode") if isinstance(manifest.pattern, dict) else "gcode"
    dur = f", {manifest.timeline.duration_s / 60:.1f} min" if manifest.timeline is not None else ""
    ax.set_title(f"{name}: {len(manifest.test_tracks())} test tracks{dur}")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")
    if profile is None:
        ax.autoscale_view()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()
