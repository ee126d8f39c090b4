"""Is ``aim``'s ``expected_error_mrad`` right? Its calibration on held-out rows
(``benchmarks/expected_error.py``, tests/test_aim_budget.py).

For every heliostat of a fitted work directory, each held-out row's expected error (the budget of
:mod:`.aim_budget` at the row's steps, sun and focal spot, as for an aim at that spot) beside its
actual error, in two settings: ``forward`` (the model fitted on the time split's training rows,
its level from what a plant had seen before the time split's first test row: the next-day rows
scored before it and the time split's validation rows; scored on the time split's test rows) and
``knn`` (the selected model, its level from its kNN validation rows; scored on the kNN test
rows).

The heliostats whose sweep selected the GP correction are checked on their own
(:func:`gp_calibration_rows`): the GP-corrected model's actual error beside the coarse budget
alone and the budget through the GP's predictive variance at the row.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from ..artifacts.schemas import COARSE_PREDICTIONS, MEASUREMENTS, SPLIT
from ..artifacts.store import read_artifact
from ..models.coarse import MeasurementBatch
from ..physics.parameters import HeliostatSpec
from .aim_budget import error_budgets, expected_error_mrad

__all__ = ["calibration_rows", "calibration_summary", "first_test_time", "gp_calibration_rows"]


def _time_selected(workdir, selected: dict) -> dict:
    """``selected`` with each heliostat's parameters of its time-split fit (``time_fitted``;
    unchanged where it has none) and no regime table: the time split's refit ends in its
    training period's latest regime."""
    from ..artifacts.schemas import COARSE_PARAMS

    p = read_artifact(workdir, COARSE_PARAMS)
    p = p[p["selected"]].sort_values(["heliostat_id", "parameter_index"])
    out = {}
    for hid, sel in selected.items():
        g = p[p["heliostat_id"] == hid]
        t = g["time_fitted"].to_numpy(float) if "time_fitted" in g else np.array([np.nan])
        params = torch.tensor(t) if len(t) == 28 and np.isfinite(t).all() else sel["params"]
        out[hid] = {**sel, "params": params, "regime_table": None}
    return out


def _coarse_budgets(workdir, setting: str, heliostats=None, model: str = "coarse"
                    ) -> tuple[dict, dict, dict]:
    """(specs, selected parameters, coarse :class:`.aim_budget.ErrorBudget`) of the heliostats
    (all: None) as ``setting`` takes them (module docstring); ``model="gp"``: aimed through the
    sweep's GP (the budgets' :attr:`~.aim_budget.ErrorBudget.fine_floor_ratio`)."""
    from ..artifacts.schemas import HELIOSTATS
    from .fit_coarse import load_selected_parameters

    helio = read_artifact(workdir, HELIOSTATS).set_index("heliostat_id")
    selected = load_selected_parameters(workdir, heliostats)
    specs = {h: HeliostatSpec.from_row(helio.loc[h]) for h in selected}
    models = {h: {"model": model, "source": "sweep"} for h in selected}
    if setting == "forward":
        # as a plant aims after its calibration: the next-day rows it had seen by then first
        selected = _time_selected(workdir, selected)
        budgets = error_budgets(workdir, specs, selected, models, split_column="time_split",
                                level_sources=("next-day", "time-split validation"),
                                known_until=first_test_time(workdir))
    else:
        budgets = error_budgets(workdir, specs, selected, models,
                                level_sources=("validation",))
    return specs, selected, budgets


