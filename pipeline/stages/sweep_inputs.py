"""One heliostat's inputs to ``sweep`` and its rows of sweep.parquet, shared by the production
selection and the training-size study (:mod:`.sweep`)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.incremental import heliostat_digests
from ..artifacts.schemas import (COARSE_PARAMS, COARSE_PREDICTIONS, HELIOSTATS, MEASUREMENTS,
                                REGIME_PARAMS, REGIMES, SPLIT)
from ..artifacts.store import artifact_present, check_fresh, read_artifact
from ..errors import FitError
from ..models.coarse import MeasurementBatch
from ..models.pretrained import PretrainConfig, fit_pretrained
from ..physics.metrics import error_mrad, measured_normal
from ..physics.parameters import HeliostatSpec, nominal_parameters
from .fit_coarse import load_selected_parameters
from .forward import load_time_parameters

__all__ = ["SweepInputs", "SweepHeliostat", "SweepInputsTable", "sweep_digests",
           "read_sweep_inputs", "coarse_by_model", "split_stats",
           "sweep_row", "fit_pretrained_errors"]


def split_stats(err: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(mean, median) of ``err`` [mrad] on the rows ``mask``; NaN without such rows."""
    if not mask.any():
        return float("nan"), float("nan")
    v = err[mask]
    return float(v.mean()), float(np.median(v))


def sweep_row(hid, model, n_train, wd, seed, err, labels, train_mask, dist, base_preset, wall,
              fade_length_deg: float = float("nan")):
    """One sweep.parquet row: a model's errors ``err`` (N,) [mrad] of one heliostat on its
    training rows ``train_mask`` and its validation and test ``labels`` (a fine model's at its
    sun fade length ``fade_length_deg`` [deg])."""
    tr = split_stats(err, train_mask)
    va = split_stats(err, labels == "validation")
    te = split_stats(err, labels == "test")
    return {"heliostat_id": hid, "model": model, "n_train": int(n_train),
            "weight_decay": wd, "seed": int(seed),
            "train_error_mrad": tr[0], "train_median_error_mrad": tr[1],
            "val_error_mrad": va[0], "val_median_error_mrad": va[1],
            "test_error_mrad": te[0], "test_median_error_mrad": te[1],
            "test_train_distance_deg": dist, "base_preset": base_preset, "wall_time_s": wall,
            "fade_length_deg": fade_length_deg}


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
    time_params: torch.Tensor | None = None   # fit-coarse's time-split fit (28,); None: none


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


class SweepInputsTable(Mapping):
    """Every heliostat's :class:`SweepInputs`, in id order, each built when first asked for: an
    update trains a few heliostats of thousands, and the others need only their digest.

    Attributes
    ----------
    digests : heliostat id -> SHA-256 (hex) of its rows in every table its inputs are taken from
        (:func:`sweep_digests`).
    schemas : those tables without rows (their columns and dtypes, for the field key).
    """

    def __init__(self, ids: Sequence[str], frames: Sequence[pd.DataFrame],
                 build: Callable[[str], SweepInputs]):
        self._ids, self._build = sorted(ids), build
        self.digests = sweep_digests(frames, self._ids)
        self.schemas = [df.iloc[:0] for df in frames]   # the tables themselves are not kept
        self._built: dict[str, SweepInputs] = {}

    def __getitem__(self, hid: str) -> SweepInputs:
        if hid not in self._built:
            if hid not in self.digests:
                raise KeyError(hid)
            self._built[hid] = self._build(hid)
        return self._built[hid]

    def __iter__(self):
        return iter(self._ids)

    def __len__(self) -> int:
        return len(self._ids)


def sweep_digests(frames: Sequence[pd.DataFrame], ids: Sequence[str]) -> dict[str, str]:
    """heliostat id (of ``ids``) -> SHA-256 (hex) of its rows in ``frames``
    (:func:`~heliocal.pipeline.artifacts.incremental.heliostat_digests`: rows hashed by value, in
    the tables' order). :func:`read_sweep_inputs` passes what the sweep reads for a heliostat: its
    rows with their split, its heliostats.parquet row, split rows and coarse_predictions rows,
    the :data:`SELECTED_FIT_COLUMNS` of its selected coarse fit, and its selected regime
    parameters and regimes; so equal digests, equal inputs."""
    digests = heliostat_digests(frames)
    return {hid: digests[hid] for hid in ids}


