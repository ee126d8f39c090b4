"""``fit-coarse``: every heliostat's rigid-body model, each parameter preset fitted on the training
rows and the preset used downstream chosen by validation error (``--preset auto``); writes
coarse_params.parquet and coarse_predictions.parquet in one transaction. The fitting itself is
:mod:`heliocal.pipeline.models.coarse`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.incremental import carry_over_unchanged
from ..artifacts.manifests import current_transaction
from ..artifacts.paths import artifact_path
from ..artifacts.schemas import (COARSE_PARAMS, COARSE_PREDICTIONS, FIELD_PRIOR, HELIOSTATS,
                                 MEASUREMENTS, REGIME_PARAMS, REGIMES, ROLLING_ORIGIN)
from ..artifacts.store import (artifact_present, check_fresh, merge_with_previous, read_artifact,
                               write_artifact)
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..errors import FitError, check_choice, check_float, check_int
from ..models.regime_fit import base_preset, table_row_parameters
from ..models.regimes import COMPONENTS as REGIME_COMPONENTS
from ..models.regimes import detect_field
from ..models.coarse import (AUTO_PRESETS, LOSSES, SOLVERS, CoarseFit, MeasurementBatch,
                             data_degeneracy, predict)
from ..models.coarse_presets import fit_presets
from ..physics.jacobian import residual_and_jacobian
from ..physics.metrics import mean_or_nan as _mean
from ..physics.parameters import (PARAMETER_NAMES, PARAMETER_UNITS, PRESET_NAMES, HeliostatSpec,
                                  nominal_parameters)
from ..runtime.parallel import map_tasks, shared_pool, warm_up_stage
from ..runtime.process_state import restores_process_state
from .coarse_prior import (PRIOR_MODES, attach_prior_columns, finish_table, plan_field_prior,
                           prior_columns, prior_frame, summary_of, with_field_prior,
                           zero_row_outputs)
from .coarse_regimes import (REGIME_STEPS, ChunkResult, CoarseChunk, HeliostatResult,
                             detect_coarse_regimes, follow_regimes, regimes_summary)
from .increments import coarse_plan, with_previous
from .rerun import coarse_kept_summary, coarse_options
from .rolling import DEFAULT_MAX_ORIGINS, add_next_day, evaluate_rolling, rolling_chunks
from .forward import (TIME_COLUMN, chunks_per_worker, forward_guarded_choice, labels_by_row,
                      load_time_labels, time_labels_of)

__all__ = [
    "fit_heliostat_chunk",
    "run_fit_coarse",
    "load_selected_parameters",
    "fit_one_heliostat",
    "coarse_fit_options",
    "FIT_OPTIONS",
    "load_split_labels",
    "detect_coarse_regimes",
    "coarse_row_parameters",
]

log = logging.getLogger("heliocal.coarse")

# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
def load_split_labels(workdir: Path, measurements: pd.DataFrame) -> pd.Series:
    """Split label per measurement row: split.parquet's if present, else all ``train``."""
    from ..artifacts.schemas import SPLIT  # local: split.py is optional at import time

    path = artifact_path(workdir, SPLIT)
    if not artifact_present(workdir, SPLIT):
        log.warning("no %s: fitting on all measurements (run `heliocal split-knn` for honest "
                    "validation and test errors)", path)
        return pd.Series("train", index=measurements.index)
    check_fresh(workdir, SPLIT, {"measurements": MEASUREMENTS})
    split = read_artifact(workdir, SPLIT, columns=["heliostat_id", "measurement_id", "split"])
    labels = pd.Series(labels_by_row(split, measurements, "split"), index=measurements.index)
    # heliostats the split left out (too few rows) are not fitted: mark them
    return labels.fillna("excluded")


@dataclass
class _Inputs:
    """What the presets' fits of one heliostat need (:func:`_heliostat_inputs`)."""

    hid: str
    spec: HeliostatSpec
    nominal: torch.Tensor          # (28,)
    data: MeasurementBatch         # all its rows
    labels: np.ndarray             # (N,) split label
    train: MeasurementBatch        # the training rows outside episodes
    episode: np.ndarray            # (N,) bool: in a detected episode left out of the fits
    time_labels: np.ndarray | None  # (N,) time split label (None: no time split)
    time_train: MeasurementBatch | None  # the time split's training rows outside episodes


