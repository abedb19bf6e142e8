"""The image channel the widths are measured on: grey, or the colour axis that best tells bead from plate.

A grey level mixes the three colour channels with fixed (luminance) weights. On a light,
grained plate the grain is almost neutral (it varies along R = G = B) while a coloured bead
differs from the plate mostly in hue: in grey the grain's contrast is a third to a half of
the bead's, and on the light-plate render the widths scattered 30-60 um (sd) at 600 dpi
where a dark plate gave 2-4 um. The linear discriminant (Fisher)

    w = (S_bg + S_bead)^-1 (m_bead - m_bg)                                   (1)

(m, S: mean colour and covariance of pixels on the beads and on the bare plate beside
them) is the projection of the colour with the largest ratio of bead/plate contrast to
the spread within each. A linear projection keeps the edge model's form (a blurred box is
a blend of two colours, measure/edges.py), so the projected image is measured exactly
like the grey one; it is rescaled to the grey image's bead and plate levels, so the
polarity and the amplitude rules stay as they are.

Presence: a line that never printed, on a light grained plate, has grain dark enough to
pass for a bead in grey (27 % of such stations on the light-plate render) but the plate's
colour. Where the axis separates bead from plate well (PRESENCE_CNR), a station whose
colour at its centre is nearer the plate's is missing (:meth:`Channel.bead_likeness`,
used by measure/widths.py), whichever image the widths are measured on.

The projection replaces grey as a candidate only when it raises the contrast-to-noise ratio |m_bead - m_bg| / sd_bg
by more than MIN_GAIN over grey (white or grey plastic on a neutral plate gains nothing),
and it is used only when the widths measured on it scatter less (:func:`width_noise`)
and read like grey's but for a constant (:func:`width_disagreement`): a JPEG stores
colour at half resolution (4:2:0), which blurs and rings a chroma-weighted image more
than the grey one. Below MIN_GAIN the same trial runs after grey's widths are measured,
where they turned out loose (:func:`retry_in_colour`): dark plastic on the light grained
plate under a phone gains 1.5x in contrast and its widths scattered 36 um in grey, 28 in
colour (bench_realism seed 0: 34.5 -> 27.6 um RMS after the fit's offset).

Colour at half resolution. A projection is luminance plus colour: every BGR channel is
Y plus chroma terms, so (1) applied to a picture is (sum w) Y + c(u, v) with c the chroma
part. Where a JPEG halved the chroma, c is restored at Y's resolution with the guided
filter (He, Sun & Tang, "Guided image filtering", IEEE TPAMI 35 (2013) 1397, eqs. 5-8),
Y the guide:

    c' = mean_k(a) Y + mean_k(b),  a = cov_k(Y, c) / (var_k(Y) + eps),  b = mean_k(c) - a mean_k(Y)   (2)

(means over (2 CHROMA_RADIUS_PX + 1)^2 windows): where the chroma follows the luminance (a
bead's edge) it takes the luminance's sharp edge, where it does not (neutral plate grain)
it stays the local mean. On the light-plate render with every phenomenon, re-encoded as
a 4:2:0 JPEG of quality 70, the widths scattered 39 um in grey, 28 um on the plain
projection and 23 um on the restored one (4:4:4: 12.5 um); and the scatter the choice
below is made on read 24.4 / 19.6 (grey kept) before and 24.4 / 16.9 after. On a lossless
picture (2) would only cost sharpness: it is applied to subsampled JPEGs only.
"""
from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from patterns.manifest import Manifest, sample_points

