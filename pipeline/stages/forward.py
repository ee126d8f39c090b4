"""Forward-in-time evaluation: every model evaluated, and chosen, on the time split as well.

``split-knn`` writes, beside the split that selects models (kNN by default), a time split of
every heliostat with timestamps (split.parquet ``time_split``: the latest measurements are test,
the ones before them validation, the earlier ones train). The operational question is
"calibrate now, aim for the coming weeks", and a model that saw a recent row cannot answer it for
that row: evaluating the kNN-trained model on the time split's test rows would leak (those rows
may be among its training rows). So every model is trained a second time, the same way, on the
time split's training rows only, and its errors on every row are written beside the model's own
(``time_error_mrad``):

- ``fit-coarse``: every preset fitted again (same solver, loss and robust start rules) on the time
  split's training rows outside detected episodes, in the same chunk task as its kNN fit; a
  regime-aware candidate (``<preset>+offsets``, ``+drift``) fitted again on those rows with the
  same regimes (a regime that starts after the last training row has no rows of its own and
  takes the parameters of the regime before it, as ``aim`` does); its parameters are
  coarse_params.parquet's ``time_fitted``.
- ``fit-hybrid``: the fitted mode trained again with the same weight decay and seed on top of
  the selected preset's time-split coarse fit.
- ``sweep``: a heliostat whose selected model is the coarse one takes fit-coarse's time-split
  errors, at no cost; with ``sweep --time-split`` a selected hybrid (or pretrained-nn) is trained
  again (the variant, weight decay and seed the kNN selection chose) on top of the time-split
  coarse fit, along the same weight-decay path down to the selected weight decay
  (:func:`add_sweep_time_split`).

Choosing forward-aware (:func:`forward_guarded_choice`): the kNN validation selects, but a choice
whose time-split validation error is worse than another candidate's by more than the margin
(:data:`heliocal.pipeline.vocabulary.MIN_IMPROVEMENT`) gives way to the candidate with the
smallest worst relative regret over both validations. On the Jülich log's heliostats with few
rows a 28-parameter fit from six rows of March extrapolated to June by 256 mrad while the kNN
validation, whose rows lie between the training rows in time, saw 1.5 mrad. A regime-aware
candidate or the refit without episodes must in addition not be worse than the plain fit on the
time split's validation rows. A heliostat without a time split (no or too few timestamps) is
chosen on the kNN validation alone and every forward-in-time figure of it is "n/a".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.schemas import COARSE_PARAMS, SPLIT
from ..artifacts.store import artifact_present, read_artifact
from ..errors import SchemaError
from ..models.coarse import MeasurementBatch
from ..models.config import ensemble_seeds
from ..models.fade import NETWORK_TIME_FADE_DAYS, Fade
from ..models.pretrained import fit_pretrained
from ..models.training import build_problem, ensemble_errors_mrad, stack_problems, take_rows
from ..physics.metrics import error_mrad, measured_normal
from ..physics.metrics import mean_or_nan as _mean
from ..physics.parameters import PARAMETER_NAMES, HeliostatSpec
from ..runtime.parallel import map_tasks
from ..runtime.process_state import deterministic_torch
from ..vocabulary import MIN_IMPROVEMENT

__all__ = [
    "TIME_COLUMN",
    "load_time_labels",
    "time_labels_of",
    "forward_guarded_choice",
    "chunks_per_worker",
    "load_time_parameters",
    "add_sweep_time_split",
    "time_rows",
]

log = logging.getLogger("heliocal.forward")

#: split.parquet's column of the time split.
TIME_COLUMN = "time_split"


def load_time_labels(workdir: str | Path, measurements: pd.DataFrame) -> np.ndarray:
    """split.parquet's ``time_split`` label per measurement row (object array; ``None`` where
    the row has none, and for every row without split.parquet)."""
    if not artifact_present(workdir, SPLIT):
        return np.full(len(measurements), None, dtype=object)
    split = read_artifact(workdir, SPLIT, columns=["heliostat_id", "measurement_id", TIME_COLUMN])
    return labels_by_row(split, measurements, TIME_COLUMN)


def labels_by_row(split: pd.DataFrame, rows: pd.DataFrame, column: str) -> np.ndarray:
    """``split[column]`` for each of ``rows`` matched on (heliostat_id, measurement_id): an
    object array, ``None`` where ``split`` has no such row or no label."""
    keys = ["heliostat_id", "measurement_id"]
    listed = pd.MultiIndex.from_frame(split[keys].astype(str))
    if not listed.is_unique:
        raise SchemaError("split.parquet lists a measurement more than once; rerun "
                          "`heliocal split-knn`")
    where = listed.get_indexer(pd.MultiIndex.from_frame(rows[keys].astype(str)))
    values = split[column].to_numpy(dtype=object)
    found = where >= 0
    out = np.full(len(rows), None, dtype=object)
    out[found] = values[where[found]]
    out[pd.isna(out)] = None
    return out


def time_labels_of(rows: pd.DataFrame) -> np.ndarray | None:
    """The ``time_split`` labels of one heliostat's rows, or ``None`` when it has no time split
    (no such column, or no time-split training row)."""
    if TIME_COLUMN not in rows.columns:
        return None
    labels = rows[TIME_COLUMN].to_numpy(dtype=object)
    return labels if (labels == "train").sum() >= 2 else None


def time_rows(labels: np.ndarray | None) -> np.ndarray:
    """``labels`` with the rows outside the time split as ``unused`` (for training code that
    treats every label other than train/validation/test as unused)."""
    return np.array(["unused" if v is None else v for v in labels], dtype=object)


# ------------------------------------------------------------------------------------------------
# fit-coarse
# ------------------------------------------------------------------------------------------------
def forward_guarded_choice(knn_val: Sequence[float], time_val: Sequence[float],
                           margin: float = MIN_IMPROVEMENT) -> int:
    """The index of the candidate to select from their mean validation errors [mrad] on the
    kNN split (``knn_val``) and of their time-split fits on the time split's validation rows
    (``time_val``; NaN where a candidate has none).

    The kNN choice (lowest ``knn_val``) stands unless its time validation error exceeds the
    best one by more than ``margin`` (relative); then the candidate with the smallest worst
    relative regret ``max(knn_val / min knn_val, time_val / min time_val)`` is chosen. Without
    any finite kNN validation error the last candidate is chosen (the largest preset asked);
    without finite time validation errors, the kNN choice."""
    kv = np.asarray(knn_val, float)
    tv = np.asarray(time_val, float)
    if not np.isfinite(kv).any():
        return len(kv) - 1
    k = int(np.nanargmin(np.where(np.isfinite(kv), kv, np.inf)))
    both = np.isfinite(kv) & np.isfinite(tv)
    if not np.isfinite(tv[k]) or both.sum() < 2:
        return k
    best_t = tv[both].min()
    if tv[k] <= (1.0 + margin) * best_t:
        return k
    regret = np.maximum(kv / kv[both].min(), tv / best_t)
    return int(np.argmin(np.where(both, regret, np.inf)))


def chunks_per_worker(solver: str) -> int:
    """``map_tasks``' grouping of fit-coarse's tasks: a batched task (64 heliostats) takes a
    second or more and heliostats with regimes take longer than others, so the tasks go out
    one at a time up to 16 per worker (groups of four left one worker idle for seconds at the
    end of a 2,000-heliostat field); scipy's tasks are single heliostats, grouped by four."""
    return 16 if solver == "batched" else 4


