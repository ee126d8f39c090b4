"""A work directory is untrusted input (issue 32): manifests, run ids, links, FIFOs and leftovers
planted in it never make heliocal read, write or remove anything outside it, never wedge it, and
always give one clear line.

Most tests drive the transaction layer directly (``workdir_lock`` + ``transaction`` of a stage
``demo`` that writes two small files), as every stage does, so that hypothesis can try many
shapes of each hostile input in milliseconds. The expected outcome of every case is written out:
the file or folder outside the work directory keeps its bytes, and the run either commits or
stops with a :class:`HeliocalError`.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from heliocal.pipeline.artifacts import transaction as txn_module
from heliocal.pipeline.artifacts.audit import hostile_entries
from heliocal.pipeline.artifacts.leftovers import OWNER_FILENAME, leftovers
from heliocal.pipeline.artifacts.manifests import (CommittedWorkdir, InvalidManifest,
                                                   load_manifest, read_committed)
from heliocal.pipeline.artifacts.paths import confined, open_regular, relative_path_problem
from heliocal.pipeline.artifacts.transaction import transaction
from heliocal.pipeline.artifacts.workdir_lock import workdir_lock
from heliocal.pipeline.errors import HeliocalError, SchemaError, UnsafePathError

STAGE = "demo"
RUN_ID = "20250101T000000Z-0123abcd"
SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])


def _run_stage(root: Path, files: dict[str, bytes]) -> None:
    """One run of the stage ``demo`` as run_* functions do it: the workdir lock, then a
    transaction that writes ``files``."""
    with workdir_lock(root, STAGE):
        with transaction(root, STAGE) as txn:
            for rel, data in files.items():
                txn.write_bytes(rel, data)


def _fresh(tmp: Path) -> tuple[Path, Path, Path]:
    """(work directory with one committed run, a victim file outside it, a victim folder)."""
    if tmp.exists():
        shutil.rmtree(tmp)
    root = tmp / "wd"
    victim = tmp / "victim.txt"
    folder = tmp / "victim_dir"
    tmp.mkdir(parents=True)
    victim.write_text("precious\n")
    folder.mkdir()
    (folder / "keep.txt").write_text("precious\n")
    _run_stage(root, {"a.txt": b"first a", "sub/b.txt": b"first b"})
    return root, victim, folder


def _untouched(victim: Path, folder: Path) -> bool:
    return (victim.read_text() == "precious\n" and not victim.is_symlink()
            and (folder / "keep.txt").read_text() == "precious\n")


def _tamper(root: Path, **changes) -> None:
    path = root / f"{STAGE}.manifest.json"
    data = json.loads(path.read_text())
    for key, value in changes.items():
        if key == "files_add":
            data["files"][value] = {"sha256": "0" * 64, "size": 1, "run_id": data["run_id"]}
        elif key == "removed_add":
            data["removed"] = [*data.get("removed", []), value]
        else:
            data[key] = value
    path.write_text(json.dumps(data))


def _next_run_keeps_outside(root: Path, victim: Path, folder: Path) -> None:
    """The next run of the stage either commits or stops with one HeliocalError; outside, nothing
    changes; and a second run then commits (nothing is wedged)."""
    try:
        _run_stage(root, {"a.txt": b"second a"})
    except HeliocalError:
        pass
    assert _untouched(victim, folder)
    _run_stage(root, {"a.txt": b"third a"})
    assert read_committed(root, STAGE, "a.txt").data == b"third a"
    assert _untouched(victim, folder)


# ------------------------------------------------------------------------------------------------
# 1. manifests: paths and run ids that would leave the folder
# ------------------------------------------------------------------------------------------------
_PARTS = st.sampled_from(["..", ".", "", "sub", "x", ".heliocal.lock", "victim.txt",
                          "victim_dir", "demo.manifest.json", "a\x00b", "C:", "\\..\\"])


@st.composite
def hostile_rel(draw) -> str:
    """A path a tampered manifest may list: traversals, absolute paths, hidden names, NUL."""
    parts = draw(st.lists(_PARTS, min_size=1, max_size=5))
    rel = "/".join(parts)
    return ("/" + rel) if draw(st.booleans()) else rel


@SETTINGS
@given(rel=hostile_rel(), where=st.sampled_from(["files_add", "removed_add"]))
def test_manifest_paths_never_reach_outside(tmp_path, rel, where):
    """Before: a `files` or `removed` entry `../victim.txt` (or absolute) was deleted by the next
    run of the stage; `..` entries also moved files (the ISSUE's finding 1)."""
    root, victim, folder = _fresh(tmp_path / "case")
    _tamper(root, **{where: rel.replace("victim.txt", os.path.relpath(victim, root))})
    _next_run_keeps_outside(root, victim, folder)


@pytest.mark.parametrize("rel", ["../victim.txt", "sub/../../victim.txt", "ABS"])
@pytest.mark.parametrize("where", ["files_add", "removed_add"])
def test_manifest_traversal_is_refused_and_replaced(tmp_path, rel, where, caplog):
    root, victim, folder = _fresh(tmp_path / "case")
    _tamper(root, **{where: str(victim) if rel == "ABS" else rel})
    with pytest.raises(InvalidManifest, match="not a valid manifest"):
        load_manifest(root, STAGE)
    _run_stage(root, {"a.txt": b"second a"})  # the stage replaces its invalid manifest
    assert victim.read_text() == "precious\n"
    assert load_manifest(root, STAGE).files.keys() == {"a.txt"}
    assert "this run replaces it" in caplog.text


@SETTINGS
@given(run_id=st.one_of(
    st.sampled_from(["x/../../victim_dir", "../victim_dir", "/ABS", "x", "", ".",
                     "20250101T000000Z-0123abcd/../../victim_dir", "20250101T000000Z-0123ABCD"]),
    st.text(min_size=0, max_size=30)))
def test_run_ids_never_remove_anything_outside(tmp_path, run_id):
    """Before: run_id `x/../../victim_dir` with a leftover `.txn-demo-x` made the next stage
    remove victim_dir and its files (finding 1)."""
    root, victim, folder = _fresh(tmp_path / "case")
    run_id = run_id.replace("/ABS", str(folder))
    _tamper(root, run_id=run_id)
    with pytest.raises(InvalidManifest, match="run id"):
        load_manifest(root, STAGE)
    (root / ".txn-demo-x").mkdir()
    _next_run_keeps_outside(root, victim, folder)


@pytest.mark.parametrize("text,why", [
    ("[]", "a JSON list, not an object"),
    ('{"manifest_version": 1, "stage": "demo", "run_id": "x"', "not JSON"),
    ("[" * 100_000, "nested too deeply"),
    (b"\xff\xfe{\xe9}", "not JSON"),
    ('{"manifest_version": 1, "stage": "ingest", "run_id": "' + RUN_ID + '", "files": {}}',
     "it names stage 'ingest', not 'demo'"),
    ('{"manifest_version": 1, "stage": "demo", "run_id": "' + RUN_ID + '", "files": '
     '{"a.txt": ["x"]}}', "its entry of 'a.txt' has no SHA-256"),
])
def test_an_invalid_manifest_is_named_and_replaced_by_its_stage(tmp_path, text, why, caplog):
    """Before: `[]` or a cut manifest made the stage fail with "rerun heliocal <stage>", which
    failed the same way, forever (finding 4)."""
    root, victim, folder = _fresh(tmp_path / "case")
    path = root / f"{STAGE}.manifest.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(InvalidManifest) as err:
        load_manifest(root, STAGE)
    assert why in str(err.value) and "rerun `heliocal demo" in str(err.value)
    assert "\n" not in str(err.value)
    _run_stage(root, {"a.txt": b"repaired"})
    assert read_committed(root, STAGE, "a.txt").data == b"repaired"
    assert f"{path}: " in caplog.text and "this run replaces it" in caplog.text


def test_a_manifest_that_is_a_folder_is_refused_in_one_line_and_kept(tmp_path):
    root, victim, folder = _fresh(tmp_path / "case")
    path = root / f"{STAGE}.manifest.json"
    path.unlink()
    path.mkdir()
    (path / "mine.txt").write_text("precious\n")
    with pytest.raises(SchemaError, match="is a folder, not the manifest of `heliocal demo`"):
        _run_stage(root, {"a.txt": b"x"})
    assert (path / "mine.txt").read_text() == "precious\n"


# ------------------------------------------------------------------------------------------------
# 2. links (and FIFOs) planted in the work directory
# ------------------------------------------------------------------------------------------------
_ENTRIES = [".heliocal.lock", "sub", "a.txt", "sub/b.txt", f".txn-demo-{RUN_ID}",
            ".ingest-spill-x", f"{STAGE}.manifest.json", ".a.txt.tmp-x"]


@SETTINGS
@given(entry=st.sampled_from(_ENTRIES),
       target=st.sampled_from(["victim", "folder", "missing", "self"]))
def test_planted_links_are_never_followed(tmp_path, entry, target):
    """Before: `.heliocal.lock` -> a file outside truncated it, a linked `sub/` (or `hybrid/`)
    received the new files, a linked leftover folder was emptied (finding 2)."""
    root, victim, folder = _fresh(tmp_path / "case")
    link = root / entry
    if link.is_dir() and not link.is_symlink():
        shutil.rmtree(link)
    elif os.path.lexists(link):
        link.unlink()
    link.parent.mkdir(parents=True, exist_ok=True)
    dest = {"victim": victim, "folder": folder, "missing": tmp_path / "case" / "nowhere",
            "self": link}[target]
    link.symlink_to(dest)
    try:
        _run_stage(root, {"a.txt": b"second a", "sub/b.txt": b"second b"})
    except HeliocalError as exc:
        assert "\n" not in str(exc)
    assert _untouched(victim, folder)
    assert sorted(p.name for p in folder.iterdir()) == ["keep.txt"]


def test_a_linked_destination_folder_is_refused_before_the_commit(tmp_path):
    root, victim, folder = _fresh(tmp_path / "case")
    shutil.rmtree(root / "sub")
    (root / "sub").symlink_to(folder)
    before = load_manifest(root, STAGE).run_id
    with pytest.raises(UnsafePathError, match=r"sub is a symbolic link .*heliocal follows no link"):
        _run_stage(root, {"a.txt": b"second a", "sub/b.txt": b"second b"})
    assert load_manifest(root, STAGE).run_id == before  # nothing committed, nothing wedged
    assert sorted(p.name for p in folder.iterdir()) == ["keep.txt"]


def test_a_link_replacing_a_committed_file_is_refused_by_the_reader(tmp_path):
    root, victim, folder = _fresh(tmp_path / "case")
    shutil.copy(root / "a.txt", tmp_path / "copy.txt")
    (root / "a.txt").unlink()
    (root / "a.txt").symlink_to(tmp_path / "copy.txt")  # the same bytes, outside
    with pytest.raises(SchemaError, match="a.txt is a symbolic link"):
        read_committed(root, STAGE, "a.txt")
    _run_stage(root, {"a.txt": b"second a"})  # the commit replaces the link itself
    assert not (root / "a.txt").is_symlink() and (tmp_path / "copy.txt").read_bytes() == b"first a"


@pytest.mark.parametrize("name", ["a.txt", f"{STAGE}.manifest.json", ".heliocal.lock"])
def test_fifos_are_never_opened(tmp_path, name):
    """A FIFO named like an artifact, a manifest or the lock file: readers refuse it without
    blocking, the stage replaces or removes it, info flags it."""
    root, victim, folder = _fresh(tmp_path / "case")
    (root / name).unlink(missing_ok=True)  # the lock file is removed when a stage ends
    os.mkfifo(root / name)
    assert any(h["path"] == str(root / name) for h in hostile_entries(root))
    if name == "a.txt":
        with pytest.raises(SchemaError, match=r"a.txt is a FIFO \(named pipe\), not a file"):
            read_committed(root, STAGE, "a.txt")
    _run_stage(root, {"a.txt": b"second a"})
    assert read_committed(root, STAGE, "a.txt").data == b"second a"


def test_open_regular_refuses_links_fifos_and_devices(tmp_path):
    (tmp_path / "f").write_bytes(b"x")
    (tmp_path / "l").symlink_to(tmp_path / "f")
    os.mkfifo(tmp_path / "p")
    os.close(open_regular(tmp_path / "f"))
    for path, why in ((tmp_path / "l", "is a symbolic link"), (tmp_path / "p", "FIFO"),
                      (Path("/dev/null"), "character device")):
        with pytest.raises(UnsafePathError, match=why):
            open_regular(path)


@SETTINGS
@given(rel=hostile_rel())
def test_confined_never_returns_a_path_outside(tmp_path_factory, rel):
    root = tmp_path_factory.getbasetemp() / "confined"
    root.mkdir(exist_ok=True)
    try:
        path = confined(root, rel)
    except UnsafePathError:
        assert relative_path_problem(rel) is not None
        return
    assert os.path.commonpath([root, os.path.abspath(path)]) == str(root)


# ------------------------------------------------------------------------------------------------
# 3. leftovers of killed runs: removed by the next run, which says so in one line
# ------------------------------------------------------------------------------------------------
def test_leftovers_of_killed_runs_are_removed_and_named(tmp_path, caplog):
    """Before: `.ingest-spill-*` of a killed ingest stayed forever and info never mentioned it
    (finding 4)."""
    root, victim, folder = _fresh(tmp_path / "case")
    (root / f".txn-demo-{RUN_ID}").mkdir()
    (root / f".txn-demo-{RUN_ID}" / "a.txt").write_bytes(b"half")
    (root / ".ingest-spill-abc").mkdir()
    (root / ".ingest-spill-abc" / OWNER_FILENAME).write_bytes(b"")
    (root / ".ingest-spill-abc" / "rejected-000000.parquet").write_bytes(b"half")
    (root / ".a.txt.tmp-x").write_bytes(b"half")
    (root / ".ingest-spill-link").symlink_to(folder)
    assert {p.name for p in leftovers(root)} == {".ingest-spill-abc", ".a.txt.tmp-x",
                                                 ".ingest-spill-link"}
    _run_stage(root, {"a.txt": b"second a"})
    assert sorted(p.name for p in root.iterdir() if p.name.startswith(".")) == []
    lines = [r.getMessage() for r in caplog.records if "removed" in r.getMessage()]
    assert len(lines) == 1, lines
    for name in (f".txn-demo-{RUN_ID}", ".ingest-spill-abc", ".a.txt.tmp-x", ".ingest-spill-link"):
        assert name in lines[0]
    assert _untouched(victim, folder)


def test_a_live_spill_folder_is_left_alone(tmp_path):
    """A spill folder whose owner file is locked belongs to a live ingest: not removed."""
    import fcntl

    root, victim, folder = _fresh(tmp_path / "case")
    spill = root / ".ingest-spill-live"
    spill.mkdir()
    with open(spill / OWNER_FILENAME, "a+b") as owner:
        fcntl.flock(owner.fileno(), fcntl.LOCK_EX)
        pid = os.fork()
        if pid == 0:  # another process runs the stage while this one holds the owner lock
            code = 0
            try:
                _run_stage(root, {"a.txt": b"second a"})
            except BaseException:
                code = 1
            os._exit(code)
        _, status = os.waitpid(pid, 0)
        assert os.WEXITSTATUS(status) == 0
        assert spill.is_dir()


# ------------------------------------------------------------------------------------------------
# 4. another file system under the work directory (EXDEV after the commit)
# ------------------------------------------------------------------------------------------------
def test_a_destination_on_another_file_system_is_copied_into_place(tmp_path, monkeypatch):
    """Before: `hybrid/` on another mount failed with `internal error OSError ... Invalid
    cross-device link` after the commit, and every later stage the same way (finding 4). Here
    os.replace raises EXDEV for every destination under sub/, as across a mount point."""
    root, victim, folder = _fresh(tmp_path / "case")
    real_replace = os.replace
    crossed = []

    def replace(src, dst, **kw):
        if "/sub/" in str(dst) and f"/.txn-{STAGE}-" in str(src):
            crossed.append(str(dst))
            raise OSError(errno.EXDEV, "Invalid cross-device link", str(src))
        return real_replace(src, dst, **kw)

    monkeypatch.setattr(txn_module.os, "replace", replace)
    _run_stage(root, {"a.txt": b"second a", "sub/b.txt": b"second b"})
    assert crossed == [str(root / "sub" / "b.txt")]
    assert read_committed(root, STAGE, "sub/b.txt").data == b"second b"
    assert sorted(p.name for p in (root / "sub").iterdir()) == ["b.txt"]  # no temporary left
    assert not list(root.glob(".txn-*"))


# ------------------------------------------------------------------------------------------------
# 5. the one reader
# ------------------------------------------------------------------------------------------------
def test_one_reader_loads_each_manifest_once_and_reads_each_file_once(tmp_path, monkeypatch):
    from heliocal.pipeline.artifacts import manifests

    root, victim, folder = _fresh(tmp_path / "case")
    loads, opens = [], []
    real_load, real_open = manifests.load_manifest, manifests._open_committed
    monkeypatch.setattr(manifests, "load_manifest",
                        lambda r, s: loads.append(s) or real_load(r, s))
    monkeypatch.setattr(manifests, "_open_committed",
                        lambda m, rel: opens.append(rel) or real_open(m, rel))
    wd = CommittedWorkdir(root)
    for _ in range(3):
        assert wd.read(STAGE, "a.txt").data == b"first a"
        assert wd.read(STAGE, "sub/b.txt").data == b"first b"
        assert wd.fingerprint(STAGE, "a.txt") is not None
    assert loads == [STAGE] and opens == ["a.txt", "sub/b.txt"]


def test_info_flags_hostile_entries(tmp_path):
    root, victim, folder = _fresh(tmp_path / "case")
    _tamper(root, run_id="x/../../victim_dir")
    (root / "sub" / "link").symlink_to(victim)
    os.mkfifo(root / "fifo.parquet")
    found = {Path(h["path"]).name: h["problem"] for h in hostile_entries(root)}
    assert set(found) == {f"{STAGE}.manifest.json", "link", "fifo.parquet"}
    assert found["link"].startswith(f"a symbolic link to {victim}")
    assert "its run id 'x/../../victim_dir' is not a heliocal run id" in found[f"{STAGE}.manifest.json"]
    assert found["fifo.parquet"].startswith("a FIFO (named pipe)")


# ------------------------------------------------------------------------------------------------
# keep_same: a file rewritten with the bytes it has is kept, never read through a link
# ------------------------------------------------------------------------------------------------
def _run_keeping(root: Path, files: dict[str, bytes]) -> dict:
    """A run of ``demo`` writing ``files`` with ``keep_same`` (as the report writes its pages);
    returns its manifest's file entries."""
    with workdir_lock(root, STAGE):
        with transaction(root, STAGE) as txn:
            for rel, data in files.items():
                txn.write_bytes(rel, data, keep_same=True)
    return load_manifest(root, STAGE).files


def test_keep_same_keeps_a_file_with_the_same_bytes_and_writes_the_changed_one(tmp_path):
    root, _, _ = _fresh(tmp_path)
    first = load_manifest(root, STAGE).files
    inode = os.stat(root / "a.txt").st_ino
    files = _run_keeping(root, {"a.txt": b"first a", "sub/b.txt": b"second b"})
    # a.txt: the first run's entry and file (same inode: not staged and renamed again)
    assert files["a.txt"] == first["a.txt"]
    assert os.stat(root / "a.txt").st_ino == inode
    # sub/b.txt: changed bytes, written by this run
    assert files["sub/b.txt"]["run_id"] != first["sub/b.txt"]["run_id"]
    assert (root / "sub/b.txt").read_bytes() == b"second b"


def test_keep_same_writes_again_a_file_changed_by_hand_since_its_run(tmp_path):
    root, _, _ = _fresh(tmp_path)
    first = load_manifest(root, STAGE).files
    (root / "a.txt").write_bytes(b"edited")
    files = _run_keeping(root, {"a.txt": b"first a"})
    assert files["a.txt"]["run_id"] != first["a.txt"]["run_id"]
    assert (root / "a.txt").read_bytes() == b"first a"


def test_keep_same_does_not_read_or_keep_a_link_with_the_same_bytes_outside(tmp_path):
    root, victim, _ = _fresh(tmp_path)
    victim.write_bytes(b"first a")
    os.remove(root / "a.txt")
    os.symlink(victim, root / "a.txt")
    try:
        files = _run_keeping(root, {"a.txt": b"first a"})
    except HeliocalError:
        files = None                          # refused with one line: also acceptable
    assert victim.read_bytes() == b"first a"
    if files is not None:                     # committed: a regular file of its own in place
        assert not os.path.islink(root / "a.txt")
        assert (root / "a.txt").read_bytes() == b"first a"
