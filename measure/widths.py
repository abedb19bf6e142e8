"""Bead width along every test track, in mm, with a one-sigma uncertainty per station.

At each station of ``patterns.manifest.sample_points`` (every 0.25 mm) the image is sampled
along the track normal *in bed millimetres* (points X + t n, t in mm, mapped through the
registration, bilinear ``scipy.ndimage.map_coordinates``): the local Jacobian of the
mapping is thereby applied exactly, and the fitted edge-pair width (measure.edges) is in
mm directly; each profile averages STRIP_LINES lines over the station's STRIP_MM of track
(despeckled along the track first: :func:`_despeckle`)
and stops NEIGHBOUR_CLEAR_SIGMAS blurs short of the nearest other bead's edge. Two passes:
first with the blur free; then the blur, which is a property of the optics and therefore
smooth over the image, is fitted as a plane s_px(u, v) over the wide beads (w > 4 s, where
w and s separate) and held fixed, which removes the w-s-A degeneracy of narrow beads.

Uncertainty: the scaled covariance of the fit (measure.edges) times
sqrt(1 / min(1, step_px)) because profile samples closer than a pixel are not independent,
times ``SD_CALIBRATION`` (set on renders so that ~68 % of true errors fall within
width_sd_mm, bench/bench_measure.py), plus ``SD_FLOOR_PX`` in quadrature (edge model error);
then per scan scaled and floored until it explains the scatter of the widths themselves
about their smooth course (measure/station_sd.py :func:`calibrated_sd`).

Glare: where a specular streak brightens one flank, the edge pair is refitted with the
streak on either side and the better of the two replaces the plain fit when it explains
significantly more (measure/streaks.py). Such stations stay valid (``glare_streak`` says
which).

Stations are flagged, never silently used (valid = 0 and a reason; the rules that judge a
station by its track's other stations are in measure/station_rules.py): ``edge`` (profile leaves
the image), ``crossing`` / ``neighbour`` (another track touches the bead or sits inside
the profile window, from the manifest geometry), ``label`` / ``fiducial`` / ``ruler``
(the same for printed furniture), ``glare`` (over SATURATED_SHARE_MAX of the bead's pixels
saturated: its crest clipped; or no edge pair where saturated pixels say something bright
is there, or saturated pixels beside the bead: a bright logo in its window), ``missing``
(no bead: width 0), ``faint`` (no bead found where one would not stand out of the
profile's noise either: ``DETECTABLE_SNR``; not data), ``fit`` (failed or implausible
fit, or far noisier than the rest of its track: a logo, scratch or string in the profile),
``blob`` (far wider than commanded, or wider than the track's bead where it coasts),
``end`` (within half a bead of a bead end, where the profile cuts the round end cap: a
track's ends and where inside it the extrusion stops or starts).
"""
from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage, special
from scipy.spatial import cKDTree

from measure import edges
from measure.station_rules import (beside_absence, dropouts, enclosed, isolated, oblique, steep,
                                   unfit)
from measure.station_sd import calibrated_sd, registration_place_sd, scatter_factor, slope_sd
from measure.shadows import SHADOW_DOUBT_MM, Shadows, with_shadows
from measure.streaks import with_glare_streaks
from measure.table import WidthTable
from patterns.manifest import Manifest, Samples, sample_points

#: A station is flagged ``glare`` only where more than this share of its bead's profile
#: samples is saturated (in any channel). A clipped crest widens the apparent width; a few
#: saturated pixels (a speck of glare) do not matter. Measured on flatbed renders (600
#: dpi, profile + glare, opaque and translucent, brightened 1-1.5x; the error relative to
#: the same track's unsaturated stations): saturated share <= 0.1: -5.3 to +0.1 um (the
#: streaks' own stations), 0.1-0.35: -3.8 to +3.1 um, 0.35-0.6: +0.8 to +8.9 um, > 0.6
#: (the whole crest): +3.5 to +12 um. Before, one saturated pixel flagged the station:
#: 34-47 % of those renders at 1-1.15x and 7-10 % of the realdata photos' stations
#: (saturated shares 0.05-0.3), whose widths agree with their valid neighbours' within
#: 2-11 um (median) at the same scatter.
SATURATED_SHARE_MAX = 0.35

#: Multiplies the fit sd; from bench_measure coverage on renders (68 % target).
SD_CALIBRATION = 0.85
#: Edge-model error added in quadrature (px), e.g. rounding of the bead shoulder. (0.03
#: before the profiles averaged STRIP_LINES lines: with the strip the flatbed render's
#: errors fell to 1.2 um and 92 % of them lay within a 0.03 px floor's sd; 0.015 puts the
#: flat, phone and translucent renders at 67-68 %; 0.010 since the strips are despeckled
#: (:func:`_despeckle`): the flat render's errors fell 1.2 -> 0.75 um RMS and 84 % lay
#: within 0.015 px; now 72 %, the phone renders 66 and 65 % either way.)
SD_FLOOR_PX = 0.010
#: Profile step (px) aimed for; the fit is insensitive below ~0.5 px.
STEP_PX = 0.5
#: Fewest background samples each side (mm) needed for a trustworthy edge fit.
MIN_BACKGROUND_MM = 0.2
#: Widths (mm) the profile window is sized for are capped here: third-party G-code can
#: command absurd widths (a restore move with a little XY motion reads as a 20 mm bead).
MAX_WINDOW_WIDTH_MM = 3.0
#: Where a track coasts (commanded width 0), a bead wider than this times its reference
#: width (+ 0.05 mm) is not its ooze but a blob (measure_widths)
BLOB_COAST_FACTOR = 1.2
#: Where the head stood still inside a track (the manifest's timeline), a station within
#: 1 mm of it wider than the bead 1-6 mm around by more than this (mm) is a blob
#: (:func:`_at_dwell`)
DWELL_BLOB_MM = 0.05
#: A track's blur takes its own level about the picture's blur plane from at least this
#: many of its stations in the blur-free pass (:func:`_learn_blur_plane`).
TRACK_BLUR_MIN_STATIONS = 20
#: The blur plane's own error is read in this many square cells across the picture's
#: stations, from cells with this many wide beads or more (:func:`_relative_spread`).
BLUR_SPREAD_CELLS = 20
BLUR_SPREAD_PER_CELL = 15
#: The blur is learned on stations at least this far (mm) from a bead end (measure_widths).
BLUR_END_CLEAR_MM = 1.5
#: A station is flagged "background" when the plate at either end of its profile window
#: lies more than this fraction of the scan's full bead contrast away from the plate's
#: level there (a smooth surface over the bed, :func:`plate_surface`): a light logo or a
#: sticker under or beside the bead. Against a bright background the bead's shaded flanks
#: stand out dark and the width the scan's reference calibrated no longer holds: on a
#: virtual RetractTest (600 dpi flatbed, every phenomenon, seed 0) the 0.3 mm line read
#: 0.17-0.23 mm for 3-4 mm at a time across a plate logo, with sds of 20-40 um. Those
#: stations lay 0.5-1.07 from the plate's level; over four scenes without a logo under a track
#: (flatbed and phone, dark and light plates, every phenomenon) the largest was 0.42, the
#: 99.9th percentile 0.07-0.19 (their medians 0.01-0.03). A real phone photo's plate is
#: not that even: on realdata StartStopTestPLA1 (translucent PLA, contrast 0.24, a grained
#: plate with a glossy sheen) the median was 0.24 and 0.3 flagged 3,035 stations scattered
#: over the plain plate; the bar is therefore also BACKGROUND_SPREAD times the scan's own
#: median (there 0.97: the flagged stations lie on the plate's FLASHFORGE and CAUTION print).
BACKGROUND_SHIFT = 0.3
BACKGROUND_SPREAD = 4.0
#: A bead whose fitted centre lies more than this fraction of its width from the line its
#: track's beads lie on (their median centre) does not cover that line (at 0.5 the line
#: misses it): it is something else, flagged "fit". A plate logo's top edge beside the
#: drain of the virtual RetractTest (seed 0) passed as a valid 0.5 mm bead 0.50 mm off the
#: path where 5 um of ooze was; the printed beads of that scan and of its StartStopTest lay
#: within 0.04 of their widths.
OFF_PATH = 0.5
#: A bead whose amplitude is below this fraction of the track's typical one is missing.
MISSING_FRACTION = 0.3
#: ... but only where a bead would be seen: its expected amplitude (``a_ref``) at least this
#: many times the profile's own noise (fit RMS), so that a present bead at half its typical
#: contrast still clears the 3-noise bar. Below it the station is ``faint``: neither a
#: width nor an absence can be read, and the fit must not take it for a zero-width bead.
#: Renders: printed valid stations 7.8-15 (1st-50th percentile) on the light-plate JPEG,
#: >= 56 on the others. Real phone photo (StartStopTestPLA1: translucent white PLA over a
#: black grained plate with white logos) 2.6-8.5 (5-95 %), and 2,676 stations (21 %) with
#: ratio 1.7-5.3 had been called missing where the beads are plainly there.
DETECTABLE_SNR = 6.0
#: The noise it is compared with is the larger of the station's fit RMS and its median over
#: +- this (mm) of the track: one station's RMS is itself noisy, and a fit that absorbed a
#: grain feature leaves a low one (beads in grain of half their contrast, synthetic: printed
#: stations called missing 15 % by the old rule, 3.5 % on the own RMS, 3.3 % on the larger).
DETECTABLE_HALF_MM = 1.0
#: ... and below this fraction of the scan's typical one at its commanded width, so that a
#: whole track that never printed is missing too (a light gradient of 40 % leaves 0.6).
SCAN_AMPLITUDE_FRACTION = 0.5
#: ... and where the bead's colour differs from the plate's (measure/contrast.py), when the
#: colour at its centre lies less than this fraction of erf(w / 2 sqrt2 s) of the way from
#: the plate's to the beads'. Light-plate render: never-printed stations that passed in grey
#: 0.00-0.13, printed ones >= 0.56 (0.25 mm) and >= 0.80 (0.5-1.6 mm).
PRESENCE_FRACTION = 0.35
#: Each station's profile averages this many lines spread over this length (mm) along the
#: track: the stations' spacing, so that every pixel row along a track is used once.
STRIP_LINES = 5
STRIP_MM = 0.25
#: :func:`_despeckle`'s element along the track (mm): longer than the plate's grain as a
#: phone blurs it (specks 0.1-0.3 mm, 0.4-0.5 mm seen through 0.16 mm of blur).
SPECK_MM = 0.45
#: Correlation of neighbouring stations' own width errors in a despeckled run (the
#: element spans two stations, so both are filtered from shared pixels). Measured on
#: renders with truth (session 38; lag-1 correlation of error / sd): 0.45 on `make demo`'s
#: 600 dpi flatbed scan (0.07 without the despeckling; lags 2, 3: 0.11, 0.02), 0.35 on
#: bench_realism's erf flatbed, 0.48 / 0.68 with every phenomenon on a dark / light plate
#: (of which 0.17 / 0.3 is shared beyond 2 mm), 0.77-0.80 on the 400 dpi test renders
#: (lags 2, 3: 0.38-0.45, 0.16-0.22). It varies with the dpi and the picture, so the fit
#: estimates it per scan (``noise.meas_corr``, fit/likelihood.py) and starts from this;
#: the table says which stations are linked (``width_corr_prev``).
NEIGHBOUR_CORR = 0.45
#: A profile's samples stop this many blur sigmas short of the nearest other bead's edge
#: (its erfc tail there is 0.7 %) ...
NEIGHBOUR_CLEAR_SIGMAS = 3.0
#: ... but reach at least this many blur sigmas beyond the bead's own edge; a station whose
#: neighbour is closer than NEIGHBOUR_FLAG_SIGMAS blurs is flagged "neighbour" (the
#: neighbour's edge then brings 2 % of the contrast into the window's end: 0.5 erfc(sqrt2)).
MIN_CLEAR_SIGMAS = 2.0
NEIGHBOUR_FLAG_SIGMAS = 4.0


