"""Where artifacts live and how they are written: safe file names from data (heliostat ids),
paths that cannot leave their folder, atomic writes (temporary file, fsync, rename) and file
hashes.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
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
    "file_sha256",
    "sha256_of_file",
    "artifact_path",
    "safe_child",
    "safe_name",
    "MAX_NAME_BYTES",
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
# atomic writes
# --------------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it into place atomically.

    On any exception (or a kill) the temporary file is removed or left under a hidden
    ``.<name>.tmp-*`` name that no stage reads, and ``path`` keeps its previous content.
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
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


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
    """SHA-256 (hex) of one file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