def load_time_parameters(workdir: str | Path, heliostats: Sequence[str] | None = None) -> dict:
    """heliostat -> the time-split fit of its selected preset (torch (28,)), for the heliostats
    that have one (coarse_params.parquet ``time_fitted``)."""
    df = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats,
                       columns=["heliostat_id", "selected", "parameter_index", "time_fitted"])
    df = df[df["selected"]].sort_values(["heliostat_id", "parameter_index"])
    out = {}
    for hid, g in df.groupby("heliostat_id", sort=True):
        v = g["time_fitted"].to_numpy(np.float64)
        if len(v) == len(PARAMETER_NAMES) and np.isfinite(v).all():
            out[str(hid)] = torch.tensor(v)
    return out


# ------------------------------------------------------------------------------------------------
# sweep
# ------------------------------------------------------------------------------------------------
@dataclass
class _TimeEntry:
    """One heliostat whose selected model the sweep trains again on the time split."""

    hid: str
    rows: pd.DataFrame          # its measurements, in the order of its predictions
    hrow: dict                  # its heliostats.parquet row
    labels: np.ndarray          # its time split's label per row (None: not in it)
    theta: torch.Tensor         # fit-coarse's time-split fit of its selected preset (28,)
    free: torch.Tensor          # the preset's free parameters (28,) bool
    weight_decay: float         # the selected model's
    seed: int                   # the selected model's
    fade_length_deg: float = float("inf")   # its sun fade length (models.fade), time fade too


