"""The fade of a fine model: its correction scaled down with the distance to its training rows.

A fine model (the hybrid networks, the Gaussian-process correction) learns the coarse model's
misfit where it has measurements. Far from them it has nothing to go on: a network extrapolates
whatever its last layers do there (issue 35: a CSV heliostat's hybrid was 36 % better than the
coarse model on validation rows 6 deg from training and 1.59x worse on test rows 11 deg away), a
Gaussian process returns to its prior mean only at its own length scale. The fade makes every
fine model return to the coarse model away from its data, with one rule for all of them::

    correction(x) = w(x) * correction_model(x),
    w(x) = exp(-(d_sun(x) / L_sun)^2 / 2 - (d_time(x) / L_time)^2 / 2)

- ``d_sun`` [deg]: distance of the row's sun position to the nearest training row's, Euclidean in
  the (azimuth, elevation) plane (split-knn's default metric, docs/split.md "Distances");
- ``d_time`` [days]: time outside the training rows' period, before the first or after the last
  of them (only for models with date inputs; a row without a timestamp has ``d_time = 0``, as the
  fine models give it the median time). Within the period a fine model interpolates in time
  between its rows (a GP by its own time kernel); beyond it, forward in time, is where a date
  input extrapolates;
- ``L_sun`` [deg], ``L_time`` [days]: the fade lengths, chosen on validation
  (:mod:`heliocal.pipeline.models.selection`); ``inf`` switches a distance off.

A training row has ``d_sun = d_time = 0``, so ``w = 1`` there and training is unchanged by the
fade. The distances are the flags aim reports beside its expected error (issue 33), computed once
here. :func:`fade_weights` is the one function every user of a fine model calls (the sweep's
scoring, ``fit-hybrid``, ``aim``), on the ``fade`` entry of the model's configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import pandas as pd

from ..errors import ParameterError

__all__ = [
    "Fade",
    "NO_FADE",
    "FADE_LENGTHS_DEG",
    "TIME_FADE_DAYS",
    "NETWORK_TIME_FADE_DAYS",
    "sun_distance_deg",
    "time_distance_days",
    "epoch_seconds",
    "fade_weights",
]

_DAY_S = 86400.0

#: Sun fade lengths [deg] a fine model's validation chooses from (longest first; ``inf``: no
#: fade). The kNN split's validation rows lie 4-8 deg from training, its test rows 8-20 deg
#: (docs/split.md); a length much shorter than the training rows' own spacing (about 4 deg)
#: would fade the model between its training rows.
FADE_LENGTHS_DEG = (math.inf, 16.0, 8.0)

#: Time fade length [days] of the GP correction with time: its correction of a date is faded
#: with the days outside its training period (forward in time: since the last training row).
TIME_FADE_DAYS = 30.0

#: The same for the hybrid networks (their inputs include the date).
NETWORK_TIME_FADE_DAYS = 30.0


def epoch_seconds(timestamps) -> np.ndarray:
    """UTC ``timestamps`` as seconds since 1970-01-01 (NaN where missing)."""
    ts = pd.to_datetime(pd.Series(timestamps), utc=True)
    return (ts - pd.Timestamp("1970-01-01", tz="UTC")).dt.total_seconds().to_numpy(np.float64)


def sun_distance_deg(azimuth_deg, elevation_deg, train_sun_deg) -> np.ndarray:
    """Distance [deg] of each sun position (N,) to the nearest of ``train_sun_deg`` (M, 2)
    (azimuth, elevation), Euclidean in the (azimuth, elevation) plane; ``inf`` without
    training rows."""
    az = np.asarray(azimuth_deg, np.float64).reshape(-1, 1)
    el = np.asarray(elevation_deg, np.float64).reshape(-1, 1)
    train = np.asarray(train_sun_deg, np.float64).reshape(-1, 2)
    if not len(train):
        return np.full(len(az), math.inf)
    out = np.empty(len(az))
    for start in range(0, len(az), 4096):        # (4096, M) at a time: bounded memory
        sl = slice(start, start + 4096)
        d2 = (az[sl] - train[:, 0]) ** 2 + (el[sl] - train[:, 1]) ** 2
        out[sl] = np.sqrt(d2.min(axis=1))
    return out


def time_distance_days(time_s, train_time_s) -> np.ndarray:
    """Time [days] from each time (N,) [s since 1970] to the training rows' period
    [first, last] of ``train_time_s`` (0 within it); 0 where the time is missing (the fine models
    give such rows the median time) or no training row has one."""
    t = np.asarray(time_s, np.float64).reshape(-1)
    train = np.asarray(train_time_s, np.float64).reshape(-1)
    train = train[np.isfinite(train)]
    out = np.zeros(len(t))
    ok = np.isfinite(t)
    if not len(train) or not ok.any():
        return out
    first, last = train.min(), train.max()
    out[ok] = np.maximum(0.0, np.maximum(t[ok] - last, first - t[ok])) / _DAY_S
    return out


@dataclass(frozen=True)
class Fade:
    """A fine model's fade (module docstring): lengths and the training rows it is measured from.

    Attributes
    ----------
    length_deg : sun fade length ``L_sun`` [deg]; ``inf``: no fade in sun position.
    length_days : time fade length ``L_time`` [days]; ``inf``: no fade in time (models without
        date inputs).
    train_sun_deg : (M, 2) the training rows' sun azimuth and elevation [deg].
    train_time_s : (M,) the training rows' times [s since 1970-01-01 UTC] (NaN: none).
    """

    length_deg: float
    length_days: float
    train_sun_deg: np.ndarray
    train_time_s: np.ndarray

    def __post_init__(self):
        for name in ("length_deg", "length_days"):
            v = float(getattr(self, name))
            if not v > 0:
                raise ParameterError(f"The '{name}' parameter of Fade must be a float in (0, inf]. "
                                     f"Got {v!r} instead.")

    @classmethod
    def of_rows(cls, rows: pd.DataFrame, length_deg: float = math.inf,
                length_days: float = math.inf) -> "Fade":
        """The fade of a model trained on ``rows`` (measurements.parquet rows)."""
        sun = rows[["sun_azimuth_deg", "sun_elevation_deg"]].to_numpy(np.float64)
        time = (epoch_seconds(rows["timestamp"]) if "timestamp" in rows
                else np.full(len(rows), np.nan))
        return cls(float(length_deg), float(length_days), sun, time)

    def with_lengths(self, length_deg: float, length_days: float | None = None) -> "Fade":
        """The same training rows with other lengths (``length_days`` None: kept)."""
        return Fade(float(length_deg), self.length_days if length_days is None
                    else float(length_days), self.train_sun_deg, self.train_time_s)

    def weights(self, azimuth_deg, elevation_deg, time_s=None) -> np.ndarray:
        """The fade ``w`` (N,) in (0, 1] at the given sun positions [deg] and times [s]."""
        az = np.asarray(azimuth_deg, np.float64).reshape(-1)
        z = np.zeros(len(az))
        if math.isfinite(self.length_deg):
            z += (sun_distance_deg(az, elevation_deg, self.train_sun_deg) / self.length_deg) ** 2
        if math.isfinite(self.length_days) and time_s is not None:
            z += (time_distance_days(time_s, self.train_time_s) / self.length_days) ** 2
        return np.exp(-0.5 * z)

    def weights_of_rows(self, rows: pd.DataFrame) -> np.ndarray:
        """:meth:`weights` at measurement rows (their sun angles and timestamps)."""
        time = epoch_seconds(rows["timestamp"]) if "timestamp" in rows else None
        return self.weights(rows["sun_azimuth_deg"].to_numpy(np.float64),
                            rows["sun_elevation_deg"].to_numpy(np.float64), time)

    def to_dict(self) -> dict:
        """JSON-ready (``inf`` as None; rows as lists) for a model's configuration."""
        inf_none = lambda v: None if not math.isfinite(v) else float(v)  # noqa: E731
        return {"length_deg": inf_none(self.length_deg),
                "length_days": inf_none(self.length_days),
                "train_sun_deg": np.round(self.train_sun_deg, 6).tolist(),
                "train_time_s": [None if not np.isfinite(t) else float(t)
                                 for t in self.train_time_s]}

    @classmethod
    def from_dict(cls, d: Mapping) -> "Fade":
        none_inf = lambda v: math.inf if v is None else float(v)  # noqa: E731
        return cls(none_inf(d.get("length_deg")), none_inf(d.get("length_days")),
                   np.asarray(d.get("train_sun_deg") or np.zeros((0, 2)), np.float64).reshape(-1, 2),
                   np.array([np.nan if t is None else t for t in d.get("train_time_s") or []],
                            np.float64))


#: No fade (the lengths ``inf``): what a model configuration without a ``fade`` entry means.
NO_FADE = Fade(math.inf, math.inf, np.zeros((0, 2)), np.zeros(0))


def fade_weights(config: Mapping, azimuth_deg, elevation_deg, timestamps=None) -> np.ndarray:
    """The fade (N,) of the fine model whose configuration is ``config`` (its ``fade`` entry,
    :meth:`Fade.to_dict`; none: 1 everywhere, models written before the fade) at sun positions
    [deg] and UTC ``timestamps``. The one call ``aim``, the sweep and ``fit-hybrid`` share."""
    entry = config.get("fade") if config is not None else None
    az = np.asarray(azimuth_deg, np.float64).reshape(-1)
    if not entry:
        return np.ones(len(az))
    time = None if timestamps is None else epoch_seconds(timestamps)
    return Fade.from_dict(entry).weights(az, elevation_deg, time)
