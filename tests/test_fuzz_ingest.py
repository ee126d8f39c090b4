"""Fuzz the CSV ingest: random damage to a valid log never crashes it and never loses a row.

Starting from tests/data/good/juelich_log_small.csv (10 rows), hypothesis deletes, duplicates
and swaps cells, writes garbage strings, NaN, inf and huge numbers, swaps header names and cuts
lines short. For every input, :func:`heliocal.pipeline.stages.ingest.ingest` either raises a
:class:`HeliocalError` with a one-line message naming the file, or keeps and rejects rows that
add up to the number of data rows of the file (counted here with Python's csv module: non-blank
records after the header).
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from heliocal.pipeline.errors import HeliocalError
from heliocal.pipeline.stages.ingest import ingest

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


def _mutate(ops, rows=None) -> str:
    grid = [list(r) for r in (ROWS if rows is None else rows)]
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
            i, j = min(op[1], len(grid[0]) - 1), min(op[2], len(grid[0]) - 1)
            grid[0][i], grid[0][j] = grid[0][j], grid[0][i]
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


def _rows_that_must_be_kept(text: str) -> list[int] | None:
    """Source rows (1-based data records) that ingest must keep, worked out from the text alone
    (Python's csv module, as ingest reads it): every record still equal to a row of the valid log
    whose (heliostat_id, sample_id) no earlier record carries (damage to one row never costs
    another; a duplicate id keeps its first row). None where the file as a whole may be refused or
    mislabelled (docs/input_formats.md): unparsable CSV, a NUL byte, a changed header, or a record
    with more non-empty cells than the header."""
    if "\0" in text:
        return None
    try:
        records = [[c.strip() for c in r] for r in csv.reader(
            io.StringIO(text, newline=""), skipinitialspace=True, strict=True)
            if r and not (len(r) == 1 and not r[0].strip())]
    except csv.Error:
        return None
    valid = [[c.strip() for c in r] for r in ROWS]
    if not records or records[0] != valid[0]:
        return None
    width = len(valid[0])
    if any(any(r[width:]) for r in records[1:]):
        return None
    hid, sid = valid[0].index("heliostat_id"), valid[0].index("sample_id")
    keep, seen = [], set()
    for i, record in enumerate(records[1:], start=1):
        key = tuple(record[j] if j < len(record) else "" for j in (hid, sid))
        if record in valid[1:] and key not in seen:
            keep.append(i)
        seen.add(key)
    return keep


def test_fuzzed_log_rows_are_all_accounted_for(fuzz_dir):
    """50 damaged logs (derandomized): each is refused with one line naming the file or has every
    row kept or rejected, and every log whose damage leaves it readable is ingested with its
    undamaged rows kept (_rows_that_must_be_kept). At least a quarter of the logs must be such:
    two of the eight kinds of damage (a swapped header, a duplicated cell that makes a row too
    long) can spoil the whole file, and a log gets 1-6 of them, so about (3/4)^3.5 = 37 % of the
    logs get neither (36 of the 50 do)."""
    outcomes = {"error": 0, "rows": 0, "readable": 0}

    @settings(max_examples=50, deadline=None, derandomize=True, database=None)
    @given(ops=st.lists(_op, min_size=1, max_size=6))
    def one_log(ops):
        text = _mutate(ops)
        path = fuzz_dir / "fuzzed_log.csv"
        path.write_text(text, encoding="utf-8")
        must_keep = _rows_that_must_be_kept(text)
        try:
            measurements, heliostats, rejected, info = ingest([path])
        except HeliocalError as exc:
            message = str(exc)
            assert "\n" not in message and message.startswith(str(path)), message
            assert must_keep is None, f"a readable log was refused: {message}"
            outcomes["error"] += 1
            return
        n = _data_rows(text)
        assert n is not None, "ingest read a file the csv module cannot parse"
        assert len(measurements) + len(rejected) == n == info["rows_read"]
        rows = measurements["source_row"].tolist() + rejected["source_row"].tolist()
        assert sorted(rows) == list(range(1, n + 1))
        assert rejected["reason"].notna().all() and rejected["detail"].notna().all()
        if must_keep is not None:
            lost = sorted(set(must_keep) - set(measurements["source_row"]))
            assert not lost, rejected[rejected["source_row"].isin(lost)].to_dict("records")
            outcomes["readable"] += bool(must_keep)
        outcomes["rows"] += 1

    one_log()
    assert outcomes["error"] + outcomes["rows"] == 50, outcomes
    assert outcomes["readable"] >= 50 // 4, outcomes


def test_unmutated_log_is_kept_whole(fuzz_dir):
    path = fuzz_dir / "plain_log.csv"
    path.write_text(_mutate([]), encoding="utf-8")
    measurements, _, rejected, _ = ingest([path])
    assert len(measurements) == 10 and len(rejected) == 0


# ------------------------------------------------------------------------------------------------
# the long fuzz (marked slow; CI runs it): thousands of CSV logs and PAINT folders
# ------------------------------------------------------------------------------------------------
#: Examples per long fuzz test: 1,000 cases in all by default (about 20 s per test on a 2-core
#: machine; 2,000 took 87 s of a suite that had reached 10 minutes); the cases are derandomized,
#: so CI runs the same ones every time; HELIOCAL_FUZZ_EXAMPLES=5000 for a long run before a
#: release (10,000 cases, about 7 minutes).
FUZZ_EXAMPLES = int(os.environ.get("HELIOCAL_FUZZ_EXAMPLES", "500"))

HOSTILE_IDS = ["../../../tmp/x/pwned", "<img src=x onerror=alert(1)>", ".hidden", "-rf", "a/b",
               "a\\b", "H" * 65, "H" * 64, "Jülich7", "AB 27", "..", ".", "...", "__init__",
               "CON", "x.pt", "\u202eRTL", "ＡＢ１", "A\tB", "0", "_", "a-b.c_d"]
_EXTREME = st.sampled_from(["1e308", "-1e308", "1e-320", "9" * 400, "-0.0", "0x10", "1_000",
                            "NaN", "-inf", "+1", "1e", ".5", "5.", "١٢٣"])
_ENCODINGS = ("utf-8", "utf-8-sig", "latin-1", "cp1252", "utf-16", "utf-32", "ascii-replace")

_long_op = st.one_of(
    _op,
    st.tuples(st.just("id"), _row, st.sampled_from(HOSTILE_IDS)),
    st.tuples(st.just("extreme"), _row, _col, _EXTREME),
    st.tuples(st.just("drop_column"), _col),
    st.tuples(st.just("add_column"), st.one_of(st.sampled_from(
        ["temperature", "env_x", "heliostat_id ", "", "__heliocal_source_row", "wind speed"]),
        _garbage), _garbage),
    st.tuples(st.just("duplicate_id"), _row, _row),
)


def _mutate_long(ops) -> tuple[list[list[str]], list]:
    """Column-, id- and number-level damage; the short fuzz's cell operations are returned to
    be applied afterwards (by :func:`_mutate`)."""
    grid = [list(r) for r in ROWS]
    plain = []
    for op in ops:
        kind = op[0]
        if kind == "id":
            grid[op[1]][0] = op[2]
        elif kind == "extreme":
            r = grid[op[1]]
            r[min(op[2], len(r) - 1)] = op[3]
        elif kind == "drop_column":
            i = min(op[1], len(grid[0]) - 1)
            if len(grid[0]) > 1:
                for r in grid:
                    if i < len(r):
                        del r[i]
        elif kind == "add_column":
            grid[0].append(op[1])
            for r in grid[1:]:
                r.append(op[2])
        elif kind == "duplicate_id":
            s = grid[0].index("sample_id") if "sample_id" in grid[0] else None
            if s is not None and s < len(grid[op[1]]) and s < len(grid[op[2]]):
                grid[op[2]][s] = grid[op[1]][s]
        else:
            plain.append(op)
    return grid, plain


def _encode(text: str, encoding: str) -> bytes:
    if encoding == "ascii-replace":
        return text.encode("ascii", "replace")
    return text.encode(encoding, "replace") if encoding != "utf-8-sig" else text.encode(encoding)


def _check_outcome(path: Path, run, n_rows_if_ok, heliocal_error_prefix: str):
    """Run ``run()``: our one-line error naming the source, or every row kept or rejected."""
    from heliocal.pipeline.artifacts.schemas import HELIOSTAT_ID_RE, REJECTION_REASONS

    try:
        measurements, heliostats, rejected, info = run()
    except HeliocalError as exc:
        message = str(exc)
        assert "\n" not in message and message.startswith(heliocal_error_prefix), message
        return "error"
    n = n_rows_if_ok()
    assert n is not None, "ingest read a source the reference parser cannot"
    assert len(measurements) + len(rejected) == n == info["rows_read"]
    assert rejected["reason"].isin(list(REJECTION_REASONS)).all()
    assert rejected["detail"].map(lambda d: isinstance(d, str) and d != "").all()
    assert all(HELIOSTAT_ID_RE.fullmatch(h) for h in measurements["heliostat_id"])
    assert set(heliostats["heliostat_id"]) == set(measurements["heliostat_id"])
    return "rows"


_OUTCOMES: dict[str, dict[str, int]] = {"csv": {}, "paint": {}}


@pytest.mark.slow
@settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(ops=st.lists(_long_op, min_size=1, max_size=8), encoding=st.sampled_from(_ENCODINGS))
def test_long_fuzz_of_csv_logs(fuzz_dir, ops, encoding):
    grid, plain = _mutate_long(ops)
    text = _mutate(plain, grid)  # the cell-level damage of the short fuzz on top
    data = _encode(text, encoding)
    path = fuzz_dir / "long_fuzzed_log.csv"
    path.write_bytes(data)

    def rows_if_ok():
        return _data_rows(data.decode("utf-8-sig"))

    outcome = _check_outcome(path, lambda: ingest([path]), rows_if_ok, str(path))
    _OUTCOMES["csv"][outcome] = _OUTCOMES["csv"].get(outcome, 0) + 1


# PAINT: one heliostat folder copied from tests/data/good/paint_small and a second one made from
# it, each file a JSON document that hypothesis damages
PAINT_SMALL = GOOD / "paint_small"
#: Heliostat folder names: the hostile ids a folder can be named (no "/", ".", "..").
PAINT_FOLDER_NAMES = [h for h in HOSTILE_IDS if "/" not in h and h not in (".", "..")]
_json_scalar = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30),
                         st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                         st.sampled_from(["45501", "1e400", "NaN", "", "UTIS", "linear"]))
_json_value = st.recursive(_json_scalar, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=8)
_CALIB_KEYS = [("motor_position",), ("motor_position", "axis_1_motor_position"),
               ("motor_position", "axis_2_motor_position"), ("target_name",), ("sun_elevation",),
               ("sun_azimuth",), ("focal_spot",), ("focal_spot", "UTIS"), ("focal_spot", "HeliOS"),
               ("focal_spot", "UTIS", 0), ("focal_spot", "UTIS", 2)]
_PROP_KEYS = [("heliostat_position",), ("heliostat_position", 0), ("initial_orientation",),
              ("kinematics_properties",), ("kinematics_properties", "actuators"),
              ("kinematics_properties", "actuators", 0), ("kinematics_properties", "actuators", 1,
                                                           "increment"),
              ("kinematics_properties", "actuators", 0, "type_axis"),
              ("kinematics_properties", "actuators", 0, "clockwise_axis_movement"),
              ("kinematics_properties", "joint_translation_e_1")]
_file = st.sampled_from(["cal0", "cal1", "cal2", "cal3", "props", "stamps"])
_paint_op = st.one_of(
    st.tuples(st.just("set"), _file, st.sampled_from(_CALIB_KEYS + _PROP_KEYS), _json_value),
    st.tuples(st.just("delete"), _file, st.sampled_from(_CALIB_KEYS + _PROP_KEYS)),
    st.tuples(st.just("extra"), _file, st.text(max_size=10), _json_value),
    st.tuples(st.just("replace"), _file, _json_value),
    st.tuples(st.just("truncate"), _file, st.floats(0.0, 1.0)),
    st.tuples(st.just("encode"), _file, st.sampled_from(["utf-16", "latin-1", "utf-8-sig"])),
    st.tuples(st.just("rename_heliostat"), st.sampled_from(PAINT_FOLDER_NAMES)),
    st.tuples(st.just("rename_file"), st.sampled_from(["cal0", "cal1", "cal2", "cal3"]),
              st.sampled_from(["118671_calibration_properties.json", "x.json", "118671-cal.json",
                               "-calibration-properties.json", "..-calibration-properties.json",
                               "a b-calibration-properties.json", "notes.txt"])),
    st.tuples(st.just("stamp"), st.sampled_from(["BE36_118671", "BF41_118750", "x"]),
              st.one_of(_json_value, st.sampled_from(["2022-06-12T13:27:37", "yesterday",
                                                      "2022-02-30T10:00:00Z", "2022-06-12"]))),
)


def _paint_docs() -> dict:
    calib = PAINT_SMALL / "BE36" / "calibration"
    docs = {f"cal{i}": ("BE36" if i < 2 else "BF41", f.name, json.loads(f.read_text()))
            for i, f in enumerate(sorted(calib.glob("*.json")))}
    first = sorted(calib.glob("*.json"))[0]
    docs["cal3"] = ("BF41", "118750-calibration-properties.json", json.loads(first.read_text()))
    props = json.loads((PAINT_SMALL / "BE36" / "BE36-heliostat-properties.json").read_text())
    stamps = json.loads((PAINT_SMALL / "timestamps.json").read_text())
    stamps["BF41_118750"] = "2022-06-13T13:45:35Z"
    return {"docs": docs, "props": props, "stamps": stamps}


_PAINT_TEMPLATE = _paint_docs()


def _set_path(doc, keys, value, delete=False):
    for k in keys[:-1]:
        if isinstance(doc, dict) and k in doc:
            doc = doc[k]
        elif isinstance(doc, list) and isinstance(k, int) and k < len(doc):
            doc = doc[k]
        else:
            return
    last = keys[-1]
    if isinstance(doc, dict) and (last in doc or not delete):
        if delete:
            del doc[last]
        else:
            doc[last] = value
    elif isinstance(doc, list) and isinstance(last, int) and last < len(doc):
        if delete:
            del doc[last]
        else:
            doc[last] = value


def _write_paint(root: Path, ops) -> Path:
    import copy

    t = copy.deepcopy(_PAINT_TEMPLATE)
    content = {k: v[2] for k, v in t["docs"].items()}
    content["props"], content["stamps"] = t["props"], t["stamps"]
    names = {k: v[1] for k, v in t["docs"].items()}
    owners = {k: v[0] for k, v in t["docs"].items()}
    raw: dict[str, bytes] = {}
    hid_names = {"BE36": "BE36", "BF41": "BF41"}
    for op in ops:
        kind = op[0]
        if kind == "set":
            _set_path(content[op[1]], op[2], op[3])
        elif kind == "delete":
            _set_path(content[op[1]], op[2], None, delete=True)
        elif kind == "extra" and isinstance(content[op[1]], dict):
            content[op[1]][op[2]] = op[3]
        elif kind == "replace":
            content[op[1]] = op[2]
        elif kind in ("truncate", "encode"):
            text = json.dumps(content[op[1]], allow_nan=True)
            raw[op[1]] = (text[: int(len(text) * op[2])].encode() if kind == "truncate"
                          else text.encode(op[2], "replace"))
        elif kind == "rename_heliostat":
            hid_names["BF41"] = op[1]
        elif kind == "rename_file":
            names[op[1]] = op[2]
        elif kind == "stamp" and isinstance(content["stamps"], dict):
            content["stamps"][op[1]] = op[2]

    def data(key):
        return raw.get(key) or json.dumps(content[key], allow_nan=True).encode()

    paint = root / "paint"
    if paint.exists():
        shutil.rmtree(paint)
    for hid in ("BE36", "BF41"):
        folder = paint / hid_names[hid]
        (folder / "calibration").mkdir(parents=True, exist_ok=True)
        (folder / f"{hid_names[hid]}-heliostat-properties.json").write_bytes(data("props"))
    for key, owner in owners.items():
        (paint / hid_names[owner] / "calibration" / names[key]).write_bytes(data(key))
    (paint / "timestamps.json").write_bytes(data("stamps"))
    return paint


@pytest.mark.slow
@settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(ops=st.lists(_paint_op, min_size=1, max_size=6))
def test_long_fuzz_of_paint_folders(fuzz_dir, ops):
    paint = _write_paint(fuzz_dir, ops)

    def rows_if_ok():
        return len(list(paint.glob("*/calibration/*.json")))

    outcome = _check_outcome(paint, lambda: ingest([paint]), rows_if_ok, str(paint))
    _OUTCOMES["paint"][outcome] = _OUTCOMES["paint"].get(outcome, 0) + 1


@pytest.mark.slow
def test_long_fuzz_ran_every_case():
    """Runs after the two long fuzz tests (file order): each ran FUZZ_EXAMPLES cases, most of
    them ingested (not refused as a whole), and says so (pytest -s shows the counts)."""
    for kind, outcomes in _OUTCOMES.items():
        if not outcomes:
            pytest.skip("the long fuzz tests were not selected")
        total = sum(outcomes.values())
        print(f"fuzz {kind}: {total} cases, {outcomes.get('rows', 0)} ingested with every row "
              f"kept or rejected, {outcomes.get('error', 0)} refused with a one-line error")
        assert total >= FUZZ_EXAMPLES
        assert outcomes.get("rows", 0) >= total // 4


# ------------------------------------------------------------------------------------------------
# what the long fuzz found (each crashed with a traceback before it was fixed)
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ops,outcome", [
    ([("replace", "stamps", None)], ("error", "the timestamps map is not a JSON object")),
    ([("replace", "stamps", [1, 2])], ("error", "the timestamps map is not a JSON object")),
    ([("set", "props", ("initial_orientation",), [])],
     ("error", "malformed heliostat properties (initial_orientation has 0 components")),
    ([("set", "props", ("kinematics_properties",), [1])],
     ("error", "malformed heliostat properties")),
    ([("set", "cal0", ("motor_position",), [45501, 53811])],
     ("rows", {"malformed_file": "motor_position is a list, not an object"})),
    ([("set", "cal1", ("focal_spot",), "UTIS")],
     ("rows", {"malformed_file": "focal_spot is a str, not an object"})),
])
def test_fuzz_findings(fuzz_dir, ops, outcome):
    paint = _write_paint(fuzz_dir, ops)
    if outcome[0] == "error":
        with pytest.raises(HeliocalError, match=outcome[1].replace("(", r"\(")):
            ingest([paint])
        return
    _, _, rejected, _ = ingest([paint])
    assert dict(zip(rejected["reason"], rejected["detail"])) == outcome[1]


def test_paint_folder_without_any_properties_file_rejects_its_rows(fuzz_dir):
    paint = _write_paint(fuzz_dir, [])
    for f in paint.glob("*/*-heliostat-properties.json"):
        f.unlink()
    measurements, _, rejected, info = ingest([paint])
    assert measurements.empty and info["rows_read"] == 4
    assert list(rejected["reason"]) == ["unknown_heliostat"] * 4
