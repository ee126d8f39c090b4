"""Daily updates (issue 36 part 3): ``ingest --append`` and the incremental ``split-knn`` and
``fit-coarse``, compared with a full rerun on the same rows.

The field is the bundled synthetic sample (4 simulated heliostats, 590 rows): the "old" log is
every row but SP13's last 5, the "new" log those 5 rows, a re-sent copy of an SQ04 row and an SQ04
row with an ingested id but another motor position.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.pipeline.artifacts.incremental import heliostat_digests
from heliocal.pipeline.artifacts.schemas import (COARSE_PARAMS, COARSE_PREDICTIONS, REGIME_PARAMS,
                                                 REGIMES, ROLLING_ORIGIN, SPLIT)
from heliocal.pipeline.errors import InputError, ParameterError
from heliocal.pipeline.io.staged import IngestOptions
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.stages.split import run_split

SYNTH = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic"
OPTIONS = IngestOptions(properties=SYNTH / "paint", tower=SYNTH / "tower-measurements.json")

#: Floats of fit-coarse's artifacts, incremental against full: relative tolerance. The batched
#: solver stops when a step, the cost or the gradient changes by less than 1e-10 relative
#: (models.coarse's ``tolerance``); a heliostat fitted in another chunk (other padding, other
#: rounding) can stop a few such steps from the full run's iterate, so 1e-7 leaves a margin of
#: 1000. Absolute floor 1e-9 (mrad, m, rad) for values near zero.
REL, ABS = 1e-7, 1e-9


def _logs(folder: Path) -> dict[str, Path]:
    log = pd.read_csv(SYNTH / "calibration_log.csv")
    late = log.index[log["heliostat_id"] == "SP13"][-5:]
    sq04 = log[log["heliostat_id"] == "SQ04"]
    conflict = sq04.iloc[[4]].copy()
    conflict["axis_1_motor_position"] += 7
    paths = {"old": log.drop(index=late), "new": pd.concat([log.loc[late], sq04.iloc[[3]], conflict]),
             "full": log}
    out = {}
    for name, df in paths.items():
        out[name] = folder / f"{name}.csv"
        df.to_csv(out[name], index=False)
    return out


def assert_same_artifact(a: pd.DataFrame, b: pd.DataFrame, name: str) -> None:
    """Structure exactly (columns, dtypes, rows, every non-float value and every missing value),
    floats within :data:`REL` / :data:`ABS`."""
    assert list(a.columns) == list(b.columns), name
    assert a.dtypes.astype(str).tolist() == b.dtypes.astype(str).tolist(), name
    assert len(a) == len(b), name
    for c in a.columns:
        x, y = a[c].reset_index(drop=True), b[c].reset_index(drop=True)
        assert (x.isna() == y.isna()).all(), f"{name}.{c}: missing values differ"
        both = x.notna().to_numpy()
        if x.dtype.kind == "f":
            np.testing.assert_allclose(x[both].to_numpy(), y[both].to_numpy(), rtol=REL,
                                       atol=ABS, err_msg=f"{name}.{c}")
        else:
            assert (x[both] == y[both]).all(), f"{name}.{c}"


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """(logs, the appended workdir after the incremental stages, the full workdir, summaries)."""
    root = tmp_path_factory.mktemp("incremental")
    logs = _logs(root)
    inc, full = root / "inc", root / "full"
    coarse = dict(batch_size=2, workers=1)  # 2 chunks of 2 in a full run: SP13 alone in the update
    run_ingest([logs["old"]], inc, OPTIONS)
    run_split(inc)
    run_fit_coarse(inc, **coarse)
    shutil.copytree(inc, root / "before-update")   # the work directory of the day before
    appended = run_ingest([logs["new"]], inc, OPTIONS, append=True)
    split = run_split(inc, incremental=True)
    fit = run_fit_coarse(inc, incremental=True, **coarse)
    run_ingest([logs["full"]], full, OPTIONS)
    run_split(full)
    run_fit_coarse(full, **coarse)
    return logs, inc, full, {"ingest": appended, "split": split, "fit": fit}


@pytest.mark.slow
def test_append_adds_the_new_rows_and_rejects_the_ingested_ones(field):
    _, inc, full, s = field
    a, f = pd.read_parquet(inc / "measurements.parquet"), pd.read_parquet(full / "measurements.parquet")
    # the rows of one ingest of the whole log, but for where each copy came from
    same = [c for c in a.columns if c not in ("source_file", "source_row")]
    pd.testing.assert_frame_equal(a[same], f[same])
    assert len(a) == 590
    assert s["ingest"]["appended"] == {"added_rows": 5, "measurements_total": 590,
                                       "heliostats_total": 4}
    assert s["ingest"]["heliostats"] == {"SP13": 5}
    rejected = pd.read_parquet(inc / "rejected.parquet")
    # new.csv rows 6 and 7 (1-based data rows): the re-sent copy and the changed copy
    assert rejected[["source_row", "measurement_id", "reason"]].values.tolist() == [
        [6, "100007", "duplicate_of_ingested_row"], [7, "100008", "duplicate_measurement_id"]]
    assert rejected["detail"].iloc[0].startswith("identical to measurement 100007 of heliostat "
                                                 "SQ04 ingested from")
    helio = pd.read_parquet(inc / "heliostats.parquet").set_index("heliostat_id")
    assert helio["n_measurements"].to_dict() == {"SP13": 144, "SQ04": 145, "SS48": 160, "ST20": 141}


@pytest.mark.slow
def test_incremental_stages_compute_only_the_changed_heliostat_and_equal_a_full_run(field):
    _, inc, full, s = field
    for schema in (SPLIT, COARSE_PARAMS, COARSE_PREDICTIONS, REGIMES, REGIME_PARAMS,
                   ROLLING_ORIGIN):
        assert_same_artifact(pd.read_parquet(inc / schema.filename),
                             pd.read_parquet(full / schema.filename), schema.name)
    assert s["split"]["incremental"] == {"computed": 1, "reused": 3, "removed": 0, "why_all": None}
    assert s["fit"]["incremental"] == {"computed": 1, "reused": 3, "removed": 0, "why_all": None}
    assert [h["heliostat_id"] for h in s["fit"]["heliostats"]] == ["SP13"]
    # the update's manifest records the digests a next --incremental run starts from
    m = json.loads((inc / "fit-coarse.manifest.json").read_text())
    assert sorted(m["incremental"]["heliostats"]) == ["SP13", "SQ04", "SS48", "ST20"]


@pytest.mark.slow
def test_unchanged_inputs_keep_the_files_and_other_options_compute_all(field, tmp_path):
    _, inc, _, _ = field
    import shutil

    wd = shutil.copytree(inc, tmp_path / "wd")
    files = {stage: json.loads((wd / f"{stage}.manifest.json").read_text())["files"]
             for stage in ("split-knn", "fit-coarse")}
    split = run_split(wd, incremental=True)
    fit = run_fit_coarse(wd, incremental=True, batch_size=2, workers=1)
    assert split["incremental"] == fit["incremental"] == {"unchanged": True}
    for stage, before in files.items():  # the same files (SHA-256), now listed by the new run
        after = json.loads((wd / f"{stage}.manifest.json").read_text())
        assert {k: v["sha256"] for k, v in after["files"].items()} == {
            k: v["sha256"] for k, v in before.items()}
        assert sorted(after["incremental"]["heliostats"]) == ["SP13", "SQ04", "SS48", "ST20"]
    # a manifest is untrusted: an input naming a stage outside the folder is not looked up, so
    # the run cannot take its inputs as unchanged and checks every heliostat's digest instead
    path = wd / "fit-coarse.manifest.json"
    m = json.loads(path.read_text())
    m["inputs"]["measurements"]["stage"] = f"../{wd.name}/fit-coarse"  # this very file
    path.write_text(json.dumps(m))
    hostile = run_fit_coarse(wd, incremental=True, batch_size=2, workers=1)
    assert hostile["incremental"] == {"computed": 0, "reused": 4, "removed": 0, "why_all": None}
    # another option is a field-wide input: every heliostat again
    again = run_fit_coarse(wd, incremental=True, batch_size=2, workers=1, rolling_origins=3)
    assert again["incremental"]["computed"] == 4 and "field-wide" in again["incremental"]["why_all"]
    assert len(pd.read_parquet(wd / "rolling_origin.parquet").groupby(
        ["heliostat_id", "origin_date"])) <= 4 * 3
    with pytest.raises(ParameterError, match="--incremental"):
        run_fit_coarse(wd, incremental=True, heliostats=["SP13"])


def test_append_without_duplicates_adds_every_row(tmp_path):
    """The usual day: no row is ingested already (the rejection table of none is empty)."""
    logs = _logs(tmp_path)
    new = pd.read_csv(logs["new"]).iloc[:5]          # SP13's 5 rows only
    new.to_csv(tmp_path / "day.csv", index=False)
    run_ingest([logs["old"]], tmp_path / "wd", OPTIONS)
    info = run_ingest([tmp_path / "day.csv"], tmp_path / "wd", OPTIONS, append=True)
    assert info["appended"]["added_rows"] == 5 and info["rejected"] == 0
    assert len(pd.read_parquet(tmp_path / "wd" / "measurements.parquet")) == 585 + 5
    assert len(pd.read_parquet(tmp_path / "wd" / "rejected.parquet")) == 0


def test_append_needs_an_ingested_workdir(tmp_path):
    with pytest.raises(InputError, match="without --append first"):
        run_ingest([SYNTH / "calibration_log.csv"], tmp_path / "empty", OPTIONS, append=True)


def test_heliostat_digest_depends_on_its_own_rows_only():
    df = pd.DataFrame({"heliostat_id": ["A", "B", "A", "B"], "x": [1.0, 2.0, 3.0, 4.0]})
    base = heliostat_digests([df])
    moved = df.assign(x=[1.0, 2.5, 3.0, 4.0])          # one of B's values
    assert heliostat_digests([moved])["A"] == base["A"]
    assert heliostat_digests([moved])["B"] != base["B"]
    grown = pd.concat([df, pd.DataFrame({"heliostat_id": ["B"], "x": [5.0]})])
    assert heliostat_digests([grown])["A"] == base["A"] != heliostat_digests([grown])["B"]
    # a heliostat absent from the second table differs from one with an empty-hash row there
    props = pd.DataFrame({"heliostat_id": ["A"], "y": [0.0]})
    two = heliostat_digests([df, props])
    assert two["A"] != base["A"] and two["B"] != base["B"]
    assert len(set(two.values())) == 2


def test_a_moved_field_prior_changes_that_heliostats_digest_only():
    """fit-coarse hashes each heliostat's prior with its rows (coarse_prior.prior_frame), so a
    prior that moved for one heliostat fits that one again and no other."""
    from heliocal.pipeline.stages.coarse_prior import PriorPlan, prior_frame

    rows = pd.DataFrame({"heliostat_id": ["A", "B", "C"], "x": [1.0, 2.0, 3.0]})
    mean, sigma = np.zeros(28), np.full(28, 1e-3)
    plan = PriorPlan("field", None, priors={"A": {"static-6": (mean, sigma)},
                                            "B": {"static-6": (mean, sigma)}})
    base = heliostat_digests([rows, prior_frame(plan, ["A", "B", "C"])])
    moved_sigma = sigma.copy()
    moved_sigma[3] *= 1.0 + 1e-12                           # the smallest move still counts
    plan.priors["B"] = {"static-6": (mean, moved_sigma)}
    moved = heliostat_digests([rows, prior_frame(plan, ["A", "B", "C"])])
    assert moved["A"] == base["A"] and moved["C"] == base["C"] and moved["B"] != base["B"]
    # a heliostat given no prior (C) hashes differently from one given a prior (A), rows equal
    same_rows = pd.DataFrame({"heliostat_id": ["A", "C"], "x": [1.0, 1.0]})
    two = heliostat_digests([same_rows, prior_frame(plan, ["A", "C"])])
    assert two["A"] != two["C"]


def _files(wd: Path, stage: str) -> dict:
    """rel path -> SHA-256 of the files the stage's manifest lists."""
    return {k: v["sha256"] for k, v in
            json.loads((wd / f"{stage}.manifest.json").read_text())["files"].items()}


