"""What `calib measure` said about its widths, as the fit needs it.

`calib measure` writes ``WIDTHS.summary.json`` next to every widths CSV; its
``apparent_width`` block (measure/calibrate.py) says whether the widths were corrected
from apparent to physical width and how well the edge offset b0 is known. The fit uses it
in two ways (issue #11 item 5, first step):

* the prior of the scan's ``scan_bias.b0_mm`` (fit/effects.py ScanBias) when the model has
  that effect: normal(0, max(sd_b0, 1 um)) for calibrated widths (the offset left is the
  calibration's own error), normal(0, UNCALIBRATED_SD_MM) for apparent widths (an edge
  offset of tens of um, measured on realistic renders: bench_realism), or normal(b0, sd_b0)
  when the reference measured the offset but too loosely to correct the widths with it
  (``prior_ok``, sd_b0 above measure/calibrate.py MAX_OFFSET_SD_MM) and more tightly than
  UNCALIBRATED_SD_MM: on the light-plate JPEG render -39 +- 12 um where the test tracks'
  offset was -38, and on ten JPEGs of a smaller print within 1.1 sd on eight, 1.8 and 2.3
  on two (the sds from the sections' floor, measure/calibrate.py);
* a caution in the trust verdict when a scan's widths are apparent and the model has no
  ``scan_bias``: an offset common to all widths can pass for back-pressure or flow.

Its ``registration`` block's ``along_track_sd_mm`` (how far along their tracks the pose may
have put the stations, measure/autoreg.py icp_covariance) is the prior sd of the scan's
``view_shift`` (fit/effects.py ViewShift), which ``--model auto`` starts with when that sd
reaches ALONG_SD_MM.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: Prior sd (mm) of scan_bias.b0_mm for widths that are not calibrated.
UNCALIBRATED_SD_MM = 0.03
#: Floor (mm) on the prior sd from a calibration.
MIN_SD_MM = 0.001
#: An applied calibration whose offset is known only to this sd (mm) or worse leaves
#: ``--model auto`` a width offset to carry (:func:`auto_start`): every photo at an angle
#: (its place doubt alone is 10 um: measure/calibrate.py PHOTO_OFFSET_SD_MM); flatbed
#: scans read 1-6.3 um (bench_realism, bench_e2e's Bowden seeds, 2026-11-27).
AUTO_SCAN_BIAS_SD_MM = 0.008
#: A scan whose stations the pose places along their tracks only to this sd (mm, the
#: median the summary gives) or worse gets ``view_shift`` from ``--model auto``: the
#: threshold at which `calib measure` says so (measure/placement.py ALONG_SD_WARN_MM).
ALONG_SD_MM = 0.05
#: Floor (mm) on view_shift's prior sd: a pose held by markers says ~0.01 mm.
MIN_SHIFT_SD_MM = 0.005


def load_calibration(widths_path) -> dict | None:
    """The ``apparent_width`` block of the summary next to ``widths_path`` (None if there is
    no readable summary: widths from elsewhere, or an older calib)."""
    p = Path(widths_path)
    s = p.with_name(p.stem + ".summary.json")
    try:
        doc = json.loads(s.read_text())
    except (OSError, ValueError):
        return None
    cal = doc.get("apparent_width") if isinstance(doc, dict) else None
    return cal if isinstance(cal, dict) else None


def load_along_sd(widths_path) -> float | None:
    """The median along-track sd (mm) of the stations' place that the summary next to
    ``widths_path`` gives (None if there is none)."""
    p = Path(widths_path)
    try:
        doc = json.loads(p.with_name(p.stem + ".summary.json").read_text())
        v = float(doc["registration"]["along_track_sd_mm"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return v if np.isfinite(v) and v >= 0 else None


def scan_states(data) -> list[dict]:
    """Per scan of ``data`` (fit.data.FitData): name, widths path, calibration block or None,
    and the along-track sd of its stations' place (mm) or None."""
    return [scan_state(sc.name, (getattr(sc, "source", None) or {}).get("widths")) for sc in data.scans]


