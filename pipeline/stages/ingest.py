"""``ingest``: PAINT folders and flat CSV/Parquet logs into the canonical measurement table.

Three source kinds are detected automatically (:func:`detect_source`):

``paint``
    A PAINT download: ``<HID>/<HID>-heliostat-properties.json`` and
    ``<HID>/calibration/<id>-calibration-properties.json`` (or ``<id>_calibration_properties.json``),
    UTC times from a ``timestamps.json`` map (``"<HID>_<id>"``) found in or above the folder, and the
    plant's ``tower-measurements.json`` found beside or above it (or given). One JSON file is one
    input row.
``wgs84-log``
    A flat CSV or Parquet calibration log with WGS84 coordinates (``focal_spot_lat/lon/alt``,
    ``heliostat_lat/lon/alt``), like the Jülich calibration log.
``enu-log``
    A flat CSV or Parquet log already in local ENU metres (``focal_spot_e_m`` ...), with the
    heliostat properties (and targets) from a small CSV or TOML file (``--properties``).
``simulate``
    A folder written by ``heliocal simulate`` (it holds the simulator's ``ground_truth.json``): read
    as its logs, each with the folder's own properties (:func:`simulate_sources`).

Heliostat ids become file names later (``hybrid/<mode>/<id>.pt``, report figures), so a row whose
id does not match :data:`~heliocal.pipeline.artifacts.schemas.HELIOSTAT_ID_RE` is rejected
(``invalid_heliostat_id``, with a suggested new name).

Nothing is lost: every input row ends in ``measurements.parquet`` or, with a reason, in
``rejected.parquet``. A source that cannot be read at all raises :class:`InputError` (one line
naming the file, the problem and the fix) before any artifact is written.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
import pandas as pd
import pyarrow as pa

from ..artifacts.paths import artifact_path
from ..artifacts.schemas import HELIOSTATS, MEASUREMENTS, REJECTED, REJECTION_REASONS
from ..artifacts.store import artifact_writer, write_artifact
from ..artifacts.table import to_table
from ..artifacts.leftovers import OWNER_FILENAME, SPILL_PREFIX
from ..artifacts.manifests import current_transaction
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..errors import InputError, check_int
from ..io.csv_log import log_context, read_log_rows, stage_log_rows
from ..io.paint import stage_paint
from ..io.sources import detect_source, expand_sources
from ..io.spill import SortedSpill
from ..io.staged import IngestOptions, Staged
from ..io.source_checks import SourceChecks
from ..io.validation import invalid_id_message, validate_rows
from ..vocabulary import DEFAULT_BATCH_ROWS
from ..runtime.process_state import restores_process_state
from .ingest_append import merge_new_rows, previous_tables, write_appended

__all__ = [
    "ingest",
    "run_ingest",
]

log = logging.getLogger("heliocal.ingest")


# ------------------------------------------------------------------------------------------------
# the stage: sources -> chunks of whole heliostats -> artifacts
# ------------------------------------------------------------------------------------------------


#: Rows per row group of measurements.parquet (sorted by heliostat, so a heliostat's rows sit in
#: one or two row groups and ``read_artifact(..., heliostats=...)`` skips the others).
MEASUREMENTS_ROW_GROUP_ROWS = 32_768


@dataclass
class _Chunk:
    kept: pd.DataFrame  # MEASUREMENTS columns + env_*, plus _src and _seq
    rejected: pd.DataFrame  # REJECTED columns plus _src, _seq, _cross
    derived: dict[str, dict]  # heliostat rows derived from the log rows (no properties)


class _Source:
    """One source: read (and spilled) on construction, validated chunk by chunk by :meth:`chunks`."""

    def __init__(self, index: int, path: Path, opts: IngestOptions, batch_rows: int | None,
                 spill_dir: Path | None):
        self.index, self.path, self.opts, self.batch_rows = index, path, opts, batch_rows
        self.kind = detect_source(path)
        if self.kind == "paint":
            self._paint = stage_paint(path, opts)
            self.rows = len(self._paint.frame)
            self.heliostats = self._paint.heliostats
            self.ignored = self._paint.ignored_columns
            self.env: dict[str, bool] = {}
        else:
            self._log = read_log_rows(path, self.kind, batch_rows, spill_dir)
            self._ctx = log_context(self._log, opts, self.kind)
            self.rows = self._log.rows
            self.heliostats = self._ctx.heliostats
            self.ignored = self._ctx.ignored
            self.env = {name: integer for name, (_, integer) in self._ctx.env.items()}

    def _staged(self) -> Iterator[Staged]:
        if self.kind == "paint":
            yield self._paint
            return
        for table in self._log.chunks(self.batch_rows):
            yield stage_log_rows(self._log.frame(table), self._ctx)

    def chunks(self) -> Iterator[_Chunk]:
        """Validated chunks holding every row of a range of heliostats, in heliostat order."""
        checks = SourceChecks(self.opts)
        for staged in self._staged():
            checks.add_rows(staged.frame)
            kept, rejected, helios = validate_rows(staged, self.opts, checks)
            kept = kept.assign(_src=self.index, _seq=kept.index.to_numpy())
            if self.kind == "paint":
                kept = kept.sort_values("heliostat_id", kind="mergesort")
            rejected = rejected.assign(_src=self.index, _seq=rejected.index.to_numpy(), _cross=0)
            derived = {h: r for h, r in helios.items() if h not in self.heliostats}
            yield _Chunk(kept, rejected, derived)
        checks.finish()


def _merge_sources(sources: list[_Source], on_rejected) -> Iterator[tuple[list[pd.DataFrame], dict]]:
    """Kept rows of all sources merged by heliostat: yields (parts in source order, heliostat
    rows) where the parts hold every kept row of a range of heliostats and the heliostat rows are
    the first source's (as :func:`ingest` always did). Rejected chunks go to ``on_rejected``."""
    iters = [s.chunks() for s in sources]
    buffers: list[pd.DataFrame | None] = [None] * len(sources)
    done = [False] * len(sources)
    derived: list[dict] = [{} for _ in sources]

    def pull(i: int) -> None:
        chunk = next(iters[i], None)
        if chunk is None:
            done[i] = True
            return
        on_rejected(chunk.rejected)
        derived[i].update(chunk.derived)
        buffers[i] = chunk.kept if buffers[i] is None or buffers[i].empty else pd.concat(
            [buffers[i], chunk.kept])

    while True:
        for i in range(len(sources)):
            while not done[i] and (buffers[i] is None or buffers[i].empty):
                pull(i)
        growing = [i for i in range(len(sources)) if not done[i]]
        live = [i for i in range(len(sources)) if buffers[i] is not None and not buffers[i].empty]
        if not live:
            return
        # rows of a heliostat below the smallest last heliostat of a source still read are complete
        cutoff = min(buffers[i]["heliostat_id"].max() for i in growing) if growing else None
        parts = []
        for i in live:
            take = (buffers[i]["heliostat_id"] < cutoff if cutoff is not None
                    else pd.Series(True, index=buffers[i].index))
            if take.any():
                parts.append(buffers[i].loc[take.to_numpy()])
                buffers[i] = buffers[i].loc[~take.to_numpy()]
        if not parts:
            for i in growing:
                if buffers[i]["heliostat_id"].max() == cutoff:
                    pull(i)
            continue
        ids = set().union(*(p["heliostat_id"].unique() for p in parts))
        rows = {}
        for hid in ids:
            for i, s in enumerate(sources):
                row = s.heliostats.get(hid) or derived[i].get(hid)
                if row is not None:
                    rows[hid] = row
                    break
            for d in derived:
                d.pop(hid, None)
        yield parts, rows


