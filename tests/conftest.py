"""Shared, generic fixtures: paths of the committed test data, the real Jülich data and a CLI runner."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

TESTS = Path(__file__).resolve().parent
GOOD = TESTS / "data" / "good"
BAD = TESTS / "data" / "bad"
#: The real PAINT data; CI keeps it in ../shared beside the repository.
JUELICH = Path(__file__).resolve().parents[2] / "shared" / "data" / "juelich"


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
