"""Renderer speed and ground-truth fidelity: a 12 MP phone photo and a 600 dpi flatbed
scan of a 120 x 120 mm pattern (issue 3 targets: <= ~15 s each, < ~4 GB)."""
from __future__ import annotations

import resource
import time

import numpy as np

from bench.common import Row
from measure.camera import Camera
from measure.render import half_contrast_widths, render
from patterns.manifest import Fiducial, Manifest, Track

SIDE_MM = 120.0
WIDTHS_MM = (0.25, 0.4, 0.6, 0.8, 1.2, 1.6)


def pattern_120mm() -> Manifest:
    """24 straight, slightly slanted 80 mm test lines (widths 0.25-1.6 mm) and 4 markers."""
    tracks = [Track(id=i, kind="test", points_mm=[[20, 22 + 3.2 * i], [100, 23 + 3.2 * i]],
                    width_mm=WIDTHS_MM[i % len(WIDTHS_MM)], height_mm=0.2, flow_mm3_s=2.0) for i in range(24)]
    cell, size = 2.0, 12.0
    fids = []
    for k, (ox, oy) in enumerate([(2, 2), (SIDE_MM - 18, 2), (SIDE_MM - 18, SIDE_MM - 18), (2, SIDE_MM - 18)]):
        bx, by = ox + cell, oy + cell
        fids.append(Fiducial(id=k, center_mm=(bx + size / 2, by + size / 2), size_mm=size,
                             corners_mm=[[bx, by + size], [bx + size, by + size], [bx + size, by], [bx, by]]))
    return Manifest(printer={}, pattern={"name": "bench"}, tracks=tracks, fiducials=fids)


def _rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6   # Linux: kB


def run() -> list[Row]:
    m = pattern_120mm()
    region = (0.0, 0.0, SIDE_MM, SIDE_MM)
    render(m, None, Camera.flatbed((0, 0, 20, 20), 300), seed=0)          # numba warm-up
    rows = []
    cases = [("phone 12 MP, 25 deg tilt, JPEG 85", Camera.phone(region, tilt_deg=25), 85),
             ("flatbed 600 dpi, 120x120 mm", Camera.flatbed(region, 600, rotation_deg=1.0), None)]
    for name, cam, jq in cases:
        t0 = time.perf_counter()
        r = render(m, None, cam, seed=1, jpeg_quality=jq)
        dt = time.perf_counter() - t0
        mp = cam.image_size[0] * cam.image_size[1] / 1e6
        rows.append(Row("render", f"render time, {name} ({mp:.1f} MP)", dt, "s", "<= 15", dt <= 15))
        _, _, truth, meas = half_contrast_widths(r, m)
        err_um = (meas - truth) * 1000
        ok = np.isfinite(err_um)
        rms = float(np.sqrt(np.mean(err_um[ok] ** 2)))
        tol = 15.0 if cam.kind == "phone" else 5.0
        rows.append(Row("render", f"oracle half-contrast width RMS error, {name}", rms, "um", f"<= {tol:g}", rms <= tol))
        wide = ok & (truth >= 0.4)
        bias = float(np.mean(err_um[wide]))
        rows.append(Row("render", f"oracle width bias (w >= 0.4 mm), {name}", bias, "um", "|.| <= 3", abs(bias) <= 3))
    peak = _rss_gb()
    rows.append(Row("render", "peak resident memory of the bench process", peak, "GB", "<= 4", peak <= 4))
    return rows


if __name__ == "__main__":
    from bench.common import print_table

    print_table(run())