def _heliostat_inputs(hrow, rows: pd.DataFrame) -> _Inputs:
    """The inputs of one heliostat's fits.

    Rows of a detected episode (column ``episode``, if present) are left out of the training
    rows, of the time split's training rows and of the validation errors that select the
    preset."""
    spec = HeliostatSpec.from_row(hrow)
    data = MeasurementBatch.from_frame(rows)
    labels = rows["split"].to_numpy()
    episode = (rows["episode"].to_numpy(bool) if "episode" in rows.columns
               else np.zeros(len(rows), dtype=bool))
    time_labels = time_labels_of(rows)
    time_train = (None if time_labels is None
                  else data.subset((time_labels == "train") & ~episode))
    return _Inputs(str(hrow["heliostat_id"]), spec, nominal_parameters(hrow), data, labels,
                   data.subset((labels == "train") & ~episode), episode, time_labels, time_train)


def _fit_inputs(inputs: Sequence[_Inputs], presets: Sequence[str], solver: str,
                **kwargs) -> tuple[list, list]:
    """Every preset of each heliostat fitted on its training rows, and again on its time split's
    training rows where it has a time split (None elsewhere): per heliostat the two lists of
    :class:`CoarseFit` in the order of ``presets``."""
    fits = fit_presets([i.spec for i in inputs], [i.nominal for i in inputs],
                       [i.train for i in inputs], presets, solver=solver, **kwargs)
    timed = [k for k, i in enumerate(inputs) if i.time_train is not None]
    time_fits: list = [None] * len(inputs)
    if timed:
        again = fit_presets([inputs[k].spec for k in timed], [inputs[k].nominal for k in timed],
                            [inputs[k].time_train for k in timed], presets, solver=solver,
                            **kwargs)
        for k, f in zip(timed, again):
            time_fits[k] = f
    return fits, time_fits


def fit_one_heliostat(hrow: pd.Series, rows: pd.DataFrame, presets: Sequence[str], *,
                      loss: str, f_scale_mrad: float, robust_start: bool,
                      priors: dict | None = None, field_geometry: dict | None = None):
    """Fit every preset for one heliostat (scipy); returns (param rows, prediction rows, summary).
    ``priors``, ``field_geometry``: as :func:`_chunk_outputs`."""
    inputs = [_heliostat_inputs(hrow, rows)]
    fits, time_fits = _fit_inputs(inputs, presets, "scipy", loss=loss,
                                  f_scale_mrad=f_scale_mrad, robust_start=robust_start,
                                  priors=priors)
    return _heliostat_outputs(inputs[0], *with_field_prior(inputs[0], fits[0], time_fits[0],
                                                            field_geometry))[:3]


def fit_heliostat_chunk(hrows: Sequence, rows: Sequence[pd.DataFrame], presets: Sequence[str], *,
                        loss: str, f_scale_mrad: float, robust_start: bool | str) -> list[tuple]:
    """Every preset for several heliostats of one kinematic and actuator type, each preset one
    batched LM solve (:func:`fit_heliostats_batched`); per heliostat the same (param rows,
    prediction rows, summary) as :func:`fit_one_heliostat`."""
    return [out[:3] for out in _chunk_outputs(hrows, rows, presets, loss=loss,
                                              f_scale_mrad=f_scale_mrad,
                                              robust_start=robust_start)]


def _chunk_outputs(hrows, rows, presets, field_geometry: dict | None = None,
                   **kwargs) -> list[tuple]:
    """:func:`fit_heliostat_chunk`'s tuples with :func:`_heliostat_outputs`' fourth item.
    ``kwargs`` go to fit_presets (with ``priors``: the field prior of each heliostat's fits);
    ``field_geometry``: heliostat -> (model name, parameters (28,)) of its field-prior geometry,
    a candidate of its selection (:mod:`.coarse_prior`)."""
    inputs = [_heliostat_inputs(h, r) for h, r in zip(hrows, rows)]
    fits, time_fits = _fit_inputs(inputs, presets, "batched", **kwargs)
    return [_heliostat_outputs(i, *with_field_prior(i, f, t, field_geometry))
            for i, f, t in zip(inputs, fits, time_fits)]


