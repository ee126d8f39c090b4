"""Tests of aim's expected error (heliocal.pipeline.stages.aim_budget) and of the nominal
fallback (heliocal.pipeline.stages.aim_choice.nominal_fallback).

Expected values: the level's closed form (a root mean square, a floor of sqrt(2) noise
scales); the Rayleigh law of a normal error of two Gaussian components (median
``sigma sqrt(2 ln 2)``, mean ``sigma sqrt(pi / 2)``) against the simulator's noise floor (the
true model's mean error on its noisy spots); and on simulated static heliostats (ground truth:
the true geometry does not change, so the budget's level is the held-out rows' error) the
calibration target of issue 33: actual <= 2x expected for >= 90 % of held-out rows.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from conftest import fitted_simulation

from heliocal.pipeline.stages.aim_budget import (ErrorBudget, LevelGrowth, error_level_mrad,
                                                 expected_error_mrad, sun_distance_deg)
from heliocal.pipeline.stages.aim_choice import nominal_fallback


def test_the_level_is_the_root_mean_square_with_the_noise_as_floor():
    # sqrt((3^2 + 4^2) / 2) = 3.5355; a NaN row is not a row
    assert error_level_mrad([3.0, 4.0, float("nan")], 0.1) == pytest.approx(math.sqrt(12.5))
    # below the floor: sqrt(2) x 2.0 per component
    assert error_level_mrad([0.5, 0.5], 2.0) == pytest.approx(2.0 * math.sqrt(2.0))
    assert error_level_mrad([], float("nan")) == 0.0


def test_without_a_covariance_the_expected_error_is_the_level():
    budget = ErrorBudget(None, 1.7, "nominal validation", np.zeros((0, 3)), None)
    got = expected_error_mrad(budget, None, None, np.zeros((4, 2)), None, None)
    assert got.tolist() == [1.7] * 4


def _rolling(scale_by_days: dict, heliostats=("A", "B", "C"), rows_per_bin=10):
    """Rolling-origin rows whose errors are the heliostat's own scale times a known factor per
    days since the fit's last row (every row of a bin the same)."""
    import pandas as pd

    rows = []
    for k, hid in enumerate(heliostats):
        for days, factor in scale_by_days.items():
            rows += [(hid, days, (k + 1) * factor)] * rows_per_bin
    return pd.DataFrame(rows, columns=["heliostat_id", "days_since_last_row", "error_mrad"])


def test_the_level_growth_is_the_field_s_normalised_error_by_days():
    # per heliostat half its rows at 0.5 d with error s, half at 20 d with 2 s: the heliostat's
    # root mean square is s sqrt(5/2), so the normalised bins are 1/sqrt(2.5) and 2/sqrt(2.5);
    # the bins between (1-3, 3-10 d) have no rows and keep the first's, the later ones the 20 d
    # bin's (the heliostats' different scales k s cancel)
    g = LevelGrowth.from_rolling(_rolling({0.5: 1.0, 20.0: 2.0}))
    low, high = 1 / math.sqrt(2.5), 2 / math.sqrt(2.5)
    assert g.factor == pytest.approx([low, low, low, high, high, high])
    assert g.at([0.0, 2.0, 29.0, 400.0]) == pytest.approx([low, low, high, high])
    # errors that shrink with time do not make a later aim expect less (non-decreasing)
    assert LevelGrowth.from_rolling(_rolling({0.5: 2.0, 20.0: 1.0})).factor == pytest.approx(
        [2 / math.sqrt(2.5)] * 6)
    # a bin of two heliostats is too few (MIN_GROWTH_HELIOSTATS = 3): no growth measured there
    two = LevelGrowth.from_rolling(_rolling({0.5: 1.0, 20.0: 2.0}, heliostats=("A", "B")))
    assert np.ptp(two.factor) == 0.0
    assert LevelGrowth.from_rolling(_rolling({})).factor.tolist() == [1.0] * 6


def test_an_aim_s_level_grows_from_its_source_s_days_to_its_own():
    g = LevelGrowth.from_rolling(_rolling({0.5: 1.0, 20.0: 2.0}))
    # a level of 1.5 mrad measured on rows at 0.5 d (reference = the first bin's growth):
    # 1.5 mrad for an aim a day after the last row, 3.0 mrad twenty days after, never below
    # the noise floor, and as measured without a time
    budget = ErrorBudget(None, 1.5, "validation", np.zeros((0, 3)), None, growth=g,
                         growth_reference=g.reference([0.5]), noise_floor_mrad=1.6)
    got = expected_error_mrad(budget, None, None, np.zeros((3, 2)), None, None,
                              [0.8, 20.0, float("nan")])
    assert got == pytest.approx([1.6, 3.0, 1.6])