def _rejected_order(df: pd.DataFrame) -> pd.Series:
    """Sort key of rejected rows: by source file and row, then (as ingest concatenated them)
    validation rejections before cross-source duplicates, by source and row."""
    return pd.Series([f"{f}\0{r:020d}\0{c}\0{s:06d}\0{q:020d}" for f, r, c, s, q in zip(
        df["source_file"], df["source_row"].astype("int64"), df["_cross"], df["_src"], df["_seq"])],
        index=df.index, dtype=object)


class _IngestRun:
    """The ingest stage over all sources, handing out its results chunk by chunk."""

    def __init__(self, sources: Sequence[Path], opts: IngestOptions, batch_rows: int | None,
                 spill_dir: Path | None):
        self.opts = opts
        self.sources = [_Source(i, p, o, batch_rows, spill_dir)
                        for i, (p, o) in enumerate(expand_sources(sources, opts))]
        env: dict[str, bool] = {}
        for s in self.sources:  # first appearance order, as pandas concatenated the sources
            for name, integer in s.env.items():
                env[name] = env.get(name, True) and integer
        for name in env:  # a source without the column gives it missing values: float
            env[name] = env[name] and all(name in s.env for s in self.sources)
        self.env_integer = env
        self.columns = MEASUREMENTS.column_names() + list(env) + (["qa_env_blanked"] if env else [])
        self.invalid_id_example: str | None = None  # detail of the first invalid_heliostat_id row

    def extra_types(self) -> dict:
        types = {"qa_sun_spa_diff_deg": pa.float64(), "qa_sun_mismatch": pa.bool_(),
                 "qa_env_blanked": pa.string()}
        types.update({n: pa.int64() if i else pa.float64() for n, i in self.env_integer.items()})
        return {n: types[n] for n in self.columns if n not in MEASUREMENTS.column_names()}

    def _complete(self, df: pd.DataFrame) -> pd.DataFrame:
        """``df`` with every env column of the run, in the dtype of the whole table."""
        df = df.reindex(columns=self.columns + ["_src", "_seq"])
        for name, integer in self.env_integer.items():
            if not integer:
                df[name] = df[name].astype(float)
        if self.env_integer:  # a source without env columns has nothing blanked
            df["qa_env_blanked"] = df["qa_env_blanked"].fillna("")
        return df

    def execute(self, on_measurements, on_heliostats, on_rejected) -> dict:
        """Validate every source; hand over measurements (with ``_src``/``_seq``), heliostat rows
        and rejected rows (with ``_src``/``_seq``/``_cross``) chunk by chunk; return the summary."""
        counts: dict[str, int] = {}
        reasons: dict[str, int] = {}
        default_geometry: list[str] = []
        n_kept = n_rejected = mismatch = 0

        def rejected(df: pd.DataFrame) -> None:
            nonlocal n_rejected
            n_rejected += len(df)
            for reason, n in df["reason"].value_counts().items():
                reasons[reason] = reasons.get(reason, 0) + int(n)
            bad_id = df["reason"] == "invalid_heliostat_id"
            if self.invalid_id_example is None and bad_id.any():
                self.invalid_id_example = str(df.loc[bad_id, "detail"].iloc[0])
            if len(df):
                on_rejected(df)

        for parts, rows in _merge_sources(self.sources, rejected):
            group = self._complete(pd.concat(parts))
            # duplicates across sources: first source wins
            key = group["heliostat_id"].astype(str) + "\0" + group["measurement_id"].astype(str)
            dup = key.duplicated(keep="first").to_numpy()
            if dup.any():
                extra = group.loc[dup]
                rejected(pd.DataFrame({
                    "source_file": extra["source_file"], "source_row": extra["source_row"],
                    "heliostat_id": extra["heliostat_id"], "measurement_id": extra["measurement_id"],
                    "reason": "duplicate_measurement_id",
                    "detail": "measurement id already ingested from an earlier source",
                    "raw": extra.drop(columns=["timestamp", "_src", "_seq"]).to_json(
                        orient="records", lines=True).splitlines(),
                    "_src": extra["_src"], "_seq": extra["_seq"], "_cross": 1}))
                group = group.loc[~dup]
            n = group.groupby("heliostat_id").size()
            helio = pd.DataFrame([{**rows[hid], "n_measurements": int(k)} for hid, k in sorted(n.items())],
                                 columns=HELIOSTATS.column_names())
            for col in (c.name for c in HELIOSTATS.columns if c.dtype == "bool"):
                helio[col] = helio[col].astype(bool)
            counts.update({h: int(k) for h, k in n.items()})
            default_geometry += [h for h in n.index if rows[h]["properties_source"] == "default-juelich"]
            n_kept += len(group)
            mismatch += int(group["qa_sun_mismatch"].sum())
            on_measurements(group)
            on_heliostats(helio)
        rows_read = sum(s.rows for s in self.sources)
        info = {
            "sources": {str(s.path): s.kind for s in self.sources},
            "rows_read": rows_read,
            "kept": n_kept,
            "rejected": n_rejected,
            "rejected_by_reason": dict(sorted(reasons.items())),
            "heliostats": dict(sorted(counts.items())),
            "heliostats_with_default_geometry": sorted(default_geometry),
            "sun_mismatch_rows": mismatch,
            "ignored_columns": {str(s.path): s.ignored for s in self.sources if s.ignored},
            "env_columns": sorted(self.env_integer),
        }
        if rows_read != n_kept + n_rejected:  # pragma: no cover - an invariant
            raise RuntimeError(f"ingest lost rows: read {rows_read}, kept {n_kept}, "
                               f"rejected {n_rejected}")
        return info


