"""The lamp's cast shadow beside a bead (measure/shadows.py, measure/edges.py fit_shadow).

The profiles here are drawn on a fine grid from a rounded bead's height field, shaded by
measure/phenomena.py's ray-marched shadow and blurred numerically: not from the fitted
model's erf formula."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from measure import edges
from measure.phenomena import cast_shadow
from measure.shadows import _reach_law, no_shadows, with_shadows
from measure.streaks import with_glare_streaks

DX_MM = 0.002          # the fine grid the profiles are drawn on
STEP_MM = 0.0085       # the profiles' sampling (600 dpi flatbed, 5 samples a pixel)
BLUR_MM = 0.035


def _profile(w, *, across=1.0, lamp_side=-1.0, h=0.2, elevation_deg=45.0, lamp_deg=6.0, depth=0.5,
             bead=0.08, plate=0.70, c=0.0, noise=0.0, rng=None, half_mm=0.5, glare=0.0, shine=60.0):
    """(t, y): a rounded bead (the slicer's flank, lateral radius h/2) of width w centred at
    c, its profile's normal ``across`` (cos of the angle to the lamp's horizontal direction),
    the lamp on the ``lamp_side`` of t, its shadow cast on plate and bead alike; ``glare``:
    the lamp's Blinn-Phong highlight (peak, exponent ``shine``) on the flank facing it."""
    x = np.arange(-1.0, 1.0, DX_MM)
    d = np.abs(x - c)
    r = min(h / 2, w / 2)
    u = np.clip((d - (w / 2 - r)) / r, 0, 1)
    z = np.where(d <= w / 2, h * np.sqrt(np.clip(1 - u ** 2, 0, 1)), 0.0)
    hf = np.tile(z, (3, 1))
    toward = np.zeros(hf.shape + (2,), np.float32)
    toward[..., 0] = lamp_side * 0.5               # half a grid step toward the lamp per step
    e = np.deg2rad(elevation_deg)
    # in the profile's plane the lamp stands higher the more the bead lies along it: its
    # horizontal part there is cos(e) x across
    light = np.array([lamp_side * np.cos(e) * across, 0.0, np.sin(e)])
    light = light / np.linalg.norm(light)
    s = cast_shadow(hf, toward, light, step_mm=0.5 * DX_MM, lamp_deg=lamp_deg)[1]
    img = np.where(d <= w / 2, bead, plate) * (1 - depth * s)
    if glare:
        normal = np.column_stack([-np.gradient(z, x), np.zeros_like(x), np.ones_like(x)])
        half_v = light + np.array([0.0, 0.0, 1.0])
        cos_h = normal @ (half_v / np.linalg.norm(half_v)) / np.linalg.norm(normal, axis=1)
        img = img + glare * np.clip(cos_h, 0, 1) ** shine * (d <= w / 2)
    img = gaussian_filter1d(img, BLUR_MM / DX_MM)
    t = np.arange(-half_mm, half_mm, STEP_MM)
    y = np.interp(t, x, img)
    if noise:
        y = y + noise * rng.standard_normal(len(t))
    return t, y


@pytest.mark.parametrize("lamp_deg", [0.5, 8.0])
def test_a_shadow_beside_a_bead_is_fitted_and_its_width_kept(lamp_deg):
    """The plain edge pair puts the shadow's side halfway across the shadow (+40-75 um on a
    0.2 mm bead lit at 45 deg); the shelf with its penumbra keeps the width within 10 um
    (the bead's own far flank in its shadow, which no term models, is most of that)."""
    for lamp_side in (-1.0, 1.0):
        t, y = _profile(0.48, lamp_side=lamp_side, lamp_deg=lamp_deg)
        p0 = edges.initial_guess(t[None], y[None], -1.0, BLUR_MM)
        plain = edges.fit_profiles(t[None], y[None], p0)
        sh = edges.fit_shadow(t[None], y[None], plain.params, -lamp_side, 0.4, fixed_s=False)
        assert plain.width[0] - 0.48 > 0.04
        assert sh.ok[0] and abs(sh.width[0] - 0.48) < 0.010
        assert 0.3 < sh.params[0, 8] / 0.70 < 0.55               # D: the shadow takes half the light
        wrong = edges.fit_shadow(t[None], y[None], plain.params, lamp_side, 0.4, fixed_s=False)
        assert wrong.rms[0] > 3 * sh.rms[0]                        # the lamp's side has none