def _preset_errors(inp: _Inputs, fit: CoarseFit, time_fit: CoarseFit | None):
    """One preset's predictions (with ``time_error_mrad``: the time split's fit's errors, NaN
    without one) and its summary of mean errors."""
    pred = predict(fit.params, inp.spec, inp.data).assign(model=fit.preset)
    err = pred["error_mrad"].to_numpy()
    t_err = (predict(time_fit.params, inp.spec, inp.data)["error_mrad"].to_numpy()
             if time_fit is not None else np.full(len(err), np.nan))
    pred["time_error_mrad"] = t_err
    t_lab = inp.time_labels if inp.time_labels is not None else np.full(len(err), None)
    outside = ~inp.episode
    summary = {"preset": fit.preset, "train": _mean(err[inp.labels == "train"]),
               "validation": _mean(err[inp.labels == "validation"]),
               "test": _mean(err[inp.labels == "test"]),
               "validation_outside_episodes": _mean(err[(inp.labels == "validation") & outside]),
               "time_validation": _mean(t_err[(t_lab == "validation") & outside]),
               "time_test": _mean(t_err[t_lab == "test"])}
    return pred, summary


def _heliostat_outputs(inp: _Inputs, fits: Sequence[CoarseFit],
                       time_fits: Sequence[CoarseFit] | None):
    """Predictions, the selection, param rows and summary of one heliostat's fits, and the
    selected fit's (residuals (n, 3), Jacobian (n, 3, 28)) on its training rows with the mask
    (N,) of those rows (the regime candidates start there; None without training rows).

    The selection (:func:`~.forward.forward_guarded_choice`): the lowest validation error
    outside detected episodes (no geometry predicts an episode's rows), unless the time split's
    fits show that preset worse forward in time than another by more than the margin; without
    validation rows the largest preset asked."""
    hid, spec, nominal, data, labels, train = (inp.hid, inp.spec, inp.nominal, inp.data,
                                               inp.labels, inp.train)
    nominal_pred = predict(nominal, spec, data).assign(model="nominal",
                                                       time_error_mrad=np.nan)
    preds, summaries = [nominal_pred], []
    for k, fit in enumerate(fits):
        pred, summary = _preset_errors(inp, fit, time_fits[k] if time_fits else None)
        preds.append(pred)
        summaries.append(summary)
    chosen = forward_guarded_choice([s["validation_outside_episodes"] for s in summaries],
                                    [s["time_validation"] for s in summaries])
    mask = (labels == "train") & ~inp.episode
    with torch.no_grad():
        start = (residual_and_jacobian(fits[chosen].params.to(torch.float64), spec, train.steps,
                                       train.sun, train.focal_spot) if len(train) else None)
    degenerate = data_degeneracy(spec, fits[chosen].params, nominal, train, jacobian=start)
    param_rows = []
    for k, (fit, s) in enumerate(zip(fits, summaries)):
        time_params = time_fits[k].params if time_fits else None
        for i, name in enumerate(PARAMETER_NAMES):
            param_rows.append({
                "heliostat_id": hid, "preset": fit.preset, "selected": k == chosen,
                "parameter_index": i, "parameter": name, "unit": PARAMETER_UNITS[name],
                "nominal": float(fit.nominal[i]), "fitted": float(fit.params[i]),
                "std_error": float(fit.std_error[i]), "free": bool(fit.free[i]),
                "determined": bool(fit.determined[i]), "fit_iterations": fit.iterations,
                "fit_cost": fit.cost, "fit_condition_number": fit.condition_number,
                "fit_status": fit.status, "fit_implausible": "; ".join(fit.implausible),
                "fit_degenerate": degenerate,
                "n_train": len(train), "train_error_mrad": s["train"],
                "val_error_mrad": s["validation"], "test_error_mrad": s["test"],
                "time_fitted": float(time_params[i]) if time_params is not None else np.nan,
                "time_val_error_mrad": s["time_validation"],
                "time_test_error_mrad": s["time_test"], **prior_columns(fit, i)})
    pred = pd.concat(preds, ignore_index=True)
    pred["heliostat_id"] = hid
    pred["split"] = np.tile(labels, len(preds))
    pred["selected"] = pred["model"] == fits[chosen].preset
    summary = {
        "heliostat_id": hid, "n_train": len(train), "selected": fits[chosen].preset,
        "nominal": {sp: _mean(nominal_pred["error_mrad"].to_numpy()[labels == sp])
                    for sp in ("train", "validation", "test")},
        "presets": {s["preset"]: {k: s[k] for k in ("train", "validation", "test")} for s in summaries},
        "implausible": {f.preset: f.implausible for f in fits if f.implausible},
        "degenerate": degenerate,
        "episode_rows": int(inp.episode.sum()),
        "wall_time_s": float(sum(f.wall_time_s for f in fits)),
    }
    return param_rows, pred, summary, (None if start is None else (*start, mask))


