"""Shared fixtures: paths of the committed test data, the real Jülich data, a CLI runner, and the
work directories that several test modules start from, built once per test session.

How the suite runs (``make test``; docs/experiments/test-durations.md has the measurements):

* a parallel pass, ``pytest -n 2 --dist loadscope -m "not alone"`` (pytest-xdist): the tests of one
  module (or of one class) go to the same worker process, in file order, so a module-scoped
  fixture is built once; modules with slow tests start first (``pytest_collection_modifyitems``);
  a module whose slow tests are independent chains can put each in a class of its own
  (test_docs_commands.py does);
  each worker runs torch and the BLAS libraries on one thread (two workers, two cores);
* a serial pass, ``pytest -m alone`` over the modules of the Makefile's ``ALONE_TESTS``: tests
  that need the machine to themselves (time windows, watchdogs, a worker pool they count) run
  there, with nothing beside them (a module with such a test joins that list;
  tests/test_suite_layout.py fails until it does).

A new test that runs stages end to end is marked ``slow`` (``make test-fast`` skips it); one whose
checks depend on time (a deadline, a window in seconds) is marked ``alone`` as well. A work
directory that several modules need is a session fixture here, built by :func:`built_once`
(once for all worker processes) and never written to: a test that changes it works on a copy
(:func:`copy_of`); a session that changed it fails at its end.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from typer.testing import CliRunner

# In a worker process of the parallel pass, torch and the BLAS pools behind numpy and scipy run
# one thread each (and so do the commands the tests start, which inherit the environment): the
# workers are as many as the cores, and a second thread per worker only makes the threads wait on
# each other's cores. Set before anything imports torch; the serial pass keeps the defaults.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
GOOD = TESTS / "data" / "good"
BAD = TESTS / "data" / "bad"
#: The real PAINT data; CI keeps it in ../shared beside the repository.
JUELICH = Path(__file__).resolve().parents[2] / "shared" / "data" / "juelich"
#: The bundled sample of three Jülich heliostats (BE36 177, BF41 170, BH35 149 measurements).
SAMPLE_PAINT = REPO / "sample_data" / "juelich" / "paint"


# ------------------------------------------------------------------------------------------------
# scheduling under pytest-xdist
# ------------------------------------------------------------------------------------------------
def _scope(item) -> str:
    """The unit of work of ``--dist loadscope``: the test's module, or its class."""
    return item.nodeid.rsplit("::", 1)[0]


#: The test modules, by path relative to the repository, that hold a test marked ``alone``, as
#: collected (before ``-m`` deselects any): the Makefile's serial pass collects only the modules of
#: its ``ALONE_TESTS`` list, and tests/test_suite_layout.py checks that the two agree.
ALONE_MODULES = pytest.StashKey[set]()


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Record :data:`ALONE_MODULES`; in a worker process of xdist, put the slow units first."""
    config.stash[ALONE_MODULES] = {
        item.path.relative_to(REPO).as_posix() for item in items if item.get_closest_marker("alone")}
    _slow_units_first(items)


def _slow_units_first(items):
    """In a worker process of xdist the units of work (modules, classes) that hold slow tests
    come first, in file order, so that the long ones start early and the short ones fill in at
    the end (``--no-loadscope-reorder`` keeps this order; xdist's own would put the units with
    the most tests first). Without xdist the order is pytest's."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        slow = {_scope(item) for item in items if item.get_closest_marker("slow")}
        items.sort(key=lambda item: _scope(item) not in slow)  # stable: file order within


#: What the stages' first calls import in the fork server of their worker pools (their
#: ``warm_up``), all at once.
STAGE_MODULES = ("heliocal.pipeline.stages.fit_coarse", "ruptures", "heliocal.pipeline.stages.sweep",
                 "heliocal.pipeline.stages.fit_hybrid", "heliocal.pipeline.stages.plan")


@functools.cache
def _warm_fork_server() -> None:
    from heliocal.pipeline.runtime.parallel import warm_up

    warm_up(STAGE_MODULES, workers=2)


