"""stop-mid-path pattern (seed 000, KISSlicer Preload wizard).

Straight lines printed at head speed v0 until the extrusion is at steady state; then the
extruder stops mid-path while the head keeps moving, and the ooze that still flows lays a
decaying bead along the rest of the line. Seed 000: elastic ooze decays exponentially,
q(t) = q0 exp(-t / tau), tau = 32 D^2 L l / d^4 * VE. Variants (one row each):

* ``exp``    the feed is slowed along the expected decay, v(t) = v0 exp(-t / tau_guess),
             so the head has covered s(t) = v0 tau_guess (1 - exp(-t / tau_guess)); if
             tau_guess is right the ooze width stays constant (seed 000 Fig. 1), if not it
             grows or shrinks, which the fit reads. The ramp is written as segments of
             duration tau_guess / 8, each at its mean speed, so the head position matches
             s(t) exactly at every segment boundary. Runs for 3 tau_guess.
* ``const``  the head keeps v0: the ooze width decays as exp(-x / (v0 tau)) along x.
* ``wizard`` stop, pass the wiper (a fast 10 mm move: hold a card there to cut the
             string), wait 3 s at a fresh spot so the ooze pools into a blob, retract.
             Where to hold the card: before each wizard line the G-code shows
             ``M117 Hold card at X<x> Y<y>`` on the printer's display (Marlin, Klipper
             and RRF all take M117) with the same text as a ``;`` comment, while the
             steady part prints; (x, y) is the middle of the wipe move, 5 mm past the
             stop. A ``; WIPER ...`` comment marks the wipe move itself and ``M117 Remove
             card`` follows the retraction. The track's params hold ``card_xy_mm``.

The coasting part belongs to the track (zero-extrusion moves between TRACK/END_TRACK):
that is where the ooze is measured.

Widths: by default the lines alternate between 1.2 and 2 nozzle diameters (``width_mm``;
KISSlicer's wizard prints one). The bead's back-pressure Kb w_sat tanh(w / w_sat) (seed
001) is read along each ooze tail, whose width falls from the line's to 0; from 0.48 mm
alone that is the curve's nearly straight start, where Kb and w_sat are one direction
(Kb w_sat tanh(w / w_sat) ~ Kb w). Measured (session 46, Adventurer 3 Bowden truth: tau
0.8 s, thermal 0.05 over 25 s, Kb 1, w_sat 0.8 mm; relative Cramer-Rao sds of tau, Kb,
w_sat, thermal a and tau_s): one width 0.74 / 3.3 / 2.1 / 7.4 / 11 %, 0.48 and 0.8 mm
0.26 / 2.0 / 1.2 / 2.6 / 8.6 %. Rendered (600 dpi flatbed, every phenomenon) and fitted
with pa+backpressure+thermal+spread+scan_bias, the one-width print put w_sat on its 3 mm
bound with a second mode within 10 BIC on both seeds tried; the two-width print on none
of 4 (docs/TRUST.md, "The stop-mid-path print"). The wide lines need A(0.8, 0.2) /
A(0.48, 0.2) ~ 1.7x the narrow ones' flow at one speed (6.1 mm^3/s at 40 mm/s, h 0.2):
within a common hot end's melt rate.
"""
from __future__ import annotations

import numpy as np

from calib.errors import UserError
from fit.geometry import bead_area_mm2
from patterns import layout
from patterns.builder import PatternBuilder
from patterns.profile import load_profile

NAME = "stop-mid-path"
RAMP_SEGMENTS_PER_TAU = 8
COAST_TAUS = 3.0
WIPE_MM = 10.0
VARIANTS = ("exp", "const", "wizard")
#: default line widths in nozzle diameters, alternating over the lines (module docstring)
DEFAULT_WIDTHS_DN = (1.2, 2.0)


