"""The code revision in every artifact's provenance is read without writing into the code's
repository (issue 32, finding 8): before, every stage ran ``git status``, which refreshes the
index when it is stale and so takes ``.git/index.lock`` and rewrites ``.git/index`` in the
checkout heliocal runs from (two runs at once could collide there).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from heliocal.pipeline.artifacts.provenance import source_revision


def _git(repo: Path, *args: str) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t",
           "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    return subprocess.run(["git", *args], cwd=repo, env=env, check=True, capture_output=True,
                          text=True).stdout.strip()


def test_the_revision_is_read_without_touching_the_index(tmp_path):
    repo = tmp_path / "code"
    repo.mkdir()
    _git(repo, "init", "-q")
    (repo / "module.py").write_text("x = 1\n")
    _git(repo, "add", "module.py")
    _git(repo, "commit", "-q", "-m", "one")
    head = _git(repo, "rev-parse", "HEAD")
    index = repo / ".git" / "index"
    st = (repo / "module.py").stat()
    os.utime(repo / "module.py", ns=(st.st_atime_ns, st.st_mtime_ns + 5 * 10**9))  # stale index
    before = index.stat()

    assert source_revision(repo) == head  # same content: clean, although the stat info differs
    after = index.stat()
    assert (after.st_ino, after.st_mtime_ns, after.st_size) == (
        before.st_ino, before.st_mtime_ns, before.st_size)
    assert not (repo / ".git" / "index.lock").exists()

    (repo / "module.py").write_text("x = 2\n")
    assert source_revision(repo) == head + "-dirty"
    assert index.stat().st_ino == before.st_ino


def test_outside_a_checkout_the_revision_is_unknown(tmp_path):
    assert source_revision(tmp_path) == "unknown"
