"""Reliability of the staged pipeline: stage inputs are checked, writes are atomic, runs reproduce.

* Stage inputs: a stage on a work directory with a missing, stale or incompatible input artifact
  exits with code 1 and one line ``Error: ...`` naming the stage to run (pipeline/artifacts.py:
  ``read_artifact`` and ``check_fresh``; freshness compares SHA-256 content hashes, not mtimes).
* Atomic writes: a stage killed (SIGKILL) inside a Parquet write leaves the previous artifact
  byte-identical and only a hidden ``.<name>.tmp-*`` leftover; an exception inside the write
  removes the temporary file. The kill is synchronised, not timed: the child process writes half
  of the real Parquet bytes to the temporary file, reports through a pipe, and sleeps until killed.
* Reproducibility: ingest -> split-knn -> fit-coarse twice, in two work directories, on the same
  sample data and seed give equal tables and equal provenance.

Data: ``sample_data/juelich/paint`` (BE36 177, BF41 170, BH35 149 measurements; see
sample_data/README.md) and ``tests/data/good/paint_small`` (BE36: 3 measurements; 118671 has both
focal-spot detectors, 118750 only HeliOS, 118826 only UTIS).
"""

from __future__ import annotations

import hashlib
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from heliocal.cli.main import app
from heliocal.pipeline import __version__
from heliocal.pipeline.artifacts.store import (SCHEMA_VERSION, check_fresh, read_artifact,
                                               read_provenance)
from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS, REJECTED
from heliocal.pipeline.artifacts.schemas import SPLIT
from heliocal.pipeline.artifacts.workdir_lock import LOCK_FILENAME, lock_holder
from conftest import copy_of
from workdir_tools import recommit

#: end-to-end runs of the stages: `make test` runs them, `make test-fast` skips them
pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
PAINT = REPO / "sample_data" / "juelich" / "paint"
PAINT_SMALL = REPO / "tests" / "data" / "good" / "paint_small"
INGEST_ARTIFACTS = ("measurements.parquet", "heliostats.parquet", "rejected.parquet")
#: Small and quick coarse fit: 6 parameters, one heliostat (about 1 s).
COARSE_ARGS = ["--preset", "static-6", "--heliostat", "BE36"]


def _run(runner, *args: str):
    return runner.invoke(app, [*map(str, args), "--quiet"])


def _one_line_error(result) -> str:
    """The single stderr line of a refused run (exit code 1, no traceback)."""
    assert result.exit_code == 1, (result.exit_code, result.stdout, result.stderr)
    assert "Traceback" not in result.output + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _set_schema_version(path: Path, version: int) -> None:
    """Rewrite ``path`` with provenance claiming another schema version (all else unchanged), and
    record the new bytes in its stage's manifest: a committed artifact of another heliocal."""
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    prov = json.loads(meta[b"heliocal"])
    prov["schema_version"] = version
    meta[b"heliocal"] = json.dumps(prov, sort_keys=True).encode()
    pq.write_table(table.replace_schema_metadata(meta), path, compression="zstd")
    recommit(path.parent, path.name)


@pytest.fixture
def workdir(sample_split, tmp_path) -> Path:
    """A private copy of sample_data/juelich/paint ingested and split (defaults, seed 0; the
    session's shared ``sample_split``, tests/conftest.py)."""
    return copy_of(sample_split, tmp_path / "run")


# ------------------------------------------------------------------------------------------------
# stage inputs: missing, stale, incompatible
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("stage", ["split-knn", "fit-coarse"])
def test_missing_measurements_names_ingest(stage, runner, tmp_path):
    line = _one_line_error(_run(runner, stage, "--workdir", tmp_path))
    assert line == (f"Error: {tmp_path}/measurements.parquet is missing: run "
                    f"`heliocal ingest SOURCE... --workdir {tmp_path}` first")
    assert os.listdir(tmp_path) == []  # nothing written


def test_missing_measurements_report(runner, tmp_path):
    line = _one_line_error(_run(runner, "report", "--workdir", tmp_path))
    assert line == (f"Error: {tmp_path}/measurements.parquet is missing: run "
                    f"`heliocal ingest SOURCE... --workdir {tmp_path}` first")


def test_fit_hybrid_without_coarse_fit_names_fit_coarse(runner, workdir):
    line = _one_line_error(_run(runner, "fit-hybrid", "--workdir", workdir))
    assert line == (f"Error: {workdir}/coarse_params.parquet is missing: run "
                    f"`heliocal fit-coarse --workdir {workdir}` first")