def test_the_sun_distance_is_the_angle_to_the_nearest_training_sun():
    train = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    budget = ErrorBudget(None, 1.0, "validation", train, None)
    el = np.radians(30.0)   # 30 deg above the eastern horizon: 30 deg from east, 60 from zenith
    got = sun_distance_deg(budget, np.array([[np.cos(el), 0.0, np.sin(el)], [0.0, 0.0, 2.0]]))
    assert got == pytest.approx([30.0, 0.0], abs=1e-9)


def _entry(val, model="static-6"):
    return {"model": "coarse", "variant": None, "preset": model, "weight_decay": None,
            "val_error_mrad": val, "test_error_mrad": 9.0, "forward_error_mrad": 9.0,
            "next_day_error_mrad": 1.0, "model_dir": None, "fallback": None}


def test_a_fit_worse_than_the_nominal_geometry_on_held_out_rows_falls_back():
    nominal = {"val_error_mrad": 2.0, "test_error_mrad": 2.1, "time_val_error_mrad": 3.0,
               "time_test_error_mrad": 3.3}
    # better on both held-out sets: kept as it is
    assert nominal_fallback(_entry(1.0), 2.9, nominal) == _entry(1.0)
    # worse on the kNN validation rows
    got = nominal_fallback(_entry(2.5), 2.9, nominal)
    assert got["model"] == "nominal" and got["val_error_mrad"] == 2.0
    assert got["forward_error_mrad"] == 3.3 and "validation 2.5 vs 2 mrad" in got["fallback"]
    # worse forward in time only (the time split's validation rows)
    got = nominal_fallback(_entry(1.0), 3.5, nominal)
    assert got["model"] == "nominal" and "forward in time 3.5 vs 3 mrad" in got["fallback"]
    # without the nominal geometry's errors (or with NaN ones) nothing to compare
    assert nominal_fallback(_entry(2.5), 3.5, None)["model"] == "coarse"
    nan = {k: float("nan") for k in nominal}
    assert nominal_fallback(_entry(2.5), 3.5, nan)["model"] == "coarse"


def test_a_fit_worse_than_the_nominal_geometry_next_day_falls_back():
    """The rolling-origin rows are forward evidence of their own: a fit better than the nominal
    geometry on both validations but worse on the next-day rows (the shared CSV log's AH48 after
    its two-month gap: 75.1 against the nominal geometry's 71.5 mrad on the same 12 rows, while
    12.5 against 108 on the time split's validation) falls back; one better there is kept."""
    nominal = {"val_error_mrad": 83.0, "test_error_mrad": 80.0, "time_val_error_mrad": 107.8,
               "time_test_error_mrad": 56.5, "next_day_error_mrad": 71.5}
    worse = {**_entry(32.1), "next_day_error_mrad": 75.1}
    got = nominal_fallback(worse, 12.5, nominal)
    assert got["model"] == "nominal" and got["forward_error_mrad"] == 56.5
    assert got["next_day_error_mrad"] == 71.5
    assert "next day 75.1 vs 71.5 mrad on the rolling-origin rows" in got["fallback"]
    assert "validation" not in got["fallback"] and "forward in time" not in got["fallback"]
    # better next day (and on both validations): the fitted model stays
    better = {**_entry(32.1), "next_day_error_mrad": 46.5}
    assert nominal_fallback(better, 12.5, nominal) == better
    # no rolling-origin rows (NaN on either side): the next day decides nothing
    assert nominal_fallback({**worse, "next_day_error_mrad": float("nan")}, 12.5,
                            nominal)["model"] == "coarse"
    assert nominal_fallback(worse, 12.5, {**nominal, "next_day_error_mrad": float("nan")}
                            )["model"] == "coarse"


