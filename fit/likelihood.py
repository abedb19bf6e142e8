"""Likelihood of measured widths given a model, and the joint posterior over several scans.

Noise model (per valid sample i, along one track, stations ordered by arc length s):

    r_i  = y_i - m_i(theta)                       residual (mm)
    r_i  = x_i + z_i + eps_i
    eps_i ~ N(0, width_sd_i^2)                    the measurement's own error at the
                                                  station, independent (the widths CSV's
                                                  width_sd_own_mm, else width_sd_mm:
                                                  WidthTable.fit_sd_mm)
    x_i  = phi_i x_{i-1} + sigma_extra sqrt(1 - phi_i^2) u_i,  phi_i = exp(-(s_i - s_{i-1}) / ell)
    u_i  ~ N(0, 1)                                everything the scan cannot see, correlated
                                                  along the track (bead wobble, filament
                                                  diameter drift, plate texture, model error)

    z_i  = optional (``NoiseOptions(short=True)``; 0 by default): the same with
           sigma_short and the fixed length SHORT_CORR_MM (0.4 mm), the bead's short
           wobble over about its own width

and with ``relative`` (the default) the long wobble's sd at station i is

    h_i = sigma_extra sqrt(1 - f + f (m_i / c_ref)^2)    (mm; m_i >= 0 the model width there)

i.e. x_i = h_i u_i with u a unit OU process: a bead wanders in proportion to its width
(filament diameter, the flow itself) as well as by a fixed amount (plate, picture).
f = ``noise.rel_share`` in [0, 1] (uniform prior), c_ref the scan's median commanded width,
so sigma_extra is the wobble's sd at the typical width whatever f: a print of one width
cannot tell f, and then only f wanders (h_i^2 = sigma_extra^2 + (sigma_rel m_i)^2 made the
two sds one ridge, and a joint fit lost its way on it). The variance depends on theta
through m, as in any regression whose noise grows with its mean; the alternatives are
worse: with the measured width y_i the covariance depends on the data and the
"likelihood" is no density (a line fit preferred a = 0.22, b = 0.44 for 0.3 / 0.6 by 211
in ln L: a gain error r = 0.26 y is a constant state of a wobble that grows with y), and
with the commanded width the lagging beads of a Bowden step grow it in the wrong place
(thermal.tau_s scatter 9.9 s against 3.1 with m, the share read 0.55 for ~1).

Why: on a Bowden scene whose beads run 0.3-0.8 mm wide (bench_e2e's adventurer3 spiral,
the virtual printer's true widths), a 1.2 % wobble over 20 mm drawn from this OU process
and fitted with a constant-sd one (f = 0) read tau with a scatter of 0.015 s over 10 draws
against a Laplace sd of 0.009, thermal.tau_s 11 s against 3.3, scan_bias.b1 0.017 against
0.005: the wide beads' larger wobble is slow structure tied to the width, and thermal ooze
with a long time constant and a width scale fit it. With f free (8 draws): 0.009 against
0.009, 3.1 s against 4.2, 0.003 against 0.005, f 0.93-1.0; an additive wobble reads f = 0
and the values as before (rms z 0.9-1.3).

So the wobble is an Ornstein-Uhlenbeck process of sd h_i (sigma_extra without
``relative``) and correlation length ell (and with ``short``, a second one of sd
sigma_short and length 0.4 mm, ell then >= LONG_MIN_FACTOR x 0.4 mm) seen through white
measurement noise, covariance diag(width_sd^2) + h_i h_j exp(-|s_i - s_j| / ell)
[+ sigma_short^2 exp(-|s_i - s_j| / 0.4)]. The
exact log-likelihood is the sum of the Kalman filter's one-step prediction terms (Durbin
& Koopman 2012, "Time Series Analysis by State Space Methods", ch. 4); for one wobble,
with the filtered state (a, P),

    predict   a' = phi a,  P' = phi^2 P + (1 - phi^2) sigma_extra^2
    innovate  v = r - a',  F = P' + width_sd^2,   ll_i = -(ln 2 pi + ln F + v^2 / F) / 2
    update    K = P' / F,  a = a' + K v,  P = P' (1 - K)

and with both the state is (x, z), the transition diag(phi, phi_s), the observation
x + z (:func:`_kalman`). With ``relative`` the long state is the unit process u (P' =
phi^2 P + 1 - phi^2) seen through h_i: v = r - h_i a' - z', F = h_i^2 P' + ... (the same
filter with a time-varying observation coefficient, Durbin & Koopman ch. 4.3).

Why the short wobble exists, and why it is not the default (issue #11 item 5, the
back-pressure fits reading tau low and Kb high together): a real bead wanders over tens
of mm (filament diameter) *and* over about its own width, and one OU process cannot be
both. On the 600 dpi back-pressure render's *true* widths (wander 1.2 % over 20 mm plus
3 um over 0.3 mm) with a white term too small to hold the short part, the one wobble's
length collapsed from ~26 mm to 3 mm and the whitened residual weighed the flow steps'
shape: tau 0.0379 s, Kb 0.218 for 0.043 / 0.2; with the short wobble 0.0426 / 0.1987,
sigma_short 2.9 um (the render's 3), ln L +300. But on the *measured* widths of the same
renders it removed only a third of the tau bias and none of Kb's (seeds 0-3: tau 0.0397
against 0.0382 with one wobble, Kb 0.218 against 0.221) while the intervals narrowed by
~27 %: over seeds 0-10 of bench_e2e 2 tau and 3 Kb intervals missed (one wobble, same
seeds: 0 and 1). Part of what is left there is the measurement's per-station sd the fit
weighs by (the own part, width_sd_own_mm: error / sd 1.7 on the fifth of the stations with
the smallest sd, 0.34 on the largest; docs/MEASUREMENT.md, "Is each station's sd what its error is?");
with the sd recalibrated per scan as well, tau centred but Kb stayed ~5 % high with the
narrower intervals (seeds 0-11: coverage 10/12 and 7/12, against 12/12 and 11/12), and the
whole calibrated sd (width_sd_mm since 2026-11-26) as the white term with one wobble
narrowed the intervals ~35 % around the same values (Kb 1 of 4 seeds covered).
Until the measurement is fixed the wider one-wobble intervals are the honest ones. The short wobble's sd has a uniform prior (it
may be absent), and the long length starts at 5 x its length so that the two cannot
trade places (with one 0.6 mm wobble in the data they did, and the sampler wandered).

Why the long wobble is shorter than a track (issue #11 item 4). Since every track starts
from the stationary state, a wobble much longer than the tracks is, on each track, one
free offset of sd sigma_extra: it then holds whatever differs from track to track, and
on a probe whose tracks differ in speed, width or the pause before them that is the
effect to be found. On the foreign printer's probe (60 mm tracks, delayed thermal ooze,
rendered and measured) `pa+scan_bias` put a 44 um wobble at the prior's 50 mm bound and
`+thermal` gained nothing (misfit 26); with the length at most a quarter of the track
(``corr_max_track_share``, :func:`corr_prior_of`) the base reads chi2_nu 21 and thermal
is named at Delta BIC 124, misfit 2.1 (bench_discover_foreign, `spread` added first: 37,
129, 2.1). On the realdata SpStartStopTest2 the same bound took `pa+backpressure`'s RMS
from 0.34 to 0.12 mm: the misfit moved out of the noise into the residuals (README). A quarter still lets a track's mean wander
(its variance sigma^2 2 ell / L) but no longer for free. A single long track (the spiral)
is not bounded by it: the prior's own 50 mm is shorter than a quarter of it.

Neighbouring stations' errors (session 38). ``measure`` despeckles each track's strips
along the track with an element (0.45 mm) longer than the stations' spacing (0.25 mm), so
neighbouring stations' widths are read from shared filtered pixels and their errors
correlate: error / sd at lag 1, 2, 3 stations 0.45, 0.11, 0.02 on `make demo`'s 600 dpi
scan (0.07 at lag 1 without the despeckling), 0.77, 0.38, 0.16 on the 400 dpi test
renders. The table links such stations (``width_corr_prev``, fit.data.ScanData.corr_prev);
where any are linked the measurement term eps_i is not white but a unit AR(1) state seen
through sd_i,

    eps_i = sd_i c_i,   c_i = rho_m c_(i-1) + sqrt(1 - rho_m^2) w_i   (linked; else c_i = w_i)

with rho_m = ``noise.meas_corr`` fitted per scan (uniform on [0, 0.95], starting at the
measurement's value): covariance sd_i sd_j rho_m^|i - j| within a linked run, the third
state of the filter (:func:`_kalman`). AR(1) rather than the one-step moving average the
filter's finite reach suggests: an MA(1) cannot correlate neighbours by more than 0.5,
and the 400 dpi renders do. What it changes, measured on the demo's scan
(pa+backpressure+thermal, MAP): ln L +912 over independent errors (rho_m 0.59; a fixed
MA(1) of 0.45 gave +957), yet the intervals hardly: Kb's sd 0.00239 against 0.00240,
because the wobble, whose length is free down to 0.02 mm, had already taken most of the
correlation (ell 0.70 -> 0.56 mm, sigma_extra 0.41 -> 0.30 um with it). So the demo's Kb
0.994 [0.990, 0.998] (truth 1) is not this: with the demo's own errors moved along the
track by 37-503 stations (their correlation kept, their place against the flow steps
not), the MAP Kb read 0.9972-1.0020 (mean 1.0003, sd 0.0017 against a stated 0.0023);
in place it reads 0.9940 (docs/MEASUREMENT.md, end of "Despeckled strips").

The first sample of every track (and every new scan) starts from the stationary state
(phi = 0 across a track start), so the sum is the exact joint log-likelihood, not a
conditional one. Optionally the standardised innovation v / sqrt(F) is Student-t(nu)
(robust option, heavy tails for blobs/glare; the filter update stays the Gaussian one).

Why the white term is separate (it was not until issue #11 item 5: the whole standardised
residual was one AR(1)): the bead's own width wanders smoothly (filament diameter, plate
texture) while the measurement error of neighbouring stations, 0.25 mm = 6 px apart at
600 dpi, is nearly independent; one AR(1) for the sum fitted ell ~5-9 mm to the wander
and then treated the measurement error as that smooth too. (On the renders of bench_e2e
that was not the main cause of `pa` reading tau 8-13 % high with +-2 % intervals: the
bead's own smoothing was, fit.effects.Spread.) Correlation along the track matters in the
first place because stations are 0.25 mm apart but bead wobble correlates widths over
~0.5-2 mm and more: independent samples overstate the information by (1 + rho) / (1 - rho).

The pointwise terms (one per sample, conditional on the previous ones) are what PSIS-LOO
uses; with correlated residuals that is a leave-one-out of the innovation, the usual
choice for time series (Buerkner et al. 2020, "Approximate leave-future-out
cross-validation").

``ell`` (``noise.corr_len_mm``) is fitted with a log-uniform prior, ``sigma_short``
(``noise.sigma_short_mm``, with ``short=True``) with a uniform one on [0, 0.1] mm;
``AR1=False`` fixes phi = 0 (x independent too: residual sd sqrt(width_sd^2 +
sigma_extra^2), and no short wobble).

Missing beads are censored data (issue #10 item 5). A station the measurement flagged
``missing`` (``fit.data.ScanData.missing_idx``: no bead seen where the nozzle passed over
a printed part of a test track) says the bead there was narrower than the scan's
detection limit w_min, not nothing. Each adds one independent term

    ll_i = ln P(missing | theta) = ln Phi((w_min_i - m_i(theta)) / s_i)
    w_min_i = max(width_sd_i, MISSING_W_MIN_FLOOR_MM)     (mm; ``measure`` writes
              width_sd = 1/ppm, one pixel, at missing stations: a bead narrower than
              about a pixel is not seen; the floor 0.05 mm covers tables without it)
    s_i = sqrt(w_min_i^2 / 4 + sigma_extra^2)             (mm; the detection threshold is
              soft by about half a pixel, and the bead wobbles by sigma_extra as anywhere)

(Phi the standard normal CDF; with ``student_nu`` the Student-t CDF of the same
standardised value.) The measurement's "missing" flag is not infallible (a thin
translucent line on textured PEI can pass for plate), so P(missing) is floored by a
misdetection rate eps = ``MISSING_FALSE_RATE``: (1 - eps) Phi(z) + eps.
With w_min = 0.05 mm and sigma_extra = 0.01 mm (s = 0.027 mm), a model that predicts no
bead there (m_i = 0) pays ln Phi(1.86) = -0.03; one that predicts a clear 0.4 mm bead
pays ln(0.02) = -3.9 (ln Phi(-13.0) = -88 without the floor): several stations seeing
nothing where the model lays a bead are strong evidence against it, one is not. The terms are independent of the Kalman filter of the valid samples (the
wobble state is not carried across a gap in the bead), and are appended after all valid
terms in the pointwise array (n_obs = n_valid + n_missing), so BIC and PSIS-LOO count
them as observations. Stations whose model width is NaN (never printed, ``ctx.printed``
False) would add ln 1 = 0 under every theta: they cannot tell models apart and are not
kept (a constant column would only give PSIS an undefined Pareto k). ``NoiseOptions(missing=False)`` (``calib fit --ignore-missing``) drops them all, as
before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numba import prange
from scipy.special import gammaln, log_ndtr, stdtr

from fit.kernels import serial_and_parallel
from fit.priors import Prior, prior_from_param

LOG2PI = math.log(2.0 * math.pi)

#: Effects whose parameters belong to one scan in a joint fit (each scan has its own
#: flow multiplier, filament diameter error and bed tilt; the extruder physics is shared).
NUISANCE_EFFECTS = ("flow_gain", "bed_tilt", "scan_bias", "scan_curve", "flow", "tilt", "layer_height",
                    "filament_diameter")

SIGMA_NAME = "noise.sigma_extra_mm"
CORR_NAME = "noise.corr_len_mm"
SHORT_NAME = "noise.sigma_short_mm"
REL_NAME = "noise.rel_share"
MEAS_NAME = "noise.meas_corr"
#: Correlation length (mm) of the short wobble: about a nozzle width, the scale over
#: which the bead's own surface tension and the nozzle's land correlate its width; at
#: the measurement's 0.25 mm station spacing neighbours correlate exp(-0.25/0.4) = 0.54.
SHORT_CORR_MM = 0.4
#: The long wobble's correlation length is at least this many times the short one's.
LONG_MIN_FACTOR = 5.0
#: Smallest detection limit (mm) of a ``missing`` station: w_min = max(width_sd, this).
MISSING_W_MIN_FLOOR_MM = 0.05
#: Chance that a present bead is flagged missing (a misdetection floor for the censored
#: term): a false flag costs at most ln(0.02) = -3.9 instead of -64 for a 0.35 mm bead.
MISSING_FALSE_RATE = 0.02


@dataclass(frozen=True)
class NoiseOptions:
    """Noise model switches: AR(1) along tracks (``relative``: part of the wobble's sd grows
    with the bead's width, ``noise.rel_share``, module docstring; ``short``: with the second, short
    wobble of correlation length ``short_corr_mm``), Student-t innovations with ``student_nu``
    degrees of freedom (None: Gaussian); ``missing``: fit the stations flagged missing as
    censored data (module docstring; on by default, a no-op when a table has none) with
    detection limit w_min = max(width_sd, ``missing_w_min_floor_mm``) (mm)."""

    ar1: bool = True
    relative: bool = True
    short: bool = False
    student_nu: float | None = None
    missing: bool = True
    missing_w_min_floor_mm: float = MISSING_W_MIN_FLOOR_MM
    missing_false_rate: float = MISSING_FALSE_RATE
    sigma_prior: Prior = field(default_factory=lambda: Prior("loguniform", 1e-4, 0.5))
    corr_prior: Prior = field(default_factory=lambda: Prior("loguniform", 0.02, 50.0))
    # the long wobble's length at most this share of the scan's typical track (module
    # docstring, "Why the long wobble is shorter than a track"); None: corr_prior's bound
    corr_max_track_share: float | None = 0.25
    # uniform, not log-uniform: when the data hold no short wobble its sd goes to 0, and a
    # log-uniform prior would leave the walkers a flat valley of several decades below
    # the measurement's own sd to wander in
    short_prior: Prior = field(default_factory=lambda: Prior("uniform", 0.0, 0.1))
    short_corr_mm: float = SHORT_CORR_MM
    # the share of the wobble's variance that grows with the width: uniform, 0 (all of it
    # the same at every width) to 1 (all of it in proportion to the width)
    rel_prior: Prior = field(default_factory=lambda: Prior("uniform", 0.0, 1.0))
    # the measurement errors' correlation between linked neighbours (module docstring,
    # "Neighbouring stations' errors"); fitted on scans whose table links any
    meas_corr: bool = True
    meas_prior: Prior = field(default_factory=lambda: Prior("uniform", 0.0, 0.95))


def pointwise_loglik(resid_mm, sd_mm, sigma_extra_mm, phi=None, student_nu=None, sigma_short_mm=None,
                     phi_short=None, rel_mm=None, link=None, rho_m=None) -> np.ndarray:
    """Pointwise log-likelihood (n_sets, n) of residuals under the noise model above
    (the Kalman filter in numpy; the reference for the compiled kernel).

    resid_mm        (n_sets, n) residuals y - m (mm), samples ordered along each track
    sd_mm           (n,) measurement sd (mm)
    sigma_extra_mm  (n_sets, 1) or scalar extra noise sd (mm)
    phi             (n_sets, n) correlation of x to the previous sample (0 at a track start),
                    or None for independent samples
    student_nu      None (Gaussian innovations) or degrees of freedom of Student-t innovations
    sigma_short_mm  (n_sets, 1) or scalar sd of the short wobble (mm), or None (absent)
    phi_short       (n_sets, n) its correlation to the previous sample (needs ``phi``)
    rel_mm          (n_sets, n) the relative wobble's sd at each sample (mm; h^2 = sigma_extra^2 + rel^2), or None
    link            (n,) 1 where the sample's measurement error is linked to the previous
                    sample's (:func:`scan_links`), or None (independent errors)
    rho_m           (n_sets, 1) or scalar: the linked errors' correlation (``noise.meas_corr``)
    """
    r = np.atleast_2d(np.asarray(resid_mm, dtype=float))
    short = sigma_short_mm is not None and phi_short is not None
    v, F = _kalman(r, np.asarray(sd_mm, dtype=float) ** 2,
                   np.broadcast_to(np.asarray(sigma_extra_mm, dtype=float) ** 2, (r.shape[0], 1))[:, 0],
                   None if phi is None else np.broadcast_to(phi, r.shape),
                   np.broadcast_to(np.asarray(sigma_short_mm, dtype=float) ** 2, (r.shape[0], 1))[:, 0]
                   if short else None,
                   np.broadcast_to(phi_short, r.shape) if short else None,
                   None if rel_mm is None else np.broadcast_to(rel_mm, r.shape), link,
                   None if rho_m is None else np.broadcast_to(np.asarray(rho_m, dtype=float), (r.shape[0], 1))[:, 0])
    if student_nu is None:
        return -0.5 * (v * v / F + np.log(F) + LOG2PI)
    nu = float(student_nu)
    c = gammaln(0.5 * (nu + 1)) - gammaln(0.5 * nu) - 0.5 * math.log(nu * math.pi)
    return c - 0.5 * np.log(F) - 0.5 * (nu + 1) * np.log1p(v * v / (F * nu))


def _kalman(r, sd2, s2x, phi, s2y=None, phi2=None, rel_mm=None, link=None, rho_m=None):
    """Innovations v and their variances F (n_sets, n) of ``r`` (n_sets, n) under the
    noise model: sd2 (n,) measurement variances, s2x (n_sets,) sigma_extra^2, phi
    (n_sets, n) or None (independent x); s2y (n_sets,) sigma_short^2 and phi2 (n_sets, n)
    of the short wobble, or None (absent); rel_mm (n_sets, n) the relative wobble's sd at
    each station (mm; :meth:`JointProblem.wobble_parts`), or None. The long wobble is a
    unit AR(1) state seen through h_j = sqrt(sigma_extra^2 + rel_j^2) (without rel, h is
    constant and this is the plain filter of the module docstring with its state scaled by
    sigma_extra). link (n,) and rho_m (n_sets,): the measurement error as a unit AR(1)
    state seen through sd_j, linked to the previous sample's where link_j = 1 with
    coefficient rho_m (module docstring, "Neighbouring stations' errors"; None: independent).
    Linear in r: whitening any vector (a Jacobian for a Cramer-Rao bound) is v / sqrt(F)
    with the same gains."""
    n_sets, n = r.shape
    v = np.empty_like(r)
    F = np.empty_like(r)
    short = s2y is not None and phi2 is not None and phi is not None
    s2y = np.zeros(n_sets) if not short else np.asarray(s2y, dtype=float)
    link = np.zeros(n) if link is None else np.asarray(link, dtype=float)
    rho_m = np.zeros(n_sets) if rho_m is None else np.broadcast_to(np.asarray(rho_m, dtype=float), (n_sets,))
    a, b, c = np.zeros(n_sets), np.zeros(n_sets), np.zeros(n_sets)
    P, P12, P22 = np.ones(n_sets), np.zeros(n_sets), s2y.copy()
    P13, P23, P33 = np.zeros(n_sets), np.zeros(n_sets), np.ones(n_sets)
    for j in range(n):
        ph = np.zeros(n_sets) if phi is None else phi[:, j]
        ph2 = phi2[:, j] if short else np.zeros(n_sets)
        q = rho_m * link[j]
        h = np.sqrt(s2x + (0.0 if rel_mm is None else rel_mm[:, j] ** 2))
        e = math.sqrt(sd2[j])
        ap, bp, cp = ph * a, ph2 * b, q * c
        Pp = ph * ph * P + (1.0 - ph * ph)
        P12p = ph * ph2 * P12
        P22p = ph2 * ph2 * P22 + (1.0 - ph2 * ph2) * s2y
        P13p, P23p, P33p = ph * q * P13, ph2 * q * P23, q * q * P33 + (1.0 - q * q)
        Su, Sz, Sc = h * Pp + P12p + e * P13p, h * P12p + P22p + e * P23p, h * P13p + P23p + e * P33p
        F[:, j] = h * Su + Sz + e * Sc
        v[:, j] = r[:, j] - h * ap - bp - e * cp
        f = F[:, j]
        a, b, c = ap + Su / f * v[:, j], bp + Sz / f * v[:, j], cp + Sc / f * v[:, j]
        P, P12, P22 = Pp - Su * Su / f, P12p - Su * Sz / f, P22p - Sz * Sz / f
        P13, P23, P33 = P13p - Su * Sc / f, P23p - Sz * Sc / f, P33p - Sc * Sc / f
    return v, F


def whiten(x_mm, sd_mm, sigma_extra_mm: float, gap_mm, corr_len_mm: float | None,
           sigma_short_mm: float = 0.0, short_corr_mm: float = SHORT_CORR_MM, rel_mm=None,
           link=None, rho_m: float = 0.0) -> np.ndarray:
    """x (n,) whitened by the noise model: v / sqrt(F), ~N(0, 1) per sample if x is
    residual noise of that model. ``corr_len_mm`` None: independent samples (and no
    short wobble); ``rel_mm`` (n,): the relative wobble's sd at each sample (mm) or None;
    ``link`` (n,) and ``rho_m``: the measurement errors' neighbour links and correlation."""
    x = np.atleast_2d(np.asarray(x_mm, dtype=float))
    g = np.asarray(gap_mm, dtype=float)
    phi = None if corr_len_mm is None else ar1_phi(g, [[corr_len_mm]])
    short = phi is not None and sigma_short_mm > 0
    v, F = _kalman(x, np.asarray(sd_mm, dtype=float) ** 2, np.array([float(sigma_extra_mm) ** 2]), phi,
                   np.array([float(sigma_short_mm) ** 2]) if short else None,
                   ar1_phi(g, [[short_corr_mm]]) if short else None,
                   None if rel_mm is None else np.atleast_2d(np.asarray(rel_mm, dtype=float)),
                   link, np.array([float(rho_m)]))
    return (v / np.sqrt(F))[0]


