"""What ``fit-coarse`` does with the regimes of each chunk of heliostats, in the chunk's task
(issue 17): detection on the first fit's residuals (:mod:`heliocal.pipeline.models.regimes`), the
refit of heliostats with episodes without the episodes' rows, and the regime-aware candidates of
heliostats with a break (:mod:`heliocal.pipeline.models.regime_fit`, batched by
:mod:`heliocal.pipeline.models.regime_batch`), each kept only by the sweep's margin on
validation; then each regime's error under the final model. :mod:`.fit_coarse` runs the stage.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..artifacts.schemas import REGIMES
from ..models.coarse import MeasurementBatch
from ..models.regime_batch import fit_candidates_batched
from ..models.regime_candidates import (CandidateSetup, TimeCandidates, candidate_setup,
                                        predict_candidates, regime_candidates)
from ..models.regime_fit import MIN_VALIDATION_DAYS, REGIME_MODELS, fit_regime_model
from ..models.regimes import (detect_field, detect_records, regime_of_rows,
                              residual_components_mrad, utc_values)
from ..physics.metrics import mean_or_nan as _mean
from ..physics.parameters import HeliostatSpec
from ..runtime.process_state import one_thread
from ..vocabulary import MIN_IMPROVEMENT
from .forward import time_labels_of, time_rows
from .coarse_prior import is_field_prior

__all__ = ["detect_coarse_regimes", "follow_regimes", "REGIME_STEPS", "MAX_EPISODE_SHARE",
           "EPISODE_REFIT_MIN_IMPROVEMENT", "CoarseChunk", "HeliostatResult", "ChunkResult"]


def detect_coarse_regimes(measurements: pd.DataFrame, predictions: pd.DataFrame,
                          heliostats: pd.DataFrame, **options) -> pd.DataFrame:
    """regimes.parquet's rows: :func:`heliocal.pipeline.models.regimes.detect_field` on the
    selected coarse model's residuals of the training and validation rows (test rows stay
    unseen), with each heliostat's renovation window as a known break; ``options`` go to
    :func:`~heliocal.pipeline.models.regimes.detect_regimes`. Each heliostat's detection is its
    own: the stage runs this on each chunk of heliostats in that chunk's task."""
    pred = predictions[predictions["selected"]
                       & predictions["split"].isin(["train", "validation"])]
    pred = pred[["heliostat_id", "measurement_id", "spot_offset_horizontal_m",
                 "spot_offset_vertical_m"]]
    geo = ["timestamp", *[f"{w}_{a}_m" for w in ("target", "heliostat") for a in "enu"]]
    rows = pred.merge(measurements[["heliostat_id", "measurement_id", *geo]],
                      on=["heliostat_id", "measurement_id"], how="left")
    rows["residual_horizontal_mrad"], rows["residual_vertical_mrad"] = residual_components_mrad(
        rows["spot_offset_horizontal_m"], rows["spot_offset_vertical_m"], _target_distance_m(rows))
    renovations = {str(h["heliostat_id"]): window for h in heliostats.to_dict("records")
                   if (window := _renovation(h)) is not None}
    return detect_field(rows, renovations, **options)


def _target_distance_m(rows: pd.DataFrame) -> np.ndarray:
    """Distance [m] from each row's heliostat to its target (ENU)."""
    return np.linalg.norm(
        np.column_stack([rows[f"target_{a}_m"].to_numpy(float) for a in "enu"])
        - np.column_stack([rows[f"heliostat_{a}_m"].to_numpy(float) for a in "enu"]), axis=1)


def _renovation(hrow: Mapping) -> tuple | None:
    """A heliostat's (start, end) renovation window, None without one."""
    a, b = hrow.get("renovation_start"), hrow.get("renovation_end")
    return (a, b) if pd.notna(a) or pd.notna(b) else None


def _selected_rows(pred: pd.DataFrame, rows: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, bool]:
    """The selected model's rows in a heliostat's predictions ``pred``: their mask, their
    measurement ids, and whether they come in the order of its ``rows`` (as fit_coarse's
    ``_heliostat_outputs`` and ``regime_candidates`` write them; the detection and the segment
    errors take the rows' columns as they are then)."""
    sel = pred["selected"].to_numpy(bool)
    mids = pred["measurement_id"].to_numpy()[sel]
    return sel, mids, np.array_equal(mids, rows["measurement_id"].to_numpy())


