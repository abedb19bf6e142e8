"""Peer methods on virtual-printer data: the OrcaSlicer PA Line ladder ("print a ladder of
PA values and pick the most even line") and the Duet3D spiral-step method (seed 004)."""
from __future__ import annotations

import numpy as np
import pytest

from fit.peers import duet3d_pa, ladder_pa, orca_ladder_values


def test_orca_ladder_defaults():
    """REFERENCE.md: direct drive 0..0.1 step 0.002, Bowden 0..1.0 step 0.02."""
    d, b = orca_ladder_values(False), orca_ladder_values(True)
    assert (len(d), d[0], d[-1]) == (51, 0.0, 0.1) and np.allclose(np.diff(d), 0.002)
    assert (len(b), b[0], b[-1]) == (51, 0.0, 1.0) and np.allclose(np.diff(b), 0.02)


@pytest.mark.parametrize("profile,tau,step", [("direct_drive", 0.043, 0.002),
                                              ("long_bowden", 0.61, 0.02)])
def test_ladder_recovers_tau_within_one_step_noiseless(profile, tau, step):
    """With firmware K = tau the linear-PA printer's width is flat (the command's
    K de/dt cancels the tau dq/dt lag exactly), so the most even line is the one
    nearest tau; tau is put between two ladder values."""
    k, scores = ladder_pa(profile, {"pa.tau_s": tau}, return_scores=True)
    assert abs(k - tau) <= step + 1e-12
    # the score falls towards tau and rises after it (one minimum)
    i = int(np.argmin(scores))
    assert np.all(np.diff(scores[: i + 1]) < 0) and np.all(np.diff(scores[i:]) > 0)


def test_ladder_with_noise_stays_near_tau():
    k = ladder_pa("direct_drive", {"pa.tau_s": 0.043}, noise_sd_mm=0.014, seed=3)
    assert abs(k - 0.043) <= 3 * 0.002


def test_duet3d_on_virtual_spiral_step():
    """Seed 004 on the virtual printer: constant head speed 20 mm/s, width stepped every
    2 s (40 mm), tau 0.3 s -> PA = 1/(C R) recovers tau (noiseless and with 10 um noise).
    The first nozzle diameter after each step is skipped: there the width is the step
    smeared over the nozzle's deposit window, not yet the exponential (fitting it biases
    PA by ~4 % low)."""
    from fit.model import build_model
    from fit.virtual import print_virtual
    from patterns import spiral_step
    from patterns.profile import load_profile

    prof = load_profile("long_bowden")
    v, step_s, tau = 20.0, 2.0, 0.3
    _, man = spiral_step.generate(prof, speeds_mm_s=(v,), n_steps=6, step_s=(step_s,))
    t = print_virtual(man, build_model("pa", prof), {"pa.tau_s": tau}).table
    tid = [tr.id for tr in man.tracks if tr.kind == "test"][0]
    sel = (t.track == tid) & t.valid
    s, w = t.s_mm[sel], t.width_mm[sel]
    skip = prof.nozzle_diameter_mm
    assert duet3d_pa(s, w, v * step_s, v, skip_mm=skip) == pytest.approx(tau, rel=0.01)
    rng = np.random.default_rng(0)
    noisy = duet3d_pa(s, w + 0.01 * rng.standard_normal(len(w)), v * step_s, v, skip_mm=skip)
    assert noisy == pytest.approx(tau, rel=0.15)
