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
import datetime as _dt
import errno
import fcntl
import functools
import hashlib
import inspect
import json
import logging
import os
import secrets
import shutil
from pathlib import Path
from typing import Callable, Iterator, Mapping

from ..errors import InputError, SchemaError, StageInputError, UnsafePathError
from .manifests import (ACTIVE_TRANSACTION, MANIFEST_VERSION, InvalidManifest, Manifest,
                        all_manifests, checked_relative_path, current_transaction, load_manifest,
                        manifest_path, staging_name)
from .leftovers import (BUSY, OWNER_FILENAME, has_staging_folder, leftovers, remove_leftover,
                        stale_staging_folders, staging_in_use, try_lock, unlock)
from .paths import confined, is_real_dir, link_message, read_regular, sha256_of_file
from .workdir_lock import holds_workdir_lock

__all__ = [
    "StageTransaction",
    "transaction",
    "stage_transaction",
    "recover",
    "stale_staging_folders",
    "pending_commits",
    "staging_in_use",
    "leftovers",
]

log = logging.getLogger("heliocal.artifacts")




def _write_point(event: str, path: Path) -> None:
    """Called right after every write, rename or removal of a transaction (``event``: ``staged``,
    ``manifest-temp``, ``commit``, ``apply``, ``remove``, ``cleanup``). A no-op; the
    crash-consistency test replaces it to kill the process at each point in turn."""


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


# ------------------------------------------------------------------------------------------------
# applying a commit and recovering interrupted ones
# ------------------------------------------------------------------------------------------------
def _move_into_place(src: Path, dst: Path, run_id: str) -> None:
    """Rename staged ``src`` to ``dst``. Across file systems (``dst``'s folder is another mount,
    ``EXDEV``) the bytes are copied to a hidden file beside ``dst`` (created, never followed),
    fsynced and renamed over ``dst``, then ``src`` is removed: the same atomic replacement."""
    try:
        os.replace(src, dst)
        return
    except OSError as exc:
        if exc.errno != errno.EXDEV:
            raise
    tmp = dst.parent / f".{dst.name}.tmp-{run_id}"
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)  # a copy of this same run that was killed
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    try:
        with open(fd, "wb", closefd=True) as out, open(src, "rb") as inp:
            shutil.copyfileobj(inp, out, 1 << 20)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, dst)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(dst.parent)
    os.unlink(src)


def _destination(root: Path, rel: str, stage: str) -> Path:
    """Where committed file ``rel`` goes: confined to ``root`` (no link on the way) and not a
    folder. Raises before a commit, so that a refused destination never wedges one."""
    dst = confined(root, rel, replace_link=True)  # a link there is replaced, never followed
    if is_real_dir(dst):  # a folder where the artifact goes: not ours to remove
        raise SchemaError(f"{dst} is a folder; remove it and rerun `heliocal {stage} "
                          f"--workdir {root}`")
    return dst


def _apply(m: Manifest) -> None:
    """Move the staged files of committed run ``m`` into place, remove the files it dropped, and
    remove its staging folder. Idempotent: a second call (or one after a kill) finishes the job.
    Every path is confined to ``m.root`` (:func:`confined`): no link is followed."""
    staging = m.staging
    moved_dirs = set()
    for rel in sorted(m.files):
        src = confined(staging, rel)  # a link planted in the staging folder is refused
        if os.path.isfile(src):
            dst = _destination(m.root, rel, m.stage)
            dst.parent.mkdir(parents=True, exist_ok=True)
            _move_into_place(src, dst, m.run_id)
            moved_dirs.add(dst.parent)
            _write_point("apply", dst)
    for d in moved_dirs:
        _fsync_dir(d)
    for rel in m.data.get("removed", []):
        if rel in m.files:
            continue
        dst = confined(m.root, rel, replace_link=True)
        if os.path.lexists(dst) and not is_real_dir(dst):
            dst.unlink()  # a file, or a link itself (never what it points to)
            _write_point("remove", dst)
    shutil.rmtree(staging, ignore_errors=True)
    _fsync_dir(m.root)
    _write_point("cleanup", staging)