@dataclass
class WidthMeasurement:
    """All that :func:`measure_widths` found; ``table`` is the widths CSV.

    centre_mm  fitted bead centre offset along the normal (mm, + = along n)
    blur_mm    edge blur s (mm); amplitude: signed bead contrast (intensity units)
    nx, ny     unit normal used at each station (bed); window_mm half-length of the profile
    glare_streak    True where the edge pair was fitted with a glare streak on one flank
    plain_width_mm  the plain edge pair's width there (the same as the table elsewhere)
    sd_scale, sd_floor_mm   how the edge fits' sd was scaled and floored (mm) into
                    ``width_sd_mm`` by the scan's own scatter (:func:`calibrated_sd`)
    place_sd_mm     the registration's along-track sd of each station (mm; :func:`slope_sd`
                    carries it into ``width_sd_mm`` where the width changes along the track)
    blur_rel_sd     how far the blur the widths were read with may be off, relative to it
                    (:func:`_relative_spread`; NaN where the blur was fitted free)
    width_per_rel_blur_mm  how far each width moves per unit relative error of that blur
                    (mm; measure/edges.py width_per_blur x the blur; None if fitted free)
    shadows         measure.shadows.Shadows: where the lamp's shadow was fitted beside the
                    bead, and the scan's ShadowModel (``shadows.model``; None: none seen)
    lamp_sd_mm      the part of ``width_sd_mm`` for the lamp's shading of beads across it
                    (mm; None without shadows)
    """

    table: WidthTable
    centre_mm: np.ndarray
    blur_mm: np.ndarray
    amplitude: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    window_mm: np.ndarray
    blur_plane_px: tuple
    glare_streak: np.ndarray | None = None
    plain_width_mm: np.ndarray | None = None
    sd_scale: float = 1.0
    sd_floor_mm: float = 0.0
    place_sd_mm: np.ndarray | None = None
    blur_rel_sd: float = float("nan")
    width_per_rel_blur_mm: np.ndarray | None = None
    shadows: Shadows | None = None
    lamp_sd_mm: np.ndarray | None = None


def widths(image, manifest_or_samples, registration, *, manifest: Manifest | None = None,
           color=None) -> WidthTable:
    """Widths table of a registered image (see :func:`measure_widths`)."""
    return measure_widths(image, manifest_or_samples, registration, manifest=manifest, color=color).table


