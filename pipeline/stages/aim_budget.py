"""How far off an aim is expected to be: each heliostat's error budget.

An aim's ``expected_error_mrad`` is the root mean square error [mrad] that a camera-target
measurement of that aim would show (the angle between the mirror normal the model set and the
one the spot reveals, as ``error_mrad`` everywhere in heliocal). Two parts add in quadrature:

* **the parameters' uncertainty at this sun position**: the coarse fit's posterior covariance
  ``C`` on the training rows its parameters rest on, through the aim's Jacobian ``J_a``:
  ``trace(J_a C J_a^T)`` (:mod:`heliocal.pipeline.models.uncertainty`). It grows where the sun
  is far from the training rows' sun positions and with few rows.
* **the level**: the root mean square error of rows the model had not seen
  (:func:`error_level_mrad`), measured as a plant would meet them, from the sources of
  :data:`LEVEL_SOURCES` with at least :data:`MIN_LEVEL_ROWS` rows: the larger level of the two
  measured forward in time (:data:`FORWARD_SOURCES`: fit-coarse's rolling-origin (next-day)
  rows, a day or a few after their fits, and the time split's validation rows of the same model
  fitted on the time split's training rows, weeks or months after; compared at equal age
  through the growth below), else the kNN validation rows, else the training rows' noise
  (:func:`robust_noise_mrad` times ``sqrt(2)``: two components of a normal's error carry the
  noise). It holds what the covariance cannot see:
  the measurement noise, drift and steps between calibration days, model error.

The level grows with the time since the model's last row (re-mounting, drift, seasons the rows
did not see): :class:`.aim_growth.LevelGrowth` learns from the field's rolling-origin rows how
the error of a fitted model grows with ``days_since_last_row`` (each heliostat's errors divided
by their own root mean square, pooled over the field, in bins of
:data:`.aim_growth.GROWTH_EDGES_DAYS`, never decreasing with time), and an aim's level is the
source's level times the growth at the aim's days over the growth at the days of the rows the
level was measured on (:meth:`ErrorBudget.level_at`). Beyond the age of the last bin with enough
rows the bins know nothing, and the level's variance grows linearly in the days past it (or past
the level's own rows, if later), as a random walk's or a field of random steps' does, at the
field's rate (:func:`.aim_growth.drift_rate_mrad2_per_day`: the within-heliostat slope of the
rolling-origin rows' normalised squared errors on their days, times the field's median mean
squared error [mrad^2/d]); without two measured bins there is no slope and the level stays flat
beyond them.

The level is at least the noise term, so an aim never expects less than its measurements'
scatter.

**A fine model with a predictive variance** (the GP correction, :mod:`heliocal.pipeline.models.gp`)
models the coarse model's residual, which the level measured on the coarse model's held-out rows
contains: the GP's prior variance there is the part of the level it models, and after the
correction only its posterior variance (and the part of the mean the fade takes away) remains.
An aim through it expects ``sqrt(trace(J_a C J_a^T) + max(level^2 - explained, min(noise,
level^2)))`` (:func:`fine_level_mrad`), ``explained = w (2 - w) (prior - posterior)`` at the aim's
sun, time and env (:attr:`heliocal.pipeline.models.gp.GPPrediction.explained_variance_mrad2`),
``noise`` the GP's white noise of both components: the measurement scatter no correction
removes, and never more than the coarse level (a correction is not expected to make an aim
worse). Far from the GP's data (``explained`` 0) this is the coarse model's budget; the
parameters' term stays (the GP's residuals are about the fitted parameters, whose error grows
away from the training rows' sun positions where the GP's mean returns to zero). What the
variance claims is held to what the GP showed on rows it had not seen: its level never goes
below ``r`` times the coarse level, ``r`` the root mean square of the GP's errors over the
coarse model's on the same held-out rows (:func:`fine_level_ratios`: the time split's
validation rows, each model fitted on its training rows, for a forward level source; the kNN
validation rows for the ``validation`` one; at most 1). Without that floor a GP whose kernel
amplitude outgrows the residual it models (a periodic term over a whole axis, a few rows)
claims to explain more than the level holds, and expects its aims at the noise.

The nominal geometry (the fallback when a fit is worse than it, :mod:`.aim_choice`) has no
covariance; its level comes from its own validation rows.

Flags beside the number: ``sun_distance_deg``, the angle between the aim's sun and the
nearest training row's sun, and ``days_since_last_row``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch

from ..artifacts.manifests import CommittedWorkdir
from ..artifacts.schemas import MEASUREMENTS, REGIMES, ROLLING_ORIGIN, SPLIT
from ..artifacts.store import artifact_present, read_artifact
from ..models.coarse import MeasurementBatch, normal_errors_mrad, prior_sigma
from ..models.uncertainty import (ParameterCovariance, aim_jacobian, aim_variance_mrad2,
                                  covariance_from_rows, fit_row_terms)
from ..physics.parameters import HeliostatSpec
from .aim_growth import LevelGrowth

__all__ = [
    "ErrorBudget",
    "FORWARD_SOURCES",
    "GROUP_SOURCE",
    "LEVEL_SOURCES",
    "MIN_LEVEL_ROWS",
    "error_level_mrad",
    "error_budgets",
    "expected_error_mrad",
    "fine_level_mrad",
    "fine_level_ratios",
    "held_out_ratios",
    "days_since",
    "LevelGrowth",
    "sun_distance_deg",
]

#: Where a heliostat's error level comes from, in order of preference (module docstring).
LEVEL_SOURCES = ("next-day", "time-split validation", "validation", "training noise")

#: The sources measured forward in time: where both have rows the larger level counts.
FORWARD_SOURCES = ("next-day", "time-split validation")

#: The level source of a heliostat without training rows of its own: its field-prior group's
#: error of the geometry it aims with (field-prior or nominal) on the test rows of the group's
#: heliostats (field_prior.parquet: the median over them of their mean test error).
GROUP_SOURCE = "heliostats like it"

#: Held-out rows a level source needs to be used.
MIN_LEVEL_ROWS = 3

_BATCH_COLUMNS = ["heliostat_id", "measurement_id", "timestamp", "axis_1_steps", "axis_2_steps",
                  "sun_e", "sun_n", "sun_u", "focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m",
                  "target_e_m", "target_n_m", "target_u_m", "target_normal_e", "target_normal_n",
                  "target_normal_u"]


@dataclass(frozen=True)
class ErrorBudget:
    """What a heliostat's aims are expected to miss by (module docstring).

    Attributes
    ----------
    covariance : the free parameters' posterior covariance of the parameters aim uses; None for
        the nominal geometry.
    level_mrad : the held-out error level [mrad], as measured on the source's rows.
    level_source : one of :data:`LEVEL_SOURCES`, or ``nominal validation``.
    train_sun_enu : (N, 3) unit sun vectors of the training rows.
    last_row_utc : time of the heliostat's last measurement (None without one).
    growth : the field's :class:`LevelGrowth` (none: the level at every time).
    growth_reference : the growth the level's rows carry (:meth:`LevelGrowth.reference`).
    reference_days : the mean days [d] since the model's last row of the level's rows (0 for
        rows without a time: the kNN validation rows lie among the training rows).
    noise_floor_mrad : the level never goes below it (``sqrt(2)`` times the training noise).
    fine_floor_ratio : an aim through a fine model with a predictive variance never expects a
        level below this fraction of the coarse level (module docstring; 0: no held-out
        evidence of the fine model, its variance alone).
    """

    covariance: ParameterCovariance | None
    level_mrad: float
    level_source: str
    train_sun_enu: np.ndarray
    last_row_utc: pd.Timestamp | None
    growth: LevelGrowth = field(default_factory=LevelGrowth.none)
    growth_reference: float = 1.0
    noise_floor_mrad: float = 0.0
    reference_days: float = 0.0
    fine_floor_ratio: float = 0.0

    def level_at(self, days_since_last_row) -> np.ndarray:
        """(M,) the level [mrad] of aims ``days_since_last_row`` (M,) after the heliostat's last
        row: the measured level times the growth from its rows' days to the aims', and beyond
        the gaps the growth was measured on the field's drift variance added in quadrature
        (:meth:`LevelGrowth.drift_variance_mrad2`) (NaN days: the level as measured)."""
        days = np.asarray(days_since_last_row, float).reshape(-1)
        scale = np.where(np.isfinite(days), self.growth.at(days) / self.growth_reference, 1.0)
        drift_mrad2 = self.growth.drift_variance_mrad2(days, self.reference_days)
        return np.maximum(np.sqrt((self.level_mrad * scale) ** 2 + drift_mrad2),
                          self.noise_floor_mrad)


def error_level_mrad(held_out_mrad, noise_mrad: float) -> float:
    """The level [mrad]: the root mean square of the held-out errors, at least ``sqrt(2)`` times
    the training residuals' scale per component ``noise_mrad`` (NaN counts as zero).

    The root mean square, not a robust scale: the rows beyond the core (a spot detection gone
    wrong, an episode, a season the training rows did not cover) are aims a plant meets too.
    The median actual / expected of ``benchmarks/expected_error.py`` says how much smaller the
    typical aim's error is on heavy-tailed heliostats."""
    e = np.asarray(held_out_mrad, float)
    e = e[np.isfinite(e)]
    rms = float(np.sqrt(np.mean(e ** 2))) if len(e) else 0.0
    return float(max(rms, np.sqrt(2.0) * float(np.nan_to_num(noise_mrad))))


