"""The sweep's selection of one heliostat (stages/selection.py): the forward-in-time check of a
chosen model with date inputs and its fallback to the static choice (issue 33, item 3).

The heliostat and its errors are written out here: ten rows whose split.parquet ``time_split``
labels are four train, three validation and three test rows; the coarse model's time-split
errors are 1 mrad on every row.
"""

import math

import numpy as np
import pandas as pd

from heliocal.pipeline.stages.selection import HeliostatChoice, apply_forward_checks, time_labels

IDS = [f"m{i}" for i in range(10)]
TIME = ["train"] * 4 + ["validation"] * 3 + ["test"] * 3


class _Item:
    """The parts of a SweepInputs the check reads."""

    def __init__(self):
        self.rows = pd.DataFrame({"measurement_id": IDS})
        self.split_rows = pd.DataFrame({"measurement_id": IDS[::-1], "time_split": TIME[::-1]})
        self.selected = {"preset": "static-6"}
        self.coarse = {"static-6": pd.DataFrame({"time_error_mrad": np.ones(10)})}


def _choice(model, time_errors=None, date_inputs=False, fallback=None):
    predictions = pd.DataFrame({"measurement_id": IDS, "error_mrad": np.zeros(10)})
    return HeliostatChoice({"heliostat_id": "H1", "model": model, "forward_check": ""}, None,
                           predictions, date_inputs, fallback, time_errors)


def _result(hybrid_time_val: float):
    """A chosen hybrid whose forward pass gave ``hybrid_time_val`` on the time-validation rows,
    with the coarse model as its static fallback."""
    fallback = _choice("coarse", time_errors=np.full(10, 1.0))
    choice = _choice("hybrid", date_inputs=True, fallback=fallback)
    choice.predictions["time_error_mrad"] = hybrid_time_val
    return {"selection": choice.selection, "selected_state": {"state": "hybrid"},
            "predictions": choice.predictions, "choice": choice}


def test_time_labels_follow_the_rows_order():
    labels = time_labels(_Item().rows, _Item().split_rows)
    assert labels.tolist() == TIME


def test_a_hybrid_no_worse_forward_in_time_is_kept():
    res = _result(0.9)                 # 0.9 against the coarse model's 1.0 on time validation
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid"
    assert res["selection"]["forward_check"] == "passed"
    assert res["selection"]["time_val_error_mrad"] == 0.9
    assert res["selection"]["coarse_time_val_error_mrad"] == 1.0


def test_a_tie_within_the_tolerance_is_not_worse():
    # 1.005 against 1.0: within FORWARD_TOLERANCE (1 %)
    res = _result(1.005)
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid" and res["selection"]["forward_check"] == "passed"


def test_a_hybrid_worse_forward_in_time_falls_back_to_the_static_choice():
    res = _result(1.2)
    apply_forward_checks([res], {"H1": _Item()})
    sel = res["selection"]
    assert sel["model"] == "coarse" and res["selected_state"] is None
    assert sel["forward_check"].startswith("failed (hybrid)")
    assert (sel["time_val_error_mrad"], sel["coarse_time_val_error_mrad"]) == (1.2, 1.0)
    # the fallback's own forward-in-time errors are what the selection reports now
    assert res["predictions"]["time_error_mrad"].tolist() == [1.0] * 10
    assert sel["time_test_error_mrad"] == 1.0 and sel["coarse_time_test_error_mrad"] == 1.0


def test_without_its_time_split_training_a_hybrid_is_kept_and_says_so():
    res = _result(float("nan"))        # a sweep without --time-split
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid"
    assert res["selection"]["forward_check"] == "not checked (no time-split training)"
    assert math.isnan(res["selection"]["time_val_error_mrad"])


def test_a_model_without_date_inputs_is_not_checked():
    res = _result(1.2)
    res["choice"].date_inputs = False   # e.g. the GP's sun structure
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid" and res["selection"]["forward_check"] == ""
