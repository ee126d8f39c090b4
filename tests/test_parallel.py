"""Per-heliostat work gives identical artifacts sequentially, on 2 local processes and on Dask.

Expected values: the sequential run itself (each heliostat's fit is deterministic and
independent, so where it runs must not change a single number), and for fit-hybrid the
heliostat-by-heliostat run (a batched program of several heliostats trains each member as it
would train alone, up to floating-point reassociation: 1e-9 mrad).
"""

import pandas as pd
import pytest

from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, COARSE_PREDICTIONS
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.artifacts.schemas import HYBRID_PREDICTIONS
from heliocal.pipeline.models.config import FineConfig
from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
from heliocal.pipeline.runtime.parallel import map_tasks, shared_pool

from conftest import copy_of

#: end-to-end runs of the stages: `make test` runs them, `make test-fast` skips them
pytestmark = pytest.mark.slow


def _square(x):
    return x * x


def test_map_tasks_keeps_order_locally():
    assert map_tasks(_square, list(range(23)), workers=2) == [x * x for x in range(23)]
    assert map_tasks(_square, list(range(5)), workers=1) == [0, 1, 4, 9, 16]


def _worker_view(_):
    import gc
    import os
    import signal

    return ({v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                            "MKL_NUM_THREADS")},
            signal.getsignal(signal.SIGINT) == signal.SIG_IGN, gc.get_freeze_count())


