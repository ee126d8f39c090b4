"""``heliocal info`` (cli/info.py): provenance of an artifact, artifacts of a work directory.

The work directory is made by the real stages on ``tests/data/good/paint_small`` (BE36, 3
measurements, so ``split-knn --n-test 0 --n-val 0 --k 1`` puts all 3 in training). Expected
hashes are computed here with hashlib from the files' bytes, not taken from heliocal.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest

import heliocal.cli.info  # noqa: F401 - registers `info` on the app
from heliocal.cli.main import app
from heliocal.pipeline import __version__
from heliocal.pipeline.artifacts.store import SCHEMA_VERSION
from heliocal.pipeline.artifacts.provenance import git_revision
from heliocal.pipeline.artifacts.schemas import SPLIT
from workdir_tools import fingerprint, recommit

PAINT_SMALL = Path(__file__).resolve().parent / "data" / "good" / "paint_small"
SPLIT_ARGS = ["--n-test", "0", "--n-val", "0", "--k", "1"]


def _run(runner, *args):
    return runner.invoke(app, [str(a) for a in args])


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _info_json(runner, path: Path) -> dict:
    result = _run(runner, "info", path, "--json")
    assert result.exit_code == 0, result.stderr
    return json.loads(result.stdout)


def _one_line_error(result) -> str:
    assert result.exit_code == 1, (result.stdout, result.stderr)
    assert "Traceback" not in result.output + result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    return result.stderr.splitlines()[0]


@pytest.fixture(scope="module")
def made_workdir(tmp_path_factory) -> Path:
    from typer.testing import CliRunner

    workdir = tmp_path_factory.mktemp("info")
    runner = CliRunner()
    for args in (["ingest", PAINT_SMALL], ["split-knn", *SPLIT_ARGS]):
        result = _run(runner, *args, "--workdir", workdir, "--quiet")
        assert result.exit_code == 0, result.stderr
    return workdir


@pytest.fixture
def workdir(made_workdir, tmp_path) -> Path:
    return Path(shutil.copytree(made_workdir, tmp_path / "run"))


def test_artifact_provenance_json(runner, made_workdir):
    d = _info_json(runner, made_workdir / "split.parquet")
    prov = d["provenance"]
    assert (d["artifact"], d["stage"], d["rows"], d["status"], d["hint"]) == (
        "split", "split-knn", 3, "fresh", None)
    assert [c["name"] for c in d["columns"]] == pd.read_parquet(
        made_workdir / "split.parquet").columns.tolist()
    assert set(SPLIT.column_names()) <= {c["name"] for c in d["columns"]}
    assert prov["schema_version"] == SCHEMA_VERSION == d["reads_schema_version"]
    assert prov["heliocal_version"] == __version__
    assert prov["git_revision"] == git_revision()
    assert prov["command"]  # the command line (just the stage name when run in-process)
    assert prov["seed"] == 0
    # the resolved options: those given and every default
    assert prov["options"] == {"method": "knn", "k": 1, "n_test": 0, "n_val": 0, "n_train": None,
                               "metric": "euclidean", "seed": 0}
    # the input is recorded by the content fingerprint of the measurements table that was read
    measurements_fp = fingerprint(made_workdir / "measurements.parquet")
    assert prov["inputs"] == {"measurements": measurements_fp}
    assert d["inputs"] == {"measurements": {
        "path": str(made_workdir / "measurements.parquet"), "recorded": measurements_fp,
        "current": measurements_fp, "status": "fresh"}}
    manifest = json.loads((made_workdir / "split-knn.manifest.json").read_text())
    assert d["commit"] == {"status": "committed", "stage": "split-knn",
                           "run_id": manifest["run_id"],
                           "manifest": str(made_workdir / "split-knn.manifest.json")}
    assert manifest["files"]["split.parquet"]["sha256"] == _sha(made_workdir / "split.parquet")


def test_ingest_artifact_records_source_and_options(runner, made_workdir):
    d = _info_json(runner, made_workdir / "measurements.parquet")
    assert (d["stage"], d["rows"], d["status"]) == ("ingest", 3, "fresh")
    assert list(d["inputs"]) == [f"source:{PAINT_SMALL}"]
    source = d["inputs"][f"source:{PAINT_SMALL}"]
    assert source["path"] == str(PAINT_SMALL) and source["status"] == "fresh"
    assert source["recorded"] == source["current"]
    assert d["provenance"]["seed"] is None  # ingest has no random step
    opts = d["provenance"]["options"]
    assert (opts["sources"], opts["focal_spot"], opts["max_spot_distance_m"], opts["tower"]) == (
        [str(PAINT_SMALL)], "utis", 25.0, None)


def test_artifact_human_output(runner, made_workdir):
    result = _run(runner, "info", made_workdir / "split.parquet")
    assert result.exit_code == 0, result.stderr
    lines = [" ".join(line.split()) for line in result.stdout.splitlines()]
    for expected in ("artifact split", "stage heliocal split-knn", "seed 0", "status fresh",
                     f"schema version {SCHEMA_VERSION}", f"heliocal {__version__} (git "
                     f"{git_revision()})", "options", "k = 1", 'method = "knn"', "n_train = null",
                     "inputs (content fingerprint of an artifact, SHA-256 of a source)"):
        assert expected in lines, (expected, result.stdout)
    fp = fingerprint(made_workdir / "measurements.parquet")[:12]
    assert any(line.startswith("measurements") and f"{fp} {fp} fresh" in line for line in lines)
    run_id = json.loads((made_workdir / "split-knn.manifest.json").read_text())["run_id"]
    assert f"run {run_id} (split-knn.manifest.json)" in lines
    assert result.stderr == ""


def test_workdir_listing(runner, made_workdir):
    d = _info_json(runner, made_workdir)
    rows = [(Path(a["path"]).name, a["stage"], a["rows"], a["status"]) for a in d["artifacts"]]
    assert rows == [("heliostats.parquet", "ingest", 1, "fresh"),
                    ("measurements.parquet", "ingest", 3, "fresh"),
                    ("rejected.parquet", "ingest", 0, "fresh"),
                    ("split.parquet", "split-knn", 3, "fresh")]
    assert (d["fresh"], d["leftovers"], d["not_artifacts"]) == (True, [], [])
    assert (d["pending_commits"], d["uncommitted_runs"]) == ([], [])
    runs = {r["stage"]: (r["files"], r["pending"], r["problems"]) for r in d["runs"]}
    assert runs == {"ingest": (3, False, []), "split-knn": (1, False, [])}
    result = _run(runner, "info", made_workdir)
    lines = [" ".join(line.split()) for line in result.stdout.splitlines()]
    assert "split.parquet split-knn 3 fresh -" in lines, result.stdout
    split_run = json.loads((made_workdir / "split-knn.manifest.json").read_text())
    assert any(line.startswith(f"split-knn {split_run['run_id']} 1 ") and line.endswith(" ok")
               for line in lines), result.stdout  # the committed runs, each file verified


def test_workdir_listing_flags_stale_incompatible_leftovers_and_foreign(runner, workdir):
    # ingest other data (HeliOS spots): split.parquet no longer matches measurements.parquet
    assert _run(runner, "ingest", PAINT_SMALL, "--focal-spot", "helios", "--workdir", workdir,
                "--quiet").exit_code == 0
    # rejected.parquet claims another schema version (and is committed so: recommit)
    table = pq.read_table(workdir / "rejected.parquet")
    prov = json.loads(table.schema.metadata[b"heliocal"])
    pq.write_table(table.replace_schema_metadata(
        {b"heliocal": json.dumps({**prov, "schema_version": 999}).encode()}),
        workdir / "rejected.parquet")
    recommit(workdir, "rejected.parquet")
    (workdir / ".split.parquet.tmp-abc123").write_bytes(b"PAR1 half")  # an interrupted write
    pd.DataFrame({"a": [1]}).to_parquet(workdir / "notes.parquet")  # not heliocal's

    d = _info_json(runner, workdir)
    status = {Path(a["path"]).name: a["status"] for a in d["artifacts"]}
    assert status == {"heliostats.parquet": "fresh", "measurements.parquet": "fresh",
                      "rejected.parquet": "incompatible", "split.parquet": "stale"}
    split = next(a for a in d["artifacts"] if a["path"].endswith("split.parquet"))
    assert split["inputs"]["measurements"]["status"] == "stale"
    assert split["inputs"]["measurements"]["current"] == fingerprint(workdir / "measurements.parquet")
    assert split["hint"] == f"rerun `heliocal split-knn --workdir {workdir}`"
    assert d["fresh"] is False
    assert d["leftovers"] == [str(workdir / ".split.parquet.tmp-abc123")]
    assert d["not_artifacts"] == [{"path": str(workdir / "notes.parquet"), "reason": (
        f"{workdir / 'notes.parquet'} is a Parquet file but not a heliocal artifact (it has no "
        "heliocal provenance metadata)")}]

    result = _run(runner, "info", workdir)
    assert result.exit_code == 0, result.stderr
    out = result.stdout
    assert f"split.parquet: stale; rerun `heliocal split-knn --workdir {workdir}`" in out
    assert (f"rejected.parquet: incompatible (schema version 999, this heliocal reads "
            f"{SCHEMA_VERSION}); rerun `heliocal ingest --workdir {workdir}`") in out
    assert "leftover of an interrupted write (no stage reads it; safe to delete): " \
           f"{workdir / '.split.parquet.tmp-abc123'}" in out
    lines = [" ".join(line.split()) for line in out.splitlines()]
    assert "split.parquet split-knn 3 stale measurements" in lines, out
    assert "rejected.parquet ingest 0 incompatible -" in lines, out


def test_moved_source_is_unknown(runner, tmp_path):
    source = Path(shutil.copytree(PAINT_SMALL, tmp_path / "paint_small"))
    shutil.copy(PAINT_SMALL.parent / "tower-measurements.json", tmp_path)
    workdir = tmp_path / "run"
    assert _run(runner, "ingest", source, "--workdir", workdir, "--quiet").exit_code == 0
    shutil.rmtree(source)
    d = _info_json(runner, workdir / "measurements.parquet")
    assert d["status"] == "unknown"
    assert d["inputs"][f"source:{source}"]["current"] is None


def test_empty_workdir(runner, tmp_path):
    result = _run(runner, "info", tmp_path)
    assert result.exit_code == 0
    assert result.stdout.strip() == (f"{tmp_path}: no heliocal artifacts (run `heliocal ingest "
                                     f"SOURCE --workdir {tmp_path}` first)")


def test_not_an_artifact_is_one_line_error(runner, tmp_path):
    plain = tmp_path / "plain.parquet"
    pd.DataFrame({"a": [1.0]}).to_parquet(plain)
    assert _one_line_error(_run(runner, "info", plain)) == (
        f"Error: {plain} is a Parquet file but not a heliocal artifact (it has no heliocal "
        "provenance metadata)")
    text = tmp_path / "log.csv"
    text.write_text("heliostat_id,sample_id\n")
    line = _one_line_error(_run(runner, "info", text))
    assert line.startswith(f"Error: {text} is not a readable Parquet file (")
    assert line.endswith("; give a heliocal artifact or a work directory")
    missing = tmp_path / "nothing.parquet"
    assert _one_line_error(_run(runner, "info", missing)) == (
        f"Error: {missing}: no such file or folder; check the path")


def test_help(runner):
    result = _run(runner, "info", "--help")
    assert result.exit_code == 0
    assert "provenance" in result.stdout and "--json" in result.stdout