def missing_loglik(pred_mm, w_min_mm, sigma_extra_mm, student_nu=None,
                   false_rate: float = 0.0) -> np.ndarray:
    """Censored log-likelihood (n_sets, n) of stations where no bead was seen:

        ln[(1 - eps) Phi((w_min - m) / s) + eps],   s = sqrt(w_min^2 / 4 + sigma_extra^2)   (mm)

    eps = ``false_rate``: the chance that the measurement flags a present bead missing
    (thin translucent lines on a grained plate were 15-29 % on the realdata photos before
    the detector was tuned), so one false flag costs at most ln eps, not ln Phi(-13).

    pred_mm (n_sets, n) model widths m (mm), w_min_mm (n,) detection limits (mm),
    sigma_extra_mm (n_sets, 1) or scalar (mm); ``student_nu``: the Student-t CDF instead
    of Phi. Non-finite values (a NaN prediction) give -inf, as the valid terms do."""
    m = np.atleast_2d(np.asarray(pred_mm, dtype=float))
    wmin = np.asarray(w_min_mm, dtype=float)[None, :]
    sig = np.asarray(sigma_extra_mm, dtype=float)
    s = np.sqrt(0.25 * wmin * wmin + sig * sig)
    z = (wmin - m) / s
    if student_nu is None:
        ll = log_ndtr(z)
    else:
        with np.errstate(divide="ignore"):
            ll = np.log(stdtr(float(student_nu), z))
    if false_rate > 0.0:
        ll = np.logaddexp(math.log1p(-false_rate) + ll, math.log(false_rate))
    return np.where(np.isfinite(ll), ll, -np.inf)