def _sources(sources: Iterable[str | os.PathLike]) -> list[Path]:
    sources = [Path(s) for s in sources]
    if not sources:
        raise InputError("no SOURCE given; pass a PAINT folder or a CSV/Parquet log")
    return sources


def _refuse_workdir_inside(sources: Sequence[Path], workdir: Path) -> None:
    """A work directory inside a source folder would be read as part of the source while ingest
    writes it (and the source would change under the run): refused, one line."""
    where = workdir.resolve()
    for src in sources:
        if src.is_dir():
            folder = src.resolve()
            if where == folder or folder in where.parents:
                raise InputError(f"the work directory {workdir} is inside the source folder {src}: "
                                 "ingest would read the files it writes there; use a --workdir "
                                 f"outside {src}")


def ingest(sources: Iterable[str | os.PathLike], options: IngestOptions | None = None):
    """Read every source and return (measurements, heliostats, rejected, info) DataFrames.

    Everything is held in memory (see :func:`run_ingest` for the streaming stage). Raises
    :class:`InputError` when a source cannot be read at all; row-level problems become rows of
    ``rejected`` with a reason from :data:`~heliocal.pipeline.artifacts.schemas.REJECTION_REASONS`.
    Rows come in source order (the artifacts sort them).
    """
    opts = (options or IngestOptions()).validate()
    run = _IngestRun(_sources(sources), opts, None, None)
    kept, helio, rejected = [], [], []
    info = run.execute(kept.append, helio.append, rejected.append)
    measurements = (pd.concat(kept) if kept else run._complete(pd.DataFrame()))
    measurements = measurements.sort_values(["_src", "_seq"], kind="mergesort")
    measurements = measurements.drop(columns=["_src", "_seq"]).reset_index(drop=True)
    helio = pd.concat(helio, ignore_index=True) if helio else pd.DataFrame(columns=HELIOSTATS.column_names())
    rej_cols = REJECTED.column_names()
    if rejected:
        rej = pd.concat(rejected).sort_values(["_cross", "_src", "_seq"], kind="mergesort")
        rej = rej[rej_cols].reset_index(drop=True)
    else:
        rej = pd.DataFrame(columns=rej_cols)
    return measurements, helio, rej, info