@pytest.mark.slow
def test_fit_hybrid_and_sweep_keep_an_unchanged_run_and_retrain_all_after_a_change(field,
                                                                                  tmp_path):
    """fit-hybrid trains heliostats in batches whose membership follows the row counts, so it
    cannot keep some heliostats and train others (a heliostat's networks depend on its
    batch-mates); what ``--incremental`` does for it is keep a run whose inputs, options, seed and
    code are unchanged, and train all otherwise. The sweep keeps such a run the same way, keeps
    every heliostat when an upstream run changed none of its inputs, and trains every heliostat
    when an option changed (the heliostats that change with rows: the test below). Small
    settings: the check is what is kept, not the models' quality."""

    from heliocal.pipeline.models.config import FineConfig, PathConfig
    from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
    from heliocal.pipeline.stages.sweep import run_sweep

    _, inc, _, _ = field
    wd = shutil.copytree(inc, tmp_path / "wd")
    config = FineConfig(max_epochs=15, ensemble=1)
    hybrid = dict(mode="hybrid", weight_decay=1e-3, config=config, workers=1)
    sweep = dict(weight_decays=[1e-2, 0.0], config=config, extra_bands=(), study=0, gp=False,
                 baselines=(), path=PathConfig(stage_epochs=15), workers=1)
    first_h, first_s = run_fit_hybrid(wd, **hybrid), run_sweep(wd, **sweep)
    assert first_h["incremental"] is None and first_s["incremental"]["unchanged"] is False
    before = {stage: _files(wd, stage) for stage in ("fit-hybrid", "sweep")}
    kept_h = run_fit_hybrid(wd, incremental=True, **hybrid)
    kept_s = run_sweep(wd, incremental=True, **sweep)
    assert kept_h["incremental"] == kept_s["incremental"] == {"unchanged": True}
    assert {stage: _files(wd, stage) for stage in before} == before
    assert [r["heliostat_id"] for r in kept_s["selection"]] == [
        r["heliostat_id"] for r in first_s["selection"]] == ["SP13", "SQ04", "SS48", "ST20"]
    # another seed is another run of fit-hybrid: trained again, its models' files differ
    reseeded = run_fit_hybrid(wd, incremental=True, seed=1, **hybrid)
    assert reseeded["incremental"] is None and len(reseeded["heliostats"]) == 4
    assert _files(wd, "fit-hybrid") != before["fit-hybrid"]
    # an upstream run with other options that changed none of the sweep's inputs (fit-coarse's
    # rolling origins): the sweep reads its inputs again and keeps every heliostat, every row as it
    # was (the files' provenance records the new upstream run)
    tables = {name: pd.read_parquet(wd / name) for name in before["sweep"]
              if name.endswith(".parquet")}
    run_fit_coarse(wd, batch_size=2, workers=1, rolling_origins=2)
    kept = run_sweep(wd, incremental=True, **sweep)
    assert kept["incremental"] == {"unchanged": False, "computed": 0, "reused": 4, "removed": 0,
                                   "chunks_computed": 0, "why_all": None}
    for name, df in tables.items():
        pd.testing.assert_frame_equal(pd.read_parquet(wd / name), df, check_exact=True, obj=name)
    # another seed of the sweep is field-wide: every heliostat is trained again
    again = run_sweep(wd, incremental=True, **{**sweep, "seeds": [1]})
    assert again["incremental"]["computed"] == 4
    assert "field-wide" in again["incremental"]["why_all"]
    assert _files(wd, "sweep") != before["sweep"]
    # a run of some heliostats records no digests, so it cannot be incremental: one clear error
    with pytest.raises(ParameterError, match="leave out --heliostat, or leave out --incremental"):
        run_sweep(wd, incremental=True, heliostats=["SP13"], **sweep)