def test_the_lamps_glare_is_fitted_beside_its_shadow():
    """The lamp that shades the plate beside one edge puts its highlight on the other flank
    (drawn here as Blinn-Phong on the rounded flank, not the model's line): the shelf alone
    takes less of the plate's light and leaves the bead wider; with the streak beside it the
    profile is explained to a seventh of the shelf's rms and the width kept."""
    for lamp_side in (-1.0, 1.0):
        t, y = _profile(0.48, lamp_side=lamp_side, glare=0.6)
        p0 = edges.initial_guess(t[None], y[None], -1.0, BLUR_MM)
        plain = edges.fit_profiles(t[None], y[None], p0)
        alone = edges.fit_shadow(t[None], y[None], plain.params, -lamp_side, 0.4, fixed_s=False)
        both = edges.fit_shadow(t[None], y[None], plain.params, -lamp_side, 0.4, fixed_s=False, glare_height_mm=0.2)
        assert both.ok[0] and both.params[0, 6] > 0 and both.rms[0] < 0.3 * alone.rms[0]
        assert abs(both.width[0] - 0.48) < 0.012 and alone.width[0] - both.width[0] > 0.004
        assert 0.4 < both.params[0, 8] / 0.70 < 0.55


def test_the_reach_law_is_read_by_heading_not_by_the_reach_each_shelf_read():
    """Shelves whose reach scatters (lognormal, 35 %) about L + P = 0.75 h |n.a|^1.5 under a
    blur of 0.05 mm: chosen as "reaching past 1.5 blurs" one by one, the near-along beads'
    long draws flatten the law to p ~ 0.7; chosen by heading bins, p is read within 0.2."""
    rng = np.random.default_rng(0)
    n = 600
    na = rng.uniform(0.3, 1.0, n)
    normals = np.column_stack([np.sqrt(1 - na ** 2), na])
    h = np.full(n, 0.2)
    outer = 0.75 * h * na ** 1.5 * np.exp(0.35 * rng.standard_normal(n))
    p = np.zeros((n, 11))
    p[:, 5], p[:, 8], p[:, 9], p[:, 10] = 0.05, 0.3, 0.6 * outer, 0.4 * outer
    k, power, fade = _reach_law(edges.ProfileFit(p, np.zeros_like(p), np.zeros(n), np.ones(n, bool)),
                                np.ones(n, bool), normals, np.array([0.0, 1.0]), h)
    assert abs(power - 1.5) < 0.2 and abs(k - 0.75) < 0.1 and abs(fade - 0.4) < 0.01


def test_no_streak_on_the_shadows_side_of_a_known_lamp():
    """A shadow no shelf models (blurred over) looks like a streak inside the edge away from
    the lamp: the streak step took it so at every bead across the lamp and read them 30 um
    wider still. Told where the lamp is (the shadows' direction), it puts no streak there."""
    t, y, fit, normals, widths = _stations(240, np.random.default_rng(3))
    h = np.full(len(t), 0.2)
    across = np.abs(normals[:, 1]) >= 0.7
    blind, took = with_glare_streaks(t, y, fit, np.ones_like(y), h, normals)
    assert took[across].mean() > 0.9 and np.median(blind.width[across] - fit.width[across]) > 0.02
    lamp = no_shadows(len(t), h)
    lamp.unresolved = np.array([0.0, 1.0])                 # away from the lamp at -y
    told, took = with_glare_streaks(t, y, fit, np.ones_like(y), h, normals, shadows=lamp)
    assert not took.any()
    np.testing.assert_array_equal(told.params, fit.params)