def read_sweep_inputs(workdir: Path, heliostats: Sequence[str] | None) -> SweepInputsTable:
    """Every heliostat's :class:`SweepInputs` (in id order, built on demand): those with a coarse
    fit, its predictions and training rows."""
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=heliostats)
    check_fresh(workdir, SPLIT, {"measurements": MEASUREMENTS})
    check_fresh(workdir, COARSE_PARAMS, {"measurements": MEASUREMENTS, "split": SPLIT})
    check_fresh(workdir, COARSE_PREDICTIONS, {"measurements": MEASUREMENTS, "split": SPLIT})
    split = read_artifact(workdir, SPLIT, heliostats=heliostats)
    selected = load_selected_parameters(workdir, heliostats)
    fit = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats,
                        columns=[*SELECTED_FIT_COLUMNS, "selected"])
    fit = fit.loc[fit["selected"], list(SELECTED_FIT_COLUMNS)]
    params = fit.drop_duplicates("heliostat_id").set_index("heliostat_id")
    preds = read_artifact(workdir, COARSE_PREDICTIONS, heliostats=heliostats)
    time_params = load_time_parameters(workdir, heliostats)
    merged = measurements.merge(split[["heliostat_id", "measurement_id", "split"]],
                                on=["heliostat_id", "measurement_id"], how="inner")
    rows_of = dict(tuple(merged.groupby("heliostat_id", sort=False)))   # not a scan per heliostat
    split_of = dict(tuple(split.groupby("heliostat_id", sort=False)))
    pred_of = dict(tuple(preds.groupby("heliostat_id", sort=False)))
    helio_of = helio.set_index("heliostat_id", drop=False)
    trained = set(split.loc[split["split"] == "train", "heliostat_id"].astype(str))
    ids = [hid for hid in sorted(selected) if hid in rows_of and hid in split_of
           and hid in helio_of.index and hid in pred_of and hid in trained]
    if not ids:
        raise FitError(f"no heliostat in {workdir} has a coarse fit and training rows; run "
                       f"`heliocal fit-coarse --workdir {workdir}` first")

    def build(hid: str) -> SweepInputs:
        rows = rows_of[hid]
        return SweepInputs(hid, rows, helio_of.loc[hid].to_dict(), split_of[hid], selected[hid],
                           coarse_by_model(pred_of[hid], rows),
                           float(params.loc[hid, "val_error_mrad"]),
                           float(params.loc[hid, "test_error_mrad"]), time_params.get(hid))

    frames = [merged, helio, split, fit, preds, *_regime_frames(workdir, heliostats)]
    return SweepInputsTable(ids, frames, build)


#: The columns of coarse_params.parquet's selected rows a heliostat's inputs hold
#: (:func:`~.fit_coarse.load_selected_parameters`, the errors, the time-split fit): what else
#: fit-coarse records there (the next-day errors, fit diagnostics) does not reach the sweep.
SELECTED_FIT_COLUMNS = ("heliostat_id", "parameter_index", "preset", "fitted", "free", "nominal",
                        "std_error", "val_error_mrad", "test_error_mrad", "time_fitted")


def _regime_frames(workdir: Path, heliostats: Sequence[str] | None) -> list[pd.DataFrame]:
    """The selected rows of regime_params.parquet and the rows of regimes.parquet, where
    fit-coarse wrote them (what a selected regime-aware model reads of its heliostat)."""
    frames = []
    if artifact_present(workdir, REGIME_PARAMS):
        table = read_artifact(workdir, REGIME_PARAMS, heliostats=heliostats)
        frames.append(table[table["selected"]])
    if artifact_present(workdir, REGIMES):
        frames.append(read_artifact(workdir, REGIMES, heliostats=heliostats))
    return frames