def scan_state(scan: str, widths_path) -> dict:
    """One entry of :func:`scan_states`: scan ``scan`` measured into ``widths_path`` (None:
    widths from nowhere known)."""
    w = widths_path
    return {"scan": scan, "widths": w, "calibration": load_calibration(w) if w else None,
            "along_sd_mm": load_along_sd(w) if w else None}


def measured_offset(cal: dict) -> tuple[float, float] | None:
    """(b0, sd) in mm that a calibration block not applied still says of its apparent widths
    (``prior_ok`` and an sd below UNCALIBRATED_SD_MM), else None."""
    if cal.get("applied") or not cal.get("prior_ok"):
        return None
    b0, sd = cal.get("offset_mm"), cal.get("offset_sd_mm")
    if b0 is None or sd is None or not (np.isfinite(b0) and 0 < sd < UNCALIBRATED_SD_MM):
        return None
    return float(b0), float(sd)


def b0_prior(cal: dict) -> dict:
    """The prior of ``scan_bias.b0_mm`` (fit.priors format) on widths whose measurement
    block is ``cal`` (module docstring)."""
    if cal.get("applied"):
        sd = cal.get("offset_sd_mm")
        return {"prior": "normal", "mu": 0.0, "sd": max(float(sd), MIN_SD_MM) if sd else UNCALIBRATED_SD_MM}
    m = measured_offset(cal)
    if m is not None:
        return {"prior": "normal", "mu": m[0], "sd": max(m[1], MIN_SD_MM)}
    return {"prior": "normal", "mu": 0.0, "sd": UNCALIBRATED_SD_MM}


def prior_overrides(states: list[dict], param_names) -> dict[str, dict]:
    """Prior overrides (fit.priors.load_priors_file format) for the scans' scan_bias.b0_mm
    and view_shift.dx_mm, dy_mm (normal(0, the along-track sd, floored at MIN_SHIFT_SD_MM))."""
    names = set(param_names)
    out = {}
    for st in states:
        cal = st["calibration"]
        for name in (f"scan_bias.b0_mm@{st['scan']}", "scan_bias.b0_mm"):
            if cal is not None and name in names:
                out[name] = b0_prior(cal)
                break
        sd = st.get("along_sd_mm")
        for p in ("dx_mm", "dy_mm"):
            for name in (f"view_shift.{p}@{st['scan']}", f"view_shift.{p}"):
                if sd is not None and name in names:
                    out[name] = {"prior": "normal", "mu": 0.0, "sd": max(float(sd), MIN_SHIFT_SD_MM)}
                    break
    return out


#: share of a scan's stations the reference band (>= 60 deg from the light) and one other
#: band of view_light must each hold for `--model auto` to start with it
LIGHT_MIN_SHARE = 0.1