def robust_noise_mrad(spec: HeliostatSpec, params: torch.Tensor, train: MeasurementBatch,
                      n_free: int) -> float:
    """The training residuals' scale per normal component [mrad], robust to outlying rows: a
    row's error angle is Rayleigh distributed with median ``sigma sqrt(2 ln 2)`` for two
    Gaussian components of scale ``sigma``; the factor ``sqrt(2N / (2N - P))`` gives back the
    degrees of freedom the fit's ``P`` free parameters took (as
    :func:`heliocal.pipeline.models.uncertainty.coarse_covariance` does for its root mean
    square). The coarse fit's own loss (soft L1) weighs outlying rows down likewise."""
    with torch.no_grad():
        e = normal_errors_mrad(params, spec, train).numpy()
    return noise_from_errors(e, n_free)


def noise_from_errors(errors_mrad, n_free: int) -> float:
    """:func:`robust_noise_mrad` from the rows' error angles [mrad] (NaN rows left out)."""
    e = np.asarray(errors_mrad, float)
    e = e[np.isfinite(e)]
    if not len(e):
        return float("nan")
    dof = max(2 * len(e) - n_free, 1)
    return float(np.median(e) / np.sqrt(2.0 * np.log(2.0)) * np.sqrt(2 * len(e) / dof))