class _SpillFolder(os.PathLike):
    """A hidden folder in the workdir for sorted runs, made when the first run is written and
    removed (with its runs) when the stage ends, also on an error; usable as the folder of a
    :class:`SortedSpill`. While it lives, the stage holds an ``flock`` on its owner file, so that
    the next stage run removes the folder of a killed ingest, and only that
    (:func:`heliocal.pipeline.artifacts.transaction.recover`)."""

    def __init__(self, workdir: Path):
        self.workdir = workdir
        self.path: Path | None = None
        self._owner = None

    def __fspath__(self) -> str:
        if self.path is None:
            self.path = Path(tempfile.mkdtemp(prefix=SPILL_PREFIX, dir=self.workdir))
            self._owner = open(self.path / OWNER_FILENAME, "a+b")
            fcntl.flock(self._owner.fileno(), fcntl.LOCK_EX)
        return str(self.path)

    def __truediv__(self, name: str) -> Path:
        return Path(self) / name

    def __enter__(self) -> "_SpillFolder":
        return self

    def __exit__(self, *exc) -> None:
        if self.path is not None:
            shutil.rmtree(self.path, ignore_errors=True)
        if self._owner is not None:
            self._owner.close()


class _RejectedSink:
    """Rejected rows in memory up to ``batch_rows``, beyond that sorted runs in the spill folder;
    :meth:`chunks` yields them in the order of rejected.parquet."""

    _KEY = "__heliocal_order"

    def __init__(self, spill_dir: Path, batch_rows: int):
        self.batch_rows = batch_rows
        self.held: list[pd.DataFrame] = []
        self.held_rows = 0
        self.spill = SortedSpill(spill_dir, "rejected", self._KEY)  # a _SpillFolder

    def _table(self, frames: list[pd.DataFrame]) -> pa.Table:
        df = pd.concat(frames)
        key = _rejected_order(df).to_numpy()
        order = np.argsort(key, kind="stable")  # the order to_table's sort keeps
        table = to_table(df.iloc[order][REJECTED.column_names()], REJECTED)
        return table.append_column(self._KEY, pa.array(key[order].tolist(), pa.string()))

    def add(self, df: pd.DataFrame) -> None:
        self.held.append(df)
        self.held_rows += len(df)
        if self.held_rows >= self.batch_rows:
            self.spill.add(self._table(self.held))
            self.held, self.held_rows = [], 0

    @property
    def spilled(self) -> bool:
        return bool(self.spill.runs)

    def chunks(self) -> Iterator[pd.DataFrame]:
        if self.held and self.spill.runs:
            self.spill.add(self._table(self.held))
            self.held = []
        if self.held:
            yield from (self._table(self.held).sort_by(self._KEY).drop_columns([self._KEY])
                        .to_pandas(),)
            return
        for table in self.spill.merged(self.batch_rows):
            yield table.drop_columns([self._KEY]).to_pandas()


