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
about their smooth course (:func:`calibrated_sd`).

Glare: where a specular streak brightens one flank (measure/edges.py :func:`fit_streak`),
the edge pair is refitted with the streak on either side and the better of the two replaces
the plain fit when it explains significantly more: F = [(RSS_plain - RSS_streak) / 2] /
[RSS_streak / (M - 7)] > ``STREAK_F``, and the streaks' sides agree with one light over the
scan (``STREAK_COHERENCE``). Such stations stay valid (``glare_streak`` says which).

Stations are flagged, never silently used (valid = 0 and a reason): ``edge`` (profile leaves
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
from scipy import ndimage, optimize, special
from scipy.spatial import cKDTree

from measure import edges
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
#: calibrated_sd: second differences over this arc length (mm), in this many bins of the
#: formal variance, with the robust sd from this quantile of |d| (0.68: a little more of the
#: tails than the median, still blind to the few steps and blobs of a track). The lag was
#: 1 mm until the strips were despeckled: the despeckled station noise fell 3x on a
#: flatbed render saved as JPEG 15, what its blocks share over a millimetre much less, and
#: 1 mm left 53 % of its errors within their sd (62 % before); 2 mm gives 60 %, the
#: bench_realism scenes within 0.02 of 1 mm's coverage.
SD_LAG_MM = 2.0
SD_BINS = 5
SD_QUANTILE = 0.68
#: Profile step (px) aimed for; the fit is insensitive below ~0.5 px.
STEP_PX = 0.5
#: Fewest background samples each side (mm) needed for a trustworthy edge fit.
MIN_BACKGROUND_MM = 0.2
#: Widths (mm) the profile window is sized for are capped here: third-party G-code can
#: command absurd widths (a restore move with a little XY motion reads as a 20 mm bead).
MAX_WINDOW_WIDTH_MM = 3.0
#: A station whose fit sd or relative residual exceeds this multiple of its track's median is flagged.
OUTLIER_FACTOR = 4.0
#: ... but a width whose sd is at most this (mm) is kept whatever its peers' sd: it carries
#: its own weight. On 600 dpi renders with every phenomenon the peers' median sd was 1.6 um,
#: so the rule flagged 1,009 stations of sd 7-18 um (12 % of the direct-drive scene, 10 %
#: of the Bowden one) whose widths erred 9.6 um RMS (8.9 for the valid ones) with |error|
#: > 3 sd on 0.8 %: honest widths, not contaminated profiles (those misfit: the residual
#: rule stays). Kept up to 15 um.
SD_OUTLIER_MIN_MM = 0.015
#: A valid station is flagged "isolated" when fewer than ISOLATED_FRACTION of its track's
#: stations within +-ISOLATED_HALF_MM (mm) are valid among those valid or flagged for a bad
#: profile (:func:`isolated`). End-to-end render (seed 7, orange beads over light-grey
#: plate logos): 5 stations 0.3-0.5 mm too wide, in stretches where 2 of 15 stations
#: passed, took the fit to chi2_nu 61 and Kb 24x the truth; flagged, the scan's RMS error
#: fell 24.9 -> 6.0 um (on the saved flatbed scene with every phenomenon, direct drive:
#: 8.8 -> 5.4 um) for 1-2 % of the stations.
ISOLATED_HALF_MM = 0.75
ISOLATED_FRACTION = 0.4
#: ... and when its run of valid stations lies inside contamination and reads another
#: width than the bead around it (:func:`enclosed`): a logo or letter on the plate beside
#: the bead, where it reaches the profile window's end, flags the station ``background``;
#: where it lies inside the window next to the bead, the edge pair takes it for part of
#: the bead and the window's ends see plain plate. On bench_realism's 35 deg phone photo
#: (direct drive, seed 1) 6 stations of a 1.6 mm bead read 2.12-2.30 mm with sds of
#: 15-25 um, between `background`+`steep` blocks 1.75 mm apart: 36 % of the scan's
#: squared error. The run is bounded by stations at most ENCLOSED_MM apart (twice
#: DROPOUT_REACH_MM, the span a dropout may have), with a contaminated flag in the block
#: on each side, and its median differs from the median of the valid stations within
#: ENCLOSED_REACH_MM by more than ENCLOSED_DEVIATION_MM. Without the width test (any run
#: so bounded) the rule took 9 % of realdata StartStopTestPLA1's valid stations (47.8 ->
#: 38.8 %), stations only 2x the scan's typical deviation; with it 1.2 points (46.6 %).
ENCLOSED_MM = 2.0
ENCLOSED_REACH_MM = 4.0
ENCLOSED_DEVIATION_MM = 0.1
#: Where a track coasts (commanded width 0), a bead wider than this times its reference
#: width (+ 0.05 mm) is not its ooze but a blob (measure_widths)
BLOB_COAST_FACTOR = 1.2
#: A station within this (mm) of a station of its track that saw no bead (``missing``) has
#: the bead's tip in its strip or its despeckling window (STRIP_MM / 2 + SPECK_MM / 2):
#: flagged "end" (:func:`beside_absence`).
TIP_REACH_MM = 0.35
#: A station that saw no bead, with stations of its track that saw one within this (mm)
#: before and after it, is a ``dropout`` (:func:`dropouts`): a misdetection, not an absence.
#: A printer that stops and restarts the flow tapers the bead out and in again over the
#: pressure's time constant at the head's speed (0.04 s at 20 mm/s is 0.8 mm, a Bowden's
#: 0.8 s is 16 mm) plus a nozzle's width each way, so a bead it interrupted is gone for
#: more than a millimetre. On bench_realism's 35 deg phone photos the narrowest beads
#: (0.25 mm, 1.5 blurs wide) were called missing at 3-157 stations of six scenes, most
#: one at a time between stations that showed them (dropouts now: 131 / 153 of 138 / 157
#: on the direct drive's seeds 1 and 0); the fit took each for a bead narrower than a
#: pixel, and those terms, independent of the wobble that ties the valid widths together,
#: pulled the width offset 25-34 um too negative (widths after the fit's offset 30.8 /
#: 31.9 um RMS; 26.3 / 20.8 with the dropouts; docs/MEASUREMENT.md, "A bead seen on both
#: sides of a gap").
DROPOUT_REACH_MM = 1.0
#: A track's blur takes its own level about the picture's blur plane from at least this
#: many of its stations in the blur-free pass (:func:`_learn_blur_plane`).
TRACK_BLUR_MIN_STATIONS = 20
#: The blur plane's own error is read in this many square cells across the picture's
#: stations, from cells with this many wide beads or more (:func:`_relative_spread`).
BLUR_SPREAD_CELLS = 20
BLUR_SPREAD_PER_CELL = 15
#: A station whose measured width changes faster than this along the track (mm/mm) is
#: flagged "steep" (:func:`steep`). Over five flatbed scenes of the virtual printer at the
#: truth (stop-mid-path direct drive and Bowden, spiral Bowden and direct drive,
#: start-stop direct drive) the 0-44 such stations read 3.5-8.8 um RMS from the model
#: through the measurement's kernel, the others 0.6-0.9 um; on the RetractTest the restore
#: bulges read 12-24 um wide.
STEEP_SLOPE = 0.2
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
CONTAMINATED_FLAGS = ("fit", "glare", "blob", "oblique", "faint", "background")
#: A valid station is flagged "oblique" when the fitted centres of its track's valid
#: stations within +-ISOLATED_HALF_MM run across the track: slope |dc/ds| > OBLIQUE_SLOPE
#: (8.5 deg) at more than OBLIQUE_T standard errors (:func:`oblique`). A string of ooze
#: crossing a line that never printed passed as a 0.16 mm "bead" for 2.3 mm (slope 0.63,
#: t 560-1550); over 45,000 printed stations of four scenes (flatbed strings, flatbed and
#: phone with every phenomenon, light-plate JPEG) the largest was 0.29 (grain-jittered
#: centres, t <= 23) and no printed station reached both.
OBLIQUE_SLOPE = 0.15
OBLIQUE_T = 50.0
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
#: F statistic above which a glare streak replaces the plain edge pair. Streak-free renders
#: (bead profile shaded, no glare) give F <= 27 on 300 stations, median 0.8 (99th
#: percentile 22); the streaks that bias the plain fit by +5..+12 um give F 300-600.
STREAK_F = 30.0
#: Streaks are believed only when at least this many stations show one and their sides,
#: as bed directions, agree: |mean of side x normal| >= STREAK_COHERENCE (glare renders
#: 0.91-0.95; edge-model misfit on translucent or phone renders 0.03-0.49).
STREAK_MIN_STATIONS = 20
STREAK_COHERENCE = 0.6
#: A streak is looked for only on beads at least this many blurs wide: on a narrower one
#: (a phone's 0.25 mm beads under 0.16 mm of blur, 1.6 blurs) the blurred streak is one more
#: bump of the bead's own shape, and trades with its contrast and width (streak fits read
#: those beads 52 um wide where the plain fit read -7 um; 0.5 mm beads, 3.2 blurs: -1 um).
STREAK_MIN_BLURS = 2.5
#: Streaks sit at one depth for the scan (:func:`_common_depth`) where the blur is wider than
#: this many flank radii (h/2): below it the free depth is read station by station (600
#: dpi flatbed, blur 0.03-0.05 mm for a 0.1 mm radius: one common depth moved the glare
#: row's bias -2.7 -> -4.2 um and the Bowden's seed 0 +3.6 -> +6.8 um).
STREAK_COMMON_BLUR = 1.0
#: The streak's depth common to a scan (:func:`_common_depth`) is searched on this grid
#: (fraction of the flank's radius h/2) over this many stations.
STREAK_DEPTH_STEP = 0.05
STREAK_DEPTH_SAMPLE = 400
#: On scans with >= this x STREAK_MIN_STATIONS fitted stations, one in this many is tried
#: for a streak first (:func:`_with_glare_streaks`).
STREAK_SCREEN_EVERY = 8
#: ... and the light those show is believed only beyond this many times the coherence n
#: passes have with their sides at random (1 / sqrt(n)): a streak-free flatbed render,
#: despeckled, had 2 of 181 pass on one side (coherence 1), then 5 at 0.6, and the full
#: test ran for nothing (50 of 1446 passed, coherence 0.08). At 2.0, 4 of 4 on one side
#: passed the bar (1.0; chance 1 in 8 on parallel tracks) and the full test ran again for
#: nothing (42 passed, coherence 0.19); at 2.5 no n < 7 passes by chance.
STREAK_SCREEN_CHANCE = 2.5
#: ... and when those agree on the light this well, the others are tried on the side that
#: faces it first (the screen's coherence was within 0.11 of the full test's on six
#: renders' scans, 0.32-0.87).
STREAK_SURE_COHERENCE = 0.7
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


def widths(image, manifest_or_samples, registration, *, manifest: Manifest | None = None,
           color=None) -> WidthTable:
    """Widths table of a registered image (see :func:`measure_widths`)."""
    return measure_widths(image, manifest_or_samples, registration, manifest=manifest, color=color).table


def measure_widths(image, manifest_or_samples, registration, *, manifest: Manifest | None = None,
                   color=None, ds_mm: float = 0.25, fix_blur: bool = True,
                   blur_prior_px=None, colour_axis=None) -> WidthMeasurement:
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
                                                       track=smp.track) if fix_blur else (None, None, np.nan)
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
    fit, streak = _with_glare_streaks(t, y, fit, wts, height, nrm)

    w = fit.width.copy()
    c = fit.centre.copy()
    sd = fit.width_sd * np.sqrt(1.0 / np.minimum(1.0, step_px)) * SD_CALIBRATION
    sd = np.sqrt(sd ** 2 + (SD_FLOOR_PX / ppm_n) ** 2)

    # -- flags from the fit ---------------------------------------------------------------
    amp = pol * fit.amplitude
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
    noise = fit.rms
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
    rel_rms = fit.rms / np.maximum(np.abs(amp), 1e-6)
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
    sd_own = sd * _scatter_factor(smp.track, w, sd, valid, rho)
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
        per_rel_blur = np.where(w > 0, edges.width_per_blur(t, fit.params, wts) * fit.params[:, 5], np.nan)
    if per_rel_blur is not None and np.isfinite(blur_rel_sd):
        by_blur = np.abs(np.nan_to_num(per_rel_blur)) * blur_rel_sd
        sd, sd_own = np.hypot(sd, by_blur), np.hypot(sd_own, by_blur)
    sd_own = np.where(np.isfinite(sd_own), sd_own, np.nan)
    w = np.where(np.isfinite(w), w, np.nan)
    sd = np.where(np.isfinite(sd), sd, np.nan)
    table = WidthTable(track=smp.track, s_mm=smp.s_mm, x_mm=smp.x_mm, y_mm=smp.y_mm, t_s=smp.t_s,
                       width_mm=w, width_sd_mm=sd, valid=valid, flag=flag, width_sd_own_mm=sd_own,
                       width_corr_prev=rho)
    return WidthMeasurement(table=table, centre_mm=c, blur_mm=fit.params[:, 5], amplitude=fit.amplitude,
                            nx=nrm[:, 0], ny=nrm[:, 1], window_mm=half,
                            blur_plane_px=tuple(plane) if plane is not None else (), glare_streak=streak,
                            plain_width_mm=np.where(streak & (w > 0), plain_w, w),
                            sd_scale=sd_scale, sd_floor_mm=sd_floor, place_sd_mm=place_sd,
                            blur_rel_sd=float(blur_rel_sd), width_per_rel_blur_mm=per_rel_blur)