def _ar1_loglik_rows(pred, order, y, sd2, link, gap, sig, share, c_ref, ell, sig_s, ell_s, rho_m, nu, c_t,
                     out):
    """Compiled :func:`pointwise_loglik` fused with the residuals: for every set i and
    valid sample j, r = y_j - pred[i, order_j], through the Kalman filter of the module
    docstring (long wobble sig[i], ell[i]; short wobble sig_s[i] with the fixed
    correlation length ell_s; the measurement error, sd^2 = sd2[j], linked to the previous
    sample's by rho_m[i] where link[j] = 1); ell[i] <= 0 means independent x (and no short
    component); nu <= 0 Gaussian, else Student-t with log normaliser c_t; share[i] the
    relative wobble's share f and c_ref the scan's median commanded width (mm): the long
    wobble's sd at a sample of model width m is sig sqrt(1 - f + f (max(m, 0) / c_ref)^2)
    (module docstring; :func:`_kalman`, the reference).
    Writes out (n_sets, n). With sig_s = 0 the short state stays 0, with rho_m = 0 the
    measurement state is white, and the arithmetic is the one-component filter's."""
    n_sets = pred.shape[0]
    n = order.shape[0]
    for i in prange(n_sets):
        s2x = sig[i] * sig[i]
        f = share[i]
        q = 1.0 / (c_ref * c_ref)
        s2y = sig_s[i] * sig_s[i] if ell[i] > 0.0 else 0.0
        el = ell[i]
        rm = rho_m[i]
        a = 0.0
        b = 0.0
        c = 0.0
        P = 1.0
        P12 = 0.0
        P22 = s2y
        P13 = 0.0
        P23 = 0.0
        P33 = 1.0
        g_prev = -1.0
        phi = 0.0
        phi2 = 0.0
        for j in range(n):
            if el > 0.0:
                g = gap[j]
                if g != g_prev:
                    phi = math.exp(-g / el)
                    phi2 = math.exp(-g / ell_s) if s2y > 0.0 else 0.0
                    g_prev = g
            m = pred[i, order[j]]
            h = sig[i] * math.sqrt(1.0 - f + f * max(m, 0.0) * max(m, 0.0) * q) if f > 0.0 else sig[i]
            e = math.sqrt(sd2[j])
            qm = rm * link[j]
            ap = phi * a
            bp = phi2 * b
            cp = qm * c
            Pp = phi * phi * P + (1.0 - phi * phi)
            P12p = phi * phi2 * P12
            P22p = phi2 * phi2 * P22 + (1.0 - phi2 * phi2) * s2y
            P13p = phi * qm * P13
            P23p = phi2 * qm * P23
            P33p = qm * qm * P33 + (1.0 - qm * qm)
            Su = h * Pp + P12p + e * P13p
            Sz = h * P12p + P22p + e * P23p
            Sc = h * P13p + P23p + e * P33p
            F = h * Su + Sz + e * Sc
            v = y[j] - m - h * ap - bp - e * cp
            if nu <= 0.0:
                ll = -0.5 * (v * v / F + math.log(F) + LOG2PI)
            else:
                ll = c_t - 0.5 * math.log(F) - 0.5 * (nu + 1.0) * math.log1p(v * v / (F * nu))
            a = ap + Su / F * v
            b = bp + Sz / F * v
            c = cp + Sc / F * v
            P = Pp - Su * Su / F
            P12 = P12p - Su * Sz / F
            P22 = P22p - Sz * Sz / F
            P13 = P13p - Su * Sc / F
            P23 = P23p - Sz * Sc / F
            P33 = P33p - Sc * Sc / F
            out[i, j] = ll if math.isfinite(ll) else -math.inf


