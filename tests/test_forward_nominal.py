"""Forward evidence against the nominal geometry on real heliostats of the shared Jülich CSV log
(docs/experiments/forward-vs-nominal.md): the rolling-origin evaluation's fits
(heliocal.pipeline.stages.rolling) and the nominal fallback of ``aim --model auto``
(heliocal.pipeline.stages.aim_choice.nominal_fallback) on the next-day rows.

Expected values come from the measurement in docs/experiments/forward-vs-nominal.md (the whole
log through ingest, split-knn and fit-coarse; each heliostat's fits depend on its own rows only,
so fitting four of them gives the same figures).
"""

from __future__ import annotations

import pytest

HELIOSTATS = ["AH33", "AH48", "AJ51", "AQ32"]


@pytest.fixture(scope="module")
def fitted(juelich_dir, tmp_path_factory):
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.split import run_split

    work = tmp_path_factory.mktemp("forward-nominal") / "work"
    run_ingest([juelich_dir / "csv" / "juelich_calibration_log.csv"], work,
               IngestOptions(properties=juelich_dir / "paint"))
    run_split(work)
    run_fit_coarse(work, heliostats=HELIOSTATS)
    return work


@pytest.mark.slow
def test_each_origin_keeps_the_better_of_the_cold_and_the_warm_start(fitted):
    """AH33's nominal geometry is about 100 mrad off; the robust start its first origin found
    on 11 rows, kept for later origins together with a warm start from that origin's fit, held
    every next-day error at 8-290 mrad (mean 164) where a cold fit of each origin's rows gives
    0.6-1.4 mrad after the first origin (mean 6.4). AQ32 is the other way round: its cold fits
    reach a minimum with a mean next-day error of 17.1 mrad, the warm starts one of 0.47-0.59.
    Keeping the start with the lower objective must give both their low figure."""
    from heliocal.pipeline.artifacts.schemas import ROLLING_ORIGIN
    from heliocal.pipeline.artifacts.store import read_artifact

    mean = read_artifact(fitted, ROLLING_ORIGIN).groupby("heliostat_id")["error_mrad"].mean()
    assert mean["AH33"] < 10.0, mean.to_dict()
    assert mean["AQ32"] < 1.0, mean.to_dict()


@pytest.mark.slow
def test_aim_falls_back_where_the_fit_is_worse_than_nominal_next_day_and_keeps_it_elsewhere(fitted):
    """AH48 (a two-month gap with a change of state; 12 next-day rows) is better than its nominal
    geometry on both validations (32.1 vs 83.0 kNN, 12.5 vs 107.8 mrad on the time split's) but
    worse on the next-day rows: 75.1 against the nominal geometry's 71.5 mrad on the same rows.
    It falls back. AJ51 (4.39 vs 6.69) and AH33 (6.38 vs 99.4, its rolling fits repaired) are
    better there and keep their fit."""
    from heliocal.pipeline.stages.aim_choice import aim_models

    models = aim_models(fitted)
    ah48 = models["AH48"]
    assert ah48["model"] == "nominal", ah48
    assert "next day 75.1 vs 71.5 mrad" in ah48["fallback"]
    assert ah48["next_day_error_mrad"] == pytest.approx(71.47, abs=0.01)
    for hid in ("AH33", "AJ51", "AQ32"):
        assert models[hid]["model"] == "coarse" and models[hid]["fallback"] is None, models[hid]
