"""The manifest: what was printed, where, when, and what the extruder was told to do.

Every later step reads it: the renderer draws its tracks, ``measure`` samples widths
along them, the simulator and the fitters run the physics on its timeline.

Files (schema ``calib.manifest/1``, documented in README "Manifest"):

* ``NAME.manifest.json``  - printer profile, pattern and parameters, fiducials, labels,
  tracks as polylines with per-vertex commanded width/height/flow.
* ``NAME.timeline.npz``   - the planned timeline (sidecar, arrays of :class:`Timeline`).

All lengths in mm, times in s, speeds in mm/s, flows in mm^3/s.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from calib.errors import UserError
from calib.fileio import atomic_write as _atomic_write
from calib.fileio import json_default as _json_default
from calib.fileio import read_json_doc

SCHEMA = "calib.manifest/1"

#: Track kinds. Only ``test`` tracks are measured and fitted; the others are printed
#: (and rendered) but exist for registration, reading or priming.
TRACK_KINDS = ("test", "prime", "fiducial", "ruler", "label", "other")


@dataclass
class Timeline:
    """The planned motion, sampled every <= 0.25 mm of head travel and <= 5 ms.

    Arrays all have the same length N. Between two samples the head moves in a straight
    line and the extruder moves by ``e_mm[k+1] - e_mm[k]``: physics must integrate with
    those increments so commanded volume is conserved exactly.

    t_s        time since the start of the program (s)
    x_mm, y_mm, z_mm   nozzle position (mm)
    v_mm_s     head (XY) speed (mm/s)
    ve_mm_s    commanded extruder velocity (mm/s of filament; negative = retracting)
    e_mm       cumulative commanded extruder position (mm of filament, monotone with
               commanded E, never reset by G92)
    track      track id the nozzle is on (-1: not on any track: travel, dwell elsewhere)
    s_mm       arc length along that track from its start (mm; NaN where track == -1)
    """

    t_s: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    v_mm_s: np.ndarray
    ve_mm_s: np.ndarray
    e_mm: np.ndarray
    track: np.ndarray
    s_mm: np.ndarray

    FIELDS = ("t_s", "x_mm", "y_mm", "z_mm", "v_mm_s", "ve_mm_s", "e_mm", "track", "s_mm")

    def __post_init__(self):
        n = len(self.t_s)
        for name in self.FIELDS:
            arr = np.asarray(getattr(self, name), dtype=np.int64 if name == "track" else float)
            if arr.shape != (n,):
                raise ValueError(f"timeline field {name} has shape {arr.shape}, expected ({n},)")
            setattr(self, name, arr)

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if len(self) else 0.0

    def save(self, path: str | os.PathLike) -> None:
        arrays = {name: getattr(self, name) for name in self.FIELDS}
        _atomic_write(path, lambda f: np.savez_compressed(f, **arrays), binary=True)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Timeline":
        try:
            with np.load(path) as z:
                return cls(**{name: z[name] for name in cls.FIELDS})
        except (OSError, KeyError, ValueError) as exc:
            raise UserError(f"cannot read timeline {path}: {exc}") from None

    def slice(self, mask: np.ndarray) -> "Timeline":
        return Timeline(**{name: getattr(self, name)[mask] for name in self.FIELDS})


@dataclass
class Track:
    """One printed polyline.

    points_mm    (M, 2) vertices in bed coordinates (mm)
    width_mm     (M,) commanded bead width at each vertex (mm; 0 where the pattern
                 deliberately coasts without extrusion, e.g. after a mid-path stop)
    height_mm    (M,) layer height at each vertex (mm)
    flow_mm3_s   (M,) commanded volumetric flow at each vertex (mm^3/s)
    kind         one of TRACK_KINDS
    group        free label that groups tracks of one test condition ("v=50mm/s")
    params       the swept parameters of this track, with units in the keys
    """

    id: int
    kind: str
    points_mm: np.ndarray
    width_mm: np.ndarray
    height_mm: np.ndarray
    flow_mm3_s: np.ndarray
    z_mm: float = 0.2
    group: str = ""
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        self.points_mm = np.asarray(self.points_mm, dtype=float).reshape(-1, 2)
        m = len(self.points_mm)
        for name in ("width_mm", "height_mm", "flow_mm3_s"):
            arr = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (m,)).copy()
            setattr(self, name, arr)
        if self.kind not in TRACK_KINDS:
            raise ValueError(f"track {self.id}: unknown kind {self.kind!r}")

    @property
    def cumlen_mm(self) -> np.ndarray:
        """Arc length (mm) at each vertex."""
        seg = np.hypot(*np.diff(self.points_mm, axis=0).T)
        return np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length_mm(self) -> float:
        return float(self.cumlen_mm[-1])

    def at(self, s_mm) -> tuple[np.ndarray, np.ndarray]:
        """Position (N, 2) and unit tangent (N, 2) at arc lengths ``s_mm``."""
        s = np.atleast_1d(np.asarray(s_mm, dtype=float))
        cl = self.cumlen_mm
        seg = np.clip(np.searchsorted(cl, s, side="right") - 1, 0, len(cl) - 2)
        d = self.points_mm[seg + 1] - self.points_mm[seg]
        L = np.hypot(d[:, 0], d[:, 1])
        frac = np.where(L > 0, (s - cl[seg]) / np.where(L > 0, L, 1), 0.0)
        pos = self.points_mm[seg] + d * frac[:, None]
        tangent = d / np.where(L > 0, L, 1)[:, None]
        return pos, tangent

    def interp(self, name: str, s_mm) -> np.ndarray:
        """Per-vertex quantity ``name`` (e.g. ``width_mm``) interpolated at arc length."""
        return np.interp(s_mm, self.cumlen_mm, getattr(self, name))

    def to_json(self) -> dict:
        d = asdict(self)
        for k in ("points_mm", "width_mm", "height_mm", "flow_mm3_s"):
            d[k] = np.round(np.asarray(d[k]), 5).tolist()
        return d


@dataclass
class Fiducial:
    """A printed square marker (ArUco DICT_4X4_50 unless ``dictionary`` says otherwise).

    corners_mm are the outer corners of the marker's black border in ArUco order
    (top-left, top-right, bottom-right, bottom-left as seen from above the bed, with bed
    +y pointing away from the viewer, i.e. up in a top-down photo).
    """

    id: int
    center_mm: tuple[float, float]
    size_mm: float
    corners_mm: list
    dictionary: str = "DICT_4X4_50"


@dataclass
class Manifest:
    printer: dict
    pattern: dict
    tracks: list[Track]
    fiducials: list[Fiducial] = field(default_factory=list)
    labels: list[dict] = field(default_factory=list)
    ruler: dict = field(default_factory=dict)
    timeline: Timeline | None = None
    gcode: str = ""
    schema: str = SCHEMA

    # -- lookup -----------------------------------------------------------------
    def track(self, track_id: int) -> Track:
        for tr in self.tracks:
            if tr.id == track_id:
                return tr
        raise KeyError(track_id)

    def test_tracks(self) -> list[Track]:
        return [tr for tr in self.tracks if tr.kind == "test"]

    def cut_to_test_tracks(self, pad_s: float = 1.0) -> "Manifest":
        """This manifest with only its test tracks and the timeline cut to them +- ``pad_s``
        (s). A fit on it skips simulating the frame, markers and labels (~90 % of a
        pattern's timeline); the extruder starts from rest ``pad_s`` before the first test
        track, so the pad must cover whatever state the print before leaves (a few s with
        bead back-pressure: bench/bench_e2e.py)."""
        tl = self.timeline
        ids = [t.id for t in self.test_tracks()]
        on = np.flatnonzero(np.isin(tl.track, ids))
        keep = (tl.t_s >= tl.t_s[on[0]] - pad_s) & (tl.t_s <= tl.t_s[on[-1]] + pad_s)
        return replace(self, tracks=self.test_tracks(), fiducials=[], labels=[], timeline=tl.slice(keep))

    # -- io ---------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write ``NAME.manifest.json`` and the sidecar ``NAME.timeline.npz`` atomically."""
        path = Path(path)
        doc = {
            "schema": self.schema,
            "printer": self.printer,
            "pattern": self.pattern,
            "gcode": self.gcode,
            "fiducials": [asdict(f) for f in self.fiducials],
            "labels": self.labels,
            "ruler": self.ruler,
            "tracks": [t.to_json() for t in self.tracks],
        }
        if self.timeline is not None:
            tl_path = timeline_path_for(path)
            self.timeline.save(tl_path)
            doc["timeline"] = {"file": tl_path.name, "samples": len(self.timeline)}
        text = json.dumps(doc, indent=1, default=_json_default)
        _atomic_write(path, lambda f: f.write(text.encode()), binary=True)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Manifest":
        path = Path(path)
        doc = read_json_doc(path, "calib.manifest/", "manifest",
                            "make one with `calib pattern` or `calib plan`")
        try:
            tracks = [Track(**t) for t in doc["tracks"]]
            fids = [Fiducial(**f) for f in doc.get("fiducials", [])]
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"manifest {path} is malformed: {exc}") from None
        timeline = None
        if doc.get("timeline"):
            tl_file = path.parent / doc["timeline"]["file"]
            if not tl_file.exists():
                raise UserError(f"manifest {path} names timeline {tl_file.name}, which is missing; "
                                "keep the .timeline.npz next to the manifest")
            timeline = Timeline.load(tl_file)
        return cls(printer=doc.get("printer", {}), pattern=doc.get("pattern", {}), tracks=tracks,
                   fiducials=fids, labels=doc.get("labels", []), ruler=doc.get("ruler", {}),
                   timeline=timeline, gcode=doc.get("gcode", ""), schema=doc["schema"])