_AR1_SERIAL, _AR1_PARALLEL = serial_and_parallel(_ar1_loglik_rows)


def scan_links(sc) -> np.ndarray:
    """(n_valid,) 1.0 where a valid sample's measurement error is linked to the previous
    valid sample's (``sc.corr_prev`` nonzero: the table's ``width_corr_prev`` between
    adjacent stations, fit/data.py), else 0.0; all 0 for scans without it."""
    rho = getattr(sc, "corr_prev", None)
    if rho is None:
        return np.zeros(len(sc.order))
    return (np.asarray(rho, dtype=float) != 0.0).astype(float)


def track_span_mm(sc) -> float:
    """Length (mm) of the track a typical valid station of ``sc`` lies on: the median over
    stations of their track's measured extent (max s - min s of its valid stations)."""
    tr, s = np.asarray(sc.track_valid), np.asarray(sc.s_valid_mm, dtype=float)
    if len(tr) == 0:
        return float("nan")
    ids, inv = np.unique(tr, return_inverse=True)
    lo = np.full(len(ids), np.inf)
    hi = np.full(len(ids), -np.inf)
    np.minimum.at(lo, inv, s)
    np.maximum.at(hi, inv, s)
    return float(np.median((hi - lo)[inv]))


def corr_prior_of(sc, noise: "NoiseOptions") -> Prior:
    """The long wobble's prior on one scan: ``noise.corr_prior``, starting at
    LONG_MIN_FACTOR x the short length with ``short``, and ending at
    ``corr_max_track_share`` x the scan's track span (track_span_mm) when that is shorter
    (never below twice the start)."""
    p = noise.corr_prior
    lower = max(p.lower, LONG_MIN_FACTOR * noise.short_corr_mm) if noise.short else p.lower
    upper = p.upper
    if noise.corr_max_track_share is not None:
        span = track_span_mm(sc)
        if np.isfinite(span) and span > 0:
            upper = min(upper, max(2.0 * lower, noise.corr_max_track_share * span))
    return replace(p, lower=lower, upper=upper)