#: The colour projection is a candidate only above this gain in contrast-to-noise ratio
#: (its trial costs two measurements; the gains that paid were 2.1-4x, a 12 MP phone render
#: of white beads on a dark plate gains 1.6x and keeps grey).
MIN_GAIN = 2.0
#: ... and then only when the widths measured on it scatter this many times less.
MIN_NOISE_GAIN = 1.25
#: Under MIN_GAIN the trial runs after grey's widths are measured, where they turned out
#: loose: their stations' median sd at least RETRY_SD_MM (a phone's dark plate 5 um, a
#: flatbed's 2-4; the light grained plate under a phone 27-31 um) and the projection's
#: gain at least RETRY_MIN_GAIN. The scatter falls by less than the contrast rises (a
#: phone's halved chroma): a gain of 1.5 cut it 1.30x (35 -> 27 um, the light plate under
#: a phone), one of 1.26 raised it (realdata SpStartStopTest2: 31 -> 39 um, a trial of
#: ~10 s for nothing on its 12 MP photo).
RETRY_MIN_GAIN = 1.4
RETRY_SD_MM = 0.015
#: ... and when the widths it reads differ from grey's by no more than this (mm) between
#: the commanded widths (:func:`width_disagreement`). A 4:2:0 JPEG's plain projection of a
#: grained light plate scattered 12.7 um against grey's 17.3 but read the 0.25 mm beads
#: 68 um narrow and the 1.2 mm ones 63 um wide (range 51 um against grey); where the
#: projection pays (the light plate as a PNG, seeds 0, 1, 3; restored 4:2:0 JPEGs) the
#: range was 4-24 um.
MAX_WIDTH_DISAGREEMENT_MM = 0.035
#: The colour axis decides presence (measure/widths.py) when it separates bead from plate
#: by at least this many plate sds.
PRESENCE_CNR = 6.0
#: Beads at least this wide (mm, commanded) give the bead colour; narrower ones are
#: mostly edge at a phone's blur.
MIN_WIDTH_MM = 0.45
#: Plate samples sit this far (mm) beyond the commanded edge; those that come within
#: 0.3 mm of any other bead are dropped.
PLATE_OFFSET_MM = 0.5
#: Guided filter (2) window half-width (px: JPEG halves chroma in pixels, whatever the
#: dpi; 1, 2, 3 px gave 26, 24, 23 um of scatter on the test above) and regulariser
#: (luminance variance, grey 0..1: windows flatter than a 1 % grey sd keep their mean).
CHROMA_RADIUS_PX = 3
CHROMA_EPS = 1e-4


@dataclass
class Channel:
    """What :func:`bead_channel` chose.

    weights     (3,) BGR weights of the projection, None when grey was kept
    cnr_gray    contrast-to-noise ratio of bead against plate in grey
    cnr_color   the same for the projection (1)
    used        whether the projection replaced grey
    plate_level, bead_level   medians of the projection on plate and on beads
    noise_*_mm, valid_*   the widths' scatter and valid fraction on either image
                (:func:`width_noise`; only when the contrast-to-noise ratio made it a candidate)
    chroma_restored   the projection's half-resolution chroma was restored by (2)
    """

    @property
    def tells_presence(self) -> bool:
        """The colour axis separates bead from plate by >= PRESENCE_CNR plate sds (whether or
        not the widths are measured on it): :func:`bead_likeness` then says bead or plate."""
        return self.weights is not None and bool(self.cnr_color >= PRESENCE_CNR)

    def bead_likeness(self, color, uv) -> np.ndarray:
        """(N,) where the colour at pixels ``uv`` (N, 2) lies between plate (0) and bead (1)
        on the discriminant axis (1)."""
        H, W = color.shape[:2]
        u, v = np.clip(uv[:, 0], 0, W - 1), np.clip(uv[:, 1], 0, H - 1)
        val = sample_colour(color, u, v) @ np.asarray(self.weights, np.float64)
        return (val - self.plate_level) / (self.bead_level - self.plate_level)

    weights: np.ndarray | None
    cnr_gray: float
    cnr_color: float
    used: bool
    plate_level: float = float("nan")
    bead_level: float = float("nan")
    noise_gray_mm: float = float("nan")
    noise_color_mm: float = float("nan")
    valid_gray: float = float("nan")
    valid_color: float = float("nan")
    chroma_restored: bool = False
    width_disagreement_mm: float = float("nan")
    #: medians of grey on beads and on plate (the projection is rescaled to them)
    gray_levels: tuple = (float("nan"), float("nan"))
    #: the trial ran after grey's widths were measured (:func:`retry_in_colour`)
    retried: bool = False

    def to_dict(self) -> dict:
        return {"channel": "colour discriminant" if self.used else "grey",
                "weights_bgr": None if self.weights is None else [float(v) for v in self.weights],
                "contrast_to_noise_grey": _finite(self.cnr_gray),
                "contrast_to_noise_colour": _finite(self.cnr_color),
                "width_noise_um_grey": _finite(self.noise_gray_mm * 1e3),
                "width_noise_um_colour": _finite(self.noise_color_mm * 1e3),
                "width_disagreement_um": _finite(self.width_disagreement_mm * 1e3),
                "chroma_restored": bool(self.chroma_restored),
                "tried_after_grey": bool(self.retried)}


