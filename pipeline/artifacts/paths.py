"""Where artifacts live and how they are written: safe file names from data (heliostat ids),
paths that cannot leave their folder, atomic writes (temporary file, fsync, rename) and file
hashes.

A work directory is untrusted input (it may have been copied, unpacked or shared): every path
heliocal takes from it (a manifest's file list, a run id) is resolved through :func:`confined`,
which refuses a path that leaves the folder (``..``, absolute, NUL) and a symbolic link anywhere
on the way, and every file is opened without following a final link and only if it is a regular
file (:func:`open_regular`), so that no read blocks on a FIFO or device and no write or removal
reaches a file outside the folder.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import stat
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

from ..errors import UnsafePathError

if TYPE_CHECKING:  # annotations only: table.py needs pyarrow, this module stays light
    from .table import ArtifactSchema

__all__ = [
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "flush_to_disk",
    "file_sha256",
    "sha256_of_file",
    "artifact_path",
    "safe_child",
    "safe_name",
    "MAX_NAME_BYTES",
    "confined",
    "relative_path_problem",
    "link_message",
    "open_regular",
    "read_regular",
    "is_real_dir",
    "kind_of",
]


def artifact_path(workdir: str | os.PathLike, schema: ArtifactSchema) -> Path:
    """Path of ``schema``'s artifact inside ``workdir``."""
    return Path(workdir) / schema.filename


#: Longest file name (bytes of its UTF-8 encoding) that common file systems accept (NAME_MAX).
MAX_NAME_BYTES = 255


def safe_name(name: str, where: str = "the work directory") -> str:
    """``name`` itself if it can be used as a plain file name (the rules of :func:`safe_child`,
    without a folder to resolve against: for names staged in a stage transaction), else
    :class:`~heliocal.pipeline.errors.UnsafePathError`."""
    why = _unsafe_name_reason(name)
    if why is not None:
        raise UnsafePathError(_unsafe_message(name, where, why))
    return name


def _unsafe_message(name, where, why: str) -> str:
    return (f"{name!r} cannot be used as a file name in {where}: {why}; names taken from the "
            "data must be plain file names (heliostat ids: letters, digits, '_', '-', '.', see "
            "docs/input_formats.md; rerun `heliocal ingest`, which rejects other ids)")


def safe_child(directory: str | os.PathLike, name: str) -> Path:
    """``directory / name`` for a file name that comes from the data (a heliostat id, say).

    Every writer and reader that puts a data value into a path goes through here, so that no
    value can reach a file outside its folder, whatever ingest let through. Refused, with
    :class:`~heliocal.pipeline.errors.UnsafePathError`: a non-string or empty name; ``.``, ``..``
    and any name starting with ``.`` (hidden: the prefix of heliocal's temporary files); ``/`` or
    ``\\`` anywhere (so no absolute path and no sub-folder); NUL and other control characters;
    names longer than :data:`MAX_NAME_BYTES` bytes in UTF-8; and a name whose resolved path
    (symbolic links followed) is not directly inside ``directory``.

    Returns the path unresolved (``Path(directory) / name``).
    """
    why = _unsafe_name_reason(name)
    if why is None:
        folder = Path(directory)
        path = folder / name
        if path.resolve().parent != folder.resolve():
            why = "it resolves outside the folder (a symbolic link?)"
    if why is not None:
        raise UnsafePathError(_unsafe_message(name, directory, why))
    return path


