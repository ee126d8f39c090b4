"""Manifests: the committed run of each stage (``ROOT/<stage>.manifest.json``) and the one way to
read a committed output, :func:`read_committed` (resolved through the manifest, bytes checked
against the recorded SHA-256). The protocol that writes them is in
:mod:`heliocal.pipeline.artifacts.transaction`.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Protocol

from ..errors import SchemaError, StageInputError, UnsafePathError
from .paths import sha256_of_file

__all__ = [
    "ActiveTransaction",
    "MANIFEST_VERSION",
    "Manifest",
    "Committed",
    "manifest_path",
    "load_manifest",
    "read_committed",
    "committed_entry",
    "current_transaction",
    "verify_files",
    "all_manifests",
    "STAGING_PREFIX",
    "checked_relative_path",
    "staging_name",
    "ACTIVE_TRANSACTION",
]


#: Layout version of ``<stage>.manifest.json``.
MANIFEST_VERSION = 1


STAGING_PREFIX = ".txn-"


# ------------------------------------------------------------------------------------------------
# manifests
# ------------------------------------------------------------------------------------------------
def manifest_path(root: str | os.PathLike, stage: str) -> Path:
    """``ROOT/<stage>.manifest.json``."""
    return Path(root) / f"{stage}.manifest.json"


def staging_name(stage: str, run_id: str) -> str:
    return f"{STAGING_PREFIX}{stage}-{run_id}"


@dataclass(frozen=True)
class Manifest:
    """A committed run of one stage (the parsed ``<stage>.manifest.json``)."""

    root: Path
    stage: str
    run_id: str
    files: dict  # relative path (POSIX) -> {"sha256", "size", "fingerprint", "artifact", "run_id"}
    inputs: dict  # label -> {"fingerprint", "sha256", "run_id", "stage", "path"}
    data: dict = field(repr=False)

    @property
    def path(self) -> Path:
        return manifest_path(self.root, self.stage)

    @property
    def staging(self) -> Path:
        return self.root / staging_name(self.stage, self.run_id)

    def pending(self) -> bool:
        """True while the run is committed but its staged files are not all in place yet."""
        return self.staging.is_dir()

    def input_fingerprints(self) -> dict:
        """label -> recorded fingerprint of every input (what freshness compares)."""
        return {k: v.get("fingerprint") for k, v in self.inputs.items()}

    def removes(self, rel: str) -> bool:
        """Whether this run dropped ``rel`` of the run before it (the file may still be on disk
        until the commit is applied; it counts as absent)."""
        return rel in self.data.get("removed", ())


def load_manifest(root: str | os.PathLike, stage: str) -> Manifest | None:
    """The committed run of ``stage`` in ``root`` (``None`` if the stage never committed there).

    Raises
    ------
    SchemaError : the manifest exists but cannot be read.
    """
    root = Path(root)
    path = manifest_path(root, stage)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise SchemaError(f"{path} cannot be read ({exc}); rerun `heliocal {stage} --workdir "
                          f"{root}`") from exc
    try:
        data = json.loads(text)
        if not isinstance(data, dict) or not isinstance(data.get("files"), dict):
            raise ValueError("not a heliocal manifest")
    except ValueError as exc:
        raise SchemaError(f"{path} is not a valid manifest ({exc}); rerun `heliocal {stage} "
                          f"--workdir {root}`") from exc
    if data.get("manifest_version") != MANIFEST_VERSION:
        raise SchemaError(f"{path} has manifest version {data.get('manifest_version')}, but this "
                          f"heliocal reads version {MANIFEST_VERSION}: rerun `heliocal {stage} "
                          f"--workdir {root}`")
    return Manifest(root, stage, str(data.get("run_id")), data["files"], data.get("inputs") or {},
                    data)


def all_manifests(root: str | os.PathLike) -> list[Manifest]:
    """Every readable manifest in ``root``, sorted by stage (unreadable ones are skipped)."""
    out = []
    for path in sorted(Path(root).glob("*.manifest.json")):
        try:
            m = load_manifest(root, path.name.removesuffix(".manifest.json"))
        except SchemaError:
            continue
        if m is not None:
            out.append(m)
    return out


def committed_entry(root: str | os.PathLike, rel: str) -> tuple[Manifest, dict] | None:
    """The manifest that lists ``rel`` (a path relative to ``root``) and its entry, if any."""
    rel = checked_relative_path(rel)
    for m in all_manifests(root):
        if rel in m.files:
            return m, m.files[rel]
    return None


def checked_relative_path(rel: str | os.PathLike) -> str:
    """A path relative to the transaction root, in POSIX form; refuses one that leaves the root."""
    text = str(rel)
    p = PurePosixPath(text.replace(os.sep, "/"))
    if "\0" in text or p.is_absolute() or not p.parts or any(part in ("", ".", "..")
                                                              for part in p.parts):
        raise UnsafePathError(f"{text!r} cannot name a file inside the work directory (a heliostat id "
                         "or name with '/', '..' or NUL?); rename it in the source and ingest "
                         "again")
    return p.as_posix()


# ------------------------------------------------------------------------------------------------
# reading committed files
# ------------------------------------------------------------------------------------------------
#: SHA-256 of files already hashed in this process, by (device, inode, size, mtime, ctime): a stage
#: that reads one input several times hashes it once. Committed files are never changed in place
#: (they are replaced by a rename, which gives a new inode), so the key identifies the bytes.
_SHA_CACHE: dict[tuple, str] = {}


def _stat_key(st: os.stat_result) -> tuple:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _read_and_hash(fh) -> tuple[bytes, str]:
    key = _stat_key(os.fstat(fh.fileno()))
    data = fh.read()
    sha = _SHA_CACHE.get(key)
    if sha is None:
        sha = hashlib.sha256(data).hexdigest()
        if _stat_key(os.fstat(fh.fileno())) == key:
            _SHA_CACHE[key] = sha
    return data, sha


@dataclass(frozen=True)
class Committed:
    """The verified bytes of one committed file and where they came from."""

    path: Path  # the fixed name (ROOT/<rel>), as messages show it
    read_from: Path  # where the bytes were read (the fixed name or the staging folder)
    data: bytes
    entry: dict
    manifest: Manifest


def _not_committed_message(path: Path, stage: str, root: Path, hint: str) -> str:
    return (f"{path} was not written by a complete `heliocal {stage}` run (no "
            f"{manifest_path(root, stage).name} lists it: made by hand, by an older heliocal or by "
            f"an interrupted run); rerun {hint}")


def read_committed(root: str | os.PathLike, stage: str, rel: str, *, hint: str | None = None,
                   missing: str | None = None, label: str | None = None) -> Committed:
    """Bytes of ``ROOT/<rel>`` as committed by the last run of ``stage``, verified by SHA-256.

    Parameters
    ----------
    hint : the command that rewrites the file, in backticks (default ``heliocal <stage>``).
    missing : message when the stage has not committed the file (default: "... is missing: run
        HINT first").
    label : the input label to record in the active transaction (default: no record).

    Raises
    ------
    StageInputError : the stage never committed this file (the message names the command).
    SchemaError : the file on disk is not the one the manifest lists (changed or removed after
        the run), or the manifest is unreadable.
    """
    root = Path(root)
    rel = checked_relative_path(rel)
    path = root / rel
    hint = hint or f"`heliocal {stage} --workdir {root}`"
    for _attempt in range(5):
        m = load_manifest(root, stage)
        if m is None or rel not in m.files:
            if path.exists() and m is None:
                raise StageInputError(_not_committed_message(path, stage, root, hint))
            if path.exists() and not m.removes(rel):
                raise StageInputError(
                    f"{path} is not part of the last `heliocal {stage}` run ({m.run_id}, see "
                    f"{m.path.name}): it is left over or made by hand; rerun {hint}")
            raise StageInputError(missing or f"{path} is missing: run {hint} first")
        entry = m.files[rel]
        fh = None
        read_from = path
        if m.pending():
            with contextlib.suppress(FileNotFoundError, NotADirectoryError):
                fh = open(m.staging / rel, "rb")
                read_from = m.staging / rel
        if fh is None:
            try:
                fh = open(path, "rb")
                read_from = path
            except FileNotFoundError:
                again = load_manifest(root, stage)
                if again is not None and again.run_id != m.run_id:
                    continue  # another run committed meanwhile: resolve again
                raise SchemaError(f"{path} is missing although the last `heliocal {stage}` run "
                                  f"({m.run_id}) wrote it (deleted by hand?); rerun {hint}") from None
            except IsADirectoryError:
                raise SchemaError(f"{path} is a folder, not the file the last `heliocal {stage}` "
                                  f"run wrote; remove it and rerun {hint}") from None
        with fh:
            data, sha = _read_and_hash(fh)
        if sha != entry.get("sha256"):
            again = load_manifest(root, stage)
            if again is not None and again.run_id != m.run_id:
                continue
            raise SchemaError(f"{path} was changed after `heliocal {stage}` wrote it (its SHA-256 "
                              f"differs from {m.path.name}, run {m.run_id}); rerun {hint}")
        txn = current_transaction()
        if txn is not None and label is not None:
            txn.record_read(label, m, rel)
        return Committed(path, read_from, data, entry, m)
    raise SchemaError(f"{path} kept changing while it was read (another heliocal run is writing "
                      f"{root}); wait for it to finish and retry")


def verify_files(m: Manifest) -> dict[str, str]:
    """Files of committed run ``m`` that are not as it wrote them: relative path -> ``missing`` or
    ``modified`` (every file is read and hashed once)."""
    problems = {}
    for rel, entry in sorted(m.files.items()):
        where = m.staging / rel if m.pending() and (m.staging / rel).is_file() else m.root / rel
        try:
            with open(where, "rb") as fh:
                _, sha = _read_and_hash(fh)
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            problems[rel] = "missing"
            continue
        if sha != entry.get("sha256"):
            problems[rel] = "modified"
    return problems


# ------------------------------------------------------------------------------------------------
# the transaction
# ------------------------------------------------------------------------------------------------
class ActiveTransaction(Protocol):
    """What readers need of the running stage transaction
    (:class:`heliocal.pipeline.artifacts.transaction.StageTransaction` is one)."""

    root: Path
    stage: str

    def record_read(self, label: str, manifest: Manifest, rel: str) -> None:
        """Record that this run read ``rel`` of ``manifest``'s run as its input ``label``."""


#: The stage transaction running in this context (set by StageTransaction while it is open).
ACTIVE_TRANSACTION: contextvars.ContextVar[ActiveTransaction | None] = contextvars.ContextVar(
    "heliocal_transaction", default=None)


def current_transaction(root: str | os.PathLike | None = None,
                        stage: str | None = None) -> ActiveTransaction | None:
    """The transaction active in this context (optionally: only if it is of ``root``/``stage``)."""
    txn = ACTIVE_TRANSACTION.get()
    if txn is None:
        return None
    if root is not None and Path(root).absolute() != txn.root.absolute():
        return None
    if stage is not None and stage != txn.stage:
        return None
    return txn