def load_selected_parameters(workdir: str | Path, heliostats: Sequence[str] | None = None) -> dict:
    """The selected coarse fit per heliostat from ``coarse_params.parquet``.

    Returns
    -------
    dict heliostat_id -> {"preset": str, "base_preset": str, "params": torch.Tensor (28,),
    "free": torch.BoolTensor (28,), "nominal": torch.Tensor (28,), "std_error": torch.Tensor
    (28,), "regime_table", "regimes"}: ``preset`` is the selected model (a preset, or a
    regime-aware candidate whose ``params`` are its latest regime's), ``base_preset`` the preset
    of its geometry; for a regime-aware model ``regime_table`` and ``regimes`` are its
    regime_params.parquet rows and the heliostat's regimes.parquet rows (else None), which
    :func:`coarse_row_parameters` turns into each row's parameters.
    """
    df = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats)
    df = df[df["selected"]].sort_values(["heliostat_id", "parameter_index"])
    tables = segments = {}
    if df["preset"].str.contains("+", regex=False).any():   # a regime-aware model is selected
        t = read_artifact(workdir, REGIME_PARAMS, heliostats=heliostats)
        tables = dict(tuple(t[t["selected"]].groupby("heliostat_id", sort=False)))
        r = read_artifact(workdir, REGIMES, heliostats=heliostats)
        segments = dict(tuple(r.groupby("heliostat_id", sort=False)))
    out = {}
    for hid, g in df.groupby("heliostat_id", sort=True):
        out[str(hid)] = {
            "regime_table": tables.get(hid), "regimes": segments.get(hid),
            "preset": str(g["preset"].iloc[0]),
            "base_preset": base_preset(str(g["preset"].iloc[0])),
            "params": torch.tensor(g["fitted"].to_numpy(np.float64)),
            "free": torch.tensor(g["free"].to_numpy(bool)),
            "nominal": torch.tensor(g["nominal"].to_numpy(np.float64)),
            "std_error": torch.tensor(g["std_error"].to_numpy(np.float64)),
        }
    return out


def coarse_row_parameters(selected: dict, timestamps) -> torch.Tensor:
    """Each row's coarse parameters (N, 28) under a heliostat's selected fit (an entry of
    :func:`load_selected_parameters`) at UTC ``timestamps`` (N,): the plain fit's parameters for
    every row, or a regime-aware model's parameters of the row's regime (and time)."""
    if selected.get("regime_table") is None:
        return selected["params"].expand(len(timestamps), len(PARAMETER_NAMES)).clone()
    return table_row_parameters(selected["params"], selected["regime_table"],
                                selected["regimes"], timestamps)


#: Options of ``fit-coarse`` that decide a fit (its provenance records them; the defaults of
#: :func:`run_fit_coarse` stand in for a file written before an option existed).
FIT_OPTIONS = {"solver": "batched", "loss": "soft_l1", "f_scale_mrad": 1.0, "robust_start": "auto"}


def coarse_fit_options(workdir: str | Path) -> dict:
    """The solver, loss, ``f_scale_mrad`` and robust start ``fit-coarse`` used in ``workdir``
    (from coarse_params.parquet's provenance), as keyword arguments of :func:`fit_presets`."""
    from ..artifacts.store import read_provenance

    recorded = read_provenance(artifact_path(workdir, COARSE_PARAMS)).get("options") or {}
    return {k: recorded.get(k, default) for k, default in FIT_OPTIONS.items()}


