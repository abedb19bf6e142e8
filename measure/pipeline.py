"""Picture -> widths table, QA overlay and summary: the whole of ``calib measure``.

``measure_scan(image_path, manifest, points=None, overlay_path=None) -> MeasureResult``:
load (measure.imageio), register (measure.register), measure the widths (measure.widths),
draw the overlay (measure.overlay) and summarise. Writes nothing but the overlay; the
caller saves the CSV and summary (so a failed check leaves no partial output).
"""
from __future__ import annotations

import json
from pathlib import Path
from collections import Counter
from dataclasses import dataclass

import numpy as np

from calib.errors import UserError
from calib.fileio import atomic_write_text
from measure.imageio import jpeg_chroma_subsampled, load_image
from measure.placement import Placement, along_track_warning, placement, track_speeds
from measure.register import FiducialsNotFound, Registration, register
from measure.shadows import SHADOW_LEFT_SHARE
from measure.table import WidthTable
from measure.widths import DETECTABLE_SNR, WidthMeasurement, measure_widths

#: Below this fraction of valid samples the picture is probably not of this pattern.
MIN_VALID_FRACTION = 0.2
#: Below this scale a 0.4 mm bead spans < 4 px and the edge pair's width and blur cannot be
#: told apart (a 200 dpi scan: 7.9 px/mm); 300 dpi is 11.8 px/mm.
MIN_PX_PER_MM = 10.0
#: Flags of a station the edge fit could not read (measure/table.py), as opposed to one a
#: label, a crossing or the picture's border took: measure/calibrate.py MIN_MEASURED_SHARE.
EDGE_FIT_FAILED = ("fit", "isolated", "missing", "faint", "dropout")
#: The width reference is "in glare" when more of its valid stations than this carry a streak.
GLARE_REFERENCE_SHARE = 0.5
#: A scan whose widths scatter this many times their edge fits' sd, or by this floor (mm),
#: gets a warning line (measure/station_sd.py calibrated_sd: 1.05x and 3.3 um on a 600 dpi
#: flatbed PNG render with every phenomenon, 3.0x and 8.5 um on its light-plate JPEG,
#: ~2.1x on a 12 MP phone photo at 35 deg)
NOISY_SD_SCALE = 2.0
NOISY_SD_FLOOR_MM = 0.005
#: Share of ``faint`` stations (measure/widths.py DETECTABLE_SNR) above which a line says so.
FAINT_WARN_FRACTION = 0.05
#: Share of ``background`` stations (over print on the plate) above which a line says so.
BACKGROUND_WARN_FRACTION = 0.05


class MeasureRefused(UserError):
    """The picture was registered and measured, but the result fails a check: the
    partial ``result`` still lets the CLI write the QA overlay and summary that show why."""

    def __init__(self, message: str, result):
        super().__init__(message)
        self.result = result


@dataclass
class MeasureResult:
    table: WidthTable
    registration: Registration
    summary: dict
    measurement: WidthMeasurement | None = None
    color: np.ndarray | None = None      # the picture (BGR uint8), for a later overlay
    placement: Placement | None = None   # the printer's track placement (measure/placement.py)