@locks_workdir("ingest")
@stage_transaction("ingest")
@restores_process_state
def run_ingest(sources: Sequence[str | os.PathLike], workdir: str | os.PathLike,
               options: IngestOptions | None = None, batch_rows: int = DEFAULT_BATCH_ROWS,
               append: bool = False) -> dict:
    """The ``ingest`` stage: read ``sources``, write the three artifacts into ``workdir``.

    Logs are read ``batch_rows`` rows at a time; a log longer than that is spilled, sorted by
    heliostat, to a hidden folder in ``workdir`` and validated heliostat range by heliostat range,
    so memory is bounded by the batch (and the largest heliostat), not by the field. The
    artifacts are written chunk by chunk to temporary files that replace the previous ones only
    when the whole stage succeeded. Returns the summary (rows read, kept, rejected per reason,
    heliostats).

    With ``append`` the new sources' rows are added to the work directory's measurements
    (:mod:`.ingest_append`; rows already ingested are rejected) instead of replacing them.
    """
    opts = (options or IngestOptions()).validate()
    batch_rows = check_int(batch_rows, "batch_rows", "ingest", 1)
    sources = _sources(sources)
    workdir = Path(workdir)
    _refuse_workdir_inside(sources, workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    inputs = {f"source:{s}": s for s in sources}
    if opts.tower:
        inputs["tower"] = opts.tower
    if opts.properties:
        inputs["properties"] = opts.properties
    resolved = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(opts).items()}
    resolved["sources"] = [str(s) for s in sources]
    prov = dict(stage="ingest", options=resolved, inputs=inputs)
    if append:
        info = _append(sources, workdir, opts, batch_rows, prov)
    else:
        info = _replace(sources, workdir, opts, batch_rows, prov)
    info["workdir"] = str(workdir)
    info["artifacts"] = [str(artifact_path(workdir, s)) for s in (MEASUREMENTS, HELIOSTATS, REJECTED)]
    _log_summary(info, opts)
    return info