def _finite(v):
    return float(v) if np.isfinite(v) else None


def bead_channel(gray, color, manifest: Manifest, registration, *, ds_mm: float = 1.0,
                 chroma_halved: bool = False):
    """(image, Channel): ``gray`` itself, or the colour projection (1) rescaled to grey's
    bead and plate levels when it separates bead from plate MIN_GAIN times better.

    gray (H, W) float 0..1 (the picture's luminance Y); color (H, W, 3) uint8 BGR; the
    registration maps bed mm to pixels. Bead pixels: the centres of test-track stations
    every ``ds_mm`` (mm) of commanded width >= MIN_WIDTH_MM; plate pixels: beside them on
    both sides (PLATE_OFFSET_MM). ``chroma_halved``: the picture's colour was stored at a
    lower resolution (measure.imageio.jpeg_chroma_subsampled): the projection's chroma is
    restored by (2).
    """
    none = Channel(None, float("nan"), float("nan"), False)
    if color is None or color.ndim != 3 or color.shape[2] != 3:
        return gray, none
    smp = sample_points(manifest, ds_mm=ds_mm)
    w = np.asarray(smp.width_nominal_mm, float)
    keep = np.isfinite(w) & (w >= MIN_WIDTH_MM)
    if keep.sum() < 30:
        return gray, none
    xy = np.column_stack([smp.x_mm, smp.y_mm])[keep]
    nrm = np.column_stack([smp.nx, smp.ny])[keep]
    half = w[keep, None] / 2
    bead_xy = np.concatenate([xy, xy + 0.15 * half * nrm, xy - 0.15 * half * nrm])
    off = half + PLATE_OFFSET_MM
    plate_xy = np.concatenate([xy + off * nrm, xy - off * nrm])
    plate_xy = plate_xy[_clear_of_beads(manifest, plate_xy)]
    if len(plate_xy) < 30:
        return gray, none
    H, W = gray.shape

    def sample(img, pts):
        uv = registration.project(pts)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
        uv = uv[ok]
        if img.ndim == 2:
            return ndimage.map_coordinates(img, [uv[:, 1], uv[:, 0]], order=1)
        return sample_colour(img, uv[:, 0], uv[:, 1])

    cb, cp = sample(color, bead_xy), sample(color, plate_xy)
    gb, gp = sample(gray, bead_xy), sample(gray, plate_xy)
    if len(cb) < 30 or len(cp) < 30:
        return gray, none
    cnr_g = _cnr(gb, gp)
    mb, mp = np.median(cb, axis=0), np.median(cp, axis=0)
    S = np.cov(_trim(cb).T) + np.cov(_trim(cp).T) + 1e-6 * np.eye(3)
    wts = np.linalg.solve(S, mb - mp)
    cnr_c = _cnr(cb @ wts, cp @ wts)
    pb, pp = float(np.median(cb @ wts)), float(np.median(cp @ wts))
    ch = Channel(wts, cnr_g, cnr_c, False, plate_level=pp, bead_level=pb,
                 gray_levels=(float(np.median(gb)), float(np.median(gp))))
    if not cnr_c > MIN_GAIN * cnr_g:
        return gray, ch
    return _trial(gray, color, manifest, registration, ch, chroma_halved)


