"""fit-coarse's regime-aware candidates of one heliostat beside its plain fit, and the choice
between them (:func:`regime_candidates`); the models themselves are
:mod:`heliocal.pipeline.models.regime_fit`'s, fitted one by one there or many at once by
:mod:`heliocal.pipeline.models.regime_batch`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..physics.metrics import mean_or_nan as _mean
from ..physics.parameters import PARAMETER_INDEX, HeliostatSpec
from ..runtime.process_state import one_thread
from .coarse import MeasurementBatch
from ..physics.kinematics import forward_kinematics
from .coarse import metrics_frame
from .regime_fit import MIN_VALIDATION_DAYS, REGIME_MODELS, RegimeFit, fit_regime_model

__all__ = ["CandidateSetup", "TimeCandidates", "candidate_setup", "predict_candidates",
           "regime_candidates"]


def predict_candidates(specs: Sequence[HeliostatSpec], setups: "Sequence[CandidateSetup]",
                       fits: Sequence[Sequence[RegimeFit]]) -> list[list[pd.DataFrame]]:
    """coarse_predictions' rows of every row of every heliostat for each of its fits (each row
    at its own regime's parameters; :func:`predict_rows`), with ``model``, ``heliostat_id``,
    ``split`` and ``selected`` (False) set, in one forward pass for all: per heliostat a list of
    frames in the order of its fits. The heliostats share one kinematic and actuator type."""
    from ..physics.lm import stack_specs, take_spec

    out: list[list[pd.DataFrame]] = [[] for _ in setups]
    pairs = [(h, f) for h, fs in enumerate(fits) for f in fs]
    if not pairs:
        return out
    sizes = [len(setups[h].data) for h, _ in pairs]
    params = torch.cat([f.row_parameters(setups[h].regime, setups[h].times) for h, f in pairs])
    owner = torch.as_tensor(np.repeat(np.arange(len(pairs)), sizes))
    spec = take_spec(stack_specs([specs[h] for h, _ in pairs]), owner)
    batches = [setups[h].data for h, _ in pairs]
    flat = MeasurementBatch(np.concatenate([b.measurement_id for b in batches]),
                            *(torch.cat([getattr(b, name) for b in batches])
                              for name in ("steps", "sun", "focal_spot", "target_center",
                                           "target_normal")))
    with torch.no_grad():
        normal, position = forward_kinematics(params, spec, flat.steps.unsqueeze(1))
    # the label columns of all frames at once (a string column per frame costs more than the
    # forward pass)
    frame = metrics_frame(flat, normal[:, 0], position[:, 0]).assign(
        model=np.repeat([f.name for _, f in pairs], sizes),
        heliostat_id=np.repeat([setups[h].hid for h, _ in pairs], sizes),
        split=np.concatenate([setups[h].labels for h, _ in pairs]), selected=False)
    ends = np.cumsum(sizes)
    for (h, _), a, b in zip(pairs, ends - sizes, ends):
        out[h].append(frame.iloc[a:b])
    return out


def _stamp(seconds: float) -> pd.Timestamp:
    """A drift time as a UTC timestamp (whole seconds); missing if not finite."""
    if not np.isfinite(seconds):
        return pd.NaT
    return pd.Timestamp(round(float(seconds)), unit="s", tz="UTC")


# ------------------------------------------------------------------------------------------------
# fit-coarse's candidates of one heliostat
# ------------------------------------------------------------------------------------------------
def _days(times: np.ndarray) -> int:
    """Distinct UTC days of datetime64 ``times`` (NaT not counted)."""
    return len(np.unique(times[~np.isnat(times)].astype("datetime64[D]")))


@dataclass
class CandidateSetup:
    """What the candidates of one heliostat are fitted and judged on (:func:`candidate_setup`)."""

    hid: str                  # the heliostat
    regime: np.ndarray        # (N,) regime number of each row
    labels: np.ndarray        # (N,) split label
    train: np.ndarray         # (N,) bool: training rows outside episodes (the fitted rows)
    val: np.ndarray           # (N,) bool: validation rows outside episodes (the judged rows)
    times: pd.Series          # (N,) UTC
    data: MeasurementBatch
    preset: str               # the plain fit's preset
    params: torch.Tensor      # (28,) its parameters
    free: np.ndarray          # (28,) its free mask
    plain_val: float          # its mean validation error on ``val`` [mrad]
    days: int                 # distinct UTC days of ``val``

    @property
    def eligible(self) -> bool:
        """Enough validation days to judge a candidate (:data:`MIN_VALIDATION_DAYS`)."""
        return self.days >= MIN_VALIDATION_DAYS


def candidate_setup(hid: str, rows: pd.DataFrame, regimes: pd.DataFrame, outputs: tuple,
                    max_episode_share: float, data: MeasurementBatch | None = None) -> CandidateSetup:
    """The rows, regimes and plain fit of one heliostat's candidates (arguments as
    :func:`regime_candidates`; ``data``: ``MeasurementBatch.from_frame(rows)`` if made)."""
    from .regimes import regime_arrays, utc_values

    param_rows, pred, _ = outputs
    regime, episode = regime_arrays(regimes, hid, rows["timestamp"])
    if episode.mean() > max_episode_share:
        episode = np.zeros_like(episode)
    labels = rows["split"].to_numpy()
    val = (labels == "validation") & ~episode
    chosen_rows = [r for r in param_rows if r["selected"]]
    return CandidateSetup(
        hid, regime, labels, (labels == "train") & ~episode, val,
        rows["timestamp"], MeasurementBatch.from_frame(rows) if data is None else data,
        chosen_rows[0]["preset"],
        torch.tensor([r["fitted"] for r in chosen_rows], dtype=torch.float64),
        np.array([r["free"] for r in chosen_rows], bool),
        _mean(pred["error_mrad"].to_numpy()[pred["selected"].to_numpy(bool)][val]),
        _days(utc_values(rows["timestamp"])[val]))


@dataclass
class TimeCandidates:
    """A heliostat's candidates fitted again on its time split's training rows (the same
    regimes), for the forward-in-time check of :func:`regime_candidates`.

    Attributes
    ----------
    fits : model (``offsets``, ``drift``) -> its time-split fit.
    frames : model -> :func:`predict_candidates`' frame of that fit (every row).
    labels : (N,) the rows' time split labels (None where a row has none).
    plain_val : the plain fit's time-split fit's mean error on the time split's validation rows
        outside episodes [mrad].
    val : (N,) bool, those validation rows.
    """

    fits: dict
    frames: dict
    labels: np.ndarray
    plain_val: float
    val: np.ndarray

    def val_error(self, model: str) -> float:
        """The model's time-split fit's mean validation error (NaN without that fit)."""
        frame = self.frames.get(model)
        return float("nan") if frame is None else _mean(frame["error_mrad"].to_numpy()[self.val])


def _choose(vals: Sequence[float], plain_val: float, margin: float,
            time_vals: Sequence[float], time_plain_val: float) -> int | None:
    """The candidate that replaces the plain fit (None: none does): the lowest validation error
    among those better than the plain fit's by ``margin`` (relative) and, where both have a
    time-split fit, not worse than the plain fit on the time split's validation rows."""
    best = None
    for k, (v, tv) in enumerate(zip(vals, time_vals)):
        if not (np.isfinite(v) and np.isfinite(plain_val) and v < (1.0 - margin) * plain_val):
            continue
        if np.isfinite(tv) and np.isfinite(time_plain_val) and tv > time_plain_val:
            continue   # better between the training rows, worse forward in time
        if best is None or v < vals[best]:
            best = k
    return best