def isolated(track, s_mm, flag, half_mm: float | None = None, fraction: float | None = None):
    """Valid stations (flag "") in a stretch of contaminated ones (bool array): fewer than
    ``fraction`` (ISOLATED_FRACTION) of the other stations of the same track within
    +-``half_mm`` (ISOLATED_HALF_MM) are valid, counting only valid ones and those flagged
    for a bad profile (CONTAMINATED_FLAGS: geometric flags such as a crossing, and missing
    beads, say nothing of the profile). A bead over a plate logo lighter than the plate
    failed the fit on most stations, and the few that passed had found the logo's edge."""
    half_mm = ISOLATED_HALF_MM if half_mm is None else half_mm
    fraction = ISOLATED_FRACTION if fraction is None else fraction
    track, s_mm, flag = np.asarray(track), np.asarray(s_mm, float), np.asarray(flag, dtype=object)
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s = s_mm[idx]
        v = (flag[idx] == "").astype(float)
        bad = np.isin(flag[idx], CONTAMINATED_FLAGS).astype(float)
        cv, cb = np.concatenate([[0.0], np.cumsum(v)]), np.concatenate([[0.0], np.cumsum(bad)])
        lo = np.searchsorted(s, s - half_mm, "left")
        hi = np.searchsorted(s, s + half_mm, "right")
        n_valid = cv[hi] - cv[lo] - v
        n = n_valid + cb[hi] - cb[lo]
        out[idx] = (v > 0) & (n > 0) & (n_valid < fraction * n)
    return out