def retry_in_colour(gray, color, manifest: Manifest, registration, channel: "Channel", table,
                    chroma_halved: bool = False):
    """(image, Channel) of the colour trial run after grey was kept, or None.

    Below MIN_GAIN the trial is not worth its cost where grey's widths are tight; where
    they are not it is: the widths ``table`` (measure.table.WidthTable) measured on grey
    have a median station sd (``width_sd_mm``, the station's whole error) of at least
    RETRY_SD_MM and the projection raised the contrast-to-noise ratio RETRY_MIN_GAIN
    times. Then the same trial as :func:`bead_channel`'s decides (scatter, valid share,
    the widths' agreement with grey's). Dark plastic on the light grained plate under a
    phone (bench_realism, seed 0: gain 1.5, stations' sd 27-31 um in grey) scattered 36 um
    in grey and 28 in colour."""
    ch = channel
    if (ch.used or ch.weights is None or np.isfinite(ch.noise_color_mm)     # tried already
            or not ch.cnr_color > RETRY_MIN_GAIN * ch.cnr_gray):
        return None
    ok = np.asarray(table.valid, bool)
    if ok.sum() < 30 or not np.median(np.asarray(table.width_sd_mm, float)[ok]) >= RETRY_SD_MM:
        return None
    ch = dataclasses.replace(ch, retried=True)
    img, ch = _trial(gray, color, manifest, registration, ch, chroma_halved)
    return img, ch


def _trial(gray, color, manifest: Manifest, registration, ch: "Channel", chroma_halved: bool):
    """(image, Channel): the projection ``ch.weights`` built and measured against grey
    (:func:`bead_channel`'s trial); grey where it does not pay."""
    wts = np.asarray(ch.weights, np.float64)
    pp, pb = ch.plate_level, ch.bead_level
    gbm, gpm = ch.gray_levels
    # the projection is only built (a 12 MP float copy) once colour is a candidate
    proj = (color.astype(np.float32) / np.float32(255.0)) @ wts.astype(np.float32)
    if chroma_halved:
        luma = np.float32(wts.sum()) * gray.astype(np.float32)
        proj = luma + guided_filter(gray.astype(np.float32), proj - luma, CHROMA_RADIUS_PX, CHROMA_EPS)
        ch.chroma_restored = True
    img = (gpm + (proj - pp) * ((gbm - gpm) / (pb - pp))).astype(np.float32)
    # The plate's contrast is not the edges': where the colour is stored at half
    # resolution and coarsely (JPEG), the projection's edges are blurred and ringing, and
    # on the dark-plate render with every phenomenon the widths scattered 18 um instead
    # of 3. Decide on what matters: the widths' scatter between neighbouring stations.
    at = sample_points(manifest, ds_mm=2.0)
    tg, tc = (_noise_table(im, color, manifest, registration, at) for im in (gray, img))
    ch.noise_gray_mm, ch.valid_gray = _noise(tg), float(np.mean(tg.valid)) if len(tg) else 0.0
    ch.noise_color_mm, ch.valid_color = _noise(tc), float(np.mean(tc.valid)) if len(tc) else 0.0
    ch.width_disagreement_mm = width_disagreement(tg, tc, at.width_nominal_mm)
    ch.used = bool(ch.noise_color_mm < ch.noise_gray_mm / MIN_NOISE_GAIN
                   and ch.valid_color >= ch.valid_gray - 0.05
                   and not ch.width_disagreement_mm > MAX_WIDTH_DISAGREEMENT_MM)
    return (img if ch.used else gray), ch


def sample_colour(color, u, v) -> np.ndarray:
    """(N, 3) BGR of the uint8 picture ``color`` at pixels (u, v) (N,), bilinear, 0..1:
    the channels are sampled where asked instead of converting the whole picture."""
    return np.column_stack([ndimage.map_coordinates(np.ascontiguousarray(color[..., k]), [v, u], order=1,
                                                    output=np.float32) for k in range(3)]) / np.float32(255.0)


def guided_filter(guide, src, radius_px: int, eps: float):
    """``src`` (H, W) float32 filtered by (2) with ``guide`` (H, W) float32 (He et al. 2013)."""
    k = (2 * radius_px + 1, 2 * radius_px + 1)

    def box(x):
        return cv2.boxFilter(x, -1, k, normalize=True, borderType=cv2.BORDER_REFLECT)

    mg, ms = box(guide), box(src)
    a = (box(guide * src) - mg * ms) / (box(guide * guide) - mg * mg + np.float32(eps))
    b = ms - a * mg
    return box(a) * guide + box(b)