def measure_scan(image_path, manifest, points=None, overlay_path=None, *,
                 max_residual_mm: float | None = None) -> MeasureResult:
    """Measure the bead widths of ``manifest``'s test tracks in the picture ``image_path``.

    points           optional point hints "x_mm,y_mm=u_px,v_px;..." (prints without fiducials)
    overlay_path     write the QA overlay PNG there
    max_residual_mm  raise UserError when the registration residual exceeds it
    """
    if not manifest.test_tracks():
        raise UserError("the manifest has no test tracks to measure; make it with `calib pattern` or `calib plan`")
    luma, color = load_image(image_path)
    reg = _register(luma, manifest, points)
    # widths are measured on the channel that best tells bead from plate (grey unless a
    # coloured bead on a grained plate separates much better in colour: measure/contrast.py)
    from measure.contrast import bead_channel, retry_in_colour
    halved = jpeg_chroma_subsampled(image_path)
    gray, channel = bead_channel(luma, color, manifest, reg, chroma_halved=halved)
    if reg.method.startswith("auto"):
        # the automatic pose is refined once more on the bead centres it measures (ICP;
        # with stations every 1 mm instead of 0.25 mm the flatbed render's pose was 30x
        # worse, so the full measurement runs twice)
        import time

        from measure.autoreg import refine_with_centres
        t0 = time.perf_counter()
        m0 = measure_widths(gray, manifest, reg, color=color, colour_axis=channel)
        t = m0.table
        reg = refine_with_centres(reg, t.x_mm, t.y_mm, m0.nx, m0.ny, m0.centre_mm, t.valid, t.track)
        reg.info["time_s"] = reg.info.get("time_s", 0.0) + time.perf_counter() - t0
    meas = measure_widths(gray, manifest, reg, color=color, colour_axis=channel)
    # grey's widths turned out loose: the colour trial the contrast alone did not call for
    retry = retry_in_colour(luma, color, manifest, reg, channel, meas.table, chroma_halved=halved)
    if retry is not None:
        gray, channel = retry
        if channel.used:
            meas = measure_widths(gray, manifest, reg, color=color, colour_axis=channel)
    table = meas.table
    # the blur each width was read with: the apparent width of a rounded bead depends on it
    # (fit/effects.py ViewBlur)
    table.blur_mm = np.asarray(meas.blur_mm, dtype=float).copy()
    # where the glare comes from: each station's angle to the light, for the fit's
    # view_light (measure/glare.py)
    from measure.glare import angle_to_light_deg, light_axis
    axis = light_axis(meas.nx, meas.ny, meas.glare_streak) if meas.glare_streak is not None else None
    if axis is not None:
        table.light_angle_deg = angle_to_light_deg(meas.nx, meas.ny, axis)
    cal = apparent_width_calibration(gray, color, manifest, reg, blur_prior_px=meas.blur_plane_px,
                                     test_measurement=meas, colour_axis=channel,
                                     luma=luma if channel.used else None)
    if cal.applied:   # physical = apparent - b0 (measure/calibrate.py); missing beads stay 0
        own = cal.heading_levels_mm if cal.heading_levels_mm is not None else 0.0
        table.width_mm = np.where(table.width_mm > 0, table.width_mm - cal.offset_mm - own, table.width_mm)
        if cal.heading_levels_mm is not None and meas.lamp_sd_mm is not None:   # most of the lamp's part is out
            table.width_sd_mm = np.sqrt(np.maximum(table.width_sd_mm ** 2 - (1 - SHADOW_LEFT_SHARE ** 2)
                                                   * meas.lamp_sd_mm ** 2, 0.0))
    elif cal.heading_levels_mm is not None:
        # a lamp's shadow no shelf could model: its heading levels still come off (the
        # widths stay apparent, at the test tracks' mean heading, for the fit's scan_bias)
        table.width_mm = np.where(table.width_mm > 0, table.width_mm - cal.heading_levels_mm, table.width_mm)
    valid_frac = float(np.mean(table.valid)) if len(table) else 0.0
    # Registration from points has no corner misfit: its residual is the RMS offset of
    # the measured bead centres from the registered centre lines (robust: central 90 %).
    good = table.valid & np.isfinite(meas.centre_mm)
    if good.sum() >= 10:
        c = meas.centre_mm[good]
        c = c[np.abs(c) <= np.percentile(np.abs(c), 90)]
        reg.track_offset_rms_mm = float(np.sqrt(np.mean(c ** 2)))
    if reg.method.startswith("auto"):
        # automatic pose: the residual is the median distance of the detected bead centre
        # lines from the projected path (robust to the beads that are not where planned)
        reg.residual_mm = float(np.median(np.abs(meas.centre_mm[good]))) if good.sum() >= 10 else float("nan")
    if not np.isfinite(reg.residual_mm):
        reg.residual_mm = reg.track_offset_rms_mm
    # the residual counts the printer's own track placement too (measure/placement.py)
    place = placement(table.track, meas.centre_mm, meas.nx, meas.ny, table.valid, track_speeds(manifest))
    warnings = list(reg.warnings) + list(cal.warnings)
    along = along_track_warning(meas.place_sd_mm, meas.nx, meas.ny, table.valid, reg.method)
    if along:
        warnings.append(along)
    if valid_frac < 0.7:
        warnings.append(f"only {valid_frac:.0%} of the samples are valid; check the QA overlay")
    faint = float(np.mean(table.flag == "faint")) if len(table) else 0.0
    if faint >= FAINT_WARN_FRACTION:
        warnings.append(f"{faint:.0%} of the samples are too faint to tell bead from plate (the bead's "
                        f"contrast is under {DETECTABLE_SNR:g}x the plate texture's; grey on the QA overlay): "
                        "neither their widths nor their absence is used; a plain plate, even light or a "
                        "flatbed scan reads them")
    off_plate = float(np.mean(table.flag == "background")) if len(table) else 0.0
    if off_plate >= BACKGROUND_WARN_FRACTION:
        warnings.append(f"{off_plate:.0%} of the samples have something other than the bare plate beside the "
                        "bead (print on the plate, a sticker, a blob: red on the QA overlay, flag 'background'): "
                        "neither their widths nor their absence is used; where it is the plate's print, place "
                        "the pattern on a plain part of the plate")
    if channel.used and channel.chroma_restored:
        # the beads differ from the plate mostly in colour and this file kept a quarter of
        # it: on the light-plate render (every phenomenon, JPEG 70) the widths scatter
        # 22.8 um at 4:2:0 against 12.5 um at 4:4:4 and 9.1 um as a PNG, each station's edge
        # fit being limited by the chroma samples it has; no restoration gets that back
        warnings.append("the beads differ from the plate mostly in colour, which this JPEG keeps at half "
                        "resolution (4:2:0 chroma): the widths scatter about twice what a PNG/TIFF scan "
                        "(or a JPEG saved with 4:4:4 chroma) gives; rescan lossless for tighter widths")
    if meas.sd_scale >= NOISY_SD_SCALE or meas.sd_floor_mm >= NOISY_SD_FLOOR_MM:
        warnings.append(f"the widths scatter along the tracks {meas.sd_scale:.1f}x their edge fits' sd plus "
                        f"{meas.sd_floor_mm * 1000:.1f} um (JPEG blocks, plate grain, glare or focus; width_sd_mm "
                        "includes it): a lossless flatbed scan (PNG/TIFF) measures tighter, and so do several "
                        "photos with the lamp moved between them, measured together (calib measure A.jpg B.jpg "
                        "C.jpg: each station the mean of its readings)")
    ok = table.valid
    summary = {
        "schema": "calib.measure-summary/1",
        "image": str(image_path),
        "image_size_px": list(reg.image_size),
        "registration": {**reg.to_dict(), "placement": place.to_dict(),
                         # how far along its track a station may sit (mm, median of the valid
                         # stations; measure/register.py place_covariance): where the width
                         # changes along the track, width_sd_mm carries slope x this
                         "along_track_sd_mm": (float(np.median(meas.place_sd_mm[ok]))
                                               if meas.place_sd_mm is not None and ok.any() else None)},
        **table_figures(table),
        # valid stations whose edge pair carries a glare streak on one flank (measure/edges.py)
        "glare_streak_stations": int(meas.glare_streak[ok].sum()) if meas.glare_streak is not None else 0,
        # the light's axis as a bed direction (deg, 0-180) when the streaks agree on one
        "light_axis_deg": round(float(np.degrees(axis)) % 180.0, 1) if axis is not None else None,
        # the lamp's shadow beside the beads (measure/shadows.py)
        "shadows": meas.shadows.to_dict() if meas.shadows is not None else None,
        # the edge fits' sd scaled and floored by the widths' own scatter along the tracks
        # (measure/station_sd.py calibrated_sd); the fit's white term takes the own part
        "station_sd": {"scale": round(meas.sd_scale, 3), "floor_mm": round(meas.sd_floor_mm, 5),
                       "own_mm_median": (float(np.median(table.width_sd_own_mm[ok])) if ok.any() else None)},
        "blur_plane_px": [float(v) for v in meas.blur_plane_px],
        "measured_on": channel.to_dict(),
        "apparent_width": cal.to_dict(),
        "warnings": warnings,
    }
    if reg.info:
        summary["automatic_registration"] = reg.info
    result = MeasureResult(table=table, registration=reg, summary=summary, measurement=meas, color=color,
                           placement=place)
    refusal = reg.info.get("refusal")        # the automatic pose found nothing convincing
    ppmm = _resolution_px_per_mm(reg, table)
    summary["resolution_px_per_mm"] = ppmm
    if refusal is None and ppmm < MIN_PX_PER_MM:
        refusal = (f"the print is imaged at {ppmm:.1f} px/mm ({ppmm * 25.4:.0f} dpi): widths need at least "
                   f"{MIN_PX_PER_MM:g} px/mm; scan at 300-1200 dpi or take the photo closer")
    if refusal is None and valid_frac < MIN_VALID_FRACTION:
        refusal = (f"only {valid_frac:.0%} of the samples could be measured: the picture does not show "
                   "this pattern's tracks where the registration puts them (wrong pattern, or wrong "
                   "--points?)")
    elif refusal is None and max_residual_mm is not None and not (reg.residual_mm <= max_residual_mm):
        refusal = (f"registration residual {reg.residual_mm:.3f} mm is above --max-residual-mm "
                   f"{max_residual_mm:g}: re-take the picture flat and sharp, or give better --points")
    if refusal:
        summary["refused"] = refusal
        raise MeasureRefused(refusal, result)
    if overlay_path is not None:
        from measure.overlay import draw_overlay, save_overlay
        save_overlay(overlay_path, draw_overlay(color, manifest, reg, meas))
    return result


