"""Spreading per-heliostat work over local processes or a Dask cluster.

Calibration is per heliostat and embarrassingly parallel. :func:`map_tasks` runs a picklable
function over a list of tasks and returns the results in task order, either

* in this process (``workers=1``),
* over ``workers`` local processes (:class:`concurrent.futures.ProcessPoolExecutor`; each
  worker uses one torch thread so that N workers use N cores), or
* as tasks on a Dask distributed cluster (``dask_address="tcp://host:port"``, or
  ``scheduler="dask"`` to start a local cluster).

Every task is deterministic (its own seed, no shared state), so the result does not depend on
where or in which order the tasks ran: artifacts are identical to a sequential run.

Shutdown. When the call is left by an exception (Ctrl-C's ``KeyboardInterrupt``, the CLI's
SIGTERM handler, an error in a task), the local workers are terminated and waited for, and Dask
tasks are cancelled (a local cluster closed) before the exception propagates, so no worker keeps
computing for a caller that is gone. If the caller dies without a chance to clean up (SIGKILL, an
OOM kill), each local worker notices within a fraction of a second through a watchdog thread
that waits on the caller's pid (a Linux pidfd, else polling) and exits; workers ignore SIGINT
(Ctrl-C reaches the whole process group; the caller decides). Dask's local workers exit with
their cluster's process by themselves (distributed closes them when their parent's pipe closes).
The one-thread environment variables the workers need are set only while the pool starts and
restored afterwards, so the caller's environment is unchanged by the call.

A stage that maps several times (``fit-coarse``: the fits, the regime detection, the regime-aware
candidates, the time split's refit) runs inside :func:`shared_pool`: its local calls then share
one process pool instead of starting one each (a worker's start, importing torch and heliocal,
costs about a second of CPU). Leaving the block by an exception stops the pool's workers as above.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import pickle
import select
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, Callable, Sequence

from ..errors import ClusterError, ParameterError, check_choice, check_int
from .process_state import one_thread
from ..vocabulary import Scheduler

__all__ = ["default_workers", "map_tasks", "shared_pool", "warm_up", "warm_up_stage", "SCHEDULERS",
           "STAGE_PRELOADS"]

SCHEDULERS = Scheduler.values()


def default_workers() -> int:
    """The machine's cores (``os.sched_getaffinity`` where available)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # pragma: no cover - not on Linux
        return max(os.cpu_count() or 1, 1)


_ONE_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _environment(values: dict[str, str]):
    """Set environment variables that are unset, for the duration; restore them afterwards."""
    added = [k for k in values if k not in os.environ]
    for k in added:
        os.environ[k] = values[k]
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def _watch_parent(pid: int, poll_seconds: float = 0.5) -> None:
    """Exit this process as soon as process ``pid`` (the caller of :func:`map_tasks`) ends.

    A daemon thread waits on a pidfd of ``pid`` (readable when the process exits; no pid-reuse
    race) or, where pidfds are missing, polls ``pid`` every ``poll_seconds``. It ends the worker
    with ``os._exit``: nothing of a dead caller's task is worth finishing.
    """
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(1)
    except (AttributeError, OSError):
        fd = None

    def alive() -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # pragma: no cover - another user's process took the pid
            return False
        return True

    def watch() -> None:
        if fd is not None:
            while True:
                readable, _, _ = select.select([fd], [], [])
                if readable:
                    break
        else:  # pragma: no cover - Linux before 5.3, other systems
            while alive():
                time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="heliocal-parent-watch", daemon=True).start()