def timeline_path_for(manifest_path: str | os.PathLike) -> Path:
    p = Path(manifest_path)
    name = p.name
    stem = name[: -len(".manifest.json")] if name.endswith(".manifest.json") else p.stem
    return p.with_name(stem + ".timeline.npz")


def manifest_path_for(gcode_path: str | os.PathLike) -> Path:
    """``OUT.gcode`` -> ``OUT.manifest.json``."""
    p = Path(gcode_path)
    return p.with_name(p.stem + ".manifest.json")


@dataclass
class Samples:
    """Measurement stations along the test tracks (the rows of a widths CSV).

    track (int), s_mm (arc length along the track), x_mm, y_mm (bed position),
    t_s (time the nozzle passed that point, from the timeline; NaN if never),
    nx, ny (unit normal to the track, for cross-sections), width_nominal_mm,
    height_mm (commanded).
    """

    track: np.ndarray
    s_mm: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    t_s: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    width_nominal_mm: np.ndarray
    height_mm: np.ndarray

    def __len__(self) -> int:
        return len(self.track)


def sample_points(manifest: Manifest, ds_mm: float = 0.25, kinds=("test",),
                  margin_mm: float = 0.0) -> Samples:
    """Stations every ``ds_mm`` (<= 0.25 mm by default) along every track of ``kinds``.

    Stations sit at s = margin, margin + ds, ... up to length - margin. ``t_s`` is the
    first time the timeline puts the nozzle at that arc length on that track.
    """
    ids, ss = [], []
    for tr in manifest.tracks:
        if tr.kind not in kinds or tr.length_mm <= 2 * margin_mm:
            continue
        n = int(np.floor((tr.length_mm - 2 * margin_mm) / ds_mm + 1e-9)) + 1
        ids.append(np.full(n, tr.id))
        ss.append(margin_mm + ds_mm * np.arange(n))
    return samples_at(manifest, np.concatenate(ids) if ids else np.zeros(0, np.int64),
                      np.concatenate(ss) if ss else np.zeros(0))