def _fit_chunk(solver: str, hrows: Sequence[dict], rows: Sequence[pd.DataFrame], presets,
               kwargs: dict) -> tuple[list[tuple], list]:
    """Every preset for the heliostats of one chunk (scipy: one by one); per heliostat (param
    rows, prediction rows, summary), and per heliostat the batched candidates' start
    (:func:`_heliostat_outputs`' fourth item; None with scipy, whose candidates start alone)."""
    if solver == "scipy":
        return ([fit_one_heliostat(pd.Series(h), r, presets, **kwargs)
                 for h, r in zip(hrows, rows)], [None] * len(hrows))
    out = _chunk_outputs([pd.Series(h) for h in hrows], rows, presets, **kwargs)
    return [o[:3] for o in out], [o[3] for o in out]


def _fit_task(chunk: CoarseChunk) -> ChunkResult:
    """One chunk of heliostats (batched: one type; scipy: one heliostat), a picklable task for
    :func:`~heliocal.pipeline.runtime.parallel.map_tasks`: the presets' fits, then what follows
    from the regimes of their residuals (:func:`.coarse_regimes.follow_regimes`), in the task, so
    that a heliostat's rows and frames go to a worker once."""
    outputs, starts = _fit_chunk(chunk.solver, chunk.heliostats, chunk.rows, chunk.presets,
                                 chunk.options)
    if chunk.regime_steps is None:
        return ChunkResult(None, [HeliostatResult(out) for out in outputs])
    return follow_regimes(chunk, outputs, starts, _fit_chunk)


#: For benchmarks only (benchmarks/regimes_cost.py): True makes fit-coarse skip everything about
#: regimes (no detection, refit or candidates; regimes.parquet empty), to measure what they cost.
#: Not an option of the stage; heliocal never sets it.
_SKIP_REGIMES = False


def _chunks_by_type(helio: pd.DataFrame, ids: Sequence[str], n_train: dict,
                    batch_size: int) -> list[list[str]]:
    """Heliostat ids in chunks for the batched solver: one kinematic and actuator type per chunk,
    similar training-row counts together (little padding). Depends only on the data, so every
    scheduler and worker count sees the same chunks (and the same numbers)."""
    chunks = []
    keys = helio.loc[list(ids), ["kinematic_type", "actuator_type"]].astype(str)
    for _, group in keys.groupby(["kinematic_type", "actuator_type"], sort=True):
        members = sorted(group.index, key=lambda h: (n_train[h], h))
        chunks += [members[i:i + batch_size] for i in range(0, len(members), batch_size)]
    return chunks


def _read_rows(workdir: Path, heliostats: Sequence[str] | None) -> tuple[pd.DataFrame, dict]:
    """(heliostats.parquet indexed by id, heliostat -> its measurements with the split and time
    split labels, without rows the split excluded) of the heliostats with training rows."""
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=heliostats)
    measurements["split"] = load_split_labels(workdir, measurements).to_numpy()
    measurements[TIME_COLUMN] = load_time_labels(workdir, measurements)
    helio = helio.set_index("heliostat_id", drop=False)
    with_train = set(measurements.loc[measurements["split"] == "train", "heliostat_id"])
    ids = [h for h in helio.index if h in with_train]   # (a scan per heliostat is O(H N))
    if not ids:
        raise FitError(f"no heliostat in {workdir} has training measurements; check split.parquet "
                       "(rerun `heliocal split-knn` with smaller --n-test/--n-val)")
    groups = dict(tuple(measurements.groupby("heliostat_id", sort=True)))
    return helio, {hid: groups[hid][groups[hid]["split"] != "excluded"] for hid in ids}


def _chunks(solver: str, helio: pd.DataFrame, rows_of: dict, batch_size: int) -> list[list[str]]:
    """The heliostats' chunks (scipy: one each; batched: :func:`_chunks_by_type`), the chunks
    with the most rows first: the longest tasks are not the last ones, so the workers finish
    together (the results come back in task order)."""
    ids = list(rows_of)
    if solver == "scipy":
        chunks = [[hid] for hid in ids]
    else:
        n_train = {hid: int((rows_of[hid]["split"] == "train").sum()) for hid in ids}
        chunks = _chunks_by_type(helio, ids, n_train, batch_size)
    chunks.sort(key=lambda chunk: -sum(len(rows_of[h]) for h in chunk))
    return chunks


