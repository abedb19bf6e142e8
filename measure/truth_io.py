"""``SCAN.truth.json``: the ground truth of a synthetic scan or photo.

Schema ``calib.scantruth/1``::

    {"schema": "calib.scantruth/1",
     "image": "SCAN.png",                       # file name of the picture, same folder
     "camera": {"H_mm_to_px": 3x3, "image_size_px": [W, H], "center_px": [cx, cy],
                "f_px": f, "k1": .., "k2": .., "mirrored": false, "kind": "phone", "info": {..}},
     "model": {"spec": "pa+thermal", "values": {"pa.tau_s": 0.5, ...}},
     "settings": {"plate": "dark", "plastic": "opaque", "seed": 1, "lighting": {..}, ...},
     "samples": {"track": [...], "s_mm": [...], "x_mm": [...], "y_mm": [...],
                 "t_s": [...], "width_mm": [...]},
     "extras": {...}}

``samples.width_mm`` is the true width (mm) at each station: the distance between the
50 % coverage points of the rendered bead edges (measure/render.py). The homography maps
bed mm to *undistorted* px; distortion (k1, k2 about center_px, normalised by f_px) is
applied after it (measure/camera.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.errors import UserError
from calib.fileio import read_json_doc, write_json
from measure.camera import Camera
from measure.table import WidthTable

SCHEMA = "calib.scantruth/1"
_SAMPLE_COLUMNS = ("track", "s_mm", "x_mm", "y_mm", "t_s", "width_mm")


@dataclass
class ScanTruth:
    """Ground truth of one synthetic picture.

    camera      the true :class:`Camera` (bed mm -> image px)
    widths      true width per station (WidthTable; width_sd_mm = 0, valid = True)
    model_spec  effects the virtual printer ran ("pa+thermal"); "" if commanded widths
    values      parameter values {"pa.tau_s": 0.5, ...}
    settings    renderer settings (plate, plastic, lighting, noise, seed, ...)
    image       file name of the picture ("" until saved)
    """

    camera: Camera
    widths: WidthTable
    model_spec: str = ""
    values: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    image: str = ""
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        w = self.widths
        samples = {"track": w.track.astype(int).tolist()}
        for c in _SAMPLE_COLUMNS[1:]:
            samples[c] = [None if not np.isfinite(v) else round(float(v), 7) for v in getattr(w, c)]
        return {"schema": SCHEMA, "image": self.image, "camera": self.camera.to_dict(),
                "model": {"spec": self.model_spec, "values": {k: float(v) for k, v in self.values.items()}},
                "settings": self.settings, "samples": samples, "extras": self.extras}

    @classmethod
    def from_dict(cls, d: dict) -> "ScanTruth":
        s = d["samples"]
        n = len(s["track"])
        cols = {c: np.array([np.nan if v is None else v for v in s[c]], dtype=float) for c in _SAMPLE_COLUMNS[1:]}
        table = WidthTable(track=np.asarray(s["track"], dtype=np.int64), width_sd_mm=np.zeros(n),
                           valid=np.ones(n, bool), **cols)
        model = d.get("model", {})
        return cls(camera=Camera.from_dict(d["camera"]), widths=table, model_spec=model.get("spec", ""),
                   values=dict(model.get("values", {})), settings=dict(d.get("settings", {})),
                   image=d.get("image", ""), extras=dict(d.get("extras", {})))


def truth_path_for(image_path) -> Path:
    """``SCAN.png`` -> ``SCAN.truth.json``."""
    p = Path(image_path)
    return p.with_name(p.stem + ".truth.json")


def save_scan_truth(path, truth: ScanTruth) -> Path:
    """Write ``truth`` to ``path`` atomically (JSON, schema above)."""
    return write_json(path, truth.to_dict())


def load_scan_truth(path) -> ScanTruth:
    """Read a ``SCAN.truth.json``; UserError if it is missing or not one."""
    path = Path(path)
    doc = read_json_doc(path, "calib.scantruth/", "scan truth", "make one with `calib simulate`")
    try:
        return ScanTruth.from_dict(doc)
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"truth file {path} is malformed: {exc}") from None