def pending_commits(root: str | os.PathLike) -> list[Manifest]:
    """Committed runs in ``root`` whose files are not all moved into place yet."""
    return [m for m in all_manifests(root) if m.pending()]


def recover(root: str | os.PathLike, *, leftover_files: bool = False) -> list[str]:
    """Finish interrupted commits in ``root`` and remove dead uncommitted staging folders; with
    ``leftover_files`` (the caller holds the work directory's lock, so no other writer is alive)
    also ingest's spill folders and temporary files of killed runs (:func:`leftovers`).

    A staging or spill folder whose owner is alive (its lock is held) is left alone. Returns what
    was done, one short item each (the caller logs them as one line).
    """
    root = Path(root)
    done = []
    staged = has_staging_folder(root)  # else no commit to complete, no dead run's folder
    for m in pending_commits(root) if staged else ():
        lock = try_lock(m.staging / OWNER_FILENAME)
        if lock is BUSY:
            continue  # its writer is still applying it
        try:
            _apply(m)
            done.append(f"completed the interrupted commit of `heliocal {m.stage}` run {m.run_id}")
        finally:
            unlock(lock)
    for folder in stale_staging_folders(root) if staged else ():
        if remove_leftover(folder):
            done.append(f"removed {folder.name} (a run that stopped before its commit)")
    if leftover_files:
        for path in leftovers(root):
            kind = "link" if os.path.islink(path) else "folder" if is_real_dir(path) else "file"
            if remove_leftover(path):
                done.append(f"removed {path.name} (a {kind} left by a killed run)")
    return done


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
    (Parquet: :func:`heliocal.pipeline.artifacts.store.write_artifact`, which finds the active
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
        self.staging = self.root / staging_name(stage, self.run_id)
        self.files: dict[str, dict] = {}
        self.inputs: dict[str, dict] = {}
        self._read_inputs: dict[str, dict] = {}  # label -> the recorded inputs of what was read
        self._sources: dict[str, tuple[Path, list]] = {}
        self.previous: Manifest | None = None
        self.options: Mapping | None = None
        self.seed: int | None = None
        self.command: str | None = None
        self.recovered: list[str] = []
        self.extra: dict = {}  # further manifest entries (artifacts.incremental's digests)
        self.replaces_invalid: InvalidManifest | None = None
        self._owner = None
        self._token = None
        self.committed = False

    # -- lifecycle ------------------------------------------------------------------------------
    def begin(self) -> "StageTransaction":
        self._check_root()
        self.root.mkdir(parents=True, exist_ok=True)
        self.recovered = recover(self.root, leftover_files=holds_workdir_lock(self.root))
        if self.recovered:
            log.warning("%s: %s", self.root, "; ".join(self.recovered))
        try:
            self.previous = load_manifest(self.root, self.stage)
        except InvalidManifest as exc:
            if is_real_dir(exc.path):
                raise SchemaError(f"{exc.path} is a folder, not the manifest of `heliocal "
                                  f"{self.stage}`; move it away, then rerun `heliocal {self.stage} "
                                  f"--workdir {self.root}`") from None
            # its own manifest, broken: this run replaces it (its old files stay until then)
            self.replaces_invalid = exc
            log.warning("%s: %s; this run replaces it", exc.path, exc.why)
            self.previous = None
        self.staging.mkdir()
        self._owner = open(self.staging / OWNER_FILENAME, "a+b")
        fcntl.flock(self._owner.fileno(), fcntl.LOCK_EX)
        self._token = ACTIVE_TRANSACTION.set(self)
        return self

    def _check_root(self) -> None:
        """A root inside a work directory this process writes (the report's folder) is confined
        to it like every other output: it may not be a symbolic link."""
        if os.path.islink(self.root) and holds_workdir_lock(self.root.parent):
            raise UnsafePathError(link_message(self.root))

    def _release(self) -> None:
        if self._token is not None:
            ACTIVE_TRANSACTION.reset(self._token)
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
        rel = checked_relative_path(rel)
        path = self.staging / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def add_file(self, rel: str | os.PathLike, *, fingerprint: str | None = None,
                 artifact: str | None = None, sha256: str | None = None) -> Path:
        """Register output ``rel``, already written to :meth:`staging_path`; returns its final path."""
        rel = checked_relative_path(rel)
        path = self.staging / rel
        _fsync_file(path)
        sha = sha256 or sha256_of_file(path)
        self.files[rel] = {"sha256": sha, "size": path.stat().st_size,
                           "fingerprint": fingerprint or sha, "artifact": artifact,
                           "run_id": self.run_id}
        _write_point("staged", path)
        return self.root / rel

    def write_bytes(self, rel: str | os.PathLike, data: bytes, *, fingerprint: str | None = None,
                    artifact: str | None = None, keep_same: bool = False) -> Path:
        """Stage output ``rel`` with content ``data``; returns its final path. With
        ``keep_same``, a file the previous run committed with these very bytes (and still holds
        them) is kept as it is instead (:meth:`carry_over`): no second copy, no fsync."""
        sha = hashlib.sha256(data).hexdigest()
        if keep_same and fingerprint is None and self._holds(rel, data, sha, artifact):
            self.carry_over([rel])
            return self.root / checked_relative_path(rel)
        path = self.staging_path(rel)
        with open(path, "wb") as fh:
            fh.write(data)
        return self.add_file(rel, fingerprint=fingerprint, artifact=artifact, sha256=sha)

    def _holds(self, rel: str | os.PathLike, data: bytes, sha: str, artifact: str | None) -> bool:
        """Whether the previous run committed ``rel`` with SHA-256 ``sha`` (as ``artifact``) and
        the regular file in place (not a link) still has the bytes ``data``."""
        rel = checked_relative_path(rel)
        entry = self.previous.files.get(rel) if self.previous is not None else None
        if (entry is None or entry.get("sha256") != sha or entry.get("artifact") != artifact
                or entry.get("fingerprint") not in (None, sha)):
            return False
        try:  # a link or anything but a regular file in place: written anew (and refused there)
            return read_regular(confined(self.root, rel)) == data
        except (OSError, UnsafePathError):
            return False

    def carry_over(self, rels) -> None:
        """Keep files of the previous committed run unchanged in this run (partial runs)."""
        if self.previous is None:
            return
        for rel in rels:
            rel = checked_relative_path(rel)
            if rel in self.previous.files and rel not in self.files:
                self.files[rel] = dict(self.previous.files[rel])

    def previous_files(self, under: str = "") -> list[str]:
        """Files of the previous committed run (optionally only those under folder ``under``)."""
        if self.previous is None:
            return []
        prefix = checked_relative_path(under) + "/" if under else ""
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

    def _check_destinations(self, data: dict) -> None:
        """Refuse, before the commit point, what would fail after it: a destination behind a
        symbolic link or occupied by a folder, and a manifest name taken by a folder."""
        for rel in data["files"]:
            _destination(self.root, rel, self.stage)
        for rel in data["removed"]:
            confined(self.root, rel, replace_link=True)
        target = manifest_path(self.root, self.stage)
        if is_real_dir(target):
            raise SchemaError(f"{target} is a folder, not the manifest of `heliocal {self.stage}`; "
                              f"move it away, then rerun `heliocal {self.stage} --workdir "
                              f"{self.root}`")

    def commit(self) -> Manifest:
        """Check the inputs, write the manifest (the commit point), move the files into place."""
        from .. import __version__
        from .revision import command_line, git_revision, jsonable

        self._check_inputs()
        try:
            current = load_manifest(self.root, self.stage)
        except InvalidManifest:
            if self.replaces_invalid is None:
                raise
            current = None  # the invalid manifest this run replaces
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
            "command": self.command or command_line(self.stage),
            "options": jsonable(dict(self.options or {})),
            "seed": self.seed,
            "inputs": {k: v for k, v in sorted(self.inputs.items())},
            "files": {k: self.files[k] for k in sorted(self.files)},
            "removed": sorted(r for r in base if r not in self.files),
            **self.extra,
        }
        self._check_destinations(data)
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