#: Columns of the sweep's artifacts that are measurements of the run, not results: each kept
#: row carries the wall time of the run that trained it.
WALL_COLUMNS = ("wall_time_s",)


def _sweep_tables(wd: Path) -> dict[str, pd.DataFrame]:
    from heliocal.pipeline.artifacts.schemas import SELECTED_PREDICTIONS, SELECTION, SWEEP

    return {s.name: pd.read_parquet(wd / s.filename).drop(columns=list(WALL_COLUMNS),
                                                          errors="ignore")
            for s in (SWEEP, SELECTION, SELECTED_PREDICTIONS)}


def _selected_models(wd: Path) -> dict[str, tuple[dict, dict]]:
    """heliostat -> (configuration, weights) of the sweep's selected models, as ``aim`` reads
    them (through the sweep's manifest, weights checked against the configuration)."""
    from heliocal.pipeline.artifacts.modelfiles import read_model

    out = {}
    for path in sorted((wd / "hybrid" / "selected").glob("*.json")):
        got = read_model(wd, "sweep", "selected", path.stem, hint="sweep")
        if got is not None:
            cfg, state = got
            out[path.stem] = ({k: v for k, v in cfg.items() if k != "weights_sha256"}, state)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("batch_size", [1, 32])
def test_incremental_sweep_trains_the_changed_heliostat_and_equals_a_full_rerun(field, tmp_path,
                                                                                batch_size):
    """The sweep of the day before, then the update (SP13 gains 5 rows) with ``sweep
    --incremental``, against a full sweep of the updated work directory (a copy). The update
    trains SP13 alone and keeps the other three, whatever the chunks: with ``batch_size=1`` every
    heliostat is its own chunk in the full sweep too; with 32 the field's two groups are one
    chunk each, so the full sweep trains SP13 beside SS48 (static-20 both) and its bits must not
    depend on that (the aligned layout, training.MEMBER_ALIGN). ST20 is a study heliostat: its
    study rows are kept with it. Every
    artifact equals the full rerun's bit for bit (structure and every value; only ``wall_time_s``,
    the run's own timing, is left out), and so do the selected models' weights and
    configurations (whose recorded inputs are the updated work directory's); the kept
    heliostats' weights files are carried over as they were."""
    from heliocal.pipeline.models.config import FineConfig, PathConfig
    from heliocal.pipeline.models.selection import SelectionRule
    from heliocal.pipeline.stages.sweep import run_sweep

    root = Path(field[1]).parent
    wd = shutil.copytree(root / "before-update", tmp_path / "wd")
    config = FineConfig(max_epochs=30, ensemble=2)
    # no margin: a network better on validation is selected, so kept heliostats have models too
    eager = SelectionRule(min_improvement=0.0, min_improvement_gp=0.0, alpha=1.0, one_se=False)
    sweep = dict(weight_decays=[1e-2, 0.0], config=config, extra_bands=(), study=["ST20"],
                 n_train=[20], baselines=(), path=PathConfig(stage_epochs=30), workers=1,
                 batch_size=batch_size, rule=eager)
    first = run_sweep(wd, **sweep)
    assert first["incremental"]["why_all"] == "not --incremental"
    day_before = _sweep_tables(wd)
    first_run = json.loads((wd / "sweep.manifest.json").read_text())
    logs = field[0]
    run_ingest([logs["new"]], wd, OPTIONS, append=True)
    run_split(wd, incremental=True)
    run_fit_coarse(wd, incremental=True, batch_size=2, workers=1)
    update = run_sweep(wd, incremental=True, **sweep)
    trained = ["SP13"]
    assert update["incremental"] == {"unchanged": False, "computed": 1, "reused": 3,
                                     "removed": 0, "chunks_computed": 1, "why_all": None}
    assert sorted(update["members_per_heliostat"]) == trained
    full = shutil.copytree(wd, tmp_path / "full")
    rerun = run_sweep(full, **sweep)
    assert rerun["incremental"]["computed"] == 4
    inc_tables, full_tables = _sweep_tables(wd), _sweep_tables(full)
    for name in inc_tables:
        pd.testing.assert_frame_equal(inc_tables[name], full_tables[name], check_exact=True,
                                      obj=name)
    assert (inc_tables["sweep"]["n_train"] == 20).any()        # ST20's study rows are there
    inc_models, full_models = _selected_models(wd), _selected_models(full)
    assert sorted(inc_models) == sorted(full_models)
    for hid, (cfg, state) in inc_models.items():
        assert cfg == full_models[hid][0], hid
        assert sorted(state) == sorted(full_models[hid][1]), hid
        for k, t in state.items():
            assert torch.equal(t, full_models[hid][1][k]), (hid, k)
    # the kept heliostats' weights files are the day before's, carried over (not loaded and
    # saved again): the same file, listed with the first run's id; their configurations are new
    update_run = json.loads((wd / "sweep.manifest.json").read_text())
    kept_weights = [rel for rel in first_run["files"] if rel.endswith(".pt")
                    and not rel.endswith("/SP13.pt")]
    assert kept_weights, "no kept heliostat has a selected model: the check would be empty"
    for rel in kept_weights:
        assert update_run["files"][rel] == first_run["files"][rel], rel
        assert update_run["files"][rel]["run_id"] == first_run["run_id"] != update_run["run_id"]
        config = rel[:-len(".pt")] + ".json"
        assert update_run["files"][config]["run_id"] == update_run["run_id"], config
    # SP13's results moved with its rows (so keeping its chunk by mistake would fail above);
    # the others' are the day before's
    for name, df in day_before.items():
        old, new = (t[t["heliostat_id"] == "SP13"].reset_index(drop=True)
                    for t in (df, inc_tables[name]))
        assert len(old) != len(new) or not old.equals(new), name
        others = lambda t: t[~t["heliostat_id"].isin(trained)].reset_index(drop=True)  # noqa: E731
        pd.testing.assert_frame_equal(others(df), others(inc_tables[name]), check_exact=True)