def _drifting_rolling(noise_mrad2: float, drift_mrad2_per_day: float,
                      days=(0.5, 2.0, 5.0, 15.0, 25.0), heliostats=("A", "B", "C"),
                      rows_per_day=10):
    """Rolling-origin rows of a field whose squared error grows linearly with the days since the
    fit's last row, ``noise + drift * days`` [mrad^2] (each row exactly at its mean square)."""
    import pandas as pd

    rows = [(hid, d, math.sqrt(noise_mrad2 + drift_mrad2_per_day * d))
            for hid in heliostats for d in days for _ in range(rows_per_day)]
    return pd.DataFrame(rows, columns=["heliostat_id", "days_since_last_row", "error_mrad"])


def test_beyond_the_measured_gaps_the_level_s_variance_grows_linearly_with_days():
    # a random walk: 0.25 mrad^2 of noise, 0.01 mrad^2 more per day since the last row, rows at
    # 0.5-25 d (the bins to 30 d measured, the last one's rows at 15 and 25 d: 20 d on average).
    # Closed form of the level 60 days out: sqrt(0.25 + 0.01 x 60) = 0.9220 mrad, whether the
    # level was measured on next-day rows (2 d) or on rows 40 d out; the bins alone held it flat
    # beyond 20 d (sqrt(0.25 + 0.01 x 20) = 0.671 mrad). Exact up to rounding (rel 1e-9).
    from heliocal.pipeline.stages.aim_growth import (drift_rate_mrad2_per_day,
                                                     normalised_drift_rate_per_day)

    noise, drift = 0.25, 0.01
    rolling = _drifting_rolling(noise, drift)
    assert drift_rate_mrad2_per_day(rolling) == pytest.approx(drift, rel=1e-9)
    # the relative slope is the drift over the field's mean square, 0.25 + 0.01 x 9.5 d
    assert normalised_drift_rate_per_day(rolling) == pytest.approx(drift / (noise + drift * 9.5))
    g = LevelGrowth.from_rolling(rolling)
    assert g.last_measured_days == pytest.approx(20.0)
    at = lambda d: math.sqrt(noise + drift * d)  # noqa: E731
    next_day = ErrorBudget(None, at(2.0), "next-day", np.zeros((0, 3)), None, growth=g,
                           growth_reference=g.reference([2.0]), reference_days=2.0)
    got = next_day.level_at([2.0, 20.0, 60.0, 200.0, float("nan")])
    assert got == pytest.approx([at(2.0), at(20.0), at(60.0), at(200.0), at(2.0)], rel=1e-9)
    later = ErrorBudget(None, at(40.0), "time-split validation", np.zeros((0, 3)), None,
                        growth=g, growth_reference=g.reference([40.0]), reference_days=40.0)
    assert later.level_at([60.0]) == pytest.approx([at(60.0)], rel=1e-9)
    # errors that do not grow give no drift; with one measured bin there is no slope to extend
    assert LevelGrowth.from_rolling(_drifting_rolling(noise, 0.0)).drift_mrad2_per_day == 0.0
    one_bin = LevelGrowth.from_rolling(_drifting_rolling(noise, drift, days=(12.0, 20.0, 29.0)))
    assert one_bin.drift_mrad2_per_day == 0.0
    assert one_bin.at([60.0]) == pytest.approx(one_bin.at([12.0]))


# --------------------------------------------------------------------------------------------
# simulated heliostats, end to end
# --------------------------------------------------------------------------------------------
def test_of_the_two_forward_sources_the_larger_level_counts():
    from heliocal.pipeline.stages.aim_budget import _level

    flat = LevelGrowth.none()
    # next-day rows RMS 1.0, the time split's validation rows RMS 3.0: the larger, 3.0, counts
    # (a heliostat whose next days were calm can still be far off months later) ...
    both = {"next-day": [1.0] * 4, "time-split validation": [3.0] * 4, "validation": [9.0] * 4}
    assert _level(both, {}, 0.1, flat) == (pytest.approx(3.0), "time-split validation", 1.0)
    # ... and the other way round; the kNN validation rows are not a forward source
    both["time-split validation"] = [0.5] * 4
    assert _level(both, {}, 0.1, flat) == (pytest.approx(1.0), "next-day", 1.0)
    # one forward source alone is the level; neither: the kNN validation rows; none: the noise
    assert _level({"time-split validation": [2.0] * 3, "validation": [9.0] * 3}, {}, 0.1,
                  flat)[:2] == (pytest.approx(2.0), "time-split validation")
    assert _level({"next-day": [2.0] * 2, "validation": [9.0] * 3}, {}, 0.1,
                  flat)[:2] == (pytest.approx(9.0), "validation")   # 2 rows are too few
    assert _level({}, {}, 0.5, flat)[:2] == (pytest.approx(0.5 * math.sqrt(2)), "training noise")
    # compared at equal age: growth x2 between 0.5 d and 20 d (the test above's field), so
    # 1.5 mrad on time-split rows 20 d out is 0.75 mrad at a day, below next-day's 1.0
    g = LevelGrowth.from_rolling(_rolling({0.5: 1.0, 20.0: 2.0}))
    level, source, reference = _level(
        {"next-day": [1.0] * 4, "time-split validation": [1.5] * 4},
        {"next-day": [0.5] * 4, "time-split validation": [20.0] * 4}, 0.1, g)
    assert (level, source) == (pytest.approx(1.0), "next-day")
    assert reference == pytest.approx(g.reference([0.5]))


