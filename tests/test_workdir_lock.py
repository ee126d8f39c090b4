"""The work directory lock: one writing stage at a time, readers never blocked, no stale lock.

A holder is a separate Python process that takes :func:`workdir_lock` for a stage and waits; the
tests check that a second writer (library call and CLI) fails at once with a message naming the
holder's stage, pid, host and start time, that ``heliocal info`` still reads the directory (and
says who writes it), and that SIGKILL of the holder frees the lock immediately.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from heliocal.cli.main import app
from heliocal.pipeline.errors import HeliocalError, InputError, WorkdirBusyError
from heliocal.pipeline.artifacts.workdir_lock import (LOCK_FILENAME, lock_holder, locks_workdir,
                                                      workdir_lock)

HOLDER = """
import sys, time
from heliocal.pipeline.artifacts.workdir_lock import workdir_lock
with workdir_lock(sys.argv[1], sys.argv[2]):
    print("locked", flush=True)
    time.sleep(600)
"""


@pytest.fixture
def holder(tmp_path):
    """A process holding the lock of ``tmp_path / 'wd'`` for stage ``sweep``."""
    wd = tmp_path / "wd"
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(wd), "sweep"],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    yield wd, proc
    if proc.poll() is None:
        proc.kill()
        proc.wait()


@pytest.mark.alone  # "at once" is measured: under 1 s
def test_second_writer_fails_at_once_naming_the_holder(holder):
    wd, proc = holder
    t0 = time.monotonic()
    with pytest.raises(WorkdirBusyError) as err:
        with workdir_lock(wd, "ingest"):
            pass
    assert time.monotonic() - t0 < 1.0  # no waiting
    message = str(err.value)
    assert "\n" not in message and isinstance(err.value, HeliocalError)
    assert message.startswith(f"{wd} is being written by `heliocal sweep` (pid {proc.pid} on this "
                              "machine, started 20")
    assert message.endswith(f"wait for it to finish or stop it (kill {proc.pid}), or use another "
                            "--workdir")
    record = json.loads((wd / LOCK_FILENAME).read_text())
    assert record["stage"] == "sweep" and record["pid"] == proc.pid
    assert lock_holder(wd)["pid"] == proc.pid


@pytest.mark.parametrize("stage", ["split-knn", "fit-coarse", "fit-hybrid", "sweep", "report"])
def test_cli_writers_are_refused_and_readers_are_not(holder, runner, stage):
    wd, proc = holder
    result = runner.invoke(app, [stage, "--workdir", str(wd), "--quiet"])
    assert result.exit_code == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"Error: {wd} is being written by `heliocal sweep` (pid {proc.pid} on this machine"), lines
    info = runner.invoke(app, ["info", str(wd)])
    assert info.exit_code == 0, info.stderr
    assert f"being written now by `heliocal sweep` (pid {proc.pid}" in info.stdout
    assert json.loads(runner.invoke(app, ["info", str(wd), "--json"]).stdout)["writer"]["pid"] == proc.pid


#: Runs the console script's main on argv[1:] in a fresh process and prints, after its exit,
#: its exit code and whether the stages' heavy libraries were imported.
CLI_THEN_MODULES = """
import sys
from heliocal.cli.main import main
sys.argv = ["heliocal", *sys.argv[1:]]
try:
    main()
except SystemExit as exc:
    print(exc.code, "torch" in sys.modules, "pandas" in sys.modules)
"""


@pytest.mark.parametrize("stage", ["fit-coarse", "sweep", "plan"])
def test_a_second_writer_is_refused_before_its_stage_is_imported(holder, stage):
    # the holder's record answers the command before it imports its stage (torch, pandas:
    # seconds), with the message the stage's own lock gives (the test above)
    wd, proc = holder
    argv = [stage, "--workdir", str(wd), "--quiet"] + (["--start", "2024-03-01"] if stage == "plan" else [])
    out = subprocess.run([sys.executable, "-c", CLI_THEN_MODULES, *argv], capture_output=True,
                         text=True, timeout=120)
    assert out.stdout.split() == ["1", "False", "False"], (out.stdout, out.stderr)
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"Error: {wd} is being written by `heliocal sweep` (pid {proc.pid} on this machine"), lines


def test_ingest_is_refused_too(holder, runner, good_dir):
    wd, _ = holder
    result = runner.invoke(app, ["ingest", str(good_dir / "juelich_log_small.csv"), "--workdir",
                                 str(wd), "--quiet"])
    assert result.exit_code == 1 and "is being written by `heliocal sweep`" in result.stderr
    assert not list(wd.glob("*.parquet"))


def test_sigkill_of_the_holder_frees_the_lock(holder):
    wd, proc = holder
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # the file with the dead holder's record stays, but the kernel released its flock
    assert (wd / LOCK_FILENAME).exists() and lock_holder(wd) is None
    with workdir_lock(wd, "ingest"):
        record = json.loads((wd / LOCK_FILENAME).read_text())
        assert (record["stage"], record["pid"]) == ("ingest", os.getpid())
    assert not (wd / LOCK_FILENAME).exists()  # removed at a normal end


def test_reentrant_in_one_thread_exclusive_between_threads(tmp_path):
    wd = tmp_path / "wd"
    seen = {}
    with workdir_lock(wd, "sweep"):
        with workdir_lock(wd, "report"):  # a stage calling another stage's function
            assert lock_holder(wd)["stage"] == "sweep"

        def other():
            try:
                with workdir_lock(wd, "ingest"):
                    seen["got"] = True
            except WorkdirBusyError as exc:
                seen["error"] = str(exc)

        t = threading.Thread(target=other)
        t.start()
        t.join()
        assert "got" not in seen and "`heliocal sweep`" in seen["error"]
    with workdir_lock(wd, "ingest"):  # free again after the outer block
        pass


def test_decorated_stage_locks_its_workdir_argument(tmp_path):
    calls = []

    @locks_workdir("demo")
    def stage(sources, workdir, *, flag=False):
        calls.append(lock_holder(workdir))  # seen from "outside": the lock is held
        return workdir

    wd = tmp_path / "wd"
    assert stage(["x"], wd, flag=True) == wd
    assert calls[0]["stage"] == "demo" and calls[0]["pid"] == os.getpid()
    assert lock_holder(wd) is None


def test_failed_stage_in_a_new_folder_leaves_nothing(runner, tmp_path):
    wd = tmp_path / "new" / "wd"
    result = runner.invoke(app, ["split-knn", "--workdir", str(wd), "--quiet"])
    assert result.exit_code == 1 and "measurements.parquet is missing" in result.stderr
    assert not (tmp_path / "new").exists()


def test_workdir_that_is_a_file_is_one_line_error(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="cannot use it as a work directory"):
        with workdir_lock(f, "ingest"):
            pass
