"""One writing stage per work directory at a time.

Every stage that writes a work directory (``ingest``, ``split-knn``, ``fit-coarse``,
``fit-hybrid``, ``sweep``, ``report``; ``simulate`` for its output folder) holds
:func:`workdir_lock` for its whole run. A second writer on the same directory fails at once with
:class:`~heliocal.pipeline.errors.WorkdirBusyError`, whose one-line message names the running
stage, its pid, host and start time. Readers (``info``, ``aim``) take no lock and are never
blocked.

The lock is an exclusive ``fcntl.flock`` on the hidden file ``DIR/.heliocal.lock``: the kernel
releases it when the holder's process ends, however it ends (also SIGKILL or an OOM kill), so a
lock can never be left stale. The holder writes its stage, pid, host, start time and command line
into the file for the message of the next writer; the file is removed when the stage ends (a
killed holder leaves it behind unlocked, and the next writer takes it over). flock works on local
file systems and on NFS (Linux emulates it with POSIX locks there).

The lock is re-entrant within one thread (a stage that runs another stage's library function on
the same directory does not lock itself out) and exclusive between threads and processes.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import fcntl
import functools
import inspect
import json
import logging
import os
import socket
import stat
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

from ..errors import InputError, WorkdirBusyError
from .paths import kind_of, read_regular

__all__ = ["LOCK_FILENAME", "workdir_lock", "lock_holder", "locks_workdir", "holds_workdir_lock",
           "refuse_if_busy"]

log = logging.getLogger("heliocal.artifacts")

#: The lock file inside a work directory (hidden: no stage reads it as an artifact).
LOCK_FILENAME = ".heliocal.lock"

_held: dict[str, tuple[int, int, int]] = {}  # resolved directory -> (fd, thread id, depth)
_held_guard = threading.Lock()


def lock_holder(workdir: str | os.PathLike) -> dict | None:
    """The holder recorded in ``workdir``'s lock file while a stage runs there, else ``None``.

    Does not lock; a file left behind by a killed stage is not reported (nobody holds it).
    """
    path = Path(workdir) / LOCK_FILENAME
    try:  # never follows a link, never blocks on a FIFO: a planted entry is nobody's lock
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_holder(path) or {}
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def refuse_if_busy(workdir: str | os.PathLike) -> None:
    """Raise :class:`WorkdirBusyError`, with :func:`workdir_lock`'s message, when another process
    or thread writes ``workdir`` now; else return. Takes no lock: the stage's own
    :func:`workdir_lock` still decides. A command asks this before it imports its stage, so a
    second writer hears at once instead of after the imports (torch and the stage: seconds)."""
    if holds_workdir_lock(workdir):   # this thread's own stage, re-entered
        return
    holder = lock_holder(workdir)
    if holder is not None:
        raise WorkdirBusyError(_busy_message(Path(workdir), holder or None))


def _read_holder(path: Path) -> dict | None:
    """The holder's JSON record (retried briefly: a new holder writes it just after locking)."""
    for _ in range(20):
        try:
            data = json.loads(read_regular(path).decode("utf-8"))
            if isinstance(data, dict) and data.get("pid"):
                return data
        except (OSError, ValueError):
            pass
        time.sleep(0.01)
    return None


def _busy_message(workdir: Path, holder: dict | None) -> str:
    if not holder:
        return (f"{workdir} is being written by another heliocal stage (its details are not "
                "readable); wait for it to finish, or use another --workdir")
    pid, host = holder.get("pid"), holder.get("host", "?")
    where = "this machine" if host == socket.gethostname() else f"host {host}"
    return (f"{workdir} is being written by `heliocal {holder.get('stage', '?')}` (pid {pid} on "
            f"{where}, started {holder.get('started', '?')}); wait for it to finish or stop it "
            f"(kill {pid}), or use another --workdir")