def test_fit_hybrid_refuses_incompatible_or_stale_coarse_fit(runner, workdir, tmp_path):
    assert _run(runner, "fit-coarse", "--workdir", workdir, *COARSE_ARGS).exit_code == 0
    other = Path(shutil.copytree(workdir, tmp_path / "other"))
    _set_schema_version(other / "coarse_params.parquet", 999)
    line = _one_line_error(_run(runner, *HYBRID_ARGS, "--workdir", other))
    assert line == (f"Error: {other}/coarse_params.parquet was written by heliocal {__version__} "
                    f"with schema version 999, but this heliocal reads version {SCHEMA_VERSION}: "
                    f"rerun `heliocal fit-coarse --workdir {other}`")
    assert _run(runner, "ingest", PAINT, "--focal-spot", "helios", "--workdir", workdir).exit_code == 0
    line = _one_line_error(_run(runner, *HYBRID_ARGS, "--workdir", workdir))
    assert line == (f"Error: {workdir}/coarse_params.parquet is stale: measurements.parquet changed "
                    f"after it was written; rerun `heliocal fit-coarse --workdir {workdir}` first")
    assert not (workdir / "hybrid_predictions.parquet").exists()


def test_stale_split_is_refused_by_fit_coarse(runner, workdir):
    # ingest again with other data: HeliOS instead of UTIS focal spots changes measurements.parquet
    before = _sha(workdir / "measurements.parquet")
    assert _run(runner, "ingest", PAINT, "--focal-spot", "helios", "--workdir", workdir).exit_code == 0
    assert _sha(workdir / "measurements.parquet") != before
    line = _one_line_error(_run(runner, "fit-coarse", "--workdir", workdir, *COARSE_ARGS))
    assert line == (f"Error: {workdir}/split.parquet is stale: measurements.parquet changed after "
                    f"it was written; rerun `heliocal split-knn --workdir {workdir}` first")
    assert not (workdir / "coarse_params.parquet").exists()
    # the fix the message names works
    assert _run(runner, "split-knn", "--workdir", workdir).exit_code == 0
    check_fresh(workdir, SPLIT, {"measurements": MEASUREMENTS})


def test_reingest_of_same_data_keeps_split_fresh(runner, workdir):
    # freshness is by content: rewriting identical measurements must not make split.parquet stale
    before = {name: _sha(workdir / name) for name in INGEST_ARTIFACTS}
    assert _run(runner, "ingest", PAINT, "--workdir", workdir).exit_code == 0
    assert {name: _sha(workdir / name) for name in INGEST_ARTIFACTS} == before
    check_fresh(workdir, SPLIT, {"measurements": MEASUREMENTS})  # no error


@pytest.mark.parametrize("artifact, stage, producer", [
    ("measurements.parquet", "split-knn", "ingest"),
    ("measurements.parquet", "fit-coarse", "ingest"),
    ("heliostats.parquet", "fit-coarse", "ingest"),
    ("split.parquet", "fit-coarse", "split-knn"),
])
def test_artifact_of_other_schema_version_is_refused(artifact, stage, producer, runner, workdir):
    _set_schema_version(workdir / artifact, 999)
    line = _one_line_error(_run(runner, stage, "--workdir", workdir, *(
        COARSE_ARGS if stage == "fit-coarse" else [])))
    assert line == (f"Error: {workdir}/{artifact} was written by heliocal {__version__} with schema "
                    f"version 999, but this heliocal reads version {SCHEMA_VERSION}: rerun "
                    f"`heliocal {producer} --workdir {workdir}`")