def _append(sources: list[Path], workdir: Path, opts: IngestOptions, batch_rows: int,
            prov: dict) -> dict:
    """``ingest --append``: the new sources validated in memory (a day's rows), merged with the
    committed artifacts (:func:`.ingest_append.merge_new_rows`) and written whole. The previous
    runs' sources stay recorded as inputs beside the new ones."""
    txn = current_transaction(workdir, "ingest")
    previous = previous_tables(workdir)
    if txn is not None and txn.previous is not None:
        for label, rec in txn.previous.inputs.items():
            txn.inputs.setdefault(label, rec)
    prov = {**prov, "options": {**prov["options"], "append": True}}
    with _SpillFolder(workdir) as spill:
        run = _IngestRun(sources, opts, batch_rows, spill)
        kept, helio, rejected = [], [], []
        info = run.execute(kept.append, helio.append, rejected.append)
    kept_df = (pd.concat(kept) if kept else run._complete(pd.DataFrame())).drop(
        columns=["_src", "_seq"])
    helio_df = (pd.concat(helio, ignore_index=True) if helio
                else pd.DataFrame(columns=HELIOSTATS.column_names()))
    rej_df = (pd.concat(rejected)[REJECTED.column_names()] if rejected
              else pd.DataFrame(columns=REJECTED.column_names()))
    result = merge_new_rows(previous, kept_df, helio_df, rej_df)
    write_appended(result, workdir, prov)
    for reason, n in result.duplicates["reason"].value_counts().items():
        info["rejected_by_reason"][reason] = info["rejected_by_reason"].get(reason, 0) + int(n)
    info["rejected_by_reason"] = dict(sorted(info["rejected_by_reason"].items()))
    info["kept"] -= len(result.duplicates)
    info["rejected"] += len(result.duplicates)
    info["heliostats"] = {str(h): int(n) for h, n in
                          result.added.groupby("heliostat_id").size().sort_index().items()}
    info["appended"] = {"added_rows": len(result.added),
                        "measurements_total": len(result.measurements),
                        "heliostats_total": len(result.heliostats)}
    return info


def _replace(sources: list[Path], workdir: Path, opts: IngestOptions, batch_rows: int,
             prov: dict) -> dict:
    """``ingest``: the sources streamed into new artifacts that replace the previous ones."""
    with _SpillFolder(workdir) as spill, contextlib.ExitStack() as stack:
        run = _IngestRun(sources, opts, batch_rows, spill)
        rejected = _RejectedSink(spill, batch_rows)
        helio: list[pd.DataFrame] = []
        # measurements.parquet is written while the sources are validated; it replaces the
        # previous one last, after rejected.parquet and heliostats.parquet
        measurements = stack.enter_context(artifact_writer(
            workdir, MEASUREMENTS, extra=run.extra_types(),
            row_group_size=MEASUREMENTS_ROW_GROUP_ROWS, **prov))
        info = run.execute(lambda df: measurements.write(df.drop(columns=["_src", "_seq"])),
                           helio.append, rejected.add)
        if info["kept"] == 0:
            reasons = ", ".join(f"{k}: {v}" for k, v in info["rejected_by_reason"].items())
            how = (f": {run.invalid_id_example}" if run.invalid_id_example
                   else "; see the reasons and fix the source")
            raise InputError(f"no measurement of {', '.join(map(str, sources))} could be kept "
                             f"({reasons}){how}")
        if rejected.spilled:
            with artifact_writer(workdir, REJECTED, **prov) as writer:
                for chunk in rejected.chunks():
                    writer.write(chunk)
        else:
            write_artifact(next(rejected.chunks(), pd.DataFrame(columns=REJECTED.column_names())),
                           workdir, REJECTED, **prov)
        write_artifact(pd.concat(helio, ignore_index=True), workdir, HELIOSTATS, **prov)
    return info


def _log_summary(info: dict, opts: IngestOptions) -> None:
    """The run's notes on stderr: rejections per reason, sun mismatches, default geometries,
    unused columns, invalid ids."""
    for reason, n in info["rejected_by_reason"].items():
        log.info("rejected %d rows: %s (%s)", n, reason, REJECTION_REASONS.get(reason, ""))
    if info["sun_mismatch_rows"]:
        log.warning("%d kept rows have logged sun angles more than %g deg from NREL SPA "
                    "(column qa_sun_mismatch)", info["sun_mismatch_rows"], opts.sun_tolerance_deg)
    if info["heliostats_with_default_geometry"]:
        log.warning("%d heliostats have no properties file and start from the default Jülich "
                    "geometry (pass --properties to give theirs)",
                    len(info["heliostats_with_default_geometry"]))
    for src, cols in info["ignored_columns"].items():
        log.info("%s: columns not used: %s", src, ", ".join(cols))
    if info["rejected_by_reason"].get("invalid_heliostat_id"):
        log.warning("%s", invalid_id_message(info["rejected_by_reason"]["invalid_heliostat_id"]))
