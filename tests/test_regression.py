"""Tests of heliocal.pipeline.report.regression: the accuracy comparison against a baseline.

The metrics dictionaries are written out by hand (one heliostat, two models); the committed
sample baseline (tests/baseline/metrics_sample.json) must pass against itself.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from heliocal.pipeline.report.regression import Tolerances, compare_metrics, main

BASELINE = Path(__file__).resolve().parent / "baseline" / "metrics_sample.json"


def _stats(n, mean, median, p95):
    return {"n": n, "n_finite": n, "mean_error_mrad": mean, "median_error_mrad": median,
            "p95_error_mrad": p95, "mean_beam_error_mrad": 2 * mean, "mean_spot_offset_m": 0.1}


BASE = {
    "metrics_schema_version": 1, "heliocal_version": "0.1.0", "git_revision": "abc",
    "inputs": {"measurements.parquet": "0" * 64},
    "data": {"n_heliostats": 1, "n_measurements": 60, "n_rejected": 2,
             "rejected_by_reason": {"missing_value": 2}},
    "heliostats": {"H1": {
        "n_measurements": 60, "split_counts": {"train": 30, "validation": 10, "test": 20},
        "selection": {"coarse_preset": "static-20", "model": "static-20"},
        "models": {
            "static-6": {"source": "coarse_predictions", "selected": False, "splits": {
                "train": _stats(30, 0.9, 0.8, 1.5), "validation": _stats(10, 1.1, 1.0, 2.0),
                "test": _stats(20, 1.3, 1.2, 2.5)}},
            "static-20": {"source": "coarse_predictions", "selected": True, "splits": {
                "train": _stats(30, 0.5, 0.4, 1.0), "validation": _stats(10, 0.8, 0.7, 1.6),
                "test": _stats(20, 1.0, 0.9, 2.0)}},
        }}},
}


def _with(path: str, value) -> dict:
    """A copy of BASE with the value at a slash-separated path replaced."""
    out = copy.deepcopy(BASE)
    *keys, last = path.split("/")
    target = out
    for k in keys:
        target = target[k]
    target[last] = value
    return out


def test_identical_metrics_pass():
    assert compare_metrics(copy.deepcopy(BASE), BASE, None) == []


def test_versions_revisions_and_hashes_are_not_compared():
    cur = _with("git_revision", "def-dirty")
    cur["heliocal_version"] = "9.9"
    cur["inputs"] = {"measurements.parquet": "f" * 64}
    assert compare_metrics(cur, BASE, None) == []


def test_mean_test_error_growth_beyond_tolerance_is_reported():
    cur = _with("heliostats/H1/models/static-6/splits/test/mean_error_mrad", 1.43)
    # allowed growth max(5 % of 1.3, 0.05) = 0.065 mrad; 0.13 is too much
    assert compare_metrics(cur, BASE, None) == [
        "H1 / static-6 / test: mean_error_mrad 1.3000 -> 1.4300 (+0.1300 mrad, +10.0 %; "
        "allowed +0.0650)"]


def test_growth_within_tolerance_and_improvements_pass():
    cur = _with("heliostats/H1/models/static-20/splits/test/mean_error_mrad", 1.049)  # < +0.05
    cur["heliostats"]["H1"]["models"]["static-6"]["splits"]["test"]["mean_error_mrad"] = 0.2
    cur["heliostats"]["H1"]["models"]["static-20"]["splits"]["test"]["p95_error_mrad"] = 2.19
    assert compare_metrics(cur, BASE, None) == []


def test_quantile_tolerance_widens_when_few_rows_lie_beyond_it():
    # p95 of 20 test rows: k = 20 * 0.05 = 1 row beyond it, so the base tolerance
    # max(10 % of 2.0, 0.1) = 0.2 mrad is widened by sqrt(5 / 1): 0.4472 mrad
    tol = Tolerances()
    assert tol.allowed("p95_error_mrad", 2.0, 20) == pytest.approx(0.2 * 5 ** 0.5)
    # from 100 rows on (k = 5) the base tolerance holds; the median reaches it at 10 rows
    assert tol.allowed("p95_error_mrad", 2.0, 100) == pytest.approx(0.2)
    assert tol.allowed("p95_error_mrad", 2.0, 400) == pytest.approx(0.2)
    assert tol.allowed("median_error_mrad", 2.0, 10) == pytest.approx(0.2)
    assert tol.allowed("median_error_mrad", 2.0, 4) == pytest.approx(0.2 * (5 / 2) ** 0.5)
    # the mean's tolerance does not depend on n
    assert tol.allowed("mean_error_mrad", 2.0, 4) == pytest.approx(0.1)
    within = _with("heliostats/H1/models/static-20/splits/test/p95_error_mrad", 2.44)
    assert compare_metrics(within, BASE, None) == []
    beyond = _with("heliostats/H1/models/static-20/splits/test/p95_error_mrad", 2.46)
    assert compare_metrics(beyond, BASE, None) == [
        "H1 / static-20 / test: p95_error_mrad 2.0000 -> 2.4600 (+0.4600 mrad, +23.0 %; "
        "allowed +0.4472)",
        "H1 / selected (static-20) / test: p95_error_mrad 2.0000 -> 2.4600 (+0.4600 mrad, "
        "+23.0 %; allowed +0.4472)"]


def test_training_error_is_not_checked():
    cur = _with("heliostats/H1/models/static-20/splits/train/mean_error_mrad", 5.0)
    assert compare_metrics(cur, BASE, None) == []


def test_selected_model_is_compared_by_accuracy_not_name():
    cur = _with("heliostats/H1/selection/model", "static-6")
    diffs = compare_metrics(cur, BASE, None)
    # static-6 is worse on validation (1.1 vs 0.8) and test (1.3 vs 1.0)
    assert ("H1 / selected (static-20 -> static-6) / test: mean_error_mrad 1.0000 -> 1.3000 "
            "(+0.3000 mrad, +30.0 %; allowed +0.0500)") in diffs
    # mean, median, p95 on validation and test, but the validation p95 (10 rows: half a row
    # beyond it, tolerance max(10 % of 1.6, 0.1) * sqrt(5 / 0.5) = 0.506 mrad) grew by 0.4 only
    assert len(diffs) == 5
    # a different winner with the same accuracy is fine
    cur["heliostats"]["H1"]["models"]["static-6"] = copy.deepcopy(
        BASE["heliostats"]["H1"]["models"]["static-20"])
    assert compare_metrics(cur, BASE, None) == []


def test_counts_must_match_exactly():
    cur = _with("heliostats/H1/split_counts", {"train": 31, "validation": 10, "test": 19})
    cur["heliostats"]["H1"]["models"]["static-6"]["splits"]["test"]["n"] = 19
    cur["data"]["rejected_by_reason"] = {"missing_value": 1, "sun_below_horizon": 1}
    assert compare_metrics(cur, BASE, None) == [
        "data: rejected_by_reason: {missing_value: 2} -> {missing_value: 1, sun_below_horizon: 1} "
        "(must match exactly)",
        "H1: split_counts: {test: 20, train: 30, validation: 10} -> "
        "{test: 19, train: 31, validation: 10} (must match exactly)",
        "H1 / static-6 / test: n: 20 -> 19 (must match exactly)",
    ]


def test_missing_heliostat_model_and_statistic():
    cur = copy.deepcopy(BASE)
    del cur["heliostats"]["H1"]["models"]["static-6"]
    cur["heliostats"]["H1"]["models"]["static-20"]["splits"]["test"]["p95_error_mrad"] = None
    assert compare_metrics(cur, BASE, None) == [  # models in sorted order
        "H1 / static-20 / test: p95_error_mrad 2.0000 -> missing",
        "H1 / static-6: model missing",
        "H1 / selected (static-20) / test: p95_error_mrad 2.0000 -> missing",
    ]
    cur = copy.deepcopy(BASE)
    cur["heliostats"] = {"H2": cur["heliostats"].pop("H1")}
    assert compare_metrics(cur, BASE, None) == [
        "H2: heliostat not in the baseline (new heliostat: regenerate the baseline)",
        "H1: heliostat missing (baseline has 60 measurements)"]


def test_new_models_in_the_current_run_are_fine():
    cur = copy.deepcopy(BASE)
    cur["heliostats"]["H1"]["models"]["hybrid"] = copy.deepcopy(
        cur["heliostats"]["H1"]["models"]["static-6"])
    assert compare_metrics(cur, BASE, None) == []


def test_tolerances_can_be_given():
    cur = _with("heliostats/H1/models/static-6/splits/test/mean_error_mrad", 1.43)
    assert compare_metrics(cur, BASE, Tolerances(mean_rel=0.2)) == []
    assert compare_metrics(cur, BASE, {"mean_abs_mrad": 0.2}) == []
    assert compare_metrics(cur, BASE, {"splits": ("validation",)}) == []


def test_command_line_exit_codes(tmp_path, capsys):
    base, worse = tmp_path / "base.json", tmp_path / "worse.json"
    base.write_text(json.dumps(BASE))
    worse.write_text(json.dumps(_with("heliostats/H1/models/static-6/splits/test/n", 21)))
    assert main([str(base), str(base)]) == 0
    assert "within tolerance" in capsys.readouterr().out
    assert main([str(worse), str(base)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"accuracy regression: {worse} against baseline {base} (1 difference):")
    assert "  - H1 / static-6 / test: n: 20 -> 21 (must match exactly)" in err
    assert main([str(tmp_path / "nope.json"), str(base)]) == 2
    assert "Error: " in capsys.readouterr().err


def test_committed_baseline_passes_against_itself():
    baseline = json.loads(BASELINE.read_text())
    assert compare_metrics(copy.deepcopy(baseline), baseline, None) == []
    # and it catches a regression of the sample's selected model
    worse = copy.deepcopy(baseline)
    sel = worse["heliostats"]["BE36"]["selection"]["model"]
    worse["heliostats"]["BE36"]["models"][sel]["splits"]["test"]["mean_error_mrad"] *= 1.5
    diffs = compare_metrics(worse, baseline, None)
    assert len(diffs) == 2 and all(d.startswith("BE36 / ") for d in diffs)
