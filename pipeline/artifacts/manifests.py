"""Manifests: the committed run of each stage (``ROOT/<stage>.manifest.json``), and the one reader
of a work directory's committed state, :class:`CommittedWorkdir` (each manifest loaded and
checked once, every file resolved through :func:`~heliocal.pipeline.artifacts.paths.confined`,
its bytes checked against the recorded SHA-256). The protocol that writes manifests is in
:mod:`heliocal.pipeline.artifacts.transaction`.

A manifest is untrusted input like any file of a work directory: :func:`load_manifest` refuses one
whose run id is not a heliocal run id, whose stage is not its file's, or whose file lists name a
path that leaves the folder, a hidden file or another manifest (:class:`InvalidManifest`, one
line naming the file and why). The stage that owns an invalid manifest replaces it on its next run.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Protocol

from ..errors import SchemaError, StageInputError, UnsafePathError
from .paths import confined, is_real_dir, open_regular, relative_path_problem

__all__ = [
    "ActiveTransaction",
    "MANIFEST_VERSION",
    "Manifest",
    "InvalidManifest",
    "Committed",
    "CommittedWorkdir",
    "RUN_ID_RE",
    "manifest_path",
    "manifest_problem",
    "load_manifest",
    "read_committed",
    "committed_entry",
    "current_transaction",
    "verify_files",
    "all_manifests",
    "invalid_manifests",
    "STAGING_PREFIX",
    "checked_relative_path",
    "staging_name",
    "ACTIVE_TRANSACTION",
]


#: Layout version of ``<stage>.manifest.json``.
MANIFEST_VERSION = 1


STAGING_PREFIX = ".txn-"

#: A run id: UTC time and 8 random hex digits (:func:`~.transaction.new_run_id`).
RUN_ID_RE = re.compile(r"\d{8}T\d{6}Z-[0-9a-f]{8}")

#: A stage name (the subcommand): lower-case letters, digits and '-'.
_STAGE_RE = re.compile(r"[a-z][a-z0-9-]{0,39}")

_SHA256_RE = re.compile(r"[0-9a-f]{64}")

_MANIFEST_SUFFIX = ".manifest.json"


# ------------------------------------------------------------------------------------------------
# manifests
# ------------------------------------------------------------------------------------------------
def manifest_path(root: str | os.PathLike, stage: str) -> Path:
    """``ROOT/<stage>.manifest.json``."""
    return Path(root) / f"{stage}{_MANIFEST_SUFFIX}"


def staging_name(stage: str, run_id: str) -> str:
    return f"{STAGING_PREFIX}{stage}-{run_id}"


@dataclass(frozen=True)
class Manifest:
    """A committed run of one stage (the parsed ``<stage>.manifest.json``, checked by
    :func:`manifest_problem`: every path in it is a plain relative path inside ``root``)."""

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
        """True while the run is committed but its staged files are not all in place yet (its
        staging folder exists as a folder, not a link)."""
        return is_real_dir(self.staging)

    def input_fingerprints(self) -> dict:
        """label -> recorded fingerprint of every input (what freshness compares)."""
        return {k: v.get("fingerprint") for k, v in self.inputs.items()}

    def removes(self, rel: str) -> bool:
        """Whether this run dropped ``rel`` of the run before it (the file may still be on disk
        until the commit is applied; it counts as absent)."""
        return rel in self.data.get("removed", ())


class InvalidManifest(SchemaError):
    """A ``<stage>.manifest.json`` that is not a valid manifest (unreadable, not JSON, or naming
    paths it may not): the message names it, why, and the stage that replaces it."""

    def __init__(self, path: Path, stage: str, root: Path, why: str):
        self.path, self.stage, self.why = path, stage, why
        super().__init__(f"{path} is not a valid manifest ({why}); rerun `heliocal {stage} "
                         f"--workdir {root}`, which replaces it")


def _entry_problem(rel) -> str | None:
    """Why ``rel`` cannot be a file a manifest lists (``None`` if it can)."""
    why = relative_path_problem(rel)
    if why is not None:
        return f"it lists {rel!r}: {why}"
    if any(part.startswith(".") for part in rel.split("/")):
        return f"it lists {rel!r}, a hidden file (heliocal's own bookkeeping, never an output)"
    if "/" not in rel and rel.endswith(_MANIFEST_SUFFIX):
        return f"it lists {rel!r}, a manifest"
    return None


def manifest_problem(data, stage: str) -> str | None:
    """Why ``data`` (a parsed ``<stage>.manifest.json``) is not a valid manifest of ``stage``, or
    ``None``: the layout version, the stage, the run id, and every listed path and entry."""
    if not isinstance(data, dict):
        return f"a JSON {type(data).__name__}, not an object"
    if data.get("manifest_version") != MANIFEST_VERSION:
        return (f"manifest version {data.get('manifest_version')!r}, but this heliocal reads "
                f"version {MANIFEST_VERSION}")
    if data.get("stage") != stage:
        return f"it names stage {data.get('stage')!r}, not {stage!r}"
    run_id = data.get("run_id")
    if not isinstance(run_id, str) or not RUN_ID_RE.fullmatch(run_id):
        return f"its run id {run_id!r} is not a heliocal run id (UTC time and 8 hex digits)"
    files, removed = data.get("files"), data.get("removed", [])
    if not isinstance(files, dict) or not isinstance(removed, list):
        return "its 'files' is not an object or its 'removed' not a list"
    if not isinstance(data.get("inputs", {}), dict):
        return "its 'inputs' is not an object"
    for rel, entry in files.items():
        why = _entry_problem(rel)
        if why is not None:
            return why
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str) \
                or not _SHA256_RE.fullmatch(entry["sha256"]):
            return f"its entry of {rel!r} has no SHA-256"
        entry_run = entry.get("run_id", run_id)
        if not isinstance(entry_run, str) or not RUN_ID_RE.fullmatch(entry_run):
            return f"its entry of {rel!r} names run id {entry_run!r}"
    for rel in removed:
        why = _entry_problem(rel)
        if why is not None:
            return why.replace("it lists", "it removes")
    return None


def _manifest_bytes(path: Path) -> bytes | None:
    """The bytes of a manifest file (``None`` if there is none); the file must be a regular file
    itself: a link, FIFO or device is refused (:class:`UnsafePathError`)."""
    try:
        fd = open_regular(path)
    except FileNotFoundError:
        return None
    with open(fd, "rb", closefd=True) as fh:
        return fh.read()


def load_manifest(root: str | os.PathLike, stage: str) -> Manifest | None:
    """The committed run of ``stage`` in ``root`` (``None`` if the stage never committed there).

    Raises
    ------
    InvalidManifest : the manifest exists but is not a valid one (unreadable, a link or FIFO, not
        JSON, or :func:`manifest_problem`); a :class:`SchemaError`.
    """
    root = Path(root)
    path = manifest_path(root, stage)
    try:
        raw = _manifest_bytes(path)
    except UnsafePathError as exc:
        raise InvalidManifest(path, stage, root, str(exc).split(";")[0].replace(
            f"{path} is ", "it is ")) from None
    except IsADirectoryError:
        raise InvalidManifest(path, stage, root, "it is a folder; remove it") from None
    except OSError as exc:
        raise InvalidManifest(path, stage, root, f"cannot be read: {exc.strerror or exc}") from None
    if raw is None:
        return None
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        why = "nested too deeply" if isinstance(exc, RecursionError) else " ".join(str(exc).split())[:120]
        raise InvalidManifest(path, stage, root, f"not JSON: {why}") from None
    why = manifest_problem(data, stage)
    if why is not None:
        raise InvalidManifest(path, stage, root, why)
    return Manifest(root, stage, data["run_id"], data["files"], data.get("inputs") or {}, data)


def _stages_in(root: Path) -> list[str]:
    """The stages that have a manifest file (of any kind) in ``root``, sorted."""
    try:
        names = sorted(os.listdir(root))
    except OSError:
        return []
    return [n[: -len(_MANIFEST_SUFFIX)] for n in names
            if n.endswith(_MANIFEST_SUFFIX) and _STAGE_RE.fullmatch(n[: -len(_MANIFEST_SUFFIX)])]


def all_manifests(root: str | os.PathLike) -> list[Manifest]:
    """Every valid manifest in ``root``, sorted by stage (invalid ones are skipped; see
    :func:`invalid_manifests`)."""
    out = []
    for stage in _stages_in(Path(root)):
        try:
            m = load_manifest(root, stage)
        except SchemaError:
            continue
        if m is not None:
            out.append(m)
    return out


def invalid_manifests(root: str | os.PathLike) -> list[InvalidManifest]:
    """The manifest files of ``root`` that :func:`load_manifest` refuses, sorted by stage."""
    out = []
    for stage in _stages_in(Path(root)):
        try:
            load_manifest(root, stage)
        except InvalidManifest as exc:
            out.append(exc)
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
# reading committed files: one reader per work directory
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


def _open_committed(m: Manifest, rel: str):
    """(open file, where) of ``rel`` of committed run ``m``: from its staging folder while the
    commit is not applied and the file is still there, else from its fixed name. Both paths are
    confined (no link followed); FileNotFoundError if neither exists."""
    if m.pending():
        with contextlib.suppress(FileNotFoundError, NotADirectoryError):
            staged = confined(m.staging, rel)
            return open(open_regular(staged), "rb", closefd=True), staged
    path = confined(m.root, rel)
    return open(open_regular(path), "rb", closefd=True), path


class CommittedWorkdir:
    """The committed state of one work directory (or report folder), opened once.

    Every stage's manifest is loaded and checked at most once (:func:`load_manifest`), every path
    is resolved through :func:`~heliocal.pipeline.artifacts.paths.confined`, and every file is
    read once, as a regular file, and checked against its manifest's SHA-256 (:meth:`read`).
    ``aim`` opens one and passes it to every reader it calls (the store's ``read_artifact``,
    ``check_fresh``, the model files, :func:`aim_models`); a reader given a plain path opens its
    own. A manifest that changes meanwhile (another run committed) is loaded again, once per read
    that meets it.

    It is :class:`os.PathLike` (its root), so code that only needs the folder's name takes it.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self._manifests: dict[str, Manifest | None | InvalidManifest] = {}
        self._files: dict[tuple[str, str], Committed] = {}

    @classmethod
    def of(cls, workdir) -> "CommittedWorkdir":
        """``workdir`` itself if it is one, else a new one on that folder."""
        return workdir if isinstance(workdir, cls) else cls(workdir)

    def __fspath__(self) -> str:
        return str(self.root)

    def __str__(self) -> str:
        return str(self.root)

    def __truediv__(self, other) -> Path:
        return self.root / other

    def manifest(self, stage: str, *, reload: bool = False) -> Manifest | None:
        """The committed run of ``stage`` (loaded once; :class:`InvalidManifest` as
        :func:`load_manifest`)."""
        if reload or stage not in self._manifests:
            try:
                self._manifests[stage] = load_manifest(self.root, stage)
            except InvalidManifest as exc:
                self._manifests[stage] = exc
            self._files = {k: v for k, v in self._files.items() if k[0] != stage}
        found = self._manifests[stage]
        if isinstance(found, InvalidManifest):
            raise found
        return found

    def listed(self, stage: str, rel: str) -> bool:
        """Whether the last run of ``stage`` committed ``rel``."""
        m = self.manifest(stage)
        return m is not None and rel in m.files

    def present(self, stage: str, rel: str) -> bool:
        """Whether ``rel`` is committed by ``stage``, or at least something of that name is there
        (which :meth:`read` then refuses with the reason)."""
        return self.listed(stage, rel) or os.path.lexists(self.root / rel)

    def read(self, stage: str, rel: str, *, hint: str | None = None, missing: str | None = None,
             label: str | None = None) -> Committed:
        """Bytes of ``ROOT/<rel>`` as committed by the last run of ``stage``, verified by SHA-256
        (read once per instance).

        Parameters
        ----------
        hint : the command that rewrites the file, in backticks (default ``heliocal <stage>``).
        missing : message when the stage has not committed the file (default: "... is missing:
            run HINT first").
        label : the input label to record in the active transaction (default: no record).

        Raises
        ------
        StageInputError : the stage never committed this file (the message names the command).
        SchemaError : the file on disk is not the one the manifest lists (changed, removed, a
            link or not a regular file), or the manifest is invalid.
        """
        rel = checked_relative_path(rel)
        hint = hint or f"`heliocal {stage} --workdir {self.root}`"
        got = self._files.get((stage, rel))
        if got is None:
            got = self._read(stage, rel, hint, missing)
            self._files[(stage, rel)] = got
        txn = current_transaction()
        if txn is not None and label is not None:
            txn.record_read(label, got.manifest, rel)
        return got

    def _read(self, stage: str, rel: str, hint: str, missing: str | None) -> Committed:
        root = self.root
        path = root / rel
        for attempt in range(5):
            m = self.manifest(stage, reload=attempt > 0)
            if m is None or rel not in m.files:
                if os.path.lexists(path) and m is None:
                    raise StageInputError(_not_committed_message(path, stage, root, hint))
                if os.path.lexists(path) and not m.removes(rel):
                    raise StageInputError(
                        f"{path} is not part of the last `heliocal {stage}` run ({m.run_id}, see "
                        f"{m.path.name}): it is left over or made by hand; rerun {hint}")
                raise StageInputError(missing or f"{path} is missing: run {hint} first")
            entry = m.files[rel]
            try:
                fh, read_from = _open_committed(m, rel)
            except (FileNotFoundError, NotADirectoryError):
                if self._changed(stage, m):
                    continue  # another run committed meanwhile: resolve again
                raise SchemaError(f"{path} is missing although the last `heliocal {stage}` run "
                                  f"({m.run_id}) wrote it (deleted by hand?); rerun {hint}") from None
            except IsADirectoryError:
                raise SchemaError(f"{path} is a folder, not the file the last `heliocal {stage}` "
                                  f"run wrote; remove it and rerun {hint}") from None
            except UnsafePathError as exc:
                raise SchemaError(f"{exc} (it should be the file `heliocal {stage}` wrote; then "
                                  f"rerun {hint})") from None
            with fh:
                data, sha = _read_and_hash(fh)
            if sha != entry.get("sha256"):
                if self._changed(stage, m):
                    continue
                raise SchemaError(f"{path} was changed after `heliocal {stage}` wrote it (its "
                                  f"SHA-256 differs from {m.path.name}, run {m.run_id}); rerun {hint}")
            return Committed(path, read_from, data, entry, m)
        raise SchemaError(f"{path} kept changing while it was read (another heliocal run is writing "
                          f"{root}); wait for it to finish and retry")

    def _changed(self, stage: str, seen: Manifest) -> bool:
        """Whether another run of ``stage`` committed since ``seen`` was loaded."""
        try:
            again = load_manifest(self.root, stage)
        except InvalidManifest:
            return False
        return again is not None and again.run_id != seen.run_id

    def fingerprint(self, stage: str, rel: str) -> str | None:
        """The content fingerprint of ``rel`` as the last run of ``stage`` committed it."""
        m = self.manifest(stage)
        entry = m.files.get(rel) if m is not None else None
        return None if entry is None else entry.get("fingerprint")


def read_committed(root: str | os.PathLike, stage: str, rel: str, *, hint: str | None = None,
                   missing: str | None = None, label: str | None = None) -> Committed:
    """:meth:`CommittedWorkdir.read` of ``root`` (a path, or an open :class:`CommittedWorkdir`)."""
    return CommittedWorkdir.of(root).read(stage, rel, hint=hint, missing=missing, label=label)


def verify_files(m: Manifest) -> dict[str, str]:
    """Files of committed run ``m`` that are not as it wrote them: relative path -> ``missing``,
    ``modified`` or what is there instead (``a symbolic link``, ``a FIFO ...``); every file is
    read and hashed once, no link followed."""
    problems = {}
    for rel, entry in sorted(m.files.items()):
        try:
            fh, _ = _open_committed(m, rel)
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            problems[rel] = "missing"
            continue
        except UnsafePathError as exc:
            problems[rel] = str(exc).split(";")[0].replace(f"{m.root / rel} is ", "")
            continue
        with fh:
            _, sha = _read_and_hash(fh)
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