def enclosed(track, s_mm, flag, w_mm, gap_mm: float | None = None,
             deviation_mm: float | None = None) -> np.ndarray:
    """Valid stations (flag "") inside contamination that read another width than the bead
    around them (bool array). A run of valid stations is taken when, on its track,
    - the stations flagged on each side of it are flagged for a bad profile
      (CONTAMINATED_FLAGS or ``steep``), the two at most ``gap_mm`` (ENCLOSED_MM) apart,
    - each side's block of such stations holds one of CONTAMINATED_FLAGS (``steep`` alone
      is a real change of width: a blob up and down again is steep-plateau-steep), and
    - the run's median width differs by more than ``deviation_mm`` (ENCLOSED_DEVIATION_MM)
      from the median of at least three valid stations outside it within ENCLOSED_REACH_MM.
    Geometric flags (a crossing, a neighbour, a bead's end) and absences bound nothing;
    without valid stations around, nothing says the run is wrong and it is kept."""
    gap_mm = ENCLOSED_MM if gap_mm is None else gap_mm
    deviation_mm = ENCLOSED_DEVIATION_MM if deviation_mm is None else deviation_mm
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    flag, w_mm = np.asarray(flag, dtype=object), np.asarray(w_mm, float)
    bounds = CONTAMINATED_FLAGS + ("steep",)
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s, f, w = s_mm[idx], flag[idx], w_mm[idx]
        v = f == ""
        bound = np.isin(f, bounds)
        dirty = np.isin(f, CONTAMINATED_FLAGS)
        edges = np.diff(np.r_[0, v.astype(np.int8), 0])
        for i, j in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            if i == 0 or j == len(idx) or not (bound[i - 1] and bound[j]) or s[j] - s[i - 1] > gap_mm:
                continue
            a = i - 1                                      # the blocks of bounds each side
            while a > 0 and bound[a - 1]:
                a -= 1
            b = j
            while b + 1 < len(idx) and bound[b + 1]:
                b += 1
            if not (dirty[a:i].any() and dirty[j:b + 1].any()):
                continue
            mid = 0.5 * (s[i] + s[j - 1])
            around = v & (np.abs(s - mid) <= ENCLOSED_REACH_MM)
            around[i:j] = False
            if around.sum() >= 3 and abs(np.median(w[i:j]) - np.median(w[around])) > deviation_mm:
                out[idx[i:j]] = True
    return out