def _level(sources: dict[str, np.ndarray], days: dict[str, np.ndarray], noise_mrad: float,
           growth: "LevelGrowth", order: tuple = LEVEL_SOURCES) -> tuple[float, str, float]:
    """(level, source, the growth its rows carry): the first source of ``order`` with enough
    rows, except that where both forward sources (:data:`FORWARD_SOURCES`) have them the larger
    level counts, each referred to its rows' days by ``growth`` (the training noise when no
    source has enough rows)."""
    found = []
    for name in order:
        e = np.asarray(sources.get(name, ()), float)
        if np.isfinite(e).sum() < MIN_LEVEL_ROWS:
            continue
        if found and name not in FORWARD_SOURCES:
            break
        level = error_level_mrad(e, noise_mrad)
        found.append((level, name, growth.reference(days.get(name, ()))))
        if name not in FORWARD_SOURCES:
            break
    if not found:
        return error_level_mrad((), noise_mrad), LEVEL_SOURCES[-1], growth.reference(())
    return max(found, key=lambda f: f[0] / f[2])


def _held_out(wd: CommittedWorkdir, ids, known_until: pd.Series | None = None
              ) -> tuple[pd.DataFrame, pd.DataFrame, LevelGrowth]:
    """(the coarse predictions of every model with each row's kNN and time split label, the
    rolling-origin rows' errors and days of the heliostats ``ids``, the field's
    :class:`LevelGrowth`: from every heliostat's rolling-origin rows, so one heliostat's budget
    is the same alone as in the field's). ``known_until`` (heliostat -> UTC time): only the
    rolling-origin rows scored before it, for the level and the growth alike."""
    from .aim_choice import time_labelled_predictions

    pred = time_labelled_predictions(wd, ids, ["split", "model", "selected", "error_mrad",
                                               "time_error_mrad"])
    columns = ["heliostat_id", "measurement_id", "days_since_last_row", "error_mrad"]
    every = (read_artifact(wd, ROLLING_ORIGIN, columns=columns)
             if artifact_present(wd, ROLLING_ORIGIN) else pd.DataFrame(columns=columns))
    if known_until is not None:
        every = _scored_before(wd, every, known_until)
    rolling = every[every["heliostat_id"].astype(str).isin(set(map(str, ids)))]
    return pred, rolling, LevelGrowth.from_rolling(every)