def width_noise(img, color, manifest: Manifest, registration, ds_mm: float = 2.0) -> tuple[float, float]:
    """(noise mm, valid fraction) of the widths measured on ``img`` at stations every
    ``ds_mm``: the robust sd of the difference between consecutive valid stations of a
    track over sqrt 2 (a bead's width changes in steps: the median absolute difference
    ignores them)."""
    t = _noise_table(img, color, manifest, registration, sample_points(manifest, ds_mm=ds_mm))
    return _noise(t), float(np.mean(t.valid)) if len(t) else 0.0


def width_disagreement(t_gray, t_color, width_nominal_mm) -> float:
    """Range (mm) over the commanded widths ``width_nominal_mm`` (mm, one per station) of the
    median difference between the widths measured on the projection and on grey at the
    same stations (both valid; >= 10 a width), NaN with fewer than two widths. A constant
    difference is the apparent width's business (measure/calibrate.py); one that changes
    with the width is an edge that one of the two images moves, and the scatter between
    neighbours does not show it."""
    both = t_gray.valid & t_color.valid
    wc = np.round(np.asarray(width_nominal_mm, float), 3)
    meds = [float(np.median((t_color.width_mm - t_gray.width_mm)[both & (wc == w)]))
            for w in np.unique(wc[both & np.isfinite(wc)]) if (both & (wc == w)).sum() >= 10]
    return max(meds) - min(meds) if len(meds) >= 2 else float("nan")


def _noise_table(img, color, manifest: Manifest, registration, at):
    """The widths measured on ``img`` at the stations ``at`` (patterns.manifest.Samples)."""
    from measure.widths import measure_widths

    return measure_widths(img, at, registration, manifest=manifest, color=color).table


def _noise(t) -> float:
    """:func:`width_noise`'s robust sd (mm) of the table ``t``."""
    d = []
    for k in np.unique(t.track):
        q = (t.track == k) & t.valid
        i = np.flatnonzero(q)
        j = i[:-1][np.diff(i) == 1]
        d.append(t.width_mm[j + 1] - t.width_mm[j])
    d = np.concatenate(d) if d else np.zeros(0)
    return 1.4826 * float(np.median(np.abs(d))) / np.sqrt(2) if len(d) >= 20 else float("nan")


def _cnr(bead, plate) -> float:
    """|median bead - median plate| / robust sd of the plate (MAD)."""
    sd = 1.4826 * np.median(np.abs(plate - np.median(plate))) + 1e-9
    return float(abs(np.median(bead) - np.median(plate)) / sd)


def _trim(x, q: float = 5.0):
    """Rows of ``x`` (N, 3) whose distance from the median lies below the (100 - q)th
    percentile: a string, logo or misregistered sample does not set the covariance."""
    d = np.linalg.norm(x - np.median(x, axis=0), axis=1)
    return x[d <= np.percentile(d, 100 - q)]


def _clear_of_beads(manifest: Manifest, pts, clearance_mm: float = 0.3) -> np.ndarray:
    """True where ``pts`` (mm) lie at least ``clearance_mm`` beyond every track's commanded edge."""
    from scipy.spatial import cKDTree

    from measure.widths import bead_points

    beads = bead_points(manifest)
    if beads is None:
        return np.ones(len(pts), bool)
    P, hw = beads[0], beads[3]
    nbs = cKDTree(P).query_ball_point(pts, float(hw.max()) + clearance_mm, return_sorted=False)
    cnt = np.fromiter((len(nb) for nb in nbs), int, len(pts))
    i = np.repeat(np.arange(len(pts)), cnt)
    nb = np.fromiter(itertools.chain.from_iterable(nbs), int, int(cnt.sum()))
    inside = np.hypot(*(P[nb] - pts[i]).T) < hw[nb] + clearance_mm
    ok = np.ones(len(pts), bool)
    ok[i[inside]] = False
    return ok
