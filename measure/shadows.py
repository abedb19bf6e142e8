"""The lamp's cast shadow beside a bead: which stations' edge pairs take one, and on which side.

A lamp at elevation e lights a bead h tall from one side; the plate beside its other edge
lies in the bead's shadow out to ~h / tan(e) (a flatbed's lamp at 45 deg: up to 0.19 mm
beyond a rounded 0.3 mm bead's footprint, measure/phenomena.py ``shadows``). The shadow is
a third level between plate and bead, and the plain edge pair puts that edge halfway
across it: on a 600 dpi flatbed render of dark beads on a light plate the widths read up
to +72 um wide where the beads lie across the lamp (a lamp 6 deg across; +91 um under a
point lamp), +3 um along it (docs/MEASUREMENT.md, "The lamp's shadow"). Where it pays,
measure/widths.py refits the station's edge pair with the shadow's shelf outside the edge
facing away from the lamp (measure/edges.py :func:`~measure.edges.fit_shadow`), and keeps
it where it explains significantly more, F = [(RSS_plain - RSS_shelf) / q] /
[RSS_shelf / (M - k - q)] > ``SHADOW_F`` (q the shelf's free parameters), and the shelves
look like one lamp's over the scan (:func:`_one_lamp`). One lamp casts every shadow the
same way: the shelf's side as a bed direction (side x normal) points away from it at
every station. Widths in mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from measure import edges

#: F statistic above which the shadow's shelf replaces the plain edge pair (the glare
#: streak's bar, measure/streaks.py STREAK_F; shadow-free renders: docs/MEASUREMENT.md).
SHADOW_F = 30.0
#: Shelves are believed only when at least this many stations show one and their sides, as
#: bed directions, agree: |mean of side x normal| >= SHADOW_COHERENCE.
SHADOW_MIN_STATIONS = 20
SHADOW_COHERENCE = 0.6
#: A shelf is looked for only on beads at least this many blurs wide (a narrower bead's
#: blurred profile trades its width with a shelf, as with a streak).
SHADOW_MIN_BLURS = 2.5
#: The shelf reaches at most this many bead heights beyond the edge: h / tan(e) for a lamp
#: down to 27 deg above the plate (a rounded flank's shadow is shorter than a wall's).
SHADOW_REACH_PER_HEIGHT = 2.0
#: ... and only where the bead lies across the lamp by at least this much (|n . away|, n the
#: profile's normal): sin of 15 deg.
SHADOW_MIN_ACROSS = 0.25
#: One lamp's shadows (:func:`_one_lamp`): at least this share of the beads well across it
#: take a shelf, and the shelves' darkening (a share of the plate's brightness) has an
#: interquartile range within this fraction of its median.
SHADOW_SHARE = 0.8
#: A shadow takes at least this share of the plate's light (the room's diffuse light fills
#: it in; below this it does not move an edge by a micron).
SHADOW_MIN_DEPTH = 0.05
#: ... and at most this share: a shelf taking all of it is the fit leaning on its bound (a
#: light bead's glare on the dark plate fitted shelves at 4-12x the plate's light before D
#: was bounded by it, 0.99 after; a real shadow keeps the room's diffuse light).
SHADOW_MAX_DEPTH = 0.95
SHADOW_DEPTH_SPREAD = 0.5
#: What the shelf leaves of the lamp's shading, per unit of |n . away| (mm), added to the
#: stations' sd on a scan with shadows: on 600 dpi flatbed renders the beads across the lamp
#: read 5-7 um (dark beads on a light plate, after the shelf) and -9 um (light beads on a
#: dark plate: their far flank in its own shadow) off those along it, against station sds
#: of ~1 um.
SHADOW_DOUBT_MM = 0.008
#: ... and the share of it left where each station's heading level came off its width (the
#: same renders: 2.4-2.8 um RMS left against 3.8-4.9 before).
SHADOW_LEFT_SHARE = 0.4
#: Large scans are screened on one station in this many, both sides, before the rest are
#: tried on the side away from the lamp the screen found.
SHADOW_SCREEN_EVERY = 8
#: ... and the lamp the screen shows is believed only beyond this many times the coherence
#: n passes have with their sides at random (1 / sqrt(n)), as for the glare streaks.
SHADOW_SCREEN_CHANCE = 2.5
#: A scan with at least SHADOW_PRESCREEN_MIN stations in a quarter of the screen is looked
#: at there first, and not screened when fewer than SHADOW_PRESCREEN_SHARE of those took a
#: shelf or their sides agree less than SHADOW_PRESCREEN_COHERENCE (half the screen's bar).
#: The screen's fits (a shelf, a streak and both, on either side) were 2.2 of a shadow-free
#: 12 MP phone render's 6.4 s. Measured on the quarter (2026-12-02, bench_realism): shadow-
#: free phone 5 % of the stations, coherence 0.40; the phone's unresolved shadows 9 %, 0.20
#: (its screen fails too: 0.15-0.20); a light plate's shadows on its colour axis (resolved
#: as "unresolved" after the screen) 20-21 %, 0.47-0.62; flatbed shadows 56-80 %, 0.72-0.86.
SHADOW_PRESCREEN_MIN = 80
SHADOW_PRESCREEN_SHARE = 0.10
SHADOW_PRESCREEN_COHERENCE = 0.3
#: The lamp's glare is fitted beside the shelves of the whole scan (:func:`_shelf_test`)
#: where at least this share of the screen's shelves took a streak (a light plate's shadows
#: in glare 0.58-0.99, without glare 0.01): 18 s for a 600 dpi flatbed scan with it, 10.5
#: without.
SHADOW_GLARE_SHARE = 0.1


@dataclass(frozen=True)
class ShadowModel:
    """One lamp's shadows over a scan, as its test tracks showed them: the bed direction
    away from the lamp (unit), the share of the plate's brightness a shadow takes
    (``depth``, None where too few shelves were resolved) and the reach law (k, p, fade) of
    :func:`_reach_law` (None where the beads' headings could not tell it), and whether its
    glare is fitted beside the shelves (:func:`_shelf_test`). Another
    measurement of the same picture (the width reference, whose passes lie one way and so
    cannot tell a shadow from a one-sided misfit) takes the scan's decision from it."""

    away: np.ndarray
    depth: float | None = None
    law: tuple | None = None
    glare: bool = True


@dataclass
class Shadows:
    """The shadow's shelf per station (N stations).

    side       -1 / +1: the shelf lies outside the low-t / high-t edge; 0: none
    shelf      (N, 3) its darkening D (intensity), full-shadow reach L (mm) and penumbra
               P (mm) (measure/edges.py fit_shadow); NaN where none
    reach_mm   (N,) the bound of L at each station (SHADOW_REACH_PER_HEIGHT x h)
    away       unit bed direction away from the lamp (the shadows' side), or None
    model      the scan's :class:`ShadowModel`, or None (no shadows found)
    unresolved the bed direction away from a lamp whose shadow the beads show but no shelf
               could model (blurred over: measure/pipeline.py then leaves the width
               reference unapplied), or None
    """

    side: np.ndarray
    shelf: np.ndarray
    reach_mm: np.ndarray
    away: np.ndarray | None = None
    model: ShadowModel | None = None
    unresolved: np.ndarray | None = None

    @property
    def any(self) -> bool:
        return bool(np.any(self.side != 0))

    def to_dict(self) -> dict:
        """The summary's ``shadows`` block: stations with a shelf, the bed direction away
        from the lamp (deg), the share of light a shadow takes, and whether a coherent
        one-sided dark band was seen that could not be modelled (``unresolved``)."""
        away = self.away if self.away is not None else self.unresolved
        return {"stations": int(np.sum(self.side != 0)),
                "away_deg": round(float(np.degrees(np.arctan2(away[1], away[0]))), 1) if away is not None else None,
                "depth": (round(self.model.depth, 3) if self.model is not None and self.model.depth is not None
                          else None),
                "unresolved": self.unresolved is not None}


def no_shadows(n: int, height_mm) -> Shadows:
    h = np.broadcast_to(np.asarray(height_mm, float), (n,))
    return Shadows(np.zeros(n), np.full((n, 3), np.nan), SHADOW_REACH_PER_HEIGHT * h)


def with_shadows(t, y, fit, wts, height_mm, normals, fixed_s: bool = True, model=None):
    """The plain fit, with stations where the lamp's shadow explains significantly more
    (F > SHADOW_F) on the side away from the scan's one lamp replaced by the shelf fit
    (their PARAMS); and the :class:`Shadows`. normals (N, 2): profile direction (bed frame).

    Large scans are screened first on one station in SHADOW_SCREEN_EVERY, on both sides:
    when those show no coherent lamp the scan has no shadows and the rest are not tried
    (and where a quarter of those shows next to no shelf, the rest of the screen is not
    tried either: SHADOW_PRESCREEN_SHARE).
    Otherwise every station is tried on the side away from the lamp the screen shows, and
    the full test's coherence decides, as for the glare streaks (measure/streaks.py).

    ``model``: the scan's :class:`ShadowModel` from its test tracks (False: they showed
    none); the stations are then fitted on its side, depth and reach, not judged anew."""
    n = len(t)
    out = no_shadows(n, height_mm)
    if model is False:
        return fit, out
    idx = np.flatnonzero(fit.ok & (fit.params[:, 4] >= SHADOW_MIN_BLURS * fit.params[:, 5]))
    h_all = np.broadcast_to(np.asarray(height_mm, float), (n,))
    if model is not None:
        return _apply_model(t, y, fit, wts, normals, idx, fixed_s, model, out, h_all)
    if len(idx) < SHADOW_MIN_STATIONS:
        return fit, out
    sub = idx[::SHADOW_SCREEN_EVERY] if len(idx) >= SHADOW_SCREEN_EVERY * SHADOW_MIN_STATIONS else idx
    pre = sub[::4]
    if len(pre) >= SHADOW_PRESCREEN_MIN:
        use, _, away_i, _ = _shelf_test(t, y, fit, wts, normals, out.reach_mm, pre, fixed_s, None)
        coherence = np.hypot(*away_i[use].mean(axis=0)) if use.any() else 0.0
        if use.mean() < SHADOW_PRESCREEN_SHARE or coherence < SHADOW_PRESCREEN_COHERENCE:
            return fit, out
    use, best, away_i, _ = _shelf_test(t, y, fit, wts, normals, out.reach_mm, sub, fixed_s, None)
    away = away_i[use].mean(axis=0) if use.any() else np.zeros(2)
    if (use.sum() < 0.5 * SHADOW_MIN_STATIONS * len(sub) / len(idx)
            or np.hypot(*away) < max(SHADOW_COHERENCE, SHADOW_SCREEN_CHANCE / np.sqrt(max(use.sum(), 1)))):
        return fit, out
    # The lamp's glare beside its shadow (_shelf_test) costs two more fits a side: past the
    # screen it is fitted only where the screen's shelves took it (a shadow-free scene's
    # screen cannot tell: on a light plate in glare the shelves alone found no lamp, or the
    # wrong side, where the glare beside them found it)
    glare = bool(np.mean(best.params[use, 6] > 0) >= SHADOW_GLARE_SHARE)
    # a bead that lies along the lamp has no shadow beside it: a shelf there is misfit
    # (11 % of such stations took one on the flatbed render, reading 10 um narrow)
    idx = idx[np.abs(normals[idx] @ (away / np.hypot(*away))) >= SHADOW_MIN_ACROSS]
    use, best, away_i, _ = _shelf_test(t, y, fit, wts, normals, out.reach_mm, idx, fixed_s, away, glare=glare)
    away = away_i[use].mean(axis=0) if use.sum() >= SHADOW_MIN_STATIONS else np.zeros(2)
    if np.hypot(*away) < SHADOW_COHERENCE:
        return fit, out
    use &= away_i @ away > 0
    h_idx = h_all[idx]
    if not _one_lamp(best, use, normals[idx], away, h_idx):
        # a dark band on one side of the beads, one way over the bed, that is no clean
        # shadow: under a blur wider than its reach (a flatbed's defocus, translucent flanks:
        # 72 % of the beads across the lamp took a shelf darkening 0.11 of the plate, the
        # truth 0.5) it cannot be modelled, and the width reference, whose passes shade one
        # another, no longer stands for the test tracks. Said where the headings span
        # enough to tell it from a one-sided misfit of parallel tracks.
        na = np.abs(normals[idx[use]] @ (away / np.hypot(*away)))
        share = _darkening(best, use, normals[idx], away)
        if (use.sum() >= SHADOW_MIN_STATIONS and np.ptp(na) >= REACH_LAW_SPAN and len(share)
                and SHADOW_MIN_DEPTH <= np.median(share) <= SHADOW_MAX_DEPTH):
            out.unresolved = away / np.hypot(*away)
        return fit, out
    # One lamp, one share of its light gone in every shadow: D is that share of the plate's
    # brightness beside the edge. Read where the shelf is wider than the blur (there D and L
    # part), held everywhere: a narrow shelf (a bead nearly along the lamp) tells only
    # D x L, and with both free it failed the F test and left its bead 10-25 um wide.
    depth = _shadow_depth(best, use, np.where(normals[idx] @ away >= 0, 1.0, -1.0))
    law = None
    if depth is not None:
        use, best, away_i, base = _shelf_test(t, y, fit, wts, normals, out.reach_mm, idx, fixed_s, away, depth,
                                              glare=glare)
        use &= away_i @ away > 0
        # ... and one lamp's elevation: the reach falls as the bead turns toward the lamp,
        # L = k h |n . away|^p, read on the shelves wider than 1.5 blurs (k and p free: a
        # wall's shadow has p = 1, a rounded flank's more). Where the shelf is narrower than
        # the F test can see, it is fitted at that reach: those beads read 6-20 um wide
        # (600 dpi flatbed render, dark beads on a light plate, normals 30-50 deg off the lamp).
        law = _reach_law(best, use, normals[idx], away, h_idx)
        if law is not None:
            _held_reach(t, y, fit, wts, normals, out.reach_mm, idx, fixed_s, away, depth, law, use, best, base, h_all)
    out.model = ShadowModel(away / np.hypot(*away), depth, law, glare)
    return _with_shelves(fit, out, idx[use], best.params[use], best.sd[use], best.rms[use], normals)


def _with_shelves(fit, out, on, params_on, sd_on, rms_on, normals):
    """The fit with the stations ``on`` replaced by their shelf fits, and ``out`` filled."""
    away = out.model.away
    params, sd, rms = fit.params.copy(), fit.sd.copy(), fit.rms.copy()
    params[on], sd[on], rms[on] = params_on[:, :6], sd_on[:, :6], rms_on
    out.side[on] = np.where(normals[on] @ away >= 0, 1.0, -1.0)
    out.shelf[on] = params_on[:, 8:11]
    out.away = away
    return edges.ProfileFit(params, sd, rms, fit.ok), out


def _apply_model(t, y, fit, wts, normals, idx, fixed_s, model, out, h):
    """Shelves on the stations ``idx`` after the scan's ``model``: on the side away from its
    lamp, across it by SHADOW_MIN_ACROSS or more; F-tested with D held at its depth (free
    without one), then at its reach law where that failed."""
    out.model = model
    idx = idx[np.abs(normals[idx] @ model.away) >= SHADOW_MIN_ACROSS]
    if len(idx) == 0:
        return _with_shelves(fit, out, idx, np.zeros((0, 11)), np.zeros((0, 11)), np.zeros(0), normals)
    use, best, _, base = _shelf_test(t, y, fit, wts, normals, out.reach_mm, idx, fixed_s, model.away,
                                     model.depth, glare=model.glare)
    if model.depth is not None and model.law is not None:
        _held_reach(t, y, fit, wts, normals, out.reach_mm, idx, fixed_s, model.away, model.depth, model.law, use,
                    best, base, h)
    return _with_shelves(fit, out, idx[use], best.params[use], best.sd[use], best.rms[use], normals)


def _one_lamp(best, use, normals, away, h) -> bool:
    """Do the shelves that passed look like one lamp's shadows? Most beads that lie well
    across it (|n . away| >= 0.7) take one (SHADOW_SHARE), their darkening is one share of
    the plate's brightness (its interquartile range on those beads within
    SHADOW_DEPTH_SPREAD of its median), and where the beads' headings tell, the shadow
    reaches further the more the bead lies across the lamp (:func:`_reach_law`'s p >= 0.5;
    a wall's shadow has 1). A one-sided misfit on parallel tracks is coherent by
    construction: a 4:2:0
    JPEG of a grained light plate measured on colour (no shadow) had 41-56 % of its
    across-beads take a shelf, darkening 0.11 of the plate with an IQR of 0.07-0.38; a
    shadow render 94-100 %, 0.47-0.48 with 0.03-0.05."""
    a = away / np.hypot(*away)
    across = np.abs(normals @ a) >= 0.7
    if not across.any() or use[across].mean() < SHADOW_SHARE:
        return False
    # read where the shelf is wide: on a dark plate the narrow shelves of beads nearly along
    # the lamp spread their share (light beads, seed 1: IQR 0.50 of the median over all
    # shelves, 0.44 over these; a shadow on the light plate 0.09 / 0.05; the grained JPEG's
    # misfit 2.2 / 2.5)
    frac = _darkening(best, use & across, normals, away)
    if len(frac) < SHADOW_MIN_STATIONS:
        return False
    q1, med, q3 = np.percentile(frac, [25, 50, 75])
    if not (SHADOW_MIN_DEPTH <= med <= SHADOW_MAX_DEPTH and (q3 - q1) <= SHADOW_DEPTH_SPREAD * med):
        return False
    law = _reach_law(best, use, normals, away, h)
    return law is None or law[1] >= 0.5


def _darkening(best, use, normals, away) -> np.ndarray:
    """The share of the plate's light each passing shelf takes (finite values only)."""
    P = best.params[use]
    side = np.where(normals[use] @ away >= 0, 1.0, -1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = P[:, 8] / np.abs(_background(P, side))
    return frac[np.isfinite(frac)]


def _background(p, side):
    """The plate's brightness beside the edge on ``side`` of fits p (N, >= 6)."""
    return p[:, 0] + p[:, 1] * (p[:, 3] + side * p[:, 4] / 2)


def _shadow_depth(best, use, sides) -> float | None:
    """The share of the plate's brightness the lamp's shadows take (0-1), the median over
    the accepted shelves whose full shadow is wider than 1.5 blurs (all of them if fewer
    than SHADOW_MIN_STATIONS are); None without enough shelves. ``sides`` (N,) +-1."""
    P = best.params[use]
    if len(P) < SHADOW_MIN_STATIONS:
        return None
    side = sides[use]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = P[:, 8] / np.abs(_background(P, side))
    wide = (P[:, 9] > 1.5 * P[:, 5]) & np.isfinite(frac)
    pick = frac[wide] if wide.sum() >= SHADOW_MIN_STATIONS else frac[np.isfinite(frac)]
    if len(pick) == 0:
        return None
    depth = float(np.median(pick))
    return depth if SHADOW_MIN_DEPTH <= depth <= SHADOW_MAX_DEPTH else None


#: The reach law is read only from at least this many resolved shelves spanning this range
#: of |n . away| (a scan whose beads all lie one way across the lamp cannot tell p).
REACH_LAW_SPAN = 0.3
#: ... read on the beads of the heading bins (this wide in |n . away|) whose median shelf
#: reaches past 1.5 blurs.
REACH_LAW_BIN = 0.1


def _reach_law(best, use, normals, away, h):
    """(k, p, f) of the shadows' outer reach L + P = k h |n . away|^p from the accepted
    shelves of the headings whose shelves reach past 1.5 blurs (least squares on
    logarithms), and the share f of it that is penumbra (the median: a lamp's angular size
    makes the penumbra grow with the distance, as the reach does), or None."""
    P = best.params
    na = np.abs(normals @ (away / np.hypot(*away)))
    outer = P[:, 9] + P[:, 10]
    # Chosen by heading, not by the reach each shelf read: of the beads nearly along the
    # lamp only the shelves that happened to read long pass "wider than 1.5 blurs", which
    # flattens the law (a defocused flatbed scan with translucent flanks: p 0.39 so, 0.64
    # by heading bins, 1.7 with D held; docs/MEASUREMENT.md "The lamp's shadow").
    wide = np.zeros(len(na), bool)
    for lo in np.arange(0.0, 1.0, REACH_LAW_BIN):
        b = use & (na > max(lo, 0.05)) & (na <= lo + REACH_LAW_BIN + 1e-9)
        if b.sum() >= 5 and np.median(outer[b]) > 1.5 * np.median(P[b, 5]):
            wide |= b
    if wide.sum() < SHADOW_MIN_STATIONS or np.ptp(na[wide]) < REACH_LAW_SPAN:
        return None
    A = np.column_stack([np.ones(wide.sum()), np.log(na[wide])])
    (a, p), *_ = np.linalg.lstsq(A, np.log(outer[wide] / h[wide]), rcond=None)
    return float(np.exp(a)), float(p), float(np.median(P[wide, 10] / outer[wide]))


def _held_reach(t, y, fit, wts, normals, reach_mm, idx, fixed_s, away, depth, law, use, best, base_rms, h):
    """The stations ``idx`` on which no shelf passed the F test, refitted on the side away
    from the lamp with D held at ``depth`` and L at the reach ``law`` (k, p): no parameter
    added (the glare streak free beside it where :func:`_shelf_test` found one: G > 0 in
    ``best``), kept where that fits better than what the shelf was tested against
    (``base_rms``). Updates ``use`` and ``best`` in place."""
    k, p, fade = law
    p = float(np.clip(p, 0.5, 3.0))
    a = away / np.hypot(*away)
    na = np.abs(normals[idx] @ a)
    reach = np.minimum(k * h[idx] * na ** p, reach_mm[idx])        # L + P
    todo = np.flatnonzero(~use & (reach > 0.1 * fit.params[idx, 5]))
    facing = np.where(normals[idx] @ a >= 0, 1.0, -1.0)
    lit = best.params[:, 6] > 0
    for side in (-1.0, 1.0):
        for glare in (False, True):
            o = todo[(facing[todo] == side) & (lit[todo] == glare)]
            if len(o) == 0:
                continue
            i = idx[o]
            f = edges.fit_shadow(t[i], y[i], fit.params[i, :6], side, reach_mm[i], fixed_s=fixed_s, weights=wts[i],
                                 dark=depth * np.abs(_background(fit.params[i], side)),
                                 reach_held=(1 - fade) * reach[o],
                                 fade_held=np.maximum(fade * reach[o], 0.05 * fit.params[i, 5]),
                                 glare_height_mm=h[i] if glare else None)
            better = f.ok & (f.rms < base_rms[o])
            j = o[better]
            use[j] = True
            best.params[j], best.sd[j], best.rms[j], best.ok[j] = f.params[better], f.sd[better], f.rms[better], \
                f.ok[better]


def _shelf_test(t, y, fit, wts, normals, reach_mm, idx, fixed_s, away=None, depth=None, glare=True):
    """For the stations ``idx``: whether a shelf passes the F test, the better side's fit
    (N, 11), that side as a bed direction (side x normal), and the rms of the fit the shelf
    was tested against (N,). ``away`` (a bed direction): only the side that faces it; None:
    both. ``depth``: D held at that share of the plate's brightness beside the edge (two
    parameters added, not three).

    The lamp that casts a shadow outside one edge puts its glare streak inside the other
    (``glare``): each side is fitted as shelf alone, against the plain pair, and as streak +
    shelf, against the streak alone (G > 0 in the fit returned), the one with the larger F
    kept; of the two sides, the one whose fit leaves the smaller residual variance. With
    the blur free the streak alone barely improves on a plain pair whose blur took glare
    and shadow both, so it is not asked to pass first (22 % of the beads across the lamp
    took a shelf then, against all with the blur held); and the side is chosen by the fit,
    not by the larger F, whose baselines differ between the sides (a streak misplaced on
    the shadow's flank is a poor one: 74 % of the beads 30-55 deg off the lamp took the
    wrong side so). Without the streak a flatbed scan in glare (dark beads, light plate)
    fitted shelves of 0.11 of the plate's light for 0.5, too few to be believed, and the
    streak step then took the unmodelled shadow for more streak: +40 um on the beads
    across the lamp."""
    n = len(idx)
    m_eff = wts[idx].sum(axis=1)
    k0 = 5 if fixed_s else 6
    extra = 3 if depth is None else 2            # D, L, P free; L, P with D held
    h = reach_mm / SHADOW_REACH_PER_HEIGHT
    rss0 = fit.rms[idx] ** 2 * np.maximum(m_eff - k0, 1)
    best_var = np.full(n, np.inf)
    best_F = np.full(n, -np.inf)
    best_side = np.zeros(n)
    base_rms = fit.rms[idx].copy()
    best = edges.ProfileFit(np.full((n, 11), np.nan), np.full((n, 11), np.nan), np.full(n, np.nan), np.zeros(n, bool))
    if away is None:
        sides = ((-1.0, np.arange(n)), (1.0, np.arange(n)))
    else:
        facing = np.where(normals[idx] @ np.asarray(away, float) >= 0, 1.0, -1.0)
        sides = tuple((s, np.flatnonzero(facing == s)) for s in (-1.0, 1.0))

    def fitted(o, f, k, base_rss):
        """Residual variance and the shelf's F of the fits f (stations o, k parameters
        before the shelf's)."""
        dof = np.maximum(m_eff[o] - k - extra, 1)
        rss = np.where(f.ok, f.rms ** 2 * dof, np.inf)
        with np.errstate(invalid="ignore"):
            return rss / dof, (base_rss - rss) / extra / np.maximum(rss / dof, 1e-300)

    for side, o in sides:
        if len(o) == 0:
            continue
        i = idx[o]
        dark = None if depth is None else depth * np.abs(_background(fit.params[i], side))
        f = edges.fit_shadow(t[i], y[i], fit.params[i, :6], side, reach_mm[i], fixed_s=fixed_s, weights=wts[i],
                             dark=dark)
        var, F = fitted(o, f, k0, rss0[o])
        rms_base = fit.rms[i].copy()
        if glare:
            g = edges.fit_streak(t[i], y[i], fit.params[i, :6], -side, h[i], fixed_s=fixed_s, weights=wts[i])
            fj = edges.fit_shadow(t[i], y[i], g.params[:, :6], side, reach_mm[i], fixed_s=fixed_s, weights=wts[i],
                                  dark=dark, glare_height_mm=h[i])
            rss_g = np.where(g.ok, g.rms ** 2 * np.maximum(m_eff[o] - k0 - 2, 1), np.inf)
            var_j, F_j = fitted(o, fj, k0 + 2, rss_g)
            lit = np.flatnonzero(fj.ok & (fj.params[:, 6] > 0) & np.isfinite(F_j)
                                 & (F_j > np.where(np.isfinite(F), F, -np.inf)))
            var[lit], F[lit], rms_base[lit] = var_j[lit], F_j[lit], g.rms[lit]
            for a, b in ((f.params, fj.params), (f.sd, fj.sd), (f.rms, fj.rms), (f.ok, fj.ok)):
                a[lit] = b[lit]
        better = np.isfinite(var) & (var < best_var[o])
        j = o[better]
        best_var[j], best_F[j], best_side[j], base_rms[j] = var[better], F[better], side, rms_base[better]
        best.params[j], best.sd[j], best.rms[j], best.ok[j] = f.params[better], f.sd[better], f.rms[better], \
            f.ok[better]
    use = np.isfinite(best_F) & (best_F > SHADOW_F) & (best.params[:, 8] > 0) & (best.params[:, 9] > 0)
    return use, best, best_side[:, None] * normals[idx], base_rms