def measure_widths(image, manifest_or_samples, registration, *, manifest: Manifest | None = None,
                   color=None, ds_mm: float = 0.25, fix_blur: bool = True,
                   blur_prior_px=None, colour_axis=None, shadows=None) -> WidthMeasurement:
    """Measure the bead width at every station.

    image                gray float (H, W), 0..1
    manifest_or_samples  a Manifest (stations every ``ds_mm`` along its test tracks) or Samples
    registration         measure.register.Registration of this image
    manifest             the manifest, for the neighbour/label flags, when Samples are given
    color                uint8 (H, W, 3) image for glare detection (saturation in any channel)
    blur_prior_px        (a, b, c) blur plane (px) from elsewhere in the picture, used when
                         the stations lie on one line (the width reference: _blur_plane)
    colour_axis          measure.contrast.Channel: where its colour axis tells bead from
                         plate, a station whose centre has the plate's colour is missing
    shadows              the scan's measure.shadows.ShadowModel from its test tracks (False:
                         they showed none); None: these stations decide (measure/shadows.py)
    """
    if isinstance(manifest_or_samples, Manifest):
        manifest = manifest_or_samples
        smp = sample_points(manifest, ds_mm=ds_mm)
    else:
        smp = manifest_or_samples
    gray = np.asarray(image, dtype=np.float32)
    n = len(smp)
    Hh, W = gray.shape
    xy = np.column_stack([smp.x_mm, smp.y_mm])
    nrm = np.column_stack([smp.nx, smp.ny])
    w_nom = np.asarray(smp.width_nominal_mm, float)
    w_ref = _reference_width(smp, w_nom)
    flag = np.array([""] * n, dtype=object)

    # -- geometry: clearance to other tracks and furniture sets window and flags -------
    gap, gap_kind = _clearance(manifest, smp, w_ref) if manifest is not None else (
        np.full(n, np.inf), np.array([""] * n, dtype=object))
    bg = np.clip(gap - 0.05, MIN_BACKGROUND_MM, np.maximum(0.6, w_ref))
    half = w_ref / 2 + bg
    touching = gap < 0.05
    crowded = ~touching & (gap - 0.05 < MIN_BACKGROUND_MM)
    flag[touching] = np.where(gap_kind[touching] == "test", "crossing", gap_kind[touching])
    flag[crowded] = np.where(gap_kind[crowded] == "test", "neighbour", gap_kind[crowded])
    flag[(flag == "prime") | (flag == "other")] = "crossing"
    if manifest is not None:
        near_f = _near_furniture(manifest, xy, half)
        flag[(flag == "") & (near_f != "")] = near_f[(flag == "") & (near_f != "")]

    # -- sample the profiles ---------------------------------------------------------
    eps = 0.05
    uv_c = registration.project(xy)
    ppm_n = np.hypot(*(registration.project(xy + eps * nrm) - registration.project(xy - eps * nrm)).T) / (2 * eps)
    m = int(np.clip(np.ceil(np.percentile(2 * half * ppm_n, 95) / STEP_PX) + 1, 24, 240)) if n else 24
    grid = np.linspace(-1.0, 1.0, m)
    t = half[:, None] * grid[None, :]
    pts = xy[:, None, :] + t[..., None] * nrm[:, None, :]
    uv = registration.project(pts.reshape(-1, 2)).reshape(n, m, 2)
    inside = (uv[..., 0] >= 0) & (uv[..., 0] <= W - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= Hh - 1)
    y = _strip_profiles(gray, registration, t, smp, manifest, W, Hh, STRIP_LINES)
    out = inside.mean(axis=1) < 0.999
    flag[out] = "edge"
    step_px = (2 * half / (m - 1)) * ppm_n

    # -- fit: blur free, then blur from the plane over wide beads ----------------------
    pol = float(getattr(registration, "polarity", 1.0))
    s0 = 1.0 / np.maximum(ppm_n, 1e-9)
    p0 = edges.initial_guess(t, y, pol, s0)
    height = np.asarray(smp.height_mm, float)
    # the blur is learned where a bead was commanded (a fit to the bare plate has any blur:
    # the RetractTest's coasting halves, all on one side of the picture, tilted the plane by
    # 1 px across it) and away from its ends (a round cap or a blob is crossed at a slant)
    steady = (flag == "") & ~(w_nom <= 0)
    if manifest is not None:
        steady &= ~_near_bead_ends(manifest, smp, BLUR_END_CLEAR_MM)
    plane, track_blur, blur_rel_sd = _learn_blur_plane(t, y, p0, inside, steady, uv_c, ppm_n, height, nrm,
                                                       prior=blur_prior_px, w_ref=w_ref, gap=gap,
                                                       track=smp.track, shadows=shadows) if fix_blur else (None, None, np.nan)
    if plane is not None:
        p1 = p0.copy()
        p1[:, 5] = np.clip(plane[0] + plane[1] * uv_c[:, 0] + plane[2] * uv_c[:, 1] + track_blur, 0.3,
                           None) / ppm_n
        wts = (inside & _clear_of_neighbour(t, w_ref, gap, p1[:, 5])).astype(float)
        fit = edges.fit_profiles(t, y, p1, fixed_s=True, weights=wts)
    else:
        wts = inside.astype(float)
        fit = edges.fit_profiles(t, y, p0, weights=wts)
    plain_w = fit.width.copy()
    fit, shade = with_shadows(t, y, fit, wts, height, nrm, model=shadows)
    fit, streak = with_glare_streaks(t, y, fit, wts, height, nrm, shadows=shade)
    # presence, noise and misfit are judged on the fit with its contrast free (a prior on
    # the contrast would read a bead where there is none, as a narrow one of full contrast)
    free_fit, amp_lam = fit, np.zeros(n)
    if plane is not None:
        fit, amp_lam = _with_scan_contrast(t, y, fit, wts, smp, pol, (flag == "") & ~streak
                                           & (shade.side == 0 if shade is not None else True))

    w = fit.width.copy()
    c = fit.centre.copy()
    sd = fit.width_sd * np.sqrt(1.0 / np.minimum(1.0, step_px)) * SD_CALIBRATION
    sd = np.sqrt(sd ** 2 + (SD_FLOOR_PX / ppm_n) ** 2)

    # -- flags from the fit ---------------------------------------------------------------
    amp = pol * free_fit.amplitude
    # A line that never printed has plate texture for its own "typical" amplitude: what a
    # bead of its width looks like comes from the whole scan too (a never-printed line on a
    # grained plate with logos passed 20 % of its stations as beads against its own median).
    # A box of width w blurred by s keeps erf(w / (2 sqrt2 s)) of the full contrast A0.
    good = fit.ok & (flag == "")
    with np.errstate(invalid="ignore", divide="ignore"):
        ef = special.erf(np.clip(np.where(np.isfinite(w_nom), w_nom, w_ref), 1e-3, None)
                         / (2 * np.sqrt(2) * np.maximum(fit.params[:, 5], 1e-4)))
        a0 = float(np.median(amp[good] / ef[good])) if good.any() else 0.0
    a_ref = np.maximum(_track_median(smp.track, amp, good), SCAN_AMPLITUDE_FRACTION * a0 * ef)
    noise = free_fit.rms
    missing = (amp < MISSING_FRACTION * a_ref) | (amp < 3 * noise) | (w < 1.0 / ppm_n)
    if color is not None and colour_axis is not None and colour_axis.tells_presence:
        # plate grain can pass for a bead in grey, not in colour (measure/contrast.py)
        # the width the station claims counts too: a grey logo's 1.2 mm stroke across a
        # coasting ring of the virtual StartStopTest (commanded 0: any colour passed) read
        # as a valid 1.2 mm bead with the plate's colour at its centre (likeness 0-0.07)
        claimed = np.maximum(np.where(np.isfinite(w_nom), w_nom, w_ref), np.where(np.isfinite(w), w, 0.0))
        ef_c = special.erf(np.clip(claimed, 1e-3, None) / (2 * np.sqrt(2) * np.maximum(fit.params[:, 5], 1e-4)))
        at = xy + np.clip(np.nan_to_num(c), -half, half)[:, None] * nrm
        missing |= colour_axis.bead_likeness(color, registration.project(at)) < PRESENCE_FRACTION * ef_c
    if color is not None:
        sat_px = _saturated_samples(color, uv)
        cc = np.nan_to_num(c)
        sat = _share_within(sat_px, t, cc, w / 2, inside) > SATURATED_SHARE_MAX
        glare = sat & (np.mean(sat) < 0.5)     # a whole saturated print is exposure, not glare
        # saturated pixels on the plate beside the bead are a bright thing that is not this
        # bead (the plate's white logo under realdata StartStopTestPLA1's beads: with them
        # in the window the edge pair took a letter's edge, 0.98-1.56 mm for 0.75 mm beads);
        # only where the fit looked (a neighbour's clipped crest is not in its window)
        beside = (sat_px & (wts > 0) & (np.abs(t - cc[:, None]) > (w / 2 + 2 * fit.params[:, 5])[:, None])).any(axis=1)
        # saturated pixels where the bead was commanded are something bright, not the bare
        # plate: a slow blob wider than the profile's window (realdata SpStartStopTest2's
        # 1 mm/s draws, 1.2-1.4 mm for 0.56 commanded) leaves no edge pair and would read
        # as "no bead"; neither its width nor its absence is known
        bright = _share_within(sat_px, t, np.zeros(n), np.where(np.isfinite(w_nom), w_nom, w_ref) / 2, inside) > 0
        beside &= np.mean(beside) < 0.5       # a light plate over-exposed as a whole is exposure
        flag[(flag == "") & (glare | beside | (missing & bright))] = "glare"
    # neither a width nor an absence is read against a background that is not the plate
    plain = fit.ok & (flag == "") & ~missing
    # the plate at the window's ends: the edge pair's background line where it found a
    # bead; where it found none, its background is whatever a box of no contrast left
    # (on the virtual StartStopTest's coasting rings, 600 stations "off the plate"), and
    # the window's own median is the plate
    ends = fit.params[:, [0]] + fit.params[:, [1]] * np.column_stack([half, -half])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        own = np.nanmedian(np.where(wts > 0, y, np.nan), axis=1)
    ends = np.where(missing[:, None], own[:, None], ends)
    off_plate = background_shift(smp.x_mm, smp.y_mm, ends, amp, plain)
    typical = float(np.nanmedian(off_plate[plain])) if np.isfinite(off_plate[plain]).any() else 0.0
    flag[(flag == "") & fit.ok & (off_plate > max(BACKGROUND_SHIFT, BACKGROUND_SPREAD * typical))] = "background"
    free = flag == ""
    seeable = a_ref >= DETECTABLE_SNR * np.maximum(noise, _along_track_median(smp.track, smp.s_mm, noise,
                                                                             DETECTABLE_HALF_MM))
    flag[free & missing & seeable] = "missing"
    flag[dropouts(smp.track, smp.s_mm, flag == "missing", free & ~missing)] = "dropout"
    flag[free & missing & ~seeable] = "faint"
    # A fit much noisier than its peers' typical one has something else in the profile
    # (plate logo, scratch, dust, a stray string): flag it rather than trust a wide sd.
    # Peers: the stations of its track at its commanded width. A wide bead's rounded,
    # shaded crown misfits the edge pair more than a narrow bead's does: against the whole
    # track, 77 % of the 1.6 mm stations of the phone render were flagged.
    peers = np.asarray(smp.track, np.int64) * 1000 + np.where(
        np.isfinite(w_nom), np.round(np.nan_to_num(w_nom) / 0.05), 999).astype(np.int64)
    sd_ref = _group_median(peers, sd, fit.ok & (flag == ""), smp.track)
    rel_rms = free_fit.rms / np.maximum(np.abs(amp), 1e-6)
    rms_ref = _group_median(peers, rel_rms, fit.ok & (flag == ""), smp.track)
    # the line the track's beads lie on, not the commanded one: a real printer places a
    # track's beads off its commanded line (realdata StartStopTestPLA1: up to 0.24 mm, the
    # beads within 0.018 mm of their own line; measure/placement.py)
    own_line = _track_median(smp.track, c, fit.ok & (flag == "") & ~missing & np.isfinite(c))
    failed = (~fit.ok | ~np.isfinite(sd) | (np.abs(c) > half - 0.5 * w) | (np.abs(c - own_line) > OFF_PATH * w)
              | (w > 2 * half - 2 * MIN_BACKGROUND_MM * 0.5)
              | unfit(np.where(np.isfinite(w_nom), w_nom, w_ref), sd, sd_ref, rel_rms, rms_ref))
    flag[(flag == "") & failed] = "fit"
    # the window cannot stay clear of a neighbour closer than NEIGHBOUR_FLAG_SIGMAS blurs:
    # its blurred edge (>= 2 % of the contrast at the window's end) would bias the width
    flag[(flag == "") & (gap < NEIGHBOUR_FLAG_SIGMAS * fit.params[:, 5])] = "neighbour"
    if manifest is not None:
        flag[(flag == "") & _at_end(manifest, smp, w, w_ref, fit.params[:, 5])] = "end"
        flag[(flag == "") & _at_dwell(manifest, smp, w, fit.params[:, 5])] = "blob"
    # "faint" is not absence: no bead would be seen there either way
    # ... and what made a dropout lies in its neighbours' strips and despeckling windows too:
    # on the phone photos they read the 0.25 mm beads 5-11 um narrower than the rest, with
    # a 5-6 um wider scatter
    flag[(flag == "") & beside_absence(smp.track, smp.s_mm, np.isin(flag, ("missing", "dropout")))] = "end"
    blob = w > np.maximum(2.2 * w_ref, w_ref + 0.6)
    # where the track coasts (commanded 0) its own ooze is narrower than the bead that
    # stopped; something wider is a blob reaching in (the virtual start-stop rings' restore
    # blobs read 0.77-1.07 mm up to 2.3 mm before the draw they restore for, on 0.3-0.8 mm
    # rings)
    blob |= (np.nan_to_num(w_nom) <= 0) & (w > BLOB_COAST_FACTOR * w_ref + 0.05)
    flag[(flag == "") & blob] = "blob"
    flag[(flag == "") & oblique(smp.track, smp.s_mm, c, flag == "")] = "oblique"
    flag[(flag == "") & isolated(smp.track, smp.s_mm, flag)] = "isolated"
    is_missing = flag == "missing"
    w[is_missing] = 0.0
    sd[is_missing] = 1.0 / ppm_n[is_missing]    # a bead narrower than ~1 px would not be seen
    c[is_missing] = 0.0
    valid = flag == ""
    # two sds (measure/table.py): the whole error, and the part each station has on its
    # own, which the fit's white term takes (its wobble takes what neighbours share). One
    # factor on the own part overstates the error of the noisiest stations (0.5 x on
    # bench_realism's all-phenomena scenes): the own part is no larger than the whole.
    rho = neighbour_corr(smp, t)
    sd_own = sd * scatter_factor(smp.track, w, sd, valid, rho)
    sd, sd_scale, sd_floor = calibrated_sd(smp.track, smp.s_mm, w, sd, valid)
    # steep beyond the widths' noise, as calibrated (a real photo's widths scatter more than
    # the edge fit says: on realdata StartStopTestPLA1 the fit's sds let 12.7 % of the valid
    # stations through as steep, the calibrated ones 4.9 %, real jumps of 0.3 mm in 0.25 mm)
    gone = np.isin(flag, ("missing", "faint"))
    is_steep = valid & steep(smp.track, smp.s_mm, np.where(gone, 0.0, w), np.where(gone, 0.0, sd))
    flag[is_steep] = "steep"
    inside = valid & ~is_steep & enclosed(smp.track, smp.s_mm, flag, w)
    flag[inside] = "isolated"
    valid = valid & ~is_steep & ~inside
    sd_own = np.minimum(sd_own, sd)
    # where the width changes along the track, not knowing where along it the station is
    # is an error in width too (the registration's along-track sd x the slope)
    tangent = np.column_stack([-nrm[:, 1], nrm[:, 0]])
    place_sd = registration_place_sd(registration, xy, tangent)
    by_slope = slope_sd(smp.track, smp.s_mm, w, sd, valid, place_sd)
    sd, sd_own = np.hypot(sd, by_slope), np.hypot(sd_own, by_slope)
    # the width was read with the blur held at the picture's plane, which is itself known
    # only to its cells' spread about it (_relative_spread), and a bead not much wider than
    # the blur moves with it (measure/edges.py width_per_blur: dw/ds -4.8 at w = 2 s).
    # On bench_realism's phone photo at 35 deg (Bowden, seed 1; true width / blur binned)
    # the errors' sd was 31 um at w/s 1.5-2 and 19 um at 2-2.5 against 9-12 um above 3,
    # error / sd 1.7 and 2.0 there; with this term 1.06 and 1.31. The truth's model fitted
    # with scan_bias (bench_realism calibrated_by_fit) read the width offset -105 um for
    # -46, Kb 0.43, w_sat 1.56 mm, tau 0.774 s (truth 1.0, 0.8 mm, 0.8 s), the narrow
    # beads' error weighed as if known; with it -81 um, 0.61, 1.12 mm, 0.796 s.
    per_rel_blur = None
    if plane is not None:
        per_rel_blur = np.where(w > 0, edges.width_per_blur(t, fit.params, wts, amp_lam=amp_lam) * fit.params[:, 5], np.nan)
    if per_rel_blur is not None and np.isfinite(blur_rel_sd):
        by_blur = np.abs(np.nan_to_num(per_rel_blur)) * blur_rel_sd
        sd, sd_own = np.hypot(sd, by_blur), np.hypot(sd_own, by_blur)
    by_lamp = None
    if shade is not None and shade.model is not None:
        # the lamp that casts the shadows shades the beads across it too (the flank away from
        # it in its own shadow): what the shelf leaves is shared along a track, so it is in
        # the whole sd, not the own (measure/shadows.py SHADOW_DOUBT_MM), until the heading
        # levels take it out (measure/pipeline.py)
        by_lamp = np.where(w > 0, SHADOW_DOUBT_MM * np.abs(nrm @ shade.model.away), 0.0)
        sd = np.hypot(sd, by_lamp)
    sd_own = np.where(np.isfinite(sd_own), sd_own, np.nan)
    w = np.where(np.isfinite(w), w, np.nan)
    sd = np.where(np.isfinite(sd), sd, np.nan)
    table = WidthTable(track=smp.track, s_mm=smp.s_mm, x_mm=smp.x_mm, y_mm=smp.y_mm, t_s=smp.t_s,
                       width_mm=w, width_sd_mm=sd, valid=valid, flag=flag, width_sd_own_mm=sd_own,
                       width_corr_prev=rho)
    return WidthMeasurement(table=table, centre_mm=c, blur_mm=fit.params[:, 5], amplitude=free_fit.amplitude,
                            nx=nrm[:, 0], ny=nrm[:, 1], window_mm=half,
                            blur_plane_px=tuple(plane) if plane is not None else (), glare_streak=streak,
                            plain_width_mm=np.where(streak & (w > 0), plain_w, w),
                            sd_scale=sd_scale, sd_floor_mm=sd_floor, place_sd_mm=place_sd,
                            blur_rel_sd=float(blur_rel_sd), width_per_rel_blur_mm=per_rel_blur, shadows=shade,
                            lamp_sd_mm=by_lamp)