def _chunk_regimes(hrows: Sequence[dict], rows: Sequence[pd.DataFrame],
                   results: Sequence[tuple]) -> pd.DataFrame:
    """:func:`detect_coarse_regimes` of one chunk's heliostats, each from its own rows and
    first fit's predictions (whose selected model's rows come in the order of its rows, as
    fit_coarse's ``_heliostat_outputs`` writes them), without the frames and the merge of the
    field-level function (they cost more than the detection)."""
    records = []
    for h, r, (_, pred, _) in zip(hrows, rows, results):
        sel, _, in_order = _selected_rows(pred, r)
        if not in_order:   # the slow way
            records += detect_coarse_regimes(r, pred, pd.DataFrame([h])).to_dict("records")
            continue
        split = r["split"].to_numpy()
        seen = (split == "train") | (split == "validation")
        comps = residual_components_mrad(pred["spot_offset_horizontal_m"].to_numpy(float)[sel],
                                         pred["spot_offset_vertical_m"].to_numpy(float)[sel],
                                         _target_distance_m(r))
        records += detect_records(str(h["heliostat_id"]), utc_values(r["timestamp"])[seen],
                                  r["measurement_id"].to_numpy()[seen],
                                  np.column_stack(comps)[seen], _renovation(h))
    return pd.DataFrame(records, columns=[c for c in REGIMES.column_names() if c != "error_mrad"])


#: Largest share of a heliostat's rows that detected episodes may hold for them to be left out
#: of its fit (issue 17: episodes of a few days among months of normal rows).
MAX_EPISODE_SHARE = 0.25

#: Relative validation improvement (outside episodes) the fit without a heliostat's episodes
#: needs to replace its first fit: the sweep's margin rule, the one constant MIN_IMPROVEMENT. With
#: the default robust loss episodes pull a fit little, and a refit without them that is only a
#: few per cent better on 20 validation rows was as often worse on test (sample_data's BH35:
#: validation -7 %, test +11 %), so a small gain is not taken.
EPISODE_REFIT_MIN_IMPROVEMENT = MIN_IMPROVEMENT


def _selected_error(predictions: pd.DataFrame, mask: np.ndarray) -> float:
    """Mean error of the selected model on the rows ``mask`` (in the heliostat's row order);
    NaN (never better) without such rows."""
    err = predictions.loc[predictions["selected"], "error_mrad"].to_numpy()
    return _mean(err[mask]) if mask.any() else float("nan")


def _segment_errors(regimes: pd.DataFrame, ids: Sequence[str], rows: Sequence[pd.DataFrame],
                    results: Sequence[tuple]) -> pd.DataFrame:
    """One chunk's regimes with ``error_mrad``: the final selected model's mean error (per
    heliostat its rows and outputs) on the rows of every split between the segment's start and
    end (an outlier: its own row). Computed in the chunk's task, where each heliostat's rows and
    predictions are at hand in the same order (the stage's process would have to merge the
    field's predictions with the measurements' times)."""
    by_h = {}
    for hid, r, (_, pred, _) in zip(ids, rows, results):
        sel, mids, in_order = _selected_rows(pred, r)
        t = utc_values(r["timestamp"])   # (in row order, else by id)
        t = t if in_order else t[pd.Index(r["measurement_id"].to_numpy()).get_indexer(mids)]
        by_h[hid] = (t, pred["error_mrad"].to_numpy(np.float64)[sel], mids)
    starts, ends = utc_values(regimes["start"]), utc_values(regimes["end"])
    errors = np.full(len(regimes), np.nan)
    for i, (hid, kind, mid) in enumerate(zip(regimes["heliostat_id"].to_numpy(),
                                             regimes["kind"].to_numpy(),
                                             regimes["measurement_id"].to_numpy())):
        if hid in by_h:
            t, err, mids = by_h[hid]
            rows = (mids == mid) if kind == "outlier" else (t >= starts[i]) & (t <= ends[i])
            errors[i] = _mean(err[rows])
    return regimes.assign(error_mrad=errors)


