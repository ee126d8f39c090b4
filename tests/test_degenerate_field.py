"""A heliostat whose training data are degenerate stays out of the field's figures (issue 32,
finding 7): before, a heliostat whose 150 training rows were one repeated measurement was
flagged degenerate on its own page, but its ~0 mrad entered the field's pooled mean and median in
metrics.json and the overview's median and 95th percentile.

The inputs are written out here: heliostat A has test errors 1 and 3 mrad, D (degenerate) 0 and
0 mrad, so the field's figures are A's alone: mean 2, median 2 (with D they would be 1 and 0.5).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.report.field import field_summary
from heliocal.pipeline.report.inputs import ReportInputs
from heliocal.pipeline.report.metrics import compute_metrics

WHY = "every training row is the same measurement"


def _inputs() -> ReportInputs:
    rows = [("A", "a1", "test", 1.0), ("A", "a2", "test", 3.0), ("A", "a3", "train", 0.5),
            ("D", "d1", "test", 0.0), ("D", "d2", "test", 0.0), ("D", "d3", "train", 0.0)]
    ids = pd.DataFrame(rows, columns=["heliostat_id", "measurement_id", "split", "error_mrad"])
    stamps = pd.date_range("2023-01-01", periods=len(ids), freq="D", tz="UTC")
    measurements = ids[["heliostat_id", "measurement_id"]].assign(timestamp=stamps)
    split = ids[["heliostat_id", "measurement_id", "split"]].assign(time_split=ids["split"])
    coarse = pd.DataFrame({"heliostat_id": ["A", "D"], "preset": "static-6", "selected": True,
                           "val_error_mrad": np.nan, "test_error_mrad": [2.0, 0.0],
                           "fit_degenerate": ["", WHY]})
    predictions = ids.assign(model="static-6", source="coarse_predictions", selected=True,
                             time_error_mrad=ids["error_mrad"])
    return ReportInputs(workdir=Path("wd"), measurements=measurements, split=split,
                        coarse_params=coarse, predictions=predictions)


def test_metrics_leave_a_degenerate_heliostat_out_of_the_field():
    m = compute_metrics(_inputs())
    field = m["field"]
    assert field["degenerate_heliostats"] == ["D"]
    pooled = field["forward_in_time"]["coarse"]["knn_test"]
    assert (pooled["n"], pooled["mean_error_mrad"], pooled["median_error_mrad"]) == (2, 2.0, 2.0)
    assert field["forward_in_time"]["coarse"]["time_test"]["mean_error_mrad"] == 2.0
    assert field["forward_in_time"]["n_heliostats_time_split"] == 1
    own = m["heliostats"]["D"]["forward_in_time"]["coarse"]["knn_test"]
    assert (own["n"], own["mean_error_mrad"]) == (2, 0.0)  # D keeps its own figures


def _table(degenerate) -> pd.DataFrame:
    t = pd.DataFrame({"heliostat_id": ["A", "B", "D"], "model": "coarse", "preset": "static-6",
                      "test_error_mrad": [1.0, 3.0, 0.0], "alerts": [[], [], ["degenerate"]]})
    return t if degenerate is None else t.assign(degenerate=degenerate)


@pytest.mark.parametrize("degenerate,median,n_error,n_degenerate", [
    ([False, False, True], 2.0, 2, 1),
    ([False, False, False], 1.0, 3, 0),
    (None, 1.0, 3, 0),  # a table without the column (written by a caller that does not know it)
])
def test_the_overview_counts_a_degenerate_heliostat_apart(degenerate, median, n_error,
                                                          n_degenerate):
    s = field_summary(_table(degenerate), alert_mrad=2.5)
    assert (s["median_test_error_mrad"], s["n_with_test_error"], s["n_degenerate"]) == (
        median, n_error, n_degenerate)
    assert s["n_above_alert"] == 1 and s["n_on_alert"] == 1