def _sweep_time_task(task) -> list[tuple[str, np.ndarray]]:
    """One group of heliostats whose selected models train together (one hybrid variant, one
    kinematic and actuator type and free parameters; or one heliostat's pretrained-nn): per
    heliostat its selected model trained on the time split's training rows, error_mrad of every
    row (rows' order)."""
    kind, entries, cfg, weight_decays, path, train_path = task
    deterministic_torch()
    out = []
    hrows = [pd.Series(e.hrow) for e in entries]
    labels = [time_rows(e.labels) for e in entries]
    if kind == "pretrained-nn":
        for e, hrow, lab in zip(entries, hrows, labels):
            d = MeasurementBatch.from_frame(e.rows)
            _, _, normal, position = fit_pretrained(e.theta, HeliostatSpec.from_row(hrow), hrow,
                                                    e.rows, d, lab, e.seed, cfg)
            with torch.no_grad():
                out.append((e.hid, error_mrad(normal, measured_normal(d.sun, position,
                                                                      d.focal_spot)).numpy()))
        return out
    k_ens = cfg.ensemble
    problems, taken, fit_labels = [], [], []
    for e, hrow, lab in zip(entries, hrows, labels):
        p = build_problem(e.rows, hrow, e.theta, e.free, cfg)
        fitting = np.isin(lab, ("train", "validation"))
        problems.append(p)
        taken.append(take_rows(p, torch.as_tensor(fitting)))
        fit_labels.append(lab[fitting])
    stacked, valid = stack_problems([t for t in taken for _ in range(k_ens)])
    n = stacked.data.steps.shape[1]
    lab = np.array([np.resize(x, n) for x in fit_labels for _ in range(k_ens)])
    seeds = [s for e in entries for s in ensemble_seeds(e.seed, k_ens)]
    # the selected weight decays are reached along the sweep's path (strong to weak)
    wds = [w for w in weight_decays if w >= min(e.weight_decay for e in entries)]
    for wd, result in train_path(stacked, torch.as_tensor(lab == "train") & valid,
                                 torch.as_tensor(lab == "validation") & valid, seeds, wds, cfg,
                                 path):
        for k, e in enumerate(entries):
            if e.weight_decay == wd:
                nets = slice(k * k_ens, (k + 1) * k_ens)
                layers = [(w[nets], b[nets]) for w, b in result.layers]
                # the model's fade, measured from the time split's training rows
                fade = Fade.of_rows(e.rows[labels[k] == "train"], e.fade_length_deg,
                                    NETWORK_TIME_FADE_DAYS).weights_of_rows(e.rows)
                with torch.no_grad():
                    out.append((e.hid, ensemble_errors_mrad(problems[k], layers, k_ens,
                                                            fade).numpy()[0]))
    return out


