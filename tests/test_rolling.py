"""Tests of heliocal.pipeline.models.rolling: the origins of the rolling-origin evaluation.

The rows are written out by hand (times of a few calibration days); the expected origins follow
from the rule in the module docstring: a day is an origin when at least ``min_rows`` usable
rows lie before it, at most ``max_origins`` of them spread evenly by rank with the last kept.
"""

from __future__ import annotations

import numpy as np

from heliocal.pipeline.models.rolling import rolling_origins


def _times(*stamps):
    return np.array([np.datetime64(s) if s else np.datetime64("NaT") for s in stamps],
                    dtype="datetime64[s]")


def test_origins_are_days_with_enough_earlier_rows():
    t = _times("2023-01-01T09:00", "2023-01-01T12:00", "2023-01-03T10:00", "",
               "2023-01-03T15:00", "2023-01-07T08:30", "2023-01-07T16:00")
    got = rolling_origins(t, min_rows=2)
    # 2023-01-01 has no earlier row; 01-03 has 2, 01-07 has 4 (the row without a time is never used)
    assert [str(o.day) for o in got] == ["2023-01-03", "2023-01-07"]
    assert got[0].train.tolist() == [True, True, False, False, False, False, False]
    assert got[0].score.tolist() == [False, False, True, False, True, False, False]
    assert got[1].train.tolist() == [True, True, True, False, True, False, False]
    # from the last training row (01-01 12:00, 01-03 15:00) to the start of the day scored
    assert got[0].days_since_last_row == 1.5
    assert got[1].days_since_last_row == 3.375
    assert rolling_origins(t, min_rows=5) == []


def test_usable_rows_and_sampling_keep_the_last_day():
    days = [f"2023-03-{d:02d}T10:00" for d in range(1, 21)]
    t = _times(*days)
    usable = np.ones(20, bool)
    usable[0] = False   # e.g. an excluded row: neither fitted nor scored
    got = rolling_origins(t, usable, min_rows=3, max_origins=4)
    # eligible days: 03-05 .. 03-20 (three usable rows before 03-05), 16 of them; four spread
    # by rank 0, 5, 10, 15 -> 03-05, 03-10, 03-15, 03-20
    assert [str(o.day) for o in got] == ["2023-03-05", "2023-03-10", "2023-03-15", "2023-03-20"]
    assert not got[0].train[0] and got[0].train.sum() == 3
    assert got[-1].train.sum() == 18 and got[-1].score.tolist()[-1]
    assert rolling_origins(t, usable, min_rows=3, max_origins=0) == []