def _unsafe_name_reason(name) -> str | None:
    if not isinstance(name, str):
        return f"it is a {type(name).__name__}, not text"
    if not name:
        return "it is empty"
    if name in (".", ".."):
        return "it names the folder itself or its parent"
    if name.startswith("."):
        return "it starts with '.' (hidden)"
    if "/" in name or "\\" in name:
        return "it contains a path separator"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "it contains a control character"
    if len(name.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES:
        return f"it is longer than {MAX_NAME_BYTES} bytes"
    return None


# --------------------------------------------------------------------------------------------
# paths inside a work directory: confined, no links followed, regular files only
# --------------------------------------------------------------------------------------------
def relative_path_problem(rel) -> str | None:
    """Why ``rel`` cannot name a file inside a folder (``None`` if it can): it must be text, a
    relative POSIX path without empty, ``.`` or ``..`` parts, without NUL or other control
    characters, and no part longer than :data:`MAX_NAME_BYTES` bytes."""
    if not isinstance(rel, str):
        return f"it is a {type(rel).__name__}, not text"
    if not rel:
        return "it is empty"
    if rel.startswith("/"):
        return "it is an absolute path"
    if any(ord(c) < 32 or ord(c) == 127 for c in rel):
        return "it contains NUL or another control character"
    parts = rel.split("/")
    if any(part in ("", ".", "..") for part in parts):
        return "it has an empty, '.' or '..' part"
    if any(len(part.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES for part in parts):
        return f"a part is longer than {MAX_NAME_BYTES} bytes"
    return None


def link_message(path: str | os.PathLike) -> str:
    """The one-line refusal of a symbolic link met inside a work directory."""
    try:
        target = f" (to {os.readlink(path)})"
    except OSError:
        target = ""
    return (f"{path} is a symbolic link{target}; heliocal follows no link inside a work "
            "directory, so that nothing outside it is read, written or removed: replace the link "
            "by the file or folder itself (or remove it), then rerun the command")


def kind_of(mode: int) -> str:
    """What a file of ``mode`` is, in words (for messages)."""
    for test, name in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def confined(root: str | os.PathLike, rel: str, *, replace_link: bool = False) -> Path:
    """``root / rel`` for a path ``rel`` relative to ``root`` (a work directory, or the report's
    folder) that stays inside it: the one helper through which every path taken from a work
    directory's contents is resolved.

    Refused with :class:`~heliocal.pipeline.errors.UnsafePathError`: a ``rel`` that
    :func:`relative_path_problem` refuses, and a symbolic link at any part of ``rel`` (an
    existing part is checked with ``lstat``; what does not exist yet follows nothing). ``root``
    itself is the user's choice and may be or lie behind a link. With ``replace_link`` (a
    destination that is renamed over or removed, which acts on a link itself, never on what it
    points to) the last part may be a link.
    """
    why = relative_path_problem(rel)
    if why is not None:
        raise UnsafePathError(f"{rel!r} cannot name a file inside {root}: {why} (a tampered "
                              "manifest?); rerun the stage that writes it")
    path = Path(root)
    parts = rel.split("/")
    for k, part in enumerate(parts):
        path = path / part
        try:
            mode = os.lstat(path).st_mode
        except (FileNotFoundError, NotADirectoryError):
            break  # nothing further exists, so nothing further can be a link
        if stat.S_ISLNK(mode) and not (replace_link and k == len(parts) - 1):
            raise UnsafePathError(link_message(path))
    return Path(root) / rel


def is_real_dir(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder itself (not a link to one)."""
    try:
        return stat.S_ISDIR(os.lstat(path).st_mode)
    except OSError:
        return False


def open_regular(path: str | os.PathLike, what: str = "") -> int:
    """A read-only file descriptor of ``path``, opened without following a final symbolic link
    and without blocking; refused (:class:`UnsafePathError`) unless it is a regular file, so a
    FIFO, socket or device named like an artifact never blocks or floods a reader.

    Raises FileNotFoundError, IsADirectoryError and NotADirectoryError as :func:`open` does."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UnsafePathError(link_message(path)) from None
        raise
    mode = os.fstat(fd).st_mode
    if stat.S_ISDIR(mode):
        os.close(fd)
        raise IsADirectoryError(errno.EISDIR, "Is a directory", str(path))
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise UnsafePathError(f"{path} is {kind_of(mode)}, not a file{what}; remove it, then "
                              "rerun the command")
    return fd


def read_regular(path: str | os.PathLike, what: str = "") -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`'s rules)."""
    with open(open_regular(path, what), "rb", closefd=True) as fh:
        return fh.read()


# --------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, durable: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it into place atomically.

    On any exception (or a kill) the temporary file is removed or left under a hidden
    ``.<name>.tmp-*`` name that no stage reads, and ``path`` keeps its previous content.
    ``durable``: the data reach the disk (fsync) before the rename, so a power loss cannot
    leave an empty file under the name either. A writer of many small files passes False and
    flushes them all at once (:func:`flush_to_disk`) before the file that marks them complete:
    one fsync costs milliseconds, thousands of them dominate such a write.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; artifacts are ordinary files
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if durable:
            with open(tmp_path, "rb+") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, durable: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (``durable``: :func:`atomic_path`'s)."""
    with atomic_path(path, durable=durable) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, *, durable: bool = True) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically (``durable``: :func:`atomic_path`'s)."""
    return atomic_write_bytes(path, text.encode("utf-8"), durable=durable)


def flush_to_disk() -> None:
    """Bring every file written so far to the disk (``sync``): once after many files written
    with ``durable=False``, before the file that says they are complete."""
    os.sync()


# --------------------------------------------------------------------------------------------
# provenance
# --------------------------------------------------------------------------------------------
def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, or of a folder's files (relative names and bytes, sorted)."""
    path = Path(path)
    h = hashlib.sha256()
    if path.is_dir():
        for p in sorted(q for q in path.rglob("*") if q.is_file()):
            h.update(str(p.relative_to(path)).encode())
            h.update(b"\0")
            h.update(sha256_of_file(p).encode())
    else:
        return sha256_of_file(path)
    return h.hexdigest()


def sha256_of_file(path: str | os.PathLike) -> str:
    """SHA-256 (hex) of one regular file's bytes, read in 1 MiB chunks. ``path`` may be a link
    (sources live outside work directories); a FIFO or device is refused
    (:class:`UnsafePathError`) instead of read without end."""
    h = hashlib.sha256()
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise UnsafePathError(f"{path} is {kind_of(mode)}, not a file; give a regular file")
    with open(fd, "rb", closefd=True) as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
