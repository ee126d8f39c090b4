"""Streaming ``ingest``: logs read in batches, regrouped by heliostat on disk, written chunk by chunk.

The reference everywhere is the same stage with one batch holding the whole log
(``batch_rows`` larger than the log: no spill, one chunk, i.e. the whole-table path ingest always
had); a batch of a few rows must give the same artifacts row for row.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

import heliocal.pipeline.stages.ingest as ingest_mod
import heliocal.pipeline.io.spill as spill_mod
from heliocal.cli.main import app
from heliocal.pipeline.artifacts.store import read_artifact, read_provenance
from heliocal.pipeline.errors import InputError
from heliocal.pipeline.io.staged import IngestOptions
from heliocal.pipeline.io.source_checks import MedianVsThreshold
from heliocal.pipeline.stages.ingest import ingest, run_ingest
from heliocal.pipeline.artifacts.schemas import MEASUREMENTS
from heliocal.pipeline.io.spill import SortedSpill

#: end-to-end runs of the stages: `make test` runs them, `make test-fast` skips them
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC_LOG = ROOT / "sample_data" / "synthetic" / "calibration_log.csv"
SYNTHETIC_PAINT = ROOT / "sample_data" / "synthetic" / "paint"
GOOD = Path(__file__).resolve().parent / "data" / "good"
BAD = Path(__file__).resolve().parent / "data" / "bad"
ARTIFACTS = ("measurements.parquet", "heliostats.parquet", "rejected.parquet")
WHOLE = 10**9  # one batch holds every log here: the whole-table path


def _csv_rows(path: Path) -> list[dict]:
    """The data rows of a CSV log, read with the standard library (independent of heliocal)."""
    with open(path, newline="", encoding="utf-8-sig") as fh:
        return [r for r in csv.DictReader(fh, skipinitialspace=True) if any(v for v in r.values())]


def _tables(workdir: Path) -> dict[str, pd.DataFrame]:
    return {name: pq.read_table(workdir / name).to_pandas() for name in ARTIFACTS}


def _assert_same(a: dict, b: dict) -> None:
    for name in ARTIFACTS:
        pd.testing.assert_frame_equal(a[name], b[name], check_exact=True, obj=name)


@pytest.fixture
def validate_calls(monkeypatch):
    """Row counts of every frame validate_rows judged (one per chunk)."""
    calls: list[int] = []
    real = ingest_mod.validate_rows

    def counting(st, opts, checks):
        calls.append(len(st.frame))
        return real(st, opts, checks)

    monkeypatch.setattr(ingest_mod, "validate_rows", counting)
    return calls


def _synthetic_case():
    return [SYNTHETIC_LOG], IngestOptions(properties=SYNTHETIC_PAINT)


# ------------------------------------------------------------------------------------------------
# tiny batches give the whole-table artifacts
# ------------------------------------------------------------------------------------------------
def test_synthetic_log_in_batches_of_7_rows_matches_one_batch(tmp_path, validate_calls):
    sources, opts = _synthetic_case()
    info_whole = run_ingest(sources, tmp_path / "whole", opts, batch_rows=WHOLE)
    assert validate_calls == [590]  # the whole log in one frame (590 data rows, counted below)
    validate_calls.clear()
    info_small = run_ingest(sources, tmp_path / "small", opts, batch_rows=7)
    # several chunks, each holding whole heliostats (the log has 4, of 141 to 160 rows each)
    assert len(validate_calls) >= 3 and sum(validate_calls) == 590
    whole, small = _tables(tmp_path / "whole"), _tables(tmp_path / "small")
    _assert_same(whole, small)
    drop = ("workdir", "artifacts")
    assert ({k: v for k, v in info_whole.items() if k not in drop}
            == {k: v for k, v in info_small.items() if k not in drop})

    # real values, from the CSV read with the csv module: every row kept or rejected once
    rows = _csv_rows(SYNTHETIC_LOG)
    assert len(rows) == 590 == info_small["rows_read"]
    m, r = small["measurements.parquet"], small["rejected.parquet"]
    assert len(m) + len(r) == len(rows)
    assert set(m["heliostat_id"]) | set(r["heliostat_id"].dropna()) == {x["heliostat_id"] for x in rows}
    # measurements sorted by (heliostat_id, timestamp, measurement_id), as MEASUREMENTS.sort_by says
    order = m.sort_values(list(MEASUREMENTS.sort_by), kind="mergesort").index
    assert list(order) == list(range(len(m)))
    # each kept row's values are its CSV row's: motor steps and logged sun elevation
    by_id = {(x["heliostat_id"], x["sample_id"]): x for x in rows}
    for _, row in m.iloc[::37].iterrows():
        src = by_id[(row["heliostat_id"], row["measurement_id"])]
        assert row["axis_1_steps"] == float(src["axis_1_motor_position"])
        assert row["sun_elevation_deg"] == pytest.approx(float(src["sun_elevation"]), abs=1e-12)
        assert row["env_temperature"] == float(src["temperature"])
    # rejected rows in source order, as before
    assert list(r["source_row"]) == sorted(r["source_row"])


def test_juelich_log_in_batches_of_101_rows_matches_one_batch(juelich_dir, tmp_path):
    log = juelich_dir / "csv" / "juelich_calibration_log.csv"
    run_ingest([log], tmp_path / "whole", batch_rows=WHOLE)
    run_ingest([log], tmp_path / "small", batch_rows=101)  # 56 runs, 100+ chunks
    whole, small = _tables(tmp_path / "whole"), _tables(tmp_path / "small")
    _assert_same(whole, small)
    n = len(_csv_rows(log))  # 5,618 rows in the copy of ../shared/data
    assert len(small["measurements.parquet"]) + len(small["rejected.parquet"]) == n
    # heliostats without properties take the median position of their rows: needs all of them
    assert (small["heliostats.parquet"]["properties_source"] == "default-juelich").all()


@pytest.mark.parametrize("sources, kwargs", [
    # duplicates: the first row of an id is kept, the later ones are rejected naming it
    ([BAD / "duplicated_measurement_id.csv"], {}),
    # one timestamp without zone among zoned ones: rejected row, not a refused source
    ([BAD / "timestamp_one_without_zone.csv"], {}),
    ([BAD / "missing_values.csv"], {}),
    ([GOOD / "enu_log.csv"], {"properties": GOOD / "enu_properties.toml"}),
    # two sources: a PAINT folder and a log of the same heliostats (every log row is a duplicate
    # of a PAINT measurement or a new one; the first source wins)
    ([SYNTHETIC_PAINT, SYNTHETIC_LOG], {}),
    ([GOOD / "juelich_log_small.csv", GOOD / "juelich_log_small.csv"], {}),
], ids=["duplicates", "one-naive-timestamp", "missing-values", "enu", "paint+log", "same-log-twice"])
def test_bad_and_multi_source_inputs_in_batches_of_1_row_match_one_batch(sources, kwargs, tmp_path):
    opts = IngestOptions(**kwargs)
    run_ingest(sources, tmp_path / "whole", opts, batch_rows=WHOLE)
    run_ingest(sources, tmp_path / "small", opts, batch_rows=1)
    whole, small = _tables(tmp_path / "whole"), _tables(tmp_path / "small")
    _assert_same(whole, small)
    assert len(small["rejected.parquet"]) > 0 or sources[0].name == "enu_log.csv"


def test_duplicates_split_over_batches_are_found(tmp_path):
    # tests/data/bad/duplicated_measurement_id.csv repeats one id of heliostat AA39 (CASES.md);
    # with one row per batch the two rows are in different batches of the first pass
    run_ingest([BAD / "duplicated_measurement_id.csv"], tmp_path, batch_rows=1)
    rejected = pd.read_parquet(tmp_path / "rejected.parquet")
    dup = rejected[rejected["reason"] == "duplicate_measurement_id"]
    assert len(dup) == 1
    first = [i + 1 for i, r in enumerate(_csv_rows(BAD / "duplicated_measurement_id.csv"))
             if (r["heliostat_id"], r["sample_id"]) == (dup["heliostat_id"].iloc[0],
                                                        dup["measurement_id"].iloc[0])]
    assert len(first) == 2 and dup["source_row"].iloc[0] == first[1]
    assert dup["detail"].iloc[0].endswith(f"already seen in source row {first[0]}")


@pytest.mark.parametrize("name, message", [
    ("timestamps_without_zone.csv", "timestamps have no time zone (e.g. '2022-06-03T09:20:02')"),
    ("azimuth_north_clockwise.csv", "sun azimuths look north-clockwise"),
])
def test_whole_source_checks_judge_the_whole_log_across_batches(name, message, tmp_path):
    # both refusals judge every row of the source (all timestamps naive; median azimuth error):
    # with one row per batch they must still fire, with the message of the whole-table run
    with pytest.raises(InputError) as whole:
        run_ingest([BAD / name], tmp_path / "whole", batch_rows=WHOLE)
    with pytest.raises(InputError) as small:
        run_ingest([BAD / name], tmp_path / "small", batch_rows=1)
    assert str(small.value) == str(whole.value)
    assert message in str(small.value)
    assert not (tmp_path / "small").exists() or os.listdir(tmp_path / "small") == []


def test_parquet_log_in_batches_matches_one_batch(tmp_path):
    # the synthetic log as Parquet, with an integer column that is empty in its last row only
    # (pandas reads such a column as float in the whole file; a batch must not read it as int)
    df = pd.read_csv(SYNTHETIC_LOG)
    df["counter"] = pd.array(np.arange(len(df)), dtype="Int64")
    df.loc[len(df) - 1, "counter"] = pd.NA
    log = tmp_path / "calibration_log.parquet"
    df.to_parquet(log, index=False)
    opts = IngestOptions(properties=SYNTHETIC_PAINT, tower=SYNTHETIC_LOG.parent / "tower-measurements.json")
    run_ingest([log], tmp_path / "whole", opts, batch_rows=WHOLE)
    run_ingest([log], tmp_path / "small", opts, batch_rows=7)
    whole, small = _tables(tmp_path / "whole"), _tables(tmp_path / "small")
    _assert_same(whole, small)
    m = small["measurements.parquet"]
    assert m["env_counter"].dtype == np.float64  # float in the whole file, so in every batch
    raw = pd.read_parquet(tmp_path / "small" / "rejected.parquet")["raw"]
    assert len(m) + len(raw) == len(df)


# ------------------------------------------------------------------------------------------------
# atomicity: a failure mid-stream leaves the previous artifacts and no temporary file
# ------------------------------------------------------------------------------------------------
def test_failure_in_the_third_batch_keeps_previous_artifacts(tmp_path, monkeypatch):
    sources, opts = _synthetic_case()
    run_ingest(sources, tmp_path, opts, batch_rows=7)
    previous = {name: (tmp_path / name).read_bytes() for name in ARTIFACTS}
    staged = []
    real = ingest_mod.stage_log_rows

    def failing(raw, ctx):  # the WGS84 -> ENU staging of the third chunk fails
        staged.append(len(raw))
        if len(staged) == 3:
            raise OSError(28, "No space left on device")
        return real(raw, ctx)

    monkeypatch.setattr(ingest_mod, "stage_log_rows", failing)
    with pytest.raises(OSError):
        run_ingest(sources, tmp_path, IngestOptions(properties=SYNTHETIC_PAINT,
                                                    max_spot_distance_m=5.0), batch_rows=7)
    assert len(staged) == 3  # it failed while streaming, after two chunks were written
    # no staging folder, no spill folder: the previous run's files and its manifest
    assert sorted(os.listdir(tmp_path)) == sorted([*ARTIFACTS, "ingest.manifest.json"])
    assert {name: (tmp_path / name).read_bytes() for name in ARTIFACTS} == previous
    assert read_provenance(tmp_path / "measurements.parquet")["options"]["max_spot_distance_m"] == 25.0


def test_no_kept_row_writes_nothing(tmp_path):
    # every row of all_rows_rejected.csv fails a check (tests/data/bad/CASES.md)
    with pytest.raises(InputError, match="could be kept"):
        run_ingest([BAD / "all_rows_rejected.csv"], tmp_path, batch_rows=1)
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------------------------
# layout: row groups hold sorted heliostat ranges
# ------------------------------------------------------------------------------------------------
def test_measurement_row_groups_hold_sorted_heliostat_ranges(tmp_path, monkeypatch):
    monkeypatch.setattr(ingest_mod, "MEASUREMENTS_ROW_GROUP_ROWS", 64)
    sources, opts = _synthetic_case()
    run_ingest(sources, tmp_path, opts, batch_rows=50)
    meta = pq.ParquetFile(tmp_path / "measurements.parquet").metadata
    col = meta.schema.names.index("heliostat_id")
    ranges = []
    for i in range(meta.num_row_groups):
        stats = meta.row_group(i).column(col).statistics
        assert stats is not None and stats.has_min_max
        ranges.append((stats.min, stats.max))
    assert meta.num_row_groups >= 590 // 64  # kept rows (most of 590) in groups of at most 64
    assert all(lo <= hi for lo, hi in ranges)
    assert all(a[1] <= b[0] for a, b in zip(ranges, ranges[1:]))  # sorted, never interleaved
    full = read_artifact(tmp_path, MEASUREMENTS)
    for hid in full["heliostat_id"].unique():
        touched = [i for i, (lo, hi) in enumerate(ranges) if lo <= hid <= hi]
        n = int((full["heliostat_id"] == hid).sum())
        assert len(touched) <= -(-n // 64) + 1  # its own rows' groups plus at most one shared
        part = read_artifact(tmp_path, MEASUREMENTS, heliostats=[hid])
        pd.testing.assert_frame_equal(part.reset_index(drop=True),
                                      full[full["heliostat_id"] == hid].reset_index(drop=True))


def test_chunks_stay_near_the_batch_size(tmp_path, validate_calls):
    # the memory bound: a validated chunk holds about one batch (plus one heliostat), not the log
    sources, opts = _synthetic_case()
    run_ingest(sources, tmp_path, opts, batch_rows=150)
    largest_heliostat = max(pd.Series([r["heliostat_id"] for r in _csv_rows(SYNTHETIC_LOG)])
                            .value_counts())
    assert len(validate_calls) >= 2
    assert max(validate_calls) < 150 + largest_heliostat + 1024  # + one read slice (spill.py)


def test_cli_batch_rows(tmp_path):
    args = ["ingest", str(SYNTHETIC_LOG), "--properties", str(SYNTHETIC_PAINT), "--quiet"]
    runner = CliRunner()
    assert runner.invoke(app, [*args, "--workdir", str(tmp_path / "a"), "--batch-rows", "7"]).exit_code == 0
    assert runner.invoke(app, [*args, "--workdir", str(tmp_path / "b")]).exit_code == 0
    _assert_same(_tables(tmp_path / "a"), _tables(tmp_path / "b"))
    result = runner.invoke(app, [*args, "--workdir", str(tmp_path / "c"), "--batch-rows", "0"])
    assert result.exit_code != 0 and not (tmp_path / "c" / "measurements.parquet").exists()


def test_in_memory_ingest_keeps_source_order():
    # ingest() (the library call) returns rows in source order, as it always did
    sources, opts = _synthetic_case()
    measurements, _, rejected, info = ingest(sources, opts)
    kept_rows = list(measurements["source_row"])
    assert kept_rows == sorted(kept_rows) and len(kept_rows) == info["kept"]
    assert sorted(kept_rows + list(rejected["source_row"])) == list(range(1, 591))


# ------------------------------------------------------------------------------------------------
# the building blocks
# ------------------------------------------------------------------------------------------------
def test_sorted_spill_merges_runs_into_whole_key_ranges(tmp_path, monkeypatch):
    monkeypatch.setattr(spill_mod, "_MIN_READ_ROWS", 1)  # slices of a few rows: keys span slices
    rng = np.random.default_rng(0)
    keys = rng.choice([f"H{i:02d}" for i in range(12)], size=400, p=None)
    keys[:120] = "H05"  # one key far larger than a slice and a chunk
    table = pa.table({"k": keys, "seq": np.arange(400)})
    spill = SortedSpill(tmp_path, "t", "k", "seq")
    for start in range(0, 400, 23):  # 18 runs, in input order
        spill.add(table.slice(start, 23))
    chunks = list(spill.merged(10))
    merged = pa.concat_tables(chunks)
    expected = table.sort_by([("k", "ascending"), ("seq", "ascending")])
    assert merged.equals(expected)
    seen = [set(c["k"].to_pylist()) for c in chunks]
    assert all(a.isdisjoint(b) for i, a in enumerate(seen) for b in seen[i + 1:])  # no key split
    assert len(chunks) > 3


@pytest.mark.parametrize("values", [
    [1.0, 2.0, 3.0, 4.0],  # even count straddling the threshold 2.5: the mean of 2 and 3
    [1.0, 5.0],
    [2.5, 2.5, 7.0, 1.0],
    [0.1] * 5 + [9.0] * 5,
    list(np.random.default_rng(1).exponential(2.5, 101)),
    list(np.random.default_rng(2).exponential(2.5, 100)),
    [1.0, np.nan, 3.0],
])
def test_median_against_a_threshold_streamed(values):
    tracker = MedianVsThreshold(2.5)
    for part in np.array_split(np.asarray(values, float), 3):
        tracker.add(part)
    truth = np.median(values)
    got = tracker.median()
    if np.isnan(truth):
        assert np.isnan(got)
    else:
        assert (got <= 2.5) == (truth <= 2.5) and (got < 2.5) == (truth < 2.5)
        lo, hi = sorted(values)[(len(values) - 1) // 2], sorted(values)[len(values) // 2]
        if lo < 2.5 < hi:
            assert got == truth  # straddling: the exact median
