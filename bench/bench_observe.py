"""The fit's prediction read as the measurement reads the bead (fit/observe.py).

The virtual printer prints a pattern, the renderer draws it (600 dpi flatbed, beads as
the measurement assumes them: no phenomena, so what is left is the kernel, not the
picture's other errors), ``calib measure`` measures it, and the model at the true
parameters predicts the widths two ways: as laid (one nozzle window per station) and
through the measurement's along-track kernel (5 sub-stations per 0.25 mm strip,
despeckled along the measurement's runs). Rows: at the stations where the two differ by
more than 2 um, the RMS of measured minus predicted for each (lower is closer to what the
picture holds); over all valid stations the same; and what the kernel costs ``predict``
(one parameter set as the MAP search calls it, 64 as the sampler does). The stop-mid-path
lines stop extruding mid-line (a bead that ends in a short tail), the spiral-step is
`make demo`'s print.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

from bench.common import Row, best_time_s

#: (pattern, printer profile, truth values of pa+backpressure)
SCENES = (("stop-mid-path", "direct_drive", {"pa.tau_s": 0.043, "backpressure.kb": 0.2,
                                             "backpressure.w_sat_mm": 0.8}),
          ("stop-mid-path", "adventurer3", {"pa.tau_s": 0.8, "backpressure.kb": 1.0,
                                            "backpressure.w_sat_mm": 0.8}),
          ("spiral-step", "adventurer3", {"pa.tau_s": 0.8, "backpressure.kb": 1.0,
                                          "backpressure.w_sat_mm": 0.8}))
MOVED_MM = 0.002


def _scene(pattern: str, profile: str, values: dict):
    from calib.commands.simulate import simulate_scan, write_image
    from fit.context import SimContext
    from fit.data import scan_from_table
    from fit.model import build_model
    from measure.pipeline import measure_scan
    from patterns import spiral_step, stop_mid_path
    from patterns.profile import load_profile

    prof = load_profile(profile)
    _, man = {"stop-mid-path": stop_mid_path, "spiral-step": spiral_step}[pattern].generate(prof)
    rendered, _ = simulate_scan(man, "pa+backpressure", values, "flatbed", profile=prof, dpi=600.0, seed=0,
                                realism="none")
    with tempfile.TemporaryDirectory() as d:
        res = measure_scan(write_image(os.path.join(d, "scan.png"), rendered), man)
    test = [t.id for t in man.tracks if t.kind == "test"]
    table = res.table.subset(np.isin(res.table.track, test))
    sc = scan_from_table(table, man, "scan")
    model = build_model("pa+backpressure", prof)
    th = model.theta_from(values)[None]
    seen = model.predict(sc.ctx, th)[0]
    plain = SimContext.build(man, sc.samples)
    laid = model.predict(plain, th)[0]
    y = np.where(table.valid, table.width_mm, np.nan)
    ok = np.isfinite(y) & np.isfinite(laid) & np.isfinite(seen)
    moved = ok & (np.abs(seen - laid) > MOVED_MM)
    rms = lambda r: float(np.sqrt(np.mean(r ** 2))) if r.size else float("nan")   # noqa: E731
    th64 = np.repeat(th, 64, axis=0)
    times = {k: (best_time_s(lambda c=c, t=t: model.predict(c, t), repeat=5),)
             for k, c, t in (("1 laid", plain, th), ("1 seen", sc.ctx, th),
                             ("64 laid", plain, th64), ("64 seen", sc.ctx, th64))}
    return {"n_moved": int(moved.sum()), "n_valid": int(ok.sum()),
            "moved_laid": rms((y - laid)[moved]), "moved_seen": rms((y - seen)[moved]),
            "all_laid": rms((y - laid)[ok]), "all_seen": rms((y - seen)[ok]), "times": times}


def run() -> list[Row]:
    rows: list[Row] = []
    for pattern, profile, values in SCENES:
        r = _scene(pattern, profile, values)
        tag = f"{pattern}, {profile}, flatbed 600 dpi, no phenomena"
        rows.append(Row("fit", f"{tag}: measured - predicted RMS where the kernel moves the width > 2 um "
                               f"({r['n_moved']} of {r['n_valid']} stations): as laid {1e3 * r['moved_laid']:.1f} um,"
                               f" read through the kernel", 1e3 * r["moved_seen"], "um",
                        "< as laid" if r["n_moved"] else "-",
                        bool(r["moved_seen"] < r["moved_laid"]) if r["n_moved"] else None))
        rows.append(Row("fit", f"{tag}: measured - predicted RMS, all valid stations: as laid "
                               f"{1e3 * r['all_laid']:.2f} um, through the kernel", 1e3 * r["all_seen"], "um",
                        "<= as laid", bool(r["all_seen"] <= r["all_laid"] + 1e-6)))
        t = r["times"]
        rows.append(Row("fit", f"{tag}: predict time through the kernel / as laid, one set "
                               f"({1e3 * t['1 seen'][0]:.2f} / {1e3 * t['1 laid'][0]:.2f} ms); 64 sets "
                               f"({1e3 * t['64 seen'][0]:.1f} / {1e3 * t['64 laid'][0]:.1f} ms)",
                        t["64 seen"][0] / t["64 laid"][0], "x", "-", None))
    return rows


if __name__ == "__main__":
    from bench.common import print_table
    print_table(run())