def add_sweep_time_split(workdir, chosen: list[dict], items: dict, variants, weight_decays,
                         path, pretrain_config, train_path: Callable, enabled: bool = True, *,
                         batch_size: int = 64, workers=1, scheduler="local",
                         dask_address=None) -> None:
    """Evaluate the sweep's selected models forward in time (in place): every result of
    ``chosen`` gets ``time_error_mrad`` in its predictions and ``time_test_error_mrad``,
    ``coarse_time_test_error_mrad`` in its selection.

    The selected model (variant, weight decay, seed) is trained again on top of fit-coarse's
    time-split fit (coarse_params.parquet ``time_fitted``) on the time split's training rows, with early
    stopping on its validation rows, along the sweep's weight-decay path down to the selected
    weight decay (``train_path``, ``path``), heliostats of one variant and type batched as in
    the selection; a heliostat whose selected model is the coarse one takes fit-coarse's
    time-split errors. ``enabled=False`` (the sweep's default): only the coarse model's (free)
    figures are written, a selected hybrid's are missing, except where it stands in for a GP the
    forward check refused (:attr:`~.selection.HeliostatChoice.refused`).

    Parameters
    ----------
    chosen : the selection results (``selection``, ``predictions``) of the sweep.
    items : heliostat -> the sweep's inputs (:class:`~.sweep_inputs.SweepInputs`).
    variants : the sweep's ``(name, FineConfig)``; ``pretrain_config``: a selected
        pretrained-nn's.
    """
    cfg_of = dict(variants)
    time_params = load_time_parameters(workdir, sorted(items))
    entries: dict = {}
    errors: dict[str, np.ndarray] = {}
    for res in chosen:
        sel = res["selection"]
        hid = sel["heliostat_id"]
        item = items[hid]
        rows, hrow, selected = item.rows.reset_index(drop=True), item.hrow, item.selected
        by_id = dict(zip(item.split_rows["measurement_id"].astype(str),
                         item.split_rows[TIME_COLUMN]))
        labels = np.array([None if pd.isna(v := by_id.get(m)) else v
                           for m in rows["measurement_id"].astype(str)], dtype=object)
        res["time_labels"] = labels
        theta = time_params.get(hid)
        if (labels == "train").sum() < 2 or theta is None:
            continue
        if res.get("choice") is not None and res["choice"].time_errors is not None:
            errors[hid] = res["choice"].time_errors   # a GP's, refitted by stages.selection
            continue
        if sel["model"] == "coarse":
            errors[hid] = item.coarse[selected["preset"]]["time_error_mrad"].to_numpy(np.float64)
            continue
        if not enabled and (res.get("choice") is None or res["choice"].refused is None):
            continue                  # a network standing in for a refused GP is always checked
        free = selected["free"]
        key = (sel["model"], str(hrow["kinematic_type"]), str(hrow["actuator_type"]),
               tuple(bool(x) for x in free.tolist()))
        entries.setdefault(key, []).append(_TimeEntry(hid, rows, hrow, labels, theta, free,
                                                      float(sel["weight_decay"]),
                                                      int(sel["seed"]),
                                                      float(sel.get("fade_length_deg", math.inf))))
    tasks = []
    for key in sorted(entries):
        step = 1 if key[0] == "pretrained-nn" else batch_size
        cfg = pretrain_config if key[0] == "pretrained-nn" else cfg_of[key[0]]
        members = entries[key]
        tasks += [(key[0], members[i:i + step], cfg, list(weight_decays), path, train_path)
                  for i in range(0, len(members), step)]
    for part in (map_tasks(_sweep_time_task, tasks, workers=workers, scheduler=scheduler,
                           dask_address=dask_address) if tasks else []):
        errors.update(dict(part))
    for res in chosen:
        sel, pred = res["selection"], res["predictions"]
        hid, labels = sel["heliostat_id"], res.pop("time_labels")
        rows = items[hid].rows.reset_index(drop=True)
        err = errors.get(hid)
        position = pd.Series(np.arange(len(rows)), index=rows["measurement_id"].astype(str))
        at = position.loc[pred["measurement_id"].astype(str).to_numpy()].to_numpy()
        pred["time_error_mrad"] = np.nan if err is None else err[at]
        test = labels == "test"
        coarse = (items[hid].coarse[items[hid].selected["preset"]]["time_error_mrad"]
                  .to_numpy(np.float64))
        sel["time_test_error_mrad"] = _mean(err[test]) if err is not None else float("nan")
        sel["coarse_time_test_error_mrad"] = _mean(coarse[test])
