"""Forward-in-time evaluation (issue 17): every model evaluated on the time split as well.

``split-knn`` writes, beside the split that selects models (kNN by default), a time split of
every heliostat with timestamps (split.parquet ``time_split``: the latest measurements are test,
the ones before them validation, the earlier ones train). The operational question is
"calibrate now, aim for the coming weeks", and a model that saw a recent row cannot answer it for
that row: evaluating the kNN-trained model on the time split's test rows would leak (those rows
may be among its training rows). So the *selected* model is trained a second time, the same way,
on the time split's training rows only, and its errors on every row are written beside the
model's own (``time_error_mrad``):

- ``fit-coarse``: the selected preset fitted again (same solver, loss and robust start rules) on
  the time split's training rows (:func:`fit_coarse_time_split`); its parameters are
  coarse_params.parquet's ``time_fitted``. (Rows of detected episodes are not left out of this
  fit: the episodes were found on residuals that include the recent rows.)
- ``fit-hybrid``: the fitted mode trained again with the same weight decay and seed on top of
  that time-split coarse fit.
- ``sweep``: a heliostat whose selected model is the coarse one takes fit-coarse's time-split
  errors, at no cost; with ``sweep --time-split`` a selected hybrid (or pretrained-nn) is trained
  again (the variant, weight decay and seed the kNN selection chose) on top of the time-split
  coarse fit, along the same weight-decay path down to the selected weight decay
  (:func:`add_sweep_time_split`). That is a second training program per chunk, measured at +50 %
  of the sweep's time on a simulated field (benchmarks/forward_cost.py), so it is not the
  default; without it the selected hybrids' forward-in-time errors are missing ("n/a").

The selection itself never looks at the time split. A heliostat without a time split (no or too
few timestamps) has no ``time_error_mrad`` and every forward-in-time figure of it is "n/a".
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
from ..models.coarse import MeasurementBatch, fit_presets, predict
from ..models.config import ensemble_seeds
from ..models.fade import NETWORK_TIME_FADE_DAYS, Fade
from ..models.pretrained import fit_pretrained
from ..models.training import build_problem, ensemble_errors_mrad, stack_problems, take_rows
from ..physics.metrics import error_mrad, measured_normal
from ..physics.metrics import mean_or_nan as _mean
from ..physics.parameters import PARAMETER_NAMES, HeliostatSpec, nominal_parameters
from ..runtime.parallel import map_tasks

__all__ = [
    "TIME_COLUMN",
    "load_time_labels",
    "time_labels_of",
    "fit_coarse_time_split",
    "chunks_per_worker",
    "attach_coarse_time",
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
    lookup = {(str(h), str(m)): v for h, m, v in zip(split["heliostat_id"], split["measurement_id"],
                                                      split[TIME_COLUMN])}
    return np.array([None if (v := lookup.get((str(h), str(m)))) is None or pd.isna(v) else str(v)
                     for h, m in zip(measurements["heliostat_id"], measurements["measurement_id"])],
                    dtype=object)


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
def _coarse_time_task(task) -> list[tuple[np.ndarray, np.ndarray]]:
    """One chunk (one type and preset): the preset fitted on each heliostat's time-split training
    rows; per heliostat (params (28,), error_mrad of every row)."""
    solver, hrows, rows, preset, options = task
    hrows = [pd.Series(h) for h in hrows]
    specs = [HeliostatSpec.from_row(h) for h in hrows]
    data = [MeasurementBatch.from_frame(r) for r in rows]
    trains = [d.subset(r[TIME_COLUMN].to_numpy(dtype=object) == "train") for d, r in zip(data, rows)]
    fits = fit_presets(specs, [nominal_parameters(h) for h in hrows], trains, (preset,),
                       solver=solver, **options)
    return [(f[0].params.numpy().copy(), predict(f[0].params, s, d)["error_mrad"].to_numpy())
            for f, s, d in zip(fits, specs, data)]


def fit_coarse_time_split(helio: pd.DataFrame, rows_of: dict, preset_of: dict, *, solver: str,
                          batch_size: int, options: dict, workers=1, scheduler="local",
                          dask_address=None) -> dict:
    """The selected preset of every heliostat with a time split, fitted again on the time
    split's training rows with fit-coarse's solver and ``options`` (loss, f_scale_mrad,
    robust_start).

    Parameters
    ----------
    helio : heliostats.parquet indexed by heliostat id.
    rows_of : heliostat -> its rows (with the ``time_split`` column), in fit-coarse's order.
    preset_of : heliostat -> its selected preset.

    Returns
    -------
    heliostat -> (params (28,) numpy, error_mrad (N,) of every row in ``rows_of``'s order).
    """
    ids = [h for h in sorted(preset_of) if time_labels_of(rows_of[h]) is not None]
    groups: dict = {}
    for hid in ids:
        key = (str(helio.loc[hid, "kinematic_type"]), str(helio.loc[hid, "actuator_type"]),
               preset_of[hid])
        groups.setdefault(key, []).append(hid)
    chunks = []
    for key in sorted(groups):
        members = sorted(groups[key], key=lambda h: (int((rows_of[h][TIME_COLUMN] == "train").sum()), h))
        step = 1 if solver == "scipy" else batch_size
        chunks += [(key[2], members[i:i + step]) for i in range(0, len(members), step)]
    tasks = [(solver, [helio.loc[h].to_dict() for h in chunk], [rows_of[h] for h in chunk],
              preset, options) for preset, chunk in chunks]
    results = map_tasks(_coarse_time_task, tasks, workers=workers, scheduler=scheduler,
                        dask_address=dask_address,
                        chunks_per_worker=chunks_per_worker(solver)) if tasks else []
    return {h: r for (_, chunk), res in zip(chunks, results) for h, r in zip(chunk, res)}


def chunks_per_worker(solver: str) -> int:
    """``map_tasks``' grouping of fit-coarse's tasks: a batched task (64 heliostats) takes a
    second or more and heliostats with regimes take longer than others, so the tasks go out
    one at a time up to 16 per worker (groups of four left one worker idle for seconds at the
    end of a 2,000-heliostat field); scipy's tasks are single heliostats, grouped by four."""
    return 16 if solver == "batched" else 4


def attach_coarse_time(params: pd.DataFrame, preds: pd.DataFrame, fits: dict,
                       rows_of: dict) -> tuple[pd.DataFrame, pd.DataFrame]:
    """coarse_params with ``time_fitted``, ``time_val_error_mrad``, ``time_test_error_mrad`` and
    coarse_predictions with ``time_error_mrad``, on the selected preset's rows of the heliostats
    in ``fits`` (:func:`fit_coarse_time_split`); missing elsewhere."""
    params = params.assign(time_fitted=np.nan, time_val_error_mrad=np.nan,
                           time_test_error_mrad=np.nan)
    preds = preds.assign(time_error_mrad=np.nan)
    if not fits:
        return params, preds
    p_sel = params["selected"].to_numpy(bool)
    p_hid = params["heliostat_id"].to_numpy()
    e_sel = preds["selected"].to_numpy(bool)
    e_hid = preds["heliostat_id"].to_numpy()
    by_p = pd.Series(np.arange(len(params))).groupby(p_hid).indices
    by_e = pd.Series(np.arange(len(preds))).groupby(e_hid).indices
    tf, tv, tt = (params[c].to_numpy(float).copy() for c in
                  ("time_fitted", "time_val_error_mrad", "time_test_error_mrad"))
    te = preds["time_error_mrad"].to_numpy(float).copy()
    # the whole columns once: converted per heliostat, they would make this quadratic in the field
    p_index = params["parameter_index"].to_numpy()
    e_mid = preds["measurement_id"].astype(str).to_numpy()
    for hid, (theta, err) in fits.items():
        labels = rows_of[hid][TIME_COLUMN].to_numpy(dtype=object)
        pi = by_p[hid][p_sel[by_p[hid]]]
        order = p_index[pi]
        tf[pi] = theta[order]
        tv[pi] = _mean(err[labels == "validation"])
        tt[pi] = _mean(err[labels == "test"])
        ei = by_e[hid][e_sel[by_e[hid]]]
        # a heliostat's prediction rows of one model are in the order of its rows
        position = pd.Series(np.arange(len(labels)),
                             index=rows_of[hid]["measurement_id"].astype(str).to_numpy())
        te[ei] = err[position.loc[e_mid[ei]].to_numpy()]
    params["time_fitted"], params["time_val_error_mrad"], params["time_test_error_mrad"] = tf, tv, tt
    preds["time_error_mrad"] = te
    return params, preds


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
    torch.use_deterministic_algorithms(True, warn_only=True)
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
    figures are written, a selected hybrid's are missing.

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
        if not enabled:
            continue
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