def _scored_before(wd: CommittedWorkdir, rolling: pd.DataFrame, known_until: pd.Series
                   ) -> pd.DataFrame:
    """The rolling-origin rows whose measurement lies before its heliostat's ``known_until``
    (heliostats without a time there: none of their rows)."""
    keys = ["heliostat_id", "measurement_id"]
    times = read_artifact(wd, MEASUREMENTS, columns=keys + ["timestamp"])
    r = rolling.merge(times, on=keys, how="left")
    cut = r["heliostat_id"].astype(str).map(known_until.rename(index=str))
    return r[pd.to_datetime(r["timestamp"], utc=True) < pd.to_datetime(cut, utc=True)]


def _grouped(keys, values) -> dict[str, np.ndarray]:
    """``values`` (N,) split by heliostat ``keys`` (N,), each heliostat's in their order."""
    keys = np.asarray(pd.Series(keys, dtype=object).astype(str))
    values = np.asarray(values)
    order = np.argsort(keys, kind="stable")
    keys, values = keys[order], values[order]
    bounds = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1], True]) if len(keys) else [0]
    return {keys[a]: values[a:b] for a, b in zip(bounds[:-1], bounds[1:])}


def _level_sources(pred: pd.DataFrame, rolling: pd.DataFrame, times: pd.DataFrame
                   ) -> tuple[dict[str, dict], dict[str, dict]]:
    """Per level source (and ``nominal validation``, the nominal geometry's validation rows)
    each heliostat's held-out errors (its selected model's), and per source with a time each
    heliostat's days of those rows since the model's last row: the rolling-origin rows' own;
    the time split's validation rows' since its last training row (``times``: every row's
    ``heliostat_id``, ``measurement_id`` and ``timestamp``). The kNN validation rows lie among
    the training rows (no days: the growth's first bin)."""
    p = pred[pred["selected"].astype(bool)]
    val = p[p["split"] == "validation"]
    time_val = p[p["time_split"] == "validation"]
    nominal = pred[(pred["model"] == "nominal") & (pred["split"] == "validation")]
    errors = {"next-day": _grouped(rolling["heliostat_id"], rolling["error_mrad"].to_numpy(float)),
              "time-split validation": _grouped(time_val["heliostat_id"],
                                                time_val["time_error_mrad"].to_numpy(float)),
              "validation": _grouped(val["heliostat_id"], val["error_mrad"].to_numpy(float)),
              "nominal validation": _grouped(nominal["heliostat_id"],
                                             nominal["error_mrad"].to_numpy())}
    days = {"next-day": _grouped(rolling["heliostat_id"],
                                 rolling["days_since_last_row"].to_numpy(float)),
            "time-split validation": _time_split_days(p, time_val, times)}
    return errors, days


def _time_split_days(selected: pd.DataFrame, time_val: pd.DataFrame, times: pd.DataFrame
                     ) -> dict[str, np.ndarray]:
    """heliostat -> days [d] from its time split's last training row to each of its time split's
    validation rows (in ``time_val``'s order)."""
    keys = ["heliostat_id", "measurement_id"]
    t = selected[keys + ["time_split"]].merge(times, on=keys, how="left")
    t["timestamp"] = pd.to_datetime(t["timestamp"], utc=True)
    last = t[t["time_split"] == "train"].groupby("heliostat_id")["timestamp"].max()
    v = time_val[keys].merge(times, on=keys, how="left")
    v_time = pd.to_datetime(v["timestamp"], utc=True)
    # a heliostat without training rows has no last one: NaN days (map on a dict: an empty
    # Series of times would be cast to float)
    last_time = pd.to_datetime(v["heliostat_id"].map(last.to_dict()), utc=True)
    days = ((v_time - last_time) / pd.Timedelta(days=1)).to_numpy(float)
    return _grouped(v["heliostat_id"], days)