def _stations(n, rng, *, shadow=True, lamp_side_along_y=-1.0, misfit=0.0):
    """n stations of widths 0.3-1.2 mm whose normals turn through the half circle; their
    profiles lit from -y (bed frame) at 45 deg, or not lit at all; ``misfit`` adds a
    one-sided bump outside the +t edge (a misfit that is no shadow)."""
    ang = rng.uniform(0, np.pi, n)
    normals = np.column_stack([np.cos(ang), np.sin(ang)])
    widths = rng.choice([0.3, 0.6, 1.2], n)
    ts, ys = [], []
    for k in range(n):
        across = normals[k] @ np.array([0.0, lamp_side_along_y])    # + : the normal points at the lamp
        side = 1.0 if across > 0 else -1.0
        t, y = _profile(widths[k], across=abs(across), lamp_side=side, depth=0.5 if shadow else 0.0,
                        noise=0.004, rng=rng, half_mm=0.9)
        if misfit:
            y = y - misfit * np.exp(-0.5 * ((t - widths[k] / 2 - 0.05) / 0.03) ** 2)
        ts.append(t)
        ys.append(y)
    t, y = np.array(ts), np.array(ys)
    p0 = edges.initial_guess(t, y, -1.0, BLUR_MM)
    p0[:, 5] = BLUR_MM
    fit = edges.fit_profiles(t, y, p0, fixed_s=True)
    return t, y, fit, normals, widths


def test_one_lamps_shadows_are_found_and_taken_out_and_none_are_invented():
    rng = np.random.default_rng(3)
    t, y, fit, normals, widths = _stations(240, rng)
    wts = np.ones_like(y)
    out, sh = with_shadows(t, y, fit, wts, 0.2, normals)
    assert sh.away is not None and sh.away @ np.array([0.0, 1.0]) > 0.98      # away from the lamp at -y
    across = np.abs(normals @ sh.away) >= 0.7
    assert np.mean(sh.side[across] != 0) > 0.95
    err_plain, err = fit.width - widths, out.width - widths
    assert np.mean(err_plain[across]) > 0.03                         # the shadow read as bead
    assert np.abs(np.median(err[across])) < 0.010 and np.abs(np.median(err[~across])) < 0.010
    # shadow-free stations, and a one-sided misfit on every station that is no shadow
    for kw in ({"shadow": False}, {"shadow": False, "misfit": 0.05}):
        t, y, fit, normals, widths = _stations(240, np.random.default_rng(4), **kw)
        out, sh = with_shadows(t, y, fit, np.ones_like(y), 0.2, normals)
        assert not sh.any and sh.away is None
        np.testing.assert_array_equal(out.params, fit.params)


def _light_plate_scan(tmp_path, realism):
    """A small spiral-step print (direct drive, 0.5 / 1.0 mm) scanned at 600 dpi on the light
    plate with ``realism``, seed 3 (the renderer's flatbed lamp at +-y): (manifest, render,
    PNG path)."""
    import cv2

    from calib.commands.simulate import simulate_scan
    from fit.truth import load_truth
    from patterns import spiral_step
    from patterns.profile import data_dir

    _, man = spiral_step.generate("direct_drive", widths_mm=(0.5, 1.0), speeds_mm_s=(20.0,), n_steps=4)[:2]
    spec, values, _ = load_truth(data_dir() / "truths" / "direct_drive.toml", man.printer)
    r, _ = simulate_scan(man, spec, values, "flatbed", profile=man.printer, dpi=600.0, seed=3, plate="light",
                         realism=realism, clutter=False)
    path = tmp_path / "scan.png"
    cv2.imwrite(str(path), r.image)
    return man, r, path


