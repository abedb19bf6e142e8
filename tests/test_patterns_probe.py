"""The discovery probe as G-code (patterns/probe.py): its stops, speeds and widths are where
its parameters say once the firmware's planner has run it, and `diagnose` names a hidden
effect on it, the library's own and the foreign printer's (bench/foreign_printer.py)."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from calib.errors import UserError
from fit.compare import observe
from fit.diagnose import diagnose
from fit.effects import REGISTRY
from fit.geometry import bead_area_mm2
from fit.model import build_model
from patterns.probe import generate
from patterns.profile import load_profile


@functools.lru_cache(maxsize=None)
def probe(printer="adventurer3", **kw):
    return generate(printer, **kw)[1]


@pytest.mark.parametrize("printer", ["adventurer3", "direct_drive"])
def test_each_line_stops_for_its_dwell_where_planned_and_stays_within_the_hot_ends_flow(printer):
    man = probe(printer)
    prof = load_profile(printer)
    tl = man.timeline
    lines = man.test_tracks()
    assert len(lines) == 8
    dwells, retracts, places, widths, flows = [], [], [], [], []
    for k, t in enumerate(lines):
        p = t.params
        on = tl.track == t.id
        s, ts, e = tl.s_mm[on], tl.t_s[on], tl.e_mm[on]
        rest = np.abs(s - p["stop_s_mm"]) < 1e-6
        # the head stands at the stop for the dwell, plus the retraction and its undoing
        extra = 2 * p["stop_retract_mm"] / prof.retract_speed_mm_s
        assert p["dwell_s"] + extra - 0.01 <= np.ptp(ts[rest]) <= p["dwell_s"] + extra + 0.2
        assert np.ptp(e[rest]) == pytest.approx(p["stop_retract_mm"], abs=1e-6)
        # alternating direction; the slow part first, then the line's fast speed
        dx = t.points_mm[-1, 0] - t.points_mm[0, 0]
        assert np.sign(dx) == (1 if k % 2 == 0 else -1)
        fast = (s > p["slow_end_s_mm"] + 3) & (s < p["stop_s_mm"] - 3)
        assert np.max(tl.v_mm_s[on][fast]) == pytest.approx(p["fast_mm_s"], rel=1e-3)
        assert p["fast_mm_s"] <= prof.max_velocity_mm_s + 1e-9
        q = float(bead_area_mm2(p["width_mm"], 0.2)) * p["fast_mm_s"]
        assert q <= 10.0 + 1e-6
        dwells.append(p["dwell_s"])
        retracts.append(p["stop_retract_mm"] > 0)
        places.append(p["stop_s_mm"])
        widths.append(p["width_mm"])
        flows.append(round(q, 2))
    # the stop covariates part: three dwells, two places, and stops with and without a
    # retraction, each at two dwells at least
    assert sorted(set(dwells)) == [1.5, 3.0, 6.0] and len(set(places)) == 2
    for r in (True, False):
        assert len({d for d, rr in zip(dwells, retracts) if rr == r}) >= 2
    assert len(set(widths)) == 4 and len(set(flows)) >= 5


def test_bad_probe_parameters_are_one_line_errors():
    with pytest.raises(UserError, match="--lines"):
        generate("adventurer3", n_lines=3)
    with pytest.raises(UserError, match="--stops-at"):
        generate("adventurer3", stops_at=(0.2,))
    with pytest.raises(UserError, match="> 0"):
        generate("adventurer3", stops_s=(float("nan"),))


@pytest.mark.parametrize("hidden", ["thermal", "backlash"])
def test_diagnose_names_a_hidden_library_effect_on_the_printed_probe(hidden):
    """fit/hidden.py's cases on the G-code probe planned by the firmware model (white noise,
    10 um): the hidden effect first, decisively, and the misfit down to the noise."""
    from fit.hidden import make_case
    c = make_case(hidden, seed=0, manifest=probe(), ds_mm=0.5)
    d = diagnose(observe(c.manifest, c.table), "pa", lambda s: build_model(s, c.manifest.printer),
                 list(REGISTRY), [], n_null=50)
    assert d.base.chi2_nu > 3.0
    assert d.candidates[0].effect == hidden and d.candidates[0].delta_bic > 100
    assert d.candidates[0].chi2_nu_after < 1.2


def test_diagnose_names_the_foreign_printers_play_on_the_printed_probe():
    """Outside the inverse crime: the foreign printer (bench/foreign_printer.py: its own
    integrator and a play with an elastic zone, a form the library does not have) prints
    the direct drive's probe as planned from its G-code; its misfit is named `backlash`
    first, and the verdict says the library's form explains only part of it."""
    from bench.foreign_printer import make_foreign_case
    c = make_foreign_case("backlash", seed=0, manifest=probe("direct_drive"))
    d = diagnose(observe(c.manifest, c.table), "pa", lambda s: build_model(s, c.manifest.printer),
                 list(REGISTRY), [], n_null=50, seed=0)
    assert d.candidates[0].effect == "backlash" and d.candidates[0].delta_bic > 100
    assert d.candidates[0].chi2_nu_after < d.base.chi2_nu / 5
    assert "explains only part" in d.verdict