def _fit_here(spec: HeliostatSpec, c: CandidateSetup, models: Sequence[str], loss: str,
              f_scale_mrad: float) -> list[RegimeFit]:
    """The candidates of one heliostat, one scipy solve per model (the scipy solver's path)."""
    fits: list[RegimeFit] = []
    with one_thread(blas=True):   # small problems: threads only add overhead and contention
        for model in models if c.eligible else ():
            fit = fit_regime_model(spec, c.preset, c.params, c.free, c.data, c.regime, c.times,
                                   c.train, model, loss=loss, f_scale_mrad=f_scale_mrad,
                                   start=fits[-1] if fits else None)
            if fit is None:
                break   # the same regimes for every model
            fits.append(fit)
    return fits


def _latest_regime(hid: str, regimes: pd.DataFrame, regime: np.ndarray) -> tuple[int, dict]:
    """The heliostat's latest regime number and each regime's time span (its segments' first
    start and last end)."""
    from .regimes import utc_values

    mine = (regimes["heliostat_id"].to_numpy() == hid) & (regimes["kind"].to_numpy() == "regime")
    seg_numbers, seg_start, seg_end = (regimes[c].array[mine] for c in ("regime", "start", "end"))
    latest = (int(seg_numbers[np.argsort(utc_values(regimes["start"])[mine], kind="stable")[-1]])
              if mine.any() else int(regime.max()))
    spans: dict = {}
    for number, start, end in zip(seg_numbers, seg_start, seg_end):
        a, b = spans.get(int(number), (start, end))
        spans[int(number)] = (min(a, start), max(b, end))
    return latest, spans