def _heliostat_sources(sources: dict[str, dict], hid: str, nominal: bool) -> dict:
    """A heliostat's held-out errors (or days) per level source: its selected model's (or,
    ``nominal``, the nominal geometry's validation rows)."""
    if nominal:
        return {"validation": sources.get("nominal validation", {}).get(hid, ())}
    return {name: sources[name].get(hid, ()) for name in LEVEL_SOURCES[:-1] if name in sources}


def _fitted_mask(times: pd.Series, regimes: pd.DataFrame | None, selected: dict,
                 fitted_regime: int | None) -> np.ndarray:
    """Which of a heliostat's training rows (at UTC ``times``) the parameters aim uses rest on:
    all of them, or for a regime-aware model those of the regime its latest parameters were
    fitted on (all of them when none is)."""
    everything = np.ones(len(times), bool)
    if selected.get("regime_table") is None or regimes is None or fitted_regime is None:
        return everything
    seg = regimes[(regimes["kind"] == "regime") & (regimes["regime"] == fitted_regime)]
    if seg.empty:
        return everything
    t = pd.to_datetime(times, utc=True)
    inside = np.zeros(len(times), bool)
    for start, end in zip(pd.to_datetime(seg["start"], utc=True), pd.to_datetime(seg["end"], utc=True)):
        inside |= ((t >= start) & (t <= end)).to_numpy()
    return inside if inside.any() else everything


def _take(batch: MeasurementBatch, index: np.ndarray) -> MeasurementBatch:
    """The rows of ``batch`` at the integer positions ``index``, in that order."""
    i = torch.from_numpy(np.asarray(index, dtype=np.int64))
    return MeasurementBatch(batch.measurement_id[i.numpy()], batch.steps[i], batch.sun[i],
                            batch.focal_spot[i], batch.target_center[i], batch.target_normal[i])


def _fitted_regimes(regime_params: pd.DataFrame | None) -> dict[str, int]:
    """heliostat -> the regime its selected model's latest parameters were fitted on."""
    if regime_params is None:
        return {}
    p = regime_params[regime_params["selected"] & regime_params["latest"]]
    p = p.drop_duplicates("heliostat_id")        # a heliostat's first such row
    return {str(h): int(v) for h, v in zip(p["heliostat_id"], p["fitted_regime"])}


