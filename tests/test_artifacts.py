"""Artifacts (pipeline/artifacts.py): schema checks, atomic writes, provenance, freshness."""

from __future__ import annotations

import json
import os

import pandas as pd
import pyarrow.parquet as pq
import pytest

from heliocal.pipeline.artifacts.store import (SCHEMA_VERSION, check_fresh, kept_reads,
                                               read_artifact, read_provenance, write_artifact)
from heliocal.pipeline.artifacts import store
from heliocal.pipeline.artifacts.paths import atomic_path
from heliocal.pipeline.errors import SchemaError, StageInputError
from heliocal.pipeline.artifacts.schemas import MEASUREMENTS, REJECTED


def _rejected(n=2) -> pd.DataFrame:
    return pd.DataFrame({"source_file": ["b.csv", "a.csv"][:n], "source_row": [2, 1][:n],
                         "heliostat_id": ["AA31", None][:n], "measurement_id": ["7", None][:n],
                         "reason": ["missing_value"] * n, "detail": ["x is empty"] * n,
                         "raw": ["{}"] * n})


def test_write_read_round_trip_sorted(tmp_path):
    src = tmp_path / "in.csv"
    src.write_text("hello\n")
    write_artifact(_rejected(), tmp_path, REJECTED, stage="ingest", options={"k": 1},
                   inputs={"source": src})
    df = read_artifact(tmp_path, REJECTED)
    assert df["source_file"].tolist() == ["a.csv", "b.csv"]  # sort_by source_file, source_row
    prov = read_provenance(tmp_path / "rejected.parquet")
    assert prov["schema_version"] == SCHEMA_VERSION and prov["stage"] == "ingest"
    # SHA-256 of b"hello\n" (sha256sum)
    assert prov["inputs"]["source"] == "5891b5b522d5df086d0ff0b110fbd9d21bb4fc7163af34d08286a2e846f6be03"
    assert prov["options"] == {"k": 1}


def test_string_columns_read_as_python_strings_with_nan_for_missing(tmp_path):
    # what pandas' astype(object) of the Arrow column gives (the reference): str values, a
    # float NaN where a value is missing; repeated values converted once are equal values
    rows = pd.concat([_rejected()] * 3, ignore_index=True)
    rows["source_row"] = range(len(rows))
    write_artifact(rows, tmp_path, REJECTED, stage="ingest")
    df = read_artifact(tmp_path, REJECTED)
    table = pq.read_table(tmp_path / "rejected.parquet")
    for column in ("heliostat_id", "measurement_id", "source_file"):
        expected = table.column(column).to_pandas().astype(object)
        got = df[column]
        assert got.dtype == object
        assert [type(v) for v in got] == [type(v) for v in expected]
        assert got.isna().tolist() == expected.isna().tolist()
        assert got.dropna().tolist() == expected.dropna().tolist()
    assert df["heliostat_id"].isna().sum() == 3 and set(df["heliostat_id"].dropna()) == {"AA31"}


def test_kept_reads_decode_once_and_callers_cannot_change_the_kept_table(tmp_path):
    write_artifact(_rejected(), tmp_path, REJECTED, stage="ingest")
    with kept_reads():
        first = read_artifact(tmp_path, REJECTED)
        first["reason"] = "changed by the caller"         # a column replaced in place
        first.loc[0, "source_row"] = 99                   # a value set in place
        again = read_artifact(tmp_path, REJECTED)
        pd.testing.assert_frame_equal(again, read_artifact(tmp_path, REJECTED))
        assert again["reason"].tolist() == ["missing_value"] * 2    # as written
        assert again["source_row"].tolist() == [1, 2]               # sorted on write
        # new bytes of the artifact: read anew, not the kept table
        write_artifact(_rejected(1), tmp_path, REJECTED, stage="ingest")
        assert len(read_artifact(tmp_path, REJECTED)) == 1
    assert store._KEPT is None                             # nothing kept outside the block


def test_missing_column_is_refused_on_write(tmp_path):
    with pytest.raises(SchemaError, match="required columns \\['raw'\\] are missing"):
        write_artifact(_rejected().drop(columns=["raw"]), tmp_path, REJECTED, stage="ingest")
    assert not (tmp_path / "rejected.parquet").exists()


def test_null_in_non_nullable_column_is_refused(tmp_path):
    df = _rejected()
    df.loc[0, "reason"] = None
    with pytest.raises(SchemaError, match="'reason' has 1 missing values"):
        write_artifact(df, tmp_path, REJECTED, stage="ingest")


def test_undeclared_column_is_refused(tmp_path):
    with pytest.raises(SchemaError, match="undeclared columns \\['foo'\\]"):
        write_artifact(_rejected().assign(foo=1), tmp_path, REJECTED, stage="ingest")


def test_missing_artifact_names_the_stage(tmp_path):
    with pytest.raises(StageInputError) as exc:
        read_artifact(tmp_path, MEASUREMENTS)
    assert str(exc.value) == (f"{tmp_path / 'measurements.parquet'} is missing: run "
                              f"`heliocal ingest SOURCE... --workdir {tmp_path}` first")


def test_wrong_schema_version_is_refused(tmp_path):
    path = write_artifact(_rejected(), tmp_path, REJECTED, stage="ingest")
    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[b"heliocal"])
    meta["schema_version"] = SCHEMA_VERSION + 1
    pq.write_table(table.replace_schema_metadata({b"heliocal": json.dumps(meta).encode()}), path)
    with pytest.raises(SchemaError, match="rerun `heliocal ingest"):
        read_artifact(tmp_path, REJECTED)


def test_atomic_path_keeps_old_content_on_failure(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["a.txt"]


def test_check_fresh_detects_changed_upstream(tmp_path):
    up = write_artifact(_rejected(), tmp_path, REJECTED, stage="ingest")
    # an artifact in tmp_path recording the hash of rejected.parquet as its input "rejected"
    from dataclasses import replace
    down = replace(REJECTED, name="down", filename="down.parquet", producer="split-knn")
    write_artifact(_rejected(1), tmp_path, down, stage="split-knn", inputs={"rejected": up})
    check_fresh(tmp_path, down, {"rejected": REJECTED})  # fresh: no error
    write_artifact(_rejected(1), tmp_path, REJECTED, stage="ingest")  # upstream changes
    with pytest.raises(StageInputError, match="is stale: rejected.parquet changed"):
        check_fresh(tmp_path, down, {"rejected": REJECTED})
