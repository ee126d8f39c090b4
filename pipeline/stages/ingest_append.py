"""``ingest --append``: a day's new calibration rows added to a work directory's measurements.

A plant adds a few rows a day. ``ingest NEW_LOG --workdir W --append`` validates the new sources
exactly as ``ingest`` does (same options, same reasons), then merges what it keeps with the rows
the work directory already holds:

* a kept row whose heliostat and measurement id are already ingested and whose content (every
  measurement column but ``source_file``/``source_row``, which name where a copy came from) is
  identical is a re-sent row: rejected as ``duplicate_of_ingested_row``;
* one with the same heliostat and id but other values cannot be a second measurement (the id is
  unique per heliostat): rejected as ``duplicate_measurement_id``, naming the ingested row;
* every other kept row is added. A heliostat new to the work directory gets its properties row
  from the new sources; a known heliostat keeps its ingested properties (as ``ingest A B`` keeps
  the first source's), with ``n_measurements`` counted again.

The three artifacts are written whole, in one transaction, as ``ingest`` writes them: the
previous rows and rejected rows are kept, so ``ingest A; ingest B --append`` holds the rows of
``ingest A B`` (a test compares them).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..artifacts.schemas import HELIOSTATS, MEASUREMENTS, REJECTED
from ..artifacts.store import artifact_present, read_artifact, write_artifact
from ..errors import InputError

__all__ = ["IDENTITY_EXCLUDED", "AppendResult", "merge_new_rows", "previous_tables", "write_appended"]

#: Columns that say where a copy of a row came from, not what was measured: left out of a row's
#: content identity.
IDENTITY_EXCLUDED = ("source_file", "source_row")


def previous_tables(workdir) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The committed (measurements, heliostats, rejected) of ``workdir``; an :class:`InputError`
    naming the fix when nothing was ingested there yet."""
    if not artifact_present(workdir, MEASUREMENTS):
        raise InputError(f"--append adds rows to an ingested work directory, but {workdir} has no "
                         "measurements.parquet; run `heliocal ingest SOURCE --workdir "
                         f"{workdir}` without --append first")
    return (read_artifact(workdir, MEASUREMENTS), read_artifact(workdir, HELIOSTATS),
            read_artifact(workdir, REJECTED))


def _keys(df: pd.DataFrame) -> pd.Series:
    return df["heliostat_id"].astype(str) + "\0" + df["measurement_id"].astype(str)


def _same_content(new: pd.DataFrame, old: pd.DataFrame) -> np.ndarray:
    """Row by row (aligned), whether two frames hold the same measurement: every shared column but
    :data:`IDENTITY_EXCLUDED` equal (missing equals missing)."""
    cols = [c for c in new.columns if c in old.columns and c not in IDENTITY_EXCLUDED]
    same = np.ones(len(new), dtype=bool)
    for c in cols:
        a, b = new[c].reset_index(drop=True), old[c].reset_index(drop=True)
        if c == "timestamp":
            a, b = pd.to_datetime(a, utc=True), pd.to_datetime(b, utc=True)
        eq = (a == b).to_numpy(bool) | (a.isna() & b.isna()).to_numpy(bool)
        same &= eq
    return same


def _rejections(rows: pd.DataFrame, old: pd.DataFrame, identical: np.ndarray) -> pd.DataFrame:
    """rejected.parquet rows for new rows already ingested (``old``: the ingested row of each)."""
    where = [f"{f} row {r}" for f, r in zip(old["source_file"], old["source_row"])]
    detail = [(f"identical to measurement {m} of heliostat {h} ingested from {w}" if same else
               f"the work directory already holds measurement {m} of heliostat {h} (from {w}) "
               "with other values; give the new measurement its own id")
              for h, m, w, same in zip(rows["heliostat_id"], rows["measurement_id"], where,
                                       identical)]
    return pd.DataFrame({
        "source_file": rows["source_file"].to_numpy(), "source_row": rows["source_row"].to_numpy(),
        "heliostat_id": rows["heliostat_id"].to_numpy(),
        "measurement_id": rows["measurement_id"].to_numpy(),
        "reason": np.where(identical, "duplicate_of_ingested_row", "duplicate_measurement_id"),
        "detail": detail,
        # (to_json of no rows is one empty line, not none)
        "raw": (rows.drop(columns=["timestamp"]).to_json(orient="records", lines=True).splitlines()
                if len(rows) else [])})


class AppendResult:
    """The merged tables of an append and what it did."""

    def __init__(self, measurements, heliostats, rejected, added, duplicates):
        self.measurements = measurements    # previous rows + added rows
        self.heliostats = heliostats        # previous heliostats + new ones, counts updated
        self.rejected = rejected            # previous rejected + new rejected + duplicates
        self.added = added                  # the rows added (MEASUREMENTS columns)
        self.duplicates = duplicates        # rejected rows of already ingested measurements


def merge_new_rows(previous: tuple, kept: pd.DataFrame, helio: pd.DataFrame,
                   rejected: pd.DataFrame) -> AppendResult:
    """Merge the new sources' kept rows, heliostat rows and rejected rows (as ``ingest`` made
    them) into the ``previous`` (measurements, heliostats, rejected) of the work directory."""
    old_m, old_h, old_r = previous
    old_index = pd.Series(np.arange(len(old_m)), index=_keys(old_m).to_numpy())
    pos = _keys(kept).map(old_index)
    seen = pos.notna().to_numpy()
    dup_rows = kept.loc[seen]
    identical = _same_content(dup_rows, old_m.iloc[pos[seen].astype(int).to_numpy()])
    duplicates = _rejections(dup_rows, old_m.iloc[pos[seen].astype(int).to_numpy()], identical)
    added = kept.loc[~seen]
    measurements = pd.concat([old_m, added], ignore_index=True)
    counts = measurements.groupby("heliostat_id").size()
    new_h = helio[~helio["heliostat_id"].isin(set(old_h["heliostat_id"]))]
    new_h = new_h[new_h["heliostat_id"].isin(set(counts.index))]
    heliostats = pd.concat([old_h, new_h], ignore_index=True)
    heliostats["n_measurements"] = heliostats["heliostat_id"].map(counts).astype("int64")
    all_rejected = pd.concat([old_r, rejected, duplicates], ignore_index=True)
    return AppendResult(measurements, heliostats, all_rejected[REJECTED.column_names()], added,
                        duplicates)


def write_appended(result: AppendResult, workdir, prov: dict) -> None:
    """Write the merged artifacts in ingest's order (measurements.parquet last)."""
    write_artifact(result.rejected, workdir, REJECTED, **prov)
    write_artifact(result.heliostats, workdir, HELIOSTATS, **prov)
    write_artifact(result.measurements, workdir, MEASUREMENTS, **prov)