def error_budgets(workdir, specs: dict[str, HeliostatSpec], selected: dict,
                  models: dict, *, split_column: str = "split",
                  level_sources: tuple = LEVEL_SOURCES,
                  known_until: pd.Series | None = None) -> dict[str, ErrorBudget]:
    """Each heliostat's :class:`ErrorBudget`.

    Parameters
    ----------
    workdir : the work directory or its :class:`CommittedWorkdir`.
    specs : heliostat_id -> its kinematic spec.
    selected : :func:`heliocal.pipeline.stages.fit_coarse.load_selected_parameters` of them.
    models : :func:`heliocal.pipeline.stages.aim_choice.aim_models` of them (``nominal`` where
        aim falls back to the nominal geometry).
    split_column, level_sources : the training rows' label column of split.parquet and the
        level's sources in order; ``time_split`` with the time split's fit in ``selected`` and
        ``("time-split validation",)`` give the budget of the model fitted on the time split
        (how ``benchmarks/expected_error.py`` checks the budget forward in time).
    known_until : heliostat -> UTC time: the rolling-origin rows (level and growth) only as far
        as a plant had them then (:func:`.aim_calibration.calibration_rows`' forward check: before the time
        split's first test row); None: all of them.
    """
    from ..artifacts.schemas import REGIME_PARAMS

    wd = CommittedWorkdir.of(workdir)
    ids = sorted(set(specs) & set(selected))
    if not ids:
        return {}
    rows = read_artifact(wd, MEASUREMENTS, heliostats=ids, columns=_BATCH_COLUMNS)
    split = (read_artifact(wd, SPLIT, heliostats=ids,
                           columns=["heliostat_id", "measurement_id", split_column])
             .rename(columns={split_column: "split"}) if artifact_present(wd, SPLIT)
             else rows[["heliostat_id", "measurement_id"]].assign(split="train"))
    rows = rows.merge(split, on=["heliostat_id", "measurement_id"], how="left")
    pred, rolling, growth = _held_out(wd, ids, known_until)
    sources, source_days = _level_sources(pred, rolling,
                                          rows[["heliostat_id", "measurement_id", "timestamp"]])
    regimes = read_artifact(wd, REGIMES, heliostats=ids) if artifact_present(wd, REGIMES) else None
    regime_params = (read_artifact(wd, REGIME_PARAMS, heliostats=ids)
                     if artifact_present(wd, REGIME_PARAMS) else None)
    by_regime = dict(tuple(regimes.groupby("heliostat_id"))) if regimes is not None else {}
    positions = _grouped(rows["heliostat_id"], np.arange(len(rows)))
    is_train = (rows["split"] == "train").to_numpy(bool)
    times = pd.to_datetime(rows["timestamp"], utc=True)
    last = times.groupby(rows["heliostat_id"].astype(str).to_numpy()).max()
    batch, sun = MeasurementBatch.from_frame(rows), rows[["sun_e", "sun_n", "sun_u"]].to_numpy(float)
    fitted, fitted_regime, train = {}, _fitted_regimes(regime_params), {}
    for hid in ids:
        idx = positions.get(hid, np.zeros(0, np.int64))
        train[hid] = idx[is_train[idx]]
        if models.get(hid, {}).get("model") != "nominal" and len(train[hid]):
            keep = _fitted_mask(times.iloc[train[hid]], by_regime.get(hid), selected[hid],
                                fitted_regime.get(hid))
            fitted[hid] = _take(batch, train[hid][keep])
    covariances = _covariances(specs, selected, fitted)
    groups = _group_levels(wd, [h for h in ids if not len(train[h])])
    fine = fine_level_ratios(wd, [h for h in ids if models.get(h, {}).get("model") == "gp"
                                  and models[h].get("source") == "sweep"], pred)
    out = {}
    for hid in ids:
        nominal = models.get(hid, {}).get("model") == "nominal"
        if hid in groups:
            out[hid] = _group_budget(groups[hid], nominal, sun[train[hid]], last.get(hid, pd.NaT))
            continue
        covariance = covariances.get(hid)
        noise = covariance.noise_mrad if covariance is not None else float("nan")
        grows = LevelGrowth.none() if nominal else growth   # no fit whose age could grow
        days = _heliostat_sources(source_days, hid, nominal)
        level, source, reference = _level(_heliostat_sources(sources, hid, nominal), days,
                                          noise, grows, level_sources)
        if nominal:
            source = "nominal validation" if source == "validation" else source
        latest = last.get(hid, pd.NaT)
        out[hid] = ErrorBudget(covariance, level, source, sun[train[hid]],
                               None if pd.isna(latest) else latest, growth=grows,
                               growth_reference=reference,
                               noise_floor_mrad=error_level_mrad((), noise),
                               reference_days=_mean_days(days.get(source, ())),
                               fine_floor_ratio=_fine_floor(fine.get(hid, {}), source))
    return out


def fine_level_ratios(workdir, heliostats, pred: pd.DataFrame | None = None
                      ) -> dict[str, dict[str, float]]:
    """heliostat -> {``validation``, ``time-split validation``: the root mean square of the
    sweep's selected model's errors over the coarse model's on the same held-out rows, at most
    1 (NaN: fewer than :data:`MIN_LEVEL_ROWS` rows with both)}: on the kNN validation rows, and
    on the time split's validation rows with both models fitted on its training rows
    (selected_predictions.parquet ``error_mrad`` / ``time_error_mrad`` against
    coarse_predictions.parquet's selected preset; ``pred``: the latter with both split labels,
    as :func:`_held_out` reads them). Module docstring."""
    from ..artifacts.schemas import SELECTED_PREDICTIONS
    from .aim_choice import time_labelled_predictions

    wd = CommittedWorkdir.of(workdir)
    if not heliostats or not artifact_present(wd, SELECTED_PREDICTIONS):
        return {}
    keys = ["heliostat_id", "measurement_id"]
    if pred is None:
        pred = time_labelled_predictions(wd, heliostats, ["split", "model", "selected",
                                                          "error_mrad", "time_error_mrad"])
    coarse = pred[pred["selected"].astype(bool)
                  & pred["heliostat_id"].astype(str).isin(set(map(str, heliostats)))]
    fine = read_artifact(wd, SELECTED_PREDICTIONS, heliostats=list(heliostats),
                         columns=keys + ["error_mrad", "time_error_mrad"])
    return held_out_ratios(coarse.merge(fine, on=keys, suffixes=("_coarse", "_fine")))