def background_shift(x_mm, y_mm, plate_ends, amp, ok) -> np.ndarray:
    """How far the plate at the ends of each station's profile window lies from the plate's
    level there, as a fraction of the scan's full bead contrast (N,):
    max_k |plate_ends[:, k] - P(x, y)| / A0, P the plate's level over the bed
    (:func:`plate_surface` through the ends' mean at the ``ok`` stations), A0 the median
    bead contrast ``amp`` of those. ``plate_ends`` (N, 2): the plate's level (intensity) at
    the window's two ends. NaN where it cannot be said."""
    n = len(x_mm)
    out = np.full(n, np.nan)
    if ok.sum() < 20:
        return out
    mid = plate_ends.mean(axis=1)
    level = plate_surface(np.asarray(x_mm, float), np.asarray(y_mm, float), mid, ok)
    a0 = float(np.median(amp[ok]))
    if not a0 > 0:
        return out
    with np.errstate(invalid="ignore"):
        return np.abs(plate_ends - level[:, None]).max(axis=1) / a0


#: Beads at least this many blurs wide show their contrast apart from their width
#: (:func:`scan_contrast`): the edge pair's A and w separate there.
CONTRAST_WIDE_BLURS = 4.0
#: The plastic's contrast is known to no better than this share of itself at any station
#: (:func:`scan_contrast`'s floor: the light, the plate and the plastic's own shine vary
#: over the picture more than a quadratic holds).
CONTRAST_SD_FLOOR = 0.03


