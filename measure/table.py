"""The widths table: what ``measure`` writes, what ``fit`` reads, what the renderer's truth holds.

CSV columns (README "Widths CSV"):

    track        int, the manifest's track id
    s_mm         arc length along the track (mm)
    x_mm, y_mm   bed position of the station (mm)
    t_s          print time of the station, from the manifest's timeline (s)
    width_mm     measured bead width (mm); 0 where the bead is missing
    width_sd_mm  one-sigma uncertainty of width_mm (mm): the station's whole error, also the
                 part it shares with its neighbours within ~1 mm (plate grain, JPEG blocks,
                 the edge model's misfit; measure/station_sd.py calibrated_sd)
    valid        1 if the sample may be fitted, 0 if not
    flag         empty, or the reason the sample is not valid (crossing, label, blob,
                 missing, glare, edge, fit, neighbour, end, isolated: a valid-looking
                 station among failed fits, or a short run of them inside contamination
                 reading another width than the bead around it, oblique: what was found runs across the
                 track, a string or another line, steep: the width changes along the
                 track faster than a strip can read, background: the plate beside the
                 bead is not the plate (a logo, a sticker), ...)
    blur_mm      optional: the edge blur (Gaussian sd, mm across the track) the width was
                 read with; empty when unknown (tables written before it, truths)
    light_angle_deg  optional: angle (deg, 0-90) between the station's flank normal and the
                 axis of the light that makes the scan's glare streaks (measure/glare.py);
                 empty when the scan has no coherent glare
    width_sd_own_mm  optional: the part of width_sd_mm that is the station's own, independent
                 of its neighbours' (mm); the fit's white measurement term (fit/likelihood.py),
                 whose along-track wobble models the shared part. Empty in older tables:
                 the fit then takes width_sd_mm
    width_corr_prev  optional: the correlation (0-1) of this station's own error with the
                 previous station's on its track, STRIP_MM before it, where the despeckling
                 along the track (measure/widths.py NEIGHBOUR_CORR) filtered both from shared
                 pixels. Nonzero links the two errors in the fit, which estimates their
                 correlation per scan from this start (``noise.meas_corr``,
                 fit/likelihood.py). Empty or 0: independent (older tables, truths, a
                 station whose predecessor was not filtered with it)
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.errors import UserError
from calib.fileio import atomic_write_text

COLUMNS = ("track", "s_mm", "x_mm", "y_mm", "t_s", "width_mm", "width_sd_mm", "valid", "flag")
#: Columns a table may lack (read as NaN).
OPTIONAL = ("blur_mm", "light_angle_deg", "width_sd_own_mm", "width_corr_prev")


@dataclass
class WidthTable:
    track: np.ndarray
    s_mm: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    t_s: np.ndarray
    width_mm: np.ndarray
    width_sd_mm: np.ndarray
    valid: np.ndarray
    flag: np.ndarray = field(default=None)
    blur_mm: np.ndarray = field(default=None)
    light_angle_deg: np.ndarray = field(default=None)
    width_sd_own_mm: np.ndarray = field(default=None)
    width_corr_prev: np.ndarray = field(default=None)

    def __post_init__(self):
        n = len(self.track)
        self.width_corr_prev = (np.zeros(n) if self.width_corr_prev is None
                                else np.nan_to_num(np.asarray(self.width_corr_prev, dtype=float).reshape(n)))
        self.width_sd_own_mm = (np.full(n, np.nan) if self.width_sd_own_mm is None
                                else np.asarray(self.width_sd_own_mm, dtype=float).reshape(n))
        self.blur_mm = (np.full(n, np.nan) if self.blur_mm is None
                        else np.asarray(self.blur_mm, dtype=float).reshape(n))
        self.light_angle_deg = (np.full(n, np.nan) if self.light_angle_deg is None
                                else np.asarray(self.light_angle_deg, dtype=float).reshape(n))
        self.track = np.asarray(self.track, dtype=np.int64)
        for name in ("s_mm", "x_mm", "y_mm", "t_s", "width_mm", "width_sd_mm"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=float).reshape(n))
        self.valid = np.asarray(self.valid).astype(bool).reshape(n)
        if self.flag is None:
            self.flag = np.array([""] * n, dtype=object)
        else:
            self.flag = np.asarray(self.flag, dtype=object).reshape(n)

    def __len__(self) -> int:
        return len(self.track)

    def fit_sd_mm(self) -> np.ndarray:
        """The sd (mm) the fit weighs each station by: ``width_sd_own_mm`` where the table has
        it, else ``width_sd_mm``."""
        own = self.width_sd_own_mm
        return np.where(np.isfinite(own) & (own > 0), own, self.width_sd_mm)

    def subset(self, mask) -> "WidthTable":
        return WidthTable(**{c: getattr(self, c)[mask] for c in COLUMNS + OPTIONAL})

    # -- io ---------------------------------------------------------------------
    def to_csv_text(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COLUMNS + OPTIONAL)
        for i in range(len(self)):
            b, a, o = self.blur_mm[i], self.light_angle_deg[i], self.width_sd_own_mm[i]
            r = self.width_corr_prev[i]
            w.writerow([int(self.track[i]), f"{self.s_mm[i]:.4f}", f"{self.x_mm[i]:.4f}",
                        f"{self.y_mm[i]:.4f}", f"{self.t_s[i]:.5f}", f"{self.width_mm[i]:.5f}",
                        f"{self.width_sd_mm[i]:.5f}", int(self.valid[i]), self.flag[i] or "",
                        f"{b:.5f}" if np.isfinite(b) else "", f"{a:.1f}" if np.isfinite(a) else "",
                        f"{o:.5f}" if np.isfinite(o) else "", f"{r:.3f}" if r != 0 else ""])
        return buf.getvalue()

    def save(self, path) -> Path:
        return atomic_write_text(path, self.to_csv_text())

    @classmethod
    def load(cls, path) -> "WidthTable":
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise UserError(f"widths file {path} does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"cannot read widths file {path}: {exc}") from None
        rows = list(csv.reader(io.StringIO(text)))
        if not rows:
            raise UserError(f"widths file {path} is empty; run `calib measure` to make one")
        header = [h.strip() for h in rows[0]]
        missing = [c for c in COLUMNS if c not in header]
        if missing:
            raise UserError(f"widths file {path} lacks column(s) {', '.join(missing)}; "
                            f"expected {','.join(COLUMNS)}")
        body = [r for r in rows[1:] if r]
        if not body:
            raise UserError(f"widths file {path} has a header but no samples")
        idx = {c: header.index(c) for c in COLUMNS + OPTIONAL if c in header}
        cols = {}
        try:
            for c in idx:
                vals = [r[idx[c]] if idx[c] < len(r) else "" for r in body]
                if c == "flag":
                    cols[c] = np.array(vals, dtype=object)
                elif c in ("track", "valid"):
                    cols[c] = np.array([int(float(v)) for v in vals])
                else:
                    cols[c] = np.array([float(v) if v.strip() else np.nan for v in vals])
        except ValueError as exc:
            raise UserError(f"widths file {path} has a non-numeric value in column {c}: {exc}") from None
        table = cls(**cols)
        bad = table.valid & ~(np.isfinite(table.width_mm) & np.isfinite(table.width_sd_mm)
                              & (table.width_sd_mm > 0))
        if bad.any():
            raise UserError(f"widths file {path}: {int(bad.sum())} valid sample(s) have NaN/inf width "
                            "or a non-positive width_sd_mm (first at row "
                            f"{int(np.argmax(bad)) + 2}); mark them valid=0 or re-measure")
        rho = table.width_corr_prev
        if np.any((rho < 0) | (rho >= 1)):
            raise UserError(f"widths file {path}: width_corr_prev must lie in [0, 1), row "
                            f"{int(np.argmax((rho < 0) | (rho >= 1))) + 2} has {rho[(rho < 0) | (rho >= 1)][0]:g}")
        return table
