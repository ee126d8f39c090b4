"""Flat calibration logs (CSV or Parquet, WGS84 or ENU): column aliases, streaming reading in
blocks, the per-source context (properties, targets) and the staging of log rows.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import pandas as pd
import pyarrow as pa

from ..errors import HeliocalError, InputError, resource_error_message
from ..physics.geodesy import wgs84_to_enu
from .paint import read_paint_properties, read_properties_table
from .sources import TOWER_FILENAME, find_tower_file, read_tower
from .spill import SortedSpill
from .staged import IngestOptions, Staged, Target
from .text import open_csv_text, shorten
from .validation import float_columns

__all__ = [
    "read_log_rows",
    "LogContext",
    "log_context",
    "stage_log_rows",
]

log = logging.getLogger("heliocal.ingest")


_LOG_ALIASES = {
    "measurement_id": ("measurement_id", "sample_id", "id"),
    "axis_1_steps": ("axis_1_steps", "axis_1_motor_position"),
    "axis_2_steps": ("axis_2_steps", "axis_2_motor_position"),
    "sun_azimuth_deg": ("sun_azimuth_deg", "sun_azimuth"),
    "sun_elevation_deg": ("sun_elevation_deg", "sun_elevation"),
}


_LOG_RECOGNISED_IGNORED = ("tracking_error_lat", "tracking_error_lon", "tracking_error_alt",
                           "tracking_error_e_m", "tracking_error_n_m", "tracking_error_u_m")


def _iter_csv_records(path: Path, rows_per_block: int) -> Iterator[tuple[list[str], list[list[str]]]]:
    """Header and blocks of data rows of a comma-separated UTF-8 file, every cell a stripped
    string, streamed: yields ``(header, rows)`` with at most ``rows_per_block`` rows per block.

    Blank lines are skipped; a short row is padded with empty cells (they become
    ``missing_value`` rejections); a row with more non-empty cells than the header raises
    :class:`InputError` naming the row, since its values cannot be assigned to columns.
    """
    with open_csv_text(path) as text:
        reader = csv.reader(text, skipinitialspace=True, strict=True)
        rows: list[list[str]] = []
        header: list[str] | None = None
        n_rows = 0
        try:
            for cells in reader:
                if not cells or (len(cells) == 1 and not cells[0].strip()):
                    continue
                cells = [c.strip() for c in cells]
                if header is None:
                    header = cells
                    continue
                n_rows += 1
                if len(cells) > len(header):
                    if any(cells[len(header):]):
                        raise InputError(
                            f"{path}: data row {n_rows} (line {reader.line_num}) has "
                            f"{len(cells)} fields but the header has {len(header)}; remove the "
                            "extra fields or quote values that contain commas")
                    cells = cells[:len(header)]
                rows.append(cells + [""] * (len(header) - len(cells)))
                if len(rows) >= rows_per_block:
                    yield header, rows
                    rows = []
        except csv.Error as exc:
            raise InputError(f"{path}: malformed CSV at line {reader.line_num} ({shorten(exc)}); "
                             "close the quote or re-export the log") from exc
    if header is None:
        raise InputError(f"{path}: the file is empty; give a calibration log with a header row "
                         "and one row per measurement")
    yield header, rows


def _check_header(path: Path, header: Sequence[str]) -> None:
    seen = set()
    for name in header:
        if name in seen:
            raise InputError(f"{path}: duplicated column {name!r}; remove one of them so each "
                             "field appears once")
        seen.add(name)
    if "" in header:
        raise InputError(f"{path}: column {header.index('') + 1} of the header has no name; name "
                         "it or remove the column")


# The pass over a log: read in batches, keyed by heliostat -------------------------------------
#: Internal columns of the spilled source rows (a log column of the same name is refused).
_KEY = "__heliocal_heliostat_key"


_SEQ = "__heliocal_source_row"


#: Rows parsed from a CSV at a time before they become one Arrow block.
_CSV_BLOCK_ROWS = 16384


def _heliostat_key(values: pd.Series) -> pd.Series:
    """The stripped heliostat id as text ('' when missing): rows of one heliostat share a key."""
    return values.map(lambda v: v.strip() if isinstance(v, str)
                      else ("" if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)))


@dataclass
class _LogRows:
    """The rows of one log after the streaming pass: in memory (one chunk) or spilled in runs."""

    path: Path
    header: list[str]
    rows: int
    parquet_schema: "pa.Schema | None"  # original schema (with pandas metadata) of a Parquet log
    float_columns: set[str]  # Parquet integer columns with nulls somewhere (pandas makes them float)
    extra_stats: dict[str, list]  # column -> [non-empty, numeric non-empty, all integer]
    tables: list  # in-memory blocks (pa.Table) when not spilled
    spill: SortedSpill | None

    def chunks(self, chunk_rows: int | None) -> Iterator["pa.Table"]:
        """Blocks holding every row of a range of heliostats, in heliostat order."""
        if self.spill is None:
            if self.tables:
                yield pa.concat_tables(self.tables)
            return
        yield from self.spill.merged(chunk_rows)

    def frame(self, table: "pa.Table") -> pd.DataFrame:
        """A block as the raw frame :func:`stage_log_rows` takes: source order, every value as
        read (Parquet: pandas' conversion of the whole file), index = source row - 1."""
        seq = table.column(_SEQ).to_numpy()
        order = np.argsort(seq, kind="stable")
        table = table.take(pa.array(order)).drop_columns([_KEY, _SEQ])
        seq = seq[order]
        if self.parquet_schema is not None:
            for name in self.float_columns:
                i = table.column_names.index(name)
                table = table.set_column(i, name, table.column(name).cast(pa.float64()))
            df = table.replace_schema_metadata(self.parquet_schema.metadata).to_pandas()
            df = df.reset_index(drop=True)
            df.columns = [str(c) for c in df.columns]
            df = df.astype(object).where(df.notna(), "")
        else:
            df = pd.DataFrame({n: table.column(n).to_numpy(zero_copy_only=False)
                               for n in table.column_names}, dtype=object)
        df.index = pd.Index(seq - 1)
        return df


def _log_column_usage(header: Sequence[str], kind: str) -> set[str]:
    """Names of the log columns :func:`log_context` maps to canonical columns."""
    names = {"heliostat_id", "timestamp", "target_name", "focal_spot_source"}
    for aliases in _LOG_ALIASES.values():
        names.update(aliases)
    if kind == "wgs84-log":
        names.update(f"{p}_{c}" for p in ("focal_spot", "heliostat", "target_center")
                     for c in ("lat", "lon", "alt"))
    else:
        names.update(_ENU_LOG_COLUMNS)
    names.update(_LOG_RECOGNISED_IGNORED)
    return names & set(header)


def _numeric_stats(values: pd.Series) -> tuple[int, int, bool]:
    """(non-empty cells, numeric non-empty cells, all integers) of an extra log column."""
    cells = values.to_numpy(dtype=object).copy()
    cells[np.array([isinstance(v, str) and v == "" for v in cells], dtype=bool)] = np.nan
    numeric = pd.to_numeric(cells, errors="coerce")
    nonempty = np.array([not isinstance(v, str) or v.strip() != "" for v in values.tolist()],
                        dtype=bool)
    return (int(nonempty.sum()), int((~pd.isna(numeric[nonempty])).sum()),
            bool(pd.api.types.is_integer_dtype(numeric)))


def read_log_rows(path: Path, kind: str, batch_rows: int | None, spill_dir: Path | None) -> _LogRows:
    """Read a CSV or Parquet log in batches of ``batch_rows`` rows (all at once with ``None``),
    keyed by heliostat; with a ``spill_dir`` and more rows than one batch, every batch is sorted
    by heliostat and spilled there as a run, so memory holds one batch.

    Errors name their cause: a file pyarrow cannot read is "not a readable Parquet file"; a full
    disk or a forbidden folder while spilling is the OSError it is (the CLI says what to free); a
    MemoryError while reading or spilling is one line naming the batch size to lower."""
    try:
        return _read_log_rows(path, kind, batch_rows, spill_dir)
    except MemoryError:
        size = f"batches of {batch_rows} rows" if batch_rows is not None else "one batch"
        raise HeliocalError(f"{path}: out of memory while reading the log in {size}; give a "
                            "smaller --batch-rows or free memory, then rerun the command") from None


def _id_column(header: Sequence[str]) -> str | None:
    return next((c for c in header if str(c).strip() == "heliostat_id"), None)


def _read_log_rows(path: Path, kind: str, batch_rows: int | None,
                   spill_dir: Path | None) -> _LogRows:
    rows = _LogRows(path, [], 0, None, set(), {}, [], None)
    extra: list[str] = []

    def add(table: pa.Table, frame: pd.DataFrame) -> None:
        key = (_heliostat_key(frame[_KEY]) if _KEY in frame.columns
               else pd.Series("", index=frame.index))
        table = table.append_column(_KEY, pa.array(key.tolist(), pa.string()))
        table = table.append_column(_SEQ, pa.array(np.arange(rows.rows + 1, rows.rows + 1
                                                               + table.num_rows), pa.int64()))
        rows.rows += table.num_rows
        for name in extra:
            if name in frame.columns:
                nonempty, numeric, integer = _numeric_stats(frame[name])
                st = rows.extra_stats.setdefault(name, [0, 0, True])
                st[0] += nonempty
                st[1] += numeric
                st[2] = st[2] and integer
        rows.tables.append(table)
        if (batch_rows is not None and spill_dir is not None
                and sum(t.num_rows for t in rows.tables) >= batch_rows):
            if rows.spill is None:
                rows.spill = SortedSpill(spill_dir, f"log-{id(rows):x}", _KEY, _SEQ)
            rows.spill.add(pa.concat_tables(rows.tables))
            rows.tables = []

    if path.suffix.lower() in (".parquet", ".pq"):
        parquet = _open_parquet(path, rows)
        extra += [n for n in rows.header if n not in _log_column_usage(rows.header, kind)]
        nulls: dict[str, int] = {}
        for table, frame in _parquet_batches(parquet, path, extra, batch_rows, nulls):
            add(table, frame)   # outside the reader's error handling: spilling has its own
        names, schema = parquet.names, rows.parquet_schema
        rows.float_columns = {n for n in names if nulls.get(n) and pa.types.is_integer(schema.field(n).type)}
    else:
        header: list[str] = []
        for header, block in _iter_csv_records(path, min(batch_rows or _CSV_BLOCK_ROWS, _CSV_BLOCK_ROWS)):
            if not rows.header:
                rows.header = list(header)
                extra = [n for n in header if n not in _log_column_usage(header, kind)]
            if not block:
                continue
            columns = list(zip(*block))
            names = list(dict.fromkeys(header))  # a duplicated column is refused below
            table = pa.table({n: pa.array(columns[header.index(n)], pa.string()) for n in names})
            frame = pd.DataFrame({n: columns[header.index(n)] for n in extra if n in names},
                                 index=range(len(block)), dtype=object)
            hcol = _id_column(names)
            if hcol:
                frame[_KEY] = pd.Series(columns[header.index(hcol)], dtype=object)
            add(table, frame)
        rows.header = list(header)
    _check_header(path, rows.header)
    if _KEY in rows.header or _SEQ in rows.header:
        raise InputError(f"{path}: column names {_KEY!r} and {_SEQ!r} are reserved by heliocal; "
                         "rename the column")
    if rows.spill is not None and rows.tables:
        rows.spill.add(pa.concat_tables(rows.tables))
        rows.tables = []
    return rows


@dataclass
class _ParquetLog:
    """An open Parquet log: the file and its data columns (the pandas index columns left out)."""

    file: object                # pyarrow.parquet.ParquetFile
    names: list[str]


def _reader_error(path: Path, exc: Exception) -> Exception:
    """What to raise for an exception of pyarrow's reader: the machine's own trouble (memory, a
    resource the CLI explains) as it is, anything else as an unreadable file."""
    if isinstance(exc, (InputError, MemoryError)) or resource_error_message(exc) is not None:
        return exc
    return InputError(f"{path}: not a readable Parquet file ({shorten(exc)}); export the log "
                      "again")


def _open_parquet(path: Path, rows: _LogRows) -> _ParquetLog:
    """Open a Parquet log; its schema and header go to ``rows``."""
    import pyarrow.parquet as pq

    try:
        pf = pq.ParquetFile(path)
        schema = pf.schema_arrow
    except Exception as exc:  # noqa: BLE001 - pyarrow raises several types
        raise _reader_error(path, exc) from exc
    index_cols = {c for c in ((schema.pandas_metadata or {}).get("index_columns") or [])
                  if isinstance(c, str)}
    names = [n for n in schema.names if n not in index_cols]
    rows.parquet_schema = schema
    rows.header = [str(n) for n in names]
    return _ParquetLog(pf, names)


def _parquet_batches(log: _ParquetLog, path: Path, extra: Sequence[str], batch_rows: int | None,
                     nulls: dict[str, int]) -> Iterator[tuple[pa.Table, pd.DataFrame]]:
    """The log's batches as (table, frame of its heliostat key and ``extra`` columns), counting
    each column's nulls in ``nulls``. Only the reading is judged here (:func:`_reader_error`):
    what the caller does with a batch raises its own errors."""
    schema = log.file.schema_arrow
    block = batch_rows or (1 << 16)
    hcol = _id_column(log.names)
    batches = log.file.iter_batches(batch_size=min(block, 1 << 16))
    while True:
        try:
            batch = next(batches, None)
            if batch is None:
                return
            table = pa.Table.from_batches([batch], schema=schema)
            for n in log.names:
                nulls[n] = nulls.get(n, 0) + table.column(n).null_count
            frame = (table.select([hcol, *extra] if hcol else list(extra))
                     .replace_schema_metadata(None).to_pandas())
            frame = frame.astype(object).where(frame.notna(), "")
            if hcol:
                frame[_KEY] = frame.pop(hcol) if hcol not in extra else frame[hcol]
        except Exception as exc:  # noqa: BLE001 - pyarrow raises several types
            raise _reader_error(path, exc) from exc
        yield table, frame


@dataclass
class LogContext:
    """What a log's header, tower file and properties define for all its rows."""

    path: Path
    kind: str
    columns: dict[str, str]  # canonical name -> log column
    env: dict[str, tuple[str, bool]]  # env_* name -> (log column, integer)
    heliostats: dict[str, dict]
    targets: dict[str, Target]
    reference: tuple[float, float, float] | None
    ignored: list[str]


_ENU_LOG_COLUMNS = ("focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m", "heliostat_e_m",
                    "heliostat_n_m", "heliostat_u_m", "target_e_m", "target_n_m", "target_u_m",
                    "target_normal_e", "target_normal_n", "target_normal_u")


def _staged_names(kind: str) -> set[str]:
    """Columns of a staged log frame (a log column of the same name is neither env_* nor
    reported as ignored)."""
    names = {"source_file", "source_row", "raw", "heliostat_id", "measurement_id", "axis_1_steps",
             "axis_2_steps", "timestamp", "sun_azimuth_deg", "sun_elevation_deg", "target_name",
             "focal_spot_source"}
    if kind == "wgs84-log":
        names |= {f"{p}_{c}" for p in ("focal_spot", "heliostat", "target_center")
                  for c in ("lat", "lon", "alt")}
        names |= {f"{p}_{a}_m" for p in ("focal_spot", "heliostat", "target") for a in "enu"}
        names.add("_hpos_wgs84")
    else:
        names |= set(_ENU_LOG_COLUMNS)
    return names


def log_context(rows: _LogRows, opts: IngestOptions, kind: str) -> LogContext:
    """Map a log's columns, read its tower and properties; raise on what no row can fix."""
    path = rows.path
    if rows.rows == 0:
        raise InputError(f"{path}: header only, no data rows; give a log with at least one "
                         "measurement")
    cols = {str(c).strip(): c for c in rows.header}
    mapping: dict[str, str] = {}
    used = set()

    def take(canonical: str, *names: str, required: bool = False):
        for name in names or (canonical,):
            if name in cols:
                mapping[canonical] = cols[name]
                used.add(name)
                return True
        if required:
            raise InputError(f"{path}: missing required column {canonical!r} (or "
                             f"{' / '.join(n for n in names if n != canonical) or 'alias'}); add it "
                             "to the log, see README 'Input formats'")
        return False

    take("heliostat_id", required=True)
    take("measurement_id", *_LOG_ALIASES["measurement_id"], required=True)
    take("axis_1_steps", *_LOG_ALIASES["axis_1_steps"], required=True)
    take("axis_2_steps", *_LOG_ALIASES["axis_2_steps"], required=True)
    has_ts = take("timestamp")
    has_az = take("sun_azimuth_deg", *_LOG_ALIASES["sun_azimuth_deg"])
    has_el = take("sun_elevation_deg", *_LOG_ALIASES["sun_elevation_deg"])
    if not (has_az and has_el) and not has_ts:
        raise InputError(f"{path}: missing required columns sun_azimuth/sun_elevation and no "
                         "timestamp to compute them from; add either")
    take("target_name", required=True)
    take("focal_spot_source")
    heliostats: dict[str, dict] = {}
    targets: dict[str, Target] = {}
    reference = None
    if kind == "wgs84-log":
        tower = read_tower(find_tower_file(path, opts.tower))
        reference = tower.reference
        if reference is None:
            raise InputError(f"{path}: no {TOWER_FILENAME} beside or above the log to define the "
                             "plant reference point; pass --tower PATH")
        targets = dict(tower.targets)
        for name in ("focal_spot_lat", "focal_spot_lon", "focal_spot_alt", "heliostat_lat",
                     "heliostat_lon", "heliostat_alt", "target_center_lat", "target_center_lon",
                     "target_center_alt"):
            take(name)
    else:  # enu-log
        for name in _ENU_LOG_COLUMNS:
            take(name)
        reference = opts.location
        if opts.properties is None:
            raise InputError(f"{path}: an ENU log needs the heliostat properties: pass --properties "
                             "FILE.toml|FILE.csv (see README 'Input formats')")
    if opts.properties is not None:
        heliostats, extra_targets = _read_properties_source(Path(opts.properties), reference)
        targets.update(extra_targets)
    if kind == "enu-log" and reference is None and not (has_az and has_el):
        raise InputError(f"{path}: sun angles are missing and no plant location to compute them; "
                         "pass --location LAT,LON,ALT")

    # extra numeric columns -> env_* (judged on the whole column: 90 % of its cells numbers)
    ignored, env = [], {}
    known = used | set(_LOG_RECOGNISED_IGNORED) | {"focal_spot_source"} | _staged_names(kind)
    for name, col in cols.items():
        if name in known:
            continue
        nonempty, numeric, integer = rows.extra_stats.get(col, (0, 0, True))
        if nonempty and numeric / nonempty >= 0.9:
            env["env_" + re.sub(r"[^0-9a-zA-Z]+", "_", name).strip("_").lower()] = (col, integer)
        else:
            ignored.append(name)
    ignored += [c for c in _LOG_RECOGNISED_IGNORED if c in cols]
    return LogContext(path, kind, mapping, env, heliostats, targets, reference, ignored)


def stage_log_rows(raw: pd.DataFrame, ctx: LogContext) -> Staged:
    """Rows of a log (a raw frame from :meth:`_LogRows.frame`) as a staged frame."""
    df = pd.DataFrame(index=raw.index)
    df["source_file"] = str(ctx.path)
    df["source_row"] = raw.index.to_numpy() + 1
    df["raw"] = [json.dumps(r, default=str) for r in raw.to_dict("records")]
    for canonical in ("heliostat_id", "measurement_id", "axis_1_steps", "axis_2_steps",
                      "timestamp", "sun_azimuth_deg", "sun_elevation_deg", "target_name",
                      "focal_spot_source"):
        df[canonical] = raw[ctx.columns[canonical]] if canonical in ctx.columns else ""
    if ctx.kind == "wgs84-log":
        for name in ("focal_spot_lat", "focal_spot_lon", "focal_spot_alt", "heliostat_lat",
                     "heliostat_lon", "heliostat_alt", "target_center_lat", "target_center_lon",
                     "target_center_alt"):
            df[name] = raw[ctx.columns[name]] if name in ctx.columns else ""
        for src, dst in (("focal_spot", "focal_spot"), ("heliostat", "heliostat"),
                         ("target_center", "target")):
            _wgs84_columns_to_enu(df, src, dst, ctx.reference)
        hpos = float_columns(df, ["heliostat_lat", "heliostat_lon", "heliostat_alt"])
        df["_hpos_wgs84"] = list(zip(*(c.tolist() for c in hpos)))
    else:
        for name in _ENU_LOG_COLUMNS:
            df[name] = raw[ctx.columns[name]] if name in ctx.columns else ""
    for env_name, (col, integer) in ctx.env.items():
        numeric = pd.to_numeric(raw[col].replace("", np.nan), errors="coerce")
        df[env_name] = numeric if integer else numeric.astype(float)
    df["_reject"] = None
    df["focal_spot_source"] = df["focal_spot_source"].replace("", "log")
    return Staged(df, ctx.heliostats, ctx.targets, ctx.reference, ctx.kind, ctx.ignored)


def _wgs84_columns_to_enu(df: pd.DataFrame, src: str, dst: str, reference) -> None:
    """Columns ``{src}_lat/lon/alt`` (text) -> ``{dst}_e_m/n_m/u_m`` (NaN where any is missing)."""
    names = [f"{src}_lat", f"{src}_lon", f"{src}_alt"]
    wgs = float_columns(df, names)
    ok = ~np.isnan(np.stack(wgs)).any(axis=0)
    enu = wgs84_to_enu(*(np.where(ok, c, 0.0) for c in wgs), reference)
    for axis, values in zip("enu", enu):
        df[f"{dst}_{axis}_m"] = np.where(ok, values, np.nan)


def _read_properties_source(path: Path, reference) -> tuple[dict[str, dict], dict[str, Target]]:
    if path.is_dir():
        files = sorted(path.rglob("*-heliostat-properties.json"))
        if not files:
            raise InputError(f"{path}: no *-heliostat-properties.json in this folder; give a PAINT "
                             "folder, a properties CSV or a TOML file")
        if reference is None:
            raise InputError(f"{path}: PAINT properties need the plant reference point; pass --tower")
        rows = [read_paint_properties(f, reference) for f in files]
        return {r["heliostat_id"]: r for r in rows}, {}
    if not path.is_file():
        raise InputError(f"{path}: properties file not found; check the --properties path")
    if path.suffix.lower() not in (".csv", ".toml"):
        raise InputError(f"{path}: properties must be a .csv, .toml or a PAINT folder")
    rows, targets = read_properties_table(path)
    return {r["heliostat_id"]: r for r in rows}, targets