@dataclass
class _FieldFits:
    """The chunks' results gathered for the field."""

    outputs: dict            # heliostat -> (coarse_params rows, coarse_predictions rows, summary)
    regimes: pd.DataFrame    # regimes.parquet
    regime_params: pd.DataFrame  # regime_params.parquet
    refitted: list[str]      # heliostats fitted again without their episodes' rows


def _collect(chunks: Sequence[list[str]], results: Sequence[ChunkResult],
             rows_of: dict) -> _FieldFits:
    """Gather the chunks' results; a heliostat refitted without its episodes gets their flags
    in ``rows_of`` (the time split's fit leaves them out too). Logs the chunks' notes."""
    outputs, found, regime_rows, refitted = {}, [], [], []
    for chunk, result in zip(chunks, results):
        if result.regimes is not None and len(result.regimes):
            found.append(result.regimes)
        for hid, h in zip(chunk, result.heliostats):
            outputs[hid] = h.outputs
            regime_rows += h.regime_params
            if h.episode_flags is not None:
                rows_of[hid] = rows_of[hid].assign(episode=h.episode_flags)
            if h.refitted:
                refitted.append(hid)
            for line in h.notes:
                log.info("%s", line)
    regimes = (pd.concat(found, ignore_index=True)
               .sort_values("heliostat_id", kind="mergesort").reset_index(drop=True)
               if found else detect_field(pd.DataFrame(columns=["heliostat_id", "timestamp",
                                                                "measurement_id",
                                                                *REGIME_COMPONENTS]))
               .assign(error_mrad=np.nan))
    return _FieldFits(outputs, regimes, pd.DataFrame(regime_rows,
                                                     columns=REGIME_PARAMS.column_names()),
                      refitted)


def _time_split_summary(preds: pd.DataFrame, rows: pd.DataFrame) -> dict | None:
    """Mean ``time_error_mrad`` of a heliostat's selected model (``preds``: its predictions) on
    each part of its time split (the model fitted again on the time split's training rows);
    None without a time split."""
    labels = time_labels_of(rows)
    if labels is None:
        return None
    mine = preds[preds["selected"].to_numpy(bool)]
    by_id = dict(zip(rows["measurement_id"].astype(str), labels))
    lab = mine["measurement_id"].astype(str).map(by_id).to_numpy(dtype=object)
    err = mine["time_error_mrad"].to_numpy(float)
    return {sp: _mean(err[lab == sp]) for sp in ("train", "validation", "test")}


def _log_fit_warnings(summary: dict) -> None:
    """A heliostat's warnings: degenerate training data, an implausible selected fit."""
    if summary["degenerate"]:
        log.warning("%s: degenerate training data: %s; its errors say nothing about accuracy "
                    "(calibrate it at more sun positions)", summary["heliostat_id"],
                    summary["degenerate"])
    for name, items in summary["implausible"].items():
        if name == summary["selected"]:
            log.warning("%s: the nominal geometry needed a large correction (%s)",
                        summary["heliostat_id"], "; ".join(items))


def _write_outputs(workdir: Path, tables: dict, heliostats: Sequence[str] | None,
                   opts: dict) -> None:
    """Write fit-coarse's four artifacts. A partial run keeps the other heliostats' fits when the
    previous run read the same inputs (artifacts.merge_with_previous); the inputs are recorded
    as they were read."""
    if heliostats:
        replaced = lambda old: old["heliostat_id"].isin(set(heliostats))  # noqa: E731
        tables = {schema: merge_with_previous(workdir, schema, df, replaced)
                  for schema, df in tables.items()}
    for schema, df in tables.items():
        write_artifact(df, workdir, schema, stage="fit-coarse", options=opts)


