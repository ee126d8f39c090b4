"""One heliostat's inputs to ``sweep`` and its rows of sweep.parquet, shared by the production
selection and the training-size study (:mod:`.sweep`)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.schemas import COARSE_PARAMS, COARSE_PREDICTIONS, HELIOSTATS, MEASUREMENTS, SPLIT
from ..artifacts.store import check_fresh, read_artifact
from ..errors import FitError
from ..models.coarse import MeasurementBatch
from ..models.pretrained import PretrainConfig, fit_pretrained
from ..physics.metrics import error_mrad, measured_normal
from ..physics.parameters import HeliostatSpec, nominal_parameters
from .fit_coarse import load_selected_parameters

__all__ = ["SweepInputs", "SweepHeliostat", "read_sweep_inputs", "coarse_by_model", "split_stats",
           "sweep_row", "fit_pretrained_errors"]


def split_stats(err: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(mean, median) of ``err`` [mrad] on the rows ``mask``; NaN without such rows."""
    if not mask.any():
        return float("nan"), float("nan")
    v = err[mask]
    return float(v.mean()), float(np.median(v))


def sweep_row(hid, model, n_train, wd, seed, err, labels, train_mask, dist, base_preset, wall):
    """One sweep.parquet row: a model's errors ``err`` (N,) [mrad] of one heliostat on its
    training rows ``train_mask`` and its validation and test ``labels``."""
    tr = split_stats(err, train_mask)
    va = split_stats(err, labels == "validation")
    te = split_stats(err, labels == "test")
    return {"heliostat_id": hid, "model": model, "n_train": int(n_train),
            "weight_decay": wd, "seed": int(seed),
            "train_error_mrad": tr[0], "train_median_error_mrad": tr[1],
            "val_error_mrad": va[0], "val_median_error_mrad": va[1],
            "test_error_mrad": te[0], "test_median_error_mrad": te[1],
            "test_train_distance_deg": dist, "base_preset": base_preset, "wall_time_s": wall}


@dataclass
class SweepInputs:
    """One heliostat's inputs to the sweep as the stage reads them (what a task carries)."""

    hid: str
    rows: pd.DataFrame          # its measurements (all splits) with the split label
    hrow: dict                  # its heliostats.parquet row
    split_rows: pd.DataFrame    # its split.parquet rows
    selected: dict              # fit-coarse's selected fit (load_selected_parameters)
    coarse: dict                # model -> DataFrame of coarse_predictions metric columns, rows' order
    coarse_val: float           # fit-coarse's selected preset's mean validation error [mrad]
    coarse_test: float          # ... and test error [mrad] (coarse_params.parquet)


@dataclass
class SweepHeliostat(SweepInputs):
    """What both parts of the sweep need of one heliostat: its inputs and what follows from them
    (built in the worker, :meth:`of`)."""

    @classmethod
    def of(cls, inputs: SweepInputs) -> "SweepHeliostat":
        return cls(**vars(inputs))

    def __post_init__(self):
        self.rows = self.rows.reset_index(drop=True)
        self.hrow = pd.Series(self.hrow)
        self.labels = self.rows["split"].to_numpy()
        self.spec = HeliostatSpec.from_row(self.hrow)
        self.nominal = nominal_parameters(self.hrow)
        self.data = MeasurementBatch.from_frame(self.rows)
        self.train = self.labels == "train"
        self.n_full = int(self.train.sum())
        test = self.split_rows["split"] == "test"
        self.test_distance = (float(self.split_rows.loc[test, "nearest_train_distance_deg"].mean())
                              if test.any() else float("nan"))


def coarse_by_model(pred: pd.DataFrame, rows: pd.DataFrame) -> dict:
    """coarse_predictions rows of one heliostat per model, in the order of ``rows``."""
    order = rows["measurement_id"].astype(str).to_numpy()
    out = {}
    for model, g in pred.groupby("model", sort=True):
        out[str(model)] = g.set_index(g["measurement_id"].astype(str)).reindex(order)
    return out


def fit_pretrained_errors(h: SweepHeliostat, coarse, labels, seed: int, config: PretrainConfig):
    """:func:`fit_pretrained` on one heliostat, plus every row's error_mrad and the seconds."""
    t0 = time.perf_counter()
    model, info, normal, position = fit_pretrained(coarse, h.spec, h.hrow, h.rows, h.data, labels,
                                                   seed, config)
    with torch.no_grad():
        err = error_mrad(normal, measured_normal(h.data.sun, position, h.data.focal_spot)).numpy()
    return model, info, normal, position, err, time.perf_counter() - t0


def read_sweep_inputs(workdir: Path, heliostats: Sequence[str] | None) -> dict[str, SweepInputs]:
    """Every heliostat's :class:`SweepInputs` (in id order): those with a coarse fit, its
    predictions and training rows."""
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=heliostats).set_index("heliostat_id",
                                                                                 drop=False)
    check_fresh(workdir, SPLIT, {"measurements": MEASUREMENTS})
    check_fresh(workdir, COARSE_PARAMS, {"measurements": MEASUREMENTS, "split": SPLIT})
    check_fresh(workdir, COARSE_PREDICTIONS, {"measurements": MEASUREMENTS, "split": SPLIT})
    split = read_artifact(workdir, SPLIT, heliostats=heliostats)
    selected = load_selected_parameters(workdir, heliostats)
    params = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats,
                           columns=["heliostat_id", "preset", "selected", "val_error_mrad",
                                    "test_error_mrad"])
    params = params[params["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")
    preds = read_artifact(workdir, COARSE_PREDICTIONS, heliostats=heliostats)
    pred_of = dict(tuple(preds.groupby("heliostat_id", sort=False)))
    merged = measurements.merge(split[["heliostat_id", "measurement_id", "split"]],
                                on=["heliostat_id", "measurement_id"], how="inner")
    rows_of = dict(tuple(merged.groupby("heliostat_id", sort=False)))   # not a scan per heliostat
    split_of = dict(tuple(split.groupby("heliostat_id", sort=False)))
    items = {}
    for hid in sorted(selected):
        rows = rows_of.get(hid)
        srows = split_of.get(hid)
        if rows is None or srows is None or hid not in helio.index or hid not in pred_of:
            continue
        if not (srows["split"] == "train").any():
            continue
        items[hid] = SweepInputs(hid, rows, helio.loc[hid].to_dict(), srows, selected[hid],
                                 coarse_by_model(pred_of[hid], rows),
                                 float(params.loc[hid, "val_error_mrad"]),
                                 float(params.loc[hid, "test_error_mrad"]))
    if not items:
        raise FitError(f"no heliostat in {workdir} has a coarse fit and training rows; run "
                       f"`heliocal fit-coarse --workdir {workdir}` first")
    return items