def test_sweep_digests_follow_what_the_sweep_reads_of_each_heliostat(field):
    """The sweep's per-heliostat digests (:func:`sweep_digests`) hash the heliostat's rows of
    the tables its inputs are taken from: a selected fit's parameter moved on SQ04 changes SQ04's
    digest alone; the coarse_params columns the sweep does not read are not in the tables at
    all, and neither are the presets fit-coarse did not select."""
    from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.stages.sweep_inputs import (SELECTED_FIT_COLUMNS, read_sweep_inputs,
                                                       sweep_digests)

    items = read_sweep_inputs(field[1], None)
    assert sorted(items.digests) == list(items) == ["SP13", "SQ04", "SS48", "ST20"]
    assert list(items.schemas[3].columns) == list(SELECTED_FIT_COLUMNS)
    params = read_artifact(field[1], COARSE_PARAMS)
    fit = params.loc[params["selected"], list(SELECTED_FIT_COLUMNS)]
    assert (fit.groupby("heliostat_id").size() == 28).all()   # the selected preset's, no other
    base = sweep_digests([fit], list(items))
    moved = fit.copy()
    row = moved.index[(moved["heliostat_id"] == "SQ04") & (moved["parameter_index"] == 3)]
    moved.loc[row, "fitted"] += 1e-12
    digests = sweep_digests([moved], list(items))
    assert [h for h in base if digests[h] != base[h]] == ["SQ04"]


