"""The fade of a fine model (models/fade.py): distances to the training rows and the weights.

Every expected value is computed by hand from the formula in the module's docstring,
``w = exp(-(d_sun / L_sun)^2 / 2 - (d_time / L_time)^2 / 2)``.
"""

import math

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.fade import (NO_FADE, Fade, epoch_seconds, fade_weights,
                                           sun_distance_deg, time_distance_days)

DAY = 86400.0
TRAIN_SUN = np.array([[0.0, 30.0], [10.0, 30.0]])
TRAIN_TIME = np.array([0.0, 10 * DAY])


def test_sun_distance_is_to_the_nearest_training_row():
    # (3, 34) is sqrt(3^2 + 4^2) = 5 deg from (0, 30) and sqrt(7^2 + 4^2) = 8.06 from (10, 30)
    d = sun_distance_deg([3.0, 10.0, -6.0], [34.0, 30.0, 22.0], TRAIN_SUN)
    assert d == pytest.approx([5.0, 0.0, 10.0])
    assert np.isinf(sun_distance_deg([0.0], [0.0], np.zeros((0, 2)))).all()


def test_time_distance_is_outside_the_training_period_and_zero_without_time():
    # training rows on days 0 and 10: day 3 is inside the period, day 12 two days after it,
    # day -1 one day before it
    d = time_distance_days(np.array([3 * DAY, 12 * DAY, -1 * DAY, np.nan]), TRAIN_TIME)
    assert d == pytest.approx([0.0, 2.0, 1.0, 0.0])
    assert time_distance_days([5 * DAY], [np.nan]) == pytest.approx([0.0])


def test_weights_follow_the_formula():
    fade = Fade(10.0, 30.0, TRAIN_SUN, TRAIN_TIME)
    w = fade.weights([3.0, 0.0], [34.0, 30.0], np.array([13 * DAY, 0.0]))
    # row 1: d_sun 5, d_time 3 days (after the last training day): exp(-(0.5^2 + 0.1^2) / 2);
    # row 2 is a training row: 1
    assert w == pytest.approx([math.exp(-0.5 * (0.25 + 0.01)), 1.0], rel=1e-12)
    # an infinite length switches a distance off
    assert fade.with_lengths(math.inf).weights([3.0], [34.0], np.array([13 * DAY])) == \
        pytest.approx([math.exp(-0.5 * 0.01)])
    assert fade.with_lengths(10.0, math.inf).weights([3.0], [34.0], None) == \
        pytest.approx([math.exp(-0.125)])


def test_configuration_round_trip_and_no_fade():
    fade = Fade(8.0, math.inf, TRAIN_SUN, np.array([0.0, np.nan]))
    d = fade.to_dict()
    assert d["length_deg"] == 8.0 and d["length_days"] is None and d["train_time_s"][1] is None
    back = Fade.from_dict(d)
    q = ([1.0, 40.0], [31.0, 50.0], np.array([DAY, 100 * DAY]))
    assert back.weights(*q) == pytest.approx(fade.weights(*q), rel=1e-12)
    # a configuration without a fade (a model written before it) is not faded
    assert fade_weights({}, [1.0, 2.0], [3.0, 4.0]).tolist() == [1.0, 1.0]
    assert fade_weights({"fade": NO_FADE.to_dict()}, [1.0], [3.0]).tolist() == [1.0]
    stamps = pd.Series(pd.to_datetime(["1970-01-02T00:00:00Z", None], utc=True))
    assert fade_weights({"fade": d}, [1.0, 1.0], [31.0, 31.0], stamps) == \
        pytest.approx(fade.weights([1.0, 1.0], [31.0, 31.0], epoch_seconds(stamps)))


def test_a_length_must_be_positive():
    with pytest.raises(ParameterError, match=r"The 'length_deg' parameter of Fade must be a float "
                                             r"in \(0, inf\]. Got 0.0 instead."):
        Fade(0.0, math.inf, TRAIN_SUN, TRAIN_TIME)
