"""Physics speed and accuracy: one model evaluation on a 20,000-sample timeline.

Targets (issue 3): linear `pa` <= 5 ms; the full nonlinear composition <= 50 ms;
64 parameter sets at once well under 64x one set: the kernels run parallel over sets
(from 4 sets), so the target is 64 / cores x 1.25 (40x on 2 cores). Accuracy: the full
composition at dt = 5 ms against the same model at dt = 0.5 ms (self-convergence).
On the demo spiral (spiral-step, adventurer3, 54k timeline samples): predict per set for
pa, pa+thermal (exact two-state kernel), pa+thermal+backpressure, at 1 and 28 sets, and
the coarsened physics timeline against the full one (max width difference).
"""
from __future__ import annotations

import os

import numpy as np

from bench.common import Row, best_time_s
from fit.context import SimContext
from fit.geometry import bead_area_mm2, filament_area_mm2
from fit.model import build_model
from patterns.manifest import Manifest, Timeline, Track

FULL = "pa+nonlinear+bernoulli+backpressure+offset+thermal+kalico_tanh+flow_gain+backlash+bed_tilt+heading"


def _zigzag_manifest(n_t: int = 20_000, dt: float = 0.004, v: float = 60.0) -> Manifest:
    """One long test track whose commanded width alternates every 20 mm (flow steps),
    with a 0.3 s dwell every 100 mm: n_t timeline samples."""
    af = filament_area_mm2(1.75)
    t = np.arange(n_t) * dt
    speed = np.where((t % 2.0) < 1.7, v, 0.0)
    s = np.concatenate([[0.0], np.cumsum(speed[:-1] * dt)])
    w = np.where((s // 20) % 2 == 0, 0.45, 0.6)
    de = np.diff(s) * bead_area_mm2(w[:-1], 0.2) / af
    e = np.concatenate([[0.0], np.cumsum(de)])
    tl = Timeline(t_s=t, x_mm=s % 200, y_mm=s // 200, z_mm=0 * t + 0.2, v_mm_s=speed,
                  ve_mm_s=np.concatenate([de / dt, [0.0]]), e_mm=e, track=np.zeros(n_t, int), s_mm=s)
    tr = Track(id=0, kind="test", points_mm=[[0, 0], [s[-1], 0]], width_mm=0.45, height_mm=0.2,
               flow_mm3_s=0)
    return Manifest(printer={"filament_diameter_mm": 1.75, "nozzle_diameter_mm": 0.4}, pattern={},
                    tracks=[tr], timeline=tl)


def _refined(m: Manifest, k: int) -> Manifest:
    """The same print with every timeline interval split into k equal parts."""
    tl = m.timeline
    n = len(tl)
    u = np.arange((n - 1) * k + 1) / k
    f = {name: np.interp(u, np.arange(n), getattr(tl, name)) for name in tl.FIELDS
         if name not in ("track",)}
    f["track"] = tl.track[np.minimum(np.floor(u).astype(int), n - 1)]
    f["ve_mm_s"] = np.interp(u, np.arange(n), tl.ve_mm_s)
    return Manifest(printer=m.printer, pattern=m.pattern, tracks=m.tracks, timeline=Timeline(**f))


def run() -> list[Row]:
    rows = []
    m = _zigzag_manifest()
    ctx = SimContext.build(m)
    pa = build_model("pa")
    full = build_model(FULL)
    th_full = full.default_theta()
    pa.predict(ctx, [0.5])          # compile / load the numba cache
    full.predict(ctx, th_full)
    t_pa = best_time_s(lambda: pa.predict(ctx, [0.5]), repeat=7)
    rows.append(Row("physics", "pa predict, 20k samples, 1 set", t_pa * 1e3, "ms", "<= 5", t_pa <= 5e-3))
    t_full = best_time_s(lambda: full.predict(ctx, th_full), repeat=5)
    rows.append(Row("physics", "full composition predict, 20k samples, 1 set", t_full * 1e3, "ms",
                    "<= 50", t_full <= 50e-3))
    cores = len(os.sched_getaffinity(0))
    ratio_max = 64 / cores * 1.25
    th64 = np.tile(th_full, (64, 1))
    th64[:, 0] = np.geomspace(0.02, 2.0, 64)
    t64 = best_time_s(lambda: full.predict(ctx, th64), repeat=3)
    rows.append(Row("physics", "full composition, 64 sets / 1 set (time ratio)", t64 / t_full, "x",
                    f"<= {ratio_max:.0f} ({cores} cores)", t64 / t_full <= ratio_max))
    pa64 = np.geomspace(0.02, 2.0, 64)[:, None]
    t64pa = best_time_s(lambda: pa.predict(ctx, pa64), repeat=3)
    rows.append(Row("physics", "pa, 64 sets / 1 set (time ratio)", t64pa / t_pa, "x",
                    f"<= {ratio_max:.0f} ({cores} cores)", t64pa / t_pa <= ratio_max))

    rows += _demo_spiral_rows()

    # Accuracy of the theta scheme: nozzle flow at dt = 5 ms against the same input
    # (each interval split into 10 equal parts: identical piecewise-constant ve) at
    # dt = 0.5 ms, at the common nodes; direct drive tau = 0.02 s, shear thinning n = 0.5.
    coarse = _zigzag_manifest(n_t=1_000, dt=0.005)
    fine = _refined(coarse, 10)
    for spec, vals in (("pa+nonlinear+bernoulli+backpressure+thermal",
                        {"pa.tau_s": 0.02, "nonlinear.n": 0.5}),
                       ("pa+kalico_tanh", {"pa.tau_s": 0.017})):
        nl = build_model(spec).with_values(vals)
        qc = nl.flow(SimContext.build(coarse), nl.default_theta())[0]
        qf = nl.flow(SimContext.build(fine), nl.default_theta())[0][::10]
        err = float(np.max(np.abs(qc - qf)) / np.max(qf))
        rows.append(Row("physics", f"{spec} tau~0.02 s: max |q(dt=5ms)-q(dt=0.5ms)| / q_max",
                        err * 100, "%", "<= 1", err <= 0.01))
    return rows


def _demo_spiral_rows() -> list[Row]:
    """predict on the demo spiral at its stations (every 0.25 mm), 1 and 28 sets."""
    from patterns import builder

    _, man = builder.PATTERNS["spiral-step"]("adventurer3")
    ctx = SimContext.build(man)
    rows = [Row("physics", f"demo spiral: physics timeline intervals (coarsened / full of {ctx.n_t - 1})",
                (ctx.physics.n_t - 1) / (ctx.n_t - 1) if ctx.physics else 1.0, "x", "", None)]
    for spec in ("pa", "pa+thermal", "pa+thermal+backpressure"):
        m = build_model(spec, man.printer)
        th = m.default_theta()
        th28 = np.tile(th, (28, 1))
        th28[:, 0] = np.geomspace(0.02, 2.0, 28)
        m.predict(ctx, th)
        m.predict(ctx, th28)
        t1 = best_time_s(lambda: m.predict(ctx, th), repeat=7)
        t28 = best_time_s(lambda: m.predict(ctx, th28), repeat=3)
        rows.append(Row("physics", f"demo spiral {spec} predict, {ctx.n_samples} stations, 1 set",
                        t1 * 1e3, "ms", "", None))
        rows.append(Row("physics", f"demo spiral {spec} predict, 28 sets", t28 * 1e3, "ms",
                        "< 28x 1 set", t28 < 28 * t1))
        full = m.simulate(ctx, th).bead_widths_mm[0]
        ok = np.isfinite(full)
        err = float(np.max(np.abs(full[ok] - m.predict(ctx, th)[0][ok])))
        rows.append(Row("physics", f"demo spiral {spec}: max |w(coarse) - w(full timeline)|",
                        err * 1e3, "um", "<= 1", err <= 1e-3))
    return rows


if __name__ == "__main__":
    from bench.common import print_table
    print_table(run())