def test_value_digest_tells_values_apart_and_equal_values_alike():
    """The digest the sweep's chunks and the report's figures are kept by: equal values (built
    anew) hash alike; the smallest change of a value, a dtype, a column name or a key does not."""
    from heliocal.pipeline.artifacts.incremental import value_digest

    def build():
        return {"frame": pd.DataFrame({"x": [1.0, 2.0], "t": pd.to_datetime(["2024-01-01"] * 2)}),
                "array": np.arange(3.0), "tensor": torch.tensor([0.5, 1.5]), "n": 3,
                "series": pd.Series({"a": 1.0}), "none": None, "nested": [("a", 1.0)]}

    base = value_digest(build())
    assert value_digest(build()) == base
    changes = [("frame", pd.DataFrame({"x": [1.0, np.nextafter(2.0, 3.0)],
                                       "t": pd.to_datetime(["2024-01-01"] * 2)})),
               ("frame", pd.DataFrame({"y": [1.0, 2.0], "t": pd.to_datetime(["2024-01-01"] * 2)})),
               ("array", np.arange(3.0).astype(np.float32)), ("array", np.arange(4.0)),
               ("tensor", torch.tensor([0.5, 1.5], dtype=torch.float64)), ("n", 3.0),
               ("series", pd.Series({"b": 1.0})), ("none", 0), ("nested", [("a", 1)])]
    for key, value in changes:
        assert value_digest({**build(), key: value}) != base, key
    assert value_digest({**build(), "other": None}) != base


