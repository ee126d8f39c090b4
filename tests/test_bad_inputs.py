"""The bad-input corpus (tests/data/bad/, written once by make_corpus.py): every case has one
expected outcome, listed in CASES below and in tests/data/bad/CASES.md.

* ``error``: exit code 1, exactly one stderr line ``Error: <file>: <what> ...; <fix>``, no
  traceback, and no artifact written.
* ``rows``: exit code 0; the damaged rows (by 1-based data row) are in rejected.parquet with the
  expected reason and a detail, every other row is in measurements.parquet (never a silent drop).

The expected rows and messages were set by reading each case's damage in make_corpus.py: e.g.
``wrong_types.csv`` puts "abc" into data row 2's axis_1_motor_position and "high" into data row
5's sun_elevation, so rows 2 and 5 must be rejected as unparsable_number and 8 of 10 kept.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from heliocal.cli.main import app
from heliocal.pipeline.artifacts.schemas import REJECTION_REASONS

BAD = Path(__file__).resolve().parent / "data" / "bad"
GOOD = Path(__file__).resolve().parent / "data" / "good"
SMALL_LOG_ROWS = 10  # tests/data/good/juelich_log_small.csv: 5 rows of AA31, 5 of AB27
ENU_PROPS = ["--properties", str(GOOD / "enu_properties.toml")]
PLANT = "50.913421122592574,6.387824755874856,87.0"  # tower-measurements.json reference point


def error(fragment: str, names: str | None = None):
    """Expected outcome: a one-line error containing ``fragment`` and naming file ``names``."""
    return ("error", fragment, names)


def rows(n_rows: int, **rejected_rows: list[int]):
    """Expected outcome: ``n_rows`` data rows; ``reason=[data rows]`` rejected, the rest kept."""
    return ("rows", n_rows, rejected_rows)


# case id -> (source relative to tests/data/bad, extra CLI options, expected outcome)
CASES = {
    # --- the source cannot be read: one-line error, exit 1, nothing written -------------------
    "empty_file": ("empty.csv", [], error("the file is empty; give a calibration log with a header")),
    "whitespace_only": ("whitespace_only.csv", [], error("the file is empty")),
    "header_only": ("header_only.csv", [], error("header only, no data rows; give a log with at "
                                                 "least one measurement")),
    "binary_garbage": ("binary_garbage.csv", [], error("binary data, not a CSV text file; give a CSV")),
    "not_utf8": ("not_utf8.csv", [], error("not UTF-8 text (line 4, byte 1209); re-save the log "
                                           "as UTF-8 CSV")),
    "wrong_delimiter": ("semicolon_delimiter.csv", [], error("seems to use ';' as delimiter: save "
                                                             "it comma-separated")),
    "missing_required_column": ("missing_column_axis_1.csv", [], error(
        "missing required column 'axis_1_steps' (or axis_1_motor_position); add it to the log")),
    "duplicated_column": ("duplicated_column.csv", [], error(
        "duplicated column 'sun_elevation'; remove one of them")),
    "row_with_extra_field": ("extra_field_in_row.csv", [], error(
        "data row 3 (line 4) has 27 fields but the header has 26; remove the extra fields")),
    "unterminated_quote": ("unterminated_quote.csv", [], error(
        "malformed CSV at line 11 (unexpected end of data); close the quote")),
    "timestamps_without_zone": ("timestamps_without_zone.csv", [], error(
        "timestamps have no time zone (e.g. '2022-06-03T09:20:02'); add a UTC offset such as 'Z' "
        "or pass --timezone")),
    "azimuth_other_convention": ("azimuth_north_clockwise.csv", [], error(
        "sun azimuths look north-clockwise (0 = north)", )),
    "unknown_file_type": ("unknown_file_type.xlsx", [], error("unknown file type '.xlsx'; give a "
                                                              ".csv or .parquet")),
    "no_such_file": ("no_such_file.csv", [], error("no such file or folder; check the path")),
    "parquet_garbage": ("parquet_garbage.parquet", [], error("not a readable Parquet file")),
    "timestamps_day_month": ("timestamps_day_month.csv", [], error(
        "timestamps such as '03.06.2022 09:20:02Z' write day and month as numbers, and heliocal "
        "cannot tell which is which; pass --date-format")),
    "every_row_rejected": ("all_rows_rejected.csv", [], error(
        "could be kept (sun_below_horizon: 10); see the reasons and fix the source")),
    "enu_log_without_properties": ("enu_log.csv", [], error(
        "an ENU log needs the heliostat properties: pass --properties")),
    "enu_log_without_sun_or_timestamp": ("enu_log_without_sun.csv", ENU_PROPS, error(
        "missing required columns sun_azimuth/sun_elevation and no timestamp")),
    "enu_log_sun_missing_no_location": (str(GOOD / "enu_log_timestamps.csv"), ENU_PROPS, error(
        "sun angles are missing and no plant location to compute them; pass --location")),
    "properties_file_missing": ("enu_log.csv", ["--properties", str(BAD / "no_such_properties.toml")],
                                error("properties file not found; check the --properties path",
                                      "no_such_properties.toml")),
    "properties_file_malformed": ("enu_log.csv", ["--properties", str(BAD / "properties_malformed.toml")],
                                  error("malformed TOML (Invalid value (at line 2, column 17)); fix",
                                        "properties_malformed.toml")),
    "properties_lack_a_key": ("enu_log.csv", ["--properties", str(BAD / "properties_lacks_max_steps.toml")],
                              error("heliostat 'H01' lacks ['axis_1_max_steps']; add them",
                                    "properties_lacks_max_steps.toml")),
    "tower_file_malformed": ("wrong_types.csv", ["--tower", str(BAD / "tower_malformed.json")],
                             error("the tower file is not valid JSON (line 38", "tower_malformed.json")),
    "paint_properties_malformed": ("paint_bad_properties", [], error(
        "malformed heliostat properties ('kinematics_properties'); restore the original PAINT file",
        "BE36-heliostat-properties.json")),
    # --- row-level damage: those rows quarantined with a reason, all others kept ---------------
    "wrong_types": ("wrong_types.csv", [], rows(10, unparsable_number=[2, 5])),
    "nan_and_inf": ("nan_inf.csv", [], rows(10, unparsable_number=[1, 3, 4])),
    "huge_number": ("huge_number.csv", [], rows(10, unparsable_number=[7])),
    "negative_steps": ("negative_steps.csv", [], rows(10, steps_out_of_range=[2])),
    "huge_steps": ("huge_steps.csv", [], rows(10, steps_out_of_range=[6])),
    "timestamp_unparsable": ("timestamp_unparsable.csv", [], rows(10, unparsable_timestamp=[3, 4])),
    "timestamp_one_without_zone": ("timestamp_one_without_zone.csv", [],
                                   rows(10, unparsable_timestamp=[8])),
    "timestamps_implausible": ("timestamps_implausible.csv", [],
                               rows(10, implausible_timestamp=[1, 3, 5])),
    "timestamp_day_month": ("timestamp_day_month.csv", [], rows(10, ambiguous_timestamp=[4])),
    "timestamps_day_month_with_format": ("timestamps_day_month.csv",
                                         ["--date-format", "%d.%m.%Y %H:%M:%S%z"], rows(10)),
    "sun_below_horizon": ("sun_below_horizon.csv", [], rows(10, sun_below_horizon=[2])),
    "sun_angle_out_of_range": ("sun_elevation_out_of_range.csv", [],
                               rows(10, sun_angle_out_of_range=[9])),
    "focal_spot_kilometres_away": ("focal_spot_kilometres_away.csv", [],
                                   rows(10, focal_spot_far_from_target=[5])),
    "focal_spot_latitude_invalid": ("focal_spot_latitude_invalid.csv", [],
                                    rows(10, unparsable_number=[4])),
    "duplicated_measurement_id": ("duplicated_measurement_id.csv", [],
                                  rows(10, duplicate_measurement_id=[4])),
    "unknown_heliostat": ("unknown_heliostat.csv", [], rows(10, unknown_heliostat=[6, 7])),
    "hostile_heliostat_ids": ("hostile_heliostat_ids.csv", [],
                              rows(10, invalid_heliostat_id=[2, 3, 4, 5, 8, 9, 10])),
    "unknown_heliostat_enu": ("enu_unknown_heliostat.csv", ENU_PROPS, rows(6, unknown_heliostat=[6])),
    "unknown_target": ("unknown_target.csv", [], rows(10, unknown_target=[7])),
    "quoted_comma_in_target": ("quoted_comma_in_target.csv", [], rows(10, unknown_target=[10])),
    "missing_values": ("missing_values.csv", [], rows(10, missing_value=[1, 2, 3])),
    "truncated_last_line": ("truncated_last_line.csv", [], rows(10, missing_value=[10])),
    "paint_mixed_valid_and_broken_json": ("paint_mixed", [], rows(
        8, malformed_file=["200001", "200002", "200003", "notes"], unknown_heliostat=["300001"])),
    # --- unusual but valid: everything kept -----------------------------------------------------
    "heliostat_with_one_measurement": ("heliostat_with_one_measurement.csv", [], rows(11)),
    "crlf_and_bom": ("crlf_bom.csv", [], rows(10)),
    "blank_lines": ("blank_lines.csv", [], rows(10)),
    "trailing_commas": ("trailing_commas.csv", [], rows(10)),
    "sun_angles_empty_filled_by_spa": ("sun_angles_empty.csv", [], rows(10)),
}


def _invoke(runner, case_id, tmp_path):
    source, extra, expected = CASES[case_id]
    workdir = tmp_path / "work"
    args = ["ingest", str(BAD / source), *extra, "--workdir", str(workdir), "--quiet"]
    return runner.invoke(app, args), workdir, expected, source


def test_corpus_is_large_enough_and_covers_every_reason():
    outcomes = [c[2][0] for c in CASES.values()]
    assert outcomes.count("error") >= 10 and outcomes.count("rows") >= 15
    covered = {r for c in CASES.values() if c[2][0] == "rows" for r in c[2][2]}
    # a row of an `ingest --append` that the work directory already holds: tests/test_incremental
    append_only = {"duplicate_of_ingested_row"}
    assert covered | append_only == set(REJECTION_REASONS), set(REJECTION_REASONS) - covered


def test_cases_table_lists_every_case():
    """tests/data/bad/CASES.md documents the same cases (one table row per case id)."""
    text = (BAD / "CASES.md").read_text(encoding="utf-8")
    missing = [cid for cid in CASES if f"| `{cid}` |" not in text]
    assert not missing


@pytest.mark.parametrize("case_id", list(CASES))
def test_bad_input(case_id, runner, tmp_path):
    result, workdir, expected, source = _invoke(runner, case_id, tmp_path)
    # whatever the outcome: no exception other than a clean exit escaped the command
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output and "Traceback" not in result.stderr
    if expected[0] == "error":
        _, fragment, names = expected
        assert result.exit_code == 1
        lines = result.stderr.splitlines()
        assert len(lines) == 1, result.stderr
        assert lines[0].startswith("Error: ")
        assert (names or Path(source).name) in lines[0]
        assert fragment in lines[0], lines[0]
        written = list(workdir.glob("*.parquet")) if workdir.exists() else []
        assert written == []
        return
    _, n_rows, rejected_rows = expected
    assert result.exit_code == 0, result.stderr
    kept = pd.read_parquet(workdir / "measurements.parquet")
    rejected = pd.read_parquet(workdir / "rejected.parquet")
    assert len(kept) + len(rejected) == n_rows
    got = {}
    for reason, grp in rejected.groupby("reason"):
        # PAINT rows are files: name them by measurement id; log rows by their data row
        ids = grp["source_row"] if source.endswith(".csv") else grp["source_file"].map(
            lambda f: Path(f).name.split("-")[0].removesuffix(".json"))
        got[reason] = sorted(ids.tolist())
    assert got == {k: sorted(v) for k, v in rejected_rows.items()}
    assert rejected["detail"].str.len().gt(0).all() and rejected["raw"].str.len().gt(0).all()
    if source.endswith(".csv"):
        assert sorted(kept["source_row"].tolist() + rejected["source_row"].tolist()) == list(
            range(1, n_rows + 1))


def test_one_measurement_heliostat_is_kept_with_count_1(runner, tmp_path):
    """Ingest keeps a heliostat with one measurement; later stages decide what it is good for."""
    result, workdir, _, _ = _invoke(runner, "heliostat_with_one_measurement", tmp_path)
    assert result.exit_code == 0
    helio = pd.read_parquet(workdir / "heliostats.parquet").set_index("heliostat_id")
    assert helio.loc["AC32", "n_measurements"] == 1
    assert helio.loc["AA31", "n_measurements"] == 5 and helio.loc["AB27", "n_measurements"] == 5


def test_empty_sun_angles_are_computed_with_spa(runner, tmp_path):
    result, workdir, _, _ = _invoke(runner, "sun_angles_empty_filled_by_spa", tmp_path)
    m = pd.read_parquet(workdir / "measurements.parquet").set_index("source_row")
    assert m.loc[1, "sun_source"] == "spa" and (m.drop(index=1)["sun_source"] == "log").all()
    # row 1 of the Jülich log (AA31 118385, 2022-06-03T09:20:02Z) logs az 54.44266 deg, el
    # 51.56795 deg; SPA for the plant reference point reproduces them within 0.01 deg.
    assert m.loc[1, "sun_azimuth_deg"] == pytest.approx(54.442661206716764, abs=0.01)
    assert m.loc[1, "sun_elevation_deg"] == pytest.approx(51.56794833385448, abs=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("source", ["binary_garbage.csv", "not_utf8.csv"])
def test_installed_command_prints_no_traceback(source, tmp_path):
    """The real console script (not CliRunner): one stderr line, exit 1, no traceback."""
    exe = Path(sys.executable).with_name("heliocal")
    proc = subprocess.run([str(exe), "ingest", str(BAD / source), "--workdir", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"Error: {BAD / source}: ")
    assert "Traceback" not in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_json_summary_accounts_for_every_row(runner, tmp_path):
    result = runner.invoke(app, ["ingest", str(BAD / "nan_inf.csv"), "--workdir", str(tmp_path),
                                 "--json", "--quiet"])
    summary = json.loads(result.stdout)
    assert summary["rows_read"] == 10 and summary["kept"] == 7
    assert summary["rejected_by_reason"] == {"unparsable_number": 3}