def samples_at(manifest: Manifest, track, s_mm) -> Samples:
    """Stations at arc lengths ``s_mm`` (mm) of the tracks ``track`` (ids of
    ``manifest.tracks``), in the given order: positions and normals from the track (at s
    clipped to it), commanded width and height, pass time ``t_s`` from the timeline (NaN
    without one, or where the nozzle never reached s)."""
    track = np.asarray(track, dtype=np.int64)
    s_mm = np.asarray(s_mm, dtype=float)
    n = len(track)
    cols = {k: np.full(n, np.nan) for k in Samples.__dataclass_fields__ if k not in ("track", "s_mm")}
    tl = manifest.timeline
    ids = {tr.id: tr for tr in manifest.tracks}
    for tid in np.unique(track):
        tr = ids[int(tid)]
        rows = np.flatnonzero(track == tid)
        s = s_mm[rows]
        pos, tan = tr.at(np.clip(s, 0.0, tr.length_mm))
        if tl is not None:
            on = tl.track == tr.id
            cols["t_s"][rows] = _first_passage_time(tl.s_mm[on], tl.t_s[on], s)
        cols["x_mm"][rows], cols["y_mm"][rows] = pos[:, 0], pos[:, 1]
        cols["nx"][rows], cols["ny"][rows] = -tan[:, 1], tan[:, 0]
        cols["width_nominal_mm"][rows] = tr.interp("width_mm", s)
        cols["height_mm"][rows] = tr.interp("height_mm", s)
    return Samples(track=track.copy(), s_mm=s_mm.copy(), **cols)


def _first_passage_time(s_tl: np.ndarray, t_tl: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Time at which the nozzle first reached arc length ``s`` (the track is traversed forward)."""
    if len(s_tl) < 2:
        return np.full(len(s), np.nan)
    # Running maximum makes s monotone; np.interp on the first occurrence of each value
    # gives the first passage (stops appear as flat runs, we want their start).
    smax = np.maximum.accumulate(s_tl)
    keep = np.concatenate([[True], np.diff(smax) > 0])
    t = np.interp(s, smax[keep], t_tl[keep], left=np.nan, right=np.nan)
    return t
