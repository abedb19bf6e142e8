"""QA overlay: what was measured, drawn on the picture for the user to check.

The registered track outline (centre line +- commanded width / 2, thin, yellow), the
measured edges (centre offset +- measured width / 2: green dots where valid, red where
flagged, magenta where the bead is missing, grey where it is too faint to tell), the
marker outlines with their ids (cyan), and a caption with the residual and the fraction
of valid samples. Large pictures are downscaled to ``max_side_px`` first so the PNG stays
small.
"""
from __future__ import annotations

import cv2
import numpy as np

from calib.fileio import atomic_write_bytes
from calib.errors import UserError

YELLOW, GREEN, RED, MAGENTA, CYAN = (0, 220, 255), (60, 220, 60), (40, 40, 255), (255, 0, 255), (255, 255, 0)
GREY = (160, 160, 160)
FLAG_COLOUR = {"missing": MAGENTA, "faint": GREY, "dropout": GREY}


def draw_overlay(color, manifest, registration, measurement, max_side_px: int = 2400) -> np.ndarray:
    """BGR uint8 overlay image (downscaled so its longer side is <= ``max_side_px``)."""
    img = np.asarray(color)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    k = min(1.0, max_side_px / max(img.shape[:2]))
    out = cv2.resize(img, (round(img.shape[1] * k), round(img.shape[0] * k)), interpolation=cv2.INTER_AREA) \
        if k < 1 else img.copy()
    # dim the photo a little so the drawing stands out
    out = (out.astype(np.float32) * 0.75).astype(np.uint8)
    sc = lambda uv: np.round(uv * k * 16).astype(np.int32)     # 4 fractional bits for LINE_AA

    nozzle = float((manifest.printer or {}).get("nozzle_diameter_mm", 0.4))
    for tr in manifest.tracks:
        if tr.kind != "test" or tr.length_mm <= 0:
            continue
        s = np.linspace(0, tr.length_mm, max(2, int(tr.length_mm / 0.5) + 1))
        pos, tan = tr.at(s)
        nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
        # a commanded "bead" wider than 4 nozzles is a blob (a third-party test restoring its
        # pressure over 1 mm at 50x the flow reads 42 mm): drawn at full width it crossed
        # the whole picture as two lines
        hw = np.minimum(tr.interp("width_mm", s), 4 * nozzle)[:, None] / 2
        for side in (-1, 1):
            uv = registration.project(pos + side * hw * nrm)
            cv2.polylines(out, [sc(uv).reshape(-1, 1, 2)], False, YELLOW, 1, cv2.LINE_AA, shift=4)

    tb = measurement.table
    xy = np.column_stack([tb.x_mm, tb.y_mm])
    nrm = np.column_stack([measurement.nx, measurement.ny])
    c = np.nan_to_num(measurement.centre_mm)
    w = np.nan_to_num(tb.width_mm)
    r = max(1, int(round(2 * k * max(1.0, 1.0 / k / 2))))
    for side in (-1, 1):
        uv = registration.project(xy + (c + side * w / 2)[:, None] * nrm) * k
        for i in range(len(tb)):
            col = GREEN if tb.valid[i] else FLAG_COLOUR.get(tb.flag[i], RED)
            if np.all(np.isfinite(uv[i])):
                cv2.circle(out, (int(round(uv[i, 0])), int(round(uv[i, 1]))), r, col, -1)

    for mid, corners in zip(registration.marker_ids, registration.marker_corners_px):
        q = sc(np.asarray(corners)).reshape(-1, 1, 2)
        cv2.polylines(out, [q], True, CYAN, 2, cv2.LINE_AA, shift=4)
        ctr = np.asarray(corners).mean(axis=0) * k
        cv2.putText(out, f"id {mid}", (int(ctr[0]) - 20, int(ctr[1]) + 5), cv2.FONT_HERSHEY_SIMPLEX,
                    0.6, CYAN, 2, cv2.LINE_AA)
    caption = (f"residual {registration.residual_mm:.3f} mm  valid {np.mean(tb.valid):.0%}  "
               f"{registration.method}  green=valid red=flagged magenta=missing grey=too faint yellow=commanded")
    cv2.putText(out, caption, (10, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    return out


def save_overlay(path, overlay) -> None:
    """Write the overlay PNG atomically."""
    ok, buf = cv2.imencode(".png", overlay)
    if not ok:
        raise UserError(f"cannot encode the QA overlay for {path}")
    atomic_write_bytes(path, buf.tobytes())
