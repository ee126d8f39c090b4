"""Issue 22: a stage's outputs are one consistent commit, freshness comes from what was read,
partial runs keep the rest, and every reader validates what it reads.

The issue's numbered cases, one test (or a few) each:

1-3. kills between a stage's writes: in test_crash_consistency.py (the harness kills every stage
     after each of its write points; ``test_case_1_...`` and ``test_case_2_...`` there check the
     moments the issue names, and case 3 is checked after every kill of the sweep);
4.   inputs re-ingested while fit-coarse runs: ``test_case_4_*``;
5.   two fit-hybrid runs at once: ``test_case_5_*`` (the second commit is refused; the workdir lock
     of issue 21 will make the second run fail at its start);
6.   partial runs (``--heliostat``) keep the other heliostats: ``test_case_6_*``;
7.   aim and the readers validate what they read; model files; full disk, read-only workdir:
     ``test_case_7_*``;
8.   ``--workdir ./a`` instead of ``a`` keeps everything fresh: ``test_case_8_*``;
9.   implausible inputs at ingest and degenerate heliostats: ``test_case_9_*``.

Data: sample_data/juelich/paint (BE36 177, BF41 170, BH35 149 measurements), small options
(static-6, 20 epochs) so that each stage takes about a second.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import torch

from heliocal.cli.main import app
from heliocal.pipeline.artifacts.store import (check_fresh, read_artifact, read_provenance,
                                               recorded_inputs, write_artifact)
from heliocal.pipeline.artifacts.provenance import table_fingerprint
from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, COARSE_PREDICTIONS
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.errors import SchemaError, StageInputError
from heliocal.pipeline.artifacts.schemas import HYBRID_PREDICTIONS
from heliocal.pipeline.stages.aim import aim_steps, load_model
from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS, REJECTED
from heliocal.pipeline.artifacts.schemas import SPLIT
from heliocal.pipeline.artifacts.manifests import load_manifest
from heliocal.pipeline.artifacts.transaction import transaction
from conftest import copy_of
from workdir_tools import fingerprint, recommit, sha256

#: end-to-end runs of the stages: `make test` runs them, `make test-fast` skips them
pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
PAINT = REPO / "sample_data" / "juelich" / "paint"
#: fit-coarse as these tests need it: one preset, no rolling-origin evaluation (what they check is
#: the transaction around the writes, which the evaluation does not change; test_rolling.py checks it)
COARSE = ["--preset", "static-6", "--workers", "1", "--rolling-origins", "0"]
HYBRID = ["--max-epochs", "20", "--workers", "1"]
SWEEP = ["--n-train", "60", "--wd-max", "1", "--wd-min", "0.1", "--ensemble", "1", "--baselines",
         "none", "--no-octaves", "--max-epochs", "20", "--stage-epochs", "20", "--workers", "1"]
AIM = dict(aim_point_enu=[0.0, 0.0, 50.0], time_utc="2023-06-21T10:00:00Z")


def _run(runner, *args):
    return runner.invoke(app, [str(a) for a in args])


def _ok(runner, *args):
    result = _run(runner, *args, "--quiet")
    assert result.exit_code == 0, (args, result.stdout, result.stderr)
    return result


def _one_line_error(result) -> str:
    """The single stderr line of a refused run (exit code 1): no traceback, no internal error."""
    assert result.exit_code == 1, (result.exit_code, result.stdout, result.stderr)
    err = result.stderr
    assert "Traceback" not in result.output + err and "Aborted" not in result.output + err
    assert "internal error" not in err
    assert len(err.splitlines()) == 1, err
    return err.splitlines()[0]


@pytest.fixture(scope="module")
def fitted(sample_split, tmp_path_factory) -> Path:
    """ingest (3 heliostats) and split-knn (the session's ``sample_split``, copied), fit-coarse
    static-6 and fit-hybrid (BE36)."""
    from typer.testing import CliRunner

    runner = CliRunner()
    wd = copy_of(sample_split, tmp_path_factory.mktemp("txn") / "wd")
    _ok(runner, "fit-coarse", "--workdir", wd, *COARSE)
    _ok(runner, "fit-hybrid", "--workdir", wd, "--heliostat", "BE36", *HYBRID)
    return wd


@pytest.fixture
def wd(fitted, tmp_path) -> Path:
    return Path(shutil.copytree(fitted, tmp_path / "wd"))


# ------------------------------------------------------------------------------------------------
# the transaction itself
# ------------------------------------------------------------------------------------------------
def test_manifest_lists_every_output_with_its_hash_and_run(fitted):
    m = load_manifest(fitted, "fit-hybrid")
    assert sorted(m.files) == ["hybrid/hybrid/BE36.json", "hybrid/hybrid/BE36.pt",
                               "hybrid_predictions.parquet"]
    for rel, entry in m.files.items():
        assert entry["sha256"] == sha256(fitted / rel)  # hashlib over the file's bytes
        assert entry["size"] == (fitted / rel).stat().st_size
        assert entry["run_id"] == m.run_id
    assert m.files["hybrid_predictions.parquet"]["fingerprint"] == fingerprint(
        fitted / "hybrid_predictions.parquet")
    # the inputs are what the run read, each with the fingerprint its stage committed
    assert sorted(m.inputs) == ["coarse_params", "heliostats", "measurements", "split"]
    for label, schema in (("measurements", MEASUREMENTS), ("split", SPLIT),
                          ("coarse_params", COARSE_PARAMS)):
        assert m.inputs[label]["fingerprint"] == fingerprint(fitted / schema.filename)
        assert m.inputs[label]["run_id"] == load_manifest(fitted, schema.producer).run_id
    # the model's config records the weights' hash
    cfg = json.loads((fitted / "hybrid/hybrid/BE36.json").read_text())
    assert cfg["weights_sha256"] == sha256(fitted / "hybrid/hybrid/BE36.pt")


def test_fingerprint_is_the_data_not_the_bytes_or_chunks(wd, tmp_path):
    path = wd / "measurements.parquet"
    table = pq.read_table(path)
    fp = table_fingerprint(table, MEASUREMENTS)
    assert fp == load_manifest(wd, "ingest").files["measurements.parquet"]["fingerprint"]
    # other chunking, other metadata, other compression: same data, same fingerprint
    other = tmp_path / "other.parquet"
    pq.write_table(table.replace_schema_metadata({b"x": b"y"}), other, compression="snappy",
                   row_group_size=7)
    assert sha256(other) != sha256(path)
    assert table_fingerprint(pq.read_table(other), MEASUREMENTS) == fp
    # one changed value: another fingerprint
    df = table.to_pandas()
    df.loc[3, "axis_1_steps"] += 1
    import pyarrow as pa

    changed = pa.Table.from_pandas(df, schema=table.schema, preserve_index=False)
    assert table_fingerprint(changed, MEASUREMENTS) != fp
    # a null and the value zero are different data
    df = table.to_pandas()
    df.loc[0, "qa_sun_spa_diff_deg"] = 0.0
    df2 = table.to_pandas()
    df2.loc[0, "qa_sun_spa_diff_deg"] = np.nan
    a, b = (table_fingerprint(pa.Table.from_pandas(d, schema=table.schema, preserve_index=False),
                              MEASUREMENTS) for d in (df, df2))
    assert a != b


def test_exception_inside_a_stage_commits_nothing(wd, monkeypatch):
    before = {p: sha256(wd / p) for p in ("coarse_params.parquet", "coarse_predictions.parquet",
                                          "fit-coarse.manifest.json")}
    import heliocal.pipeline.stages.fit_coarse as coarse

    real = coarse.write_artifact
    calls = []

    def second_write_fails(df, workdir, schema, **kw):
        calls.append(schema.name)
        if len(calls) == 2:
            raise RuntimeError("boom")
        return real(df, workdir, schema, **kw)

    monkeypatch.setattr(coarse, "write_artifact", second_write_fails)
    with pytest.raises(RuntimeError):
        run_fit_coarse(wd, preset="stone-8", workers=1, rolling_origins=0)
    assert calls == ["coarse_params", "coarse_predictions"]
    assert {p: sha256(wd / p) for p in before} == before  # the first write was never visible
    assert not list(wd.glob(".txn-*"))


def test_a_file_changed_by_hand_is_refused_with_the_stage_to_rerun(wd):
    table = pq.read_table(wd / "split.parquet")
    pq.write_table(table, wd / "split.parquet", compression="snappy")  # same data, other bytes
    with pytest.raises(SchemaError) as exc:
        read_artifact(wd, SPLIT)
    run_id = load_manifest(wd, "split-knn").run_id
    assert str(exc.value) == (
        f"{wd}/split.parquet was changed after `heliocal split-knn` wrote it (its SHA-256 differs "
        f"from split-knn.manifest.json, run {run_id}); rerun `heliocal split-knn --workdir {wd}`")


def test_listed_file_deleted_is_refused_and_unlisted_file_is_not_read(wd):
    (wd / "coarse_predictions.parquet").unlink()
    with pytest.raises(SchemaError, match="coarse_predictions.parquet is missing although the "
                                          "last `heliocal fit-coarse` run"):
        read_artifact(wd, COARSE_PREDICTIONS)
    shutil.copy(wd / "coarse_params.parquet", wd / "sweep.parquet")  # no sweep ever ran
    from heliocal.pipeline.artifacts.schemas import SWEEP as SWEEP_SCHEMA

    with pytest.raises(StageInputError, match="sweep.parquet was not written by a complete "
                                              "`heliocal sweep` run"):
        read_artifact(wd, SWEEP_SCHEMA)


def test_inputs_that_disagree_are_refused_at_commit(wd):
    """Freshness from what was read: a run that read split.parquet (made from measurements M1)
    and then measurements.parquet M2 (re-ingested meanwhile) does not commit."""
    with pytest.raises(StageInputError) as exc:
        with transaction(wd, "fit-coarse"):
            read_artifact(wd, SPLIT)
            run_ingest([PAINT / "BE36"], wd)  # another writer replaces measurements.parquet
            read_artifact(wd, MEASUREMENTS)
            write_artifact(read_artifact(wd, COARSE_PARAMS), wd, COARSE_PARAMS,
                           stage="fit-coarse")
    assert str(exc.value).startswith(f"{wd}/split.parquet was made from another measurements "
                                     "than the one this run read (measurements changed while "
                                     "`heliocal fit-coarse` ran)")


# ------------------------------------------------------------------------------------------------
# case 4: measurements re-ingested while fit-coarse runs
# ------------------------------------------------------------------------------------------------
def test_case_4_reingest_during_fit_coarse_leaves_a_stale_fit(wd, monkeypatch):
    import heliocal.pipeline.stages.fit_coarse as coarse

    old_fp = fingerprint(wd / "measurements.parquet")
    old_ids = set(read_artifact(wd, MEASUREMENTS)["measurement_id"])
    real = coarse.map_tasks

    def reingest_then_fit(*args, **kwargs):  # after fit-coarse read its inputs, before it fits
        run_ingest([PAINT / "BE36"], wd)  # 177 rows of one heliostat instead of 496 of three
        return real(*args, **kwargs)

    monkeypatch.setattr(coarse, "map_tasks", reingest_then_fit)
    run_fit_coarse(wd, preset="static-6", workers=1, rolling_origins=0)
    new_ids = set(read_artifact(wd, MEASUREMENTS)["measurement_id"])
    assert (len(old_ids), len(new_ids)) == (496, 177)
    # the fit records the measurements it read, not the ones present when it wrote
    assert recorded_inputs(wd, COARSE_PARAMS)["measurements"] == old_fp
    assert read_provenance(wd / "coarse_params.parquet")["inputs"]["measurements"] == old_fp
    assert old_fp != fingerprint(wd / "measurements.parquet")
    preds = read_artifact(wd, COARSE_PREDICTIONS)
    assert len(set(preds["measurement_id"]) - new_ids) > 0  # ids that no longer exist...
    with pytest.raises(StageInputError, match="coarse_params.parquet is stale: measurements."
                                              "parquet changed after it was written"):
        check_fresh(wd, COARSE_PARAMS, {"measurements": MEASUREMENTS})
    with pytest.raises(StageInputError, match="is stale"):  # ...so fit-hybrid refuses the fit
        run_fit_hybrid(wd, heliostats=["BE36"])


# ------------------------------------------------------------------------------------------------
# case 5: two fit-hybrid runs at once
# ------------------------------------------------------------------------------------------------
def test_case_5_second_of_two_concurrent_fit_hybrid_runs_is_refused_by_the_lock(wd, monkeypatch):
    """Issue 22's case 5 (an nn-only run and a hybrid run at once on one workdir): the workdir lock
    of issue 21 refuses the second writer at its start with a one-line error naming the running
    one, and the first run commits; nothing of either is lost."""
    import heliocal.pipeline.stages.fit_hybrid as hybrid

    real = hybrid.map_tasks
    seen = {}

    def second_run_while_the_first_trains(*args, **kwargs):
        seen["out"] = subprocess.run(
            [sys.executable, "-m", "heliocal.cli.main", "fit-hybrid", "--mode", "hybrid",
             "--heliostat", "BF41", *HYBRID, "--workdir", str(wd), "--quiet"],
            capture_output=True, text=True, timeout=300)
        return real(*args, **kwargs)

    monkeypatch.setattr(hybrid, "map_tasks", second_run_while_the_first_trains)
    run_fit_hybrid(wd, mode="nn-only", heliostats=["BE36"],
                   config=hybrid.FineConfig(max_epochs=20), workers=1)
    out = seen["out"]
    assert out.returncode == 1
    assert out.stderr.count("\n") == 1 and "is being written by `heliocal fit-hybrid`" in out.stderr
    pred = read_artifact(wd, HYBRID_PREDICTIONS)
    assert sorted(set(zip(pred["heliostat_id"], pred["model"]))) == [("BE36", "hybrid"),
                                                                     ("BE36", "nn-only")]
    assert not list(wd.glob(".txn-*"))


def test_case_5_without_a_working_lock_the_second_run_does_not_commit(wd, monkeypatch):
    """Where the lock cannot work (two machines on a file system without locks), the
    transaction's own check remains: the hybrid run (another process, run past the lock as such
    a machine would) commits while the nn-only run trains; the nn-only run then refuses to commit
    instead of dropping the hybrid run's rows."""
    import heliocal.pipeline.stages.fit_hybrid as hybrid

    before = load_manifest(wd, "fit-hybrid").run_id
    real = hybrid.map_tasks
    unlocked = ("import sys; from heliocal.pipeline.models.config import FineConfig; from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid; "
                "run_fit_hybrid.__wrapped__(sys.argv[1], mode='hybrid', heliostats=['BF41'], "
                "config=FineConfig(max_epochs=20), workers=1)")

    def other_process_commits(*args, **kwargs):
        out = subprocess.run([sys.executable, "-c", unlocked, str(wd)], capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        return real(*args, **kwargs)

    monkeypatch.setattr(hybrid, "map_tasks", other_process_commits)
    with pytest.raises(StageInputError) as exc:
        run_fit_hybrid(wd, mode="nn-only", heliostats=["BE36"],
                       config=hybrid.FineConfig(max_epochs=20), workers=1)
    assert "another `heliocal fit-hybrid` run committed" in str(exc.value)
    after = load_manifest(wd, "fit-hybrid")
    assert after.run_id != before
    pred = read_artifact(wd, HYBRID_PREDICTIONS)
    # the other run's work is all there: BE36 (kept from before) and BF41 (its own), hybrid mode
    assert sorted(set(zip(pred["heliostat_id"], pred["model"]))) == [("BE36", "hybrid"),
                                                                     ("BF41", "hybrid")]
    assert not list(wd.glob(".txn-*"))
    # rerun when the other has finished: both modes, nothing lost
    monkeypatch.setattr(hybrid, "map_tasks", real)
    run_fit_hybrid(wd, mode="nn-only", heliostats=["BE36"],
                   config=hybrid.FineConfig(max_epochs=20), workers=1)
    pred = read_artifact(wd, HYBRID_PREDICTIONS)
    assert sorted(set(zip(pred["heliostat_id"], pred["model"]))) == [
        ("BE36", "hybrid"), ("BE36", "nn-only"), ("BF41", "hybrid")]


# ------------------------------------------------------------------------------------------------
# case 6: partial runs keep the other heliostats
# ------------------------------------------------------------------------------------------------
def test_case_6_fit_coarse_for_one_heliostat_keeps_the_others(wd, runner):
    params, preds = read_artifact(wd, COARSE_PARAMS), read_artifact(wd, COARSE_PREDICTIONS)
    _ok(runner, "fit-coarse", "--workdir", wd, "--heliostat", "BE36", "--preset", "stone-8",
        "--workers", "1", "--rolling-origins", "0")
    new_params, new_preds = read_artifact(wd, COARSE_PARAMS), read_artifact(wd, COARSE_PREDICTIONS)
    assert sorted(new_params["heliostat_id"].unique()) == ["BE36", "BF41", "BH35"]
    for old, new in ((params, new_params), (preds, new_preds)):
        keep_old = old[old["heliostat_id"] != "BE36"].reset_index(drop=True)
        keep_new = new[new["heliostat_id"] != "BE36"].reset_index(drop=True)
        pd.testing.assert_frame_equal(keep_old, keep_new)  # the others exactly as they were
    # stone-8 and, BE36 having breaks, the regime-aware candidates on it (models/regime_fit.py)
    regime_models = {"stone-8+offsets", "stone-8+drift"}
    assert set(new_params.loc[new_params["heliostat_id"] == "BE36", "preset"]) - regime_models \
        == {"stone-8"}
    assert set(new_preds.loc[new_preds["heliostat_id"] == "BE36", "model"]) - regime_models \
        == {"nominal", "stone-8"}
    check_fresh(wd, COARSE_PARAMS, {"measurements": MEASUREMENTS, "split": SPLIT})
    out = aim_steps(wd, "BF41", model="coarse", **AIM)  # other heliostats still have their fit
    assert np.isfinite(out["axis_1_steps"])


def test_case_6_partial_run_after_other_inputs_keeps_only_what_it_fitted(wd, runner, caplog):
    _ok(runner, "ingest", PAINT, "--focal-spot", "helios", "--workdir", wd)
    _ok(runner, "split-knn", "--workdir", wd)
    _ok(runner, "fit-coarse", "--workdir", wd, "--heliostat", "BE36", *COARSE)
    # the other heliostats' fits were made from other measurements: not kept as if fresh
    assert sorted(read_artifact(wd, COARSE_PARAMS)["heliostat_id"].unique()) == ["BE36"]
    check_fresh(wd, COARSE_PARAMS, {"measurements": MEASUREMENTS, "split": SPLIT})


def test_case_6_fit_hybrid_and_sweep_for_one_heliostat_keep_the_others(wd, runner):
    _ok(runner, "fit-hybrid", "--workdir", wd, "--heliostat", "BF41", *HYBRID)
    pred = read_artifact(wd, HYBRID_PREDICTIONS)
    assert sorted(pred["heliostat_id"].unique()) == ["BE36", "BF41"]
    assert load_model(wd, "hybrid", "BE36") is not None and load_model(wd, "hybrid", "BF41")
    from heliocal.pipeline.artifacts.schemas import (SELECTED_PREDICTIONS, SELECTION,
                                                     SWEEP as SWEEP_SCHEMA)

    _ok(runner, "sweep", "--workdir", wd, "--heliostat", "BE36", *SWEEP)
    first = {s.name: read_artifact(wd, s) for s in (SWEEP_SCHEMA, SELECTION, SELECTED_PREDICTIONS)}
    _ok(runner, "sweep", "--workdir", wd, "--heliostat", "BF41", *SWEEP)
    for s in (SWEEP_SCHEMA, SELECTION, SELECTED_PREDICTIONS):
        df = read_artifact(wd, s)
        assert sorted(df["heliostat_id"].unique()) == ["BE36", "BF41"], s.name
        old = first[s.name].drop(columns=["wall_time_s"], errors="ignore").reset_index(drop=True)
        kept = df[df["heliostat_id"] == "BE36"].drop(columns=["wall_time_s"], errors="ignore")
        pd.testing.assert_frame_equal(old, kept.reset_index(drop=True), obj=s.name)


def test_split_knn_has_no_partial_run(runner, tmp_path):
    """split-knn splits every heliostat at once (it has no --heliostat option), so it has nothing
    to merge: its help lists its options (docs/split.md) but not --heliostat, and --heliostat is
    refused as a usage error (click's exit code 2) before anything is written."""
    result = _run(runner, "split-knn", "--help")
    assert result.exit_code == 0, (result.exit_code, result.stdout, result.stderr)
    for option in ("--workdir", "--method", "--n-test", "--n-val", "--n-train", "--seed"):
        assert option in result.stdout, option
    assert "--heliostat" not in result.stdout
    refused = _run(runner, "split-knn", "--workdir", tmp_path, "--heliostat", "BE36")
    assert refused.exit_code == 2, (refused.exit_code, refused.stdout, refused.stderr)
    assert "No such option: --heliostat" in refused.stderr
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------------------------
# case 7: aim and the readers validate what they read
# ------------------------------------------------------------------------------------------------
def test_case_7_hand_made_selection_is_refused_by_aim(wd, runner):
    pd.DataFrame({"heliostat_id": ["BE36"], "model": ["hybrid"]}).to_parquet(
        wd / "selection.parquet")
    line = _one_line_error(_run(runner, "aim", "--workdir", wd, "--heliostat", "BE36",
                                "--target", "0,0,50", "--time", "2023-06-21T10:00Z"))
    assert line == (f"Error: {wd}/selection.parquet was not written by a complete `heliocal "
                    "sweep` run (no sweep.manifest.json lists it: made by hand, by an older "
                    "heliocal or by an interrupted run); rerun `heliocal sweep --workdir "
                    f"{wd}`")


def test_case_7_changed_or_stale_selection_is_refused_by_aim(wd, runner):
    _ok(runner, "sweep", "--workdir", wd, "--heliostat", "BE36", *SWEEP)
    args = ["aim", "--workdir", wd, "--heliostat", "BE36", "--target", "0,0,50", "--time",
            "2023-06-21T10:00Z"]
    assert _run(runner, *args).exit_code == 0
    good = (wd / "selection.parquet").read_bytes()
    table = pq.read_table(wd / "selection.parquet")
    df = table.to_pandas()
    df["model"] = "hybrid" if df["model"].iloc[0] == "coarse" else "coarse"
    import pyarrow as pa

    pq.write_table(pa.Table.from_pandas(df, schema=table.schema, preserve_index=False),
                   wd / "selection.parquet")
    line = _one_line_error(_run(runner, *args))
    assert line.startswith(f"Error: {wd}/selection.parquet was changed after `heliocal sweep` "
                           "wrote it")
    (wd / "selection.parquet").write_bytes(good)
    _ok(runner, "fit-coarse", "--workdir", wd, "--preset", "stone-8", "--workers", "1",
        "--rolling-origins", "0")
    line = _one_line_error(_run(runner, *args))
    assert line == (f"Error: {wd}/selection.parquet is stale: coarse_params.parquet changed "
                    f"after it was written; rerun `heliocal sweep --workdir {wd}` first")


def _forge(wd: Path, rel: str, data: bytes, weights: bool = True) -> None:
    """Replace a model file and make everything agree with it (manifest; for weights also the
    config's weights_sha256): a damaged file that only the loader itself can catch."""
    (wd / rel).write_bytes(data)
    recommit(wd, rel)
    if weights:
        cfg_rel = rel.replace(".pt", ".json")
        cfg = json.loads((wd / cfg_rel).read_text())
        cfg["weights_sha256"] = hashlib.sha256(data).hexdigest()
        (wd / cfg_rel).write_text(json.dumps(cfg))
        recommit(wd, cfg_rel)


class NotATensor:  # a pickled object that torch.load(weights_only=True) must refuse
    def __reduce__(self):
        return (print, ("this would run",))


def _torch_bytes(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


@pytest.mark.parametrize("damage, expected", [
    ("truncated", "{pt} was changed after `heliocal fit-hybrid` wrote it"),
    ("empty", "{pt} is empty, not a torch model file; rerun {hint}"),
    ("garbage", "{pt} is not a readable torch model file (truncated or corrupt: "),
    ("pickle", "{pt} was refused: it holds objects other than tensors (heliocal loads model files "
               "with weights_only=True and never runs code from them: "),
    ("other shapes", "{pt} holds weights of other layer sizes than its configuration BE36.json "
                     "describes; rerun {hint}"),
    ("config not json", "{cfg} is not a valid model configuration ("),
    ("config of other weights", "{pt} is not the weights file its configuration BE36.json was "
                                "written with (weights_sha256 differs); rerun {hint}"),
])
def test_case_7_damaged_model_files_give_one_line_errors(damage, expected, wd, runner):
    pt, cfg = wd / "hybrid/hybrid/BE36.pt", wd / "hybrid/hybrid/BE36.json"
    hint = f"`heliocal fit-hybrid --workdir {wd} --mode hybrid`"
    good = pt.read_bytes()
    if damage == "truncated":
        pt.write_bytes(good[: len(good) // 2])
    elif damage == "empty":
        _forge(wd, "hybrid/hybrid/BE36.pt", b"")
    elif damage == "garbage":
        _forge(wd, "hybrid/hybrid/BE36.pt", b"PK\x03\x04 not really a zip" * 10)
    elif damage == "pickle":
        _forge(wd, "hybrid/hybrid/BE36.pt", _torch_bytes({"layers.0.weight": NotATensor()}))
    elif damage == "other shapes":
        state = torch.load(io.BytesIO(good), weights_only=True)
        state = {k: torch.cat([v, v], dim=1) for k, v in state.items()}
        _forge(wd, "hybrid/hybrid/BE36.pt", _torch_bytes(state))
    elif damage == "config not json":
        _forge(wd, "hybrid/hybrid/BE36.json", b"{not json", weights=False)
    elif damage == "config of other weights":
        _forge(wd, "hybrid/hybrid/BE36.pt", _torch_bytes(torch.load(io.BytesIO(good),
                                                                    weights_only=True)) + b"\0",
               weights=False)
    line = _one_line_error(_run(runner, "aim", "--workdir", wd, "--heliostat", "BE36", "--model",
                                "hybrid", "--target", "0,0,50", "--time", "2023-06-21T10:00Z"))
    assert line.startswith("Error: " + expected.format(pt=pt, cfg=cfg, hint=hint)), line
    assert line.endswith(hint), line  # what to do: the command that writes the model again
    assert "weights_only=False" not in line


#: (stage command, what fails, the error) for the resource-limit cases: a full disk and a
#: read-only or forbidden work directory are the user's to fix, never "internal error".
RESOURCE_CASES = [
    (["ingest", str(PAINT / "BE36")], "parquet", errno.ENOSPC),
    (["fit-coarse", *COARSE], "parquet", errno.EDQUOT),
    (["fit-hybrid", "--heliostat", "BE36", *HYBRID], "model", errno.ENOSPC),
    (["report"], "model", errno.ENOSPC),  # report figures are written like model files
    (["split-knn"], "commit", errno.ENOSPC),
    (["split-knn"], "mkdir", errno.EROFS),
    (["fit-coarse", *COARSE], "mkdir", errno.EACCES),
    (["ingest", str(PAINT / "BE36")], "arrow text", errno.ENOSPC),
]


@pytest.mark.parametrize("argv, where, code", RESOURCE_CASES,
                         ids=[f"{a[0]}-{w}-{errno.errorcode[c]}" for a, w, c in RESOURCE_CASES])
def test_case_7_full_disk_and_read_only_workdir_are_the_users_to_fix(argv, where, code, wd,
                                                                      monkeypatch, capsys):
    from heliocal.cli.main import main
    import heliocal.pipeline.artifacts.transaction as transaction

    before = {p.name: sha256(p) for p in wd.iterdir() if p.is_file()}
    text = os.strerror(code)

    def fail(*args, **kwargs):
        raise OSError(code, text, str(wd / "some-file"))

    if where == "parquet":
        monkeypatch.setattr(pq, "write_table", fail)
        monkeypatch.setattr(pq.ParquetWriter, "write_table", fail)
    elif where == "arrow text":  # pyarrow's own form: no errno attribute, "[errno N]" in the text
        def arrow_fail(*args, **kwargs):
            raise OSError(f"Error writing bytes to file. Detail: [errno {code}] {text}")
        monkeypatch.setattr(pq, "write_table", arrow_fail)
        monkeypatch.setattr(pq.ParquetWriter, "write_table", arrow_fail)
    elif where == "model":
        monkeypatch.setattr(transaction.StageTransaction, "write_bytes", fail)
    elif where == "commit":
        real_replace = os.replace

        def replace(src, dst, *a, **k):
            if str(dst).endswith(".manifest.json"):
                fail()
            return real_replace(src, dst, *a, **k)
        monkeypatch.setattr(transaction.os, "replace", replace)
    elif where == "mkdir":  # tests run as root, whom chmod does not stop: the OS call fails
        real_mkdir = Path.mkdir

        def mkdir(self, *a, **k):
            if self.name.startswith(".txn-"):
                fail()
            return real_mkdir(self, *a, **k)
        monkeypatch.setattr(Path, "mkdir", mkdir)
    monkeypatch.setattr(sys, "argv", ["heliocal", *argv, "--workdir", str(wd), "--quiet"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 1
    err = capsys.readouterr().err
    assert "internal error" not in err and "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and err.splitlines()[-1] == errors[0], err  # after any warnings
    err = errors[0]
    name = errno.errorcode[code]
    assert f"({name}); " in err and "This is not a bug in heliocal" in err, err
    if where not in ("arrow text",):
        assert err.startswith(f"Error: {wd / 'some-file'}: "), err
    # nothing was committed: every file of the work directory is as it was, no staging left
    assert {p.name: sha256(p) for p in wd.iterdir() if p.is_file()} == before
    assert not list(wd.glob(".txn-*"))


@pytest.mark.skipif(os.geteuid() == 0, reason="root is not stopped by file permissions")
def test_case_7_read_only_workdir_by_permissions(wd, runner):  # pragma: no cover - root in CI
    os.chmod(wd, 0o555)
    try:
        line = _one_line_error(_run(runner, "split-knn", "--workdir", wd))
    finally:
        os.chmod(wd, 0o755)
    assert "permission denied (EACCES)" in line and "not a bug in heliocal" in line


# ------------------------------------------------------------------------------------------------
# case 8: the command line's spelling is not an input
# ------------------------------------------------------------------------------------------------
def test_case_8_workdir_spelled_differently_keeps_models_fresh(tmp_path, monkeypatch, runner):
    monkeypatch.chdir(tmp_path)
    _ok(runner, "ingest", PAINT / "BE36", "--workdir", "a")
    _ok(runner, "split-knn", "--workdir", "a")
    _ok(runner, "fit-coarse", "--workdir", "a", *COARSE)
    _ok(runner, "fit-hybrid", "--workdir", "a", *HYBRID)
    fp = fingerprint(Path("a/coarse_params.parquet"))
    _ok(runner, "fit-coarse", "--workdir", "./a", *COARSE)
    assert fingerprint(Path("a/coarse_params.parquet")) == fp  # the same fit
    from heliocal.cli.info import describe_workdir

    d = describe_workdir(Path("a"))
    assert {Path(a["path"]).name: a["status"] for a in d["artifacts"]} == {
        name: "fresh" for name in ("coarse_params.parquet", "coarse_predictions.parquet",
                                   "heliostats.parquet", "hybrid_predictions.parquet", "regimes.parquet",
                                   "regime_params.parquet", "measurements.parquet",
                                   "rejected.parquet", "split.parquet", "rolling_origin.parquet",
                                       "field_prior.parquet")}
    result = _run(runner, "aim", "--workdir", "./a", "--heliostat", "BE36", "--model", "hybrid",
                  "--target", "0,0,50", "--time", "2023-06-21T10:00Z")
    assert result.exit_code == 0, result.stderr
    assert json.loads(result.stdout)["model"] == "hybrid"


# ------------------------------------------------------------------------------------------------
# case 9: implausible inputs at ingest, degenerate heliostats
# ------------------------------------------------------------------------------------------------
BAD = REPO / "tests" / "data" / "bad"
GOOD = REPO / "tests" / "data" / "good"


def test_case_9_implausible_years_are_rejected_with_the_reason(tmp_path, runner):
    _ok(runner, "ingest", BAD / "timestamps_implausible.csv", "--workdir", tmp_path)
    rej = read_artifact(tmp_path, REJECTED).sort_values("source_row")
    assert rej["reason"].tolist() == ["implausible_timestamp"] * 3
    assert rej["detail"].tolist()[0] == ("timestamp '1700-06-03T09:20:02Z' is before --time-min "
                                         "1990-01-01T00:00:00+00:00 (the plausible range of a "
                                         "calibration)")
    assert rej["detail"].tolist()[2].startswith("timestamp '9999-12-31T23:59:59Z' is after "
                                                "--time-max ")
    m = read_artifact(tmp_path, MEASUREMENTS)
    assert len(m) == 7
    # the nanosecond timestamp of data row 6 (2022-03-02T10:56:04.123456789Z) is kept, truncated
    # to the microsecond (the artifact's unit)
    row6 = m[m["source_row"] == 6]["timestamp"].iloc[0]
    assert row6 == pd.Timestamp("2022-03-02T10:56:04.123456Z")
    # the range is an option: with --time-min 1600 and --time-max 2400 only 9999 is refused
    _ok(runner, "ingest", BAD / "timestamps_implausible.csv", "--workdir", tmp_path,
        "--time-min", "1600-01-01", "--time-max", "2400-01-01")
    rej = read_artifact(tmp_path, REJECTED)
    assert rej["source_row"].tolist() == [5]
    kept = read_artifact(tmp_path, MEASUREMENTS)
    assert sorted(kept["timestamp"].dt.year.unique().tolist())[:1] == [1700]


def test_case_9_day_month_timestamps_need_a_date_format(tmp_path, runner):
    _ok(runner, "ingest", BAD / "timestamp_day_month.csv", "--workdir", tmp_path)
    rej = read_artifact(tmp_path, REJECTED)
    assert rej[["source_row", "reason"]].values.tolist() == [[4, "ambiguous_timestamp"]]
    line = _one_line_error(_run(runner, "ingest", BAD / "timestamps_day_month.csv", "--workdir",
                                tmp_path / "b"))
    assert "pass --date-format" in line
    _ok(runner, "ingest", BAD / "timestamps_day_month.csv", "--workdir", tmp_path / "c",
        "--date-format", "%d.%m.%Y %H:%M:%S%z")
    got = read_artifact(tmp_path / "c", MEASUREMENTS).sort_values("source_row")["timestamp"]
    iso = read_artifact(tmp_path, MEASUREMENTS).sort_values("source_row")
    # read day first: the same instants as the ISO log (row 4 was 03.06.2022 = 3 June)
    ref = pd.read_csv(GOOD / "juelich_log_small.csv")["timestamp"]
    assert [t.isoformat() for t in got] == [pd.Timestamp(t).isoformat() for t in ref]
    assert len(iso) == 9


def test_case_9_infinite_and_overflowing_env_values_are_blanked(tmp_path, runner):
    text = (GOOD / "juelich_log_small.csv").read_text().splitlines()
    header = text[0].split(",")
    col = header.index("temperature")
    rows = [line.split(",") for line in text[1:]]
    rows[0][col], rows[1][col], rows[2][col], rows[3][col] = "inf", "1e308", "-inf", "nan"
    log = tmp_path / "log.csv"
    log.write_text("\n".join([text[0]] + [",".join(r) for r in rows]) + "\n")
    shutil.copy(GOOD / "tower-measurements.json", tmp_path)
    _ok(runner, "ingest", log, "--workdir", tmp_path / "wd")
    m = read_artifact(tmp_path / "wd", MEASUREMENTS).sort_values("source_row")
    assert len(m) == 10  # the rows are kept: their measurement is fine
    assert m["env_temperature"].isna().tolist() == [True] * 4 + [False] * 6
    assert m["qa_env_blanked"].tolist()[:4] == ["env_temperature=inf", "env_temperature=1e+308",
                                                 "env_temperature=-inf", ""]  # NaN: just missing
    assert np.isfinite(m["env_temperature"].dropna()).all()


def _synthetic_workdir(tmp_path: Path, rows: pd.DataFrame) -> Path:
    from test_hybrid import HELIOSTAT_ROW

    wd = tmp_path / "syn"
    write_artifact(rows, wd, MEASUREMENTS, stage="test")
    write_artifact(pd.DataFrame([dict(HELIOSTAT_ROW, n_measurements=len(rows))]), wd, HELIOSTATS,
                   stage="test")
    return wd


@pytest.mark.parametrize("kind", ["identical", "narrow", "wide"])
def test_case_9_degenerate_heliostat_is_flagged_in_fit_and_report(kind, tmp_path):
    from heliocal.pipeline.stages.report import run_report
    from heliocal.pipeline.stages.split import run_split
    from test_hybrid import synthetic_measurements

    rows = synthetic_measurements(150)
    if kind == "identical":  # 60 copies of one measurement (ids differ)
        rows = pd.concat([rows.iloc[[0]]] * 60, ignore_index=True)
        rows["measurement_id"] = [f"{200000 + i}" for i in range(60)]
    elif kind == "narrow":  # the 12 rows whose sun lies within 10 deg of the first row's sun
        s = rows[["sun_e", "sun_n", "sun_u"]].to_numpy()
        rows = rows[np.degrees(np.arccos(np.clip(s @ s[0], -1, 1))) <= 10].reset_index(drop=True)
    wd = _synthetic_workdir(tmp_path, rows)
    n_test, n_val = (10, 10) if kind != "narrow" else (2, 2)
    run_split(wd, n_test=n_test, n_val=n_val)
    summary = run_fit_coarse(wd, preset="auto", robust_start="never", workers=1)
    params = read_artifact(wd, COARSE_PARAMS)
    flag = set(params["fit_degenerate"])
    assert len(flag) == 1
    flag = flag.pop()
    h = summary["heliostats"][0]
    if kind == "identical":
        assert flag == "all 40 training rows are identical"
        # what the issue saw: a perfect score on identical rows
        assert h["presets"][h["selected"]]["test"] < 0.01
    elif kind == "narrow":
        assert flag.startswith(f"the {len(rows) - 4} training rows ({len(rows) - 4} distinct, sun "
                               "positions within ")
        assert flag.endswith("of the 6 parameters of static-6")
    else:
        assert flag == ""
    report = run_report(wd)
    text = Path(report["markdown"]).read_text()
    note = "SYN1: degenerate training data ("
    assert (note in text) == (kind != "wide")
    assert ("SYN1 (degenerate data)" in text) == (kind != "wide")


def test_output_names_cannot_leave_the_work_directory(wd):
    """Defence in depth (ingest validates heliostat ids): a model file named from an id with '..'
    or '/' is refused with a one-line error, not written outside the work directory."""
    from heliocal.pipeline.errors import InputError
    from heliocal.pipeline.artifacts.modelfiles import write_model

    # (modelfiles refuses the id as a file name first; the transaction refuses any path leaving it)
    with pytest.raises(InputError, match="cannot be used as a file name in hybrid/hybrid"):
        with transaction(wd, "fit-hybrid") as txn:
            write_model(txn, "hybrid", "../../escaped", {}, {})
    assert not (wd.parent / "escaped.pt").exists() and not list(wd.glob(".txn-*"))
    with pytest.raises(InputError, match="cannot name a file inside the work directory"):
        with transaction(wd, "fit-hybrid") as txn:
            txn.write_bytes("hybrid/../../escaped.pt", b"x")
    assert not (wd.parent / "escaped.pt").exists() and not list(wd.glob(".txn-*"))