@pytest.fixture(scope="module")
def static_field(tmp_path_factory):
    return fitted_simulation(tmp_path_factory.mktemp("budget"), rolling_origins=4,
                             n_heliostats=3, seed=11, measurements=(150, 150),
                             dynamic_fraction=0.0, noise_mrad=0.4, deviations="static-20")


@pytest.mark.slow
def test_the_robust_noise_scale_is_the_rayleigh_scale_of_the_true_model(static_field):
    """At the true parameters the errors are the noise: their median-based scale (the budget's)
    and the simulator's noise floor (their mean) agree through the Rayleigh law, within the
    spread of 150 rows (the median's relative standard error ~ 0.06 here; 15 % allowed)."""
    from heliocal.pipeline.artifacts.schemas import MEASUREMENTS
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.coarse import MeasurementBatch
    from heliocal.pipeline.stages.aim_budget import robust_noise_mrad

    field, work = static_field
    rows = read_artifact(work, MEASUREMENTS)
    for hid, h in field.heliostats.items():
        batch = MeasurementBatch.from_frame(rows[rows["heliostat_id"] == hid])
        got = robust_noise_mrad(h.spec, h.true, batch, 0)
        sigma_from_mean = h.noise_floor_mrad / math.sqrt(math.pi / 2.0)
        assert got == pytest.approx(sigma_from_mean, rel=0.15), hid


@pytest.mark.slow
def test_the_expected_error_holds_on_held_out_rows_of_static_heliostats(static_field):
    from heliocal.pipeline.stages.aim_calibration import calibration_rows, calibration_summary

    _, work = static_field
    for setting in ("knn", "forward"):
        s = calibration_summary(calibration_rows(work, setting))
        assert s["rows"] >= 60, setting
        # issue 33's target: actual <= 2 x expected for >= 90 % of the aims ...
        assert s["within_2x"] >= 0.9, (setting, s)
        # ... and not inflated: a Gaussian normal error puts the median at 0.83 of the root
        # mean square; 0.5 would mean the expected error is twice what the rows show
        assert 0.5 <= s["median_ratio"] <= 1.2, (setting, s)


@pytest.mark.slow
def test_the_forward_check_uses_only_next_day_rows_scored_before_the_test_rows(static_field):
    # what a plant had seen when it aimed: every rolling-origin row the forward check's budget
    # keeps lies before its heliostat's first time-split test row, and some rows are cut
    import pandas as pd

    from heliocal.pipeline.artifacts.schemas import MEASUREMENTS, ROLLING_ORIGIN
    from heliocal.pipeline.artifacts.manifests import CommittedWorkdir
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.stages.aim_budget import _scored_before
    from heliocal.pipeline.stages.aim_calibration import first_test_time

    _, work = static_field
    cut = first_test_time(work)
    rolling = read_artifact(work, ROLLING_ORIGIN)
    kept = _scored_before(CommittedWorkdir.of(work), rolling, cut)
    times = read_artifact(work, MEASUREMENTS, columns=["heliostat_id", "measurement_id",
                                                       "timestamp"])
    t = kept.merge(times, on=["heliostat_id", "measurement_id"], suffixes=("", "_m"))
    assert len(t) == len(kept) > 0
    assert (pd.to_datetime(t["timestamp_m"], utc=True)
            < pd.to_datetime(t["heliostat_id"].map(cut), utc=True)).all()
    assert len(kept) < len(rolling)