def exp_feed_ramp(v0_mm_s: float, tau_s: float, duration_s: float | None = None,
                  segments_per_tau: int = RAMP_SEGMENTS_PER_TAU):
    """Segment boundaries of the exponential feed ramp v(t) = v0 exp(-t / tau) (seed 000).

    Returns (t_s, s_mm, v_mm_s): boundary times, head distance since the stop at those
    times, s = v0 tau (1 - exp(-t / tau)), and the mean speed (mm/s) of each segment.
    """
    duration_s = COAST_TAUS * tau_s if duration_s is None else duration_s
    n = max(1, int(round(duration_s / tau_s * segments_per_tau)))
    t = np.linspace(0.0, duration_s, n + 1)
    s = v0_mm_s * tau_s * (1.0 - np.exp(-t / tau_s))
    v = np.diff(s) / np.diff(t)
    return t, s, v


def _rows(profile, speeds, taus, variants, steady_s, tau0, widths_mm, h):
    """One dict per printed line; the widths (mm) alternate over the lines in order."""
    rows = []
    for v0 in speeds:
        for var in variants:
            for tau in (taus if var == "exp" else [tau0]):
                if var == "exp":
                    coast = v0 * tau * (1 - np.exp(-COAST_TAUS))
                    label = f"{v0:g}mm/s {tau:.2g}s"
                elif var == "const":
                    coast = v0 * COAST_TAUS * tau
                    label = f"{v0:g}mm/s const"
                else:
                    coast = WIPE_MM
                    label = f"{v0:g}mm/s wiper"
                w = float(widths_mm[len(rows) % len(widths_mm)])
                rows.append(dict(v0=v0, tau=tau, variant=var, steady_mm=v0 * steady_s, coast_mm=coast,
                                 length_mm=v0 * steady_s + coast, label=label, group=f"{v0:g}", width_mm=w))
    return rows


