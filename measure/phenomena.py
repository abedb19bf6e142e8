"""What real prints and real pictures do that the width measurement does not assume.

The width measurement (measure/edges.py) fits an erf edge pair: a box of plastic blurred
by a Gaussian. A bench that renders beads as exactly that (measure/render.py's default
"erf" footprint) scores the measurement on its own assumption, the *inverse crime*.
These phenomena, switched on by name, break each assumption in the way real prints and
cameras do, so ``make bench`` can show one row per phenomenon and one with all of them
(bench/bench_realism.py):

  profile      the bead's real cross-section instead of an erf footprint: the slicer's
               rounded rectangle (fit/geometry.py: flat top, semicircular flanks of
               radius h/2), seen from above as a hard footprint edge at +-w/2, with
               Lambertian shading of the flanks, I ~ a + (1 - a) cos(theta) (theta the
               surface slope), so flanks are darker than the crown
  translucent  natural/white PLA: light passes the thin flanks, opacity
               1 - exp(-t / l) with t the plastic thickness (Beer-Lambert) and
               l = 0.08-0.15 mm, so the apparent edge sits inside the physical one
               (implies ``profile``)
  glare        specular highlights of glossy plastic: Blinn-Phong (n . h)^p on the
               flanks facing the light (p = 40-80), saturating on light plastic; heading
               dependent, so a streak runs along one side of some beads only
  strings      plastic deposited on travel moves (ooze with no retraction), from the same
               physics as the beads (the virtual printer's extruded volume on each travel
               interval), drawn as round strings of diameter sqrt(4 V / (pi L))
  raster_gaps  every non-test track (fiducial rasters, labels, ruler, prime line) at the
               width its deposited volume gives (fit/geometry.py inverse) instead of the
               commanded width: neighbouring raster lines merge only as far as they reach
  grain        textured PEI: grains 0.1-0.3 mm of +-30 % brightness under the whole
               pattern (procedural, evaluated at every pixel's bed position)
  logos        printed text/logos on the plate under and between the pattern's tracks
  sparkle      textured PEI as a phone photographs it under a lamp: its grain's facets
               mirror the light, bright specks (``Realism.sparkle``) 0.1-0.3 mm across,
               where the plate is seen (through translucent flanks too). Its strength is
               set by the realdata photos (black textured plate): their valid widths
               scatter 45 and 22 um along the tracks (robust sd of second differences over
               1 mm), the 35 deg phone render 7 um without it and 47 um with it (55 um
               at 0.15 mm specks of 0.5 reflectance, 139 um at 0.8). Not in ``all``
               (EXTRA_PHENOMENA): every other bench figure was measured without it; its
               own bench row says what it does to the measurement.
  shadows      the lamp's cast shadows: a bead h tall, lit from elevation e, shades the
               plate beside it on the side away from the lamp out to h / tan(e) (flatbed:
               the scanner's lamp at 45 deg, 0.2-0.3 mm; phone: a lamp at 30-60 deg, up to
               0.5 mm), the more the more the bead lies across the light; a lamp of some
               size (a scanner's tube 4-12 deg, a room lamp 1-8 deg across its radius)
               leaves a penumbra that widens away from the bead. In shadow the surface
               keeps only the room's diffuse light (1 - ``shadow_depth`` of its
               brightness) and the plate's specks go out. A height field ray-marched
               toward the lamp (:func:`cast_shadow`); the measurement's edge model has no
               term for it. Not in ``all`` (EXTRA_PHENOMENA): its own bench rows say what
               it does first
  light        strongly uneven light: 40 % gradient, 45 % vignetting, a soft hotspot
  defocus      blur that grows across the image (depth of field of a tilted phone, a
               print not flat on the glass): sigma 0.6 -> 2.4 px
  jpeg         JPEG quality 70 (chroma subsampling, blocking at bead edges)
  irregular    the printed bead itself is not the smooth width the physics predicts:
               filament diameter drift (+-0.02 mm on 1.75 mm is +-2.3 % of the flow;
               one mm of filament lays ~30 mm of bead, so it wanders slowly) and the
               plate's texture under the bead (grain 0.1-0.3 mm) make it wander. Two
               smooth random width changes with *Gaussian* correlations (not the
               exponential one the fit's noise model assumes): sd ``irregular_rel`` x w
               over ``irregular_corr_mm`` (filament) plus sd ``irregular_mm`` over
               ``irregular_short_mm`` (texture). Part of the truth (the footprint).

``profile`` changes what a width *is* for the measurement: the true (physical) width is
the footprint, and a profile-aware picture has an apparent (half-contrast) width that
differs from it by an amount depending on colour, plate, light and translucency. That
difference is what measure/calibrate.py calibrates per scan.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PHENOMENA = ("profile", "translucent", "glare", "strings", "raster_gaps", "grain", "logos", "light",
             "defocus", "jpeg", "irregular")
#: Phenomena known by name but not part of "all" (see ``sparkle`` above).
EXTRA_PHENOMENA = ("sparkle", "shadows")
#: Phenomena that need the virtual printer's deposition (not only the stations' widths).
NEEDS_PHYSICS = ("strings", "raster_gaps")


@dataclass(frozen=True)
class Realism:
    """The phenomena to render, by name (see the module docstring), and their strengths.

    attenuation_mm    Beer-Lambert length l of translucent plastic (mm); None = seeded 0.08-0.15
    ambient           shading floor a of the flanks (fraction of the crown's brightness)
    glare_dn          peak specular highlight (DN, 0-255 scale) before clipping
    sparkle           brightest speck of ``sparkle``, a reflectance (0-1) added to the plate's
    shadow_depth      share of a surface's brightness a cast shadow takes (``shadows``);
                      None = seeded, 0.3-0.6 (a phone under a room lamp), 0.5 (a flatbed)
    lamp_deg          the lamp's angular radius (deg) for ``shadows``; None = seeded,
                      4-12 (a flatbed's tube), 1-8 (a phone's room lamp)
    jpeg_quality      quality used by ``jpeg``
    irregular_*       strengths of ``irregular`` (relative, mm) and their correlation lengths (mm)
    """

    enabled: frozenset = field(default_factory=frozenset)
    attenuation_mm: float | None = None
    ambient: float = 0.35
    glare_dn: float = 160.0
    sparkle: float = 0.3
    shadow_depth: float | None = None
    lamp_deg: float | None = None
    jpeg_quality: int = 70
    irregular_rel: float = 0.012
    irregular_corr_mm: float = 20.0
    irregular_mm: float = 0.003
    irregular_short_mm: float = 0.3

    def __post_init__(self):
        unknown = set(self.enabled) - set(PHENOMENA) - set(EXTRA_PHENOMENA)
        if unknown:
            raise ValueError(f"unknown phenomenon {sorted(unknown)[0]!r}; known: "
                             f"{', '.join(PHENOMENA + EXTRA_PHENOMENA)}")
        en = set(self.enabled)
        if {"translucent", "glare", "shadows"} & en:
            en.add("profile")   # all are properties of the bead's cross-section
        object.__setattr__(self, "enabled", frozenset(en))

    def __contains__(self, name: str) -> bool:
        return name in self.enabled

    @classmethod
    def parse(cls, text: str | None, camera_kind: str = "flatbed") -> "Realism":
        """Realism from text: "all", "none", "default" or a comma list ("profile,grain"; "all"
        may be one of its items: "all,sparkle"); default = all for a phone photo, none for a
        flatbed scan."""
        t = (text or "default").strip().lower()
        if t == "default":
            t = "all" if camera_kind == "phone" else "none"
        if t in ("none", ""):
            return cls()
        names = set()
        for p in (p.strip() for p in t.split(",")):
            names |= set(PHENOMENA) if p == "all" else ({p} if p else set())
        return cls(frozenset(names))

    @property
    def label(self) -> str:
        if not self.enabled:
            return "none"
        extra = [p for p in EXTRA_PHENOMENA if p in self.enabled]
        if set(PHENOMENA) <= self.enabled:
            return ",".join(["all"] + extra)
        return ",".join([p for p in PHENOMENA if p in self.enabled] + extra)


# =====================================================================================
# the bead itself: irregular width
# =====================================================================================
def irregular_widths(track: np.ndarray, s_mm: np.ndarray, width_mm: np.ndarray, rng, *, rel: float = 0.012,
                     corr_mm: float = 20.0, abs_mm: float = 0.003, short_mm: float = 0.3) -> np.ndarray:
    """``width_mm`` (mm) with a smooth random wander along each track:
    w' = max(w + rel w e1(s) + abs_mm e2(s), 0), e1, e2 unit-sd Gaussian-correlated
    processes (correlation exp(-d^2 / L^2), L = corr_mm and short_mm); zero widths stay
    zero (no bead)."""
    out = np.asarray(width_mm, dtype=float).copy()
    for tid in np.unique(track):
        i = np.flatnonzero(track == tid)
        s = s_mm[i]
        if len(i) == 0 or not np.isfinite(s).all():
            continue
        w = out[i]
        e1 = _smooth_noise(s, corr_mm, rng)
        e2 = _smooth_noise(s, short_mm, rng)
        bead = np.isfinite(w) & (w > 0)
        out[i] = np.where(bead, np.maximum(w + rel * w * e1 + abs_mm * e2, 0.0), w)
    return out


def _smooth_noise(s_mm: np.ndarray, corr_mm: float, rng) -> np.ndarray:
    """Unit-sd random process at ``s_mm`` with correlation exp(-d^2 / corr_mm^2): white
    noise on a grid of corr_mm / 10 smoothed by a Gaussian of sd corr_mm / 2."""
    from scipy.ndimage import gaussian_filter1d

    step = corr_mm / 10.0
    s0, s1 = float(np.min(s_mm)), float(np.max(s_mm))
    pad = 21
    grid = s0 + step * (np.arange(int(np.ceil((s1 - s0) / step)) + 1 + 2 * pad) - pad)
    e = gaussian_filter1d(rng.standard_normal(len(grid)), 5.0, mode="wrap")
    e /= max(float(np.std(e)), 1e-12)
    return np.interp(s_mm, grid, e)


# =====================================================================================
# deposition from the physics: raster widths and travel strings
# =====================================================================================
def deposit_pieces(manifest, vp, *, string_min_mm: float = 0.02, string_max_mm: float = 0.6,
                   min_speed_mm_s: float = 0.5):
    """Where the virtual printer put plastic that the station table does not describe.

    Returns (track_pieces, strings):
      track_pieces  {track id: [(seg (K, 4) mm, w (K, 2) mm)]} for every non-test track,
                    its width per timeline interval from the volume deposited there,
                    w = bead_width(V / L, h) (fit/geometry.py), pieces split where nothing
                    was deposited
      strings       [(seg (K, 4), d (K, 2), d_mean)] travel intervals with plastic, as round
                    strings of diameter d = sqrt(4 V / (pi L)) (mm); thinner than
                    ``string_min_mm`` is not drawn (it would not show at any dpi we use),
                    thicker than ``string_max_mm`` is a blob dragged along and capped there
    ``vp``: fit.virtual.VirtualPrint of ``manifest`` (its ``sim`` holds the per-interval
    extruded filament length).
    """
    from fit.geometry import bead_width_mm, filament_area_mm2

    tl = manifest.timeline
    if tl is None or vp is None or vp.sim is None:
        return {}, []
    out_mm = np.asarray(vp.sim.out_mm[0], dtype=float)           # filament mm per interval
    n = min(len(out_mm), len(tl) - 1)
    af = filament_area_mm2(float(manifest.printer.get("filament_diameter_mm", 1.75)))
    vol = np.maximum(out_mm[:n], 0.0) * af
    x, y = tl.x_mm, tl.y_mm
    L = np.hypot(np.diff(x[:n + 1]), np.diff(y[:n + 1]))
    dt = np.diff(tl.t_s[:n + 1])
    # a near-still interval (head slower than min_speed_mm_s) holds a blob, not a bead
    moving = (L > 1e-6) & (L > min_speed_mm_s * np.maximum(dt, 0.0))
    trk = tl.track[:n]
    same = trk == tl.track[1:n + 1]
    kinds = {tr.id: tr.kind for tr in manifest.tracks}
    tracks = {tr.id: tr for tr in manifest.tracks}
    heights = {tr.id: float(np.nanmean(tr.height_mm)) if len(tr.height_mm) else 0.2 for tr in manifest.tracks}
    track_pieces: dict[int, list] = {}
    strings = []

    ux = np.divide(np.diff(x[:n + 1]), L, out=np.zeros(n), where=L > 0)
    uy = np.divide(np.diff(y[:n + 1]), L, out=np.zeros(n), where=L > 0)

    def runs(mask):
        """Consecutive intervals, cut at turns > 60 deg (a marker's serpentine turns in
        two 90-degree steps) so that neighbouring lines of one raster add up where they
        touch (as in render._track_pieces)."""
        idx = np.flatnonzero(mask)
        if len(idx) == 0:
            return []
        turn = ux[idx[1:]] * ux[idx[:-1]] + uy[idx[1:]] * uy[idx[:-1]] < np.cos(np.deg2rad(60.0))
        cut = np.flatnonzero((np.diff(idx) > 1) | turn) + 1
        return np.split(idx, cut)

    for tid, kind in kinds.items():
        if kind == "test":
            continue
        h = max(heights[tid], 0.05)
        # a blob dragged along would read as an arbitrarily wide line: capped at twice
        # the widest command
        m = (trk == tid) & same & moving
        w_int = np.zeros(n)
        w_cap = 2.0 * max(float(np.max(tracks[tid].width_mm, initial=0.0)), 0.5)
        w_int[m] = np.minimum(bead_width_mm(vol[m] / L[m], h), w_cap)
        for r in runs(m & (w_int > 0.02)):
            seg, ww = _chain(x, y, r, w_int)
            track_pieces.setdefault(tid, []).append((seg, ww))
        track_pieces.setdefault(tid, [])
    travel = (trk == -1) & moving
    d_int = np.zeros(n)
    d_int[travel] = np.minimum(np.sqrt(4.0 * vol[travel] / (np.pi * L[travel])), string_max_mm)
    for r in runs(travel & (d_int >= string_min_mm)):
        seg, dd = _chain(x, y, r, d_int)
        strings.append((seg, dd, float(np.mean(d_int[r]))))
    return track_pieces, strings


def _chain(x, y, idx, w_int):
    """Segments (K, 4) and end widths (K, 2) of consecutive intervals ``idx``; widths are
    per interval, made continuous by averaging at the shared nodes."""
    a = np.column_stack([x[idx], y[idx]])
    b = np.column_stack([x[idx + 1], y[idx + 1]])
    w = w_int[idx]
    wn = np.concatenate([[w[0]], 0.5 * (w[:-1] + w[1:]), [w[-1]]])   # node widths
    return np.hstack([a, b]), np.column_stack([wn[:-1], wn[1:]])


# =====================================================================================
# plate and picture
# =====================================================================================
def pei_grain(Xc, Yc, seed: int, cell_mm: float = 0.18, contrast: float = 0.30) -> np.ndarray:
    """Multiplicative brightness (H, W) of textured PEI at bed positions (mm).

    Value noise on a lattice of ``cell_mm`` (grains 0.1-0.3 mm after the smooth
    interpolation), hashed from the integer lattice coordinates so it is a property of
    the plate (the same grain under every camera), plus a finer octave at cell/2.
    Mean 1, values in 1 +- contrast.
    """
    out = np.zeros(Xc.shape, np.float32)
    for octave, amp in ((1.0, 0.7), (0.5, 0.3)):
        c = cell_mm * octave
        gx, gy = Xc / c, Yc / c
        ix, iy = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
        fx, fy = (gx - ix).astype(np.float32), (gy - iy).astype(np.float32)
        sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)     # smoothstep
        v00 = _hash01(ix, iy, seed + int(octave * 100))
        v10 = _hash01(ix + 1, iy, seed + int(octave * 100))
        v01 = _hash01(ix, iy + 1, seed + int(octave * 100))
        v11 = _hash01(ix + 1, iy + 1, seed + int(octave * 100))
        v = (v00 * (1 - sx) + v10 * sx) * (1 - sy) + (v01 * (1 - sx) + v11 * sx) * sy
        out += amp * (2.0 * v - 1.0)
    return 1.0 + contrast * out


def pei_sparkle(Xc, Yc, seed: int, cell_mm: float = 0.25) -> np.ndarray:
    """Specular specks of textured PEI (H, W), 0..1, at bed positions (mm): the facets of
    its grain that mirror the lamp into the camera. The grain's value noise on its own
    lattice (``cell_mm``), kept where it is high: s = clip((g - 1) / 0.5, 0, 1)^1.5 with
    g = pei_grain(contrast 1), so about half the plate catches some light."""
    g = pei_grain(Xc, Yc, seed=seed + 7919, cell_mm=cell_mm, contrast=1.0)
    return np.clip((g - 1.0) / 0.5, 0.0, 1.0) ** 1.5


def _hash01(ix, iy, seed: int) -> np.ndarray:
    """Uniform [0, 1) per integer lattice point (a 64-bit integer hash; no global state)."""
    h = (ix * np.int64(73856093)) ^ (iy * np.int64(19349663)) ^ np.int64(seed * 83492791 + 1)
    h = (h ^ (h >> 13)) * np.int64(1274126177)
    h = h ^ (h >> 16)
    return ((h & 0xFFFFFF).astype(np.float32) / np.float32(0x1000000))


def varying_blur(img: np.ndarray, sigma_map: np.ndarray, levels: int = 5) -> np.ndarray:
    """Gaussian blur whose sigma (px) varies over the image (depth of field).

    The image is blurred at ``levels`` sigmas spanning the map's range and each pixel
    interpolates linearly between the two levels that bracket its sigma.
    """
    import cv2

    lo, hi = float(sigma_map.min()), float(sigma_map.max())
    sig = np.linspace(lo, hi, levels) if hi > lo else np.array([lo])
    stack = [cv2.GaussianBlur(img, (0, 0), max(s, 1e-3)) if s > 0.05 else img for s in sig]
    if len(sig) == 1:
        return stack[0]
    pos = (sigma_map - lo) / (hi - lo) * (levels - 1)
    k = np.clip(np.floor(pos).astype(int), 0, levels - 2)
    f = (pos - k).astype(np.float32)
    out = np.zeros_like(img)
    for j in range(levels - 1):
        m = k == j
        if not m.any():
            continue
        fj = f[m][:, None] if img.ndim == 3 else f[m]
        out[m] = stack[j][m] * (1 - fj) + stack[j + 1][m] * fj
    return out


def defocus_map(W: int, H: int, rng, lo_px: float = 0.6, hi_px: float = 2.4) -> np.ndarray:
    """Blur sigma (px) rising linearly across the image in a seeded direction."""
    a = rng.uniform(0, 2 * np.pi)
    u = np.linspace(-1, 1, W, dtype=np.float32)[None, :]
    v = np.linspace(-1, 1, H, dtype=np.float32)[:, None]
    t = (np.cos(a) * u + np.sin(a) * v) / (abs(np.cos(a)) + abs(np.sin(a)))
    return (lo_px + (hi_px - lo_px) * 0.5 * (t + 1.0)).astype(np.float32)


def light_vector(camera_kind: str, rng) -> np.ndarray:
    """Unit vector toward the lamp (bed frame, z up).

    Flatbed: the lamp shines from +-y at ~45 deg, the sensor looks straight down. Phone:
    a window or ceiling light at 30-60 deg elevation, seeded azimuth.
    """
    if camera_kind == "flatbed":
        return np.array([0.0, np.sin(np.deg2rad(45)) * (1 if rng.uniform() < 0.5 else -1), np.cos(np.deg2rad(45))])
    el, az = np.deg2rad(rng.uniform(30, 60)), rng.uniform(0, 2 * np.pi)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def half_vector(light: np.ndarray) -> np.ndarray:
    """Blinn-Phong half vector (unit, bed frame) between the light and the view, the
    camera looking down (the view's small x/y part at a phone's tilt is neglected: the
    highlight's position moves by a fraction of a bead, its side does not)."""
    hv = np.asarray(light, float) + np.array([0.0, 0.0, 1.0])
    return hv / np.linalg.norm(hv)


def cast_shadow(height_mm: np.ndarray, step_px: np.ndarray, light: np.ndarray, *, step_mm: float,
                lamp_deg: float = 0.0) -> np.ndarray:
    """Share of each pixel (0-1) in the shadow the height field casts under a lamp.

    height_mm   (H, W) plastic thickness above the plate (mm) at each pixel
    step_px     (H, W, 2) image offset (px) of one ``step_mm`` on the bed toward the lamp
                at each pixel (the camera's Jacobian times the lamp's horizontal direction)
    light       unit vector toward the lamp's centre (bed frame, z up)
    lamp_deg    the lamp's angular radius as seen from the plate (deg): 0 a point

    The horizon toward the lamp: a point at height z sees the surface d mm toward the lamp
    under the angle atan((z(d) - z) / d); the highest such angle over d = step_mm, 2 step_mm,
    ... up to the tallest point's reach (ray marching) hides every part of the lamp below
    it. A lamp seen as a band of elevations e +- lamp_deg (a scanner's tube, a window) is
    hidden by the share clip((horizon - (e - lamp_deg)) / (2 lamp_deg), 0, 1): a penumbra
    that widens with the distance from the bead, as real shadows do.
    """
    import cv2

    l = np.asarray(light, float)
    horiz = float(np.hypot(l[0], l[1]))
    top = float(np.max(height_mm)) if height_mm.size else 0.0
    if horiz < 1e-6 or top <= 0.0:
        return np.zeros(height_mm.shape, np.float32)
    e = np.arctan2(l[2], horiz)
    a = np.deg2rad(max(lamp_deg, 0.05))
    low = max(e - a, np.deg2rad(2.0))
    n = int(np.ceil(top / np.tan(low) / step_mm))
    H, W = height_mm.shape
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(H, dtype=np.float32)[:, None]
    z = height_mm.astype(np.float32)
    tan_h = np.full((H, W), -np.inf, np.float32)
    for k in range(1, n + 1):
        ahead = cv2.remap(z, u + k * step_px[..., 0], v + k * step_px[..., 1], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        np.maximum(tan_h, (ahead - z) / np.float32(k * step_mm), out=tan_h)
    return np.clip((np.arctan(tan_h) - low) / np.float32(e + a - low), 0.0, 1.0)