def _regime_table_rows(hid: str, fit: RegimeFit, selected: bool, numbers, spans: dict,
                       latest: int) -> list[dict]:
    """regime_params.parquet's rows of one candidate: per regime and moved parameter."""
    out = []
    for number in numbers:
        s = int(fit.source([number])[0])
        start, end = spans.get(number, (pd.NaT, pd.NaT))
        drift_stamps = ((_stamp(fit.reference_s[s]), _stamp(fit.span_s[s, 0]),
                         _stamp(fit.span_s[s, 1])) if fit.drifting else (pd.NaT,) * 3)
        for j, name in enumerate(fit.moved):
            d = fit.drifting.index(name) if name in fit.drifting else None
            out.append({
                "heliostat_id": hid, "model": fit.name, "selected": selected,
                "regime": number, "fitted_regime": int(fit.fitted[s]),
                "start": start, "end": end,
                "n_train": int(fit.n_train[s]), "parameter": name,
                "offset_rad": float(fit.offsets[s, j]),
                "value_rad": float(fit.base[PARAMETER_INDEX[name]]) + float(fit.offsets[s, j]),
                "drift_rad_per_year": float(fit.rates[s, d]) if d is not None else 0.0,
                "drift_reference": drift_stamps[0] if d is not None else pd.NaT,
                "drift_from": drift_stamps[1] if d is not None else pd.NaT,
                "drift_to": drift_stamps[2] if d is not None else pd.NaT,
                "latest": number == latest})
    return out


def _plain_time(pred: pd.DataFrame, chosen_rows: Sequence[dict]) -> tuple:
    """The selected plain fit's time-split fit: its parameters (28,) and its errors of every
    row (``time_error_mrad``; NaN without those columns)."""
    params = np.array([r.get("time_fitted", np.nan) for r in chosen_rows], float)
    sel = pred["selected"].to_numpy(bool)
    err = (pred["time_error_mrad"].to_numpy(float)[sel] if "time_error_mrad" in pred.columns
           else np.full(int(sel.sum()), np.nan))
    return params, err