def _test_rows(workdir, setting: str, predictions=COARSE_PREDICTIONS, heliostats=None
               ) -> tuple[pd.DataFrame, pd.Series, str]:
    """(the measurement rows of ``setting``'s test rows with the selected model's actual error
    of ``predictions``, each heliostat's last training row's time, the actual error's column)."""
    label, actual = ("time_split", "time_error_mrad") if setting == "forward" else ("split", "error_mrad")
    split = read_artifact(workdir, SPLIT, columns=["heliostat_id", "measurement_id", label],
                          heliostats=heliostats)
    pred = read_artifact(workdir, predictions, heliostats=heliostats,
                         columns=["heliostat_id", "measurement_id", "selected", actual])
    pred = pred[pred["selected"]].merge(split, on=["heliostat_id", "measurement_id"])
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    last_train = _last_training_time(measurements, pred, label)
    pred = pred[pred[label] == "test"]
    rows = measurements.merge(
        pred[["heliostat_id", "measurement_id", actual]], on=["heliostat_id", "measurement_id"])
    return rows, last_train, actual


def _days(g: pd.DataFrame, last_train: pd.Series, hid: str, setting: str) -> np.ndarray | None:
    """forward: the test rows' days since the time split's last training row (the level grows
    to them); kNN: None (test rows lie among the training rows: the level as measured)."""
    if setting != "forward":
        return None
    return ((pd.to_datetime(g["timestamp"], utc=True) - last_train.get(hid, pd.NaT))
            / pd.Timedelta(days=1)).to_numpy(float)


def calibration_rows(workdir, setting: str) -> pd.DataFrame:
    """Per held-out row of ``setting`` (``forward`` or ``knn``): heliostat, actual and expected
    error [mrad], the level source."""
    specs, selected, budgets = _coarse_budgets(workdir, setting)
    rows, last_train, actual = _test_rows(workdir, setting)
    out = []
    for hid, g in rows.groupby("heliostat_id"):
        if hid not in budgets or not np.isfinite(g[actual]).any():
            continue
        b = MeasurementBatch.from_frame(g)
        expected = expected_error_mrad(budgets[hid], specs[hid], selected[hid]["params"],
                                       b.steps, b.sun, b.focal_spot,
                                       _days(g, last_train, hid, setting))
        out.append(pd.DataFrame({"heliostat_id": hid, "actual_mrad": g[actual].to_numpy(float),
                                 "expected_mrad": expected,
                                 "level_source": budgets[hid].level_source}))
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame()


def gp_selected(workdir) -> list[str]:
    """The heliostats whose sweep selected the GP correction (``gp``, ``gp-sun``) and whose
    model ``aim --model auto`` uses."""
    from .aim_choice import aim_models

    return sorted(h for h, m in aim_models(workdir).items() if m["model"] == "gp")


def _time_split_gp(workdir, hid: str, spec, time_params, model, cfg: dict, fitted: dict):
    """The GP of ``model``'s structure and fade lengths fitted again on the time split's training
    rows on top of fit-coarse's time-split parameters ``time_params`` (28,), as the sweep's
    forward check fits it (:func:`heliocal.pipeline.stages.selection.gp_time_errors`: of a
    regime-aware model, the training rows of its latest regime; ``fitted``: the heliostat's
    entry of :func:`.fit_coarse.load_selected_parameters`)."""
    import dataclasses

    from ..models.gp import GPConfig
    from ..models.gp_heliostat import fit_heliostat_gps
    from .selection import latest_regime_labels

    keys = ["heliostat_id", "measurement_id"]
    rows = read_artifact(workdir, MEASUREMENTS, heliostats=[hid]).merge(
        read_artifact(workdir, SPLIT, heliostats=[hid], columns=keys + ["time_split"]), on=keys)
    labels = latest_regime_labels(fitted, rows["timestamp"],
                                  rows["time_split"].to_numpy(object))
    config = dataclasses.replace(GPConfig.from_dict(cfg["gp_config"]),
                                 structures=(model.structure,))
    fits = fit_heliostat_gps(rows, labels, spec, MeasurementBatch.from_frame(rows), time_params,
                             config, np.ones(int((labels == "validation").sum())),
                             lengths=(model.fade.length_deg,),
                             time_length_days=model.fade.length_days)
    return fits[model.structure].model


