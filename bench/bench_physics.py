"""Physics speed and accuracy: one model evaluation on a 20,000-sample timeline.

Targets (issue 3): linear `pa` <= 5 ms; the full nonlinear composition <= 50 ms;
64 parameter sets at once well under 64x one set (we ask <= 16x). Accuracy: the full
composition at dt = 5 ms against the same model at dt = 0.5 ms (self-convergence).
"""
from __future__ import annotations

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
    th64 = np.tile(th_full, (64, 1))
    th64[:, 0] = np.geomspace(0.02, 2.0, 64)
    t64 = best_time_s(lambda: full.predict(ctx, th64), repeat=3)
    rows.append(Row("physics", "full composition, 64 sets / 1 set (time ratio)", t64 / t_full, "x",
                    "<= 16", t64 / t_full <= 16))
    pa64 = np.geomspace(0.02, 2.0, 64)[:, None]
    t64pa = best_time_s(lambda: pa.predict(ctx, pa64), repeat=3)
    rows.append(Row("physics", "pa, 64 sets / 1 set (time ratio)", t64pa / t_pa, "x", "<= 16",
                    t64pa / t_pa <= 16))

    # Self-convergence of the theta scheme: dt = 5 ms vs 0.5 ms on the same physical print.
    coarse = _zigzag_manifest(n_t=1_000, dt=0.005)
    fine = _zigzag_manifest(n_t=10_000, dt=0.0005)
    nl = build_model("pa+nonlinear+bernoulli+backpressure+thermal").with_values(
        {"pa.tau_s": 0.02, "nonlinear.n": 0.5})
    wc = nl.predict(SimContext.build(coarse), nl.default_theta())[0]
    ctx_f = SimContext.build(fine, samples=None)
    wf = nl.predict(ctx_f, nl.default_theta())[0]
    n = min(len(wc), len(wf))
    err = float(np.nanmax(np.abs(wc[:n] - wf[:n])))
    rows.append(Row("physics", "nonlinear tau=0.02 s n=0.5: max |w(dt=5ms) - w(dt=0.5ms)|", err * 1e3,
                    "um", "<= 5", err <= 5e-3))
    return rows


if __name__ == "__main__":
    from bench.common import print_table
    print_table(run())
