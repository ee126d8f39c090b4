"""Dask addresses and errors (issue 32 finding 6, issue 31): a malformed address is refused in one
line, an unreachable one fails fast and says so, a task's own OSError is not blamed on the
scheduler, and a local cluster interrupted while it starts kills its own processes only.
"""

from __future__ import annotations

import multiprocessing as mp
import time

import pytest

from heliocal.pipeline.errors import ClusterError, ParameterError
from heliocal.pipeline.runtime import parallel
from heliocal.pipeline.runtime.parallel import map_tasks


def _square(x):
    return x * x


def _missing_file(_):
    open("/nonexistent/heliocal-test-input.csv", "rb")


@pytest.mark.parametrize("address,why", [
    ("not a url", "missing port number in address 'not a url'"),
    ("tcp://host", "missing port number in address 'host'"),
    ("tcp://127.0.0.1:99999", "port 99999 is not in 1..65535"),
])
def test_a_malformed_address_is_refused_at_once(address, why):
    """Before: 'not a url' was an internal ValueError."""
    t0 = time.monotonic()
    with pytest.raises(ParameterError) as err:
        map_tasks(_square, [1, 2], dask_address=address)
    assert str(err.value) == (f"--dask-address must be a Dask scheduler address such as "
                              f"tcp://HOST:8786. Got {address!r} instead ({why}).")
    assert time.monotonic() - t0 < 3


def test_an_unreachable_scheduler_fails_fast_and_says_so(monkeypatch):
    """Before: about 30 s, then "The 'dask_address' parameter ... must reach a running Dask
    scheduler", blaming the parameter. Nothing listens on port 1 of this machine."""
    monkeypatch.setattr(parallel, "DASK_CONNECT_TIMEOUT_S", 0.5)
    t0 = time.monotonic()
    with pytest.raises(ClusterError) as err:
        map_tasks(_square, [1, 2], dask_address="tcp://127.0.0.1:1")
    assert time.monotonic() - t0 < 5
    assert str(err.value).startswith("could not reach a Dask scheduler at tcp://127.0.0.1:1 "
                                     "within 0.5 s (")
    assert str(err.value).endswith("start one there (`dask scheduler`) or check --dask-address")


def test_an_oserror_of_a_task_is_raised_as_itself():
    """Before: any OSError raised inside a task became "must reach a running Dask scheduler"."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster:
        assert map_tasks(_square, [3], dask_address=cluster.scheduler_address) == [9]
        with pytest.raises(FileNotFoundError, match="heliocal-test-input.csv"):
            map_tasks(_missing_file, [1], dask_address=cluster.scheduler_address)


def _sleep(seconds):
    time.sleep(seconds)


class _ClusterInterruptedWhileStarting:
    """Starts one worker process, then is interrupted (Ctrl-C) before it is a cluster."""

    started: list = []

    def __init__(self, **kwargs):
        p = mp.get_context("fork").Process(target=_sleep, args=(60,), daemon=True)
        p.start()
        self.started.append(p)
        raise KeyboardInterrupt


def test_an_interrupted_local_cluster_kills_only_its_own_processes(monkeypatch):
    """Before: every multiprocessing child of the process was SIGKILLed, also ones that were not
    the cluster's (another pool's workers, the caller's own)."""
    import distributed

    bystander = mp.get_context("fork").Process(target=_sleep, args=(60,), daemon=True)
    bystander.start()
    monkeypatch.setattr(distributed, "LocalCluster", _ClusterInterruptedWhileStarting)
    try:
        with pytest.raises(KeyboardInterrupt):
            map_tasks(_square, [1, 2], scheduler="dask", workers=1)
        own = _ClusterInterruptedWhileStarting.started[-1]
        own.join(5)
        assert own.exitcode == -9  # the cluster's process: killed
        assert bystander.is_alive()  # not the cluster's: left alone
    finally:
        bystander.kill()
        bystander.join(5)