def test_a_fine_model_s_explained_variance_lowers_the_level_down_to_its_noise():
    from heliocal.pipeline.stages.aim_budget import fine_level_mrad

    # sqrt(max(level^2 - explained, min(noise, level^2))), closed form per row: a level of
    # 2 mrad (4 mrad^2) with 3 explained is 1 mrad; with 10 explained it stops at the noise
    # (0.25 mrad^2: 0.5 mrad); a noise above the level never raises it (2 mrad); nothing
    # explained is the coarse level
    got = fine_level_mrad([2.0, 2.0, 2.0, 2.0], [3.0, 10.0, 10.0, 0.0], [0.25, 0.25, 9.0, 0.25])
    assert got == pytest.approx([1.0, 0.5, 2.0, 2.0])
    # in the expected error, beside the parameters' term (no covariance here: the level alone),
    # at the level's growth: 1.5 mrad measured a day out is 3.0 mrad at 20 days (the growth
    # test's field), of which 5 mrad^2 explained leaves 2.0 mrad
    g = LevelGrowth.from_rolling(_rolling({0.5: 1.0, 20.0: 2.0}))
    budget = ErrorBudget(None, 1.5, "validation", np.zeros((0, 3)), None, growth=g,
                         growth_reference=g.reference([0.5]))
    got = expected_error_mrad(budget, None, None, np.zeros((2, 2)), None, None, [20.0, 20.0],
                              explained_mrad2=np.array([5.0, 0.0]), fine_noise_mrad2=0.01)
    assert got == pytest.approx([2.0, 3.0])


def test_a_fine_model_never_expects_less_than_its_held_out_rows_showed():
    from heliocal.pipeline.stages.aim_budget import fine_level_mrad

    # closed form, a 2 mrad level with 3 mrad^2 explained (1 mrad without a floor): a floor of
    # 0.75 x the level holds it at 1.5 mrad; a floor of 0.25 (0.5 mrad) is below it; nothing
    # explained stays 2 mrad under any floor of at most 1
    got = fine_level_mrad([2.0, 2.0, 2.0], [3.0, 3.0, 0.0], 0.0, [0.75, 0.25, 1.0])
    assert got == pytest.approx([1.5, 1.0, 2.0])
    # in the expected error, through the budget's floor
    budget = ErrorBudget(None, 2.0, "validation", np.zeros((0, 3)), None, fine_floor_ratio=0.75)
    got = expected_error_mrad(budget, None, None, np.zeros((1, 2)), None, None,
                              explained_mrad2=np.array([3.0]))
    assert got == pytest.approx([1.5])


def test_the_floor_is_the_fine_model_s_held_out_error_over_the_coarse_model_s():
    from heliocal.pipeline.stages.aim_budget import _fine_floor, held_out_ratios

    # heliostat A: the fine model errs half the coarse model's on its 4 kNN validation rows
    # (RMS ratio 0.5) and 1.5 times it on its 3 time-split validation rows (capped at 1);
    # heliostat B has only 2 time-split validation rows (fewer than MIN_LEVEL_ROWS): no ratio
    coarse = np.array([1.0, 2.0, 3.0, 4.0, 2.0, 2.0, 2.0])
    both = pd.DataFrame({
        "heliostat_id": ["A"] * 7 + ["B"] * 2,
        "split": ["validation"] * 4 + ["train"] * 3 + ["train"] * 2,
        "time_split": ["train"] * 4 + ["validation"] * 3 + ["validation"] * 2,
        "error_mrad_coarse": np.r_[coarse, 1.0, 1.0],
        "error_mrad_fine": np.r_[0.5 * coarse, 1.0, 1.0],
        "time_error_mrad_coarse": np.r_[coarse, 1.0, 1.0],
        "time_error_mrad_fine": np.r_[1.5 * coarse, 0.5, 0.5]})
    got = held_out_ratios(both)
    assert got["A"] == pytest.approx({"validation": 0.5, "time-split validation": 1.0})
    assert math.isnan(got["B"]["time-split validation"]) and math.isnan(got["B"]["validation"])
    # a forward level source takes the time split's ratio, the kNN one its own; either falls
    # back to the other, and without both the variance alone counts (0)
    assert _fine_floor(got["A"], "next-day") == 1.0
    assert _fine_floor(got["A"], "validation") == 0.5
    assert _fine_floor({"validation": 0.5, "time-split validation": math.nan}, "next-day") == 0.5
    assert _fine_floor(got["B"], "validation") == 0.0

