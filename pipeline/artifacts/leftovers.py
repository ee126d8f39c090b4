"""Leftovers of killed stage runs in a work directory, and the owner locks that tell a live
run's folders from a dead one's.

A stage run's staging folder (``.txn-<stage>-<run id>``) and ingest's spill folder
(``.ingest-spill-*``) each hold an owner file that their live writer keeps an ``flock`` on; a
folder whose owner file is not locked belongs to a run that died (a kill, SIGKILL, power), and
the next run removes it (:func:`heliocal.pipeline.artifacts.transaction.recover`). Nothing here
follows a symbolic link: a link named like a leftover is removed itself, never what it points to.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import stat
from pathlib import Path

from .manifests import STAGING_PREFIX, all_manifests
from .paths import is_real_dir

__all__ = ["OWNER_FILENAME", "SPILL_PREFIX", "BUSY", "try_lock", "unlock",
           "has_staging_folder", "stale_staging_folders", "leftovers", "staging_in_use",
           "remove_leftover"]

#: The file in a staging or spill folder that its live writer holds an ``flock`` on.
OWNER_FILENAME = ".owner"

#: Prefix of ingest's spill folders (:mod:`heliocal.pipeline.stages.ingest`), removed with the
#: other leftovers of killed runs.
SPILL_PREFIX = ".ingest-spill-"

#: What :func:`try_lock` returns when a live writer holds the lock.
BUSY = object()


def try_lock(path: Path):
    """An open file of the owner file ``path`` holding an exclusive ``flock``; ``None`` when there
    is no such regular file (missing, or a link: never followed), so no live writer; ``BUSY``
    when another process holds it (a live transaction)."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    fh = open(fd, "rb", closefd=True)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        fh.close()
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        fh.close()
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return BUSY
        raise
    return fh


def unlock(lock) -> None:
    """Release a lock :func:`try_lock` took."""
    if lock is not None and lock is not BUSY:
        lock.close()


def has_staging_folder(root: str | os.PathLike) -> bool:
    """Whether anything in ``root`` is named like a staging folder: without one, no committed run
    is pending and no staging folder is stale (one listing, where those checks load every
    manifest)."""
    try:
        return any(name.startswith(STAGING_PREFIX) for name in os.listdir(root))
    except OSError:
        return True  # the full checks say what is wrong


def stale_staging_folders(root: str | os.PathLike) -> list[Path]:
    """Staging folders of runs that were never committed (live or dead); folders only, not links
    named like them (:func:`leftovers` lists those)."""
    root = Path(root)
    committed = {m.staging.name for m in all_manifests(root)}
    return sorted(p for p in root.glob(STAGING_PREFIX + "*")
                  if is_real_dir(p) and p.name not in committed)


def leftovers(root: str | os.PathLike) -> list[Path]:
    """What killed runs leave in ``root`` besides staging folders: ingest's spill folders
    (``.ingest-spill-*``), temporary files of interrupted writes (``.*.tmp-*``), and links named
    like a staging or spill folder (planted: no heliocal writes one)."""
    root = Path(root)
    out = []
    for p in sorted(root.glob(".*")):
        if p.name.startswith(SPILL_PREFIX) or ".tmp-" in p.name:
            out.append(p)
        elif p.name.startswith(STAGING_PREFIX) and os.path.islink(p):
            out.append(p)
    return out


def staging_in_use(folder: str | os.PathLike) -> bool:
    """Whether a live run holds the staging (or spill) folder ``folder`` (read-only check)."""
    if not is_real_dir(folder):
        return False
    try:
        fd = os.open(Path(folder) / OWNER_FILENAME, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK
                     | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def remove_leftover(path: Path) -> bool:
    """Remove a leftover file, link or folder of a dead run (a link itself, never its target);
    False when a live run holds it."""
    if is_real_dir(path):
        lock = try_lock(path / OWNER_FILENAME)
        if lock is BUSY:
            return False
        try:
            shutil.rmtree(path, ignore_errors=True)
        finally:
            unlock(lock)
    else:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
    return True