def test_workers_get_one_thread_env_and_the_caller_keeps_its_own(monkeypatch):
    """The workers see OMP/OpenBLAS/MKL at 1 thread and ignore Ctrl-C, and what they start with
    (at least the modules that unpickle this task: thousands of objects) is frozen out of the
    collector's passes; the caller's environment and collector are the same after the call as
    before (the variables were only set while the pool started)."""
    import gc
    import os

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")  # a value of the caller's is not overwritten
    before, frozen = dict(os.environ), gc.get_freeze_count()
    views = map_tasks(_worker_view, list(range(4)), workers=2)
    assert dict(os.environ) == before and gc.get_freeze_count() == frozen
    for env, ignores_sigint, worker_frozen in views:
        assert env["OMP_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == "1"
        assert ignores_sigint
        assert worker_frozen > 1000


def _probe_in_fresh_processes(tmp_path, probe: str, script: str, modes) -> dict[str, str]:
    """What ``script`` prints in a fresh interpreter per mode (its argv[1]), with ``probe``
    saved as the importable module ``probe`` (the workers' task functions). A process has one
    fork server, started with the modules of its first start: this one's may already run."""
    import os
    import subprocess
    import sys

    (tmp_path / "probe.py").write_text(probe)
    out = {}
    for mode in modes:
        proc = subprocess.run([sys.executable, "-c", script, mode], cwd=tmp_path, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(tmp_path)},
                              capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr[-2000:]
        out[mode] = proc.stdout.strip()
    return out


def test_warm_up_imports_the_stage_modules_once_in_the_fork_server(tmp_path):
    """Workers forked after warm_up(modules) start with those modules imported (the fork server
    imported them) and not others, torch's compiler (torch._dynamo) among them; without warm_up
    none is."""
    probe = "import sys\n\n\ndef loaded(name):\n    return name in sys.modules\n"
    script = ("import sys\nfrom heliocal.pipeline.runtime.parallel import map_tasks, warm_up\n"
              "from probe import loaded\n"
              "names = ['heliocal.pipeline.models.regimes', 'heliocal.pipeline.models.simulator',"
              " 'torch._dynamo']\n"
              "if sys.argv[1] == 'warm':\n    warm_up(names[:1], workers=2)\n"
              "print(map_tasks(loaded, names * 2, workers=2))\n")
    out = _probe_in_fresh_processes(tmp_path, probe, script, ("warm", "cold"))
    # the networks' training no longer needs torch._dynamo (models/adam.py): nothing imports it
    assert out == {"warm": "[True, False, False, True, False, False]",
                   "cold": "[False, False, False, False, False, False]"}


def test_workers_of_tasks_without_torch_do_not_import_it(tmp_path):
    """map_tasks(torch_threads=False) (the report's figures): the pool's workers leave torch
    unimported; tasks that run torch (the default) get it imported and on one thread. Fresh
    interpreters, whose fork server preloads nothing (this process's may have torch)."""
    probe = ("import sys\n\n\ndef torch_threads(_):\n"
             "    torch = sys.modules.get('torch')\n"
             "    return None if torch is None else torch.get_num_threads()\n")
    script = ("import sys\nfrom heliocal.pipeline.runtime.parallel import map_tasks\n"
              "from probe import torch_threads\n"
              "print(map_tasks(torch_threads, range(4), workers=2, chunks_per_worker=2,\n"
              "                torch_threads=sys.argv[1] == 'torch'))\n")
    out = _probe_in_fresh_processes(tmp_path, probe, script, ("torch", "none"))
    assert out == {"torch": "[1, 1, 1, 1]", "none": "[None, None, None, None]"}


def test_tasks_with_tensors_travel_by_value_without_a_descriptor_server(tmp_path):
    """A sweep's tasks hold tensors (the coarse fits). Sent through torch's multiprocessing
    reducers each would be a file descriptor, which the caller hands over from a server thread
    that the worker connects to; a worker stopped (SIGTERM) during that handshake made the
    thread print a traceback beside the one `Error:` line (tests/test_shutdown.py, seen once in
    a full run). The chunks now travel pickled by value: the results are the tasks' sums
    (1 + 2 + 3 + 4 + 5 = 15, plus 5 k), and no descriptor server was started."""
    probe = ("def total(task):\n"
             "    return float(task['x'].sum())\n")
    script = ("import torch\nfrom multiprocessing import resource_sharer\n"
              "from heliocal.pipeline.runtime.parallel import map_tasks\n"
              "from probe import total\n"
              "out = map_tasks(total, [{'x': torch.arange(1.0, 6.0) + k} for k in range(6)],\n"
              "                workers=2, chunks_per_worker=2)\n"
              "print(out, resource_sharer._resource_sharer._thread is None)\n")
    out = _probe_in_fresh_processes(tmp_path, probe, script, ("run",))
    assert out == {"run": "[15.0, 20.0, 25.0, 30.0, 35.0, 40.0] True"}


def _fail_on_3(x):
    if x == 3:
        raise ValueError("task 3 failed")
    return x


def test_a_failing_task_stops_the_pool_and_raises():
    import multiprocessing

    with pytest.raises(ValueError, match="task 3 failed"):
        map_tasks(_fail_on_3, list(range(8)), workers=2, chunks_per_worker=4)
    # the pool's workers were terminated and joined, not left behind
    assert not [p for p in multiprocessing.active_children() if "Process" in type(p).__name__
                and p.is_alive()]


def _pid(_):
    import os

    return os.getpid()


def _live_workers() -> list:
    import multiprocessing

    return [p for p in multiprocessing.active_children() if "Process" in type(p).__name__
            and p.is_alive()]


def test_calls_in_a_shared_pool_block_reuse_its_workers_and_the_block_stops_them(monkeypatch):
    """Inside shared_pool() every local call runs on the same two worker processes (started
    once, with the one-thread environment), and none is left when the block ends, normally or
    by an exception; outside, each call has its own pool."""
    import os

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    with shared_pool():
        first = set(map_tasks(_pid, list(range(16)), workers=2))
        views = map_tasks(_worker_view, list(range(4)), workers=2)
        second = set(map_tasks(_pid, list(range(16)), workers=2))
        assert "OMP_NUM_THREADS" not in os.environ
    assert len(first) == 2 and second == first and os.getpid() not in first
    assert all(env["OMP_NUM_THREADS"] == "1" for env, _, _ in views)
    assert _live_workers() == []
    with pytest.raises(ValueError, match="task 3 failed"):
        with shared_pool():
            map_tasks(_pid, list(range(4)), workers=2)
            map_tasks(_fail_on_3, list(range(8)), workers=2)
    assert _live_workers() == []
    assert set(map_tasks(_pid, list(range(16)), workers=2)).isdisjoint(first)


@pytest.fixture(scope="module")
def workdirs(sample_split, tmp_path_factory):
    """Four copies of the sample ingested and split (n_test=30, n_val=20: the session's
    ``sample_split``)."""
    base = tmp_path_factory.mktemp("par")
    return {name: copy_of(sample_split, base / name) for name in ("seq", "local2", "dask", "batched")}


def _fit(workdir, batch_size=1, training_dtype=FineConfig.training_dtype, **kw):
    run_fit_coarse(workdir, preset="static-6", heliostats=["BE36", "BH35"], **kw)
    config = FineConfig(max_epochs=40, patience=40, training_dtype=training_dtype)
    run_fit_hybrid(workdir, weight_decay=1e-3, config=config, batch_size=batch_size, **kw)
    return (pd.read_parquet(workdir / COARSE_PARAMS.filename),
            pd.read_parquet(workdir / COARSE_PREDICTIONS.filename),
            pd.read_parquet(workdir / HYBRID_PREDICTIONS.filename))


def test_local_processes_and_dask_cluster_match_sequential(workdirs):
    from distributed import LocalCluster

    seq = _fit(workdirs["seq"], workers=1)
    par = _fit(workdirs["local2"], workers=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        dsk = _fit(workdirs["dask"], dask_address=cluster.scheduler_address)
    for other in (par, dsk):
        for a, b in zip(seq, other):
            cols = [c for c in a.columns if c != "wall_time_s"]
            pd.testing.assert_frame_equal(a[cols], b[cols], check_exact=True)


def test_fit_hybrid_batched_program_matches_one_heliostat_at_a_time(workdirs):
    # float64: stacking heliostats must not change a training (in float32 the stacked and the
    # single programs round differently in the last bits and drift apart by ~1e-7 mrad)
    one = _fit(workdirs["seq"], workers=1, batch_size=1, training_dtype="float64")[2]
    both = _fit(workdirs["batched"], workers=1, batch_size=2, training_dtype="float64")[2]
    assert len(one) == len(both) == 177 + 149
    pd.testing.assert_series_equal(one["measurement_id"], both["measurement_id"])
    diff = (one["error_mrad"] - both["error_mrad"]).abs().max()
    assert diff < 1e-9
    # the networks trained (this is not the untrained coarse model twice)
    coarse = pd.read_parquet(workdirs["seq"] / COARSE_PREDICTIONS.filename)
    assert not set(one["error_mrad"].round(9)) <= set(coarse["error_mrad"].round(9))


def _many_tensors(n):
    import torch

    return [torch.full((3,), float(k)) for k in range(n)]


def test_worker_results_with_thousands_of_tensors_come_back_whole():
    """A fit-hybrid chunk returns hundreds of state dicts. Torch's multiprocessing reducers
    would send each tensor as a file descriptor, and a few thousand of them broke the process
    pool ("received 0 items of ancdata") on the 2,000-heliostat benchmark; results now travel
    pickled by value. Expected values: the tensors the task built (k at index k)."""
    out = map_tasks(_many_tensors, [20000, 20000], workers=2, chunks_per_worker=1)
    assert len(out) == 2 and all(len(o) == 20000 for o in out)
    assert float(out[1][19999][0]) == 19999.0


class _SeesCollector:
    """Unpickles to an object that records whether the collector ran while it was built."""

    def __reduce__(self):
        return (_collector_state, ())


def _collector_state():
    import gc

    return gc.isenabled()


def test_results_are_unpickled_with_the_collector_paused_and_restored():
    """parallel._loads builds a chunk's results with the garbage collector paused (they are many
    new objects without cycles) and leaves it as it found it, also when unpickling fails."""
    import gc
    import pickle

    from heliocal.pipeline.runtime.parallel import _loads

    assert gc.isenabled()
    assert _loads(pickle.dumps([_SeesCollector(), 1])) == [False, 1]
    assert gc.isenabled()
    with pytest.raises(pickle.UnpicklingError):
        _loads(b"not a pickle")
    assert gc.isenabled()
    gc.disable()
    try:   # a caller that had it off keeps it off
        assert _loads(pickle.dumps(_SeesCollector())) is False and not gc.isenabled()
    finally:
        gc.enable()


def test_each_stage_preload_names_its_own_module_and_importable_ones():
    """The command line starts a stage's fork server from STAGE_PRELOADS before importing the
    stage, and the stage's warm-up then keeps that server: an entry must name the command's own
    stage module first (the stage's functions are what the workers run) and only modules that
    exist (a typo would make the server fail to start)."""
    import importlib.util

    from heliocal.pipeline.runtime.parallel import STAGE_PRELOADS

    assert set(STAGE_PRELOADS) == {"fit-coarse", "fit-hybrid", "sweep", "plan"}
    for command, modules in STAGE_PRELOADS.items():
        assert modules[0] == "heliocal.pipeline.stages." + command.replace("-", "_"), command
        assert all(importlib.util.find_spec(m) is not None for m in modules), modules