def scan_contrast(x_mm, y_mm, amp, width_mm, blur_mm, ok, amp_sd=None, track=None, s_mm=None):
    """The plastic's contrast against the plate at every station (N,; intensity, > 0), read
    on the scan's wide beads; the relative sd of a bead's true contrast about it; and how
    many times the edge fits' own variance of the contrast (``amp_sd``, (N,)) its noise
    is (>= 1; 1 without ``amp_sd``, ``track`` and ``s_mm``). None where fewer than 18
    wide beads.

    One plastic on one plate keeps one contrast, changed over the picture only by the
    light (a gradient, vignetting: smooth): :func:`plate_surface`'s robust quadratic in bed
    x, y through the contrast ``amp`` of the ``ok`` stations at least CONTRAST_WIDE_BLURS
    blurs wide, where the edge pair tells A from w. The noise is read as the widths' is
    (measure/station_sd.py :func:`~measure.station_sd.calibrated_sd`: second differences
    along each track, which a contrast changing from bead to bead or over the bed does
    not enter); what the wide beads' robust spread (1.4826 MAD) about the surface holds
    beyond that noise is their true contrast's spread, at least CONTRAST_SD_FLOOR.
    """
    amp = np.asarray(amp, float)
    wide = ok & np.isfinite(amp) & (amp > 0) & (np.asarray(width_mm, float) > CONTRAST_WIDE_BLURS * blur_mm)
    if wide.sum() < 18:
        return None
    level = plate_surface(np.asarray(x_mm, float), np.asarray(y_mm, float), amp, wide)
    if not np.all(np.isfinite(level[wide])) or np.any(level[wide] <= 0):
        return None
    r = amp[wide] / level[wide]
    spread = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    over, noise = 1.0, 0.0
    if amp_sd is not None and track is not None and s_mm is not None:
        rel_sd = np.where(wide, np.asarray(amp_sd, float) / level, np.nan)
        fine = wide & np.isfinite(rel_sd) & (rel_sd > 0)
        if fine.sum() >= 18:
            full, _, _ = calibrated_sd(np.asarray(track), np.asarray(s_mm, float), amp / level,
                                       np.where(fine, rel_sd, np.nan), fine)
            over = float(np.median((full[fine] / rel_sd[fine]) ** 2))
            noise = float(np.median(full[fine]))
    true_spread = np.sqrt(max(spread ** 2 - noise ** 2, 0.0))
    return level, max(CONTRAST_SD_FLOOR, true_spread), over


def _with_scan_contrast(t, y, fit, wts, smp: Samples, pol: float, rows):
    """``fit`` (blur held) refitted at the ``rows`` with the plastic's contrast as a prior
    (measure/edges.py fit_profiles ``amp_prior``; :func:`scan_contrast`): the MAP of the
    edge pair given what the scan's wide beads say its contrast is; and the prior's lam
    at every station (0 where not refitted).

    Under ~3 blurs a bead shows its area A w better than A or w: a narrow bead that reads
    10 % low in contrast reads ~10 % wide. On bench_realism's phone photo of dark beads on
    the light plate (35 deg, direct drive, seed 3, blur 0.17 mm) the 0.25 mm beads' fitted
    contrast scattered 37 % about the wide beads' and their width error 84 um with it
    (correlation -0.86); the wide beads' contrast held the narrow ones' to 20 um.

    The prior weighs against the profile as their errors do: lam = k rms^2 / (rel A_ref)^2,
    rms^2 the profile's noise variance per sample, and k how much more the wide beads'
    contrast scatters along their tracks than their fits' sds say (:func:`scan_contrast`):
    a profile's samples share their errors (despeckled strips, JPEG blocks, plate grain), so
    its sum of squares overstates what it knows of A (k 27 on that photo, 14 on the dark
    plate's Bowden seed 3; with k = 1 the narrow beads' contrast kept 17 % of scatter and
    their width error 61 um). k read from the contrast's whole spread about the surface
    instead took the beads' own differences for noise: on the foreign printer's rendered
    probe (bench/foreign_printer.py, a bowl-shaped bed under translucent beads: contrast
    spread 54 %) k 299, and its beads under 0.5 mm read 17 um of scatter for 10.

    Only beads under CONTRAST_WIDE_BLURS blurs are refitted: wider, the edge pair tells A
    from w, and a bead's own contrast stands.
    """
    ok = rows & fit.ok & np.isfinite(fit.params[:, 4])
    narrow = fit.width < CONTRAST_WIDE_BLURS * fit.params[:, 5]
    got = scan_contrast(smp.x_mm, smp.y_mm, pol * fit.amplitude, fit.width, fit.params[:, 5], ok,
                        amp_sd=fit.sd[:, 2], track=smp.track, s_mm=smp.s_mm)
    lam_all = np.zeros(len(fit.rms))
    if got is None:
        return fit, lam_all
    level, rel, over = got
    idx = np.flatnonzero(ok & narrow & np.isfinite(level) & (level > 0) & (fit.rms > 0))
    if not len(idx):
        return fit, lam_all
    lam = over * fit.rms[idx] ** 2 / (rel * level[idx]) ** 2
    # started where the bead keeps the area it was read with at the scan's contrast: from
    # the free fit, a narrow bead read at half its contrast could slide to "no bead" at
    # the window's end (1 of 200 in a test)
    start = fit.params[idx, :6].copy()
    start[:, 4] *= np.clip(pol * start[:, 2] / level[idx], 0.5, 2.0)
    start[:, 2] = pol * level[idx]
    re = edges.fit_profiles(t[idx], y[idx], start, fixed_s=True, weights=wts[idx],
                            amp_prior=(pol * level[idx], lam))
    params, sd, rms, good = (a.copy() for a in (fit.params, fit.sd, fit.rms, fit.ok))
    keep = idx[re.ok]
    params[keep, :6], sd[keep, :6] = re.params[re.ok], re.sd[re.ok]
    lam_all[keep] = lam[re.ok]
    return edges.ProfileFit(params, sd, rms, good), lam_all


def plate_surface(x_mm, y_mm, values, ok, passes: int = 4) -> np.ndarray:
    """A quadratic in bed x, y (mm) through ``values`` at the ``ok`` stations, refitted
    ``passes`` times without those beyond 4 robust sds (a logo or a sticker is a minority
    of the stations; uneven light and vignetting are smooth): the plate's level beside the
    beads (N,)."""
    keep = ok & np.isfinite(values)
    if keep.sum() < 18:          # too few for a quadratic: the plate's median level
        return np.full(len(values), float(np.median(values[keep])) if keep.any() else np.nan)
    # the first fit without what stands far out of the levels' spread: a least-squares
    # quadratic through a logo on 13 % of the stations bends to it, and its residuals'
    # spread then keeps the logo in every refit
    q25, med, q75 = np.percentile(values[keep], [25, 50, 75])
    keep &= np.abs(values - med) <= 3 * max(q75 - q25, 1e-4)
    if keep.sum() < 18:
        return np.full(len(values), float(med))
    xc, yc = x_mm - np.median(x_mm[keep]), y_mm - np.median(y_mm[keep])
    A = np.column_stack([np.ones_like(xc), xc, yc, xc * xc, xc * yc, yc * yc])
    coef = np.zeros(A.shape[1])
    for _ in range(passes):
        if keep.sum() < A.shape[1] * 3:
            break
        coef = np.linalg.lstsq(A[keep], values[keep], rcond=None)[0]
        r = values - A @ coef
        mad = 1.4826 * float(np.median(np.abs(r[keep])))
        keep = ok & np.isfinite(values) & (np.abs(r) < 4 * max(mad, 1e-4))
    return A @ coef


def _strip_profiles(gray, registration, t, smp: Samples, manifest, W, H, lines: int):
    """Profiles (N, M) at offsets ``t`` (N, M) (mm) along the normals of the stations ``smp``,
    each the mean of ``lines`` profiles spread evenly over STRIP_MM of the track around
    the station, each across the track where it lies (``manifest`` given: the track's own
    polyline; else straight along the station's tangent), after :func:`_despeckle`. One
    line per station uses one pixel row in six at 600 dpi; five cut the widths' scatter by
    10-15 % (light plate, PNG: 13.5 -> 8.6 um RMS; flatbed with every phenomenon 10.5 -> 9.2 um)."""
    n, m = t.shape
    nrm = np.column_stack([smp.nx, smp.ny])
    xy = np.column_stack([smp.x_mm, smp.y_mm])
    tracks = {tr.id: tr for tr in manifest.tracks} if manifest is not None else {}
    stack = np.empty((lines, n, m), np.float32)
    for j, f in enumerate((np.arange(lines) + 0.5) / lines - 0.5):
        pos, nf = xy + f * STRIP_MM * np.column_stack([nrm[:, 1], -nrm[:, 0]]), nrm
        if f != 0.0 and tracks:
            # a straight line along the tangent leaves a curved bead: on a spiral's inner
            # turns the averaged centres moved inwards, and the automatic pose's ICP step
            # with them (phone renders: true pose error 13 -> 17, 14 -> 21 um; following
            # the track: 11, 13 um, against 13, 14 from one line per station)
            pos, nf = pos.copy(), nrm.copy()
            for k in np.unique(smp.track):
                tr = tracks.get(int(k))
                if tr is None or tr.length_mm <= 0:
                    continue
                i = np.flatnonzero(smp.track == k)
                p_, tan = tr.at(np.clip(smp.s_mm[i] + f * STRIP_MM, 0.0, tr.length_mm))
                pos[i], nf[i] = p_, np.column_stack([-tan[:, 1], tan[:, 0]])
        uv = registration.project((pos[:, None, :] + t[..., None] * nf[:, None, :]).reshape(-1, 2))
        stack[j] = ndimage.map_coordinates(gray, [np.clip(uv[:, 1], 0, H - 1), np.clip(uv[:, 0], 0, W - 1)],
                                           order=1, mode="nearest").reshape(n, m)
    return _despeckle(stack, smp, t).mean(axis=0, dtype=np.float64)


