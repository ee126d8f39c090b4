"""Stage transactions: all outputs of a stage run become visible together, at one atomic step.

A stage writes several files (``fit-coarse``: two Parquet tables; ``fit-hybrid``: a model file
pair per heliostat and a table). Renaming each file into place atomically is not enough: a stage
killed between two renames would leave files of two runs side by side. So every stage run is a
*transaction* on a root folder ``ROOT`` (the work directory; for ``report`` its output folder)::

    ROOT/<stage>.manifest.json     the stage's committed run: run id, options, the inputs it read
                                   (each with its content fingerprint) and, per output file, its
                                   SHA-256, size and content fingerprint
    ROOT/<path>                    the output files under their fixed names (the workdir contract)
    ROOT/.txn-<stage>-<run id>/    the staging folder of a run (same file system as ROOT)

A run

1. **begins**: completes a run of ROOT that was committed but not yet applied (roll forward) and
   removes the staging folders of runs that died before their commit (a live run holds an
   ``fcntl`` lock on its staging folder, so only dead ones are removed);
2. **stages** every output inside its staging folder (each file fsynced);
3. **commits**: writes the new manifest to a temporary file and renames it over
   ``ROOT/<stage>.manifest.json`` with :func:`os.replace`. This one rename is the commit point;
4. **applies**: renames each staged file to its fixed name, removes the previous run's files that
   the new run does not list, and removes the staging folder.

Readers resolve every file through the manifest (:func:`read_committed`): while the committed run's
staging folder still exists, a file that is still in it is read from there. The bytes read are
hashed and compared with the manifest's SHA-256. A reader therefore sees the previous run (killed
before step 3) or the new run (killed after it), never a mix; a file that is not listed, or whose
bytes differ from the manifest, is refused with the stage to rerun.

Freshness is decided from what was read: each read inside a transaction is recorded with the
content fingerprint of the file (:func:`table_fingerprint`: the table's data, without provenance
metadata or timing columns) and the manifest records these. An artifact is *fresh* when the
fingerprints it recorded equal those of the current upstream manifests; rerunning an upstream stage
with other spellings of the same command (``--workdir ./a`` or ``a``) gives the same fingerprints.

One writer per ROOT at a time is the job of the workdir lock (``pipeline/workdir_lock.py``); under
it the protocol above is exact. Without it, a run refuses to commit if another run of its stage
committed after it began (it would replace that run's outputs, or drop what that run merged),
and recovery leaves alone the staging folder of a run that is still alive.
"""

from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import errno
import fcntl
import functools
import hashlib
import inspect
import json
import os
import secrets
import shutil
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Callable, Iterator, Mapping

from .errors import InputError, SchemaError, StageInputError, UnsafePathError

__all__ = [
    "MANIFEST_VERSION",
    "Manifest",
    "StageTransaction",
    "sha256_of_file",
    "Committed",
    "manifest_path",
    "load_manifest",
    "read_committed",
    "committed_entry",
    "current_transaction",
    "transaction",
    "stage_transaction",
    "recover",
    "stale_staging_folders",
    "pending_commits",
    "staging_in_use",
    "verify_files",
    "all_manifests",
]

#: Layout version of ``<stage>.manifest.json``.
MANIFEST_VERSION = 1
_STAGING_PREFIX = ".txn-"
_OWNER = ".owner"


def _write_point(event: str, path: Path) -> None:
    """Called right after every write, rename or removal of a transaction (``event``: ``staged``,
    ``manifest-temp``, ``commit``, ``apply``, ``remove``, ``cleanup``). A no-op; the
    crash-consistency test replaces it to kill the process at each point in turn."""


# ------------------------------------------------------------------------------------------------
# manifests
# ------------------------------------------------------------------------------------------------
def manifest_path(root: str | os.PathLike, stage: str) -> Path:
    """``ROOT/<stage>.manifest.json``."""
    return Path(root) / f"{stage}.manifest.json"


