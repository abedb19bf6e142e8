"""A second virtual printer, written apart from fit/ so that discovery is scored without
the inverse crime.

Nothing here calls fit/effects.py, fit/kernels.py or fit/context.py. Shared with the
library are only definitions: the planned timeline of the probe print (fit/hidden.py),
the stations (patterns.manifest.sample_points) and the bead cross-section
A = (w - h) h + pi h^2 / 4 (fit/geometry.py). What differs:

- discretisation: the commanded E(t) is resampled on a uniform 1 ms grid and the state
  is integrated by explicit midpoint (RK2) steps, where the library integrates exactly on
  merged constant-command intervals;
- deposition: each step's outflow volume is laid on its track at the nozzle's arc length
  with a Gaussian footprint (sd 0.12 mm), where the library averages over a window;
- each hidden effect has another functional form than the library's:

  ==============  ==========================================  ===========================
  foreign effect  here                                        library (fit/effects.py)
  ==============  ==========================================  ===========================
  thermal         gamma (shape 2) kernel: delayed ooze,       exponential kernel
                  two cascaded lags of tau_th/2
  nonlinear       logarithmic Preq = tau v0 ln(1 + vn/v0)     power law, tanh, 1/x
  backpressure    sub-linear power law Kb w_r (w/w_r)^0.5     Kb w_sat tanh(w/w_sat)
  backlash        play of width be followed by an elastic     dead band on reversal
                  zone (first-order lag, 40 ms)
  bed             quadratic bowl h(r) = h0 (1 + c r^2)        plane (bed_tilt); 3 x 3 grid
                                                              interpolated bilinearly
                                                              (bed_mesh: chords, not the
                                                              parabola)
  gear_slip       slip grows with the filament pressure       no library form (the
                  ve_eff = ve (1 - k P)                       example user effect is
                                                              speed-dependent)
  ==============  ==========================================  ===========================

The family each foreign effect belongs to (what diagnose should name) is ``FAMILY``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from fit.geometry import bead_width_mm, filament_area_mm2
from measure.table import WidthTable
from patterns.manifest import sample_points

DT_S = 0.001
#: mm of prime line before the probe's first track (fit.hidden.probe_manifest)
PRIME_MM = 60.0
#: The probe's stops (fit.hidden.probe_manifest): ``CALIB_BENCH_FOREIGN_PROBE`` "separated"
#: varies each track's stop length (1.5 / 3 / 6 s), place (half or three quarters along)
#: and whether the head retracts there (each head speed once with, once without), so that
#: the last stop's length, the time since a retraction and the arc length part; "plain"
#: (the default) is the probe as the covariate rules were shaped on: every stop 3 s, 65 %
#: along, no retraction.
PROBE = os.environ.get("CALIB_BENCH_FOREIGN_PROBE", "plain")
PROBE_KW = {"plain": {},
            "separated": {"stop_s": (1.5, 3.0, 6.0), "stop_at": (0.5, 0.75),
                          "stop_retract": (True, False, False, True, False, True, True, False)}}
FOOTPRINT_SD_MM = 0.12
#: The rendered probe prints our width reference (``CALIB_BENCH_FOREIGN_REFERENCE``, "1" by
#: default; "0": apparent widths, as before session 60). Without it the fit frees the
#: picture's edge offset (``scan_bias``), which also takes the part of a width-dependent
#: effect that looks like an offset: on back-pressure seed 0 the base misfit then lined up
#: with the advance (score 0.23) where, the true offset removed, it lines up with head
#: speed and flow (0.62 / 0.56; docs/DISCOVER.md "The rendered probe with a width reference").
REFERENCE = os.environ.get("CALIB_BENCH_FOREIGN_REFERENCE", "1") != "0"

#: foreign effect -> its parameters (sizes comparable to fit/hidden.py's cases)
FOREIGN = {
    "thermal": {"a": 0.3, "tau_th_s": 8.0},
    "nonlinear": {"v0_mm_s": 2.5},
    "backpressure": {"kb": 0.5, "w_ref_mm": 0.6},
    "backlash": {"be_mm": 0.8, "lag_s": 0.04},
    "bed": {"c_per_mm2": 6e-5},
    "gear_slip": {"k_per_mm": 0.12},
}
#: a case with no hidden effect: the foreign printer's plain spring, the probe's right model
#: being `pa` (what diagnose says of a right model; not in FOREIGN)
RIGHT_MODEL = "none"
#: library effects that count as naming the foreign effect
FAMILY = {
    "thermal": {"thermal"},
    "nonlinear": {"nonlinear", "bernoulli", "kalico_tanh", "kalico_recip", "offset"},
    "backpressure": {"backpressure"},
    "backlash": {"backlash"},
    "bed": {"bed_tilt", "bed_mesh"},
    "gear_slip": {"gear_slip"},
}
#: covariates that point at the foreign effect
RIGHT_COVARIATES = {
    "thermal": {"time_since_stop_s", "last_stop_duration_s"},
    "nonlinear": {"flow_mm3_s", "extruder_speed_mm_s", "time_since_flow_change_s"},
    "backpressure": {"width_nominal_mm", "flow_mm3_s"},
    "backlash": {"time_since_stop_s", "s_mm", "time_since_flow_change_s", "time_since_retract_s"},
    "bed": {"x_mm", "y_mm", "r_mm"},
    # the foreign slip grows with the filament pressure (ve (1 - k P)): flow is its
    # steady-state proxy, the advance the fitted model holds (fit/covariates.py) its cause
    "gear_slip": {"flow_mm3_s", "extruder_speed_mm_s", "advance_mm"},
}


@dataclass
class ForeignCase:
    hidden: str
    table: WidthTable
    manifest: object
    noise_mm: float
    effect_rms_mm: float


def _uniform(tl):
    """The timeline on a uniform DT_S grid: t, commanded E, head x, y, speed, track, s."""
    t = np.arange(tl.t_s[0], tl.t_s[-1], DT_S)
    e = np.interp(t, tl.t_s, tl.e_mm)
    idx = np.clip(np.searchsorted(tl.t_s, t, side="right") - 1, 0, len(tl.t_s) - 1)
    return (t, e, np.interp(t, tl.t_s, tl.x_mm), np.interp(t, tl.t_s, tl.y_mm),
            np.interp(t, tl.t_s, tl.v_mm_s), tl.track[idx], np.interp(t, tl.t_s, tl.s_mm))


def simulate(manifest, tau_s: float, hidden: str | None, p: dict | None = None,
             height_mm: float = 0.2, ds_mm: float = 0.5, margin_mm: float = 0.5,
             record: dict | None = None):
    """Deposited cross-section A (mm^2) at every station of ``sample_points(manifest, ds_mm,
    margin_mm=margin_mm)``
    (and the stations), for the base linear spring ``tau_s`` plus ``hidden``. ``record``:
    a dict that receives the outflow, ``t_s`` (uniform DT_S grid) and ``q_mm3_s`` on it."""
    p = p or {}
    prof = manifest.printer
    af = filament_area_mm2(prof["filament_diameter_mm"])
    t, e, x, y, vh, trk, s = _uniform(manifest.timeline)
    n = len(t)
    ve_cmd = np.gradient(e, DT_S)
    # heights: a bowl-shaped bed for "bed", flat otherwise
    if hidden == "bed":
        r2 = x ** 2 + y ** 2
        hgt = height_mm * (1.0 + p["c_per_mm2"] * r2)
    else:
        hgt = np.full(n, height_mm)

    def outflow(P, vhead, h):
        """Nozzle outflow vn (mm/s of filament) for the stored advance P (mm)."""
        if P <= 0.0:
            return 0.0
        if hidden == "nonlinear":
            v0 = p["v0_mm_s"]
            return v0 * math.expm1(P / (tau_s * v0))
        if hidden == "backpressure":
            # P = tau vn + Kb w_r (w/w_r)^0.5, w the width of the bead this outflow lays
            # (A = (w - h) h + pi h^2/4, w >= h; pi w h / 4 below): bisection on vn
            lo, hi = 0.0, P / tau_s
            c = p["kb"] * math.sqrt(p["w_ref_mm"])
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                area = mid * af / max(vhead, 2.0)
                w = area / h + h * (1 - math.pi / 4) if area >= math.pi * h * h / 4 else \
                    4 * area / (math.pi * h)
                if tau_s * mid + c * math.sqrt(w) > P:
                    hi = mid
                else:
                    lo = mid
            return lo
        return P / tau_s

    P = 0.0
    g = e[0]            # gear position after the play (backlash)
    ge = e[0]           # after the elastic zone
    x1 = x2 = 0.0       # thermal lags
    q = np.zeros(n)     # outflow volume rate, mm^3/s
    for k in range(n - 1):
        if hidden == "backlash":
            half = 0.5 * p["be_mm"]
            g = min(max(g, e[k + 1] - half), e[k + 1] + half)
            ge_new = ge + (g - ge) * (1.0 - math.exp(-DT_S / p["lag_s"]))
            ve = (ge_new - ge) / DT_S
            ge = ge_new
        else:
            ve = ve_cmd[k]
        if hidden == "gear_slip":
            ve *= max(0.0, 1.0 - p["k_per_mm"] * max(P, 0.0))
        # explicit midpoint step of dP/dt = ve - vn
        v1 = outflow(P, vh[k], hgt[k])
        Pm = P + 0.5 * DT_S * (ve - v1)
        v2 = outflow(Pm, 0.5 * (vh[k] + vh[k + 1]), hgt[k])
        P = P + DT_S * (ve - v2)
        vn = v2
        if hidden == "thermal":
            th = 0.5 * p["tau_th_s"]
            x1 += DT_S * (vn - x1) / th
            x2 += DT_S * (x1 - x2) / th
            vn = max(0.0, vn + p["a"] * (x2 - vn))
        q[k] = vn * af
    if record is not None:
        record.update(t_s=t, q_mm3_s=q)
    smp = sample_points(manifest, ds_mm=ds_mm, margin_mm=margin_mm)
    area = np.zeros(len(smp.s_mm))
    for tid in np.unique(smp.track):
        on = (trk == tid) & np.isfinite(s)
        st = smp.track == tid
        if not on.any():
            continue
        # volume laid per step at the nozzle's arc length, Gaussian footprint along s
        vol = q[on] * DT_S
        ss = s[on]
        grid = np.arange(-1.0, ss.max() + 1.0, 0.02)
        dep = np.histogram(ss, bins=np.append(grid, grid[-1] + 0.02), weights=vol)[0] / 0.02
        kx = np.arange(-4 * FOOTPRINT_SD_MM, 4 * FOOTPRINT_SD_MM + 1e-9, 0.02)
        ker = np.exp(-0.5 * (kx / FOOTPRINT_SD_MM) ** 2)
        dep = np.convolve(dep, ker / ker.sum(), mode="same")
        area[st] = np.interp(smp.s_mm[st], grid + 0.01, dep)
    h_st = np.full(len(area), height_mm)
    if hidden == "bed":
        h_st = height_mm * (1.0 + p["c_per_mm2"] * (smp.x_mm ** 2 + smp.y_mm ** 2))
    return area, h_st, smp


def _draw(hidden: str, seed: int, reference: bool = False, manifest=None):
    """(rng, probe manifest, tau_s, effect parameters) of a case: tau 0.35 s x lognormal(0.2),
    the effect's parameters within +-20 % of FOREIGN's (none for RIGHT_MODEL: the plain
    spring, dP/dt = ve - P / tau, which `pa` describes). ``reference``: the probe with the
    width reference our patterns print (fit.hidden.probe_manifest). ``manifest``: another
    print instead (e.g. patterns/probe.py's, planned from its G-code)."""
    from fit.hidden import probe_manifest

    rng = np.random.default_rng(seed)
    # a prime line first: the two printers start their extruder's state differently (the
    # library's dead band pushed forward, this one's in the middle of its play), and no
    # real print's starting state is known either; its purge line sets it
    man = manifest or probe_manifest(prime_mm=PRIME_MM, reference=reference, **PROBE_KW[PROBE])
    tau = 0.35 * float(np.exp(0.2 * rng.standard_normal()))
    p = {k: v * float(1.0 + 0.2 * (2 * rng.random() - 1)) for k, v in FOREIGN.get(hidden, {}).items()}
    return rng, man, tau, p


def make_foreign_case(hidden: str, seed: int = 0, noise_mm: float = 0.01, manifest=None) -> ForeignCase:
    """The probe print (fit/hidden.py; or ``manifest``'s) on the foreign printer with
    ``hidden``, widths with ``noise_mm`` of white measurement noise; the same stop blobs
    flagged as make_case."""
    rng, man, tau, p = _draw(hidden, seed, manifest=manifest)
    a1, h1, smp = simulate(man, tau, hidden, p)
    a0, h0, _ = simulate(man, tau, None)
    w1 = np.asarray(bead_width_mm(np.maximum(a1, 0.0), h1))
    w0 = np.asarray(bead_width_mm(np.maximum(a0, 0.0), h0))
    stop_at = np.array([man.track(int(k)).params.get("stop_s_mm", np.nan) for k in smp.track])
    blob = np.abs(smp.s_mm - stop_at) <= 1.0
    valid = np.isfinite(w1) & ~blob & (w1 > 0.05)
    meas = w1 + noise_mm * rng.standard_normal(len(w1))
    flag = np.where(blob, "blob", np.where(valid, "", "missing")).astype(object)
    table = WidthTable(track=smp.track, s_mm=smp.s_mm, x_mm=smp.x_mm, y_mm=smp.y_mm, t_s=smp.t_s,
                       width_mm=np.where(valid, meas, 0.0), width_sd_mm=np.full(len(w1), noise_mm),
                       valid=valid, flag=flag)
    rms = float(np.sqrt(np.mean((w1[valid] - w0[valid]) ** 2)))
    return ForeignCase(hidden, table, man, noise_mm, rms)


@dataclass
class RenderedForeignCase(ForeignCase):
    """A foreign case pictured and measured: ``table`` is what `calib measure` read (every
    other station, 0.5 mm apart as the white-noise cases); ``truth_mm`` the foreign
    printer's widths at those stations; ``figures`` the measurement's error against them
    (rms_mm, bias_mm over the valid stations, valid share, whether the widths are apparent)."""

    truth_mm: np.ndarray = None
    figures: dict = None
    #: the measurement summary's ``apparent_width`` block (fit/measurement.py auto_start)
    calibration: dict = None


def render_foreign_case(hidden: str, seed: int = 0, camera: str = "flatbed", realism: str = "all",
                        plate: str = "dark", plastic: str = "opaque", dpi: float = 600.0,
                        tilt_deg: float = 35.0, reference: bool | None = None) -> RenderedForeignCase:
    """The probe print of :func:`make_foreign_case` (the same draws of tau and the effect),
    pictured by measure/render.py with ``realism`` (measure/phenomena.py; strings and raster
    gaps from this printer's own outflow) and measured by measure/pipeline.py with the pose
    given by eight points of the true camera (the probe has no markers; issue #11 item 4:
    "rendered with the realistic camera ... and measured by our pipeline").

    ``reference`` (default REFERENCE): the probe prints the width reference every pattern
    of ours prints (fit.hidden.probe_manifest), which the measurement calibrates the
    apparent widths from, as it does on a user's print; without it they stay apparent.

    What the fit then sees is not this module's widths plus white noise but apparent
    widths: an edge offset of tens of um (no width reference on the probe, so not
    calibrated unless ``reference``; the diagnosis starts where `calib fit --model auto`
    would, fit/measurement.py auto_start), per-station
    sds from the edge fits, flags. Stations within 1 mm of a planned stop are not used, as
    in make_foreign_case (the two printers lay a standing nozzle's blob differently)."""
    import os
    import tempfile
    from types import SimpleNamespace

    from calib.commands.simulate import camera_for, write_image
    from measure.phenomena import NEEDS_PHYSICS, Realism, deposit_pieces, irregular_widths
    from measure.pipeline import measure_scan
    from measure.render import render

    _, man, tau, p = _draw(hidden, seed, REFERENCE if reference is None else reference)
    rec: dict = {}
    a1, h1, smp = simulate(man, tau, hidden, p, ds_mm=0.25, margin_mm=0.0, record=rec)
    a0, h0, _ = simulate(man, tau, None, ds_mm=0.25, margin_mm=0.0)
    w1 = np.asarray(bead_width_mm(np.maximum(a1, 0.0), h1))
    w0 = np.asarray(bead_width_mm(np.maximum(a0, 0.0), h0))
    printed = np.isfinite(w1) & (w1 > 0.05)
    n = len(w1)
    stop_at = np.array([man.track(int(k)).params.get("stop_s_mm", np.nan) for k in smp.track])
    at_stop = np.abs(smp.s_mm - stop_at) <= 1.0
    # a standing nozzle lays its ooze at one arc length: as a flat bead that would be tens
    # of mm wide; it is a dome, pictured (as deposit_pieces draws blobs) at most twice the
    # commanded width. Those stations are not used (below).
    w_draw = np.where(at_stop, np.minimum(w1, 2.0 * np.maximum(smp.width_nominal_mm, 0.3)), w1)
    truth = WidthTable(track=smp.track, s_mm=smp.s_mm, x_mm=smp.x_mm, y_mm=smp.y_mm, t_s=smp.t_s,
                       width_mm=np.where(printed, w_draw, 0.0), width_sd_mm=np.zeros(n), valid=printed,
                       flag=np.where(printed, "", "missing").astype(object))
    real = Realism.parse(realism, camera)
    if "irregular" in real:
        truth.width_mm[:] = irregular_widths(truth.track, truth.s_mm, truth.width_mm,
                                             np.random.default_rng([int(seed), 11]), rel=real.irregular_rel,
                                             corr_mm=real.irregular_corr_mm, abs_mm=real.irregular_mm,
                                             short_mm=real.irregular_short_mm)
    deposits = None
    if set(NEEDS_PHYSICS) & real.enabled:
        # this printer's outflow per timeline interval (filament mm), for the prime line and
        # the strings on travel moves (measure/phenomena.py deposit_pieces)
        tl = man.timeline
        af = filament_area_mm2(man.printer["filament_diameter_mm"])
        v_cum = np.concatenate([[0.0], np.cumsum(rec["q_mm3_s"] * DT_S)])
        t_cum = np.concatenate([rec["t_s"], [rec["t_s"][-1] + DT_S]])
        out = np.diff(np.interp(tl.t_s, t_cum, v_cum)) / af
        deposits = deposit_pieces(man, SimpleNamespace(sim=SimpleNamespace(out_mm=[out])))
    cam = camera_for(man, camera, dpi=dpi, tilt_deg=tilt_deg, seed=seed)
    rendered = render(man, truth, cam, plate=plate, plastic=plastic, seed=seed, realism=real,
                      deposits=deposits, jpeg_quality=85 if camera == "phone" else None)
    xs, ys = np.percentile(smp.x_mm, [5, 50, 95]), np.percentile(smp.y_mm, [5, 50, 95])
    bed = np.array([(x, y) for x in xs for y in ys if (x, y) != (xs[1], ys[1])], float)
    with tempfile.TemporaryDirectory() as d:
        path = write_image(os.path.join(d, "scan.jpg" if rendered.encoded else "scan.png"), rendered)
        res = measure_scan(path, man, points=(bed, cam.project(bed)))
    tb = res.table
    key = {(int(t), round(float(s), 3)): i for i, (t, s) in enumerate(zip(truth.track, truth.s_mm))}
    idx = np.array([key.get((int(t), round(float(s), 3)), -1) for t, s in zip(tb.track, tb.s_mm)])
    # every other station (0.5 mm): the density of make_foreign_case, and half the fit's cost
    keep = (idx >= 0) & (np.round(tb.s_mm / 0.25).astype(int) % 2 == 0)
    tb, idx = tb.subset(keep), idx[keep]
    stop_at = np.array([man.track(int(k)).params.get("stop_s_mm", np.nan) for k in tb.track])
    blob = np.abs(tb.s_mm - stop_at) <= 1.0
    tb.valid = tb.valid & ~blob
    tb.flag = np.where(blob, "blob", tb.flag).astype(object)
    t_true = truth.width_mm[idx]
    ok = tb.valid & (t_true > 0)
    e = tb.width_mm[ok] - t_true[ok]
    figs = {"rms_mm": float(np.sqrt(np.mean(e ** 2))) if ok.any() else float("nan"),
            "bias_mm": float(np.mean(e)) if ok.any() else float("nan"),
            "valid": float(np.mean(tb.valid[t_true > 0])) if (t_true > 0).any() else 0.0,
            "apparent": not bool(res.summary["apparent_width"]["applied"])}
    on = printed & ~at_stop
    rms = float(np.sqrt(np.mean((w1[on] - w0[on]) ** 2)))
    noise = float(np.median(tb.width_sd_mm[tb.valid])) if tb.valid.any() else float("nan")
    return RenderedForeignCase(hidden, tb, man, noise, rms, truth_mm=t_true, figures=figs,
                               calibration=res.summary["apparent_width"])


# ----------------------------------------------------------------------------------------
# The firmware's compensation on this printer: what `calib export` is scored against

def with_linear_advance(manifest, k_s: float):
    """``manifest`` with linear advance K (s) applied to its commanded extruder position, as
    Marlin's LA 1.5 does (no smoothing): E + K ve wherever the move extrudes while the head
    moves (ve > 0 and head speed > 0; retractions, primes and travel get none). Written
    from the firmware's rule (docs/ARCHITECTURE.md, REFERENCE), not from fit/'s
    FirmwarePA: the advance follows the timeline's planned extruder speed, ramps included."""
    from dataclasses import replace

    tl = manifest.timeline
    on = (tl.ve_mm_s > 0) & (tl.v_mm_s > 1e-6)
    return replace(manifest, timeline=replace(tl, e_mm=tl.e_mm + k_s * np.where(on, tl.ve_mm_s, 0.0)))


def width_error_mm(manifest, tau_s: float, hidden: str | None, p: dict | None, k_s: float) -> float:
    """RMS (mm) of the printed width less the commanded one over every station (0.5 mm
    apart, from each line's very start to its end) of ``manifest``'s test tracks, printed on
    this printer (the spring ``tau_s`` with ``hidden``) with linear advance ``k_s``."""
    tl = manifest.timeline
    h = float(np.median(tl.z_mm[tl.track >= 0]))
    area, h_st, smp = simulate(with_linear_advance(manifest, k_s), tau_s, hidden, p, height_mm=h,
                               margin_mm=0.0)
    w = np.asarray(bead_width_mm(np.maximum(area, 0.0), h_st))
    nominal = np.asarray(smp.width_nominal_mm, float)
    ok = (nominal > 0) & np.isfinite(w)
    return float(np.sqrt(np.mean((w[ok] - nominal[ok]) ** 2)))


def optimal_advance(manifest, tau_s: float, hidden: str | None, p: dict | None) -> tuple[float, float]:
    """(K s, RMS mm): the linear advance that prints ``manifest``'s widths best on this
    printer, searched over [0, 4 tau] (bounded Brent). With nothing hidden it is not tau:
    the Gaussian footprint rounds every line's ends whatever the flow does, and a little
    less advance fills them (0.344 s for tau 0.359 on the standard move mix)."""
    from scipy.optimize import minimize_scalar

    r = minimize_scalar(lambda k: width_error_mm(manifest, tau_s, hidden, p, k), bounds=(0.0, 4.0 * tau_s),
                        method="bounded", options={"xatol": 1e-3 * tau_s})
    return float(r.x), float(r.fun)