def held_out_ratios(both: pd.DataFrame) -> dict[str, dict[str, float]]:
    """:func:`fine_level_ratios` of the rows ``both``: per heliostat and measurement its
    ``split`` and ``time_split`` labels and ``error_mrad`` and ``time_error_mrad`` of the coarse
    model (suffix ``_coarse``) and the fine one (``_fine``)."""
    return {str(hid): {"validation": _rms_ratio(g[g["split"] == "validation"], "error_mrad"),
                       "time-split validation": _rms_ratio(g[g["time_split"] == "validation"],
                                                           "time_error_mrad")}
            for hid, g in both.groupby("heliostat_id")}


def _rms_ratio(rows: pd.DataFrame, column: str) -> float:
    """min(1, RMS(fine) / RMS(coarse)) of ``column`` on the rows where both are finite."""
    f, c = rows[f"{column}_fine"].to_numpy(float), rows[f"{column}_coarse"].to_numpy(float)
    ok = np.isfinite(f) & np.isfinite(c)
    if ok.sum() < MIN_LEVEL_ROWS or not np.any(c[ok] > 0):
        return float("nan")
    return float(min(1.0, np.sqrt(np.mean(f[ok] ** 2) / np.mean(c[ok] ** 2))))


def _fine_floor(ratios: dict[str, float], source: str) -> float:
    """The :attr:`ErrorBudget.fine_floor_ratio` of a level ``source``: the ratio of the rows
    like it (a forward source's: the time split's validation rows; else the kNN validation
    rows'), the other where it has none, 0 without either."""
    order = (("time-split validation", "validation") if source in FORWARD_SOURCES
             else ("validation", "time-split validation"))
    for name in order:
        r = ratios.get(name, float("nan"))
        if np.isfinite(r):
            return float(r)
    return 0.0


def _mean_days(days) -> float:
    """The mean [d] of a level source's rows' days (0 without any: rows among the training
    rows)."""
    d = np.asarray(days, float)
    d = d[np.isfinite(d)]
    return float(d.mean()) if len(d) else 0.0


def _group_levels(wd: CommittedWorkdir, ids) -> dict[str, dict]:
    """heliostat -> its field-prior group's errors (aim_choice's reading of field_prior.parquet)
    for the heliostats ``ids`` without training rows whose group has them measured."""
    from .aim_choice import group_prior_errors

    if not ids:
        return {}
    every = group_prior_errors(wd)
    return {h: every[h] for h in ids if h in every
            and np.isfinite([every[h]["expected_error_mrad"], every[h]["nominal_error_mrad"]]).all()}


def _group_budget(group: dict, nominal: bool, train_sun: np.ndarray, latest) -> ErrorBudget:
    """The budget of a heliostat without training rows: no covariance of its own, the level its
    group measured for the geometry it aims with (:data:`GROUP_SOURCE`), no growth (the
    geometry is no fit that ages)."""
    level = group["nominal_error_mrad"] if nominal else group["expected_error_mrad"]
    return ErrorBudget(None, float(level), GROUP_SOURCE, train_sun,
                       None if pd.isna(latest) else latest)


def _covariances(specs: dict, selected: dict, fitted: dict[str, MeasurementBatch]
                 ) -> dict[str, ParameterCovariance]:
    """Each heliostat's posterior covariance on its ``fitted`` rows with the robust noise scale
    (:func:`robust_noise_mrad`): :func:`heliocal.pipeline.models.uncertainty.coarse_covariance`,
    its chain evaluated for all heliostats in batches (:func:`fit_row_terms`)."""
    ids = list(fitted)
    terms = fit_row_terms([specs[h] for h in ids], [selected[h]["params"] for h in ids],
                          [fitted[h] for h in ids])
    out = {}
    for hid, t in zip(ids, terms):
        free_idx = np.flatnonzero(selected[hid]["free"].numpy())
        r, j = t.finite(free_idx)
        out[hid] = covariance_from_rows(
            r, j, free_idx, prior_sigma(selected[hid]["nominal"])[free_idx],
            noise_mrad=noise_from_errors(t.error_mrad, len(free_idx)))
    return out


