"""Top-view preview of a pattern: tracks coloured by commanded volumetric flow (mm^3/s),
fiducial outlines with their ids, labels and the bed outline. matplotlib, Agg backend.

The PNG is exactly FIGSIZE_IN * dpi pixels square (constrained layout, no tight bbox), so
callers can map bed mm to image pixels with :func:`render_preview_mapped`.
"""
from __future__ import annotations

import io

import numpy as np


FIGSIZE_IN = 8.0


def render_preview(manifest, profile=None, *, dpi: int = 150) -> bytes:
    """PNG bytes of the top view, FIGSIZE_IN * dpi pixels square; beads drawn at their
    commanded width (mm, to scale, at least 0.3 pt)."""
    return render_preview_mapped(manifest, profile, dpi=dpi)[0]


def render_preview_mapped(manifest, profile=None, *, dpi: int = 150):
    """(PNG bytes, to_px): ``to_px(xy_mm (N, 2)) -> (N, 2)`` image pixels (u right, v down)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon, Rectangle

    fig, ax = plt.subplots(figsize=(FIGSIZE_IN, FIGSIZE_IN), dpi=dpi, layout="constrained")
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
            elif tr.kind == "test":     # hops between strokes of furniture are not drawn
                coast.append(p[i:i + 2])
    qmax = max(flows) if flows else 1.0
    lc = LineCollection(segs, array=np.asarray(flows), cmap="viridis", linewidths=0.5)
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
    # Beads to scale: after a layout pass, 1 mm of bed is known in points (equal aspect).
    fig.canvas.draw()
    pt_per_mm = abs(np.diff(ax.transData.transform([[0.0, 0.0], [1.0, 0.0]])[:, 0])[0]) * 72.0 / dpi
    lc.set_linewidths(np.maximum(np.asarray(lws) * pt_per_mm, 0.3))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    trans = ax.transData.frozen()       # after the draw: the final constrained layout
    height_px = fig.bbox.height
    plt.close(fig)

    def to_px(xy_mm):
        d = trans.transform(np.asarray(xy_mm, dtype=float).reshape(-1, 2))
        return np.column_stack([d[:, 0], height_px - d[:, 1]])

    return buf.getvalue(), to_px