# ------------------------------------------------------------------------------------------------
# atomic writes
# ------------------------------------------------------------------------------------------------
#: Runs `heliocal ingest` in a child process whose pyarrow.parquet.write_table, for the file
#: named in HELIOCAL_TEST_STOP_IN, writes the first half of the real Parquet bytes to the staged
#: file, reports on the pipe HELIOCAL_TEST_FD and sleeps: the parent kills it inside the write.
#: An artifact written chunk by chunk (pyarrow.parquet.ParquetWriter: measurements.parquet) is
#: stopped the same way when its writer is closed: its row groups are on disk, its footer is not.
#: Only the ingest command is imported (no torch), so the child starts in about a second.
_CHILD = textwrap.dedent("""
    import io, os, sys, time
    import pyarrow.parquet as pq

    real_write_table = pq.write_table
    stop_in = os.environ["HELIOCAL_TEST_STOP_IN"]
    fd = int(os.environ["HELIOCAL_TEST_FD"])

    def staged(where):  # the file inside the run's staging folder ROOT/.txn-ingest-<run>/
        where = str(where)
        return os.path.basename(where) == stop_in and "/.txn-ingest-" in where

    def write_table(table, where, *args, **kwargs):
        if not staged(where):
            return real_write_table(table, where, *args, **kwargs)
        buffer = io.BytesIO()
        real_write_table(table, buffer, *args, **kwargs)
        data = buffer.getvalue()
        with open(where, "wb") as fh:
            fh.write(data[: len(data) // 2])
            fh.flush()
            os.fsync(fh.fileno())
        os.write(fd, str(where).encode())  # inside the write now
        time.sleep(300)

    pq.write_table = write_table
    real_close = pq.ParquetWriter.close

    def close(self):
        if self.is_open and staged(self.where):
            os.write(fd, str(self.where).encode())  # all chunks written, the footer not yet
            time.sleep(300)
        return real_close(self)

    pq.ParquetWriter.close = close
    from heliocal.cli.app import app
    import heliocal.cli.ingest  # noqa: F401 - registers `ingest`
    app(args=sys.argv[1:], prog_name="heliocal")
""")