def _despeckle(stack, smp: Samples, t, speck_mm: float | None = None):
    """The lines ``stack`` (L, N, M) of the stations' strips, each offset t's sequence along
    the track replaced by the mean of its open-close and its close-open (flat element
    ``speck_mm`` long; Serra's alternating filters, "Image Analysis and Mathematical
    Morphology", 1982).

    Stations every STRIP_MM along a track tile it with their L lines each (one every
    STRIP_MM / L mm), so a run of stations with the same offsets ``t`` is one sequence along
    the track per offset. An opening removes what is brighter than both sides along the
    track over less than ``speck_mm``, a closing what is darker (a bright speck of the plate
    beside a bright bead, a dark pit on it; either order of bead and plate): the grain that
    sparkles under a lamp, which the mean of the lines only dilutes. A sequence that only
    rises or falls along the track (a bead widening or narrowing, an edge that moves) is
    left as it is: both keep monotone sequences. Open-close alone leans to the lower
    envelope of fine noise (an edge's aliasing ripple: flatbed render at 400 dpi, -1.7 um
    width bias), close-open to the upper; their mean to neither (+0.04 um). What they
    flatten is the bead's own bumps and necks shorter than ``speck_mm``, below the scales
    the fit reads. Runs shorter than two elements are left alone."""
    lines, n, m = stack.shape
    k = _speck_samples(lines, speck_mm)
    runs = _despeckled_runs(smp, t, lines, speck_mm)
    if not runs:
        return stack.copy()
    # Each end continued by its own value: a run that starts on its maximum (an end blob) or
    # minimum stays monotone there; mirrored, the end became a peak the opening cut (the
    # demo's start blob read 1.05 for 1.19 mm, and the blob's reach shrank by a station).
    # The four filters reach 4 (k // 2) <= 2k samples, so the runs, each continued 2k
    # samples by its end values, are filtered in one array as if each were alone (a 12 MP
    # photo has ~2,000 runs: 0.7 s filtered one by one, 0.2 s in one).
    base = stack.transpose(1, 0, 2).reshape(n * lines, m)      # station by station, its lines
    pad = 2 * k
    rows, keep = [], []
    for idx in runs:
        r = (idx[:, None] * lines + np.arange(lines)).ravel()
        rows.append(np.concatenate([np.full(pad, r[0]), r, np.full(pad, r[-1])]))
        keep.append(np.r_[np.zeros(pad, bool), np.ones(len(r), bool), np.zeros(pad, bool)])
    rows, keep = np.concatenate(rows), np.concatenate(keep)
    seq = np.ascontiguousarray(base[rows])
    seq = 0.5 * (_close(_open(seq, k), k) + _open(_close(seq, k), k))
    out = base.copy()
    out[rows[keep]] = seq[keep]
    return out.reshape(n, lines, m).transpose(1, 0, 2)


def _speck_samples(lines: int, speck_mm: float | None = None) -> int:
    """:func:`_despeckle`'s element in samples along the track (STRIP_MM / ``lines`` apart)."""
    return int(round((SPECK_MM if speck_mm is None else speck_mm) / (STRIP_MM / lines)))


def _despeckled_runs(smp: Samples, t, lines: int, speck_mm: float | None = None) -> list[np.ndarray]:
    """The runs :func:`_despeckle` filters, each an index array of stations in order along
    the track: consecutive stations (STRIP_MM apart) of one track with the same offsets ``t``,
    at least two elements long."""
    n = len(smp.track)
    k = _speck_samples(lines, speck_mm)
    if k < 2 or n < 2:
        return []
    order = np.lexsort((smp.s_mm, smp.track))
    tr, ss, to = np.asarray(smp.track)[order], np.asarray(smp.s_mm)[order], t[order]
    brk = np.ones(n, bool)
    brk[1:] = ((tr[1:] != tr[:-1]) | (np.abs(np.diff(ss) - STRIP_MM) > 1e-6)
               | np.any(np.abs(to[1:] - to[:-1]) > 1e-9, axis=1))
    starts = np.flatnonzero(brk)
    return [order[a:b] for a, b in zip(starts, np.append(starts[1:], n)) if (b - a) * lines >= 2 * k]


def neighbour_corr(smp: Samples, t, lines: int = STRIP_LINES, speck_mm: float | None = None) -> np.ndarray:
    """Per station (n,): the correlation of its own width error with the previous
    station's on its track (the table's ``width_corr_prev``): NEIGHBOUR_CORR where
    :func:`_despeckle` filtered both in one run, 0 elsewhere."""
    out = np.zeros(len(smp.track))
    for idx in _despeckled_runs(smp, t, lines, speck_mm):
        out[idx[1:]] = NEIGHBOUR_CORR
    return out


def _open(a, k):
    """Grey opening of the 2-D array ``a`` along axis 0 with a flat element of ``k`` samples
    (OpenCV's: ~10x scipy.ndimage's min/max filters along axis 0 of a tall array; the same
    values, window [i - k//2, i + (k-1)//2], ends continued by their own values)."""
    return _morph(_morph(a, k, cv2.erode), k, cv2.dilate)


def _close(a, k):
    """Grey closing of ``a`` along axis 0 (see :func:`_open`)."""
    return _morph(_morph(a, k, cv2.dilate), k, cv2.erode)


def _morph(a, k, op):
    return op(a, np.ones((k, 1), np.uint8), borderType=cv2.BORDER_REPLICATE)


def _clear_of_neighbour(t, w_ref, gap, blur_mm):
    """(N, M) mask of profile samples at least NEIGHBOUR_CLEAR_SIGMAS blurs short of the
    nearest other bead's edge (at |t| = w/2 + gap), but never closer to this bead's edge
    than MIN_CLEAR_SIGMAS blurs. The window reaches 0.05 mm short of the neighbour, which is
    clear of it at a flatbed's blur (~0.04 mm); at a phone's (0.15-0.2 mm) the neighbour's
    blurred edge lifts the background at the window's ends by up to 40 % of the contrast,
    and the 1.6 mm beads read 25 um narrow where the blur was largest."""
    lim = np.maximum(w_ref / 2 + gap - NEIGHBOUR_CLEAR_SIGMAS * blur_mm, w_ref / 2 + MIN_CLEAR_SIGMAS * blur_mm)
    return np.abs(t) <= np.where(np.isfinite(gap), lim, np.inf)[:, None]


def _learn_blur_plane(t, y, p0, inside, usable, uv_c, ppm_n, height_mm, normals, prior=None, w_ref=None,
                      gap=None, track=None, shadows=None):
    """The blur plane s_px(u, v) from a blur-free pass over (up to 3000 of) the stations
    (``prior``: a plane from elsewhere in the image, see :func:`_blur_plane`); with the
    beads' widths ``w_ref`` and clearances ``gap`` (mm), a second pass keeps the profiles
    clear of the neighbours' edges at the blur the first found (:func:`_clear_of_neighbour`)."""
    n = len(t)
    sub = np.arange(n) if n <= 3000 else np.random.default_rng(0).choice(n, 3000, replace=False)
    wts = inside[sub]
    fit1 = edges.fit_profiles(t[sub], y[sub], p0[sub], weights=wts.astype(float))
    if gap is not None and np.isfinite(gap[sub]).any():
        s1 = np.where(fit1.ok, fit1.params[:, 5], p0[sub, 5])
        wts = wts & _clear_of_neighbour(t[sub], w_ref[sub], gap[sub], np.clip(s1, 0, 0.5))
        fit1 = edges.fit_profiles(t[sub], y[sub], np.where(fit1.ok[:, None], fit1.params, p0[sub]),
                                  weights=wts.astype(float))
    # A glare streak makes its edge look sharp (the prime line, in glare all along on a
    # flatbed, read s 20 % small and the bead 10 um wide): the blur is read with it modelled.
    # So does the lamp's shadow beside the other edge make it look soft.
    fit1, sh1 = with_shadows(t[sub], y[sub], fit1, wts.astype(float), height_mm[sub], normals[sub], fixed_s=False,
                             model=shadows)
    fit1, _ = with_glare_streaks(t[sub], y[sub], fit1, wts.astype(float), height_mm[sub], normals[sub],
                                  fixed_s=False, shadows=sh1)
    blur_px = fit1.params[:, 5] * ppm_n[sub]
    ok1 = fit1.ok & usable[sub] & (fit1.width > 4 * fit1.params[:, 5])
    plane = _blur_plane(uv_c[sub], blur_px, fit1, ok=ok1, prior=prior)
    if plane is None:
        return None, np.zeros(n), float("nan")
    level = plane[0] + plane[1] * uv_c[sub, 0] + plane[2] * uv_c[sub, 1]
    if track is None:
        return plane, np.zeros(n), _relative_spread(blur_px, level, ok1, uv_c[sub])
    # each track's own level about the plane: the edge of a taller bead is softer (its
    # rounded flank), and a blur too small reads the bead wide (seed 001's RetractTest,
    # heights 0.10-0.35 mm line by line: +0.3 ... +9.7 um with one plane)
    r = blur_px - (plane[0] + plane[1] * uv_c[sub, 0] + plane[2] * uv_c[sub, 1])
    off = np.zeros(n)
    trk = np.asarray(track)[sub]
    for tid in np.unique(trk[ok1]):
        k = ok1 & (trk == tid) & np.isfinite(r)
        if k.sum() >= TRACK_BLUR_MIN_STATIONS:
            off[np.asarray(track) == tid] = float(np.median(r[k]))
    return plane, off, _relative_spread(blur_px, level + off[sub], ok1, uv_c[sub])


