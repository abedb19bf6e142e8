"""The batched edge-pair fit recovers known parameters with an honest covariance."""
import numpy as np
import pytest

from measure.edges import edge_pair, fit_profiles, initial_guess


def _profiles(n, polarity, noise, rng, s=0.03):
    w = rng.uniform(0.25, 1.6, n)
    half = w / 2 + np.maximum(0.5, w)
    t = np.linspace(-1, 1, 100)[None] * half[:, None]
    p = np.column_stack([np.full(n, 0.5), np.full(n, 0.03), np.full(n, 0.35 * polarity),
                         rng.normal(0, 0.03, n), w, np.full(n, s)])
    return t, edge_pair(t, p) + rng.normal(0, noise, t.shape), p


@pytest.mark.parametrize("polarity", [1.0, -1.0])
def test_noiseless_profiles_are_fitted_exactly(polarity):
    t, y, p = _profiles(200, polarity, 0.0, np.random.default_rng(1))
    fit = fit_profiles(t, y, initial_guess(t, y, polarity, 0.05))
    assert fit.ok.all()
    np.testing.assert_allclose(fit.width, p[:, 4], atol=1e-6)
    np.testing.assert_allclose(fit.centre, p[:, 3], atol=1e-6)
    np.testing.assert_allclose(fit.params[:, 5], p[:, 5], atol=1e-5)


def test_width_sd_covers_68_percent_of_true_errors():
    rng = np.random.default_rng(2)
    t, y, p = _profiles(3000, 1.0, 0.02, rng)
    fit = fit_profiles(t, y, initial_guess(t, y, 1.0, 0.05))
    z = (fit.width - p[:, 4]) / fit.width_sd
    assert np.mean(np.abs(z) < 1) == pytest.approx(0.683, abs=0.03)
    assert abs(np.mean(fit.width - p[:, 4])) < 3 * np.std(fit.width - p[:, 4]) / np.sqrt(3000)


def test_fixed_blur_is_kept_and_reduces_narrow_bead_scatter():
    rng = np.random.default_rng(3)
    t, y, p = _profiles(1500, 1.0, 0.03, rng, s=0.06)
    p0 = initial_guess(t, y, 1.0, 0.06)
    free = fit_profiles(t, y, p0)
    fixed = fit_profiles(t, y, p0, fixed_s=True)
    assert np.all(fixed.params[:, 5] == 0.06)
    narrow = p[:, 4] < 0.4
    assert np.std((fixed.width - p[:, 4])[narrow]) < 0.8 * np.std((free.width - p[:, 4])[narrow])


@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_a_glare_streak_on_one_flank_is_fitted_and_the_width_recovered(side):
    """Box + a blur-wide specular line 0.06 mm inside one edge (bead height 0.2 mm): the
    plain edge pair reads the bead wide; the streak model, with the blur held, does not,
    and on the wrong side it explains less."""
    from measure.edges import STREAK_PARAMS, fit_streak

    rng = np.random.default_rng(3)
    n, s = 200, 0.04
    w = rng.uniform(0.35, 1.0, n)
    t = np.linspace(-1, 1, 120)[None] * (w / 2 + 0.5)[:, None]
    p = np.column_stack([np.full(n, 0.1), np.zeros(n), np.full(n, 0.6), rng.normal(0, 0.02, n), w, np.full(n, s)])
    cg = p[:, 3] + side * (w / 2 - 0.06)
    y = edge_pair(t, p) + 0.2 * np.exp(-0.5 * ((t - cg[:, None]) / s) ** 2) + rng.normal(0, 0.005, t.shape)
    p0 = initial_guess(t, y, 1.0, s)
    plain = fit_profiles(t, y, p0, fixed_s=True)
    assert np.mean(plain.width - w) > 0.005
    right = fit_streak(t, y, plain.params, side, height_mm=0.2)
    wrong = fit_streak(t, y, plain.params, -side, height_mm=0.2)
    assert right.params.shape[1] == len(STREAK_PARAMS) and right.ok.all()
    assert abs(np.mean(right.width - w)) < 0.001 and np.std(right.width - w) < 0.003
    np.testing.assert_allclose(right.params[:, 6], 0.2, rtol=0.1)     # G
    np.testing.assert_allclose(right.params[:, 7], 0.06, atol=0.005)  # depth inside the edge (mm)
    assert np.all(right.rms < 0.7 * wrong.rms)
    z = (right.width - w) / right.width_sd
    assert 0.55 < np.mean(np.abs(z) < 1) < 0.8


