"""``fit-coarse``'s rolling-origin evaluation: the next-day error of a heliostat that is
recalibrated every calibration day (:mod:`heliocal.pipeline.models.rolling` picks the origins).

At each origin the heliostat's selected preset is fitted again, with ``fit-coarse``'s solver
options, on every row measured before that day, and scores that day's rows. For a heliostat
whose selected model is regime-aware the fit takes only the rows since its latest break before
the origin (when at least :data:`~heliocal.pipeline.models.rolling.MIN_ORIGIN_ROWS` such rows
exist; else every earlier row): the latest regime's own geometry, as the regime-aware model
gives it. The breaks are those ``fit-coarse`` detected on the whole history; a break just before
an origin may not have been detectable on that day, so right after breaks this is a little
optimistic. Every row before the origin is fitted, episodes included (a plant does not know on
the day which rows will later look like an episode; the robust loss discounts them).

Each origin's fit minimises the objective of a cold fit on that origin's rows (the prior centred
on the nominal geometry, or on the robust start searched on those rows), from the previous
origin's fit (warm start), and also from the cold fit's own start where there is no previous
fit or where the warm fit leaves its rows unexplained: data residuals above
:data:`COLD_RETRY_SCALES` loss scales; the lower objective is kept (:func:`_origin_fits`). One
start alone is not enough on real heliostats with a badly wrong nominal geometry: the robust
start of a first origin's few rows, kept for every later origin, and a warm start from a poor
early fit held the Jülich log's AH33 at a mean next-day error of 164 mrad (residuals of tens of
mrad) where the cold fits of the same rows give 6.4, while a cold start alone lands AQ32's
origins in a minimum 30 times worse than the warm start's
(docs/experiments/forward-vs-nominal.md). A warm fit at the noise lands where the cold one
would (tests/test_rolling.py), so the cold start, the slower of the two, is spent where it can
change the fit. Each step is one batched Levenberg-Marquardt program per start for the
heliostats of a chunk (one kinematic type, actuator type and preset); the reference solver
(scipy) fits each origin cold, since its explicit start would also move the prior's centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..models.coarse import MeasurementBatch, fit_heliostats_batched, fit_heliostat, predict
from ..models.regime_fit import base_preset
from ..models.regimes import utc_values
from ..models.rolling import DEFAULT_MAX_ORIGINS, MIN_ORIGIN_ROWS, Origin, rolling_origins
from ..physics.parameters import HeliostatSpec, nominal_parameters
from ..runtime.parallel import map_tasks
from ..runtime.process_state import one_thread
from .coarse_prior import is_field_prior

__all__ = ["RollingChunk", "rolling_chunks", "evaluate_rolling", "add_next_day",
           "ROLLING_COLUMNS",
           "DEFAULT_MAX_ORIGINS"]

#: A warm-started origin fit whose data residuals' RMS exceeds this many loss scales
#: (``f_scale_mrad``) is fitted from the cold start too (:func:`_needs_cold_start`).
COLD_RETRY_SCALES = 3.0

#: rolling_origin.parquet's columns, in order (pipeline/artifacts/schemas.py declares them).
ROLLING_COLUMNS = ("heliostat_id", "measurement_id", "origin_date", "model", "n_train",
                   "days_since_last_row", "error_mrad")


@dataclass
class RollingChunk:
    """One task: heliostats of one kinematic type, actuator type and preset."""

    solver: str                  # fit-coarse's solver: batched or scipy
    preset: str                  # the preset refitted at every origin
    heliostats: list[dict]       # heliostats.parquet rows
    rows: list[pd.DataFrame]     # each one's rows (timestamp, measurement_id, ...)
    breaks: list[np.ndarray]     # each one's regime starts (datetime64[s]) if regime-aware
    options: dict                # loss, f_scale_mrad, robust_start
    max_origins: int
    priors: list | None = None   # each one's field prior of the preset (None: the default)
    fixed: list | None = None    # a field-prior geometry's parameters (28,): not refitted


def _origins(rows: pd.DataFrame, breaks: np.ndarray, max_origins: int) -> list[Origin]:
    """A heliostat's origins, each origin's training rows cut to its latest regime (module
    docstring)."""
    times = utc_values(rows["timestamp"]).astype("datetime64[s]")
    origins = rolling_origins(times, max_origins=max_origins)
    if not len(breaks):
        return origins
    out = []
    for o in origins:
        start = o.day.astype("datetime64[s]")
        before = breaks[breaks <= start]
        if len(before):
            recent = o.train & (times >= before.max())
            if recent.sum() >= MIN_ORIGIN_ROWS:
                o = Origin(o.day, recent, o.score, o.days_since_last_row)
        out.append(o)
    return out


def _rolling_task(chunk: RollingChunk) -> list[pd.DataFrame]:
    """Every origin of the chunk's heliostats; per heliostat its rolling_origin rows. Torch and
    the BLAS pools on one thread for the whole task (setting the BLAS limit scans the process's
    loaded libraries: once per task, not once per origin)."""
    with one_thread(blas=True):
        return _rolling_records(chunk)


def _rolling_records(chunk: RollingChunk) -> list[pd.DataFrame]:
    hrows = [pd.Series(h) for h in chunk.heliostats]
    specs = [HeliostatSpec.from_row(h) for h in hrows]
    nominals = [nominal_parameters(h) for h in hrows]
    data = [MeasurementBatch.from_frame(r) for r in chunk.rows]
    times = [utc_values(r["timestamp"]).astype("datetime64[s]") for r in chunk.rows]
    origins = [_origins(r, b, chunk.max_origins) for r, b in zip(chunk.rows, chunk.breaks)]
    priors = chunk.priors or [None] * len(hrows)
    previous: list = [None] * len(hrows)
    records: list[list] = [[] for _ in hrows]
    for j in range(max((len(o) for o in origins), default=0)):
        now = [h for h in range(len(hrows)) if len(origins[h]) > j]
        trains = [data[h].subset(origins[h][j].train) for h in now]
        if chunk.fixed is not None:
            params = [torch.as_tensor(chunk.fixed[h], dtype=torch.float64) for h in now]
        else:
            params = _origin_fits(chunk, [specs[h] for h in now], [nominals[h] for h in now],
                                  trains, [previous[h] for h in now], [priors[h] for h in now])
        for h, fitted in zip(now, params):
            o = origins[h][j]
            scored = data[h].subset(o.score)
            err = predict(fitted, specs[h], scored)["error_mrad"].to_numpy()
            last = times[h][o.train].max()
            gap_days = (times[h][o.score] - last) / np.timedelta64(1, "D")
            records[h].append(pd.DataFrame({
                "heliostat_id": str(hrows[h]["heliostat_id"]),
                "measurement_id": scored.measurement_id, "origin_date": o.day,
                "model": chunk.preset, "n_train": int(o.train.sum()),
                "days_since_last_row": gap_days.astype(float), "error_mrad": err}))
            previous[h] = fitted
    return [pd.concat(r, ignore_index=True) if r else _empty() for r in records]


def _origin_fits(chunk: RollingChunk, specs, nominals, trains, previous, priors) -> list:
    """The parameters (28,) fitted at one origin for each heliostat: the objective of a cold fit
    on its ``trains`` rows (a fresh start cache: the robust start searched on these rows),
    minimised with the batched solver from the ``previous`` origin's fit where there is one,
    and from the cold start where there is none or where the warm fit leaves its rows
    unexplained (:func:`_needs_cold_start`); with both starts the lower objective wins (module
    docstring)."""
    if chunk.solver != "batched":
        return [fit_heliostat(s, n, t, chunk.preset, start_cache={}, prior=p,
                              **chunk.options).params
                for s, n, t, p in zip(specs, nominals, trains, priors)]
    caches = [{} for _ in specs]   # a heliostat's cold fit shares its warm fit's robust start

    def fit(which, starts):
        return fit_heliostats_batched(
            [specs[k] for k in which], [nominals[k] for k in which], [trains[k] for k in which],
            chunk.preset, start_caches=[caches[k] for k in which], starts=starts,
            priors=[priors[k] for k in which], **chunk.options)

    warm = [k for k, x in enumerate(previous) if x is not None]
    best = dict(zip(warm, fit(warm, [previous[k] for k in warm]))) if warm else {}
    scale = float(chunk.options.get("f_scale_mrad", 1.0))
    cold = [k for k in range(len(specs)) if k not in best or _needs_cold_start(best[k], scale)]
    for k, c in zip(cold, fit(cold, [None] * len(cold)) if cold else []):
        if k not in best or c.cost < best[k].cost:
            best[k] = c
    return [best[k].params for k in range(len(specs))]


def _needs_cold_start(warm, f_scale_mrad: float) -> bool:
    """Whether a warm-started origin fit is also tried from the cold start: when its data
    residuals' RMS (``noise_mrad``) is above :data:`COLD_RETRY_SCALES` times the loss's scale
    ``f_scale_mrad`` (or unknown). A warm start that explains its rows to within a few loss
    scales is in the basin of those rows, and the cold start lands in the same minimum; one
    held in a poor basin by an early fit leaves residuals of tens of mrad
    (docs/experiments/forward-vs-nominal.md)."""
    return not (warm.noise_mrad <= COLD_RETRY_SCALES * f_scale_mrad)


def _empty() -> pd.DataFrame:
    return pd.DataFrame({c: pd.Series(dtype=t) for c, t in zip(
        ROLLING_COLUMNS, ("string", "string", "datetime64[s]", "string", "int64", "float64",
                          "float64"))})


def rolling_chunks(helio: pd.DataFrame, rows_of: dict, selected: dict, regimes: pd.DataFrame, *,
                   solver: str, options: dict, batch_size: int,
                   max_origins: int = DEFAULT_MAX_ORIGINS, priors: dict | None = None,
                   fixed: dict | None = None) -> list[RollingChunk]:
    """The rolling-origin tasks of a field.

    Parameters
    ----------
    helio : heliostats.parquet indexed by heliostat id.
    rows_of : heliostat -> its rows as fit-coarse fitted them.
    selected : heliostat -> its selected model's name (a preset or ``<preset>+<model>``).
    regimes : regimes.parquet (the breaks of regime-aware heliostats).
    priors : heliostat -> preset -> the field prior of its fits (fit-coarse's MAP prior, the same
        at every origin; a heliostat or preset without one: the default prior).
    fixed : heliostat -> its field-prior geometry (28,): a heliostat whose selected model is that
        geometry is not refitted, its next-day error is the geometry's.
    """
    priors, fixed = priors or {}, fixed or {}
    starts = regimes[(regimes["kind"] == "regime")
                     & regimes["cause"].isin(["detected", "renovation"])]
    breaks = {h: np.sort(utc_values(g["start"]).astype("datetime64[s]"))
              for h, g in starts.groupby("heliostat_id", sort=False)}
    groups: dict = {}
    for hid in sorted(selected):
        if "timestamp" not in rows_of[hid].columns:
            continue
        model = selected[hid]
        key = (str(helio.loc[hid, "kinematic_type"]), str(helio.loc[hid, "actuator_type"]),
               model if is_field_prior(model) else base_preset(model))
        groups.setdefault(key, []).append(hid)
    chunks = []
    step = 1 if solver == "scipy" else batch_size
    for key in sorted(groups):
        members = sorted(groups[key], key=lambda h: (len(rows_of[h]), h))
        for i in range(0, len(members), step):
            part = members[i:i + step]
            regime_aware = lambda h: "+" in selected[h] and not is_field_prior(selected[h])  # noqa: E731
            chunks.append(RollingChunk(
                solver, key[2], [helio.loc[h].to_dict() for h in part],
                [rows_of[h] for h in part],
                [breaks.get(h, np.array([], "datetime64[s]")) if regime_aware(h)
                 else np.array([], "datetime64[s]") for h in part],
                dict(options), max_origins,
                [priors.get(h, {}).get(key[2]) for h in part],
                [fixed[h] for h in part] if is_field_prior(key[2]) else None))
    return chunks


def evaluate_rolling(chunks: Sequence[RollingChunk], *, workers=1, scheduler="local",
                     dask_address=None, chunks_per_worker: int = 16) -> pd.DataFrame:
    """rolling_origin.parquet's rows of every chunk (:func:`rolling_chunks`), sorted by
    heliostat and measurement."""
    if not chunks:
        return _empty()
    results = map_tasks(_rolling_task, list(chunks), workers=workers, scheduler=scheduler,
                        dask_address=dask_address, chunks_per_worker=chunks_per_worker)
    frames = [f for part in results for f in part if len(f)]
    if not frames:
        return _empty()
    out = pd.concat(frames, ignore_index=True)
    return out.sort_values(["heliostat_id", "measurement_id"], kind="mergesort").reset_index(drop=True)


def add_next_day(summaries: Sequence[dict], rolling: pd.DataFrame) -> None:
    """Each summary's ``next_day``: the rolling-origin evaluation's origins, rows and mean
    next-day error (None without origins)."""
    by_h = dict(tuple(rolling.groupby("heliostat_id", sort=False))) if len(rolling) else {}
    for s in summaries:
        g = by_h.get(s["heliostat_id"])
        s["next_day"] = None if g is None else {
            "origins": int(g["origin_date"].nunique()), "rows": len(g),
            "mean_error_mrad": float(g["error_mrad"].mean())}