def ar1_phi(gap_mm: np.ndarray, corr_len_mm) -> np.ndarray:
    """phi_i = exp(-gap_i / ell); gap = inf at a track start gives 0. Shapes (n,), (n_sets, 1)."""
    return np.exp(-gap_mm[None, :] / np.asarray(corr_len_mm))


def _median_commanded_mm(scan) -> float:
    """The median commanded width (mm) of ``scan``'s valid samples (its manifest's, at
    ``scan.order``); the median measured width where the manifest has none."""
    smp = getattr(scan, "samples", None)
    w = getattr(smp, "width_nominal_mm", None)
    if w is not None and len(scan.y_mm):
        w = np.asarray(w, dtype=float)[np.asarray(scan.order)]
        w = w[np.isfinite(w) & (w > 0)]
        if len(w):
            return float(np.median(w))
    y = np.abs(np.asarray(scan.y_mm, dtype=float))
    return float(np.median(y)) if len(y) and np.median(y) > 0 else 0.5


def censored_rows(scan) -> np.ndarray:
    """Rows of ``scan.missing_idx`` (fit/data.py) whose model width is defined: the
    station is printed in the simulation context (and in its coarsened physics context,
    which ``predict`` integrates)."""
    idx = np.asarray(getattr(scan, "missing_idx", ()), dtype=np.int64)
    for c in (scan.ctx, getattr(scan.ctx, "physics", None)):
        printed = getattr(c, "station_printed", None)
        if printed is not None and len(idx):
            idx = idx[np.asarray(printed, dtype=bool)[idx]]
    return idx