@pytest.fixture(autouse=True)
def _fork_server_with_the_stages(request):
    """In a worker process of xdist, before its first slow test: start the process's fork server
    with the stages' modules imported, as a command's stage does first (``warm_up``). A fork
    server keeps the modules of its first start, and a test that starts a pool directly
    (test_parallel's) would otherwise leave one without torch, each later pool worker importing
    torch and the stages itself (about 1.3 s of CPU per worker; a sampling profile of the suite
    found 4 % of its CPU there, docs/experiments/test-durations.md). ``make test-fast`` runs no
    slow test and starts no server."""
    if os.environ.get("PYTEST_XDIST_WORKER") and request.node.get_closest_marker("slow"):
        _warm_fork_server()


# ------------------------------------------------------------------------------------------------
# folders built once per session, shared by the worker processes
# ------------------------------------------------------------------------------------------------
def _digest(folder: Path) -> str:
    """SHA-256 over the relative names and bytes of every file under ``folder``."""
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(folder)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def built_once(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """The folder ``name``, made by ``build(folder)`` once in this test session: the worker
    processes of ``pytest -n`` share one (a file lock lets the first build it and the others wait
    for it). Read it, never write it: copy it first (:func:`copy_of`)."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, above the workers' own
    folder = root / f"shared-{name}"
    done = root / f"shared-{name}.sha256"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.write_text(_digest(folder))
    return folder


def check_unchanged(folder: Path) -> None:
    """Fail if a shared folder of :func:`built_once` was written to since it was built."""
    recorded = (folder.parent / f"{folder.name}.sha256").read_text()
    assert _digest(folder) == recorded, (
        f"a test changed the shared folder {folder}; tests must work on a copy (copy_of)")


def fitted_simulation(root: Path, *, rolling_origins: int = 3, **simulate) -> tuple:
    """(the simulated field, its work directory under ``root`` after ingest, split-knn and
    fit-coarse): ``simulate`` are :func:`simulate_field`'s arguments."""
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.simulate import write_field
    from heliocal.pipeline.stages.split import run_split

    field = simulate_field(**simulate)
    write_field(field, root / "field")
    work = root / "work"
    run_ingest([root / "field" / "paint"], work, IngestOptions())
    run_split(work)
    run_fit_coarse(work, rolling_origins=rolling_origins)
    return field, work


def copy_of(folder: Path, dest: Path) -> Path:
    """A private copy of ``folder`` at ``dest`` (modification times kept, as Make needs)."""
    return Path(shutil.copytree(folder, dest, symlinks=True))


@pytest.fixture(scope="session")
def sample_split(tmp_path_factory) -> Path:
    """``heliocal ingest sample_data/juelich/paint`` and ``heliocal split-knn`` (defaults: 30 test
    + 20 validation, kNN, seed 0) in one work directory, as the first two stages of ``make
    sample`` make it. Shared: read only, or copy it (:func:`copy_of`)."""
    from heliocal.cli.main import app

    def build(wd: Path) -> None:
        runner = CliRunner()
        for args in (["ingest", str(SAMPLE_PAINT)], ["split-knn"]):
            result = runner.invoke(app, [*args, "--workdir", str(wd), "--quiet"])
            assert result.exit_code == 0, (args, result.stdout, result.stderr)

    folder = built_once(tmp_path_factory, "sample-split", build)
    yield folder
    check_unchanged(folder)


# ------------------------------------------------------------------------------------------------
# data and a runner
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def good_dir() -> Path:
    """Small valid fixtures written out by tests/data/bad/make_corpus.py."""
    return GOOD


@pytest.fixture(scope="session")
def bad_dir() -> Path:
    """The bad-input corpus (see tests/data/bad/CASES.md)."""
    return BAD


@pytest.fixture(scope="session")
def juelich_dir() -> Path:
    """The real Jülich data, or skip when this checkout has no ../shared/data/juelich."""
    if not (JUELICH / "tower-measurements.json").is_file():
        pytest.skip(f"real Jülich data not found at {JUELICH} (CI keeps it in ../shared/data)")
    return JUELICH


@pytest.fixture
def runner() -> CliRunner:
    """Click/typer test runner; stderr is kept apart from stdout (result.stderr)."""
    return CliRunner()
