"""Reruns on unchanged inputs: whether a stage's previous committed run can be kept as it is, decided
from the manifests alone, and keeping it. Standard library only, so that the command line can
answer an unchanged ``--incremental`` rerun before it imports pandas, torch or scikit-learn
(``cli/rerun.py``).

The previous committed run of a stage is *kept* when

* it recorded the code it ran (``incremental.code``: :func:`~.revision.code_identity`), which is
  this process's code, with this heliocal version;
* its options equal the ones asked for now (each one given; and the seed, where one is given);
* every input it recorded is what its producer has committed now (the fingerprint of each input
  equals the one in the producer's manifest; a source file outside the work directory is never
  taken as unchanged, since a stage that reads one records it with a path the work directory
  cannot resolve);
* every file it committed is still there, with its size (a file deleted by hand is made again);
* where the stage depends on more than its recorded inputs (the report: every committed artifact
  that exists, the measurement floor, the git revision it prints), the digest of that *state*
  (``incremental.state``) is the one it recorded.

Keeping it reads no table and computes nothing: it is a stage run like any other, under the
work directory's lock and in one stage transaction, whose manifest lists the previous run's files
(their entries, run ids included, unchanged), inputs, options, seed and digests, and names the
run it kept (``kept_run``), so a further ``--incremental`` run starts from it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Callable, Mapping

from .manifests import (CommittedWorkdir, InvalidManifest, Manifest, all_manifests, load_manifest,
                        manifest_path)
from .paths import relative_path_problem
from .revision import code_identity, jsonable

__all__ = ["INCREMENTAL_KEY", "KEPT_KEY", "unchanged_problem", "carry_over_unchanged",
           "mark_rerunnable", "keep_if_unchanged", "workdir_state", "state_digest"]

#: Key of a stage's incremental record in its manifest (code, digests, state).
INCREMENTAL_KEY = "incremental"

#: Key naming, in the manifest of a run that kept its previous run's files, the run it kept.
KEPT_KEY = "kept_run"

#: A stage name as manifests spell it (lower-case letters, digits and '-').
_STAGE_NAME = re.compile(r"[a-z][a-z0-9-]{0,39}")


def unchanged_problem(prev: Manifest | None, workdir: str | os.PathLike, options: Mapping,
                      seed: int | None = None, state: str | None = None) -> str | None:
    """Why ``prev`` (a stage's previous committed run) cannot be kept for a run with ``options``
    (and ``seed``, ``state`` where given), reading the committed inputs of ``workdir``; ``None``
    when it can (see the module docstring)."""
    from .. import __version__

    if prev is None:
        return "there is no previous run"
    record = prev.data.get(INCREMENTAL_KEY)
    if not isinstance(record, dict) or not prev.inputs:
        return "the previous run recorded no code or inputs"
    recorded = prev.data.get("options")
    given = jsonable(dict(options))
    if not isinstance(recorded, dict) or any(k not in recorded or recorded[k] != v
                                             for k, v in given.items()):
        return "other options"
    if seed is not None and prev.data.get("seed") != seed:
        return "another seed"
    if record.get("code") != code_identity() or prev.data.get("heliocal_version") != __version__:
        return "other code"
    if state is not None and record.get("state") != state:
        return "another state of the work directory"
    wd = CommittedWorkdir.of(workdir)
    for rec in prev.inputs.values():
        # a manifest is untrusted input: only a stage's name and a plain relative path are looked up
        if not (isinstance(rec, dict) and isinstance(rec.get("stage"), str)
                and _STAGE_NAME.fullmatch(rec["stage"]) and isinstance(rec.get("path"), str)
                and relative_path_problem(rec["path"]) is None):
            return "an input the work directory does not resolve"
        try:
            current = wd.fingerprint(rec["stage"], rec["path"])
        except InvalidManifest:
            return f"the manifest of {rec['stage']} is invalid"
        if current is None or current != rec.get("fingerprint"):
            return f"{rec['path']} changed"
    for rel, entry in prev.files.items():
        try:
            size = os.lstat(prev.root / rel).st_size
        except OSError:
            return f"{rel} is missing"
        if size != entry.get("size"):
            return f"{rel} changed"
    return None


def carry_over_unchanged(txn, options: Mapping, seed: int | None = None, *,
                         workdir: str | os.PathLike | None = None,
                         state: str | None = None) -> bool:
    """When the previous committed run of ``txn``'s stage (``txn``: the active
    :class:`~.transaction.StageTransaction`) can be kept (:func:`unchanged_problem`; its inputs
    resolved in ``workdir``, default the transaction's root), make this run keep its files,
    inputs, options and digests as they are, without reading anything, and return True."""
    prev = txn.previous
    if unchanged_problem(prev, txn.root if workdir is None else workdir, options, seed,
                         state) is not None:
        return False
    txn.carry_over(txn.previous_files())
    txn.inputs.update(prev.inputs)
    txn.extra[INCREMENTAL_KEY] = prev.data[INCREMENTAL_KEY]
    txn.extra[KEPT_KEY] = prev.run_id
    txn.options, txn.seed = prev.data["options"], prev.data.get("seed")
    return True


def mark_rerunnable(txn) -> None:
    """Record the code in ``txn``'s manifest, so that a later run of a stage that is computed
    whole (no per-heliostat digests: fit-hybrid, sweep) can keep it with
    :func:`carry_over_unchanged`."""
    txn.extra.setdefault(INCREMENTAL_KEY, {"code": code_identity()})


def keep_if_unchanged(root: str | os.PathLike, stage: str, options: Mapping, *,
                      workdir: str | os.PathLike | None = None, seed: int | None = None,
                      state: Callable[[], str] | None = None,
                      command: str | None = None) -> Manifest | None:
    """Run ``stage`` on ``root`` (its work directory, or the report's folder in ``workdir``) as a
    run that keeps the previous one, if it can be kept (:func:`carry_over_unchanged`; ``state``
    is computed under the lock), and return the committed run. Returns None, having committed
    nothing, when it cannot, or when the folder needs what a stage's first step does besides
    (an interrupted commit to complete, a dead run's leftovers to remove, an invalid manifest to
    replace): the stage's own run then does that and says so."""
    from .leftovers import has_staging_folder, leftovers
    from .transaction import StageTransaction
    from .workdir_lock import workdir_lock

    root = Path(root)
    workdir = root if workdir is None else Path(workdir)
    if not (root.is_dir() and workdir.is_dir() and manifest_path(root, stage).is_file()):
        return None
    with workdir_lock(workdir, stage):
        try:
            if load_manifest(root, stage) is None:
                return None
        except InvalidManifest:
            return None
        if has_staging_folder(root) or (root == workdir and leftovers(root)):
            return None  # an interrupted commit or a dead run's leftovers: the stage's to say
        txn = StageTransaction(root, stage).begin()
        try:
            if not carry_over_unchanged(txn, options, seed, workdir=workdir,
                                        state=state() if state is not None else None):
                txn.abort()
                return None
            txn.command = command
            return txn.commit()
        except BaseException:
            txn.abort()
            raise


def workdir_state(workdir: str | os.PathLike, skip: tuple[str, ...] = ()) -> dict:
    """What the committed runs of ``workdir`` hold, by stage (except ``skip``): each file's
    SHA-256, each input's fingerprint, the options and seed; and the names of the entries of
    the folder (hidden ones aside), so that a file no run committed counts too."""
    root = Path(workdir)
    runs = {m.stage: {"files": {rel: e.get("sha256") for rel, e in sorted(m.files.items())},
                      "inputs": {k: (v.get("fingerprint") if isinstance(v, dict) else None)
                                 for k, v in sorted(m.inputs.items())},
                      "options": m.data.get("options"), "seed": m.data.get("seed")}
            for m in all_manifests(root) if m.stage not in skip}
    entries = sorted(n for n in os.listdir(root) if not n.startswith("."))
    return {"runs": runs, "entries": entries}


def state_digest(value) -> str:
    """SHA-256 (hex) of a JSON-able ``value`` (keys sorted)."""
    text = json.dumps(jsonable(value), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