def generate(profile, *, speeds_mm_s=(20.0, 40.0), tau_s=None, variants=VARIANTS, steady_s=None,
             width_mm=None, layer_height_mm=0.2, wizard_wait_s=3.0):
    """G-code and manifest of the stop-mid-path pattern.

    speeds_mm_s  head speeds v0 (mm/s) of the printed part
    tau_s        ooze time constants guessed for the ``exp`` ramps (s); default the
                 seed 000 estimate for this printer times 0.5, 1, 2
    variants     any of exp, const, wizard
    steady_s     printing time before the stop (s); default max(2 s, 4 tau), shortened to fit
    width_mm     bead width (mm), or several that alternate over the lines in order;
                 default DEFAULT_WIDTHS_DN nozzle diameters
    wizard_wait_s  wizard variant: wait after the wipe (s); the display (M117) says where
                 to hold the wiper card, see the module docstring
    """
    profile = load_profile(profile)
    speeds = [float(v) for v in np.atleast_1d(speeds_mm_s)]
    tau0 = layout.tau_guess_s(profile)
    taus = [float(t) for t in np.atleast_1d(tau_s)] if tau_s is not None else [round(f * tau0, 4) for f in (0.5, 1.0, 2.0)]
    variants = [variants] if isinstance(variants, str) else list(variants)
    bad = [v for v in variants if v not in VARIANTS]
    if bad or not variants:
        raise UserError(f"stop-mid-path: unknown variant {bad[0] if bad else '(none)'}: use {', '.join(VARIANTS)}")
    if min(speeds) <= 0 or min(taus) <= 0:
        raise UserError("stop-mid-path: --speeds and --tau must be > 0")
    if max(speeds) > profile.max_velocity_mm_s:
        raise UserError(f"stop-mid-path: speed {max(speeds):g} mm/s exceeds the printer's max "
                        f"{profile.max_velocity_mm_s:g} mm/s: reduce --speeds")
    for v0 in speeds:
        for tau in taus:
            # The ramp decelerates at v/tau; the planner (and printer) cannot follow faster.
            if "exp" in variants and v0 / tau > profile.max_accel_mm_s2:
                raise UserError(f"stop-mid-path: a feed ramp from {v0:g} mm/s with tau {tau:g} s needs "
                                f"{v0 / tau:.0f} mm/s^2, more than the printer's {profile.max_accel_mm_s2:g}: "
                                "use a larger --tau or lower --speeds")
    ws = ([float(x) for x in np.atleast_1d(width_mm)] if width_mm is not None
          else [round(f * profile.nozzle_diameter_mm, 2) for f in DEFAULT_WIDTHS_DN])
    if not ws or not all(np.isfinite(x) and x > 0 for x in ws):
        raise UserError(f"stop-mid-path: --width must be > 0 mm, got {', '.join(f'{x:g}' for x in ws)}")
    max_w, _ = layout.max_content_mm(profile)
    want_steady = float(steady_s) if steady_s is not None else max(2.0, 4.0 * tau0)
    probe = _rows(profile, speeds, taus, variants, 0.0, tau0, ws, layer_height_mm)
    room = max_w - 40.0 - max(r["coast_mm"] for r in probe)     # 40 mm: label column
    fit_steady = min(room / r["v0"] for r in probe)
    steady = want_steady if steady_s is not None else min(want_steady, fit_steady)
    if steady < 1.0 and steady_s is None:
        raise UserError(f"stop-mid-path: lines at {max(speeds):g} mm/s do not reach steady state on this "
                        "bed: reduce --speeds or --tau")
    params = {"speeds_mm_s": speeds, "tau_s": taus, "variants": variants, "steady_s": round(steady, 4),
              "width_mm": ws[0], "widths_mm": ws, "layer_height_mm": float(layer_height_mm),
              "wizard_wait_s": float(wizard_wait_s),
              "tau_printer_guess_s": round(tau0, 4)}
    rows = _rows(profile, speeds, taus, variants, steady, tau0, ws, layer_height_mm)
    frame = layout.place_rows(profile, NAME, rows, pitch_mm=5.0,
                              hint="reduce --speeds, --tau or --steady-s, or fewer --variants")
    b = PatternBuilder(profile, NAME, params, layer_height_mm=layer_height_mm, line_width_mm=ws[0])
    b.set_z(layer_height_mm)
    b.frame_prime(frame)
    for r in rows:
        w = r["width_mm"]
        q0 = float(bead_area_mm2(w, layer_height_mm))
        x0, y = r["start_xy"]
        xs = x0 + r["steady_mm"]
        tp = {"speed_mm_s": r["v0"], "variant": r["variant"], "width_mm": w,
              "flow_mm3_s": q0 * r["v0"], "stop_s_mm": r["steady_mm"]}
        if r["variant"] != "wizard":
            tp["tau_guess_s"] = r["tau"]
        else:
            card = (round(xs + WIPE_MM / 2, 1), round(y, 1))
            tp["card_xy_mm"] = list(card)
            b.writer.display_message(f"Hold card at X{card[0]:g} Y{card[1]:g}")
        r["track"] = b.begin("test", (x0, y), group=r["label"], params=tp)
        b.extrude([(x0, y), (xs, y)], w, r["v0"])
        if r["variant"] == "exp":
            _, s, v = exp_feed_ramp(r["v0"], r["tau"])
            b.coast(np.column_stack([xs + s, np.full_like(s, y)]), v)
        elif r["variant"] == "const":
            b.coast([(xs, y), (xs + r["coast_mm"], y)], r["v0"])
        else:
            b.writer.comment(f"WIPER: extrusion stopped; the head now wipes across the card held at "
                             f"X{card[0]:g} Y{card[1]:g} (mm), then waits {wizard_wait_s:g} s and retracts")
            b.coast([(xs, y), (xs + WIPE_MM, y)], profile.travel_speed)
            b.writer.dwell(wizard_wait_s)
            b.retract()
        b.end()
        if r["variant"] == "wizard":
            b.writer.display_message("Remove card")
    b.frame_furniture(frame, title="stop-mid-path")
    for r in rows:
        b.label(r["label"], r["label_xy"], height_mm=layout.ROW_LABEL_H_MM, for_tracks=[r["track"]])
    return b.build()