def table_figures(table: WidthTable) -> dict:
    """The summary's figures of a widths table: samples, valid (count and share), flags,
    median width and sd of the valid stations (mm), and per track the same."""
    ok = table.valid

    def median(x, m):
        return float(np.median(x[m])) if m.any() else None
    return {"samples": int(len(table)), "valid": int(ok.sum()),
            "fraction_valid": float(np.mean(ok)) if len(table) else 0.0,
            "flags": dict(sorted(Counter(f for f in table.flag if f).items())),
            "width_mm_median": median(table.width_mm, ok),
            "width_sd_mm_median": median(table.width_sd_mm, ok),
            "per_track": {str(t): {"valid": int((ok & (table.track == t)).sum()),
                                   "samples": int((table.track == t).sum()),
                                   "width_mm_median": median(table.width_mm, ok & (table.track == t))}
                          for t in np.unique(table.track)}}


def _resolution_px_per_mm(reg, table) -> float:
    """Median image scale (px/mm) over the test-track stations."""
    xy = np.column_stack([table.x_mm, table.y_mm])
    if not len(xy):
        return float("nan")
    return float(np.median(reg.px_per_mm(xy[:: max(1, len(xy) // 500)])))


def apparent_width_calibration(gray, color, manifest, reg, blur_prior_px=None, test_measurement=None,
                               colour_axis=None, luma=None):
    """measure/calibrate.py on the print's width-reference prime line, measured like the
    test tracks (a reference in glare gets a bracketed offset unless ``test_measurement``,
    the test tracks' WidthMeasurement, vouches for the streak model: measure/calibrate.py);
    an unapplied WidthCalibration saying why when the print has none.

    ``luma``: the picture's luminance when ``gray`` is a colour projection (measure/contrast.py).
    A glare streak is the lamp's white light, a luminance feature; the projection cancels
    luminance, except where a JPEG's halved chroma was restored with luminance as its guide,
    which copies luminance structure beside the edges. On the light-plate JPEG render that
    passed for a streak on 53 % of the reference's stations (3 % on the same scene as a PNG,
    none in luminance), the streak fits read the reference 35 um wide of its plain edges and
    the bracket between them (sd 18 um) was not applied. So the reference is in glare on a
    projection only when its luminance says so too.

    The offset read at the reference's heading is moved to the test tracks' mean heading,
    by how their own widths change with heading (measure/calibrate.py heading_shift): a
    photo at an angle foreshortens, a scanner's lamp lights beads along it unlike the rest."""
    from measure.calibrate import (WidthCalibration, calibrate, heading_shift, reference_stations,
                                   streak_consistency)
    from patterns.manifest import sample_points

    ref = reference_stations(manifest)
    if ref is None:
        return WidthCalibration(note="no apparent-width calibration: the print has no width-reference prime "
                                     "line (third-party G-code?); widths are apparent widths")
    smp, section, since, settle = ref
    # the reference's passes lie one way: whether the lamp casts shadows is the test tracks' call
    seen = test_measurement.shadows if test_measurement is not None else None
    shadows = seen.model if seen is not None and seen.model is not None else False
    m = measure_widths(gray, smp, reg, manifest=manifest, color=color, blur_prior_px=blur_prior_px,
                       colour_axis=colour_axis, shadows=shadows)
    h = float(np.nanmedian(smp.height_mm)) if len(smp) else 0.2
    ok = m.table.valid
    in_glare = bool(ok.any()) and m.glare_streak[ok].mean() > GLARE_REFERENCE_SHARE
    width = m.table.width_mm
    if in_glare and luma is not None:
        ml = measure_widths(luma, smp, reg, manifest=manifest, color=color, shadows=shadows)
        okl = ml.table.valid
        if not (okl.any() and ml.glare_streak[okl].mean() > GLARE_REFERENCE_SHARE):
            in_glare, width = False, m.plain_width_mm
    check = heading = levels = None
    tm = test_measurement
    photo = _is_photo(reg, manifest)
    nominal = sample_points(manifest).width_nominal_mm if tm is not None else None
    if tm is not None and len(nominal) == len(tm.table):
        t = tm.table
        if in_glare and tm.glare_streak is not None:
            tl = manifest.timeline
            speed = (np.interp(t.t_s, tl.t_s, tl.v_mm_s) if tl is not None and len(tl.t_s) > 1 else None)
            check = streak_consistency(t.track, t.t_s, nominal, t.width_mm, tm.plain_width_mm,
                                       tm.glare_streak, t.valid, speed_mm_s=speed)
        if ok.any():
            heading = heading_shift(t.track, t.s_mm, t.t_s, nominal, t.width_mm, t.valid, tm.nx, tm.ny,
                                    smp.nx[ok], smp.ny[ok], levels=True)
            if heading is not None:
                heading, levels = heading[:4], heading[4]
    cal = calibrate(width, ok, smp.width_nominal_mm, section, height_mm=h,
                    plain_width_mm=m.plain_width_mm if in_glare else None, streak_check=check,
                    t_s=smp.t_s, since_s=since, settle_s=settle, x_mm=smp.x_mm, photo=photo,
                    section_floor_mm=tm.sd_floor_mm if tm is not None else 0.0, heading=heading,
                    failed=np.isin(m.table.flag, EDGE_FIT_FAILED), blur_mm=m.blur_mm,
                    blur_sens_mm=m.width_per_rel_blur_mm, blur_rel_sd=_blur_doubt(m, tm))
    if cal.applied and seen is not None and seen.model is not None and levels is not None:
        # one lamp shades every bead across it a little (its far flank in its own shadow,
        # what the shelf leaves): each station's heading level comes off its width, not
        # only the mean's (600 dpi flatbed renders: +-5-9 um by heading against ~1 um sds)
        from dataclasses import replace
        cal = replace(cal, heading_levels_mm=levels)
    if seen is not None and seen.unresolved is not None and (cal.applied or cal.prior_ok):
        # the test tracks' beads carry a shadow the edge fits could not model, and the
        # reference's passes shade each other: its offset does not stand for them (a flatbed
        # render with defocus, translucent flanks and the lamp's shadow: applied, it left the
        # widths +55 um off with an sd of 4.7 um; with the heading levels too, -10 / +11 um
        # on seeds 3 / 1 of the PNG scan with every phenomenon). What each heading adds is
        # read from the test tracks themselves and still comes off: 11.1 -> 9.1 and 15.6 ->
        # 12.3 um RMS after the fit's scan_bias on those scans.
        from dataclasses import replace
        cal = replace(cal, applied=False, prior_ok=False, heading_levels_mm=levels,
                      note=cal.note + "; not applied: the beads carry a lamp's shadow the measurement could not model",
                      warnings=[*cal.warnings, "the beads show a dark band beside them on the side away from one "
                                "direction (a lamp's shadow) that the edge fits could not model (the picture is "
                                "blurred over it): widths across that direction read wider and the width "
                                "reference is not applied; scan with the print flat on the glass (in focus) or "
                                "photograph it in diffuse light"])
    return cal


def _blur_doubt(ref, test) -> float:
    """How far the blur the width reference was read with may be off, relative to it: the
    test tracks' blur plane's own error (measure/widths.py ``blur_rel_sd``), which the
    reference takes at its own level, or the reference's own spread without them."""
    for m in (test, ref):
        v = getattr(m, "blur_rel_sd", float("nan")) if m is not None else float("nan")
        if np.isfinite(v):
            return float(v)
    return float("nan")


def _is_photo(reg, manifest) -> bool:
    """Whether the picture's scale (px/mm) varies over the print by more than
    measure.register.PERSPECTIVE: a photo at an angle, not a scanner's affine mapping."""
    from measure.register import PERSPECTIVE
    from patterns.manifest import sample_points

    smp = sample_points(manifest, ds_mm=5.0, kinds=("test", "prime"))
    if len(smp) < 2:
        return False
    s = np.asarray(reg.px_per_mm(np.column_stack([smp.x_mm, smp.y_mm])), float)
    s = s[np.isfinite(s) & (s > 0)]
    return bool(len(s) >= 2 and s.max() / s.min() - 1.0 > PERSPECTIVE)


def _register(gray, manifest, points) -> Registration:
    """Fiducials, else the user's points, else the automatic pose (measure.autoreg): for
    third-party prints (no fiducials in the manifest) and when the markers are not found."""
    from measure.autoreg import auto_register

    if points is None and not manifest.fiducials:
        return auto_register(gray, manifest)
    try:
        return register(gray, manifest, points=points)
    except FiducialsNotFound as exc:
        reg = auto_register(gray, manifest)
        why = str(exc).split(":")[0]          # "found 1 of the pattern's 4 fiducials (need >= 2)"
        if reg.info.get("refusal"):
            reg.info["refusal"] = f"{why}, and {reg.info['refusal']}"
        reg.warnings.append(f"{why}; registered automatically from the track layout instead")
        return reg


def summary_path_for(widths_path):
    """``widths.csv`` -> ``widths.summary.json``: the summary `calib measure` always writes
    next to the widths, which `calib fit` reads for the apparent-width calibration."""
    p = Path(widths_path)
    return p.with_name(p.stem + ".summary.json")


def save_summary(path, summary: dict) -> None:
    atomic_write_text(path, json.dumps(summary, indent=1, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
