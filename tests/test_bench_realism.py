"""The realism bench's summary over seeds (bench/bench_realism.py spread_rows)."""
import math

from bench.bench_realism import offset_coverage_row, offset_z, spread_rows


def _f(rms_um, bias_um, calibrated=True, by_fit=None, sd_um=None):
    return {"rms": rms_um / 1000, "bias": bias_um / 1000, "calibrated": calibrated,
            "offset_sd": None if sd_um is None else sd_um / 1000,
            "by_fit": None if by_fit is None else {"rms": by_fit[0] / 1000, "bias": by_fit[1] / 1000}}


def test_spread_rows_take_the_fit_offset_where_the_calibration_was_not_applied():
    per_seed = {3: _f(7.3, -6.0), 0: _f(4.1, 0.4), 5: _f(48.1, -47.9, calibrated=False, by_fit=(7.0, 4.5))}
    rows = {r.metric: r for r in spread_rows("flatbed, all, Bowden", "flatbed", per_seed)}
    by = {k.split("seeds 0,3,5: ")[1]: r for k, r in rows.items()}
    med = next(r for k, r in by.items() if k.startswith("width RMS error, median"))
    worst = by["width RMS error, worst seed"]
    # seed 5's apparent 48 um is replaced by its widths after the fit's offset (7.0 um)
    assert math.isclose(med.value, 0.0070) and med.passed
    assert math.isclose(worst.value, 0.0073) and worst.passed
    assert "5: 7.0*" in med.metric
    bias_med = next(r for k, r in by.items() if k.startswith("|width bias|, median"))
    bias_worst = by["|width bias|, worst seed"]
    assert math.isclose(bias_med.value, 0.0045) and bias_med.passed
    assert math.isclose(bias_worst.value, 0.0060) and not bias_worst.passed
    applied = next(r for k, r in by.items() if k.startswith("the width reference's calibration applied"))
    assert math.isclose(applied.value, 2 / 3)


def test_spread_rows_on_a_phone_have_no_bias_rows_and_fail_on_a_lost_seed():
    per_seed = {3: _f(14.9, 11.4), 0: _f(float("nan"), float("nan"), calibrated=False)}
    rows = spread_rows("phone", "phone", per_seed)
    assert not any("|width bias|" in r.metric for r in rows)
    worst = next(r for r in rows if r.metric.endswith("worst seed"))
    assert math.isclose(worst.value, 0.0149) and not worst.passed   # a seed that measured nothing fails
    assert not any("valid test stations" in r.metric for r in rows)  # evaluate() gave no share


def test_spread_rows_give_the_valid_share_of_the_worst_seed():
    per_seed = {3: {**_f(16.9, 0.0, calibrated=False), "valid": 0.966},
                0: {**_f(23.8, 0.0, calibrated=False), "valid": 0.794},
                1: {**_f(18.2, 0.0, calibrated=False), "valid": 0.830}}
    row = next(r for r in spread_rows("phone", "phone", per_seed) if "valid test stations" in r.metric)
    assert math.isclose(row.value, 0.794) and not row.passed
    assert "(0: 79 %, 1: 83 %, 3: 97 %)" in row.metric
    for f in per_seed.values():
        f["valid"] = 0.95
    row = next(r for r in spread_rows("phone", "phone", per_seed) if "valid test stations" in r.metric)
    assert row.passed


def test_offset_coverage_counts_applied_offsets_by_their_own_sd():
    """bench_realism, 2026-11-29: the light PNG seed 1 applied -51 +- 4 um where the test
    tracks needed -41: its calibrated widths' bias +10 um is 2.5 of its sd."""
    assert math.isclose(offset_z(_f(13.4, 10.0, sd_um=4.0)), 2.5, rel_tol=1e-9)
    assert math.isnan(offset_z(_f(48.0, -47.9, calibrated=False, sd_um=4.0)))     # not applied: no miss
    z = [offset_z(_f(5, b, sd_um=3.0)) for b in (1.0, -2.0, 7.0, 9.0)] + [float("nan")]
    row = offset_coverage_row(z)
    assert math.isclose(row.value, 0.5) and not row.passed              # 7/3 and 9/3 sd outside
    assert "4 applied; worst +3.0 sd" in row.metric
    assert offset_coverage_row([0.5, -1.0, 1.5]).passed
    rows = spread_rows("flatbed, all", "flatbed", {3: _f(5, 10.0, sd_um=4.0), 0: _f(5, 1.0, calibrated=False)})
    assert any("(its miss / its sd: 3: +2.5)" in r.metric for r in rows)