def gp_calibration_rows(workdir, setting: str) -> pd.DataFrame:
    """Per held-out row of ``setting`` of the heliostats aim aims with the GP correction
    (:func:`gp_selected`): the GP-corrected model's actual error (selected_predictions.parquet;
    forward: the GP fitted on the time split's training rows), ``expected_before_mrad`` (the
    coarse budget alone) and ``expected_mrad`` (through the GP's predictive variance at the
    row's sun, time and env: :func:`.aim_budget.fine_level_mrad`) [mrad], the level source."""
    from ..artifacts.schemas import SELECTED_PREDICTIONS
    from ..models.gp import GPCorrection
    from .aim import load_model
    from .fit_coarse import load_selected_parameters

    ids = gp_selected(workdir)
    if not ids:
        return pd.DataFrame()
    specs, selected, budgets = _coarse_budgets(workdir, setting, ids, model="gp")
    # the regimes of the selected fits (the forward budgets' ``selected`` has none)
    fitted = load_selected_parameters(workdir, ids) if setting == "forward" else {}
    rows, last_train, actual = _test_rows(workdir, setting, SELECTED_PREDICTIONS, ids)
    out = []
    for hid, g in rows.groupby("heliostat_id"):
        if hid not in budgets or not np.isfinite(g[actual]).any():
            continue
        cfg, state = load_model(workdir, "selected", hid)
        model = GPCorrection.from_model(cfg, state)
        if setting == "forward":
            model = _time_split_gp(workdir, hid, specs[hid], selected[hid]["params"], model, cfg,
                                   fitted[hid])
        gp = model.predict_rows(g)
        b = MeasurementBatch.from_frame(g)
        args = (budgets[hid], specs[hid], selected[hid]["params"], b.steps, b.sun, b.focal_spot,
                _days(g, last_train, hid, setting))
        out.append(pd.DataFrame({
            "heliostat_id": hid, "actual_mrad": g[actual].to_numpy(float),
            "expected_before_mrad": expected_error_mrad(*args),
            "expected_mrad": expected_error_mrad(*args,
                                                 explained_mrad2=gp.explained_variance_mrad2,
                                                 fine_noise_mrad2=gp.noise_mrad2),
            "level_source": budgets[hid].level_source}))
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame()


def first_test_time(workdir) -> pd.Series:
    """heliostat -> the time [UTC] of its time split's first test row."""
    keys = ["heliostat_id", "measurement_id"]
    split = read_artifact(workdir, SPLIT, columns=keys + ["time_split"])
    test = split[split["time_split"] == "test"].merge(
        read_artifact(workdir, MEASUREMENTS, columns=keys + ["timestamp"]), on=keys)
    return pd.to_datetime(test["timestamp"], utc=True).groupby(test["heliostat_id"]).min()


def _last_training_time(measurements: pd.DataFrame, labelled: pd.DataFrame, label: str
                        ) -> pd.Series:
    """heliostat -> the time [UTC] of its last row labelled ``train`` in ``labelled[label]``."""
    keys = ["heliostat_id", "measurement_id"]
    train = labelled.loc[labelled[label] == "train", keys].merge(
        measurements[keys + ["timestamp"]], on=keys)
    return pd.to_datetime(train["timestamp"], utc=True).groupby(train["heliostat_id"]).max()


def calibration_summary(rows: pd.DataFrame) -> dict:
    """rows, ``within_2x`` (share with actual <= 2 x expected), ``median_ratio`` (actual /
    expected) and the mean actual and expected error of :func:`calibration_rows`."""
    ok = rows.dropna(subset=["actual_mrad", "expected_mrad"])
    ratio = ok["actual_mrad"] / ok["expected_mrad"]
    return {"rows": len(ok), "within_2x": float((ratio <= 2.0).mean()) if len(ok) else np.nan,
            "median_ratio": float(ratio.median()) if len(ok) else np.nan,
            "mean_actual": float(ok["actual_mrad"].mean()) if len(ok) else np.nan,
            "mean_expected": float(ok["expected_mrad"].mean()) if len(ok) else np.nan}