def light_varies(angle_deg) -> bool:
    """Whether the flank's angle to the scan's light (the widths CSV's ``light_angle_deg`` at
    the scan's stations, deg; None or NaN: unknown) is known on half the stations and spans
    view_light's bands (fit/effects.py): the reference beyond 60 deg and one band within it
    each hold >= LIGHT_MIN_SHARE. A print of parallel lines has one angle for every bead, and
    the band offsets would then be one offset for all, read as flow or back-pressure."""
    if angle_deg is None:
        return False
    a = np.asarray(angle_deg, dtype=float)
    ok = np.isfinite(a)
    if a.size == 0 or ok.mean() < 0.5:
        return False
    share = np.bincount(np.minimum(a[ok] // 15.0, 4).astype(int), minlength=5) / ok.sum()
    return bool(share[4] >= LIGHT_MIN_SHARE and share[:4].max() >= LIGHT_MIN_SHARE)


def auto_start(scan: str, cal: dict | None, light: bool = False,
               along_sd_mm: float | None = None) -> tuple[str, dict[str, dict]]:
    """(base model, prior overrides) where ``--model auto`` starts on a scan whose
    measurement block is ``cal``: ``pa+scan_bias`` with the prior above when the widths are
    apparent widths (its offset would otherwise be read as back-pressure or flow) or
    corrected by an offset known to AUTO_SCAN_BIAS_SD_MM or worse (a phone's: on the 35 deg
    Bowden render it was 23.5 um off, 2 sd, and bench_e2e's phone fits, whose 90 % intervals
    held tau on 91.7 % of 24 seeds, all carried scan_bias), else ``pa``; ``+view_light`` when ``light`` (:func:`light_varies`): beads whose flank faces a
    flatbed's lamp read ~2.5 um wider, and on bench_e2e's back-pressure scans that pulled Kb
    high (with it, 40 seeds: Kb 0.0034 lower on 39, tau 0.0007 s higher on 37, Kb's 90 %
    coverage 85 -> 90 %, tau's 95 % both); ``+view_shift`` with its prior when the pose
    places the stations along their tracks only to ``along_sd_mm`` >= ALONG_SD_MM."""
    tail = "+view_light" if light else ""
    shift = along_sd_mm is not None and along_sd_mm >= ALONG_SD_MM
    if shift:
        tail += "+view_shift"
    state = [{"scan": scan, "calibration": cal, "along_sd_mm": along_sd_mm}]
    shift_names = ["view_shift.dx_mm", "view_shift.dy_mm"] if shift else []
    if cal is None or (cal.get("applied") and not (cal.get("offset_sd_mm") or 0.0) >= AUTO_SCAN_BIAS_SD_MM):
        return "pa" + tail, prior_overrides(state, shift_names)
    return "pa+scan_bias" + tail, prior_overrides(state, ["scan_bias.b0_mm", *shift_names])


def priors_for(scan: str, widths_path) -> dict[str, dict]:
    """The prior overrides `calib fit` gives scan ``scan``'s ``scan_bias.b0_mm`` and
    ``view_shift`` from what `calib measure` wrote beside ``widths_path``
    (:func:`prior_overrides`), for whichever model has them: `calib diagnose` and `calib
    compare` fit with them too, so their tables rank the models `calib fit` would fit. A
    phone scan's apparent widths diagnosed without them read reduced chi-square 90 for the
    `pa+scan_bias+view_light` that `calib fit` fitted at 26: the offset's default prior,
    0 +- 5 um, held it at -27 um where the reference said -48 +- 16."""
    return prior_overrides([scan_state(scan, widths_path)],
                           ["scan_bias.b0_mm", "view_shift.dx_mm", "view_shift.dy_mm"])


def start_for(scan, widths_path) -> tuple[str, dict[str, dict]]:
    """:func:`auto_start` for ``scan`` (fit.data.ScanData observed from the widths CSV
    ``widths_path``), read from what `calib measure` wrote beside those widths."""
    return auto_start(scan.name, load_calibration(widths_path),
                      light_varies(scan.table.light_angle_deg[scan.table.valid]),
                      load_along_sd(widths_path))


def notes(states: list[dict], has_scan_bias: bool, has_view_shift: bool = False) -> list[str]:
    """One plain sentence per scan whose widths are apparent widths, and per scan whose
    stations the pose places along their tracks only to ALONG_SD_MM or worse when the model
    has no ``view_shift``."""
    out = []
    for st in states:
        sd = st.get("along_sd_mm")
        if not has_view_shift and sd is not None and sd >= ALONG_SD_MM:
            out.append(f"{st['scan']}: the picture places its stations along their tracks only to +-{sd:.2f} mm, "
                       "one shift for all of them that the fit reads as tau or a delay: add view_shift to the "
                       "model")
    for st in states:
        cal = st["calibration"]
        if cal is None or cal.get("applied"):
            continue
        m = measured_offset(cal)
        tail = ("an offset common to all widths can pass for back-pressure or flow: add scan_bias to the model"
                if not has_scan_bias else "scan_bias carries it with a wide prior" if m is None else
                f"scan_bias carries it with the reference's {m[0] * 1000:+.0f} +- {m[1] * 1000:.0f} um as its prior")
        why = (cal.get("note") or "not calibrated").split(";")[0]
        out.append(f"{st['scan']}: widths are apparent widths ({why}); {tail}")
    return out


def scatter(scan, wobble_rel: float | None = None) -> dict:
    """How much of one scan's width error its stations share with their neighbours, against
    what the misfit check allows the bead (fit/result.py chi2_nu_bead), all in mm.

    own_sd_mm     median sd the fit weighs each station by (``width_sd_own_mm``)
    shared_sd_mm  median sqrt(width_sd_mm^2 - own^2): the part of the calibrated sd
                  (measure/station_sd.py ``calibrated_sd``: the widths' second differences
                  along the tracks) that neighbours share: plate texture, JPEG blocks,
                  glare, focus
    wobble_allowed_mm  WOBBLE_REL_MAX x the median width: the bead wobble chi2_nu_bead
                  accepts beyond the own sd
    chi2_nu_bead_expected  (own^2 + shared^2 + allowed^2) / (own^2 + allowed^2): what a
                  model that is right reads on these widths, the measurement alone

    On a phone photo of a sparkling textured plate (the direct-drive spiral, `--realism
    all,sparkle`) the shared part was 29 um against 13 allowed, expected 2.3; the right
    model's fits of bench_e2e's sparkle case read chi2_nu_bead 2.6-3.1 and were refused
    as misfits. Over the valid stations of ``scan`` (fit.data.ScanData).
    """
    from fit.result import WOBBLE_REL_MAX

    rel = WOBBLE_REL_MAX if wobble_rel is None else wobble_rel
    t = scan.table
    idx = scan.order
    whole = np.asarray(t.width_sd_mm, float)[idx]
    own = np.asarray(t.fit_sd_mm(), float)[idx]
    ok = np.isfinite(whole) & np.isfinite(own)
    if not ok.any():
        return {}
    o = float(np.median(own[ok]))
    sh = float(np.median(np.sqrt(np.maximum(whole[ok] ** 2 - own[ok] ** 2, 0.0))))
    a = rel * float(np.median(np.abs(scan.y_mm))) if len(scan.y_mm) else 0.0
    den = o * o + a * a
    return {"own_sd_mm": o, "shared_sd_mm": sh, "wobble_allowed_mm": a,
            "chi2_nu_bead_expected": float((den + sh * sh) / den) if den > 0 else float("nan")}


def picture_widths(scan) -> bool:
    """Whether the widths of ``scan`` (fit.data.ScanData) were measured from a picture:
    `calib measure` gives every station its edge blur and the part of its sd that is its
    own (measure/table.py). Widths from elsewhere (a simulation with white noise, calipers)
    have neither, and no error shared by a whole track (fit/covariates.py score_covariates
    ``within_tracks``)."""
    t = scan.table
    return bool(np.isfinite(np.asarray(t.width_sd_own_mm, float)).any()
                or np.isfinite(np.asarray(t.blur_mm, float)).any())


def chi2_nu_expected(scan) -> float:
    """The reduced chi-square a right model reads on ``scan`` from its measurement alone,
    weighed as the fit weighs it (by each station's own sd, ``width_sd_own_mm``):

        E[chi2_nu] = mean_i (width_sd_i / own_i)^2

    ``width_sd_mm`` is calibrated on the widths' second differences along the tracks
    (measure/station_sd.py ``calibrated_sd``): the scatter the stations share with their
    neighbours (plate texture, JPEG blocks, glare, the bead's own short wobble) as well as
    their own. 1 for widths with white noise of known sd; 1.8-3.5 on the foreign probe
    prints rendered on a 600 dpi flatbed with every phenomenon (bench_discover_foreign). A
    misfit is what exceeds it (fit/diagnose.py). Scatter over longer stretches (the bead's
    slow wobble, the light over the picture) is not in it: the probe's right model read
    chi2_nu 3.4-21 times it there (docs/DISCOVER.md). NaN without sds; over the valid
    stations of ``scan``."""
    t = scan.table
    idx = scan.order
    whole = np.asarray(t.width_sd_mm, float)[idx]
    own = np.asarray(t.fit_sd_mm(), float)[idx]
    ok = np.isfinite(whole) & np.isfinite(own) & (own > 0)
    if not ok.any():
        return float("nan")
    return float(np.mean(np.maximum(whole[ok] / own[ok], 1.0) ** 2))