def is_noise(param_name: str) -> bool:
    """A parameter of the noise model (``noise.*``), not of the print."""
    return param_name.startswith("noise.")


def is_nuisance(param_name: str) -> bool:
    return param_name.split(".", 1)[0] in NUISANCE_EFFECTS


class JointProblem:
    """The posterior over the shared physical parameters, per-scan nuisance and noise
    parameters of one or several scans.

    ``scans``: list of :class:`fit.data.ScanData` (ctx, y, sd, gaps), ``models``: one model
    per scan with identical ``param_names`` (same spec; the profile may differ). Global
    parameter names: shared ones as the model names them (``pa.tau_s``); per-scan ones get
    ``@<scan name>`` appended when there is more than one scan.
    """

    def __init__(self, scans, models, noise: NoiseOptions = NoiseOptions(),
                 prior_overrides: dict | None = None):
        from fit.priors import apply_overrides

        if len(scans) != len(models) or not scans:
            raise ValueError("need one model per scan and at least one scan")
        names0 = list(models[0].param_names)
        for m in models[1:]:
            if list(m.param_names) != names0:
                raise ValueError("all scans of a joint fit need the same model parameters")
        self.scans, self.models, self.noise = list(scans), list(models), noise
        self.prior_overrides = dict(prior_overrides or {})
        joint = len(scans) > 1
        params = {p.name: p for p in models[0].params}
        names: list[str] = []
        priors: dict[str, Prior] = {}
        self.index: list[np.ndarray] = []        # per scan: global index of each model param
        self.noise_index: list[tuple[int, int | None, int | None]] = []
        self.rel_index: list[int | None] = []       # per scan: noise.rel_share (relative wobble)
        self.meas_index: list[int | None] = []      # per scan: noise.meas_corr (linked errors)
        # per scan: the median commanded width (mm), where sigma_extra is the wobble's sd
        # whatever its relative share (module docstring)
        self.c_ref_mm = [_median_commanded_mm(sc) for sc in scans]
        shared_pos = {}
        for n in names0:
            if not (joint and is_nuisance(n)):
                shared_pos[n] = len(names)
                names.append(n)
                priors[n] = prior_from_param(params[n])
        for k, sc in enumerate(scans):
            idx = []
            for n in names0:
                if n in shared_pos:
                    idx.append(shared_pos[n])
                else:
                    g = f"{n}@{sc.name}"
                    idx.append(len(names))
                    names.append(g)
                    priors[g] = prior_from_param(params[n])
            self.index.append(np.array(idx, dtype=int))
        for sc in scans:
            suffix = f"@{sc.name}" if joint else ""
            i_sig = len(names)
            names.append(SIGMA_NAME + suffix)
            priors[SIGMA_NAME + suffix] = noise.sigma_prior
            i_rel = None
            if noise.relative:
                i_rel = len(names)
                names.append(REL_NAME + suffix)
                priors[REL_NAME + suffix] = noise.rel_prior
            self.rel_index.append(i_rel)
            i_cor = i_short = None
            if noise.ar1:
                i_cor = len(names)
                names.append(CORR_NAME + suffix)
                # with the short wobble the long one starts at LONG_MIN_FACTOR x its length:
                # two components of one length are one component with two names, and the
                # walkers then wander between them (a toy fit with a single 0.6 mm wobble
                # did not converge in 6000 steps)
                priors[CORR_NAME + suffix] = corr_prior_of(sc, noise)
                if noise.short:
                    i_short = len(names)
                    names.append(SHORT_NAME + suffix)
                    priors[SHORT_NAME + suffix] = noise.short_prior
            self.noise_index.append((i_sig, i_cor, i_short))
            i_meas = None
            if noise.meas_corr and np.any(scan_links(sc)):
                i_meas = len(names)
                names.append(MEAS_NAME + suffix)
                priors[MEAS_NAME + suffix] = noise.meas_prior
            self.meas_index.append(i_meas)
        if prior_overrides:
            priors = apply_overrides(priors, prior_overrides)
        self.param_names = names
        self.priors = [priors[n] for n in names]
        # censored stations (module docstring): rows of each scan and their w_min (mm)
        self.missing_idx: list[np.ndarray] = []
        self.missing_w_min_mm: list[np.ndarray] = []
        for sc in scans:
            idx = censored_rows(sc) if noise.missing else np.zeros(0, np.int64)
            sd = np.asarray(sc.table.fit_sd_mm(), dtype=float)[idx] if len(idx) else np.zeros(0)
            sd = np.where(np.isfinite(sd), sd, 0.0)
            self.missing_idx.append(idx)
            self.missing_w_min_mm.append(np.maximum(sd, float(noise.missing_w_min_floor_mm)))
        self.n_valid = int(sum(sc.n_valid for sc in scans))
        self.n_missing = int(sum(len(i) for i in self.missing_idx))
        self.n_obs = self.n_valid + self.n_missing

    def with_noise(self, noise: NoiseOptions) -> "JointProblem":
        """The same scans, models and prior overrides under another noise model."""
        return JointProblem(self.scans, self.models, noise, self.prior_overrides or None)

    # -- parameter vector ---------------------------------------------------------
    @property
    def ndim(self) -> int:
        return len(self.param_names)

    @property
    def bounds(self) -> np.ndarray:
        return np.array([[p.lower, p.upper] for p in self.priors])

    def default_theta(self) -> np.ndarray:
        th = np.empty(self.ndim)
        for k, m in enumerate(self.models):
            th[self.index[k]] = m.default_theta()
        for i_sig, i_cor, i_short in self.noise_index:
            th[i_sig] = 0.01
            if i_cor is not None:
                th[i_cor] = 0.5
            if i_short is not None:
                th[i_short] = 0.001
        # the relative share starts at 0, the constant-sd wobble: from 0.5 the toy joint fit
        # of tests/test_fit_core.py fell into the basin where a 0.12 mm wobble absorbs the
        # flow steps (tau at its 3 s bound, ln posterior 136 below the truth's)
        for i_rel in self.rel_index:
            if i_rel is not None:
                th[i_rel] = 0.0
        # the measurement's own value of the linked errors' correlation (its table)
        for sc, i_meas in zip(self.scans, self.meas_index):
            if i_meas is not None:
                rho = np.asarray(sc.corr_prev, dtype=float)
                th[i_meas] = float(np.median(rho[rho != 0]))
        lo, hi = self.bounds.T
        return np.clip(th, lo, hi)

    def log_prior(self, theta) -> np.ndarray:
        th = np.atleast_2d(theta)
        lp = np.zeros(th.shape[0])
        for j, p in enumerate(self.priors):
            lp += p.log_prob(th[:, j])
        return lp

    def model_theta(self, theta, k: int) -> np.ndarray:
        """The (n_sets, n_model_params) parameter array of scan ``k``'s model."""
        return np.atleast_2d(theta)[:, self.index[k]]

    # -- evaluation ---------------------------------------------------------------
    def predict(self, theta, k: int) -> np.ndarray:
        """Model widths (n_sets, n_rows) of scan ``k`` at all its rows (mm). The last
        batch evaluated by :meth:`pointwise` is reused (LOO draws then predictions)."""
        mt = self.model_theta(theta, k)
        cached = getattr(self, "_last_pred", {}).get(k)
        if cached is not None and cached[0].shape == mt.shape and np.array_equal(cached[0], mt):
            return cached[1].copy()
        return np.atleast_2d(self.models[k].predict(self.scans[k].ctx, mt))

    def log_prob(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """(log posterior (n_sets,), pointwise log-likelihood (n_sets, n_obs))."""
        th = np.atleast_2d(np.asarray(theta, dtype=float))
        lp = self.log_prior(th)
        ll = np.full((th.shape[0], self.n_obs), -np.inf)
        ok = np.isfinite(lp)
        for k, m in enumerate(self.models):
            if ok.any() and hasattr(m, "log_prior"):
                lpm = np.asarray(m.log_prior(self.model_theta(th[ok], k)), dtype=float).reshape(-1)
                sub = np.flatnonzero(ok)
                ok[sub[~np.isfinite(lpm)]] = False
        if ok.any():
            ll_ok = self.pointwise(th[ok])
            ll[ok] = ll_ok
        total = np.where(ok, lp + ll.sum(axis=1), -np.inf)
        total = np.where(np.isfinite(total), total, -np.inf)
        return total, ll

    def pointwise(self, theta) -> np.ndarray:
        """Pointwise log-likelihood (n_sets, n_obs) for parameters inside the support:
        the valid samples of every scan (Kalman terms, scan after scan), then the censored
        terms of every scan's missing stations (:func:`missing_loglik`)."""
        th = np.atleast_2d(np.asarray(theta, dtype=float))
        n_sets = th.shape[0]
        nu = self.noise.student_nu
        nu_f = -1.0 if nu is None else float(nu)
        c_t = 0.0 if nu is None else float(gammaln(0.5 * (nu_f + 1)) - gammaln(0.5 * nu_f)
                                           - 0.5 * math.log(nu_f * math.pi))
        kern = _AR1_PARALLEL if n_sets >= 4 else _AR1_SERIAL
        out = np.empty((n_sets, self.n_obs))
        direct = len(self.scans) == 1 and self.n_missing == 0
        col, col_m = 0, self.n_valid
        for k, sc in enumerate(self.scans):
            # pointwise_loglik (the reference) with the residuals, in one compiled pass
            pred = np.ascontiguousarray(self.predict(th, k), dtype=float)
            self._last_pred = {**getattr(self, "_last_pred", {}), k: (self.model_theta(th, k).copy(), pred)}
            i_sig, i_cor, i_short = self.noise_index[k]
            sig = np.ascontiguousarray(th[:, i_sig])
            ell = np.ascontiguousarray(th[:, i_cor]) if i_cor is not None else np.zeros(n_sets)
            sig_s = np.ascontiguousarray(th[:, i_short]) if i_short is not None else np.zeros(n_sets)
            i_rel = self.rel_index[k]
            share = np.ascontiguousarray(th[:, i_rel]) if i_rel is not None else np.zeros(n_sets)
            n = len(sc.order)
            buf = out if direct else np.empty((n_sets, n))
            i_meas = self.meas_index[k]
            rho_m = np.ascontiguousarray(th[:, i_meas]) if i_meas is not None else np.zeros(n_sets)
            kern(pred, *self._kernel_arrays(k), sig, share, self.c_ref_mm[k], ell, sig_s,
                 float(self.noise.short_corr_mm), rho_m, nu_f, c_t, buf)
            if buf is not out:
                out[:, col:col + n] = buf
            col += n
            mi = self.missing_idx[k]
            if len(mi):
                out[:, col_m:col_m + len(mi)] = missing_loglik(
                    pred[:, mi], self.missing_w_min_mm[k], np.hypot(sig, sig_s)[:, None], nu,
                    self.noise.missing_false_rate)
                col_m += len(mi)
        return out

    def _kernel_arrays(self, k: int) -> tuple:
        """(order, y, sd^2, link, gap) of scan k as the AR(1) kernel takes them, built
        once: the sampler calls :meth:`pointwise` thousands of times on the same data."""
        sc = self.scans[k]
        rho = getattr(sc, "corr_prev", None)
        key = (id(sc.order), id(sc.y_mm), id(sc.sd_mm), id(sc.gap_mm), id(rho))
        cache = self.__dict__.setdefault("_arrays", {})
        if cache.get(k, (None,))[0] != key:
            link = scan_links(sc) if self.meas_index[k] is not None else np.zeros(len(sc.order))
            cache[k] = (key, (np.ascontiguousarray(sc.order, dtype=np.int64),
                              np.ascontiguousarray(sc.y_mm, dtype=float),
                              np.ascontiguousarray(sc.sd_mm, dtype=float) ** 2,
                              np.ascontiguousarray(link, dtype=float),
                              np.ascontiguousarray(sc.gap_mm, dtype=float)))
        return cache[k][1]

    def wobble_parts(self, theta, k: int, pred_mm) -> tuple[float, np.ndarray | None]:
        """The long wobble of scan ``k`` as (fixed sd, relative sd per valid sample or None)
        (mm), h^2 = fixed^2 + rel^2 (module docstring): sigma_extra sqrt(1 - f) and
        sigma_extra sqrt(f) max(m, 0) / c_ref, for one theta and its model widths ``pred_mm``
        at the valid samples (mm)."""
        th = np.asarray(theta, dtype=float)
        sig = float(th[self.noise_index[k][0]])
        i_rel = self.rel_index[k]
        if i_rel is None:
            return sig, None
        f = float(th[i_rel])
        m = np.maximum(np.asarray(pred_mm, dtype=float), 0.0)
        return sig * math.sqrt(1.0 - f), sig * math.sqrt(f) * m / self.c_ref_mm[k]

    def meas_parts(self, theta, k: int) -> tuple[np.ndarray | None, float]:
        """Scan ``k``'s linked measurement errors for one theta: (link (n_valid,) or None,
        correlation ``noise.meas_corr``), as :func:`whiten` takes them."""
        i_meas = self.meas_index[k]
        if i_meas is None:
            return None, 0.0
        return scan_links(self.scans[k]), float(np.asarray(theta, dtype=float)[i_meas])

    def residuals(self, theta) -> list[np.ndarray]:
        """Residuals y - m (mm) at the valid samples of each scan, for one theta."""
        th = np.atleast_2d(theta)[:1]
        return [sc.y_mm - self.predict(th, k)[0, sc.order] for k, sc in enumerate(self.scans)]

    def whitened_residuals(self, theta) -> np.ndarray:
        """Standardised innovations v / sqrt(F) (dimensionless, ~N(0,1) if the model is
        right), all scans."""
        th = np.atleast_2d(theta)[:1]
        out = []
        for k, sc in enumerate(self.scans):
            m = self.predict(th, k)[0, sc.order]
            i_sig, i_cor, i_short = self.noise_index[k]
            fixed, rel = self.wobble_parts(th[0], k, m)
            out.append(whiten(sc.y_mm - m, sc.sd_mm, fixed, sc.gap_mm, None if i_cor is None else th[0, i_cor],
                              0.0 if i_short is None else float(th[0, i_short]), self.noise.short_corr_mm, rel,
                              *self.meas_parts(th[0], k)))
        return np.concatenate(out)