def _staging_name(stage: str, run_id: str) -> str:
    return f"{_STAGING_PREFIX}{stage}-{run_id}"


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
        return self.root / _staging_name(self.stage, self.run_id)

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
    rel = _rel(rel)
    for m in all_manifests(root):
        if rel in m.files:
            return m, m.files[rel]
    return None


def _rel(rel: str | os.PathLike) -> str:
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
    rel = _rel(rel)
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


# ------------------------------------------------------------------------------------------------
# durability helpers
# ------------------------------------------------------------------------------------------------
def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def sha256_of_file(path: Path) -> str:
    """SHA-256 (hex) of one file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _try_lock(path: Path):
    """An open file of ``path`` holding an exclusive ``flock``, or ``None`` if another process
    holds it (a live transaction)."""
    try:
        fh = open(path, "a+b")
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        fh.close()
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return None
        raise
    return fh


# ------------------------------------------------------------------------------------------------
# applying a commit and recovering interrupted ones
# ------------------------------------------------------------------------------------------------
def _apply(m: Manifest) -> None:
    """Move the staged files of committed run ``m`` into place, remove the files it dropped, and
    remove its staging folder. Idempotent: a second call (or one after a kill) finishes the job."""
    staging = m.staging
    moved_dirs = set()
    for rel in sorted(m.files):
        src = staging / rel
        if src.is_file():
            dst = m.root / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            if dst.is_dir():  # a folder where the artifact goes: not ours to remove
                raise SchemaError(f"{dst} is a folder; remove it and rerun `heliocal {m.stage} "
                                  f"--workdir {m.root}`")
            os.replace(src, dst)
            moved_dirs.add(dst.parent)
            _write_point("apply", dst)
    for d in moved_dirs:
        _fsync_dir(d)
    for rel in m.data.get("removed", []):
        dst = m.root / rel
        if rel not in m.files and dst.is_file():
            dst.unlink()
            _write_point("remove", dst)
    shutil.rmtree(staging, ignore_errors=True)
    _fsync_dir(m.root)
    _write_point("cleanup", staging)


def pending_commits(root: str | os.PathLike) -> list[Manifest]:
    """Committed runs in ``root`` whose files are not all moved into place yet."""
    return [m for m in all_manifests(root) if m.pending()]


def stale_staging_folders(root: str | os.PathLike) -> list[Path]:
    """Staging folders of runs that were never committed (live or dead)."""
    root = Path(root)
    committed = {m.staging.name for m in all_manifests(root)}
    return sorted(p for p in root.glob(_STAGING_PREFIX + "*")
                  if p.is_dir() and p.name not in committed)


def staging_in_use(folder: str | os.PathLike) -> bool:
    """Whether a live run holds the staging folder ``folder`` (read-only check)."""
    try:
        fh = open(Path(folder) / _OWNER, "rb")
    except OSError:
        return False
    with fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return True
    return False


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


def recover(root: str | os.PathLike) -> list[str]:
    """Finish interrupted commits in ``root`` and remove dead uncommitted staging folders.

    A staging folder whose owner is alive (its lock is held) is left alone. Returns what was done,
    one line per item (logged by the caller).
    """
    root = Path(root)
    done = []
    for m in pending_commits(root):
        lock = _try_lock(m.staging / _OWNER)
        if lock is None and (m.staging / _OWNER).exists():
            continue  # its writer is still applying it
        try:
            _apply(m)
            done.append(f"completed the interrupted commit of `heliocal {m.stage}` run {m.run_id}")
        finally:
            if lock is not None:
                lock.close()
    for folder in stale_staging_folders(root):
        lock = _try_lock(folder / _OWNER)
        if lock is None and (folder / _OWNER).exists():
            continue
        try:
            shutil.rmtree(folder, ignore_errors=True)
            done.append(f"removed {folder.name} (a run that stopped before its commit)")
        finally:
            if lock is not None:
                lock.close()
    return done


# ------------------------------------------------------------------------------------------------
# the transaction
# ------------------------------------------------------------------------------------------------
_CURRENT: contextvars.ContextVar["StageTransaction | None"] = contextvars.ContextVar(
    "heliocal_transaction", default=None)


def current_transaction(root: str | os.PathLike | None = None,
                        stage: str | None = None) -> "StageTransaction | None":
    """The transaction active in this context (optionally: only if it is of ``root``/``stage``)."""
    txn = _CURRENT.get()
    if txn is None:
        return None
    if root is not None and Path(root).absolute() != txn.root.absolute():
        return None
    if stage is not None and stage != txn.stage:
        return None
    return txn


def new_run_id() -> str:
    """A unique, sortable run id: UTC time and 8 random hex digits."""
    now = _dt.datetime.now(_dt.timezone.utc)
    return f"{now:%Y%m%dT%H%M%S}Z-{secrets.token_hex(4)}"


def _source_signature(path: Path) -> list:
    """(relative name, size, mtime, inode) of a source file or of every file of a folder: compared
    after the run to tell that the source did not change while it was read."""
    if path.is_dir():
        files = sorted(q for q in path.rglob("*") if q.is_file())
    else:
        files = [path] if path.exists() else []
    out = []
    for q in files:
        st = q.stat()
        out.append((str(q.relative_to(path)) if q != path else "", st.st_size, st.st_mtime_ns,
                    st.st_ino))
    return out


class StageTransaction:
    """One run of a stage as a transaction on ``root`` (see the module docstring).

    Use :func:`transaction` (a context manager) or :func:`stage_transaction` (a decorator); code
    inside writes outputs with :meth:`write_bytes` / :meth:`staging_path` + :meth:`add_file`
    (Parquet: :func:`heliocal.pipeline.artifacts.write_artifact`, which finds the active
    transaction) and keeps files of the previous run with :meth:`carry_over`.

    Parameters
    ----------
    root : the folder the stage writes (work directory, or the report's output folder).
    stage : the subcommand (manifest ``ROOT/<stage>.manifest.json``).
    consistent_inputs : refuse to commit when two inputs read disagree (an artifact records another
        fingerprint of an upstream artifact than the one this run read): set ``False`` for a stage
        that reports stale inputs instead of refusing them (``report``).
    """

    def __init__(self, root: str | os.PathLike, stage: str, *, consistent_inputs: bool = True):
        self.root = Path(root)
        self.stage = stage
        self.consistent_inputs = consistent_inputs
        self.run_id = new_run_id()
        self.staging = self.root / _staging_name(stage, self.run_id)
        self.files: dict[str, dict] = {}
        self.inputs: dict[str, dict] = {}
        self._read_inputs: dict[str, dict] = {}  # label -> the recorded inputs of what was read
        self._sources: dict[str, tuple[Path, list]] = {}
        self.previous: Manifest | None = None
        self.options: Mapping | None = None
        self.seed: int | None = None
        self.command: str | None = None
        self.recovered: list[str] = []
        self._owner = None
        self._token = None
        self.committed = False

    # -- lifecycle ------------------------------------------------------------------------------
    def begin(self) -> "StageTransaction":
        self.root.mkdir(parents=True, exist_ok=True)
        self.recovered = recover(self.root)
        self.previous = load_manifest(self.root, self.stage)
        self.staging.mkdir()
        self._owner = open(self.staging / _OWNER, "a+b")
        fcntl.flock(self._owner.fileno(), fcntl.LOCK_EX)
        self._token = _CURRENT.set(self)
        return self

    def _release(self) -> None:
        if self._token is not None:
            _CURRENT.reset(self._token)
            self._token = None
        if self._owner is not None:
            self._owner.close()
            self._owner = None

    def abort(self) -> None:
        """Discard everything staged; the previous run stays the committed one. After the commit
        point nothing is discarded: the staged files belong to the committed run, and the next
        run (or reader) finds them there."""
        self._release()
        if not self.committed:
            shutil.rmtree(self.staging, ignore_errors=True)

    # -- inputs ---------------------------------------------------------------------------------
    def record_read(self, label: str, m: Manifest, rel: str) -> None:
        """Record that this run read ``rel`` of committed run ``m`` as input ``label``."""
        if m.root.absolute() == self.root.absolute() and m.stage == self.stage:
            return  # its own previous outputs (a partial run merging them): not an input
        entry = m.files[rel]
        rec = {"fingerprint": entry.get("fingerprint") or entry.get("sha256"),
               "sha256": entry.get("sha256"), "run_id": entry.get("run_id", m.run_id),
               "stage": m.stage, "path": rel}
        old = self.inputs.get(label)
        if old is not None and old["sha256"] != rec["sha256"]:
            raise StageInputError(
                f"{m.root / rel} changed while `heliocal {self.stage}` was reading it (another run "
                f"of `heliocal {m.stage}` committed meanwhile); rerun `heliocal {self.stage} "
                f"--workdir {self.root}`")
        self.inputs[label] = rec
        self._read_inputs[label] = m.input_fingerprints()

    def add_source(self, label: str, path: str | os.PathLike, sha256: str | None) -> None:
        """Record a source file or folder read by this run (``ingest``): its hash taken before
        reading and its file signature, compared again at commit."""
        path = Path(path)
        self.inputs[label] = {"sha256": sha256, "fingerprint": sha256, "path": str(path)}
        self._sources[label] = (path, _source_signature(path))

    def input_fingerprints(self) -> dict:
        return {k: v.get("fingerprint") for k, v in sorted(self.inputs.items())}

    # -- outputs --------------------------------------------------------------------------------
    def staging_path(self, rel: str | os.PathLike) -> Path:
        """Where to write output ``rel`` (its parent folders are made)."""
        rel = _rel(rel)
        path = self.staging / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def add_file(self, rel: str | os.PathLike, *, fingerprint: str | None = None,
                 artifact: str | None = None, sha256: str | None = None) -> Path:
        """Register output ``rel``, already written to :meth:`staging_path`; returns its final path."""
        rel = _rel(rel)
        path = self.staging / rel
        _fsync_file(path)
        sha = sha256 or sha256_of_file(path)
        self.files[rel] = {"sha256": sha, "size": path.stat().st_size,
                           "fingerprint": fingerprint or sha, "artifact": artifact,
                           "run_id": self.run_id}
        _write_point("staged", path)
        return self.root / rel

    def write_bytes(self, rel: str | os.PathLike, data: bytes, *, fingerprint: str | None = None,
                    artifact: str | None = None) -> Path:
        """Stage output ``rel`` with content ``data``; returns its final path."""
        path = self.staging_path(rel)
        with open(path, "wb") as fh:
            fh.write(data)
        return self.add_file(rel, fingerprint=fingerprint, artifact=artifact,
                             sha256=hashlib.sha256(data).hexdigest())

    def carry_over(self, rels) -> None:
        """Keep files of the previous committed run unchanged in this run (partial runs)."""
        if self.previous is None:
            return
        for rel in rels:
            rel = _rel(rel)
            if rel in self.previous.files and rel not in self.files:
                self.files[rel] = dict(self.previous.files[rel])

    def previous_files(self, under: str = "") -> list[str]:
        """Files of the previous committed run (optionally only those under folder ``under``)."""
        if self.previous is None:
            return []
        prefix = _rel(under) + "/" if under else ""
        return sorted(r for r in self.previous.files if r.startswith(prefix))

    # -- commit ---------------------------------------------------------------------------------
    def _check_inputs(self) -> None:
        for label, (path, signature) in self._sources.items():
            if _source_signature(path) != signature:
                raise InputError(f"{path} changed while `heliocal {self.stage}` was reading it; "
                                 f"rerun `heliocal {self.stage}` when it no longer changes")
        if not self.consistent_inputs:
            return
        for label, recorded in self._read_inputs.items():
            for up, fp in recorded.items():
                if up in self.inputs and fp is not None and self.inputs[up]["fingerprint"] != fp:
                    rec = self.inputs[label]
                    raise StageInputError(
                        f"{self.root / rec['path']} was made from another {up} than the one this "
                        f"run read ({up} changed while `heliocal {self.stage}` ran); rerun "
                        f"`heliocal {rec['stage']} --workdir {self.root}` and then this stage")

    def commit(self) -> Manifest:
        """Check the inputs, write the manifest (the commit point), move the files into place."""
        from . import __version__
        from .artifacts import _command_line, _jsonable, git_revision

        self._check_inputs()
        current = load_manifest(self.root, self.stage)
        prev_id = self.previous.run_id if self.previous else None
        if (current.run_id if current else None) != prev_id:
            # two runs of one stage at once: committing this one would silently replace the
            # other's outputs (or drop what it merged), so this one is not committed
            raise StageInputError(
                f"another `heliocal {self.stage}` run committed to {self.root} while this one ran "
                f"(run {current.run_id if current else None}); this run's outputs were not "
                f"committed, so nothing of the other run is lost: rerun `heliocal {self.stage} "
                f"--workdir {self.root}` when it has finished")
        base = current.files if current is not None else {}
        data = {
            "manifest_version": MANIFEST_VERSION,
            "stage": self.stage,
            "run_id": self.run_id,
            "previous_run_id": current.run_id if current else None,
            "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "heliocal_version": __version__,
            "git_revision": git_revision(),
            "command": self.command or _command_line(self.stage),
            "options": _jsonable(dict(self.options or {})),
            "seed": self.seed,
            "inputs": {k: v for k, v in sorted(self.inputs.items())},
            "files": {k: self.files[k] for k in sorted(self.files)},
            "removed": sorted(r for r in base if r not in self.files),
        }
        _fsync_dir(self.staging)
        text = json.dumps(data, indent=1, sort_keys=True) + "\n"
        target = manifest_path(self.root, self.stage)
        tmp = self.staging / f".{target.name}.tmp"  # removed with the staging folder
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        _write_point("manifest-temp", tmp)
        try:
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        self.committed = True
        _fsync_dir(self.root)
        _write_point("commit", target)
        m = Manifest(self.root, self.stage, self.run_id, data["files"], data["inputs"], data)
        _apply(m)  # still holding the owner lock: no one else applies it concurrently
        self._release()
        return m


@contextlib.contextmanager
def transaction(root: str | os.PathLike, stage: str, **kwargs) -> Iterator[StageTransaction]:
    """Run the block as one transaction of ``stage`` on ``root``: committed when the block ends
    without an exception, discarded (the previous run stays) when it raises.

    Inside a transaction of the same root and stage, a nested call reuses the outer one.
    """
    outer = current_transaction(root, stage)
    if outer is not None:
        yield outer
        return
    txn = StageTransaction(root, stage, **kwargs).begin()
    try:
        yield txn
    except BaseException:
        txn.abort()
        raise
    try:
        txn.commit()
    except BaseException:
        txn.abort()
        raise


def stage_transaction(stage: str, *, root: Callable[[Mapping], os.PathLike] | None = None,
                      **kwargs) -> Callable:
    """Decorator: the function (whose ``workdir`` argument is the root, unless ``root`` computes
    it from the bound arguments) runs as one transaction of ``stage``."""

    def decorator(func: Callable) -> Callable:
        sig = inspect.signature(func)

        @functools.wraps(func)
        def wrapper(*args, **kw):
            bound = sig.bind(*args, **kw)
            bound.apply_defaults()
            where = root(bound.arguments) if root is not None else bound.arguments["workdir"]
            with transaction(Path(where), stage, **kwargs):
                return func(*args, **kw)

        return wrapper

    return decorator