#: What ``fit-coarse`` does about regimes (``run_fit_coarse(regime_steps=...)``):
#: ``candidates`` (the default: detection, the refit without episodes, the regime-aware
#: candidates) or ``detect`` (detection and the refit only).
REGIME_STEPS = ("candidates", "detect")


@dataclass
class CoarseChunk:
    """One task of ``fit-coarse``: heliostats of one kinematic and actuator type whose presets
    are fitted together (scipy: one heliostat), then what follows from their regimes."""

    solver: str                       # CoarseSolver: batched or scipy
    heliostats: list[dict]            # their heliostats.parquet rows
    rows: list[pd.DataFrame]          # each one's measurements with the split label
    presets: tuple[str, ...]          # the presets to fit
    options: dict                     # loss, f_scale_mrad, robust_start (fit_presets' keywords)
    regime_steps: str | None          # one of REGIME_STEPS; None: the presets' fits only


@dataclass
class HeliostatResult:
    """What a chunk's task returns for one heliostat."""

    outputs: tuple                    # (coarse_params rows, coarse_predictions rows, summary)
    regime_params: list[dict] = field(default_factory=list)  # its candidates' regime_params rows
    episode_flags: np.ndarray | None = None  # per row: in a left-out episode (None: no refit)
    refitted: bool = False            # fitted again without its episodes' rows
    notes: list[str] = field(default_factory=list)  # lines for the stage's log


@dataclass
class ChunkResult:
    """What a chunk's task returns: its regimes.parquet rows (None without regime steps) and
    per heliostat, in the chunk's order, its :class:`HeliostatResult`."""

    regimes: pd.DataFrame | None
    heliostats: list[HeliostatResult]


def _batches(frames: Sequence[pd.DataFrame]) -> list[MeasurementBatch]:
    """``MeasurementBatch.from_frame`` of each frame, converted in one pass over the columns (for
    small frames the per-column overhead costs more than the rows); views of one set of tensors."""
    if not frames:
        return []
    whole = MeasurementBatch.from_frame(pd.concat(list(frames), ignore_index=True))
    ends = np.cumsum([len(f) for f in frames])
    return [MeasurementBatch(*(getattr(whole, f.name)[e - len(df):e] for f in fields(whole)))
            for e, df in zip(ends, frames)]


def _selected_time_error(outputs: tuple, rows: pd.DataFrame, mask: np.ndarray) -> float:
    """Mean ``time_error_mrad`` of the selected model of a heliostat's ``outputs`` on the time
    split's validation rows where ``mask`` (N,) holds; NaN without a time split."""
    labels = time_labels_of(rows)
    if labels is None:
        return float("nan")
    pred = outputs[1]
    err = pred.loc[pred["selected"], "time_error_mrad"].to_numpy(float)
    return _mean(err[(labels == "validation") & mask])


def _time_setup(hid: str, rows: pd.DataFrame, regimes: pd.DataFrame, outputs: tuple,
                data: MeasurementBatch) -> CandidateSetup | None:
    """The candidates' setup on the time split: the time split's labels in place of the split's
    and the selected plain fit's time-split fit as the plain fit; None without a time split or
    without that fit. Its validation days are not required (it is not judged by them: it says
    how the model chosen on the kNN split does forward in time)."""
    labels = time_labels_of(rows)
    if labels is None:
        return None
    param_rows, pred, summary = outputs
    plain = [{**r, "fitted": r["time_fitted"]} for r in param_rows if r["selected"]]
    if not np.isfinite([r["fitted"] for r in plain]).all():
        return None
    setup = candidate_setup(hid, rows.assign(split=time_rows(labels)), regimes,
                            (plain, pred.assign(error_mrad=pred["time_error_mrad"]), summary),
                            MAX_EPISODE_SHARE, data)
    return dataclasses.replace(setup, days=max(setup.days, MIN_VALIDATION_DAYS))


