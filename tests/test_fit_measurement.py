"""The fit reads what `calib measure` said of its widths (fit/measurement.py): a calibrated
scan's edge-offset sd becomes the scan_bias prior; apparent widths widen it, and without
scan_bias in the model they are a caution in the verdict and a line on stderr."""
import json
import shutil
from pathlib import Path

import pytest

from calib.commands.fit import run_fit
from fit import measurement
from fit.trust import assess

EX = Path("data/examples/gear_slip")


def scan_with_summary(tmp_path, calibration):
    shutil.copy(EX / "widths.csv", tmp_path / "widths.csv")
    for f in ("probe.manifest.json", "probe.timeline.npz"):
        shutil.copy(EX / f, tmp_path / f)
    if calibration is not None:
        (tmp_path / "widths.summary.json").write_text(json.dumps({"apparent_width": calibration}))
    return [(str(tmp_path / "widths.csv"), str(tmp_path / "probe.manifest.json"))]


CAL = {"applied": True, "offset_mm": -0.031, "offset_sd_mm": 0.0024, "note": "apparent-width calibration: ..."}
UNCAL = {"applied": False, "offset_mm": None, "offset_sd_mm": None,
         "note": "apparent-width calibration not applied: the width reference had not settled; widths are apparent"}


def _prior(problem, name):
    return problem.priors[problem.param_names.index(name)]


@pytest.mark.parametrize("cal,sd", [(CAL, 0.0024), (UNCAL, measurement.UNCALIBRATED_SD_MM), (None, 0.005)])
def test_scan_bias_prior_follows_the_calibration(tmp_path, cal, sd, capsys):
    _, problem = run_fit(scan_with_summary(tmp_path, cal), "pa+scan_bias", map_only=True, progress=False)
    p = _prior(problem, "scan_bias.b0_mm")
    assert p.kind == "normal" and p.sd == pytest.approx(sd)       # None: the effect's own normal(0, 5 um)
    err = capsys.readouterr().err
    assert ("apparent widths" in err) == (cal is UNCAL) and "add scan_bias" not in err


def test_apparent_widths_without_scan_bias_are_said_and_a_caution(tmp_path, capsys):
    pairs = scan_with_summary(tmp_path, UNCAL)
    run_fit(pairs, "pa", map_only=True, progress=False)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "widths are apparent widths" in err[0] and "add scan_bias" in err[0]
    notes = measurement.notes([{"scan": "widths", "calibration": UNCAL}], has_scan_bias=False)
    doc = {"converged": True, "information": {"chi2_nu": 1.0, "n_obs": 100}, "params": {}, "priors": {},
           "diagnostics": {"measurement": {"notes": notes}}}
    v = assess(doc)
    assert v.trustworthy and any("apparent widths" in c for c in v.cautions)
