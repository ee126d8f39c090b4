"""Tests of heliocal.pipeline.models.rolling: the origins of the rolling-origin evaluation.

The rows are written out by hand (times of a few calibration days); the expected origins follow
from the rule in the module docstring: a day is an origin when at least ``min_rows`` usable
rows lie before it, at most ``max_origins`` of them spread evenly by rank with the last kept.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

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


# --------------------------------------------------------------------------------------------
# fit-coarse's rolling-origin evaluation, end to end on simulated heliostats (ground truth from
# the simulator: a static heliostat's true model, the noise floor, and a step of known size)
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rolled(tmp_path_factory):
    from heliocal.pipeline.artifacts.schemas import ROLLING_ORIGIN
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.simulate import write_field
    from heliocal.pipeline.stages.split import run_split

    root = tmp_path_factory.mktemp("rolling")
    field = simulate_field(2, seed=4, measurements=(160, 160), dynamic_fraction=0.0,
                           noise_mrad=0.4, deviations="static-6")
    write_field(field, root / "field")
    work = root / "work"
    run_ingest([root / "field" / "paint"], work, IngestOptions())
    run_split(work)
    summary = run_fit_coarse(work, preset="static-6", rolling_origins=6)
    return {"field": field, "work": work, "summary": summary,
            "rolling": read_artifact(work, ROLLING_ORIGIN)}


@pytest.mark.slow
def test_next_day_errors_of_static_heliostats_sit_at_their_noise_floor(rolled):
    from heliocal.pipeline.artifacts.schemas import MEASUREMENTS
    from heliocal.pipeline.artifacts.store import read_artifact

    rolling = rolled["rolling"]
    meas = read_artifact(rolled["work"], MEASUREMENTS)
    assert set(rolling["heliostat_id"]) == set(rolled["field"].heliostats)
    for hid, g in rolling.groupby("heliostat_id"):
        h = rolled["field"].heliostats[hid]
        # six origins, each scoring the rows of its own UTC day with a fit on the earlier rows
        assert g["origin_date"].nunique() == 6
        # a static heliostat's geometry is learnt from the first origin's 10+ rows on: the
        # next-day error is the noise floor (the true model's mean error on the noisy spots,
        # from the simulator) within its sampling spread on ~20 rows
        assert g["error_mrad"].mean() < 1.5 * h.noise_floor_mrad, (hid, g["error_mrad"].mean())
        assert (g["days_since_last_row"] > 0).all()
        # no leak: an origin's fit has exactly the rows before its day, and scores rows of
        # that day only (the measurements' own times, counted here)
        times = pd.to_datetime(meas.loc[meas["heliostat_id"] == hid, "timestamp"], utc=True)
        by_id = dict(zip(meas.loc[meas["heliostat_id"] == hid, "measurement_id"], times))
        for day, o in g.groupby("origin_date"):
            assert o["n_train"].iloc[0] == int((times < day).sum())
            scored = pd.to_datetime(o["measurement_id"].map(by_id), utc=True).dt.floor("D")
            assert (scored == day).all()
        n = g.drop_duplicates("origin_date").sort_values("origin_date")["n_train"].to_numpy()
        assert (np.diff(n) > 0).all() and n[0] >= 10


@pytest.mark.slow
def test_a_warm_started_origin_fit_is_the_cold_fit_of_its_rows(rolled):
    """The warm start changes where LM starts, not the objective: the last origin's fit of a
    heliostat, redone cold on the same rows, gives the same errors (to 1e-5 mrad)."""
    from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.coarse import MeasurementBatch, fit_heliostats_batched, predict
    from heliocal.pipeline.physics.parameters import HeliostatSpec, nominal_parameters

    work, rolling = rolled["work"], rolled["rolling"]
    hid = sorted(rolling["heliostat_id"].unique())[0]
    rows = read_artifact(work, MEASUREMENTS, heliostats=[hid]).reset_index(drop=True)
    hrow = read_artifact(work, HELIOSTATS, heliostats=[hid]).iloc[0]
    last = rolling[rolling["heliostat_id"] == hid]["origin_date"].max()
    day = pd.to_datetime(rows["timestamp"], utc=True).dt.floor("D")
    data = MeasurementBatch.from_frame(rows)
    train, scored = (day < last).to_numpy(), (day == last).to_numpy()
    spec = HeliostatSpec.from_row(hrow)
    cold = fit_heliostats_batched([spec], [nominal_parameters(hrow)], [data.subset(train)],
                                  "static-6", loss="soft_l1", robust_start="auto")[0]
    want = predict(cold.params, spec, data.subset(scored))["error_mrad"].to_numpy()
    got = (rolling[(rolling["heliostat_id"] == hid) & (rolling["origin_date"] == last)]
           .set_index("measurement_id").loc[data.subset(scored).measurement_id, "error_mrad"])
    np.testing.assert_allclose(got.to_numpy(), want, atol=1e-5)



def test_a_warm_fit_is_tried_cold_only_when_it_leaves_its_rows_unexplained():
    # the rule of rolling._needs_cold_start: data residuals' RMS above 3 loss scales, or unknown
    from types import SimpleNamespace

    from heliocal.pipeline.stages.rolling import COLD_RETRY_SCALES, _needs_cold_start

    assert COLD_RETRY_SCALES == 3.0
    fit = lambda noise: SimpleNamespace(noise_mrad=noise)  # noqa: E731
    assert not _needs_cold_start(fit(2.99), 1.0) and _needs_cold_start(fit(3.01), 1.0)
    assert not _needs_cold_start(fit(5.9), 2.0) and _needs_cold_start(fit(6.1), 2.0)
    assert _needs_cold_start(fit(float("nan")), 1.0)   # too few rows for a noise estimate


@pytest.mark.slow
def test_static_heliostats_start_cold_only_at_their_first_origin(rolled, tmp_path, monkeypatch):
    """On the simulated static heliostats every warm fit explains its rows to the noise (0.4
    mrad, under 3 loss scales of 1 mrad), so the cold start, which lands in the same minimum
    (test above), is fitted once per heliostat: at its first origin, where there is no warm
    start. The rows equal the fixture's, fitted before with the same objective (1e-5 mrad)."""
    from heliocal.pipeline.artifacts.schemas import ROLLING_ORIGIN
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.stages import rolling as rolling_stage
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from conftest import copy_of

    seen = []   # the start of every heliostat fitted at an origin
    inner = rolling_stage.fit_heliostats_batched

    def spy(*args, starts=None, **kwargs):
        seen.extend("cold" if s is None else "warm" for s in starts)
        return inner(*args, starts=starts, **kwargs)

    monkeypatch.setattr(rolling_stage, "fit_heliostats_batched", spy)
    work = copy_of(rolled["work"], tmp_path / "work")
    run_fit_coarse(work, preset="static-6", rolling_origins=6)
    n_helio = len(rolled["field"].heliostats)
    assert seen.count("cold") == n_helio and seen.count("warm") == 5 * n_helio
    again = read_artifact(work, ROLLING_ORIGIN)
    pd.testing.assert_frame_equal(again.drop(columns="error_mrad"),
                                  rolled["rolling"].drop(columns="error_mrad"))
    np.testing.assert_allclose(again["error_mrad"], rolled["rolling"]["error_mrad"], atol=1e-5)
