"""Rolling-origin (prequential) evaluation: what a plant that keeps calibrating sees.

A heliostat's calibration days are walked in time order. At each *origin* (a calibration day)
the model is fitted again on every row measured before that day and scores that day's rows:
the *next-day error* of a model that is recalibrated every day and used until the next
calibration. This module picks the origins and their rows; ``fit-coarse`` fits them
(:mod:`heliocal.pipeline.stages.rolling`).

Origins are the calibration days (UTC dates) that have at least ``min_rows`` earlier rows. A
heliostat with many calibration days is sampled: at most ``max_origins`` origins, spread evenly
over its eligible days by rank, the last day always included, so the evaluation costs at most
``max_origins`` fits per heliostat whatever its history. Each origin's fit starts from the
previous origin's (warm start), so the fits are sequential per heliostat and batched over
heliostats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..vocabulary import DEFAULT_ROLLING_ORIGINS

__all__ = ["Origin", "DEFAULT_MAX_ORIGINS", "MIN_ORIGIN_ROWS", "rolling_origins", "utc_days"]

#: Origins per heliostat by default (the cost is one warm-started fit per origin).
DEFAULT_MAX_ORIGINS = DEFAULT_ROLLING_ORIGINS

#: Rows a fit needs before an origin, at the least: each row gives two equations, so 10 rows
#: give 20 for the 6 to 28 free parameters of a preset held by its prior.
MIN_ORIGIN_ROWS = 10


@dataclass(frozen=True)
class Origin:
    """One origin of one heliostat.

    Attributes
    ----------
    day : the UTC date scored (numpy datetime64[D]).
    train : (N,) bool, the rows before ``day`` (the fit's rows).
    score : (N,) bool, the rows of ``day``.
    days_since_last_row : days from the last training row to the start of ``day`` [d].
    """

    day: np.datetime64
    train: np.ndarray
    score: np.ndarray
    days_since_last_row: float


def utc_days(times_utc: np.ndarray) -> np.ndarray:
    """UTC dates (datetime64[D]) of datetime64 times; NaT stays NaT."""
    return np.asarray(times_utc).astype("datetime64[D]")


def rolling_origins(times_utc: np.ndarray, usable: np.ndarray | None = None, *,
                    max_origins: int = DEFAULT_MAX_ORIGINS,
                    min_rows: int = MIN_ORIGIN_ROWS) -> list[Origin]:
    """The origins of one heliostat, in time order.

    Parameters
    ----------
    times_utc : (N,) datetime64 UTC times of its rows (NaT: a row without a time, never used).
    usable : (N,) bool, rows that may be fitted and scored (default: all with a time).
    max_origins : at most this many origins (evenly spread by rank, the last day kept).
    min_rows : an origin needs at least this many usable rows before its day.
    """
    t = np.asarray(times_utc).astype("datetime64[s]")
    ok = ~np.isnat(t) if usable is None else (np.asarray(usable, bool) & ~np.isnat(t))
    if not ok.any() or max_origins < 1:
        return []
    days = utc_days(t)
    distinct = np.unique(days[ok])
    before = np.array([int((ok & (days < d)).sum()) for d in distinct])
    eligible = distinct[before >= min_rows]
    if len(eligible) > max_origins:
        pick = np.unique(np.round(np.linspace(0, len(eligible) - 1, max_origins)).astype(int))
        eligible = eligible[pick]
    out = []
    for d in eligible:
        train = ok & (days < d)
        last = t[train].max()
        gap = (d.astype("datetime64[s]") - last) / np.timedelta64(1, "D")
        out.append(Origin(d, train, ok & (days == d), float(gap)))
    return out
