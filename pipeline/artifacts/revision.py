"""Which code and command made a run: the git revision of the source tree, the identity of the
library's code, the command line, and options as JSON. Standard library only: a stage's
transaction records these on every commit, also when a rerun on unchanged inputs decides to keep
its files before pandas or torch is imported (:mod:`.unchanged`).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Mapping

__all__ = ["source_revision", "git_revision", "code_identity", "command_line", "jsonable"]


_GIT_REV: str | None = None


def source_revision(folder: str | os.PathLike) -> str:
    """Git revision of the checkout holding ``folder`` (``-dirty`` with local changes to tracked
    files; ``unknown`` outside a checkout or without git).

    Read-only: git runs with ``--no-optional-locks`` (and ``GIT_OPTIONAL_LOCKS=0``), so
    ``status`` compares the files without refreshing the index, and never takes
    ``.git/index.lock``: a run writes nothing into the code's repository, and runs at once do
    not collide there.
    """
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}

    def git(*args: str) -> str:
        return subprocess.run(["git", "--no-optional-locks", *args], cwd=folder,
                              capture_output=True, text=True, timeout=5, check=False,
                              env=env).stdout.strip()

    try:
        rev = git("rev-parse", "HEAD") or "unknown"
        if rev != "unknown" and git("status", "--porcelain", "--untracked-files=no"):
            rev += "-dirty"
    except (OSError, subprocess.SubprocessError):
        rev = "unknown"
    return rev


def git_revision() -> str:
    """Git revision of the heliocal source tree (:func:`source_revision`), asked once per
    process."""
    global _GIT_REV
    if _GIT_REV is None:
        _GIT_REV = source_revision(Path(__file__).resolve().parent)
    return _GIT_REV


def command_line(stage: str) -> str:
    """The heliocal command line of this run (``heliocal <stage>`` for in-process library calls)."""
    try:
        import click

        ctx = click.get_current_context(silent=True)
    except ImportError:  # pragma: no cover
        ctx = None
    if ctx is not None or Path(sys.argv[0]).name == "heliocal":
        return "heliocal " + " ".join(sys.argv[1:])
    return f"heliocal {stage} (library call)"


def jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


_CODE: str | None = None


def code_identity() -> str:
    """The code a result is computed with: the SHA-256 of every ``pipeline/**/*.py`` (path and
    bytes), so an edited library is never taken for another, whatever git says, and edits
    elsewhere (docs, tests) do not count. Asked once per process (about 100 files)."""
    global _CODE
    if _CODE is None:
        root = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for path in sorted(root.rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
        _CODE = h.hexdigest()
    return _CODE