def _ingest_killed_inside_write(workdir: Path, stop_in: str, *args: str) -> Path:
    """Run ``heliocal ingest ARGS`` in a child, SIGKILL it inside ``stop_in``'s write.

    Returns the temporary file the child was writing.
    """
    read_fd, write_fd = os.pipe()
    env = {**os.environ, "HELIOCAL_TEST_STOP_IN": stop_in, "HELIOCAL_TEST_FD": str(write_fd)}
    child = subprocess.Popen([sys.executable, "-c", _CHILD, "ingest", *args, "--workdir",
                              str(workdir), "--quiet"], env=env, pass_fds=(write_fd,),
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(write_fd)  # the child's copy is the only writer: EOF if it exits without reporting
    try:
        ready, _, _ = select.select([read_fd], [], [], 120)
        message = os.read(read_fd, 4096).decode() if ready else ""
        if not message:
            child.kill()
            pytest.fail(f"the child never reached the write of {stop_in}: "
                        f"{child.communicate()[1].decode()}")
        child.send_signal(signal.SIGKILL)
        assert child.wait(30) == -signal.SIGKILL
        child.stderr.close()
    finally:
        os.close(read_fd)
        if child.poll() is None:
            child.kill()
            child.wait()
    return Path(message)


@pytest.mark.parametrize("stop_in", ["rejected.parquet", "measurements.parquet"])
def test_kill_inside_a_write_leaves_previous_artifact_intact(stop_in, runner, tmp_path):
    workdir = tmp_path / "run"
    # previous complete run: UTIS spots. The killed run would write HeliOS spots (other bytes).
    assert _run(runner, "ingest", PAINT_SMALL, "--workdir", workdir).exit_code == 0
    previous = {name: (workdir / name).read_bytes() for name in INGEST_ARTIFACTS}
    manifest = (workdir / "ingest.manifest.json").read_bytes()
    tmp = _ingest_killed_inside_write(workdir, stop_in, str(PAINT_SMALL), "--focal-spot", "helios")

    # the only leftovers are the killed run's staging folder (the partial file of the interrupted
    # write and what was staged before it) and the workdir lock's file, unlocked: the kernel released
    # the killed stage's lock. measurements.parquet is staged chunk by chunk while the sources are
    # validated and closed last, after rejected.parquet and heliostats.parquet
    staging = tmp.parent
    assert staging.parent == workdir and staging.name.startswith(".txn-ingest-")
    assert sorted(p.name for p in workdir.iterdir() if p.name != LOCK_FILENAME) == sorted(
        [*INGEST_ARTIFACTS, "ingest.manifest.json", staging.name])
    assert lock_holder(workdir) is None
    others = {"rejected.parquet": ["measurements.parquet"],
              "measurements.parquet": ["heliostats.parquet", "rejected.parquet"]}
    assert sorted(p.name for p in staging.iterdir() if p.name not in (stop_in, ".owner")) == \
        others[stop_in]
    assert tmp.stat().st_size > 0
    with pytest.raises(Exception):
        pq.read_table(tmp)  # half a Parquet file: no footer
    # the run never reached its commit: every artifact and the manifest are the previous run's
    assert {name: (workdir / name).read_bytes() for name in INGEST_ARTIFACTS} == previous
    assert (workdir / "ingest.manifest.json").read_bytes() == manifest
    for schema in (MEASUREMENTS, HELIOSTATS, REJECTED):  # every artifact is whole and readable
        read_artifact(workdir, schema)
    # `info` names the leftover; the next run of any stage removes it
    listing = runner.invoke(app, ["info", str(workdir)])
    assert ("leftover of a run that stopped before its commit (no stage reads it; the next run "
            f"removes it; safe to delete): {staging}") in " ".join(listing.stdout.split())
    assert _run(runner, "ingest", PAINT_SMALL, "--workdir", workdir).exit_code == 0
    assert not staging.exists()
    assert {name: (workdir / name).read_bytes() for name in INGEST_ARTIFACTS} == previous


#: What the CLI says when the disk is full: the user's to fix, not a bug in heliocal
#: (errors.resource_error_message).
ENOSPC_LINE = ("Error: No space left on device: no space left on the device (ENOSPC); free space on "
               "that disk or use another --workdir, then rerun the command. This is not a bug in "
               "heliocal: nothing was committed, the stage's previous outputs are still the ones "
               "in use")


@pytest.mark.parametrize("crash, code, message", [
    (OSError(28, "No space left on device"), 1, None),
    (KeyboardInterrupt(), 130, None),
])
def test_crash_inside_a_write_removes_the_staged_files(crash, code, message, runner, tmp_path,
                                                       monkeypatch, capsys):
    from heliocal.cli.main import main

    workdir = tmp_path / "run"
    assert _run(runner, "ingest", PAINT_SMALL, "--workdir", workdir).exit_code == 0
    previous = {name: (workdir / name).read_bytes()
                for name in (*INGEST_ARTIFACTS, "ingest.manifest.json")}
    real_write_table = pq.write_table
    seen = []

    def half_then_crash(table, where, *args, **kwargs):
        real_write_table(table, where, *args, **kwargs)
        Path(where).write_bytes(Path(where).read_bytes()[:100])  # a partial file on disk
        seen.append(Path(where))
        raise crash

    monkeypatch.setattr(pq, "write_table", half_then_crash)
    monkeypatch.setattr(sys, "argv", ["heliocal", "ingest", str(PAINT_SMALL), "--focal-spot",
                                      "helios", "--workdir", str(workdir), "--quiet"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == code
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err
    if code == 1:
        assert err.splitlines() == [ENOSPC_LINE.replace("No space left on device: ", "")]
    # the first write crashed, inside the run's staging folder
    assert seen and seen[0].name == "rejected.parquet"
    assert seen[0].parent.name.startswith(".txn-ingest-")
    assert sorted(os.listdir(workdir)) == sorted(previous)  # staging folder removed
    assert {name: (workdir / name).read_bytes() for name in previous} == previous


def test_artifact_permissions_follow_umask(runner, tmp_path):
    # mkstemp creates 0600 files; an artifact must be an ordinary file (0644 under umask 022)
    old = os.umask(0o022)
    try:
        assert _run(runner, "ingest", PAINT_SMALL, "--workdir", tmp_path).exit_code == 0
    finally:
        os.umask(old)
    assert oct((tmp_path / "measurements.parquet").stat().st_mode & 0o777) == oct(0o644)


# ------------------------------------------------------------------------------------------------
# reproducibility
# ------------------------------------------------------------------------------------------------
#: Columns that measure the run, not the result (wall-clock seconds): left out of the comparison.
TIMING_COLUMNS = {"wall_time_s"}


#: fit-hybrid: BE36 only, 30 epochs (well under a second).
HYBRID_ARGS = ["fit-hybrid", "--heliostat", "BE36", "--max-epochs", "30", "--seed", "0"]


def _pipeline(runner, workdir: Path) -> None:
    stages = [["ingest", PAINT], ["split-knn", "--seed", "0"], ["fit-coarse", *COARSE_ARGS]]
    for args in stages + [HYBRID_ARGS]:
        result = _run(runner, *args, "--workdir", workdir)
        assert result.exit_code == 0, (args, result.stderr)


def _normalized_provenance(path: Path, workdir: Path) -> dict:
    """Provenance with the work directory's path (the only legitimate difference) replaced."""
    text = json.dumps(read_provenance(path), sort_keys=True)
    return json.loads(text.replace(str(workdir), "<workdir>"))


def test_same_inputs_and_seed_give_identical_artifacts(runner, tmp_path):
    first, second = tmp_path / "first", tmp_path / "second"
    _pipeline(runner, first)
    _pipeline(runner, second)
    files = sorted(str(p.relative_to(first)) for p in first.rglob("*")
                   if p.is_file() and not p.name.endswith(".manifest.json"))
    assert files == sorted(str(p.relative_to(second)) for p in second.rglob("*")
                           if p.is_file() and not p.name.endswith(".manifest.json"))
    names = [f for f in files if f.endswith(".parquet")]
    assert names == ["coarse_params.parquet", "coarse_predictions.parquet", "heliostats.parquet",
                     "hybrid_predictions.parquet",
                     "measurements.parquet", "regime_params.parquet", "regimes.parquet",
                     "rejected.parquet", "rolling_origin.parquet", "split.parquet"]
    for name in names:
        a, b = pd.read_parquet(first / name), pd.read_parquet(second / name)
        assert len(a) > 0 or name == "rejected.parquet", name  # the sample keeps all 496 rows
        a, b = a.drop(columns=TIMING_COLUMNS & set(a.columns)), b.drop(columns=TIMING_COLUMNS
                                                                        & set(b.columns))
        floats = [c for c in a.columns if a[c].dtype.kind == "f"]
        other = [c for c in a.columns if c not in floats]
        # strings, ints, bools, timestamps exactly; floats to 1e-12 (threads may reorder sums)
        pd.testing.assert_frame_equal(a[other], b[other], check_exact=True, obj=name)
        pd.testing.assert_frame_equal(a[floats], b[floats], check_exact=False, rtol=1e-12,
                                      atol=0.0, obj=name)
        assert _normalized_provenance(first / name, first) == \
            _normalized_provenance(second / name, second), name
    # the fine model's files: weights exactly equal (fit-hybrid runs single-threaded)
    import torch

    assert [f for f in files if not f.endswith(".parquet")] == ["hybrid/hybrid/BE36.json",
                                                                "hybrid/hybrid/BE36.pt"]
    a, b = (torch.load(d / "hybrid/hybrid/BE36.pt", weights_only=True) for d in (first, second))
    assert list(a) == list(b) and all(torch.equal(a[k], b[k]) for k in a)
    a, b = (json.loads((d / "hybrid/hybrid/BE36.json").read_text()) for d in (first, second))
    assert a == b
    # freshness compares content hashes, so a rerun on the same inputs must write the same bytes
    for name in ("measurements.parquet", "heliostats.parquet", "rejected.parquet", "split.parquet",
                 "coarse_params.parquet"):
        assert _sha(first / name) == _sha(second / name), name
    # the fit did something: BE36's static-6 fit (and, BE36 having breaks, its regime-aware
    # candidates) have finite test errors, and one of them is selected
    params = pd.read_parquet(first / "coarse_params.parquet")
    assert set(params["heliostat_id"]) == {"BE36"}
    assert set(params["preset"]) <= {"static-6", "static-6+offsets", "static-6+drift"}
    assert params.groupby("preset")["selected"].all().sum() == 1
    assert np.isfinite(params["test_error_mrad"]).all()


# ------------------------------------------------------------------------------------------------
# unreadable and incomplete inputs name the stage to rerun
# ------------------------------------------------------------------------------------------------
def test_unreadable_input_artifact_names_the_stage(runner, workdir):
    data = (workdir / "measurements.parquet").read_bytes()
    (workdir / "measurements.parquet").write_bytes(data[: len(data) // 2])  # e.g. a copy cut short
    line = _one_line_error(_run(runner, "split-knn", "--workdir", workdir))
    assert "`heliocal ingest" in line


def test_coarse_fit_made_without_split_is_not_fresh_once_split_exists(runner, tmp_path):
    from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS
    from heliocal.pipeline.errors import StageInputError

    workdir = tmp_path / "run"
    for args in (["ingest", PAINT], ["fit-coarse", *COARSE_ARGS], ["split-knn"]):
        assert _run(runner, *args, "--workdir", workdir).exit_code == 0
    assert "split" not in read_provenance(workdir / "coarse_params.parquet")["inputs"]
    with pytest.raises(StageInputError, match="split.parquet"):  # the check fit-hybrid makes
        check_fresh(workdir, COARSE_PARAMS, {"measurements": MEASUREMENTS,
                                             "heliostats": HELIOSTATS, "split": SPLIT})