@pytest.mark.parametrize("fixed_s, side", [(False, 0.0), (True, 0.0), (True, 1.0), (False, -1.0)])
def test_compiled_normal_equations_match_finite_differences(fixed_s, side):
    """The fused kernel's cost, J^T W J and J^T W r against a central-difference Jacobian of
    the model written out here from the module docstring (edge pair + streak
    G exp(-(t - c_g)^2 / 2 s^2), c_g = c + side (w/2 - d)), with a 0/1 mask."""
    from measure.edges import _free_columns, _normal_equations

    rng = np.random.default_rng(4)
    t, y, p = _profiles(6, 1.0, 0.02, rng)
    p = np.column_stack([p, np.full(6, 0.04), np.full(6, 0.08)])   # G, d

    def model(q):
        f = edge_pair(t, q[:, :6])
        if side:
            cg = q[:, 3:4] + side * (q[:, 4:5] / 2 - q[:, 7:8])
            f = f + q[:, 6:7] * np.exp(-0.5 * ((t - cg) / q[:, 5:6]) ** 2)
        return f

    wts = (rng.uniform(size=t.shape) > 0.1).astype(float)
    free = _free_columns(fixed_s, side)
    cols = []
    for k in free:
        h = 1e-6 * max(1.0, abs(p[:, k]).max())
        hi, lo = p.copy(), p.copy()
        hi[:, k] += h
        lo[:, k] -= h
        cols.append((model(hi) - model(lo)) / (2 * h))
    J = np.stack(cols, axis=-1) * wts[..., None]
    r = (y - model(p)) * wts
    cost, JTJ, JTr = _normal_equations(t, y, wts, p if side else p[:, :6].copy(), np.arange(6), fixed_s, side)
    np.testing.assert_allclose(cost, (r * r).sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(JTJ, J.transpose(0, 2, 1) @ J, rtol=1e-5, atol=1e-6 * np.abs(JTJ).max())
    np.testing.assert_allclose(JTr, (J.transpose(0, 2, 1) @ r[..., None])[..., 0], rtol=1e-5,
                               atol=1e-6 * np.abs(JTr).max())


def _shallow_streak(n, s):
    """(t, y, true widths, plain fit) of n profiles with a strong streak 0.02 mm inside the
    +t edge, shallower than the flank allows at bead height 0.2 mm (blur ``s`` mm)."""
    rng = np.random.default_rng(5)
    w = rng.uniform(0.4, 0.9, n)
    t = np.linspace(-1, 1, 150)[None] * (w / 2 + 0.5)[:, None]
    p = np.column_stack([np.full(n, 0.1), np.zeros(n), np.full(n, 0.6), rng.normal(0, 0.02, n), w, np.full(n, s)])
    cg = p[:, 3] + (w / 2 - 0.02)
    y = edge_pair(t, p) + 0.3 * np.exp(-0.5 * ((t - cg[:, None]) / s) ** 2) + rng.normal(0, 0.01, t.shape)
    return t, y, w, fit_profiles(t, y, initial_guess(t, y, 1.0, s), fixed_s=True)


def test_a_parameter_held_at_its_bound_gives_the_bounded_least_squares_optimum():
    """A streak deeper inside its edge than the flank allows (0.02 mm for a bound of 0.04
    at bead height 0.2 mm): the depth rests on its bound and the rest is fitted around it.
    Known answer: scipy's bounded least squares (trust-region reflective) on each profile,
    reached within 12 LM steps (clipping the full step instead crept a micron a step)."""
    from scipy.optimize import least_squares

    from measure.edges import STREAK_FLANK, fit_streak

    n, s, h = 12, 0.05, 0.2
    t, y, w, plain = _shallow_streak(n, s)
    fit = fit_streak(t, y, plain.params, 1.0, height_mm=h, n_iter=12)
    lo_d, hi_d = STREAK_FLANK[0] * h / 2, STREAK_FLANK[1] * h / 2
    np.testing.assert_allclose(fit.params[:, 7], lo_d)
    for i in range(n):
        def resid(q, i=i):
            b0, b1, A, c, wi, G, d = q
            cgi = c + wi / 2 - d
            return (edge_pair(t[i:i + 1], np.array([[b0, b1, A, c, wi, s]]))[0]
                    + G * np.exp(-0.5 * ((t[i] - cgi) / s) ** 2) - y[i])
        q0 = np.r_[plain.params[i, :5], 0.1, 0.5 * (lo_d + hi_d)]
        lb = [-np.inf, -np.inf, -np.inf, t[i, 0], 0.0, 0.0, lo_d]
        ub = [np.inf, np.inf, np.inf, t[i, -1], np.inf, np.inf, hi_d]
        ref = least_squares(resid, q0, bounds=(lb, ub), method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12)
        assert fit.params[i, 4] == pytest.approx(ref.x[4], abs=2e-5)       # width, mm
        assert fit.params[i, 6] == pytest.approx(ref.x[5], rel=1e-3)       # G
        assert fit.rms[i] ** 2 * (t.shape[1] - 7) == pytest.approx(2 * ref.cost, rel=1e-6)


def test_a_depth_held_for_the_scan_is_held_in_the_covariance_too():
    """Known answer: the streak's depth held at one value (bounds that meet) gives the
    textbook covariance of the fit without it, inv(J^T J) RSS / (M - p) with p = 6 (b0, b1,
    A, c, w, G; the blur held too), J by central differences. With the held depth left in
    the linearised covariance the width's sd read a trade the fit never made (phone
    renders: 15x the sd of the stations without a streak). A free depth that ends on its
    bound keeps its trade in the sd."""
    from measure.edges import STREAK_FLANK, fit_streak

    n, s, h, frac = 8, 0.05, 0.2, 0.7
    t, y, w, plain = _shallow_streak(n, s)
    held = fit_streak(t, y, plain.params, 1.0, height_mm=h, flank=(frac, frac))
    d = frac * h / 2
    np.testing.assert_allclose(held.params[:, 7], d)
    assert np.all(held.sd[:, 7] == 0.0)
    for i in range(n):
        def model(q, i=i):
            b0, b1, A, c, wi, G = q
            return (edge_pair(t[i:i + 1], np.array([[b0, b1, A, c, wi, s]]))[0]
                    + G * np.exp(-0.5 * ((t[i] - (c + wi / 2 - d)) / s) ** 2))
        q = held.params[i, [0, 1, 2, 3, 4, 6]]
        J = np.column_stack([(model(q + e) - model(q - e)) / 2e-7 for e in 1e-7 * np.eye(6)])
        rss = np.sum((y[i] - model(q)) ** 2)
        cov = np.linalg.inv(J.T @ J) * rss / (t.shape[1] - 6)
        assert held.width_sd[i] == pytest.approx(np.sqrt(cov[4, 4]), rel=1e-3)
    free = fit_streak(t, y, plain.params, 1.0, height_mm=h)
    on = np.isclose(free.params[:, 7], STREAK_FLANK[0] * h / 2, rtol=1e-9)
    assert on.any() and np.all(free.sd[on, 7] > 0)


def test_under_a_phones_blur_the_streak_sits_at_one_depth_for_the_scan():
    """A phone's blur (0.16 mm) is wider than the flank (0.1 mm): a streak 0.07 mm inside
    the edge trades with it, and each station's free depth ends on a bound and reads its
    bead 16 um RMS off. The scan's one light puts every streak at one depth, found from
    the stations whose depth the data did fix: within 6 um. Beads under 2.5 blurs wide
    (0.25 mm) are not tried: there the blurred streak is a bump of the bead's own shape."""
    from measure.edges import fit_streak
    from measure.streaks import with_glare_streaks

    rng = np.random.default_rng(7)
    n, s = 600, 0.16
    w = np.where(rng.uniform(size=n) < 0.2, 0.25, rng.uniform(0.5, 1.6, n))
    t = np.linspace(-1, 1, 160)[None] * (w / 2 + 0.6)[:, None]
    p = np.column_stack([np.full(n, 0.1), np.zeros(n), np.full(n, 0.6), np.zeros(n), w, np.full(n, s)])
    y = (edge_pair(t, p) + 0.15 * np.exp(-0.5 * ((t - (w / 2 - 0.07)[:, None]) / s) ** 2)
         + rng.normal(0, 0.01, t.shape))
    plain = fit_profiles(t, y, initial_guess(t, y, 1.0, s), fixed_s=True)
    fit, streak = with_glare_streaks(t, y, plain, np.ones_like(y), np.full(n, 0.2), np.tile([1.0, 0.0], (n, 1)))
    wide = w > 0.4
    assert streak[wide].all() and not streak[~wide].any()
    assert np.sqrt(np.mean((fit.width - w)[wide] ** 2)) < 0.006                   # mm
    each = fit_streak(t[wide], y[wide], plain.params[wide], 1.0, height_mm=0.2)
    assert np.sqrt(np.mean((each.width - w[wide]) ** 2)) > 0.012
    np.testing.assert_array_equal(fit.params[~wide], plain.params[~wide])


@pytest.mark.parametrize("share_facing, expect", [(1.0, "all"), (0.7, "none")])
def test_streaks_are_believed_only_when_their_sides_agree_on_one_light(share_facing, expect):
    """400 stations, every profile with a strong streak; ``share_facing`` of them on the
    flank that faces +x, the rest on the other. All one way: one light, every streak fitted
    (the screen is sure of it, and the rest try that side first). 70/30: coherence 0.4, no
    single light, no streak believed; trying the screen's side first had let every station
    agree with it (measure/streaks.py STREAK_SURE_COHERENCE: a light plate read 22 -> 40 um)."""
    from measure.streaks import with_glare_streaks

    rng = np.random.default_rng(7)
    n, s = 400, 0.04
    w = rng.uniform(0.45, 0.9, n)
    t = np.linspace(-1, 1, 120)[None] * (w / 2 + 0.5)[:, None]
    p = np.column_stack([np.full(n, 0.1), np.zeros(n), np.full(n, 0.6), np.zeros(n), w, np.full(n, s)])
    side = np.where(rng.uniform(size=n) < share_facing, 1.0, -1.0)
    rng.shuffle(side)
    cg = side * (w / 2 - 0.06)
    y = edge_pair(t, p) + 0.2 * np.exp(-0.5 * ((t - cg[:, None]) / s) ** 2) + rng.normal(0, 0.005, t.shape)
    plain = fit_profiles(t, y, initial_guess(t, y, 1.0, s), fixed_s=True)
    normals = np.tile([1.0, 0.0], (n, 1))          # side +1 lies towards +x
    fit, streak = with_glare_streaks(t, y, plain, np.ones_like(y), np.full(n, 0.2), normals)
    if expect == "all":
        assert streak.mean() > 0.95
        assert np.sqrt(np.mean((fit.width - w)[streak] ** 2)) < 0.002      # mm
    else:
        assert not streak.any()
        np.testing.assert_array_equal(fit.params, plain.params)


def test_width_per_blur_is_how_the_fitted_width_moves_with_the_blur_it_is_held_at():
    """A fit with the blur held 2 % off: the width it returns moves by width_per_blur x the
    blur's error, large for a bead not much wider than the blur, small for a wide one."""
    from measure.edges import width_per_blur

    s = 0.15
    w = np.array([0.25, 0.3, 0.45, 0.9])
    half = w / 2 + 3 * s + 0.5
    t = np.linspace(-1, 1, 160)[None] * half[:, None]
    p = np.column_stack([np.full(4, 0.2), np.full(4, 0.01), np.full(4, 0.4), np.zeros(4), w, np.full(4, s)])
    y = edge_pair(t, p)
    moved = []
    for ds in (-0.02 * s, 0.02 * s):
        q = p.copy()
        q[:, 5] += ds
        moved.append(fit_profiles(t, y, q, fixed_s=True).width)
    numeric = (moved[1] - moved[0]) / (0.04 * s)
    slope = width_per_blur(t, p)
    np.testing.assert_allclose(slope, numeric, rtol=0.05)
    assert slope[0] < -4.0 and -1.0 < slope[3] < 0.0          # w = 1.7 s against w = 6 s
    # a function of w / s: the same bead and window at twice the scale
    np.testing.assert_allclose(width_per_blur(2 * t, p * [1, 0.5, 1, 2, 2, 2]), slope, rtol=1e-3)


def test_a_contrast_prior_is_the_map_of_the_edge_pair_and_holds_a_narrow_bead():
    """fit_profiles(amp_prior=(A_ref, lam)) minimises SS + lam (A - A_ref)^2: lam 0 is the
    plain fit, a large lam pins A at A_ref; in between, the gradient of that objective
    vanishes at the result (finite differences). A bead 1.5 blurs wide under noise shared
    by neighbouring samples (a photo's profile) scatters in A w's direction; the true
    contrast as a prior holds its width 3x tighter, and a wide bead's width hardly moves."""
    rng = np.random.default_rng(11)
    n, s = 400, 0.17
    w = np.where(np.arange(n) < n // 2, 0.25, 1.0)
    half = w / 2 + 0.6
    t = np.linspace(-1, 1, 80)[None] * half[:, None]
    p = np.column_stack([np.full(n, 0.7), np.zeros(n), np.full(n, -0.35), np.zeros(n), w, np.full(n, s)])
    # noise correlated over ~0.1 mm (grain, JPEG blocks): what a sum of squares overstates
    raw = rng.normal(0, 0.015, (n, 80 + 12))
    noise = np.stack([np.convolve(r, np.ones(12) / np.sqrt(12), "valid")[:80] for r in raw])
    y = edge_pair(t, p) + noise
    p0 = initial_guess(t, y, -1.0, s)
    free = fit_profiles(t, y, p0, fixed_s=True)
    zero = fit_profiles(t, y, p0, fixed_s=True, amp_prior=(np.full(n, -0.35), np.zeros(n)))
    np.testing.assert_allclose(zero.params, free.params, atol=1e-9)
    pinned = fit_profiles(t, y, p0, fixed_s=True, amp_prior=(np.full(n, -0.35), np.full(n, 1e9)))
    np.testing.assert_allclose(pinned.amplitude, -0.35, atol=1e-5)
    lam = 40 * free.rms ** 2 / (0.03 * 0.35) ** 2
    prior = fit_profiles(t, y, free.params, fixed_s=True, amp_prior=(np.full(n, -0.35), lam))
    assert prior.ok.all()
    narrow = w < 0.5
    err_free = np.std((free.width - w)[narrow])
    err_prior = np.std((prior.width - w)[narrow])
    assert err_prior < err_free / 3
    assert np.std((prior.width - free.width)[~narrow]) < 0.2 * np.std((free.width - w)[~narrow])

    # the result is a stationary point of SS + lam (A - A_ref)^2 in the five free parameters
    def objective(q, i):
        pp = prior.params[i:i + 1].copy()
        pp[0, :5] = q
        return float(np.sum((y[i] - edge_pair(t[i:i + 1], pp)[0]) ** 2) + lam[i] * (q[2] + 0.35) ** 2)
    for i in (0, n - 1):
        q0 = prior.params[i, :5]
        h = 1e-6 * np.maximum(np.abs(q0), 1e-3)
        grad = [(objective(q0 + h * e, i) - objective(q0 - h * e, i)) / (2 * h[k]) for k, e in enumerate(np.eye(5))]
        scale = objective(q0, i) / np.maximum(np.abs(q0), 1e-2)
        assert np.all(np.abs(grad) < 1e-3 * scale)