def test_a_flatbeds_lamp_shadows_are_measured_out_of_a_scan(tmp_path):
    """A 600 dpi flatbed scan of dark beads on a light plate, the scanner's lamp at 45 deg
    (measure/phenomena.py shadows): without the shelf the beads across the lamp read up to
    +70 um; `calib measure`'s pipeline finds the lamp (its side), fits the shelves, applies
    the width reference and takes each station's heading level off: the widths within a
    few um, and the summary says where the shadows fell."""
    import measure.widths as mw
    from measure.pipeline import measure_scan

    man, r, path = _light_plate_scan(tmp_path, "shadows")
    res = measure_scan(path, man)
    tb, tr = res.table, r.table
    ok = tb.valid & (tr.width_mm > 0)
    err = tb.width_mm[ok] - tr.width_mm[ok]
    sh = res.summary["shadows"]
    assert sh["stations"] > 0.3 * ok.sum() and not sh["unresolved"] and 0.35 < sh["depth"] < 0.6
    away = np.deg2rad(sh["away_deg"])                  # the renderer's flatbed lamp is at +-y
    assert abs(np.sin(away)) > 0.99
    assert res.summary["apparent_width"]["applied"]
    assert abs(np.mean(err)) < 0.004 and np.sqrt(np.mean(err ** 2)) < 0.006
    # the same scan with the shelf switched off: the widths across the lamp read wide
    orig = mw.with_shadows
    try:
        mw.with_shadows = lambda t, y, fit, wts, h, nrm, fixed_s=True, model=None: (fit, None)
        plain = measure_scan(path, man).table
    finally:
        mw.with_shadows = orig
    ok2 = plain.valid & (tr.width_mm > 0)
    assert np.sqrt(np.mean((plain.width_mm[ok2] - tr.width_mm[ok2]) ** 2)) > 0.02


def test_a_shadow_blurred_over_is_said_and_the_headings_levelled(tmp_path):
    """Dark beads on a light grained plate in glare, defocused, with translucent flanks and
    the lamp's shadow, measured on the colour axis, which keeps little of a grey shadow: no
    shelf resolves. `calib measure` says so, leaves the width reference unapplied, and
    takes what each heading adds off the widths, so what is left is an offset the fit's
    scan_bias takes (the errors' sd about their mean 37 um before: the streak step put the
    shadow on the far flank as glare)."""
    from measure.pipeline import measure_scan

    man, r, path = _light_plate_scan(tmp_path, "profile,translucent,glare,grain,light,defocus,shadows")
    res = measure_scan(path, man)
    cal = res.summary["apparent_width"]
    assert res.summary["shadows"]["unresolved"] and not cal["applied"]
    assert cal["heading_levels_range_mm"] is not None
    assert any("shadow" in w for w in res.summary["warnings"])
    ok = res.table.valid & (r.table.width_mm > 0)
    err = res.table.width_mm[ok] - r.table.width_mm[ok]
    assert ok.mean() > 0.9 and np.std(err) < 0.010


def test_a_large_scan_without_shadows_stops_at_a_quarter_of_the_screen(monkeypatch):
    """Screened on one station in eight, a scan looks at a quarter of those first
    (SHADOW_PRESCREEN_SHARE): without a shadow next to none of them takes a shelf and the
    rest of the screen is not fitted (its fits were a third of a 12 MP photo's time); with
    one, the screen and the full test run as before and find the lamp."""
    import measure.shadows as sh_mod
    seen = []
    orig = sh_mod._shelf_test

    def counting(t, y, fit, wts, normals, reach, idx, *a, **k):
        seen.append(len(idx))
        return orig(t, y, fit, wts, normals, reach, idx, *a, **k)
    monkeypatch.setattr(sh_mod, "_shelf_test", counting)
    monkeypatch.setattr(sh_mod, "SHADOW_PRESCREEN_MIN", 20)      # a smaller scan, the same rule
    n = 4 * sh_mod.SHADOW_SCREEN_EVERY * sh_mod.SHADOW_PRESCREEN_MIN + 40
    t, y, fit, normals, widths = _stations(n, np.random.default_rng(6), shadow=False)
    out, sh = with_shadows(t, y, fit, np.ones_like(y), 0.2, normals)
    assert not sh.any and seen == [len(range(0, n, sh_mod.SHADOW_SCREEN_EVERY * 4))]
    seen.clear()
    t, y, fit, normals, widths = _stations(n, np.random.default_rng(7))
    out, sh = with_shadows(t, y, fit, np.ones_like(y), 0.2, normals)
    assert len(seen) >= 3 and seen[1] == len(range(0, n, sh_mod.SHADOW_SCREEN_EVERY))
    assert sh.away is not None and sh.away @ np.array([0.0, 1.0]) > 0.98