def test_value_digest_tells_string_and_time_columns_apart():
    """Frames are hashed column by column, strings as their lengths and bytes: strings whose
    concatenation is the same, a missing string, a time one microsecond later, a value moved
    to the next column each give another digest; equal frames built anew (or sliced out of a
    larger one) hash alike."""
    from heliocal.pipeline.artifacts.incremental import value_digest

    def build(ids=("ab", "c"), t0="2024-01-01 10:00:00", names=("x", "y")):
        return pd.DataFrame({"id": list(ids), "target": list(names),
                             "t": pd.to_datetime([t0, "2024-01-02 00:00:00.000000"], utc=True, format="ISO8601").as_unit("us"),
                             "v": [1.0, 2.0]})

    base = value_digest(build())
    assert value_digest(build()) == base
    wide = pd.concat([build(), build(ids=("zz", "zz"))], ignore_index=True)
    assert value_digest(wide.iloc[:2].reset_index(drop=True)) == base
    for changed in (build(ids=("a", "bc")), build(ids=("ab", None)), build(ids=("ab", "c\0")),
                    build(t0="2024-01-01 10:00:00.000001"), build(names=("y", "x")),
                    build().rename(columns={"id": "target", "target": "id"})):
        assert value_digest(changed) != base
    moved = build()
    moved[["id", "target"]] = moved[["target", "id"]].to_numpy()
    assert value_digest(moved) != base
    texts = pd.DataFrame({"s": pd.Series(["a", "b"], dtype="str")})
    assert value_digest(texts) == value_digest(texts.copy())
    assert value_digest(texts) != value_digest(pd.DataFrame({"s": pd.Series(["ab", ""],
                                                                            dtype="str")}))


