"""The structural golden-file comparison (heliocal.pipeline.report.golden): rounding noise passes, a real
change of one number, key, column, dtype, row or string fails.

The golden copy is the committed ``sample_data/synthetic``; the perturbed copies are made here by
editing one value, so each expected outcome follows from the edit, not from the code under test.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from heliocal.pipeline.report.golden import close, compare_csv, compare_json, compare_trees

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic"


@pytest.fixture()
def copy(tmp_path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(SAMPLE, out)
    return out


def _edit_truth(folder: Path, edit) -> None:
    path = folder / "ground_truth.json"
    truth = json.loads(path.read_text())
    edit(truth)
    path.write_text(json.dumps(truth, indent=2))


def _first_heliostat(truth: dict) -> dict:
    return next(iter(truth["heliostats"].values()))


def test_identical_copy_has_no_difference(copy):
    assert compare_trees(copy, SAMPLE) == []


def test_last_digit_rounding_passes(copy):
    # the failure of issue 15: 5.931404151891251 vs 5.93140415189125 (2e-16 relative)
    def edit(truth):
        h = _first_heliostat(truth)
        h["error_nominal_mrad"] = h["error_nominal_mrad"] * (1 + 2e-16)
        h["noise_floor_mrad"] = h["noise_floor_mrad"] * (1 - 3e-12)
    _edit_truth(copy, edit)
    assert (copy / "ground_truth.json").read_bytes() != (SAMPLE / "ground_truth.json").read_bytes()
    assert compare_trees(copy, SAMPLE) == []


def test_one_number_perturbed_by_1e6_relative_fails(copy):
    def edit(truth):
        h = _first_heliostat(truth)
        h["error_nominal_mrad"] = h["error_nominal_mrad"] * (1 + 1e-6)
    _edit_truth(copy, edit)
    diff = compare_trees(copy, SAMPLE)
    assert len(diff) == 1 and "error_nominal_mrad" in diff[0] and "tolerance rel 1e-09" in diff[0]


def test_csv_number_perturbed_by_1e6_relative_fails(copy):
    path = copy / "calibration_log.csv"
    table = pd.read_csv(path)
    column = next(c for c in table.columns if pd.api.types.is_float_dtype(table[c]) and table[c].abs().min() > 0)
    table.loc[7, column] = table.loc[7, column] * (1 + 1e-6)
    table.to_csv(path, index=False)
    diff = compare_trees(copy, SAMPLE)
    assert diff == [f"calibration_log.csv[{column}] row 7: " + diff[0].split(": ", 1)[1]]
    assert "tolerance rel 1e-09" in diff[0]


def test_structure_changes_fail():
    golden = {"a": 1, "b": [1.0, "x"], "c": {"d": None}}
    assert compare_json({"a": 1, "b": [1.0, "x"], "c": {"d": None}}, golden) == []
    assert compare_json({"b": [1.0, "x"], "a": 1, "c": {"d": None}}, golden)  # key order
    assert compare_json({"a": 1.0, "b": [1.0, "x"], "c": {"d": None}}, golden)  # int -> float
    assert compare_json({"a": 1, "b": [1.0], "c": {"d": None}}, golden)  # array length
    assert compare_json({"a": 1, "b": [1.0, "y"], "c": {"d": None}}, golden)  # a string
    assert compare_json({"a": 2, "b": [1.0, "x"], "c": {"d": None}}, golden)  # ints are exact
    assert compare_json({"a": 1, "b": [1.0, "x"], "c": {"d": 0.0}}, golden)  # null -> number


def test_csv_structure_changes_fail():
    golden = b"id,x,n\nA,1.5,1\nB,2.5,2\n"
    assert compare_csv(b"id,x,n\nA,1.5000000000000002,1\nB,2.5,2\n", golden) == []
    assert compare_csv(b"id,n,x\nA,1,1.5\nB,2,2.5\n", golden)  # column order
    assert compare_csv(b"id,x,n\nB,2.5,2\nA,1.5,1\n", golden)  # row order
    assert compare_csv(b"id,x,n\nA,1.5,1.0\nB,2.5,2.0\n", golden)  # dtype int -> float
    assert compare_csv(b"id,x,n\nA,1.5,1\n", golden)  # a row lost
    assert compare_csv(b"id,x,n\nA,1.5,1\nC,2.5,2\n", golden)  # a string


def test_close_tolerance_is_relative_with_a_tiny_absolute_floor():
    assert close(1000.0, 1000.0 * (1 + 9e-10)) and not close(1000.0, 1000.0 * (1 + 2e-9))
    assert close(0.0, 1e-13) and not close(0.0, 1e-11)
    assert close(float("nan"), float("nan")) and not close(float("nan"), 0.0)