def _prior_plan(workdir: Path, presets, prior: str, prior_from, **fit_options):
    """The run's field prior (:func:`~.coarse_prior.plan_field_prior`), estimated from the whole
    field (a partial run's fits are a full run's) on every row that is no heliostat's test row
    (rows the split skipped included: a plant's history; a heliostat's own rows never enter its
    own prior, :mod:`~heliocal.pipeline.models.field_prior`). Logs what it does not cover."""
    helio = read_artifact(workdir, HELIOSTATS).set_index("heliostat_id", drop=False)
    known: dict = {}
    if prior != "none" and prior_from is None:
        measurements = read_artifact(workdir, MEASUREMENTS)
        labels = load_split_labels(workdir, measurements).to_numpy()
        rows = measurements[labels != "test"].assign(split="train")
        known = dict(tuple(rows.groupby("heliostat_id", sort=True)))
    plan = plan_field_prior(helio, known, presets, mode=prior, prior_from=prior_from,
                            **fit_options)
    for line in plan.notes:
        log.warning("%s", line)
    return plan, helio


@locks_workdir("fit-coarse")
@stage_transaction("fit-coarse")
@restores_process_state
@shared_pool()
def run_fit_coarse(workdir: str | Path, *, preset: str = "auto", loss: str = "soft_l1",
                   f_scale_mrad: float = 1.0, robust_start: str = "auto",
                   heliostats: Sequence[str] | None = None, progress=None,
                   workers: int | None = 1, scheduler: str = "local",
                   dask_address: str | None = None, solver: str = "batched",
                   batch_size: int = 64, regime_steps: str = "candidates",
                   rolling_origins: int = DEFAULT_MAX_ORIGINS, prior: str = "none",
                   prior_from: str | Path | None = None, incremental: bool = False) -> dict:
    """The ``fit-coarse`` stage: fit, write coarse_params and coarse_predictions, return a summary.

    Parameters
    ----------
    preset : a preset name, or ``auto`` (all of :data:`AUTO_PRESETS`, the best on validation is
        selected per heliostat).
    loss, f_scale_mrad, robust_start : see :func:`fit_heliostat`.
    heliostats : restrict to these ids.
    progress : optional callable ``progress(done, total, heliostat_id)``.
    workers, scheduler, dask_address : where the per-heliostat fits run
        (:func:`heliocal.pipeline.runtime.parallel.map_tasks`); results do not depend on it.
    solver : ``batched`` (heliostats of one type in chunks of ``batch_size``, one vectorized
        Levenberg-Marquardt program per chunk and preset, :mod:`heliocal.pipeline.physics.lm`) or
        ``scipy`` (one :func:`scipy.optimize.least_squares` per heliostat, the reference).
    batch_size : heliostats per chunk of the batched solver (one task for ``map_tasks``).
    regime_steps : one of :data:`REGIME_STEPS`: ``candidates`` (the default) or ``detect``
        (detection and the refit without episodes, no regime-aware candidates).
    rolling_origins : origins per heliostat of the rolling-origin evaluation
        (:mod:`.rolling`; rolling_origin.parquet); 0 skips it (the artifact is then empty).
    prior : one of :data:`~.coarse_prior.PRIOR_MODES`: ``none`` (the default: the weak prior
        around the nominal geometry only), ``field`` (the field's empirical-Bayes prior where a
        group has enough well-determined heliostats, :mod:`.coarse_prior`) or ``field+spatial``
        (its mean from the nearest heliostats where that helps).
    prior_from : another work directory whose field_prior.parquet to use (``prior="field"``).
    incremental : fit only the heliostats whose rows, split or properties changed since the last
        committed run with the same options and code, and keep the others' rows of the five
        artifacts (:mod:`.increments`); otherwise (and when options or code changed) all.
    """
    check_choice(preset, "preset", "fit_coarse", ("auto",) + PRESET_NAMES)
    check_choice(loss, "loss", "fit_coarse", LOSSES)
    check_float(f_scale_mrad, "f_scale_mrad", "fit_coarse", 0.0, None, low_inclusive=False)
    check_choice(solver, "solver", "fit_coarse", SOLVERS)
    check_choice(regime_steps, "regime_steps", "fit_coarse", REGIME_STEPS)
    check_choice(prior, "prior", "fit_coarse", PRIOR_MODES)
    batch_size = check_int(batch_size, "batch_size", "fit_coarse", 1)
    rolling_origins = check_int(rolling_origins, "rolling_origins", "fit_coarse", 0)
    steps = None if _SKIP_REGIMES else regime_steps
    workdir = Path(workdir)
    opts = coarse_options(preset=preset, loss=loss, f_scale_mrad=f_scale_mrad,
                          robust_start=robust_start, solver=solver,
                          regime_steps=steps or "none", rolling_origins=rolling_origins,
                          prior=prior, prior_from=prior_from, heliostats=heliostats)
    if incremental and not heliostats and carry_over_unchanged(
            current_transaction(workdir, "fit-coarse"), opts):
        return coarse_kept_summary(workdir, preset, loss)
    warm_up_stage("fit-coarse", workers=workers, scheduler=scheduler, dask_address=dask_address)
    helio, rows_of = _read_rows(workdir, heliostats)
    presets = AUTO_PRESETS if preset == "auto" else (preset,)
    kwargs = {"loss": loss, "f_scale_mrad": f_scale_mrad, "robust_start": robust_start}
    plan, field = _prior_plan(workdir, presets, prior, prior_from, solver=solver, options=kwargs,
                              batch_size=batch_size, workers=workers, scheduler=scheduler,
                              dask_address=dask_address)
    with_rows = set(rows_of)
    increment = coarse_plan(workdir, helio, rows_of, opts, incremental, heliostats,
                            priors=prior_frame(plan, rows_of))
    if increment is not None and increment.partial:
        rows_of = {h: rows_of[h] for h in increment.compute}
    ids = list(rows_of)
    chunks = _chunks(solver, helio, rows_of, batch_size)
    tasks = [CoarseChunk(solver, [helio.loc[h].to_dict() for h in chunk],
                         [rows_of[h] for h in chunk], presets,
                         dict(kwargs, **plan.options_for(chunk)), steps) for chunk in chunks]
    chunk_results = map_tasks(_fit_task, tasks, workers=workers, scheduler=scheduler,
                              dask_address=dask_address,
                              progress=(lambda done, total: progress(done, total, None))
                              if progress else None,
                              chunks_per_worker=chunks_per_worker(solver)) if tasks else []
    fits = _collect(chunks, chunk_results, rows_of)
    all_params, all_preds, summaries = [], [], []
    for hid in ids:
        params, preds, summary = fits.outputs[hid]
        _log_fit_warnings(summary)
        summary["time_split"] = _time_split_summary(preds, rows_of[hid])
        all_params += params
        all_preds.append(preds)
        summaries.append(summary)
    zero_rows, zero_ids = zero_row_outputs(field, plan, with_rows, heliostats)
    params = attach_prior_columns(pd.DataFrame(all_params + zero_rows,
                                               columns=COARSE_PARAMS.column_names()
                                               if not all_params + zero_rows else None), plan)
    preds = (pd.concat(all_preds, ignore_index=True) if all_preds
             else pd.DataFrame(columns=COARSE_PREDICTIONS.column_names()))
    rolling = evaluate_rolling(
        rolling_chunks(helio, rows_of, {s["heliostat_id"]: s["selected"] for s in summaries},
                       fits.regimes, solver=solver, options=kwargs, batch_size=batch_size,
                       max_origins=rolling_origins, priors=plan.priors,
                       fixed={h: g[1] for h, g in plan.geometry.items()})
        if rolling_origins else [],
        workers=workers, scheduler=scheduler, dask_address=dask_address,
        chunks_per_worker=chunks_per_worker(solver))
    add_next_day(summaries, rolling)
    tables = {schema: with_previous(workdir, schema, df, increment)
              for schema, df in {COARSE_PARAMS: params, COARSE_PREDICTIONS: preds,
                                 REGIMES: fits.regimes, REGIME_PARAMS: fits.regime_params,
                                 ROLLING_ORIGIN: rolling}.items()}
    _write_outputs(workdir, tables, heliostats, opts)
    table = finish_table(plan, field, tables[COARSE_PARAMS], tables[COARSE_PREDICTIONS])
    write_artifact(table, workdir, FIELD_PRIOR, stage="fit-coarse", options=opts)
    return {"workdir": str(workdir), "preset": preset, "loss": loss, "heliostats": summaries,
            "regimes": regimes_summary(fits.regimes, fits.regime_params, fits.refitted, summaries),
            "field_prior": summary_of(plan, table, zero_ids),
            "incremental": increment.summary() if increment is not None else None}