def steep(track, s_mm, w_mm, sd_mm=None, max_slope: float | None = None) -> np.ndarray:
    """Stations where the measured width changes faster than ``max_slope`` (STEEP_SLOPE, mm
    of width per mm of track; central differences along the track, NaN as 0) by more than
    two sds of that difference (from the widths' sds ``sd_mm``): the strip then holds
    widths ``max_slope`` x STRIP_MM apart, whose mean profile's edge pair is not their
    mean width, and the outline the picture shows is the union of the bead's round
    footprints, wider than the width by ~w'^2 / 8 of it (the envelope of circles). Where
    the widths are noisy (a phone photo of a real print: sds of 20-60 um) the noise's
    slope is not a steep bead, and a bias of a few um is well inside the sd."""
    max_slope = STEEP_SLOPE if max_slope is None else max_slope
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    w = np.nan_to_num(np.asarray(w_mm, float))
    var = np.zeros(len(w)) if sd_mm is None else np.nan_to_num(np.asarray(sd_mm, float), nan=0.0) ** 2
    out = np.zeros(len(track), bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        if len(idx) < 2:
            continue
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s = s_mm[idx]
        if np.any(np.diff(s) <= 0):
            continue
        v = var[idx]
        # central difference (w[j+1] - w[j-1]) / (s[j+1] - s[j-1]); one-sided at the ends
        gap = np.r_[s[1] - s[0], s[2:] - s[:-2], s[-1] - s[-2]] if len(s) > 2 else np.full(len(s), s[1] - s[0])
        v_pair = np.r_[v[0] + v[1], v[2:] + v[:-2], v[-1] + v[-2]] if len(s) > 2 else np.full(len(s), v.sum())
        out[idx] = np.abs(np.gradient(w[idx], s)) - 2.0 * np.sqrt(v_pair) / gap > max_slope
    return out


def beside_absence(track, s_mm, absent, reach_mm: float | None = None) -> np.ndarray:
    """Stations within ``reach_mm`` (TIP_REACH_MM) of an ``absent`` station of the same
    track (bool array): where a bead fades out or in, the strip of the last station that
    sees it holds the tip, a sliver whose edge pair reads wider than the sliver. The
    virtual direct drive's RetractTest at the truth: 15 valid stations read 0.12-0.16 mm
    where the bead, carried 0.3 mm past the commanded stop by the moving retraction, had
    tapered to 0.0-0.08 mm (7.2 um RMS over the valid stations, every station beyond
    40 um one of these), wherever the commanded stop's own reach (:func:`_at_end`) ended
    before the bead did."""
    reach_mm = TIP_REACH_MM if reach_mm is None else reach_mm
    track, s_mm, absent = np.asarray(track), np.asarray(s_mm, float), np.asarray(absent, bool)
    out = np.zeros(len(track), bool)
    for t in np.unique(track[absent]):
        idx = np.flatnonzero(track == t)
        s_abs = np.sort(s_mm[idx][absent[idx]])
        s = s_mm[idx]
        k = np.clip(np.searchsorted(s_abs, s), 1, len(s_abs) - 1) if len(s_abs) > 1 else np.zeros(len(s), int)
        d = np.abs(s - s_abs[k])
        if len(s_abs) > 1:
            d = np.minimum(d, np.abs(s - s_abs[k - 1]))
        out[idx] = (d <= reach_mm) & ~absent[idx]
    return out


def dropouts(track, s_mm, absent, seen, reach_mm: float | None = None) -> np.ndarray:
    """``absent`` stations (bool array) with a ``seen`` station of the same track within
    ``reach_mm`` (DROPOUT_REACH_MM) before *and* after them: a bead seen on both sides of a
    gap shorter than a printer can leave in it (DROPOUT_REACH_MM) was there, and the
    station that missed it misread the picture."""
    reach_mm = DROPOUT_REACH_MM if reach_mm is None else reach_mm
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    absent, seen = np.asarray(absent, bool), np.asarray(seen, bool)
    out = np.zeros(len(track), bool)
    for t in np.unique(track[absent]):
        idx = np.flatnonzero(track == t)
        s_seen = np.sort(s_mm[idx][seen[idx]])
        if len(s_seen) < 2:
            continue
        i_abs = idx[absent[idx]]
        s = s_mm[i_abs]
        k = np.searchsorted(s_seen, s)          # s_seen[k - 1] < s <= s_seen[k]
        before = np.where(k > 0, s - s_seen[np.maximum(k - 1, 0)], np.inf)
        after = np.where(k < len(s_seen), s_seen[np.minimum(k, len(s_seen) - 1)] - s, np.inf)
        out[i_abs] = (before <= reach_mm) & (after <= reach_mm)
    return out


def oblique(track, s_mm, centre_mm, ok, half_mm: float | None = None,
            max_slope: float | None = None, min_t: float | None = None):
    """Stations (bool array, among ``ok``) where what the edge fit found runs at an angle to
    the track: the least-squares line through the centres (mm, along the normal) of the
    ``ok`` stations of the same track within +-``half_mm`` of arc length has a slope over
    ``max_slope`` (OBLIQUE_SLOPE) that is ``min_t`` (OBLIQUE_T) standard errors from 0.
    A bead runs along its track (a misregistration shifts its centre slowly); a string or a
    line crossing at an angle is a straight feature whose centre walks off at once."""
    half_mm = ISOLATED_HALF_MM if half_mm is None else half_mm
    max_slope = OBLIQUE_SLOPE if max_slope is None else max_slope
    min_t = OBLIQUE_T if min_t is None else min_t
    track, s_mm = np.asarray(track), np.asarray(s_mm, float)
    c, ok = np.asarray(centre_mm, float), np.asarray(ok, bool) & np.isfinite(centre_mm)
    out = np.zeros(len(track), bool)
    for t in np.unique(track[ok]):
        idx = np.flatnonzero((track == t) & ok)
        idx = idx[np.argsort(s_mm[idx], kind="stable")]
        s, y = s_mm[idx], c[idx]
        # windowed sums give every station's local regression at once
        cum = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(s), s, y, s * s, s * y, y * y)]
        lo = np.searchsorted(s, s - half_mm, "left")
        hi = np.searchsorted(s, s + half_mm, "right")
        n, sx, sy, sxx, sxy, syy = (q[hi] - q[lo] for q in cum)
        with np.errstate(invalid="ignore", divide="ignore"):
            vxx = sxx - sx * sx / n
            slope = (sxy - sx * sy / n) / vxx
            rss = np.maximum(syy - sy * sy / n - slope * (sxy - sx * sy / n), 0.0)
            se = np.sqrt(rss / np.maximum(n - 2, 1) / vxx)
            # a perfectly straight feature has rss ~ 0: its t is large, not undefined
            tval = np.abs(slope) / np.maximum(se, 1e-9)
        out[idx] = (n >= 4) & (np.abs(slope) > max_slope) & (tval > min_t)
    return out


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