def regime_candidates(hid: str, spec: HeliostatSpec, rows: pd.DataFrame, regimes: pd.DataFrame,
                      outputs: tuple, *, loss: str, f_scale_mrad: float, margin: float,
                      max_episode_share: float, models: Sequence[str] = REGIME_MODELS,
                      fits: "Sequence[RegimeFit] | None" = None,
                      setup: CandidateSetup | None = None,
                      frames: "Sequence[pd.DataFrame] | None" = None,
                      time: TimeCandidates | None = None):
    """The regime-aware candidates of one heliostat beside its plain fit, and the selection.

    Parameters
    ----------
    hid, spec, rows : the heliostat, its rows (with ``split`` and ``timestamp``) in the order of
        ``outputs``' predictions.
    regimes : regimes.parquet's rows (the detection on the plain fit's residuals).
    outputs : ``fit-coarse``'s (param rows, predictions, summary) of the heliostat.
    loss, f_scale_mrad : ``fit-coarse``'s options.
    margin : relative validation improvement a candidate needs over the plain fit (the sweep's
        rule); validation rows of detected episodes are left out of both errors. Without
        validation rows on :data:`MIN_VALIDATION_DAYS` days no candidate is fitted.
    max_episode_share : episodes' rows are left out of the fits when they hold at most this
        share of the rows (``fit-coarse``'s rule for its episode refit).
    fits : the candidates already fitted (:func:`heliocal.pipeline.models.regime_batch.
        fit_candidates_batched`, one program for many heliostats); None fits them here, one
        scipy solve per model.
    setup : :func:`candidate_setup` of these arguments, if already made.
    frames : :func:`predict_candidates` of ``fits``, if already made (for many heliostats at
        once).
    time : the candidates fitted again on the time split's training rows: a candidate is chosen
        only if it is not worse forward in time than the plain fit, and its rows get the
        time-split columns (``time_fitted``, ``time_*_error_mrad``, ``time_error_mrad``).

    Returns
    -------
    (outputs with the candidates' rows added and the selection moved to the chosen one,
    regime_params.parquet rows of the candidates)
    """
    from .regimes import utc_values

    param_rows, pred, summary = outputs
    chosen_rows = [r for r in param_rows if r["selected"]]
    c = setup or candidate_setup(hid, rows, regimes, outputs, max_episode_share)
    if fits is None:
        fits = _fit_here(spec, c, models, loss, f_scale_mrad)
    if frames is None:
        frames = predict_candidates([spec], [c], [fits])[0]
    vals = [_mean(f["error_mrad"].to_numpy()[c.val]) for f in frames]
    # a candidate that cannot be fitted on the time split (no second regime with enough rows
    # before its end) is, fitted on the past, the plain fit: it takes the plain fit's errors
    plain_time = _plain_time(pred, chosen_rows)
    time_vals = [(time.val_error(f.model) if f.model in time.fits else time.plain_val)
                 if time else float("nan") for f in fits]
    best = _choose(vals, c.plain_val, margin, time_vals,
                   time.plain_val if time else float("nan"))
    latest, spans = _latest_regime(hid, regimes, c.regime)
    stamps = utc_values(c.times)
    t_end = stamps[~np.isnat(stamps)].max(keepdims=True)   # the last row's time (datetime64)
    numbers = sorted(set(spans) | set(np.unique(c.regime).tolist()))
    new_params, out_rows, time_errors = [], [], []
    if best is not None:
        for r in param_rows:
            r["selected"] = False
        summary["selected"] = fits[best].name
    for k, (fit, frame) in enumerate(zip(fits, frames)):
        err = frame["error_mrad"].to_numpy()
        errs = {sp: _mean(err[c.labels == sp]) for sp in ("train", "validation", "test")}
        summary["presets"][fit.name] = errs
        latest_params = fit.row_parameters([latest], t_end)[0]
        t_fit = time.fits.get(fit.model) if time else None
        if t_fit is not None:
            t_params = t_fit.row_parameters([latest], t_end)[0].numpy()
            t_err = time.frames[fit.model]["error_mrad"].to_numpy()
        else:
            t_params, t_err = plain_time if time else (None, np.full(len(err), np.nan))
        time_errors.append(t_err)
        t_test = _mean(t_err[time.labels == "test"]) if time else float("nan")
        for r in chosen_rows:
            i = r["parameter_index"]
            new_params.append({**r, "preset": fit.name, "selected": k == best,
                               "fitted": float(latest_params[i]), "std_error": float("nan"),
                               "fit_iterations": fit.iterations, "fit_cost": fit.cost,
                               "fit_condition_number": fit.condition_number, "fit_status": fit.status,
                               "n_train": int(fit.n_train.sum()), "train_error_mrad": errs["train"],
                               "val_error_mrad": errs["validation"],
                               "test_error_mrad": errs["test"],
                               "time_fitted": (float(t_params[i]) if t_params is not None
                                               else float("nan")),
                               "time_val_error_mrad": time_vals[k], "time_test_error_mrad": t_test})
        out_rows += _regime_table_rows(hid, fit, k == best, numbers, spans, latest)
    summary["regime_candidates"] = {"plain_validation": c.plain_val, "validation_days": int(c.days),
                                    **{f.model: v for f, v in zip(fits, vals)},
                                    "time_plain_validation": time.plain_val if time else None,
                                    **{f"time_{f.model}": v for f, v in zip(fits, time_vals)},
                                    "selected": fits[best].model if best is not None else None}
    if frames:   # the frames as they are, then the selection (setting a column on any of them
        n_plain = len(pred)   # first made pandas' concat several times slower)
        plain_time = (pred["time_error_mrad"].to_numpy(float) if "time_error_mrad" in pred.columns
                      else np.full(n_plain, np.nan))
        pred = pd.concat([pred, *frames], ignore_index=True)
        pred["time_error_mrad"] = np.concatenate([plain_time, *time_errors])
        if best is not None:
            pred["selected"] = np.repeat([False, *(k == best for k in range(len(frames)))],
                                         [n_plain, *map(len, frames)])
    return (param_rows + new_params, pred, summary), out_rows