def fine_level_mrad(level_mrad, explained_mrad2=0.0, noise_mrad2=0.0,
                    floor_ratio=0.0) -> np.ndarray:
    """(M,) the level [mrad] of aims through a fine model with a predictive variance:
    ``sqrt(max(level^2 - explained, (floor_ratio level)^2, min(noise, level^2)))`` for the
    coarse level ``level_mrad`` (M,) [mrad], the variance the correction is expected to remove
    ``explained_mrad2`` (M,) [mrad^2], its measurement noise ``noise_mrad2`` [mrad^2] (both
    components) and :attr:`ErrorBudget.fine_floor_ratio` (module docstring). ``explained`` 0
    (the coarse model, a fine model without a variance) gives the level unchanged."""
    level2 = np.asarray(level_mrad, float) ** 2
    floor = np.maximum(np.minimum(np.asarray(noise_mrad2, float), level2),
                       np.asarray(floor_ratio, float) ** 2 * level2)
    return np.sqrt(np.maximum(level2 - np.asarray(explained_mrad2, float), floor))


def expected_error_mrad(budget: ErrorBudget, spec: HeliostatSpec, params: torch.Tensor,
                        steps: torch.Tensor, sun: torch.Tensor, aim_point_enu: torch.Tensor,
                        days_since_last_row=None, *, explained_mrad2=0.0,
                        fine_noise_mrad2=0.0) -> np.ndarray:
    """(M,) expected error [mrad] of aims at ``steps`` (M, 2) for unit sun vectors ``sun`` (M, 3)
    and aim points (M, 3) [m ENU] with parameters ``params`` (28,): ``sqrt(trace(J_a C J_a^T)
    + level^2)`` (module docstring), the level at ``days_since_last_row`` (M,) [d] (None: as
    measured), through a fine model's predictive variance (``explained_mrad2`` (M,) and
    ``fine_noise_mrad2`` [mrad^2]: :func:`fine_level_mrad`; 0: the coarse model's); NaN where
    the chain is not finite. With each aim's own parameters (``params`` (M, 28)) the aims come
    as batches of one: ``steps`` (M, 1, 2), ``sun`` and ``aim_point_enu`` (M, 1, 3)."""
    variance = np.zeros(len(steps))
    if budget.covariance is not None:
        jac = aim_jacobian(spec, params, budget.covariance.free_idx, steps, sun, aim_point_enu)
        variance = aim_variance_mrad2(jac.reshape(-1, *jac.shape[-2:]), budget.covariance)
    days = np.full(len(steps), np.nan) if days_since_last_row is None else days_since_last_row
    level = fine_level_mrad(budget.level_at(days), explained_mrad2, fine_noise_mrad2,
                            budget.fine_floor_ratio)
    return np.sqrt(variance + level ** 2)


def days_since(budget: ErrorBudget, time_utc) -> float:
    """Days [d] from the heliostat's last row to ``time_utc`` (NaN without either)."""
    if time_utc is None or budget.last_row_utc is None:
        return float("nan")
    return float((pd.Timestamp(time_utc) - budget.last_row_utc) / pd.Timedelta(days=1))


def sun_distance_deg(budget: ErrorBudget, sun_enu: np.ndarray) -> np.ndarray:
    """(M,) angle [deg] between each sun vector (M, 3) and the nearest training row's sun (NaN
    without training rows)."""
    sun_enu = np.asarray(sun_enu, float).reshape(-1, 3)
    if not len(budget.train_sun_enu):
        return np.full(len(sun_enu), np.nan)
    unit = lambda v: v / np.linalg.norm(v, axis=1, keepdims=True)  # noqa: E731
    cos = unit(sun_enu) @ unit(budget.train_sun_enu).T
    return np.degrees(np.arccos(np.clip(cos.max(axis=1), -1.0, 1.0)))