def _init_local_worker(parent_pid: int) -> None:
    """A local pool worker: one thread, ignores Ctrl-C (the caller stops it), dies with the
    caller. torch is set to one thread here only if the fork server imported it; otherwise the
    first chunk of a task that runs torch imports and sets it (:func:`_run_chunk`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _watch_parent(parent_pid)
    _init_worker(torch_threads=False)
    # what the worker starts with (the modules imported in the fork server) lives as long as
    # the worker: out of the collector's sight, its full collections pass over the tasks'
    # objects only (gc.freeze, the documented use for forked workers)
    gc.freeze()


def _init_worker(torch_threads: bool = True) -> None:
    """One thread per worker process (torch and the BLAS behind numpy/scipy): N workers, N cores.
    ``torch_threads=False`` (tasks that run no torch) sets torch's threads only if the process
    has imported torch already, instead of importing it (about 1.3 s) to set them."""
    torch = sys.modules.get("torch")
    if torch is None and torch_threads:
        import torch
    if torch is not None:
        torch.set_num_threads(1)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - comes with scikit-learn
        pass


def _run_chunk(func: Callable, chunk: Sequence[Any], torch_threads: bool = True) -> list:
    _init_worker(torch_threads)
    return [func(task) for task in chunk]


def _run_chunk_pickled(func: Callable, chunk: Sequence[Any], torch_threads: bool = True) -> bytes:
    """:func:`_run_chunk` with the results pickled to bytes in the worker.

    Torch registers its own reducers with multiprocessing: a tensor would travel as a
    shared-memory file descriptor, one per tensor. A result with thousands of them (the state
    dicts of a few hundred networks) exhausts the descriptors passed over the socket ("received
    0 items of ancdata") and breaks the pool. A task's tensors (a sweep's coarse fits) would be
    handed over by a thread of the caller that the worker connects to, and a worker stopped
    during that handshake (SIGTERM) makes the thread print a traceback; so the caller sends
    each chunk :class:`ByValue`. Plain pickle sends both by value.
    """
    return pickle.dumps(_run_chunk(func, chunk, torch_threads), protocol=pickle.HIGHEST_PROTOCOL)


class ByValue:
    """A chunk of tasks that multiprocessing pickles by value (plain pickle: tensors with their
    data, no file descriptor) when it sends it to a worker, which receives the chunk itself."""

    def __init__(self, chunk: Sequence[Any]):
        self.chunk = chunk

    def __reduce__(self):
        return pickle.loads, (pickle.dumps(self.chunk, protocol=pickle.HIGHEST_PROTOCOL),)


def _chunks(tasks: Sequence[Any], n: int) -> list[list[Any]]:
    size = max(1, -(-len(tasks) // n))
    return [list(tasks[i:i + size]) for i in range(0, len(tasks), size)]


def map_tasks(func: Callable, tasks: Sequence[Any], *, workers: int | None = None,
              scheduler: str = "local", dask_address: str | None = None,
              progress: Callable[[int, int], None] | None = None,
              chunks_per_worker: int = 4, torch_threads: bool = True) -> list:
    """``[func(t) for t in tasks]``, spread over processes or a Dask cluster, in task order.

    Parameters
    ----------
    func : a module-level (picklable) function of one task.
    tasks : picklable task descriptions.
    workers : local processes (default :func:`default_workers`); 1 runs in this process.
    scheduler : ``local`` or ``dask``; ``dask_address`` implies ``dask``.
    dask_address : address of a running Dask scheduler (``tcp://HOST:PORT``); with
        ``scheduler="dask"`` and no address a :class:`distributed.LocalCluster` of ``workers``
        processes is started for the call.
    progress : called as ``progress(done, total)`` after each finished chunk.
    chunks_per_worker : tasks are grouped into ``workers * chunks_per_worker`` chunks to keep
        scheduling overhead low while balancing load.
    torch_threads : ``False`` for tasks that run no torch: torch is then not imported to be set
        to one thread, in this process (``workers`` 1, :func:`.process_state.one_thread`) or in
        a worker (:func:`_init_worker`).
    """
    check_choice(scheduler, "scheduler", "map_tasks", SCHEDULERS)
    if dask_address:
        scheduler = "dask"
    workers = default_workers() if workers is None else check_int(workers, "workers", "map_tasks", 1)
    tasks = list(tasks)
    total = len(tasks)
    if not tasks:
        return []
    if scheduler == "dask":
        return _map_dask(func, tasks, workers, dask_address, progress, chunks_per_worker,
                         torch_threads)
    if workers == 1 or total == 1:
        out = []
        with one_thread(blas=True, torch_threads=torch_threads):
            for k, t in enumerate(tasks):
                out.append(func(t))
                if progress:
                    progress(k + 1, total)
        return out
    return _map_local(func, tasks, workers, progress, chunks_per_worker, torch_threads)


#: What each stage's fork server imports (:func:`warm_up_stage`), by command: the stage's module
#: (with it torch and heliocal) and what its tasks import besides.
STAGE_PRELOADS = {
    "fit-coarse": ("heliocal.pipeline.stages.fit_coarse", "ruptures"),
    "fit-hybrid": ("heliocal.pipeline.stages.fit_hybrid",),
    "sweep": ("heliocal.pipeline.stages.sweep",),
    "plan": ("heliocal.pipeline.stages.plan",),
}


def warm_up(modules: Sequence[str], *, workers: int | None = None, scheduler: str = "local",
            dask_address: str | None = None) -> None:
    """Start the local workers' fork server now and import ``modules`` there while the caller
    reads its inputs: the workers that :func:`map_tasks` forks from it later start with them
    imported instead of each importing them on its first task, which costs every worker its own
    CPU time for the heavy imports (torch, heliocal, ``ruptures`` with scipy.stats; measured in
    docs/experiments/regimes-cost.md). A stage calls this first.
    Nothing happens for one worker, a Dask run, without the forkserver start method, or when the
    server already runs (its modules are those of its first start)."""
    import multiprocessing as mp

    workers = default_workers() if workers is None else workers
    if (workers <= 1 or dask_address or scheduler != "local"
            or "forkserver" not in mp.get_all_start_methods()):
        return
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["__main__", *modules])   # __main__: the default preload
    # the server imports numpy and torch: with the one-thread variables, as the pool's workers
    with _environment({var: "1" for var in _ONE_THREAD_ENV}):
        from multiprocessing import forkserver
        forkserver.ensure_running()   # returns once started; the imports run in the server


def warm_up_stage(command: str, *, workers: int | None = None, scheduler: str = "local",
                  dask_address: str | None = None) -> None:
    """:func:`warm_up` with the stage ``command``'s :data:`STAGE_PRELOADS`. The command line
    calls it before it imports the stage (the server's imports of torch and the stage then run
    beside its own, about 2.5 s each); the stage calls it first too, and then finds the server
    running."""
    warm_up(STAGE_PRELOADS[command], workers=workers, scheduler=scheduler,
            dask_address=dask_address)


#: The pools of the running :func:`shared_pool` block by worker count (``None``: no block).
_SHARED_POOLS: dict[int, ProcessPoolExecutor] | None = None


@contextlib.contextmanager
def shared_pool():
    """Within this block (or a function decorated with it), local :func:`map_tasks` calls with
    the same worker count reuse one process pool, started by the first and stopped when the
    block ends (module docstring); an inner block joins the outer one."""
    global _SHARED_POOLS
    if _SHARED_POOLS is not None:
        yield
        return
    _SHARED_POOLS = {}
    try:
        yield
    except BaseException:
        for pool in _SHARED_POOLS.values():
            _stop_pool(pool)
        raise
    else:
        for pool in _SHARED_POOLS.values():
            pool.shutdown(wait=True)
    finally:
        _SHARED_POOLS = None


def _new_pool(workers: int) -> ProcessPoolExecutor:
    import multiprocessing as mp

    ctx = mp.get_context("forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn")
    # the one-thread variables reach the forkserver (started with the first pool) and the workers
    # before numpy loads there; this process's environment is restored when the workers started
    with _environment({var: "1" for var in _ONE_THREAD_ENV}):
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                   initializer=_init_local_worker, initargs=(os.getpid(),))
        try:  # the workers start now, while the variables are set
            for fut in [pool.submit(os.getpid) for _ in range(workers)]:
                fut.result()
        except BaseException:
            _stop_pool(pool)
            raise
    return pool


def _map_local(func, tasks, workers, progress, chunks_per_worker, torch_threads) -> list:
    chunks = _chunks(tasks, workers * chunks_per_worker)
    results: list = [None] * len(chunks)
    done = 0
    shared = _SHARED_POOLS is not None
    pool = _SHARED_POOLS.get(workers) if shared else None
    if pool is None:
        pool = _new_pool(workers)
        if shared:
            _SHARED_POOLS[workers] = pool
    try:
        pending = {pool.submit(_run_chunk_pickled, func, ByValue(c), torch_threads): i
                   for i, c in enumerate(chunks)}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                i = pending.pop(fut)
                results[i] = _loads(fut.result())
                done += len(chunks[i])
                if progress:
                    progress(done, len(tasks))
    except BaseException:
        _stop_pool(pool)
        if shared:
            _SHARED_POOLS.pop(workers, None)
        raise
    if not shared:
        pool.shutdown(wait=True)
    return [r for chunk in results for r in chunk]


def _loads(data: bytes):
    """``pickle.loads`` of a chunk's results with the collector paused: they are many new
    container objects (row dicts, frames) without cycles, and the collections their allocation
    triggers would walk the caller's whole heap again and again, on the core the workers need
    (the measurements: docs/experiments/regimes-cost.md, "The stage's process unpickles results
    with the collector paused")."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        return pickle.loads(data)
    finally:
        if enabled:
            gc.enable()


def _stop_pool(pool: ProcessPoolExecutor, grace_seconds: float = 2.0) -> None:
    """Cancel what has not started, terminate the workers (SIGTERM, then SIGKILL after
    ``grace_seconds``) and wait for them, so none outlives the call."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + grace_seconds
    for p in processes:
        with contextlib.suppress(Exception):
            p.join(max(deadline - time.monotonic(), 0.0))
    for p in processes:
        with contextlib.suppress(Exception):
            if p.is_alive():
                p.kill()
                p.join(1.0)


#: How long a stage waits for a Dask scheduler to answer before it stops [s]: a scheduler that
#: is up answers within a second; an address where none listens should fail at once.
DASK_CONNECT_TIMEOUT_S = 5.0


def _checked_dask_address(address: str) -> str:
    """``address`` if it reads as a Dask scheduler address (``tcp://HOST:PORT``, ``HOST:PORT``,
    ``tls://...``, ``inproc://...``), else :class:`ParameterError`."""
    from distributed.comm import parse_address, parse_host_port

    why = None
    try:
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls"):
            host, port = parse_host_port(location)
            if not host or not 0 < int(port) < 65536:
                why = f"port {port} is not in 1..65535" if host else "no host"
    except (ValueError, TypeError) as exc:
        why = " ".join(str(exc).split())
    if why is not None:
        raise ParameterError(f"--dask-address must be a Dask scheduler address such as "
                             f"tcp://HOST:8786. Got {address!r} instead ({why}).")
    return address


def _connect(address: str, cluster):
    """A Dask client of the scheduler at ``address``; a scheduler that does not answer within
    :data:`DASK_CONNECT_TIMEOUT_S` is a :class:`ClusterError` that says so."""
    from distributed import Client

    try:
        return Client(address, timeout=f"{DASK_CONNECT_TIMEOUT_S:g}s")
    except (OSError, TimeoutError) as exc:
        if cluster is not None:
            raise  # our own local cluster: not the user's address to check
        why = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise ClusterError(f"could not reach a Dask scheduler at {address} within "
                           f"{DASK_CONNECT_TIMEOUT_S:g} s ({why}); start one there (`dask "
                           "scheduler`) or check --dask-address") from None


def _start_local_cluster(workers: int):
    """A :class:`distributed.LocalCluster` of ``workers`` single-threaded processes. Interrupted
    (or failed) while it starts, its worker processes exist without a cluster object to close
    them: the processes it started, and only those, are killed before the exception goes on."""
    import multiprocessing as mp

    from distributed import LocalCluster

    before = set(mp.active_children())
    try:
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=None, host="127.0.0.1")
    except BaseException:
        _kill_child_processes(exclude=before)
        raise


def _map_dask(func, tasks, workers, address, progress, chunks_per_worker, torch_threads) -> list:
    try:
        from distributed import as_completed
        from distributed.comm import CommClosedError
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise ParameterError("The 'scheduler' parameter of map_tasks must be 'local' when Dask "
                             "distributed is not installed. Got 'dask' instead.") from exc
    cluster = None
    interrupted = False
    if address is None:
        cluster = _start_local_cluster(workers)
        address = cluster.scheduler_address
    else:
        address = _checked_dask_address(address)
    try:
        with _connect(address, cluster) as client:
            n = max(len(client.scheduler_info().get("workers", {})), 1)
            chunks = _chunks(tasks, n * chunks_per_worker)
            futures = [client.submit(_run_chunk, func, c, torch_threads, pure=False)
                       for c in chunks]
            try:
                index = {f.key: i for i, f in enumerate(futures)}
                results: list = [None] * len(chunks)
                done = 0
                for fut in as_completed(futures):
                    i = index[fut.key]
                    results[i] = fut.result()  # a task's own exception is raised as it is
                    done += len(chunks[i])
                    if progress:
                        progress(done, len(tasks))
            except CommClosedError as exc:
                interrupted = True
                raise ClusterError(f"lost the connection to the Dask scheduler at {address} while "
                                   f"its tasks ran ({exc}); check the scheduler and rerun the "
                                   "command") from None
            except BaseException:
                # an interrupted or failed call leaves nothing queued or running on the cluster
                interrupted = True
                if cluster is not None:
                    _silence_distributed_logs()
                    _kill_local_workers(cluster)
                else:
                    with contextlib.suppress(Exception):
                        client.cancel(futures, force=True)
                raise
    finally:
        if cluster is not None:
            # interrupted: its workers are dead already, so closing only tidies up; bounded so
            # that a stopped stage exits within seconds even on a busy machine
            with contextlib.suppress(Exception) if interrupted else contextlib.nullcontext():
                cluster.close(timeout=2 if interrupted else None)
    return [r for chunk in results for r in chunk]


def _kill_child_processes(exclude=()) -> None:
    """SIGKILL the processes this process started with multiprocessing, except those in
    ``exclude`` (the children that were there before: another pool's workers, the caller's own).
    Not reaped here: their owners, Dask's nannies, read their exit status as they close."""
    import multiprocessing as mp

    for p in mp.active_children():
        if p in exclude:
            continue
        with contextlib.suppress(Exception):
            p.kill()


def _silence_distributed_logs() -> None:
    """Mute Dask distributed's own loggers for the rest of this process. Called when we stop our
    own LocalCluster on purpose: its comms then report the connections we cut (``CommClosedError``
    tracebacks from background threads, at INFO or ERROR level), which are expected and would
    bury the one line the CLI prints about the interruption."""
    names = [n for n in logging.root.manager.loggerDict
             if n.split(".")[0] in ("distributed", "tornado")]
    for name in ["distributed", "tornado", *names]:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def _kill_local_workers(cluster) -> None:
    """End the worker processes of our own LocalCluster at once (a running task cannot be
    cancelled, and the nannies would give each busy worker 4 s before killing it); the nannies are
    told first not to restart them, so that ``cluster.close()`` then only tidies up."""
    for nanny in list(getattr(cluster, "workers", {}).values()):
        with contextlib.suppress(Exception):
            pid = nanny.pid
            nanny.close_gracefully(reason="heliocal: interrupted")
            if pid:
                os.kill(pid, signal.SIGKILL)