def _relative_spread(blur_px, model_px, ok, uv, cells: int = BLUR_SPREAD_CELLS,
                     per_cell: int = BLUR_SPREAD_PER_CELL) -> float:
    """How far the blur the widths are measured with is off where it is applied, relative
    to it: the robust sd (1.4826 MAD) of the blur-free pass's median relative misfit in
    square cells (``cells`` across the stations' extent in the picture, ``per_cell`` wide
    beads ``ok`` or more each, at least 8 such cells), less what each cell's median keeps of
    its fits' own noise: the plane's error, which changes slowly over the picture. Else the
    stations' robust sd (>= 20), else NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = blur_px / model_px - 1.0
    use = ok & np.isfinite(rel) & (model_px > 0)
    if use.sum() < 20:
        return float("nan")
    rel, uv = rel[use], np.asarray(uv, float)[use]
    size = max(float(np.ptp(uv, axis=0).max()) / cells, 1.0)
    key = np.floor(uv[:, 0] / size) * 1e6 + np.floor(uv[:, 1] / size)
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    full = np.flatnonzero(counts >= per_cell)
    spread = float(1.4826 * np.median(np.abs(rel - np.median(rel))))
    if len(full) < 8:
        return spread
    meds = np.array([np.median(rel[inv == i]) for i in full])
    within = np.concatenate([rel[inv == i] - m for i, m in zip(full, meds)])
    # a cell's median still holds its stations' noise: sd 1.2533 sigma / sqrt(n)
    noise_var = np.mean((1.2533 * 1.4826 * np.median(np.abs(within))) ** 2 / counts[full])
    between = (1.4826 * np.median(np.abs(meds - np.median(meds)))) ** 2
    return float(np.sqrt(max(between - noise_var, 0.0)))


def bead_ends_mm(track, step_mm: float = 0.05) -> np.ndarray:
    """Arc lengths (mm) where ``track``'s bead ends: its two ends and, inside it, every
    place its commanded width goes to or from zero (a line that stops extruding and
    coasts, a restore before the next draw: seed 001's StartStopTest and RetractTest)."""
    L = float(track.length_mm)
    ends = [0.0, L]
    if L > 2 * step_mm:
        ss = np.arange(0.0, L + 1e-9, step_mm)
        on = np.asarray(track.interp("width_mm", ss), float) > 1e-6
        k = np.flatnonzero(on[1:] != on[:-1])
        ends += list(0.5 * (ss[k] + ss[k + 1]))
    return np.unique(np.round(ends, 9))


def _near_bead_ends(manifest, smp, reach_mm: float) -> np.ndarray:
    """Stations within ``reach_mm`` of a bead end of their track (:func:`bead_ends_mm`)."""
    out = np.zeros(len(smp), bool)
    for tid in np.unique(smp.track):
        on = np.flatnonzero(smp.track == tid)
        ends = bead_ends_mm(manifest.track(int(tid)))
        d = np.min(np.abs(smp.s_mm[on][:, None] - ends[None, :]), axis=1)
        out[on] = d < reach_mm
    return out


def _at_end(manifest, smp, w_meas, w_ref, blur_mm=None):
    """Stations within half a bead (+ 0.1 mm) of a bead end (:func:`bead_ends_mm`: a
    track's ends and where inside it the extrusion stops or starts), where the profile
    cuts the round end cap (a chord, not the width). "Bead" = the widest measured within
    3 mm of that end, since end blobs are common (ooze, restore).

    A blob (radius R, centred on the end) wider than the bead (width w, the median 1-3 mm
    before the end) lifts the widths of the stations whose profile sees it: the profile
    spans STRIP_MM of track and sees the blob's edge through the blur (``blur_mm``, sd),
    so the reach is also STRIP_MM / 2 + 2 blurs + sqrt(R^2 - (w/2)^2) (where the blob's
    chord is wider than the bead). The foreign printer's probe (bench/foreign_printer.py):
    the drain after a track's last move left a 0.8 mm blob, and the station 0.5 mm before
    the end, outside the reach of half the bead + 0.1 mm (0.48 mm), read 0.18-0.20 mm too
    wide on two tracks. Inside a track, the virtual printer's start-stop rings (direct
    drive, pa + nonlinear at the truth) read 60-100 um wide 0.25 mm after the prime line's
    stop and 0.1-0.9 mm wide up to 2.3 mm before the restore blob of the next draw, where
    the bead is commanded 0: 61 um RMS over the valid stations at the truth, and `--model
    auto` named no effect."""
    out = np.zeros(len(smp), bool)
    wm = np.where(np.isfinite(w_meas), w_meas, 0.0)
    blur = np.zeros(len(smp)) if blur_mm is None else np.nan_to_num(np.asarray(blur_mm, float))
    for tid in np.unique(smp.track):
        on = np.flatnonzero(smp.track == tid)
        s = smp.s_mm[on]
        for e in bead_ends_mm(manifest.track(int(tid))):
            d = np.abs(s - e)
            near = d < 3.0
            if near.any():
                widest = max(float(np.max(wm[on][near])), float(np.max(w_ref[on][near])))
                reach = widest / 2 + 0.1
                before = near & (d >= 1.0) & (wm[on] > 0)
                if before.any():
                    r_blob = float(np.max(wm[on][near & (d < 1.0)], initial=0.0)) / 2
                    w_bead = float(np.median(wm[on][before]))
                    if r_blob > w_bead / 2:
                        reach = max(reach, STRIP_MM / 2 + 2 * float(np.median(blur[on][near]))
                                    + float(np.sqrt(r_blob ** 2 - (w_bead / 2) ** 2)))
                out[on[near & (d < reach)]] = True
    return out


def dwell_points_mm(manifest) -> dict:
    """{track id: arc lengths (mm)} where the head stands still on the track in the
    manifest's timeline (a stop mid path, a G4, an unretract before it moves; fit/blobs.py
    ``still_intervals``, the rule the virtual printer lays its blobs by)."""
    from fit.blobs import still_intervals

    tl = manifest.timeline
    if tl is None or len(tl) < 2:
        return {}
    trk = np.asarray(tl.track)
    s = np.nan_to_num(np.asarray(tl.s_mm, float))
    on = (trk[:-1] == trk[1:]) & (trk[:-1] >= 0)
    k = np.flatnonzero(still_intervals(on, np.diff(s)))
    return {int(t): np.unique(np.round(s[k][trk[k] == t], 3)) for t in np.unique(trk[k])}


def _at_dwell(manifest, smp, w_meas, blur_mm=None):
    """Stations a dwell's blob covers inside a track: where the head stood still
    (:func:`dwell_points_mm`) and the widest station within 1 mm reads more than
    DWELL_BLOB_MM over the bead (the median 1-6 mm around), every station within STRIP_MM
    / 2 + 2 blurs + sqrt(R^2 - (w/2)^2) of it (R half that widest width, w the bead: where
    the blob's chord is wider than the bead, as :func:`_at_end`). The fit predicts the
    bead there (fit/model.py ``predict``), and the blob's crest, level across the stop,
    is not `steep` (session 66: a 1 mm restore disc on a 0.5 mm bead read 1 mm at its
    centre and passed)."""
    out = np.zeros(len(smp), bool)
    pts = dwell_points_mm(manifest)
    if not pts:
        return out
    wm = np.where(np.isfinite(w_meas), w_meas, 0.0)
    blur = np.zeros(len(smp)) if blur_mm is None else np.nan_to_num(np.asarray(blur_mm, float))
    for tid, s0s in pts.items():
        on = np.flatnonzero(smp.track == tid)
        if not len(on):
            continue
        s = smp.s_mm[on]
        for s0 in s0s:
            d = np.abs(s - s0)
            near = d < 1.0
            bead = (d >= 1.0) & (d < 6.0) & (wm[on] > 0)
            if not near.any() or not bead.any():
                continue
            w_bead = float(np.median(wm[on][bead]))
            widest = float(np.max(wm[on][near]))
            if widest <= w_bead + DWELL_BLOB_MM:
                continue
            reach = STRIP_MM / 2 + 2 * float(np.median(blur[on][near])) \
                + float(np.sqrt((widest / 2) ** 2 - (w_bead / 2) ** 2))
            out[on[d < reach]] = True
    return out


# -- helpers -----------------------------------------------------------------------------
def _reference_width(smp: Samples, w_nom):
    """Width (mm) the profile window is sized for: the commanded width, or where the
    pattern coasts (commanded 0) the track's typical commanded width."""
    w = np.array(w_nom, float)
    zero = w <= 0
    if zero.any():
        for tid in np.unique(smp.track[zero]):
            on = smp.track == tid
            pos = w[on] > 0
            w[on & zero] = np.median(w[on][pos]) if pos.any() else 0.4
    return np.minimum(w, MAX_WINDOW_WIDTH_MM)


def bead_points(manifest: Manifest, step_mm: float = 0.1):
    """Every printed bead of the manifest as points every ``step_mm`` (mm): (xy (N, 2), track
    id, arc length s (mm), half width (mm, commanded, capped at MAX_WINDOW_WIDTH_MM / 2),
    track kind), or None when nothing is printed."""
    pts, tid, s, hw, kind = [], [], [], [], []
    for tr in manifest.tracks:
        if tr.length_mm <= 0:
            continue
        ss = np.arange(0.0, tr.length_mm + 1e-9, step_mm)
        w = tr.interp("width_mm", ss)
        keep = w > 0
        pts.append(tr.at(ss[keep])[0])
        tid.append(np.full(keep.sum(), tr.id))
        s.append(ss[keep])
        hw.append(np.minimum(w[keep], MAX_WINDOW_WIDTH_MM) / 2)
        kind.append(np.full(keep.sum(), tr.kind, dtype=object))
    if not pts:
        return None
    return tuple(map(np.concatenate, (pts, tid, s, hw, kind)))


def _clearance(manifest: Manifest, smp: Samples, w_ref):
    """Edge-to-edge gap (mm) from each station's bead to the nearest other bead, and the
    kind of that track ("test", "label", "ruler", "fiducial", ...).

    Other bead = any track but this one, or this track more than a bead-scale away along
    its length (spirals, hairpins, self-crossings).
    """
    n = len(smp)
    gap = np.full(n, np.inf)
    gkind = np.array([""] * n, dtype=object)
    beads = bead_points(manifest)
    if beads is None:
        return gap, gkind
    pts, tid, s, hw, kind = beads
    tree = cKDTree(pts)
    xy = np.column_stack([smp.x_mm, smp.y_mm])
    reach = w_ref / 2 + float(hw.max()) + max(0.6, float(np.max(w_ref, initial=0.4)))
    # every (station, neighbour) pair as one flat array, not a Python loop over the
    # stations (0.8 -> 0.7 s a call on a 12 MP photo's 11,000 stations; the same gaps)
    nbs = tree.query_ball_point(xy, reach, return_sorted=False)
    cnt = np.fromiter((len(nb) for nb in nbs), int, n)
    i = np.repeat(np.arange(n), cnt)
    nb = np.fromiter(itertools.chain.from_iterable(nbs), int, int(cnt.sum()))
    other = (tid[nb] != smp.track[i]) | (np.abs(s[nb] - smp.s_mm[i]) > 2.0 * reach[i] + 0.5)
    i, nb = i[other], nb[other]
    g = np.hypot(*(pts[nb] - xy[i]).T) - hw[nb] - w_ref[i] / 2
    if len(i) == 0:
        return gap, gkind
    start = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])     # i is sorted: one run per station
    lo = np.minimum.reduceat(g, start)
    at = np.flatnonzero(g == np.repeat(lo, np.diff(np.r_[start, len(g)])))
    first = at[np.r_[True, i[at][1:] != i[at][:-1]]]          # the first nearest, as argmin did
    gap[i[first]], gkind[i[first]] = g[first], kind[nb[first]]
    return gap, gkind


