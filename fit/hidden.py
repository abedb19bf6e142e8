"""Datasets with a hidden effect: the truth has one effect the fitted model lacks.

Used by the discovery tests and ``bench/bench_discover.py`` to show that
:func:`fit.diagnose.diagnose` finds what is missing.

The probe print (:func:`probe_manifest`) is a compact virtual test print built directly
as a timeline, so it is fast and self-contained: parallel straight tracks spread over the
bed (bed tilt), alternating direction (heading), one commanded width per track swept over
0.40-0.85 mm (back-pressure, seed 001 RetractTest "constant ve with varying w"), each
track slow (20 mm/s) for its first part and then fast (30-140 mm/s, speed sweep for
nonlinear flow and gear slip; the flow step is the linear-advance transient of seed 001),
with a mid-track stop of a few seconds (seed 000 ooze and its thermal tail) and a
retraction between tracks (backlash acts on the reversal), optionally after a prime line
that sets the extruder's state as a real print's purge line does. The head follows trapezoidal
speed profiles (constant acceleration), the extruder follows the head at constant width
(ve = A(w, h) v / Af, fit/geometry.py), sampled every <= 0.25 mm and <= 5 ms as the
Timeline contract asks.

Widths: the truth model's prediction at stations every ``ds_mm`` plus Gaussian
measurement noise of ``noise_mm`` (the edge-pair erf fit gives 2-5 um on scans,
REFERENCE "Measuring width"; 10 um adds bead roughness).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fit.geometry import bead_area_mm2, filament_area_mm2
from measure.table import WidthTable
from patterns.manifest import Manifest, Timeline, Track, sample_points

#: Where the worked user-effect example lives (its GearSlip effect is the "outside" truth).
EXAMPLES_DIR = Path(__file__).resolve().parent.parent / "data" / "examples"

#: Base truth shared by all hidden-effect cases (a Bowden printer, seed 000 range).
BASE_SPEC = "pa"
BASE_VALUES = {"pa.tau_s": 0.35}

#: Hidden effect -> values of its parameters in the truth. Sizes are typical of the
#: sources: thermal ooze 10-30x smaller than the elastic one with a tens-of-seconds time
#: constant (seed 000); Kb ~1 and saturation near 2x nozzle (seed 001); shear thinning
#: n ~0.3-0.5 (REFERENCE); backlash 0.4-1.2 mm (seed 001 logs); a 0.1 %/mm bed slope;
#: gear slip of a few % at 10 mm/s of filament (RRF M592 style).
HIDDEN: dict[str, dict[str, float]] = {
    "thermal": {"thermal.a": 0.3, "thermal.tau_s": 8.0},
    "backpressure": {"backpressure.kb": 1.5, "backpressure.w_sat_mm": 0.8},
    "nonlinear": {"nonlinear.n": 0.5},
    "backlash": {"backlash.be_mm": 0.8},
    "bed_tilt": {"bed_tilt.gx": 0.0006, "bed_tilt.gy": -0.0008},
    "gear_slip": {"gear_slip.a_s_mm": -0.004, "gear_slip.b_s2_mm2": -0.0006},
}

#: The covariates that point at each hidden effect (for "the top covariate is right").
RIGHT_COVARIATES = {
    "gear_slip": {"extruder_speed_mm_s", "flow_mm3_s"},
    "bed_tilt": {"x_mm", "y_mm", "r_mm"},
    "thermal": {"time_since_stop_s", "last_stop_duration_s"},
    "backpressure": {"width_nominal_mm"},
    "nonlinear": {"flow_mm3_s", "extruder_speed_mm_s", "time_since_flow_change_s"},
    "backlash": {"time_since_stop_s", "s_mm", "time_since_flow_change_s", "time_since_retract_s"},
}

#: Library effects that are alternative functional forms of the same physics.
FAMILIES = {"nonlinear": {"nonlinear", "bernoulli", "kalico_tanh", "kalico_recip"}}


def user_effects():
    """The example's user effect classes (data/examples/my_effects.py)."""
    from fit.effects import load_effects_file
    return load_effects_file(EXAMPLES_DIR / "my_effects.py")


def probe_printer() -> dict:
    return {"name": "probe-bowden", "filament_diameter_mm": 1.75, "nozzle_diameter_mm": 0.4,
            "nozzle_land_length_mm": 0.6, "bowden_length_mm": 200.0}


