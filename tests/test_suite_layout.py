"""The Makefile's two passes run every test: a test marked ``alone`` sits in a module that the
serial pass collects.

``make test`` runs ``pytest -m "not alone"`` over the whole suite, then ``pytest -m alone`` over
the modules of the Makefile's ``ALONE_TESTS`` only (collecting every module again costs seconds
for six tests). A test marked ``alone`` in any other module would be deselected by the first pass
and never collected by the second: it would silently never run.
"""

from __future__ import annotations

import shlex

from conftest import ALONE_MODULES, REPO


def _makefile_alone_tests() -> set[str]:
    """The modules of the Makefile's ``ALONE_TESTS = ...`` line."""
    lines = [line for line in (REPO / "Makefile").read_text().splitlines()
             if line.startswith("ALONE_TESTS")]
    assert len(lines) == 1, lines
    return set(shlex.split(lines[0].split("=", 1)[1]))


def test_every_module_with_an_alone_test_is_in_the_serial_pass(request):
    listed = _makefile_alone_tests()
    collected = request.config.stash[ALONE_MODULES]  # of the modules this session collected
    assert collected <= listed, (
        f"tests marked alone in {sorted(collected - listed)}, which the Makefile's ALONE_TESTS "
        "does not list: make test would never run them")
    # every listed module exists and, when this session collected it, holds an alone test
    assert all((REPO / m).is_file() for m in listed), listed
    seen = {item.path.relative_to(REPO).as_posix() for item in request.session.items}
    assert {m for m in listed if m in seen} <= collected, (
        f"the Makefile's ALONE_TESTS lists {sorted(m for m in listed if m in seen) } but only "
        f"{sorted(collected)} hold tests marked alone")
