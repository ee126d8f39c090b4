"""How a heliostat's error level grows with the days since its model's last row, field-wide.

The level of :mod:`.aim_budget` is measured on held-out rows of some age (days since the model's
last row); an aim is made at another. :class:`LevelGrowth` learns from a field's rolling-origin
rows (``fit-coarse``'s next-day evaluation) how the error grows with that age, in two parts:

1. **the bins**: each heliostat's errors divided by their own root mean square, pooled over the
   field, their root mean square in bins of :data:`GROWTH_EDGES_DAYS` (a bin needs
   :data:`MIN_GROWTH_ROWS` rows of :data:`MIN_GROWTH_HELIOSTATS` heliostats, else it takes the
   one before; never decreasing): a factor on the level within the ages the rows reach;
2. **the drift beyond them**: past the age the last measured bin stands for the bins know
   nothing, and the level's variance grows linearly in the days, as a random walk's or a field
   of random steps' does, at the field's rate :func:`drift_rate_mrad2_per_day` [mrad^2/d] (no
   slope, and a flat level beyond the bins, with fewer than two measured bins).

:meth:`.aim_budget.ErrorBudget.level_at` combines them for an aim.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = ["GROWTH_EDGES_DAYS", "LevelGrowth", "MIN_GROWTH_HELIOSTATS", "MIN_GROWTH_ROWS",
           "drift_rate_mrad2_per_day", "normalised_drift_rate_per_day"]

#: Edges [d] of the bins of days since the model's last row in which :class:`LevelGrowth` is
#: measured: a day, then steps of about 3x (a calibration campaign, a week, a month, a season).
GROWTH_EDGES_DAYS = (1.0, 3.0, 10.0, 30.0, 100.0)

#: Rolling-origin rows (and heliostats) a growth bin needs; a bin with fewer takes the previous
#: bin's growth.
MIN_GROWTH_ROWS, MIN_GROWTH_HELIOSTATS = 30, 3


@dataclass(frozen=True)
class LevelGrowth:
    """How the held-out error grows with the days since a model's last row, field-wide.

    ``factor`` (len(:data:`GROWTH_EDGES_DAYS`) + 1,): the root mean square of the normalised
    rolling-origin errors (each heliostat's divided by its own root mean square) in each bin of
    days, non-decreasing (a bin below the one before takes its value); 1 everywhere without
    rolling-origin rows (no growth known: the level as measured).

    ``last_measured_days`` [d]: the age the last measured bin's factor stands for (the mean
    ``days_since_last_row`` of its rows; a bin is measured with enough rows and heliostats).
    ``drift_mrad2_per_day`` [mrad^2/d]: beyond that age, where the bins hold the factor flat, the
    level's variance keeps growing linearly in the days, as a random walk's or a field of
    independent steps' does (:meth:`.aim_budget.ErrorBudget.level_at`), at the field's rate
    :func:`drift_rate_mrad2_per_day` of all its rolling-origin rows; 0 (flat beyond) with fewer
    than two measured bins (no slope measured between ages).
    """

    factor: np.ndarray
    last_measured_days: float = float("inf")
    drift_mrad2_per_day: float = 0.0

    @classmethod
    def none(cls) -> "LevelGrowth":
        return cls(np.ones(len(GROWTH_EDGES_DAYS) + 1))

    @classmethod
    def from_rolling(cls, rolling: pd.DataFrame) -> "LevelGrowth":
        """From rolling_origin.parquet's ``heliostat_id``, ``days_since_last_row`` and
        ``error_mrad``."""
        r = rolling[["heliostat_id", "days_since_last_row", "error_mrad"]].dropna()
        if r.empty:
            return cls.none()
        rms = r.groupby("heliostat_id")["error_mrad"].transform(lambda e: np.sqrt(np.mean(e ** 2)))
        r = r[rms > 0]
        norm = (r["error_mrad"] / rms[rms > 0]).to_numpy(float)
        bins = _growth_bin(r["days_since_last_row"].to_numpy(float))
        factor = np.ones(len(GROWTH_EDGES_DAYS) + 1)
        measured = np.zeros(len(factor), bool)
        for b in range(len(factor)):
            inside = bins == b
            measured[b] = (inside.sum() >= MIN_GROWTH_ROWS
                           and r["heliostat_id"][inside].nunique() >= MIN_GROWTH_HELIOSTATS)
            factor[b] = (float(np.sqrt(np.mean(norm[inside] ** 2))) if measured[b]
                         else factor[b - 1] if b else np.nan)
        if np.isnan(factor[0]):      # too few rows in the first bin: start at the first measured
            found = factor[np.isfinite(factor)]
            factor = np.where(np.isfinite(factor), factor, found[0] if len(found) else 1.0)
        if measured.sum() < 2:
            return cls(np.maximum.accumulate(factor))
        last_bin = bins == np.flatnonzero(measured)[-1]
        return cls(np.maximum.accumulate(factor),
                   last_measured_days=float(r["days_since_last_row"][last_bin].mean()),
                   drift_mrad2_per_day=drift_rate_mrad2_per_day(r))

    def at(self, days) -> np.ndarray:
        """The growth at ``days`` (array; NaN days: the first bin's)."""
        return self.factor[_growth_bin(np.nan_to_num(np.asarray(days, float), nan=0.0))]

    def reference(self, days) -> float:
        """The growth a level measured on rows at ``days`` carries: the root mean square of
        :meth:`at` over them (the first bin's without rows)."""
        g = self.at(days)
        return float(np.sqrt(np.mean(g ** 2))) if len(g) else float(self.factor[0])

    def drift_variance_mrad2(self, days, reference_days: float) -> np.ndarray:
        """The variance [mrad^2] the level gains beyond the measured ages by ``days`` (array
        [d]): ``drift_mrad2_per_day`` times the days past both ``last_measured_days`` and
        ``reference_days`` (the days of the level's own rows, which already carry the drift up
        to them); 0 for NaN days."""
        start_days = max(self.last_measured_days, float(np.nan_to_num(reference_days)))
        beyond_days = np.maximum(np.nan_to_num(np.asarray(days, float), nan=0.0) - start_days, 0.0)
        return self.drift_mrad2_per_day * beyond_days


def drift_rate_mrad2_per_day(rolling: pd.DataFrame) -> float:
    """The field's growth of a heliostat's squared error per day [mrad^2/d] from rolling-origin
    rows (``heliostat_id``, ``days_since_last_row``, ``error_mrad``), in two named steps:

    1. :func:`normalised_drift_rate_per_day`: the relative rate [1/d], each heliostat's squared
       errors divided by their own mean, so that no heliostat's scale dominates (as the bins of
       :class:`LevelGrowth`);
    2. times the median over the heliostats of their mean squared error [mrad^2]: the rate of
       the field's typical heliostat, in absolute units, added alike to every heliostat's
       variance (a drift or a step of the geometry does not scale with a heliostat's noise).
    """
    r = rolling[["heliostat_id", "days_since_last_row", "error_mrad"]].dropna()
    if r.empty:
        return 0.0
    mean_square_mrad2 = (r["error_mrad"] ** 2).groupby(r["heliostat_id"].astype(str)).mean()
    return normalised_drift_rate_per_day(r) * float(np.median(mean_square_mrad2))


def normalised_drift_rate_per_day(rolling: pd.DataFrame) -> float:
    """The within-heliostat least-squares slope [1/d] of the normalised squared error (each
    row's ``error_mrad ** 2`` over its heliostat's mean of them) on ``days_since_last_row``,
    each heliostat's own means of both taken out (a common slope, each heliostat its own
    intercept); never negative (an error does not shrink by waiting); 0 without a spread of
    days."""
    heliostat = rolling["heliostat_id"].astype(str).to_numpy()
    days = rolling["days_since_last_row"].to_numpy(float)
    error2_mrad2 = rolling["error_mrad"].to_numpy(float) ** 2
    mean2_mrad2 = pd.Series(error2_mrad2).groupby(heliostat).transform("mean").to_numpy()
    keep = mean2_mrad2 > 0
    heliostat, days = heliostat[keep], days[keep]
    relative = error2_mrad2[keep] / mean2_mrad2[keep]
    days_centred = days - pd.Series(days).groupby(heliostat).transform("mean").to_numpy()
    relative_mean = pd.Series(relative).groupby(heliostat).transform("mean").to_numpy()
    relative_centred = relative - relative_mean
    spread = float(np.sum(days_centred ** 2))
    if spread <= 0.0:
        return 0.0
    return max(float(np.sum(days_centred * relative_centred)) / spread, 0.0)


def _growth_bin(days: np.ndarray) -> np.ndarray:
    return np.searchsorted(np.asarray(GROWTH_EDGES_DAYS), days, side="left")
