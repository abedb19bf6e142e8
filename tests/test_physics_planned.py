"""The physics on a planned G-code pattern (patterns.builder + planner timeline)."""
from __future__ import annotations

import numpy as np
import pytest

from fit.context import SimContext
from fit.model import build_model
from fit.virtual import print_virtual

builder = pytest.importorskip("patterns.builder")


@pytest.fixture(scope="module")
def start_stop_manifest():
    _, man = builder.PATTERNS["start-stop"]("direct_drive")
    return man


def test_planned_pattern_conserves_volume_and_holds_commanded_width(start_stop_manifest):
    man = start_stop_manifest
    vp = print_virtual(man, build_model("pa"), {"pa.tau_s": 0.02})
    assert vp.extruded_mm3 == pytest.approx(vp.commanded_mm3 - vp.stored_mm3, rel=1e-10)
    assert vp.deposited_mm3 + vp.dribble_mm3 == pytest.approx(vp.extruded_mm3, rel=1e-10)
    ctx = SimContext.build(man)
    w, nom = vp.table.width_mm, ctx.s_width_nominal_mm
    steady = nom > 0.1
    # A fast direct drive follows the command: most stations sit at their commanded width.
    close = np.abs(w[steady] - nom[steady]) < 0.01
    assert close.mean() > 0.5
    # A slow Bowden (tau = 0.8 s) on the same print does not.
    vb = print_virtual(man, build_model("pa"), {"pa.tau_s": 0.8}, ctx=ctx)
    close_b = np.abs(vb.table.width_mm[steady] - nom[steady]) < 0.01
    assert close_b.mean() < close.mean() - 0.2