def unfit(width_cmd_mm, sd_mm, sd_ref_mm, rel_rms, rel_rms_ref):
    """Stations whose edge fit is not to be trusted (bool array): a relative residual over
    OUTLIER_FACTOR x its peers' (something else in the profile: a logo, a scratch, a
    string), an sd over a quarter of the *commanded* width ``width_cmd_mm``, or an sd over
    OUTLIER_FACTOR x its peers' that is also above SD_OUTLIER_MIN_MM (below it the width
    carries its own weight). The bar is not the measured width: a narrow bead's sd grows
    as it reads narrower (width and contrast trade off under the blur), so a quarter of the
    measured width dropped the stations that erred narrow and kept those that erred wide
    (phone render of a sparkling plate, 0.25 mm beads: mean error -4 um of the kept ones,
    -14 um with the commanded width, against -45 um for 1.6 mm beads)."""
    return ((sd_mm > 0.25 * np.maximum(width_cmd_mm, 0.1))
            | (sd_mm > np.maximum(OUTLIER_FACTOR * sd_ref_mm, SD_OUTLIER_MIN_MM))
            | (rel_rms > OUTLIER_FACTOR * rel_rms_ref))


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
                      gap=None, track=None):
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
    fit1, _ = _with_glare_streaks(t[sub], y[sub], fit1, wts.astype(float), height_mm[sub], normals[sub],
                                  fixed_s=False)
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


def _with_glare_streaks(t, y, fit, wts, height_mm, normals, fixed_s: bool = True):
    """The plain fit, with stations where a glare streak explains significantly more
    (F > STREAK_F, module docstring) on the side that faces the scan's light replaced by
    the streak fit; and which were. normals (N, 2): profile direction (bed frame).

    The streak fits cost more than the rest of the measurement: on large scans one station
    in STREAK_SCREEN_EVERY is tried first, on both sides, and when those show no coherent
    light (under half the stations or half the coherence the full test needs) the scan has
    no glare and the rest are not tried. When they show a light beyond doubt (coherence >=
    STREAK_SURE_COHERENCE), the rest are tried on the side facing it, and on the other
    side only where that one passes; in between, on both sides, since then the full test's
    coherence decides (a light plate with every phenomenon: 0.32 on the screen, 0.28 on
    all stations, no streaks; trying the facing side first made it 0.9 and the widths'
    RMS 22 -> 40 um)."""
    n = len(t)
    streak = np.zeros(n, bool)
    idx = np.flatnonzero(fit.ok & (fit.params[:, 4] >= STREAK_MIN_BLURS * fit.params[:, 5]))
    if len(idx) == 0:
        return fit, streak
    k = STREAK_SCREEN_EVERY
    light = None
    if len(idx) >= k * STREAK_MIN_STATIONS:
        sub = idx[::k]
        use, _, toward = _streak_test(t, y, fit, wts, height_mm, normals, sub, fixed_s)
        light = toward[use].mean(axis=0) if use.any() else np.zeros(2)
        if (use.sum() < 0.5 * STREAK_MIN_STATIONS / k
                or np.hypot(*light) < max(0.5 * STREAK_COHERENCE, STREAK_SCREEN_CHANCE / np.sqrt(use.sum()))):
            return fit, streak
        if np.hypot(*light) < STREAK_SURE_COHERENCE:
            light = None
    use, best, toward = _streak_test(t, y, fit, wts, height_mm, normals, idx, fixed_s, light)
    # One light lights one flank: the streak's side, as a bed direction (side x normal),
    # points the same way at every station. Edge-model misfit that merely looks like a
    # streak (translucent edges: 6 % of stations passed the F test, 57 % of those then
    # outside 3 sd) picks its side at random.
    light = toward[use].mean(axis=0) if use.sum() >= STREAK_MIN_STATIONS else np.zeros(2)
    if np.hypot(*light) < STREAK_COHERENCE:
        use[:] = False
    else:
        use &= toward @ light > 0
    streak[idx[use]] = True
    side = np.sign(np.einsum("ij,ij->i", toward, normals[idx]))
    best = _common_depth(t, y, fit, wts, height_mm, idx, use, best, side, fixed_s)
    params, sd, rms = fit.params.copy(), fit.sd.copy(), fit.rms.copy()
    params[idx[use]] = best.params[use, :6]
    sd[idx[use]] = best.sd[use, :6]
    rms[idx[use]] = best.rms[use]
    return edges.ProfileFit(params, sd, rms, fit.ok), streak


