"""Checks of ``ingest`` that judge a whole source rather than a row (its time zones, its azimuth
convention), accumulated over the chunks the source is streamed in, in constant memory; the rows'
own checks are :mod:`heliocal.pipeline.io.validation`'s.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from ..errors import InputError
from ..physics.sun import sun_vector_enu, wrap_deg
from .staged import IngestOptions

__all__ = ["MedianVsThreshold", "SourceChecks"]


class MedianVsThreshold:
    """Compares the median of values seen in chunks with a fixed threshold, in constant memory.

    :meth:`median` returns ``np.median`` of all values when the two middle values lie on both
    sides of the threshold (they are then the largest value below and the smallest above it,
    which are kept), and otherwise a value on the same side of the threshold as the median.
    """

    def __init__(self, threshold: float):
        self.threshold = float(threshold)
        self.n_lt = self.n_eq = self.n_gt = self.n_nan = 0
        self.max_lt, self.min_gt = -math.inf, math.inf

    @property
    def n(self) -> int:
        return self.n_lt + self.n_eq + self.n_gt + self.n_nan

    def add(self, values) -> None:
        v = np.asarray(values, float)
        lt, gt, nan = v < self.threshold, v > self.threshold, np.isnan(v)
        self.n_lt += int(lt.sum())
        self.n_gt += int(gt.sum())
        self.n_nan += int(nan.sum())
        self.n_eq += int(len(v) - lt.sum() - gt.sum() - nan.sum())
        if lt.any():
            self.max_lt = max(self.max_lt, float(v[lt].max()))
        if gt.any():
            self.min_gt = min(self.min_gt, float(v[gt].min()))

    def median(self) -> float:
        if self.n_nan:
            return math.nan

        def at(i: int) -> float:
            if i < self.n_lt:
                return self.max_lt
            return self.threshold if i < self.n_lt + self.n_eq else self.min_gt

        n = self.n
        if n % 2:
            return at(n // 2)
        return (at(n // 2 - 1) + at(n // 2)) / 2


class SourceChecks:
    """Checks of :func:`validate_rows` that judge a whole source (time zones, azimuth convention):
    the chunks of one source add their rows here, :meth:`finish` raises once all were seen."""

    def __init__(self, opts: IngestOptions):
        self.opts = opts
        self.first: tuple | None = None  # (row label, source file) of the source's first row
        self.ts_given = 0
        self.naive = 0
        self.naive_example: tuple | None = None  # (row label, timestamp)
        self.ambiguous = 0
        self.ambiguous_example: tuple | None = None
        self.sun_diff = MedianVsThreshold(5 * opts.sun_tolerance_deg + 1.0)
        self.sun_alt_diff = MedianVsThreshold(1.0)

    def add_rows(self, df: pd.DataFrame) -> None:
        if len(df):
            label = df.index.min()
            if self.first is None or label < self.first[0]:
                self.first = (label, df.loc[label, "source_file"])

    def add_timestamps(self, df: pd.DataFrame, ts_given: pd.Series, naive: pd.Series,
                       ambiguous: pd.Series | None = None) -> None:
        self.ts_given += int(ts_given.sum())
        self.naive += int((naive & ts_given).sum())
        if ambiguous is not None and ambiguous.any():
            self.ambiguous += int((ambiguous & ts_given).sum())
            label = ambiguous[ambiguous].index.min()
            if self.ambiguous_example is None or label < self.ambiguous_example[0]:
                self.ambiguous_example = (label, df.loc[label, "timestamp"])
        if naive.any():
            label = naive[naive].index.min()
            if self.naive_example is None or label < self.naive_example[0]:
                self.naive_example = (label, df.loc[label, "timestamp"])

    def add_sun(self, az, el, spa_az, spa_el, diff) -> None:
        """Logged sun angles against SPA, and the same with azimuths read north-clockwise."""
        alt = sun_vector_enu(wrap_deg(180.0 - np.asarray(az, float)), el)
        alt_diff = np.degrees(np.arccos(np.clip((alt * sun_vector_enu(spa_az, spa_el)).sum(axis=1),
                                                -1, 1)))
        self.sun_diff.add(diff)
        self.sun_alt_diff.add(alt_diff)

    def finish(self) -> None:
        source = self.first[1] if self.first else "?"
        if self.naive and self.naive == self.ts_given and self.opts.timezone is None:
            raise InputError(f"{source}: timestamps have no time zone (e.g. "
                             f"{self.naive_example[1]!r}); add a UTC offset such as 'Z' or pass "
                             "--timezone Europe/Berlin")
        if self.ambiguous and self.ambiguous == self.ts_given:
            raise InputError(f"{source}: timestamps such as {self.ambiguous_example[1]!r} write "
                             "day and month as numbers, and heliocal cannot tell which is which; "
                             "pass --date-format, e.g. '%d.%m.%Y %H:%M:%S%z' (day first) or "
                             "'%m/%d/%Y %H:%M:%S%z' (month first)")
        # a log whose azimuths are clearly north-clockwise (0 = north) is refused
        if (self.opts.azimuth_convention == "south" and self.sun_diff.n >= 3
                and not self.sun_diff.median() <= self.sun_diff.threshold
                and self.sun_alt_diff.median() < 1.0):
            raise InputError(f"{source}: sun azimuths look north-clockwise (0 = north); heliocal's "
                             "convention is 0 = south, positive toward east: pass "
                             "--azimuth-convention north-clockwise")