def _report_files(wd: Path) -> dict[str, bytes]:
    """Every file of ``wd``'s report but its manifest, with the work directory's path (in
    titles and hints) replaced by ``WD``."""
    rep = wd / "report"
    return {p.relative_to(rep).as_posix(): p.read_bytes().replace(str(wd).encode(), b"WD")
            for p in sorted(rep.rglob("*")) if p.is_file() and not p.name.endswith(".json")
            or p.name == "metrics.json"}


@pytest.mark.slow
def test_incremental_report_keeps_unchanged_figures_and_equals_a_full_report(field, tmp_path):
    """The report of the day before, then the update (SP13 gains 5 rows, every stage
    incremental) with ``report --incremental``, against a full report of the updated work
    directory (a copy). Compared: every file of the report (pages, report.md, metrics.json and
    the figures' PNG bytes; matplotlib draws the same pixels for the same data), the work
    directory's path aside. Kept: SQ04's, SS48's and ST20's own figures; drawn: SP13's and the
    field figures, which hold every heliostat's numbers."""
    from heliocal.pipeline.models.config import FineConfig, PathConfig
    from heliocal.pipeline.stages.report import run_report
    from heliocal.pipeline.stages.sweep import run_sweep

    root = Path(field[1]).parent
    wd = shutil.copytree(root / "before-update", tmp_path / "wd")
    sweep = dict(weight_decays=[1e-2, 0.0], config=FineConfig(max_epochs=20, ensemble=1),
                 extra_bands=(), study=0, baselines=(), path=PathConfig(stage_epochs=20),
                 workers=1, batch_size=1)
    run_sweep(wd, **sweep)
    first = run_report(wd, workers=1)
    assert first["figures_kept"] == 0 and first["figures_drawn"] > 0
    run_ingest([field[0]["new"]], wd, OPTIONS, append=True)
    run_split(wd, incremental=True)
    run_fit_coarse(wd, incremental=True, batch_size=2, workers=1)
    run_sweep(wd, incremental=True, **sweep)
    update = run_report(wd, workers=1, incremental=True)
    full = shutil.copytree(wd, tmp_path / "full", ignore=shutil.ignore_patterns("report"))
    rerun = run_report(full, workers=1)
    inc_files, full_files = _report_files(wd), _report_files(full)
    assert sorted(inc_files) == sorted(full_files)
    for name, data in inc_files.items():
        assert data == full_files[name], name
    figures = sorted(Path(f).name for f in update["figures"])
    assert update["figures_drawn"] + update["figures_kept"] == rerun["figures_drawn"]
    own = lambda hid: {f for f in figures if hid in f}  # noqa: E731
    assert own("SP13") and own("SQ04") and own("SS48") and own("ST20")
    assert update["figures_kept"] == len(own("SQ04") | own("SS48") | own("ST20"))
