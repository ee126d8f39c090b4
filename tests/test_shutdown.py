"""Stopping a stage: SIGTERM, Ctrl-C and SIGKILL of a running 2-worker sweep leave no process.

A small simulated field (2 heliostats x 70 measurements) is ingested, split and coarse-fitted once,
and a quick sweep writes the "previous" artifacts. Each test then starts the real console script
``heliocal sweep --workers 2`` (default settings: about a minute of work) with a unique marker in
its environment, waits until its two worker processes run, stops it, and checks, reading
``/proc`` (no ps, no psutil):

* within 5 s no process carrying the marker is left (parent, forkserver, workers, Dask workers,
  multiprocessing's resource tracker);
* SIGTERM exits with 143 and Ctrl-C (SIGINT to the whole process group, as a terminal sends it)
  with 130, each after exactly one ``Error: ...`` line on stderr; SIGKILL leaves the workers to
  notice by themselves (their watchdog) since the parent gets no chance to clean up;
* every file of the work directory is byte-identical to before (nothing half-written or
  fresh-looking), no hidden temporary file is left, and the workdir lock is free again.

The Dask path is checked the same way with ``--scheduler dask`` (a LocalCluster of 2 worker
processes).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.stages.simulate import write_field
from heliocal.pipeline.stages.split import run_split
from heliocal.pipeline.stages.sweep import run_sweep
from heliocal.pipeline.artifacts.transaction import staging_in_use
from heliocal.pipeline.artifacts.workdir_lock import LOCK_FILENAME, lock_holder, workdir_lock

#: slow (a minute of sweeps) and alone: the 5-s window for the processes to go, and the workers'
#: watchdog of a second, must not be stretched by other tests' work beside them
pytestmark = [pytest.mark.slow, pytest.mark.alone,
              pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc")]

HELIOCAL = Path(sys.executable).with_name("heliocal")
MARKER = "HELIOCAL_TEST_RUN"


def _marked(tag: str) -> dict[int, dict]:
    """Live processes whose environment carries ``MARKER=tag``: pid -> {ppid, cmdline}."""
    needle = f"{MARKER}={tag}".encode()
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/environ", "rb") as fh:
                if needle not in fh.read().split(b"\0"):
                    continue
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:  # gone meanwhile, or not ours
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if fields[0] == "Z":  # a zombie is dead; only its parent's wait() is missing
            continue
        out[int(entry)] = {"ppid": int(fields[1]), "cmd": cmd}
    return out


def _digest(workdir: Path) -> dict[str, str]:
    """SHA-256 of every file under ``workdir`` (relative name -> hash), hidden ones included."""
    return {str(p.relative_to(workdir)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(workdir.rglob("*")) if p.is_file() and p.name != LOCK_FILENAME}


@pytest.fixture(scope="module")
def field_workdir(tmp_path_factory) -> Path:
    """ingest + split-knn + fit-coarse (static-6) + a quick sweep of a small simulated field."""
    root = tmp_path_factory.mktemp("shutdown")
    write_field(simulate_field(2, seed=3, measurements=(70, 70)), root / "field")
    wd = root / "work"
    run_ingest([root / "field"], wd)
    run_split(wd, n_test=15, n_val=10)
    run_fit_coarse(wd, preset="static-6", workers=1, rolling_origins=0)
    from heliocal.pipeline.models.config import FineConfig, PathConfig

    # "previous" artifacts that only have to stay as they are: no study, one quick path
    run_sweep(wd, n_train=[20], weight_decays=[1.0, 0.0], seeds=[0], baselines=(),
              config=FineConfig(max_epochs=20, ensemble=1), workers=1,
              path=PathConfig(stage_epochs=20), study=0)
    return wd


def _start(workdir: Path, tag: str, scheduler: str) -> subprocess.Popen:
    env = dict(os.environ, **{MARKER: tag})
    return subprocess.Popen(
        [str(HELIOCAL), "sweep", "--workdir", str(workdir), "--workers", "2",
         "--scheduler", scheduler, "--quiet"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,  # its own process group, as a command started in a terminal
        preexec_fn=_foreground_signals)


def _foreground_signals() -> None:
    """Ctrl-C at its default, as for a command in a terminal's foreground. A runner started as a
    background job of a non-interactive shell (``make test &``, CI wrappers) ignores SIGINT, the
    ignore is inherited, and Python then installs no KeyboardInterrupt handler: the sweep would
    rightly ignore the test's Ctrl-C (a background job is not meant to receive it)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for_workers(proc: subprocess.Popen, tag: str, scheduler: str, timeout: float = 90) -> dict:
    """Wait until the run's two worker processes exist (local: children of the forkserver;
    dask: processes started with multiprocessing's spawn), then let them work: 0.5 s for the
    local workers (forked with the stage imported, they compute at once), 1.5 s for Dask's
    (spawned, they import heliocal first)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        procs = _marked(tag)
        if scheduler == "local":
            workers = [p for p, d in procs.items() if d["ppid"] in procs and d["ppid"] != proc.pid]
        else:
            workers = [p for p, d in procs.items() if "spawn_main" in d["cmd"]]
        if len(workers) >= 2:
            time.sleep(0.5 if scheduler == "local" else 1.5)
            return procs
        time.sleep(0.2)
    proc.kill()
    pytest.fail(f"the workers of the sweep did not start within {timeout} s")


def _survivors_after(tag: str, seconds: float) -> dict:
    deadline = time.monotonic() + seconds
    while True:
        left = _marked(tag)
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.1)


@pytest.mark.parametrize("scheduler,how", [
    ("local", "SIGTERM"), ("local", "SIGINT"), ("local", "SIGKILL"),
    ("dask", "SIGTERM"), ("dask", "SIGKILL"),
])
def test_stopped_sweep_leaves_no_worker_and_no_new_artifact(field_workdir, scheduler, how):
    before = _digest(field_workdir)
    tag = uuid.uuid4().hex
    proc = _start(field_workdir, tag, scheduler)
    try:
        running = _wait_for_workers(proc, tag, scheduler)
        assert len(running) >= 3, running  # the sweep itself and at least its 2 workers
        if how == "SIGTERM" and scheduler == "local":
            # meanwhile, a second writer on the same workdir is refused at once, naming the sweep
            t0 = time.monotonic()
            other = subprocess.run([str(HELIOCAL), "fit-coarse", "--workdir", str(field_workdir),
                                    "--preset", "static-6", "--quiet"],
                                   capture_output=True, text=True, timeout=120)
            assert other.returncode == 1 and other.stderr.count("\n") == 1, other.stderr
            assert (f"is being written by `heliocal sweep` (pid {proc.pid} on this machine, "
                    "started ") in other.stderr
            assert time.monotonic() - t0 < 30  # import time only: it did not wait for the sweep
        if how == "SIGINT":
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole process group
        else:
            os.kill(proc.pid, getattr(signal, how))
        left = _survivors_after(tag, 5.0)
        assert left == {}, f"still running 5 s after {how}: {left}"
        _, stderr = proc.communicate(timeout=30)
    finally:  # a failed check must not leave the run's processes busy
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        for pid in _marked(tag):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
    if how == "SIGKILL":
        assert proc.returncode == -signal.SIGKILL
    else:
        assert proc.returncode == {"SIGTERM": 143, "SIGINT": 130}[how], stderr
        lines = stderr.splitlines()
        # a run that starts after a SIGKILLed one (an earlier case) first removes that run's
        # staging folder and says so: one log record (wrapped to the width of the console)
        removed = " ".join(" ".join(lines[:-1]).split())
        assert not removed or (removed.startswith(f"WARNING {field_workdir}: removed .txn-sweep-")
                               and removed.endswith("(a run that stopped before its commit)")), stderr
        assert lines[-1].startswith(f"Error: {'terminated (SIGTERM)' if how == 'SIGTERM' else 'interrupted (SIGINT)'}; "
                                   "nothing of this run was committed unless it had finished")
    # nothing half-written or fresh-looking: every committed file as before. A stopped run removes
    # its staging folder; a SIGKILLed one cannot, and leaves it uncommitted (no reader looks at
    # it, `heliocal info` lists it, the next run of the stage removes it; docs/reliability.md)
    after = _digest(field_workdir)
    staged_before = {k for k in before if k.startswith(".txn-")}
    staged = {k for k in after if k.startswith(".txn-")}
    folders = {field_workdir / k.split("/", 1)[0] for k in staged}
    assert all(not staging_in_use(f) for f in folders), folders
    if how != "SIGKILL":   # (a run starting removes an earlier killed run's folder)
        assert not staged - staged_before, staged
    after = {k: v for k, v in after.items() if k not in staged}
    before = {k: v for k, v in before.items() if k not in staged_before}
    assert after == before
    assert not list(field_workdir.rglob(".*.tmp-*"))
    # the lock died with the process (after SIGKILL its file may stay, but nobody holds it)
    assert lock_holder(field_workdir) is None
    with workdir_lock(field_workdir, "test"):
        pass
    if how != "SIGKILL":
        assert not (field_workdir / LOCK_FILENAME).exists()