@contextlib.contextmanager
def workdir_lock(workdir: str | os.PathLike, stage: str) -> Iterator[Path]:
    """Hold the exclusive write lock of ``workdir`` (created if missing) for ``stage``.

    Fails at once, without waiting, with :class:`WorkdirBusyError` when another process or
    thread holds it. A folder created here and still empty at the end is removed again. Yields
    the lock file's path.
    """
    folder = Path(workdir)
    created = [p for p in (folder, *folder.parents) if not p.exists()]  # innermost first
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{folder}: cannot use it as a work directory ({exc.strerror or exc}); "
                         "give a folder you can write") from exc
    key = str(folder.resolve())
    path = folder / LOCK_FILENAME
    me = threading.get_ident()
    with _held_guard:
        held = _held.get(key)
        if held is not None:
            if held[1] != me:
                raise WorkdirBusyError(_busy_message(folder, _read_holder(path)))
            _held[key] = (held[0], me, held[2] + 1)
    if held is not None:  # re-entered by the same thread
        try:
            yield path
        finally:
            with _held_guard:
                fd, owner, depth = _held[key]
                _held[key] = (fd, owner, depth - 1)
        return
    fd = _acquire(folder, path, stage)
    with _held_guard:
        _held[key] = (fd, me, 1)
    try:
        yield path
    finally:
        with _held_guard:
            del _held[key]
        _release(fd, path)
        for made in created:  # a stage that wrote nothing leaves no empty folder behind
            try:
                made.rmdir()
            except OSError:
                break


def holds_workdir_lock(folder: str | os.PathLike) -> bool:
    """Whether this thread holds :func:`workdir_lock` of ``folder`` (so no other writer is alive
    there)."""
    try:
        key = str(Path(folder).resolve())
    except OSError:
        return False
    with _held_guard:
        held = _held.get(key)
    return held is not None and held[1] == threading.get_ident()


def _open_lock_file(path: Path) -> int:
    """The lock file's descriptor, created if missing, never through a link. A link, FIFO or
    other non-file planted under its name is removed (it cannot be anyone's lock: heliocal
    makes a regular file) with a warning; a folder there is refused."""
    for _ in range(3):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK
                         | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            if exc.errno == errno.EISDIR:
                raise InputError(f"{path} is a folder, not heliocal's lock file; move it away, "
                                 "then rerun the command") from None
            if exc.errno not in (errno.ELOOP, errno.ENXIO):
                raise
            mode = stat.S_IFLNK if exc.errno == errno.ELOOP else os.lstat(path).st_mode
        else:
            mode = os.fstat(fd).st_mode
            if stat.S_ISREG(mode):
                return fd
            os.close(fd)
        log.warning("removed %s: it was %s, not heliocal's lock file (which is made anew)", path,
                    kind_of(mode))
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
    raise InputError(f"{path} keeps being replaced by something other than a file; stop whatever "
                     "writes it, then rerun the command")


def _acquire(folder: Path, path: Path, stage: str) -> int:
    while True:
        fd = _open_lock_file(path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise WorkdirBusyError(_busy_message(folder, _read_holder(path))) from None
        except BaseException:
            os.close(fd)
            raise
        # the previous holder may have removed the file between our open and flock: then we hold
        # a lock on a deleted file, and must lock the file that is there now instead
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    record = {"stage": stage, "pid": os.getpid(), "host": socket.gethostname(),
              "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
              "command": " ".join(["heliocal", *sys.argv[1:]])}
    os.ftruncate(fd, 0)
    os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
    return fd


def _release(fd: int, path: Path) -> None:
    try:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # while still locked: a waiting opener then sees a new file (see _acquire)
        os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the flock


def locks_workdir(stage: str, argument: str = "workdir") -> Callable:
    """Decorator: run a stage function under :func:`workdir_lock` of its ``argument`` folder."""

    def decorator(func: Callable) -> Callable:
        signature = inspect.signature(func)

        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            folder = signature.bind(*args, **kwargs).arguments[argument]
            with workdir_lock(folder, stage):
                return func(*args, **kwargs)

        return wrapper

    return decorator
