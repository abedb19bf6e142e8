"""The virtual printer: print a manifest's timeline with a chosen model and values.

Returns the true bead width at every station (a WidthTable with width_sd 0, valid 1),
the nozzle flow q(t), widths per track, and where plastic went that is not a bead:
dribble (flow while on no track: travel, dwell off the part) and blobs (flow while the
head stands still on a track). Bead geometry: fit/geometry.py (rounded rectangle
A = (w - h) h + pi h^2 / 4); deposit windows: fit/context.py.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fit.blobs import disc_radius_mm
from fit.context import SimContext
from fit.model import Model, Simulation
from measure.table import WidthTable


@dataclass
class Blob:
    """Plastic deposited while the head stood still on a track (mm, s, mm^3)."""

    track: int
    s_mm: float
    x_mm: float
    y_mm: float
    t_start_s: float
    t_end_s: float
    volume_mm3: float
    h_mm: float = 0.2
    diameter_mm: float = 0.0         # of its disc, sqrt(4 V / (pi h)) (fit/blobs.py)


@dataclass
class VirtualPrint:
    """Ground truth of one virtual print.

    table            WidthTable of true widths at the stations (width_sd 0, valid 1;
                     stations never printed: width 0, valid 0, flag "missing"; where a
                     blob's disc is wider than the bead: its chord, valid 0, flag "blob")
    t_s, q_mm3_s     nozzle flow at the timeline nodes
    widths           track id -> (s_mm, width_mm) arrays
    commanded_mm3    commanded volume (sum of de * Af)
    extruded_mm3     volume out of the nozzle
    deposited_mm3    volume laid on tracks (beads + blobs)
    dribble_mm3      volume out while on no track
    stored_mm3       volume still stored as compression at the end (P_end * Af)
    blobs            dwells on a track that left plastic (discs: fit/blobs.py)
    model_spec, values   the truth
    """

    table: WidthTable
    t_s: np.ndarray
    q_mm3_s: np.ndarray
    widths: dict
    commanded_mm3: float
    extruded_mm3: float
    deposited_mm3: float
    dribble_mm3: float
    stored_mm3: float
    blobs: list[Blob] = field(default_factory=list)
    model_spec: str = ""
    values: dict = field(default_factory=dict)
    sim: Simulation | None = field(default=None, repr=False)
    #: (n_s,) the width the moving head laid at the stations, without the blobs' discs
    #: (mm; ``table`` holds the width with them, what a picture shows)
    bead_width_mm: np.ndarray | None = field(default=None, repr=False)


def print_virtual(manifest, model: Model, values: dict, samples=None,
                  ctx: SimContext | None = None, blob_min_mm3: float = 1e-3) -> VirtualPrint:
    """Simulate printing ``manifest`` on a printer obeying ``model`` with ``values``.

    ``values``: full parameter names -> values (missing ones take the defaults).
    ``samples``: stations (Samples or WidthTable); default sample_points(manifest).
    """
    ctx = ctx or SimContext.build(manifest, samples)
    m = model.with_values(values)
    sim = m.simulate(ctx, m.default_theta())
    af = ctx.filament_area_mm2
    out = sim.out_mm[0]
    w = sim.widths_mm[0]
    printed = ctx.printed & np.isfinite(w)
    bead = sim.bead_widths_mm[0]
    # where a blob's disc is wider than the bead the picture shows the blob: flagged as a
    # measurement flags it, so a fit of this table sees the beads the model predicts
    blob = printed & (w > bead + 1e-9)
    table = WidthTable(track=ctx.s_track, s_mm=ctx.s_mm, x_mm=ctx.s_x_mm, y_mm=ctx.s_y_mm,
                       t_s=ctx.s_t_s, width_mm=np.where(printed, w, 0.0),
                       width_sd_mm=np.zeros(ctx.n_samples), valid=printed & ~blob,
                       flag=np.where(blob, "blob", np.where(printed, "", "missing")).astype(object))
    widths = {int(t): (ctx.s_mm[ctx.s_track == t], table.width_mm[ctx.s_track == t])
              for t in np.unique(ctx.s_track)}
    on = ctx.on_track
    blobs = _blobs(manifest, ctx, sim, blob_min_mm3)
    return VirtualPrint(
        table=table, t_s=ctx.t_s, q_mm3_s=sim.vn_node_mm_s[0] * af, widths=widths,
        commanded_mm3=float(np.sum(ctx.de_mm) * af),
        extruded_mm3=float(np.sum(out) * af),
        deposited_mm3=float(np.sum(out[on]) * af),
        dribble_mm3=float(np.sum(out[~on]) * af),
        stored_mm3=float(sim.p_end_mm[0] * af),
        blobs=blobs, model_spec=m.spec, values=m.values(m.default_theta()), sim=sim,
        bead_width_mm=np.where(printed, bead, 0.0))


def _blobs(manifest, ctx: SimContext, sim: Simulation, min_mm3: float) -> list[Blob]:
    """The blobs of ``ctx.blobs`` (fit/blobs.py) holding at least ``min_mm3``."""
    bm = ctx.blobs
    if bm is None or not bm.n_blobs:
        return []
    tl = manifest.timeline
    vol = sim.blob_volume_mm3[0]
    blobs = []
    for b in range(bm.n_blobs):
        if vol[b] < min_mm3:
            continue
        k = np.flatnonzero(bm.interval_blob == b)
        blobs.append(Blob(track=int(bm.track[b]), s_mm=float(bm.s_mm[b]), x_mm=float(tl.x_mm[k[0]]),
                          y_mm=float(tl.y_mm[k[0]]), t_start_s=float(ctx.t_s[k[0]]),
                          t_end_s=float(ctx.t_s[k[-1] + 1]), volume_mm3=float(vol[b]),
                          h_mm=float(bm.h_mm[b]),
                          diameter_mm=float(2.0 * disc_radius_mm(vol[b], bm.h_mm[b]))))
    return blobs