def _reference(emit, travel, t, e, pos, xa_mm, xb_mm, y_low_mm, tid, height_mm, printer, af):
    """Print the width reference (patterns/builder.py ``reference_line``) between x =
    ``xa_mm`` and ``xb_mm`` with its lowest pass at ``y_low_mm``, at its one volumetric flow
    and each section's head speed; returns (t, e, pos) at its end (not retracted) and its
    Track."""
    from types import SimpleNamespace

    from patterns.builder import REFERENCE_PASSES, REFERENCE_PITCH_MM, reference_line
    from patterns.layout import tau_guess_s

    prof = SimpleNamespace(**{k: printer.get(k, d) for k, d in (
        ("filament_diameter_mm", 1.75), ("bowden_length_mm", 0.0), ("nozzle_land_length_mm", 0.6),
        ("nozzle_diameter_mm", 0.4))})
    ref = reference_line(xa_mm, xb_mm, y_low_mm + (REFERENCE_PASSES - 1) * REFERENCE_PITCH_MM, REFERENCE_PASSES,
                         REFERENCE_PITCH_MM, prof.nozzle_diameter_mm, height_mm, tau_guess_s(prof))
    pts, s_node, cuts = ref.points_mm, ref.s_node_mm, ref.cuts_mm
    t = travel(t, pos, tuple(pts[0]))
    # arc length against time: each section at its own speed, the extruder at one rate
    t_cut = np.concatenate([[0.0], np.cumsum(np.diff(cuts) / np.asarray(ref.speeds_mm_s))])
    tq = np.unique(np.concatenate([np.arange(0.0, t_cut[-1], 0.004), t_cut]))
    sq = np.interp(tq, t_cut, cuts)
    k = np.clip(np.searchsorted(t_cut, tq, side="right") - 1, 0, len(ref.speeds_mm_s) - 1)
    vq = np.asarray(ref.speeds_mm_s)[k]
    ve = ref.flow_mm3_s / af
    emit(t + tq, np.interp(sq, s_node, pts[:, 0]), np.interp(sq, s_node, pts[:, 1]), vq,
         np.full(len(tq), ve), e + ve * tq, tid, sq)
    t, e = t + t_cut[-1], e + ve * t_cut[-1]
    # the track's vertices: the path's, and a pair at each section's start (the width steps there)
    s_v = np.unique(np.concatenate([s_node, cuts, cuts[1:-1] - 1e-4]))
    kv = np.clip(np.searchsorted(cuts, s_v, side="right") - 1, 0, len(ref.widths_mm) - 1)
    verts = np.column_stack([np.interp(s_v, s_node, pts[:, 0]), np.interp(s_v, s_node, pts[:, 1])])
    track = Track(id=tid, kind="prime", points_mm=verts, width_mm=np.asarray(ref.widths_mm)[kv],
                  height_mm=height_mm, flow_mm3_s=ref.flow_mm3_s, z_mm=height_mm, group="width reference",
                  params=ref.params())
    return t, e, np.array(pts[-1]), track


