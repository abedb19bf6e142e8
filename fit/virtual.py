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


@dataclass
class VirtualPrint:
    """Ground truth of one virtual print.

    table            WidthTable of true widths at the stations (width_sd 0, valid 1;
                     stations never printed: width 0, valid 0, flag "missing")
    t_s, q_mm3_s     nozzle flow at the timeline nodes
    widths           track id -> (s_mm, width_mm) arrays
    commanded_mm3    commanded volume (sum of de * Af)
    extruded_mm3     volume out of the nozzle
    deposited_mm3    volume laid on tracks (beads + blobs)
    dribble_mm3      volume out while on no track
    stored_mm3       volume still stored as compression at the end (P_end * Af)
    blobs            dwells on a track that left plastic
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
    table = WidthTable(track=ctx.s_track, s_mm=ctx.s_mm, x_mm=ctx.s_x_mm, y_mm=ctx.s_y_mm,
                       t_s=ctx.s_t_s, width_mm=np.where(printed, w, 0.0),
                       width_sd_mm=np.zeros(ctx.n_samples), valid=printed,
                       flag=np.where(printed, "", "missing").astype(object))
    widths = {int(t): (ctx.s_mm[ctx.s_track == t], table.width_mm[ctx.s_track == t])
              for t in np.unique(ctx.s_track)}
    on = ctx.on_track
    blobs = _blobs(manifest, ctx, out * af, blob_min_mm3)
    return VirtualPrint(
        table=table, t_s=ctx.t_s, q_mm3_s=sim.vn_node_mm_s[0] * af, widths=widths,
        commanded_mm3=float(np.sum(ctx.de_mm) * af),
        extruded_mm3=float(np.sum(out) * af),
        deposited_mm3=float(np.sum(out[on]) * af),
        dribble_mm3=float(np.sum(out[~on]) * af),
        stored_mm3=float(sim.p_end_mm[0] * af),
        blobs=blobs, model_spec=m.spec, values=m.values(m.default_theta()), sim=sim)


def _blobs(manifest, ctx: SimContext, dv_mm3: np.ndarray, min_mm3: float) -> list[Blob]:
    """Runs of consecutive on-track intervals with the head still (v_head ~ 0)."""
    still = ctx.on_track & (ctx.v_head_mm_s * ctx.dt_s < 1e-6)
    tl = manifest.timeline
    blobs = []
    k = 0
    n = len(still)
    while k < n:
        if not still[k]:
            k += 1
            continue
        j = k
        while j + 1 < n and still[j + 1] and ctx.track[j + 1] == ctx.track[k]:
            j += 1
        vol = float(dv_mm3[k:j + 1].sum())
        if vol >= min_mm3:
            blobs.append(Blob(track=int(ctx.track[k]), s_mm=float(tl.s_mm[k]), x_mm=float(tl.x_mm[k]),
                              y_mm=float(tl.y_mm[k]), t_start_s=float(ctx.t_s[k]),
                              t_end_s=float(ctx.t_s[j + 1]), volume_mm3=vol))
        k = j + 1
    return blobs
