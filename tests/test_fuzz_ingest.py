"""Fuzz the CSV ingest: random damage to a valid log never crashes it and never loses a row.

Starting from tests/data/good/juelich_log_small.csv (10 rows), hypothesis deletes, duplicates
and swaps cells, writes garbage strings, NaN, inf and huge numbers, swaps header names and cuts
lines short. For every input, :func:`heliocal.pipeline.ingest.ingest` either raises a
:class:`HeliocalError` with a one-line message naming the file, or keeps and rejects rows that
add up to the number of data rows of the file (counted here with Python's csv module: non-blank
records after the header).
"""

from __future__ import annotations

import csv
import io
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from heliocal.pipeline.errors import HeliocalError
from heliocal.pipeline.ingest import ingest

GOOD = Path(__file__).resolve().parent / "data" / "good"
ROWS = list(csv.reader(io.StringIO((GOOD / "juelich_log_small.csv").read_text(encoding="utf-8"))))
N_COLS = len(ROWS[0])

_garbage = st.one_of(
    st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=12),
    st.sampled_from(["", " ", "NaN", "nan", "inf", "-inf", "Infinity", "1e400", "-1e400",
                     "1e308", "9" * 40, "0x1F", "1,5", '"', "''", "None", "null", "-0",
                     "2022-06-12", "2022-02-30T10:00:00Z", "T", "\t", ";", "ä", "\ufeff"]),
)
_row = st.integers(1, len(ROWS) - 1)
_col = st.integers(0, N_COLS - 1)
_op = st.one_of(
    st.tuples(st.just("set"), _row, _col, _garbage),
    st.tuples(st.just("delete"), _row, _col),
    st.tuples(st.just("duplicate"), _row, _col),
    st.tuples(st.just("swap_cells"), _row, _col, _col),
    st.tuples(st.just("swap_header"), _col, _col),
    st.tuples(st.just("number"), _row, _col, st.floats(allow_nan=True, allow_infinity=True)),
    st.tuples(st.just("duplicate_row"), _row),
    st.tuples(st.just("truncate"), _row, st.floats(0.0, 1.0)),
)


def _mutate(ops) -> str:
    grid = [list(r) for r in ROWS]
    truncations = []
    for op in ops:
        kind = op[0]
        if kind == "set":
            grid[op[1]][min(op[2], len(grid[op[1]]) - 1)] = op[3]
        elif kind == "delete" and len(grid[op[1]]) > 1:
            del grid[op[1]][min(op[2], len(grid[op[1]]) - 1)]
        elif kind == "duplicate":
            r = grid[op[1]]
            r.insert(min(op[2], len(r) - 1), r[min(op[2], len(r) - 1)])
        elif kind == "swap_cells":
            r = grid[op[1]]
            i, j = min(op[2], len(r) - 1), min(op[3], len(r) - 1)
            r[i], r[j] = r[j], r[i]
        elif kind == "swap_header":
            grid[0][op[1]], grid[0][op[2]] = grid[0][op[2]], grid[0][op[1]]
        elif kind == "number":
            grid[op[1]][min(op[2], len(grid[op[1]]) - 1)] = repr(op[3])
        elif kind == "duplicate_row":
            grid.append(list(grid[op[1]]))
        elif kind == "truncate":
            truncations.append((op[1], op[2]))
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(grid)
    lines = out.getvalue().split("\n")
    for line_no, frac in truncations:
        if line_no < len(lines):
            lines[line_no] = lines[line_no][: int(len(lines[line_no]) * frac)]
    return "\n".join(lines)


def _data_rows(text: str) -> int | None:
    """Non-blank CSV records after the header (None if the csv module cannot parse it)."""
    try:
        records = [r for r in csv.reader(io.StringIO(text, newline=""), skipinitialspace=True,
                                         strict=True) if r and not (len(r) == 1 and not r[0].strip())]
    except csv.Error:
        return None
    return max(len(records) - 1, 0)


@pytest.fixture(scope="module")
def fuzz_dir():
    with tempfile.TemporaryDirectory() as d:
        shutil.copyfile(GOOD / "tower-measurements.json", Path(d) / "tower-measurements.json")
        yield Path(d)


@settings(max_examples=50, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=st.lists(_op, min_size=1, max_size=6))
def test_fuzzed_log_rows_are_all_accounted_for(fuzz_dir, ops):
    text = _mutate(ops)
    path = fuzz_dir / "fuzzed_log.csv"
    path.write_text(text, encoding="utf-8")
    try:
        measurements, heliostats, rejected, info = ingest([path])
    except HeliocalError as exc:
        message = str(exc)
        assert "\n" not in message and message.startswith(str(path)), message
        return
    n = _data_rows(text)
    assert n is not None, "ingest read a file the csv module cannot parse"
    assert len(measurements) + len(rejected) == n == info["rows_read"]
    assert sorted(measurements["source_row"].tolist() + rejected["source_row"].tolist()) == list(
        range(1, n + 1))
    assert rejected["reason"].notna().all() and rejected["detail"].notna().all()


def test_unmutated_log_is_kept_whole(fuzz_dir):
    path = fuzz_dir / "plain_log.csv"
    path.write_text(_mutate([]), encoding="utf-8")
    measurements, _, rejected, _ = ingest([path])
    assert len(measurements) == 10 and len(rejected) == 0