def probe_manifest(n_tracks: int = 8, length_mm: float = 60.0, height_mm: float = 0.2,
                   accel_mm_s2: float = 1500.0, stop_s=3.0, slow_mm_s: float = 20.0,
                   fast_mm_s=(30.0, 60.0, 100.0, 140.0), widths_mm=(0.40, 0.55, 0.70, 0.85),
                   gap_mm: float = 8.0, retract_mm: float = 1.0, prime_mm: float = 0.0,
                   printer: dict | None = None, stop_at=0.65, stop_retract=False,
                   reference: bool = False) -> Manifest:
    """The probe print described in the module docstring, as a Manifest with its timeline.

    ``stop_s`` (s) and ``stop_at`` (fraction of the track's length): the mid-track stop's
    length and place, one value or a sequence cycled over the tracks. With one of each
    (the default) every stop lasts as long and sits as far along its track, so the last
    stop's length, the time since a retraction and the arc length move together and no
    residual can tell them apart (fit/covariates.py aliases); cycled with periods prime to
    each other they do not. ``stop_retract`` (bool, or a sequence cycled likewise): the head
    retracts ``retract_mm`` at the start of that stop and unretracts at its end, as a
    slicer's retraction at a layer change or a wipe does, so that the time since a
    retraction and since a stop part.
    ``prime_mm``: a prime line (not a track: nothing is measured on it) printed at
    ``slow_mm_s`` before the first track, as a real print's purge line. Without it the
    first track depends on where the extruder's state begins, which no print can know: the
    library's dead band starts pushed forward, another printer's may start in the middle
    of its play, and the probe's first track then read 0.58 mm apart at its start with the
    same physics (bench/foreign_printer.py, backlash 0.8 mm; 60 mm of prime: 0 um). Off by
    default: data made by the library itself starts where the library does.
    ``reference``: print, instead of the prime line, the width reference every pattern of
    ours prints (patterns/builder.py ``reference_line``: a serpentine at one volumetric
    flow in sections of 2.5 and 1 nozzle diameters, above the tracks), a track of kind
    ``prime`` with id ``n_tracks`` that measure/calibrate.py calibrates a picture's
    apparent widths from. Without it a picture's widths carry an unknown edge offset, and
    a fit that frees it (``scan_bias``) also takes the part of a width-dependent effect
    that looks like one (bench_discover_foreign's rendered rows)."""
    printer = dict(printer or probe_printer())
    af = filament_area_mm2(printer["filament_diameter_mm"])
    x0 = -length_mm / 2
    y0 = -(n_tracks - 1) * gap_mm / 2
    nodes: dict[str, list] = {k: [] for k in Timeline.FIELDS}
    tracks = []
    t, e = 0.0, 0.0
    pos = np.array([x0 - 10.0, y0])

    def emit(tt, xx, yy, vv, vee, ee, trk, ss):
        for k, a in zip(Timeline.FIELDS, (tt, xx, yy, np.full(len(tt), height_mm), vv, vee, ee,
                                          np.full(len(tt), trk), ss)):
            nodes[k].append(np.asarray(a, dtype=float))

    def travel(t, pos, to):
        """Travel at 150 mm/s (retracted, no extrusion) from pos to ``to``; the end time."""
        d = float(np.hypot(to[0] - pos[0], to[1] - pos[1]))
        nt = max(2, int(np.ceil(d / 150.0 / 0.005)) + 1)
        tt = t + np.linspace(0, d / 150.0, nt)
        emit(tt, np.linspace(pos[0], to[0], nt), np.linspace(pos[1], to[1], nt), np.full(nt, 150.0),
             np.zeros(nt), np.full(nt, e), -1, np.full(nt, np.nan))
        return tt[-1]

    def move_e(t, at, sign):
        """Retract (sign -1) or unretract (+1) ``retract_mm`` in place at 30 mm/s; (t, e) after."""
        tt = t + np.linspace(0, retract_mm / 30.0, 8)[1:]
        emit(tt, np.full(7, at[0]), np.full(7, at[1]), np.zeros(7), np.full(7, sign * 30.0),
             e + sign * 30.0 * (tt - t), -1, np.full(7, np.nan))
        return tt[-1], e + sign * retract_mm

    if prime_mm > 0:
        start = (x0, y0 - gap_mm)
        t = travel(t, pos, start)
        area = float(bead_area_mm2(widths_mm[0], height_mm))
        nt = int(np.ceil(prime_mm / slow_mm_s / 0.004)) + 1
        tq = np.linspace(0.0, prime_mm / slow_mm_s, nt)
        emit(t + tq, x0 + slow_mm_s * tq, np.full(nt, start[1]), np.full(nt, slow_mm_s),
             np.full(nt, area * slow_mm_s / af), e + area * slow_mm_s * tq / af, -1, np.full(nt, np.nan))
        t, e = t + tq[-1], e + area * prime_mm / af
        pos = np.array([x0 + prime_mm, start[1]])
        t, e = move_e(t, pos, -1.0)
    ref_track = None
    if reference:
        t, e, pos, ref_track = _reference(emit, travel, t, e, pos, x0, x0 + length_mm,
                                          y0 + n_tracks * gap_mm, n_tracks, height_mm, printer, af)
        t, e = move_e(t, pos, -1.0)
    stops = np.atleast_1d(np.asarray(stop_s, dtype=float))
    places = np.atleast_1d(np.asarray(stop_at, dtype=float))
    retracts = np.atleast_1d(np.asarray(stop_retract, dtype=bool))
    rt = retract_mm / 30.0   # s: a retraction at 30 mm/s, as move_e
    for i in range(n_tracks):
        v_fast = fast_mm_s[i % len(fast_mm_s)]
        dwell, place = float(stops[i % len(stops)]), float(places[i % len(places)])
        retract_here = bool(retracts[i % len(retracts)])
        w = widths_mm[(i + i // len(fast_mm_s)) % len(widths_mm)]
        forward = i % 2 == 0
        y = y0 + i * gap_mm
        xa, xb = (x0, x0 + length_mm) if forward else (x0 + length_mm, x0)
        # travel (retracted) to the track start, then unretract in place
        t = travel(t, pos, (xa, y))
        t, e = move_e(t, (xa, y), 1.0)
        # the track: speed profile over arc length with accel limits and a stop
        s_slow, s_stop = 0.25 * length_mm, place * length_mm
        ds = 0.02
        s = np.arange(0, length_mm + ds / 2, ds)
        vt = np.where(s < s_slow, slow_mm_s, v_fast)
        v = vt.copy()
        v[0] = 0.0
        v[-1] = 0.0
        istop = int(round(s_stop / ds))
        v[istop] = 0.0
        for k in range(1, len(s)):
            v[k] = min(v[k], np.sqrt(v[k - 1] ** 2 + 2 * accel_mm_s2 * ds))
        for k in range(len(s) - 2, -1, -1):
            v[k] = min(v[k], np.sqrt(v[k + 1] ** 2 + 2 * accel_mm_s2 * ds))
        dt_seg = 2 * ds / (v[1:] + v[:-1])
        ts = np.concatenate([[0.0], np.cumsum(dt_seg)])
        ts[istop + 1:] += dwell  # dwell at the stop: the time jumps, s does not
        area = float(bead_area_mm2(w, height_mm))
        # resample uniformly in time (<= 4 ms) and add the dwell nodes
        t_end = ts[-1]
        t0, t1 = ts[istop], ts[istop + 1]
        r_nodes = t0 + rt * np.linspace(0, 1, 8)[1:]
        u_nodes = t1 - rt + rt * np.linspace(0, 1, 8)[1:]
        tq = np.unique(np.concatenate([np.arange(0, t_end, 0.004), [t_end], np.linspace(t0, t1, 40)]
                                      + ([r_nodes, u_nodes] if retract_here else [])))
        before = tq <= ts[istop]
        sq = np.where(before, np.interp(tq, ts[:istop + 1], s[:istop + 1]),
                      np.interp(tq, ts[istop + 1:], s[istop + 1:]))
        sq = np.where((tq > ts[istop]) & (tq < ts[istop + 1]), s[istop], sq)
        vq = np.where(before, np.interp(tq, ts[:istop + 1], v[:istop + 1]),
                      np.interp(tq, ts[istop + 1:], v[istop + 1:]))
        vq = np.where((tq > ts[istop]) & (tq < ts[istop + 1]), 0.0, vq)
        eq = e + area * sq / af
        veq = area * vq / af
        if retract_here:     # E back retract_mm over rt from t0, forward over rt up to t1
            back = np.clip(tq - t0, 0.0, rt) - np.clip(tq - (t1 - rt), 0.0, rt)
            eq = eq - 30.0 * back
            veq = np.where((tq > t0 + 1e-9) & (tq <= t0 + rt + 1e-9), -30.0, veq)
            veq = np.where((tq > t1 - rt + 1e-9) & (tq <= t1 + 1e-9), 30.0, veq)
        sign = 1.0 if forward else -1.0
        emit(t + tq, xa + sign * sq, np.full(len(tq), y), vq, veq, eq, i, sq)
        t, e = t + t_end, e + area * length_mm / af
        tracks.append(Track(id=i, kind="test", points_mm=[[xa, y], [xb, y]], width_mm=w,
                            height_mm=height_mm, flow_mm3_s=area * v_fast, z_mm=height_mm,
                            group=f"v={v_fast:g}mm/s w={w:g}mm",
                            params={"v_fast_mm_s": v_fast, "width_mm": w,
                                    "stop_s_mm": float(s[istop])}))
        # retract at the end, in place
        t, e = move_e(t, (xb, y), -1.0)
        pos = np.array([xb, y])
    if ref_track is not None:
        tracks.append(ref_track)
    arrays = {k: np.concatenate(v) for k, v in nodes.items()}
    # drop exact duplicate times at phase joins (keep the later node: its E is current)
    keep = np.concatenate([np.diff(arrays["t_s"]) > 1e-12, [True]])
    arrays = {k: a[keep] for k, a in arrays.items()}
    arrays["track"] = arrays["track"].astype(np.int64)
    tl = Timeline(**arrays)
    return Manifest(printer=printer, pattern={"name": "probe", "params": {}}, tracks=tracks,
                    timeline=tl)


@dataclass
class HiddenCase:
    """A dataset with a hidden effect.

    truth_spec/truth_values: what the virtual printer ran; base_spec: what is fitted;
    hidden: the effect left out; table: the noisy widths; effect_rms_mm: RMS change of the
    true widths caused by the hidden effect (compare with noise_mm).
    """

    hidden: str
    base_spec: str
    truth_spec: str
    truth_values: dict
    manifest: Manifest
    table: WidthTable
    noise_mm: float
    effect_rms_mm: float
    extra_effects: list = field(default_factory=list)


def make_case(hidden: str, seed: int = 0, noise_mm: float = 0.01, ds_mm: float = 0.25,
              scale: float = 1.0, manifest: Manifest | None = None, **probe) -> HiddenCase:
    """Simulate the probe print with BASE_SPEC + ``hidden`` and measure it with noise.

    ``scale`` multiplies the hidden effect's departure from "absent" (for sweeps of the
    effect size). Truth values of the hidden effect are jittered by +-20 % per seed.
    """
    from fit.model import build_model

    if hidden not in HIDDEN:
        raise ValueError(f"unknown hidden effect {hidden!r}; choose from {', '.join(HIDDEN)}")
    rng = np.random.default_rng(seed)
    extra = user_effects() if hidden == "gear_slip" else []
    man = manifest or probe_manifest(**probe)
    samples = sample_points(man, ds_mm=ds_mm, margin_mm=0.5)
    spec = f"{BASE_SPEC}+{hidden}"
    model = build_model(spec, man.printer, extra_effects=extra)
    values = dict(BASE_VALUES)
    values["pa.tau_s"] *= float(np.exp(0.2 * rng.standard_normal()))
    for k, v in HIDDEN[hidden].items():
        values[k] = v * scale * float(1.0 + 0.2 * (2 * rng.random() - 1))
    theta = _theta(model, values)
    absent = _theta(model, {**values, **{k: _absent_value(model, k) for k in HIDDEN[hidden]}})
    from fit.blobs import under_blobs
    from fit.context import SimContext
    ctx = SimContext.build(man, samples)
    w_true, w_absent = np.asarray(model.predict(ctx, np.stack([theta, absent])))
    w_meas = w_true + noise_mm * rng.standard_normal(len(w_true))
    # What a scan measurement flags: the blob where the head stood still (its width is
    # not a bead width: 1 mm about the stop, or its disc and 0.5 mm, fit/blobs.py) and
    # samples with no bead.
    stop_at = np.array([man.track(int(k)).params.get("stop_s_mm", np.nan) for k in samples.track])
    vol = model.simulate(ctx, theta[None]).blob_volume_mm3[0]
    blob = (np.abs(samples.s_mm - stop_at) <= 1.0) | under_blobs(ctx.blobs, vol, len(samples.s_mm))
    valid = np.isfinite(w_true) & ~blob & (w_true > 0.05)
    flag = np.where(blob, "blob", np.where(valid, "", "missing")).astype(object)
    table = WidthTable(track=samples.track, s_mm=samples.s_mm, x_mm=samples.x_mm,
                       y_mm=samples.y_mm, t_s=samples.t_s, width_mm=np.where(valid, w_meas, 0.0),
                       width_sd_mm=np.full(len(w_true), noise_mm), valid=valid, flag=flag)
    w_true, w_absent = w_true[valid], w_absent[valid]
    return HiddenCase(hidden=hidden, base_spec=BASE_SPEC, truth_spec=spec, truth_values=values,
                      manifest=man, table=table, noise_mm=noise_mm,
                      effect_rms_mm=float(np.sqrt(np.mean((w_true - w_absent) ** 2))),
                      extra_effects=extra)


def _theta(model, values: dict) -> np.ndarray:
    th = np.asarray(model.default_theta(), dtype=float).copy()
    for j, name in enumerate(model.param_names):
        if name in values:
            th[j] = values[name]
    return th


def _absent_value(model, name: str) -> float:
    """The parameter value at which its effect vanishes (0 amplitude, n = 1)."""
    return 1.0 if name.endswith(".n") or name.endswith(".gain") else 0.0