def _time_candidates(chunk: CoarseChunk, ks: Sequence[int], specs: dict, rows: Sequence,
                     of: dict, results: Sequence, batches: dict) -> dict:
    """The regime-aware candidates of the heliostats ``ks`` of a chunk fitted again on their
    time split's training rows (batched or scipy, as the chunk): k -> :class:`TimeCandidates`."""
    ids = [str(h["heliostat_id"]) for h in chunk.heliostats]
    setups = {k: st for k in ks
              if (st := _time_setup(ids[k], rows[k], of[ids[k]], results[k], batches[k]))}
    if not setups:
        return {}
    kwargs = chunk.options
    order = sorted(setups)
    with one_thread(blas=True):
        if chunk.solver == "batched":
            fitted = fit_candidates_batched([specs[k] for k in order], [setups[k] for k in order],
                                            loss=kwargs["loss"], f_scale_mrad=kwargs["f_scale_mrad"])
        else:
            fitted = [_scipy_candidates(specs[k], setups[k], kwargs) for k in order]
        frames = predict_candidates([specs[k] for k in order], [setups[k] for k in order], fitted)
    return {k: TimeCandidates({f.model: f for f in fits},
                              {f.model: fr for f, fr in zip(fits, frs)},
                              time_labels_of(rows[k]), setups[k].plain_val, setups[k].val)
            for k, fits, frs in zip(order, fitted, frames)}


def _scipy_candidates(spec: HeliostatSpec, setup: CandidateSetup, options: dict) -> list:
    """One heliostat's candidates, one scipy solve per model (each starting from the last)."""
    fits: list = []
    for model in REGIME_MODELS:
        fit = fit_regime_model(spec, setup.preset, setup.params, setup.free, setup.data,
                               setup.regime, setup.times, setup.train, model,
                               loss=options["loss"], f_scale_mrad=options["f_scale_mrad"],
                               start=fits[-1] if fits else None)
        if fit is None:
            break
        fits.append(fit)
    return fits