def _near_furniture(manifest: Manifest, xy, half):
    """"fiducial" / "label" where the profile window reaches a marker (with its quiet
    frame) or a label's bounding box."""
    out = np.array([""] * len(xy), dtype=object)
    for f in manifest.fiducials:
        c = np.asarray(f.corners_mm, float)
        lo, hi = c.min(axis=0) - f.size_mm / 6, c.max(axis=0) + f.size_mm / 6
        d = _box_distance(xy, lo, hi)
        out[(d < half) & (out == "")] = "fiducial"
    for lab in manifest.labels:
        bb = lab.get("bbox_mm") if isinstance(lab, dict) else None
        if bb and len(bb) == 4:
            d = _box_distance(xy, np.array(bb[:2], float) - 0.3, np.array(bb[2:], float) + 0.3)
            out[(d < half) & (out == "")] = "label"
    return out


def _box_distance(xy, lo, hi):
    dx = np.maximum(np.maximum(lo[0] - xy[:, 0], xy[:, 0] - hi[0]), 0)
    dy = np.maximum(np.maximum(lo[1] - xy[:, 1], xy[:, 1] - hi[1]), 0)
    return np.hypot(dx, dy)


def _blur_plane(uv, blur_px, fit, ok, prior=None):
    """Least-squares plane s_px = a + b u + c v over the stations ``ok`` (2 rounds with
    3-MAD outlier rejection); None if fewer than 20 stations qualify. Stations along one
    line do not span a plane: then the ``prior`` plane (a, b, c: from the test tracks,
    which cover the picture) moved to their median level, or that median alone."""
    if ok.sum() < 20:
        return None
    A = np.column_stack([np.ones(ok.sum()), uv[ok]])
    b = blur_px[ok]
    # Stations along one line (the prime line's wide section) do not span a plane: its
    # slope across the line is noise (on the phone render it extrapolated the blur to the
    # line's ends 2x off), and one section says nothing of how the blur changes along it.
    spread = np.linalg.svd(uv[ok] - uv[ok].mean(axis=0), compute_uv=False)
    if spread[-1] < 0.05 * spread[0]:
        base = np.zeros(3) if prior is None or len(prior) != 3 else np.asarray(prior, float)
        level = float(np.nanmedian(b - A @ base))
        return base + np.array([level, 0.0, 0.0])
    keep = np.isfinite(b)
    coef = None
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
        r = b - A @ coef
        mad = np.median(np.abs(r[keep])) * 1.4826 + 1e-9
        keep = np.abs(r) < 3 * mad
        if keep.sum() < 10:
            break
    return coef


def _along_track_median(track, s_mm, values, half_mm):
    """Median of ``values`` over the stations of the same track within about +- ``half_mm``
    of arc length (stations in order of s; their spacing from the track's median step)."""
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    out = np.asarray(values, float).copy()
    for tid in np.unique(track):
        idx = np.flatnonzero(track == tid)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        if len(idx) < 3:
            continue
        step = float(np.median(np.diff(s_mm[idx]))) or 1.0
        size = max(1, 2 * int(round(half_mm / step)) + 1)
        v = out[idx]
        fin = np.isfinite(v)
        if not fin.any():
            continue
        # a profile outside the image has no RMS: it must not spread to its neighbours
        out[idx] = ndimage.median_filter(np.where(fin, v, np.median(v[fin])), size=size, mode="nearest")
    return out


def _track_median(track, values, ok):
    """Per-station median of ``values`` over the good stations of its track (global
    median where a track has none)."""
    out = np.full(len(track), np.nan)
    finite = np.isfinite(values)
    # a picture of something else can leave no finite value at all: NaN, without a warning
    glob = np.median(values[ok]) if ok.any() else (np.median(values[finite]) if finite.any() else np.nan)
    for tid in np.unique(track):
        on = track == tid
        good = on & ok
        out[on] = np.median(values[good]) if good.sum() >= 5 else glob
    return out


def _group_median(group, values, ok, track):
    """Per-station median of ``values`` over the good stations of its group (of its track
    where the group has fewer than 5, see :func:`_track_median`)."""
    out = _track_median(track, values, ok)
    for g in np.unique(group):
        on = group == g
        good = on & ok
        if good.sum() >= 5:
            out[on] = np.median(values[good])
    return out


def _saturated_samples(color, uv) -> np.ndarray:
    """(N, M) profile samples whose pixel is saturated in any channel."""
    col = np.asarray(color)
    # the brightest channel at the profile's pixels only (not a 12 MP max and float copy)
    chans = [np.ascontiguousarray(col[..., k]) for k in range(col.shape[2])] if col.ndim == 3 else [col]
    at = [uv[..., 1].ravel(), uv[..., 0].ravel()]
    peak = np.max([ndimage.map_coordinates(ch, at, order=0, mode="constant", cval=0) for ch in chans], axis=0)
    return peak.reshape(uv.shape[:2]) >= 254


def _share_within(mask, t, c, half, inside) -> np.ndarray:
    """(N,) share of each station's samples with |t - c| < half (mm) that ``mask`` holds."""
    on = (np.abs(t - c[:, None]) < np.maximum(np.nan_to_num(half), 0)[:, None]) & inside
    return (mask & on).sum(axis=1) / np.maximum(on.sum(axis=1), 1)