def _common_depth(t, y, fit, wts, height_mm, idx, use, best, side, fixed_s):
    """The streak fits ``best`` of the stations ``idx[use]`` (streak on ``side``, -1 / +1)
    refitted with the streak's depth held at one value for the scan: one light over the
    scan puts the highlight where the flank's slope is half its zenith angle, at one depth
    (as a fraction of the flank's radius h/2). Each keeps its own depth unless at least
    STREAK_MIN_STATIONS free fits ended inside the depth's bounds.

    That depth maximises the joint likelihood of those stations (a subsample of
    STREAK_DEPTH_SAMPLE), each with its own noise level: sum_i m_i ln RSS_i(d) is least,
    over a grid of STREAK_DEPTH_STEP refined by a parabola through the least three.

    Where the blur is wider than the flank (a phone's 0.16 mm against 0.1 mm), a free depth
    trades with the edge: on a phone render (direct drive, seed 0) 80 % of the free streak
    fits ended on a bound of the depth, those at 0.4 reading the beads 11-13 um narrow and
    those at 1.0 scattering 64-100 um (0.5 and 1.6 mm beads), and the width's sd, with the
    depth free in its covariance, 15x its peers': 70 % of the streak stations were
    flagged. Held at 0.71 the streak stations read within 3 um of the others (6-9 um
    RMS). Why not every streak station's likelihood: the renderer's shaded crown is
    no edge pair, and the stations whose depth went to the bound pulled the common one
    there too (0.40; the widths 10-14 um narrower than the stations without a streak).
    Nor the median of the free depths: 0.77 on synthetic profiles whose depth is 0.70."""
    on = np.flatnonzero(use & best.ok)
    h = np.broadcast_to(np.asarray(height_mm, float), (len(t),))
    if len(on) == 0 or np.median(fit.params[idx[on], 5]) <= STREAK_COMMON_BLUR * np.median(h[idx[on]]) / 2:
        return best
    lo, hi = edges.STREAK_FLANK
    frac = best.params[on, 7] / (0.5 * h[idx[on]])
    free = on[(frac > lo + STREAK_DEPTH_STEP / 5) & (frac < hi - STREAK_DEPTH_STEP / 5)]
    if len(free) < STREAK_MIN_STATIONS:
        return best

    def refit(o, d):
        out = edges.ProfileFit(np.full((len(o), 8), np.nan), np.full((len(o), 8), np.nan), np.full(len(o), np.nan),
                               np.zeros(len(o), bool))
        for sd_ in (-1.0, 1.0):
            j = np.flatnonzero(side[o] == sd_)
            if len(j):
                i = idx[o[j]]
                f = edges.fit_streak(t[i], y[i], fit.params[i], sd_, h[i], fixed_s=fixed_s, weights=wts[i],
                                     flank=(d, d))
                out.params[j], out.sd[j], out.rms[j], out.ok[j] = f.params, f.sd, f.rms, f.ok
        return out

    grid = np.arange(lo, hi + 1e-9, STREAK_DEPTH_STEP)
    sub = free[:: max(1, len(free) // STREAK_DEPTH_SAMPLE)]
    m = wts[idx[sub]].sum(axis=1)
    rss = np.array([np.where(f.ok, f.rms ** 2 * np.maximum(m - 7, 1), np.nan)
                    for f in (refit(sub, d) for d in grid)])
    every = np.isfinite(rss).all(axis=0)
    cost = (m[every] * np.log(np.maximum(rss[:, every], 1e-300))).sum(axis=1)
    j = int(np.clip(np.argmin(cost), 1, len(grid) - 2))
    c0, c1, c2 = cost[j - 1:j + 2]
    curv = c0 - 2 * c1 + c2
    d = float(np.clip(grid[j] + (0.5 * STREAK_DEPTH_STEP * (c0 - c2) / curv if curv > 0 else 0.0), lo, hi))
    f = refit(on, d)
    # a station whose held fit failed keeps its free one
    on, f = on[f.ok], edges.ProfileFit(f.params[f.ok], f.sd[f.ok], f.rms[f.ok], f.ok[f.ok])
    out = edges.ProfileFit(best.params.copy(), best.sd.copy(), best.rms.copy(), best.ok.copy())
    out.params[on], out.sd[on], out.rms[on] = f.params, f.sd, f.rms
    return out


def _streak_test(t, y, fit, wts, height_mm, normals, idx, fixed_s, light=None):
    """For the stations ``idx``: whether a streak passes the F test, the better side's fit,
    and that side as a bed direction (side x normal). ``light`` (a bed direction): try the
    side that faces it, and the other only where that one passes; None: both everywhere."""
    n = len(idx)
    m_eff = wts[idx].sum(axis=1)
    k0 = 5 if fixed_s else 6
    rss0 = fit.rms[idx] ** 2 * np.maximum(m_eff - k0, 1)
    best_rss = np.full(n, np.inf)
    best_side = np.zeros(n)
    k = len(edges.STREAK_PARAMS)
    best = edges.ProfileFit(np.full((n, k), np.nan), np.full((n, k), np.nan), np.full(n, np.nan), np.zeros(n, bool))

    def try_sides(on, sides):
        for side in (-1.0, 1.0):
            o = on[sides == side]
            if len(o) == 0:
                continue
            i = idx[o]
            f = edges.fit_streak(t[i], y[i], fit.params[i], side, height_mm[i], fixed_s=fixed_s, weights=wts[i])
            rss = np.where(f.ok, f.rms ** 2 * np.maximum(m_eff[o] - k0 - 2, 1), np.inf)
            better = rss < best_rss[o]
            j = o[better]
            best_rss[j], best_side[j] = rss[better], side
            best.params[j], best.sd[j] = f.params[better], f.sd[better]
            best.rms[j], best.ok[j] = f.rms[better], f.ok[better]

    def passes():
        with np.errstate(invalid="ignore"):
            F = 0.5 * (rss0 - best_rss) / np.maximum(best_rss / np.maximum(m_eff - k0 - 2, 1), 1e-300)
        return np.isfinite(F) & (F > STREAK_F) & (best.params[:, 6] > 0)

    every = np.arange(n)
    if light is None:
        try_sides(np.repeat(every, 2), np.tile([-1.0, 1.0], n))
    else:
        # the side facing the light first; the other only where that one passes, to see
        # which explains more (misfit that merely looks like a streak fits either side)
        facing = np.where(normals[idx] @ np.asarray(light, float) >= 0, 1.0, -1.0)
        try_sides(every, facing)
        cand = np.flatnonzero(passes())
        try_sides(cand, -facing[cand])
    return passes(), best, best_side[:, None] * normals[idx]


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


def registration_place_sd(registration, xy_mm, tangent) -> np.ndarray:
    """Along-track sd (mm) of where the registration puts each station (0 when it does not say)."""
    f = getattr(registration, "place_sd_mm", None)
    return np.zeros(len(xy_mm)) if f is None else np.nan_to_num(f(xy_mm, tangent))


def slope_sd(track, s_mm, w_mm, sd_mm, valid, place_sd_mm, half_mm: float = 0.5,
             k_sig: float = 3.0) -> np.ndarray:
    """Width sd (mm) from not knowing where along its track a station is: |dw/ds| x
    ``place_sd_mm`` (errors in the independent variable carried through the slope: the
    effective-variance method, Orear 1982, Am. J. Phys. 50, 912).

    The slope (mm/mm) is the larger of two estimates from the valid stations of the same
    track: the least-squares line over +-``half_mm``, its square debiased by its variance
    from the widths' sds (so that noise alone adds little: ~0.2 um per um of sd at a 0.2
    mm place sd); and, where a width steps faster than that line can follow, the one-sided
    differences to the neighbours that exceed ``k_sig`` sds of their two widths (the RMS
    of the two sides: a step's corner station has a flat side and a steep one). 0 at
    invalid stations and where ``place_sd_mm`` is 0 (markers hold the pose to ~0.01 mm).

    Why: registered from point hints, the parallel tracks of the foreign printer's probe
    (bench/foreign_printer.py) sat 0.04-0.24 mm off along their length (the pose's own
    sd there: 0.08-0.28 mm), and the stations on the slow-to-fast width step (slope
    0.4-0.6) read 25-105 um off with sds of 6-7 um: 63 % of a right model's chi2 on 1 %
    of its stations."""
    track, s = np.asarray(track), np.asarray(s_mm, float)
    w, sd = np.asarray(w_mm, float), np.asarray(sd_mm, float)
    place = np.asarray(place_sd_mm, float)
    out = np.zeros(len(s))
    ok = np.asarray(valid, bool) & np.isfinite(w) & np.isfinite(sd) & (place > 0)
    for t in np.unique(track[ok]):
        i = np.flatnonzero((track == t) & ok)
        i = i[np.argsort(s[i], kind="stable")]
        if len(i) < 2:
            continue
        ss, ww, vv = s[i] - s[i].mean(), w[i], sd[i] ** 2     # centred: the sums cancel less
        # windowed least-squares slope and its variance sum((s_j - mean)^2 var_j) / Sxx^2,
        # every station's window at once from cumulative sums
        cum = [np.concatenate([[0.0], np.cumsum(v)])
               for v in (np.ones_like(ss), ss, ww, ss * ss, ss * ww, vv, ss * vv, ss * ss * vv)]
        lo = np.searchsorted(ss, ss - half_mm, "left")
        hi = np.searchsorted(ss, ss + half_mm, "right")
        n, sx, sy, sxx, sxy, sv, ssv, sssv = (q[hi] - q[lo] for q in cum)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = sx / n
            vxx = sxx - sx * mean
            g = (sxy - mean * sy) / vxx
            var_g = (sssv - 2 * mean * ssv + mean * mean * sv) / vxx ** 2
            g2 = np.where((n >= 3) & (vxx > 1e-12), np.maximum(g * g - var_g, 0.0), 0.0)
        ds = np.maximum(np.diff(ss), 1e-6)
        dw2 = np.diff(ww) ** 2
        step = (dw2 > k_sig ** 2 * (vv[1:] + vv[:-1])) & (ds <= 2 * half_mm)
        side = np.where(step, (dw2 - vv[1:] - vv[:-1]) / ds ** 2, 0.0)
        both = (np.concatenate([[0.0], side]) + np.concatenate([side, [0.0]])) / 2
        out[i] = np.sqrt(np.maximum(g2, both))
    return out * np.where(ok, place, 0.0)


def _scatter_factor(track, w, sd, valid, rho=None) -> float:
    """Factor >= 1 on the fit sd so that it explains the observed station-to-station scatter:
    the station's own error (``width_sd_own_mm``), what the fit's white term takes.

    Second differences d2 = w[i-1] - 2 w[i] + w[i+1] along a track remove the smooth
    (physical) width changes; for errors whose neighbours correlate by rho_i (station i with
    i - 1; ``rho``, :func:`neighbour_corr`, None: 0) and no further, var(d2) =
    (6 - 4 (rho_i + rho_(i+1))) sd^2: 6 sd^2 for independent ones, 2.4 sd^2 despeckled
    (dividing by 6 there read the own error 1.6x small). The fit sd misses
    correlated noise (JPEG blocks, texture), which shows up here. Robust (MAD) so steps
    and blobs do not count.
    """
    same = (track[1:-1] == track[:-2]) & (track[1:-1] == track[2:])
    ok = same & valid[1:-1] & valid[:-2] & valid[2:]
    if ok.sum() < 30:
        return 1.0
    r = np.zeros(len(track)) if rho is None else np.asarray(rho, dtype=float)
    d2 = ((w[:-2] - 2 * w[1:-1] + w[2:]) / np.sqrt(6.0 - 4.0 * (r[1:-1] + r[2:])))[ok]
    observed = 1.4826 * np.median(np.abs(d2 - np.median(d2)))
    predicted = np.median(sd[1:-1][ok])
    return float(max(1.0, observed / predicted)) if predicted > 0 else 1.0


def calibrated_sd(track, s_mm, w, sd, valid, lag_mm: float = SD_LAG_MM, bins: int = SD_BINS):
    """Per-station sd (mm) rescaled so that it explains the scatter the scan itself shows:
    sd' = sqrt((k sd)^2 + f^2), k >= 1, f >= 0 (mm). Returns (sd', k, f).

    Second differences d_i = w(s_i - L) - 2 w(s_i) + w(s_i + L) along a track remove the
    smooth (physical) width changes; for errors independent over L their variance is
    v_i = sd(s_i - L)^2 + 4 sd(s_i)^2 + sd(s_i + L)^2 when the sds are right, and
    k^2 v_i + 6 f^2 under the model. Stations are put in ``bins`` quantile bins of v; in
    each the robust variance of d (``SD_QUANTILE`` of |d|, steps and blobs do not count)
    gives one equation, and k^2 - 1 and f^2 come from non-negative least squares: a scale
    where the errors grow with the formal sd, a floor where they do not. Never below the
    edge fit's own sd (k, f = 1, 0 when the scatter is smaller or there are < 30 stations a bin).

    Why a floor and a lag of L = ``SD_LAG_MM`` (1 mm then; 2 mm since the strips are
    despeckled, see SD_LAG_MM), not one factor on adjacent stations:
    on 600 dpi renders with every phenomenon (bench_realism) the errors are 3.4-7 um
    whatever the formal sd (2-14 um) and correlated between neighbours (0.29-0.5 at
    0.25 mm): one factor from adjacent stations (1.7) left the smallest-sd fifth's errors at
    1.6 x their sd and the largest at 0.5 x; this gives 0.94 and 0.75 (k 1.05, f 3.3 um;
    Bowden 0.89 and 0.78; light-plate JPEG 1.80 / 1.18 -> 1.33 / 1.19 with k 3.0, f 8.5 um).
    """
    track, s_mm, w, sd = (np.asarray(a) for a in (track, s_mm, w, sd))
    valid = np.asarray(valid, dtype=bool)
    triples = []                # (before, station, after) indices
    for tid in np.unique(track[valid]):
        on = np.flatnonzero((track == tid) & valid)
        if len(on) < 3:
            continue
        on = on[np.argsort(s_mm[on], kind="stable")]
        s = s_mm[on]
        # the valid stations nearest L before and after (flags leave gaps in the grid)
        a, b = _nearest(s, s - lag_mm), _nearest(s, s + lag_mm)
        ok = (np.abs(s[a] - (s - lag_mm)) < 0.25 * lag_mm) & (np.abs(s[b] - (s + lag_mm)) < 0.25 * lag_mm)
        triples.append(np.column_stack([on[a[ok]], on[ok], on[b[ok]]]))
    if not triples or sum(len(x) for x in triples) < 30 * bins:
        return sd, 1.0, 0.0
    i, j, k_ = np.concatenate(triples).T
    d = w[i] - 2 * w[j] + w[k_]
    d = d - np.median(d)
    v = sd[i] ** 2 + 4 * sd[j] ** 2 + sd[k_] ** 2
    good = np.isfinite(d) & np.isfinite(v)
    d, v = d[good], v[good]
    if len(d) < 30 * bins:
        return sd, 1.0, 0.0
    c = 1.0 / special.ndtri(0.5 + SD_QUANTILE / 2)
    edges_v = np.quantile(v, np.linspace(0.0, 1.0, bins + 1))
    keep = np.ones(len(d), bool)
    for _ in range(2):
        A, y = [], []
        for b0, b1 in zip(edges_v[:-1], edges_v[1:]):
            m = (v >= b0) & (v <= b1) & keep
            if m.sum() < 10:
                continue
            vm = np.mean(v[m])      # rows in units of their own variance: each bin counts alike
            A.append([1.0, 6.0 / vm])
            y.append((c * np.quantile(np.abs(d[m]), SD_QUANTILE)) ** 2 / vm - 1.0)
        if len(A) < 2:
            return sd, 1.0, 0.0
        (k2m1, f2), _ = optimize.nnls(np.array(A), np.array(y))
        # second pass without the flow steps and blobs the first one still counted (4 %
        # of the stations of a track with one step 1 mm either side of it read k 1.02-1.07
        # for 1.00): beyond 4 sd of the model they are not measurement error
        keep = np.abs(d) <= 4.0 * np.sqrt((1.0 + k2m1) * v + 6.0 * f2)
    k, f = float(np.sqrt(1.0 + k2m1)), float(np.sqrt(f2))
    return np.sqrt((k * sd) ** 2 + f ** 2), k, f


def _nearest(s, target):
    """Index of the element of the sorted ``s`` nearest each ``target``."""
    idx = np.clip(np.searchsorted(s, target), 1, len(s) - 1)
    return np.where(np.abs(s[idx - 1] - target) <= np.abs(s[idx] - target), idx - 1, idx)


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
