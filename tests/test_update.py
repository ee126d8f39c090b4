"""``update`` (issue 36 part 3): a day's rows through every stage a work directory has run, in one
process, with the options each stage recorded; against the same day done by hand (``ingest
--append`` and each stage with ``--incremental``, the commands README.md documents).

The field is tests/test_incremental.py's: the bundled synthetic sample (4 simulated heliostats)
without SP13's last 5 rows, then a new log with those rows, a re-sent row and a conflicting one.
The day before is built with options other than the defaults (split sizes and seed, preset,
rolling origins, the sweep's study, sizes and small networks, the report's alert level), so an
update that ran any stage with its defaults would compute every heliostat again and fail the
"computed 1, kept 3" checks below.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from heliocal.pipeline.artifacts.schemas import (COARSE_PARAMS, COARSE_PREDICTIONS, REGIME_PARAMS,
                                                 REGIMES, ROLLING_ORIGIN, SPLIT)
from heliocal.pipeline.errors import InputError, ParameterError
from heliocal.pipeline.models.config import FineConfig, PathConfig
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.stages.report import run_report
from heliocal.pipeline.stages.split import run_split
from heliocal.pipeline.stages.sweep import run_sweep
from heliocal.pipeline.stages.update import recorded_runs, run_update
from test_incremental import OPTIONS, _files, _logs, _sweep_tables, assert_same_artifact

SPLIT_OPTIONS = dict(n_test=25, n_val=15, seed=3)
COARSE_OPTIONS = dict(preset="static-6", rolling_origins=2, workers=1)
SWEEP_OPTIONS = dict(weight_decays=[1e-2, 0.0], config=FineConfig(max_epochs=15, ensemble=1),
                     extra_bands=(), study=["ST20"], n_train=[20], baselines=(),
                     path=PathConfig(stage_epochs=15), workers=1)
REPORT_OPTIONS = dict(alert_mrad=1.5, workers=1)


@pytest.fixture(scope="module")
def day_before(tmp_path_factory):
    """(the logs, a work directory through every stage but fit-hybrid on the old log)."""
    root = tmp_path_factory.mktemp("update")
    logs = _logs(root)
    wd = root / "day-before"
    run_ingest([logs["old"]], wd, OPTIONS)
    run_split(wd, **SPLIT_OPTIONS)
    run_fit_coarse(wd, **COARSE_OPTIONS)
    run_sweep(wd, **SWEEP_OPTIONS)
    run_report(wd, **REPORT_OPTIONS)
    return logs, wd


def _by_hand(wd: Path, new_log: Path) -> None:
    """The day's update as README.md spells it stage by stage, each stage with the day before's
    options."""
    run_ingest([new_log], wd, OPTIONS, append=True)
    run_split(wd, incremental=True, **SPLIT_OPTIONS)
    run_fit_coarse(wd, incremental=True, **COARSE_OPTIONS)
    run_sweep(wd, incremental=True, **SWEEP_OPTIONS)
    run_report(wd, incremental=True, **REPORT_OPTIONS)


def _manifest_files(wd: Path) -> dict[str, dict]:
    """stage -> {file: SHA-256} of every committed stage of ``wd`` (the report's too)."""
    stages = [p.name.removesuffix(".manifest.json") for p in wd.glob("*.manifest.json")]
    return {**{stage: _files(wd, stage) for stage in stages},
            "report": _files(wd / "report", "report")}


@pytest.mark.slow
def test_update_equals_the_day_done_by_hand_and_computes_only_the_changed_heliostat(day_before,
                                                                                    tmp_path):
    logs, before = day_before
    auto, hand = (shutil.copytree(before, tmp_path / name) for name in ("auto", "hand"))
    summary = run_update([logs["new"]], auto, workers=1)
    _by_hand(hand, logs["new"])

    # the ingest: the 5 new rows kept; the re-sent and the conflicting row rejected
    assert (summary["ingest"]["kept"], summary["ingest"]["rejected"]) == (5, 2)
    assert summary["ingest"]["rejected_by_reason"] == {"duplicate_measurement_id": 1,
                                                       "duplicate_of_ingested_row": 1}
    # every stage the day before ran, in order, each computing SP13 alone (the recorded options
    # replayed: with any default in their place every heliostat would be computed again)
    stages = {s["stage"]: s for s in summary["stages"]}
    assert list(stages) == ["split-knn", "fit-coarse", "sweep", "report"]
    for stage in ("split-knn", "fit-coarse", "sweep"):
        assert (stages[stage]["computed"], stages[stage]["reused"]) == (1, 3), stage
    # SP13's figures drawn again, the other heliostats' kept
    assert stages["report"]["figures_drawn"] > 0 and stages["report"]["figures_kept"] > 0

    # the artifacts are those of the day by hand: tables as tests/test_incremental.py compares an
    # incremental run with a full one (the sweep's bit for bit, but for its wall times)
    for schema in (SPLIT, COARSE_PARAMS, COARSE_PREDICTIONS, REGIMES, REGIME_PARAMS,
                   ROLLING_ORIGIN):
        assert_same_artifact(pd.read_parquet(auto / schema.filename),
                             pd.read_parquet(hand / schema.filename), schema.name)
    for name, table in _sweep_tables(auto).items():
        pd.testing.assert_frame_equal(table, _sweep_tables(hand)[name], check_exact=True, obj=name)
    auto_metrics, hand_metrics = (json.loads((w / "report" / "metrics.json").read_text())
                                  for w in (auto, hand))
    assert auto_metrics["heliostats"] == hand_metrics["heliostats"]
    assert auto_metrics["field"] == hand_metrics["field"]
    assert sorted(p.name for p in (auto / "report" / "figures").iterdir()) == sorted(
        p.name for p in (hand / "report" / "figures").iterdir())

    # the next update without a new log finds every stage up to date and writes nothing
    files = _manifest_files(auto)
    again = run_update([], auto, workers=1)
    assert again["ingest"] is None
    assert [(s["stage"], s.get("unchanged")) for s in again["stages"]] == [
        ("split-knn", True), ("fit-coarse", True), ("sweep", True), ("report", True)]
    assert _manifest_files(auto) == files


@pytest.mark.slow
def test_update_replays_the_recorded_options(day_before):
    """The keyword arguments the update gives each stage are the day before's options (the
    values set in this module), read back from the manifests."""
    runs = {r.stage: r.kwargs for r in recorded_runs(day_before[1])}
    assert list(runs) == ["split-knn", "fit-coarse", "sweep", "report"]
    assert {k: runs["split-knn"][k] for k in ("n_test", "n_val", "seed", "method")} == {
        "n_test": 25, "n_val": 15, "seed": 3, "method": "knn"}
    assert (runs["fit-coarse"]["preset"], runs["fit-coarse"]["rolling_origins"]) == ("static-6", 2)
    sweep = runs["sweep"]
    assert sweep["config"] == SWEEP_OPTIONS["config"] and sweep["path"] == SWEEP_OPTIONS["path"]
    assert (sweep["study"], sweep["n_train"], sweep["extra_bands"]) == (["ST20"], [20], [])
    assert sweep["weight_decays"] == [1e-2, 0.0] and sweep["gp"] is True
    assert runs["report"]["alert_mrad"] == 1.5


def test_update_of_a_workdir_without_ingested_rows_is_one_clear_error(tmp_path, runner):
    from heliocal.cli.main import app

    with pytest.raises(InputError, match="has no ingested measurements to update: run `heliocal "
                                         "ingest SOURCE --workdir"):
        run_update([], tmp_path / "empty")
    with pytest.raises(ParameterError, match="The 'workers' parameter of update must be"):
        run_update([], tmp_path / "empty", workers=0)
    result = runner.invoke(app, ["update", "--workdir", str(tmp_path / "empty")])
    assert result.exit_code == 1
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("Error: ")
    assert not (tmp_path / "empty" / "measurements.parquet").exists()


@pytest.mark.slow
def test_update_refuses_a_stage_last_run_on_some_heliostats(tmp_path):
    """A run of some heliostats records no digests, so its stage cannot be brought up to date
    heliostat by heliostat: the update says which stage and what to run, before it ingests."""
    logs = _logs(tmp_path)
    wd = tmp_path / "wd"
    run_ingest([logs["old"]], wd, OPTIONS)
    run_split(wd)
    run_fit_coarse(wd, preset="static-6", rolling_origins=0, heliostats=["SP13"], workers=1)
    rows = len(pd.read_parquet(wd / "measurements.parquet"))
    with pytest.raises(InputError, match=r"last fit-coarse ran on some heliostats only "
                                         r"\(--heliostat\).*run `heliocal fit-coarse --workdir"):
        run_update([logs["new"]], wd, workers=1)
    assert len(pd.read_parquet(wd / "measurements.parquet")) == rows   # nothing ingested


@pytest.mark.slow
def test_update_repeats_fit_hybrid_and_refuses_a_second_mode(tmp_path):
    """fit-hybrid's manifest records its last mode: the update repeats that run (kept whole
    when nothing changed, which shows the options it repeats are the recorded ones) and refuses
    a work directory holding another mode's models, which it would leave on the old rows."""
    from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid

    logs = _logs(tmp_path)
    wd = tmp_path / "wd"
    run_ingest([logs["old"]], wd, OPTIONS)
    run_split(wd)
    run_fit_coarse(wd, preset="static-6", rolling_origins=0, workers=1)
    hybrid = dict(weight_decay=1e-3, config=FineConfig(max_epochs=10, ensemble=1), workers=1)
    run_fit_hybrid(wd, mode="hybrid", **hybrid)
    first = run_update([logs["new"]], wd, workers=1)
    assert [s["stage"] for s in first["stages"]] == ["split-knn", "fit-coarse", "fit-hybrid"]
    assert first["stages"][2]["unchanged"] is False          # retrained: its inputs changed
    again = run_update([], wd, workers=1)
    assert [s.get("unchanged") for s in again["stages"]] == [True, True, True]

    run_fit_hybrid(wd, mode="nn-only", **hybrid)
    rows = len(pd.read_parquet(wd / "measurements.parquet"))
    with pytest.raises(InputError, match=r"holds fit-hybrid models of the modes hybrid, nn-only, "
                                         r"and an update repeats the last fit-hybrid run only "
                                         r"\(nn-only\)"):
        run_update([logs["new"]], wd, workers=1)
    assert len(pd.read_parquet(wd / "measurements.parquet")) == rows