def follow_regimes(chunk: CoarseChunk, outputs: Sequence[tuple], starts: Sequence,
                   fit_again: Callable) -> ChunkResult:
    """Regimes of each heliostat of a chunk on its first fit's residuals (``outputs``: per
    heliostat (param rows, prediction rows, summary); ``starts``: the batched candidates' start
    or None); heliostats with episodes fitted again without the episodes' rows (kept by the
    sweep's margin); then the regime-aware candidates of the heliostats with a break
    (``chunk.regime_steps == "candidates"``). ``fit_again`` is fit_coarse's ``_fit_chunk`` (the
    presets' fits of some of the chunk's heliostats)."""
    hrows, presets, kwargs = chunk.heliostats, chunk.presets, chunk.options
    ids = [str(h["heliostat_id"]) for h in hrows]
    regimes = _chunk_regimes(hrows, chunk.rows, outputs)
    rows, results, starts = list(chunk.rows), list(outputs), list(starts)
    flags_of: list = [None] * len(ids)
    notes: list[list[str]] = [[] for _ in ids]
    refit = []
    with_episode = set(regimes.loc[regimes["kind"] == "episode", "heliostat_id"])
    for k, hid in enumerate(ids):
        if hid not in with_episode:
            continue
        flags = regime_of_rows(regimes, hid, rows[k]["timestamp"])["episode"].to_numpy()
        # episodes are short exceptions; when they hold a large share of the rows the heliostat
        # is not "a healthy one with episodes" and its fit stays as it is
        if flags.any() and flags.mean() <= MAX_EPISODE_SHARE:
            rows[k] = rows[k].assign(episode=flags)
            flags_of[k] = flags
            refit.append(k)
    if refit:
        again, again_starts = fit_again(chunk.solver, [hrows[k] for k in refit],
                                        [rows[k] for k in refit], presets, kwargs)
        for k, res, start in zip(refit, again, again_starts):
            # the refit is a candidate: kept only if it beats the first fit by the sweep's margin
            # on the validation rows outside the episodes (the rows both fits are meant for)
            ok = (rows[k]["split"].to_numpy() == "validation") & ~flags_of[k]
            old, new = (_selected_error(r[1], ok) for r in (results[k], res))
            # forward in time: the refit may not be worse on the time split's validation rows
            t_old, t_new = (_selected_time_error(r, rows[k], ~flags_of[k])
                            for r in (results[k], res))
            forward_ok = not (np.isfinite(t_old) and np.isfinite(t_new) and t_new > t_old)
            if new < (1.0 - EPISODE_REFIT_MIN_IMPROVEMENT) * old and forward_ok:
                results[k], starts[k] = res, start
            elif not forward_ok:
                notes[k].append(f"{ids[k]}: the fit without its episodes is worse forward in "
                                f"time ({t_new:.3f} vs {t_old:.3f} mrad on the time split's "
                                "validation rows); the first fit is kept")
            else:
                notes[k].append(f"{ids[k]}: the fit without its episodes is not "
                                f"{100 * EPISODE_REFIT_MIN_IMPROVEMENT:g} % better on "
                                f"validation ({new:.3f} vs {old:.3f} mrad); the first fit is kept")
    # regime-aware candidates (per-regime offsets, drift) of heliostats with a break: each
    # replaces the fit above only if it beats it by the same margin on validation
    breaks = set(regimes.loc[regimes["cause"].isin(["detected", "renovation"]), "heliostat_id"])
    of = dict(tuple(regimes.groupby("heliostat_id", sort=False)))
    # (not on a field-prior geometry: it is not fitted to the heliostat's rows at all)
    broken = ([k for k, hid in enumerate(ids)
               if hid in breaks and not is_field_prior(results[k][2]["selected"])]
              if chunk.regime_steps == "candidates" else [])
    specs = {k: HeliostatSpec.from_row(pd.Series(hrows[k])) for k in broken}
    batches = dict(zip(broken, _batches([rows[k] for k in broken])))
    setups = {k: candidate_setup(ids[k], rows[k], of[ids[k]], results[k], MAX_EPISODE_SHARE,
                                 batches[k]) for k in broken}
    fits, frames = {}, {}
    if chunk.solver == "batched" and broken:   # the chunk is of one type: one program for all
        with one_thread(blas=True):
            fitted = fit_candidates_batched([specs[k] for k in broken],
                                            [setups[k] for k in broken], loss=kwargs["loss"],
                                            f_scale_mrad=kwargs["f_scale_mrad"],
                                            starts=[starts[k] for k in broken])
            predicted = predict_candidates([specs[k] for k in broken],
                                           [setups[k] for k in broken], fitted)
        fits, frames = dict(zip(broken, fitted)), dict(zip(broken, predicted))
    timed = _time_candidates(chunk, [k for k in broken if setups[k].eligible], specs, rows, of,
                             results, batches)
    out = []
    for k, hid in enumerate(ids):
        regime_rows: list = []
        if k in setups:
            results[k], regime_rows = regime_candidates(
                hid, specs[k], rows[k], of[hid], results[k], loss=kwargs["loss"],
                f_scale_mrad=kwargs["f_scale_mrad"], margin=EPISODE_REFIT_MIN_IMPROVEMENT,
                max_episode_share=MAX_EPISODE_SHARE, setup=setups[k], fits=fits.get(k),
                frames=frames.get(k), time=timed.get(k))
        out.append(HeliostatResult(results[k], regime_rows, flags_of[k], k in refit, notes[k]))
    return ChunkResult(_segment_errors(regimes, ids, rows, results), out)


def regimes_summary(regimes: pd.DataFrame, regime_params: pd.DataFrame,
                    refitted: Sequence[str], summaries: Sequence[dict]) -> dict:
    """fit-coarse's summary of regimes.parquet and regime_params.parquet: the breaks, episodes
    and outliers found, the heliostats fitted again without their episodes (of ``refitted``,
    those with episode rows), and the regime-aware models fitted and selected (``summaries``:
    the run's per-heliostat summaries)."""
    with_episodes = {s["heliostat_id"] for s in summaries if s.get("episode_rows")}
    return {
        "heliostats_with_breaks": int(regimes.loc[regimes["cause"].isin(
            ["detected", "renovation"]), "heliostat_id"].nunique()),
        "detected_breaks": int((regimes["cause"] == "detected").sum()),
        "renovation_breaks": int((regimes["cause"] == "renovation").sum()),
        "episodes": int((regimes["kind"] == "episode").sum()),
        "outliers": int((regimes["kind"] == "outlier").sum()),
        "refitted_without_episodes": sorted(h for h in refitted if h in with_episodes),
        "regime_models_fitted": int(regime_params["heliostat_id"].nunique()),
        "regime_models_selected": sorted(
            s["heliostat_id"] for s in summaries
            if s.get("regime_candidates", {}).get("selected"))}
