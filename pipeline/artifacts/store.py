"""Artifacts: declared schemas, atomic writes, provenance and freshness checks.

Every stage reads its inputs from a work directory and writes its outputs there under fixed
names (the *workdir contract*). Each Parquet artifact has a declared :class:`ArtifactSchema`
(declared once, in the module of the stage that writes it) that is checked on write and on read.

Writes are transactional (:mod:`heliocal.pipeline.artifacts.transaction`): inside a stage run every
artifact is written to the run's staging folder and all of them replace the previous ones at one
atomic step, the rename of the stage's manifest ``<stage>.manifest.json``. Reads go through that
manifest: :func:`read_artifact` reads only a file the last complete run of its producer listed,
and only if its bytes still have the SHA-256 the manifest records.

Each artifact carries its provenance in the Parquet key-value metadata under the key
``heliocal``: schema version, artifact name, stage, heliocal version and git revision, the
command line and its resolved options, the seed, and the content fingerprints of the inputs the
run *read* (:func:`table_fingerprint`; a source file or folder: its SHA-256). A stage that reads an
artifact checks that it was made from the current version of *its* inputs (:func:`check_fresh`),
so a stale artifact is refused with the stage to rerun.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from .. import __version__
from ..errors import SchemaError, StageInputError, UnsafePathError
from .manifests import CommittedWorkdir, committed_entry, current_transaction, read_committed
from .paths import artifact_path, file_sha256, open_regular
from .provenance import Fingerprint, command_line, git_revision, jsonable, table_fingerprint
from .table import ArtifactSchema, to_table
from .transaction import transaction

__all__ = [
    "SCHEMA_VERSION",
    "committed_fingerprint",
    "parse_provenance",
    "PROVENANCE_KEY",
    "recorded_inputs",
    "write_artifact",
    "artifact_writer",
    "ArtifactWriter",
    "read_artifact",
    "kept_reads",
    "artifact_columns",
    "read_provenance",
    "check_fresh",
    "artifact_present",
    "previous_run_matches",
    "merge_with_previous",
]

log = logging.getLogger("heliocal.artifacts")


#: Version of the artifact layout. Bump when a column changes meaning or a required one is added.
SCHEMA_VERSION = 2


#: Key of the Parquet footer metadata under which every artifact keeps its provenance JSON.
PROVENANCE_KEY = _META_KEY = b"heliocal"




def _provenance(schema: ArtifactSchema, stage: str, options: Mapping | None, seed: int | None,
                inputs: Mapping[str, str | None]) -> dict:
    """The ``heliocal`` metadata of an artifact; ``inputs`` maps label -> fingerprint (hex)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "artifact": schema.name,
        "stage": stage,
        "heliocal_version": __version__,
        "git_revision": git_revision(),
        "command": command_line(stage),
        "options": jsonable(dict(options or {})),
        "seed": seed,
        "inputs": dict(sorted(inputs.items())),
    }


def _record_inputs(txn, workdir: Path, inputs: Mapping[str, str | os.PathLike] | None) -> None:
    """Record inputs named explicitly by a writer (``ingest``'s sources, scripts and tests) in the
    transaction: an artifact committed in ``workdir`` by its fingerprint (read and verified now),
    any other file or folder by its SHA-256 (hashed once per transaction)."""
    for label, p in (inputs or {}).items():
        p = Path(p)
        if label in txn.inputs and txn.inputs[label].get("path") in (str(p), None):
            continue
        try:
            rel = p.absolute().relative_to(workdir.absolute()).as_posix()
        except ValueError:
            rel = None
        found = committed_entry(workdir, rel) if rel else None
        if found is not None:
            read_committed(workdir, found[0].stage, rel, label=label)
        else:
            txn.add_source(label, p, file_sha256(p) if p.exists() else None)


@contextlib.contextmanager
def _artifact_transaction(workdir: Path, schema: ArtifactSchema, options, seed):
    """The active transaction of ``schema``'s producer in ``workdir``, or a one-file transaction
    that keeps the producer's other committed files (a write outside a stage run)."""
    active = current_transaction(workdir, schema.producer)
    with transaction(workdir, schema.producer) as txn:
        if active is None:
            txn.carry_over(txn.previous_files())
            if txn.previous is not None:
                for label, rec in txn.previous.inputs.items():
                    txn.inputs.setdefault(label, rec)
        if txn.options is None:
            txn.options, txn.seed = options, seed
        yield txn


def write_artifact(df: pd.DataFrame, workdir: str | os.PathLike, schema: ArtifactSchema, *,
                   stage: str, options: Mapping | None = None, seed: int | None = None,
                   inputs: Mapping[str, str | os.PathLike] | None = None,
                   row_group_size: int | None = None) -> Path:
    """Check ``df`` against ``schema`` and write it as ``workdir/schema.filename``.

    Inside a stage run (:func:`heliocal.pipeline.artifacts.transaction.transaction`) the file is staged and
    becomes visible with the run's other outputs when the run commits. Outside one, the write is
    its own transaction of ``schema.producer`` (the producer's other committed files are kept).

    Parameters
    ----------
    df : the table; columns are cast to the declared types and rows sorted by ``schema.sort_by``.
    workdir : the work directory.
    stage : the subcommand writing it (recorded in the provenance).
    options : resolved options of the run (recorded).
    seed : the seed of the run, if it has random steps.
    inputs : label -> path of inputs that were not read with :func:`read_artifact` (ingest's
        sources). Artifacts read with :func:`read_artifact` in the same run are recorded
        without being named here, with the fingerprint of what was read.
    row_group_size : rows per Parquet row group (default: pyarrow's).

    Returns
    -------
    The artifact's path.
    """
    workdir = Path(workdir)
    table = to_table(df, schema)
    with _artifact_transaction(workdir, schema, options, seed) as txn:
        _record_inputs(txn, workdir, inputs)
        meta = dict(table.schema.metadata or {})
        meta[_META_KEY] = json.dumps(_provenance(schema, stage, options, seed,
                                                 txn.input_fingerprints()), sort_keys=True).encode()
        table = table.replace_schema_metadata(meta)
        tmp = txn.staging_path(schema.filename)
        pq.write_table(table, tmp, row_group_size=row_group_size, compression="zstd")
        txn.add_file(schema.filename, fingerprint=table_fingerprint(table, schema),
                     artifact=schema.name)
    return artifact_path(workdir, schema)


class ArtifactWriter:
    """Appends DataFrame chunks to one artifact being written (see :func:`artifact_writer`)."""

    def __init__(self, writer: pq.ParquetWriter, schema: ArtifactSchema, arrow_schema: pa.Schema,
                 row_group_size: int | None):
        self._writer = writer
        self.schema = schema
        self.arrow_schema = arrow_schema
        self.row_group_size = row_group_size
        self.rows = 0
        self.fingerprint = Fingerprint(arrow_schema, schema)

    def write(self, df: pd.DataFrame) -> None:
        """Check ``df`` against the schema, sort it by ``schema.sort_by`` and append it.

        Chunks must come in ``sort_by`` order (each one sorted within itself here), so the file
        is sorted as :func:`write_artifact` would sort the whole table.
        """
        table = to_table(df, self.schema)
        extra = [f.name for f in self.arrow_schema][len(self.schema.columns):]
        unexpected = [n for n in table.column_names[len(self.schema.columns):] if n not in extra]
        if unexpected:
            raise SchemaError(
                f"cannot write {self.schema.filename}: columns {unexpected} were not declared when "
                "the file was opened (this is a bug in heliocal; please report it)")
        for name in extra:  # a chunk without an extra column gets it empty
            if name not in table.column_names:
                table = table.append_column(name, pa.nulls(table.num_rows))
        try:
            table = table.select(self.arrow_schema.names).cast(self.arrow_schema)
        except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as exc:
            raise SchemaError(
                f"cannot write {self.schema.filename}: a chunk does not match the columns declared "
                f"when the file was opened ({exc}); this is a bug in heliocal, please report it"
            ) from exc
        self._writer.write_table(table, row_group_size=self.row_group_size)
        self.fingerprint.add(table)
        self.rows += table.num_rows


@contextlib.contextmanager
def artifact_writer(workdir: str | os.PathLike, schema: ArtifactSchema, *, stage: str,
                    extra: Mapping[str, pa.DataType] | None = None,
                    options: Mapping | None = None, seed: int | None = None,
                    inputs: Mapping[str, str | os.PathLike] | None = None,
                    row_group_size: int | None = None) -> Iterator[ArtifactWriter]:
    """Write ``schema``'s artifact chunk by chunk, with provenance metadata.

    The streaming twin of :func:`write_artifact`: yields an :class:`ArtifactWriter` whose
    ``write(df)`` checks and appends one chunk. The file is staged in the run's transaction and
    becomes ``workdir/schema.filename`` when the run commits; on an exception nothing replaces the
    previous artifact.

    Parameters
    ----------
    extra : name -> Arrow type of the extra columns (``env_*``, ``qa_*``) the chunks may hold; a
        chunk without one of them gets it empty.
    inputs : see :func:`write_artifact` (recorded when the writer is opened, i.e. before the
        chunks are read from the sources).
    row_group_size : rows per Parquet row group at most (a chunk never shares a row group with
        the next one).
    """
    workdir = Path(workdir)
    arrow_schema = schema.arrow_schema(extra)
    with _artifact_transaction(workdir, schema, options, seed) as txn:
        _record_inputs(txn, workdir, inputs)
        meta = {_META_KEY: json.dumps(_provenance(schema, stage, options, seed,
                                                  txn.input_fingerprints()),
                                      sort_keys=True).encode()}
        arrow_schema = arrow_schema.with_metadata(meta)
        tmp = txn.staging_path(schema.filename)
        with pq.ParquetWriter(tmp, arrow_schema, compression="zstd") as writer:
            out = ArtifactWriter(writer, schema, arrow_schema, row_group_size)
            yield out
        txn.add_file(schema.filename, fingerprint=out.fingerprint.hexdigest(),
                     artifact=schema.name)


def read_provenance(path: str | os.PathLike) -> dict:
    """The provenance dictionary stored in a heliocal Parquet artifact."""
    path = Path(path)
    try:  # the footer only, of a regular file opened without following a link
        with open(open_regular(path), "rb", closefd=True) as fh:
            meta = pq.read_schema(fh).metadata or {}
    except UnsafePathError as exc:
        raise SchemaError(f"{exc}") from None
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path} is not a readable Parquet file ({exc}); rerun the stage "
                          "that writes it") from exc
    return _provenance_of(meta, path)


def _provenance_of(meta: Mapping, path: Path) -> dict:
    if _META_KEY not in meta:
        raise SchemaError(f"{path} was not written by heliocal (no provenance metadata); rerun "
                          "the stage that writes it")
    return parse_provenance(meta[_META_KEY], path)


def parse_provenance(text, path) -> dict:
    """The provenance dict of an artifact from its metadata value ``text`` (a JSON object, stored
    under :data:`PROVENANCE_KEY`), else a :class:`SchemaError` naming ``path``."""
    try:
        prov = json.loads(text)
        if not isinstance(prov, dict):
            raise ValueError("not a JSON object")
    except ValueError as exc:
        raise SchemaError(f"{path} has unreadable heliocal provenance metadata ({exc}); rerun the "
                          "stage that writes it") from exc
    return prov


def _rerun(schema: ArtifactSchema, workdir: Path) -> str:
    args = " SOURCE..." if schema.producer == "ingest" else ""
    return f"`heliocal {schema.producer}{args} --workdir {workdir}`"


def _missing_message(path: Path, schema: ArtifactSchema) -> str:
    return f"{path} is missing: run {_rerun(schema, path.parent)} first"


#: The tables :func:`read_artifact` keeps inside :func:`kept_reads` (``None`` outside it):
#: request (artifact, SHA-256 of its committed bytes, columns, heliostats) -> frame, the most
#: recently used last.
_KEPT: OrderedDict | None = None

#: How much :func:`kept_reads` keeps: the frames' memory (shallow: strings read once per
#: distinct value share their objects), the least recently used dropped first.
KEPT_BYTES = 1 << 30


@contextlib.contextmanager
def kept_reads() -> Iterator[None]:
    """Inside the block, :func:`read_artifact` decodes a request it has answered before only
    once: the same committed bytes (by their SHA-256, verified on every read as always) with the
    same columns and heliostats give a shallow copy of the kept frame, which pandas'
    copy-on-write keeps apart from it. For ``heliocal update``, whose stages run in one process
    and read the same measurements, split and predictions in turn. At most :data:`KEPT_BYTES`
    are kept, and none of an artifact's earlier bytes once it has been read anew. Nested blocks
    share the outermost one's tables."""
    global _KEPT
    outer = _KEPT
    if outer is None:
        _KEPT = OrderedDict()
    try:
        yield
    finally:
        if outer is None:
            _KEPT = None


def _kept(key: tuple) -> pd.DataFrame | None:
    if _KEPT is None or key not in _KEPT:
        return None
    _KEPT.move_to_end(key)
    return _KEPT[key][0].copy(deep=False)


def _keep(key: tuple, df: pd.DataFrame) -> pd.DataFrame:
    """``df`` kept under ``key`` (inside :func:`kept_reads`); the caller gets a shallow copy."""
    if _KEPT is None:
        return df
    for old in [k for k in _KEPT if k[0] == key[0] and k[1] != key[1]]:
        del _KEPT[old]                   # the artifact's earlier bytes: not read again
    _KEPT[key] = (df, int(df.memory_usage(index=True, deep=False).sum()))
    while sum(size for _, size in _KEPT.values()) > KEPT_BYTES and len(_KEPT) > 1:
        _KEPT.popitem(last=False)
    return df.copy(deep=False)


def read_artifact(workdir: str | os.PathLike, schema: ArtifactSchema, *,
                  columns: Sequence[str] | None = None,
                  heliostats: Iterable[str] | None = None) -> pd.DataFrame:
    """Read and check ``schema``'s artifact from ``workdir``.

    Only the file the last complete run of ``schema.producer`` committed is read, and only if its
    bytes still have the SHA-256 recorded in the producer's manifest. Inside a stage run the read is
    recorded as an input of the run (with the file's content fingerprint).

    Parameters
    ----------
    workdir : the work directory, or its :class:`CommittedWorkdir` (its manifests and bytes are
        then read once for all the calls that share it).
    columns : read only these columns (default all).
    heliostats : read only rows of these heliostat ids (uses Parquet row-group statistics, so a
        large field is not decoded whole).

    Raises
    ------
    StageInputError : the file is missing or not committed (the message names the stage to run).
    SchemaError : it was changed after its run, was written by an incompatible schema version, or
        lacks declared columns.
    """
    wd = CommittedWorkdir.of(workdir)
    workdir = wd.root
    path = artifact_path(workdir, schema)
    committed = wd.read(schema.producer, schema.filename, hint=_rerun(schema, workdir),
                        missing=_missing_message(path, schema), label=schema.name)
    try:
        file_schema = pq.read_schema(pa.BufferReader(committed.data))
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path} is not a readable Parquet file ({' '.join(str(exc).split())}); "
                          f"rerun {_rerun(schema, workdir)}") from exc
    try:
        prov = _provenance_of(file_schema.metadata or {}, path)
    except SchemaError as exc:
        raise SchemaError(f"{exc}: {_rerun(schema, workdir)}") from exc
    if prov.get("artifact") != schema.name:
        raise SchemaError(f"{path} holds a {prov.get('artifact')!r} artifact, not "
                          f"{schema.name!r}; rerun {_rerun(schema, workdir)}")
    if prov.get("schema_version") != SCHEMA_VERSION:
        raise SchemaError(
            f"{path} was written by heliocal {prov.get('heliocal_version')} with schema version "
            f"{prov.get('schema_version')}, but this heliocal reads version {SCHEMA_VERSION}: "
            f"rerun `heliocal {schema.producer} --workdir {path.parent}`")
    absent = [c for c in schema.column_names() if c not in file_schema.names]
    if absent:
        raise SchemaError(f"{path} lacks columns {absent}: rerun `heliocal {schema.producer} "
                          f"--workdir {path.parent}`")
    if heliostats is not None:
        heliostats = list(heliostats)
    key = (schema.name, committed.entry.get("sha256"), tuple(columns) if columns else None,
           None if heliostats is None else tuple(heliostats))
    kept = _kept(key)
    if kept is not None:
        return kept
    filters = None
    if heliostats is not None:
        filters = [("heliostat_id", "in", heliostats)]
    try:
        table = pq.read_table(pa.BufferReader(committed.data),
                              columns=list(columns) if columns else None, filters=filters)
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path} is not a readable Parquet file ({' '.join(str(exc).split())}); "
                          f"rerun {_rerun(schema, workdir)}") from exc
    df = table.to_pandas()
    for c in schema.columns:
        if c.name in df.columns and c.dtype == "string":
            df[c.name] = pd.Series(_python_strings(table.column(c.name)), index=df.index,
                                   dtype=object)
    return _keep(key, df)


def _python_strings(column: pa.ChunkedArray) -> np.ndarray:
    """An Arrow string column as an object array of Python strings, missing values NaN (what
    pandas' ``astype(object)`` of it gives), each distinct string converted once: a field's
    string columns repeat a few values over many rows (heliostat ids, splits, models), and
    making a Python object per row took most of a field-scale read."""
    encoded = column.combine_chunks().dictionary_encode()
    distinct = np.empty(len(encoded.dictionary) + 1, dtype=object)
    distinct[:-1] = encoded.dictionary.to_pylist()
    distinct[-1] = np.nan
    return distinct[encoded.indices.fill_null(len(encoded.dictionary)).to_numpy()]


def artifact_columns(workdir, schema: ArtifactSchema) -> list[str]:
    """The column names of ``schema``'s committed artifact (declared and extra ones, such as
    ``env_*``), read through its manifest like :func:`read_artifact`."""
    wd = CommittedWorkdir.of(workdir)
    committed = wd.read(schema.producer, schema.filename, hint=_rerun(schema, wd.root),
                        missing=_missing_message(artifact_path(wd.root, schema), schema))
    try:
        return list(pq.read_schema(pa.BufferReader(committed.data)).names)
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{committed.path} is not a readable Parquet file "
                          f"({' '.join(str(exc).split())}); rerun {_rerun(schema, wd.root)}") from exc


def committed_fingerprint(workdir: str | os.PathLike, schema: ArtifactSchema) -> str | None:
    """The content fingerprint of ``schema``'s artifact as its producer's last run committed it
    (``None`` if it did not)."""
    return CommittedWorkdir.of(workdir).fingerprint(schema.producer, schema.filename)


def recorded_inputs(workdir: str | os.PathLike, schema: ArtifactSchema) -> dict:
    """label -> fingerprint of the inputs ``schema``'s committed artifact was made from.

    Raises
    ------
    StageInputError : the artifact is not committed.
    """
    wd = CommittedWorkdir.of(workdir)
    path = artifact_path(wd.root, schema)
    m = wd.manifest(schema.producer)
    if m is None or schema.filename not in m.files:
        if os.path.lexists(path):
            wd.read(schema.producer, schema.filename, hint=_rerun(schema, wd.root))
        raise StageInputError(_missing_message(path, schema))
    return m.input_fingerprints()


def check_fresh(workdir: str | os.PathLike, schema: ArtifactSchema,
                upstream: Mapping[str, ArtifactSchema]) -> None:
    """Raise :class:`StageInputError` if ``schema``'s artifact was made from older inputs.

    ``upstream`` maps the input labels the artifact's run recorded (the artifact names it read) to
    the schemas of those artifacts; each recorded content fingerprint must equal the fingerprint of
    the upstream artifact its producer committed last. Nothing is hashed: the manifests hold the
    fingerprints (and every read verifies the bytes against them).
    """
    wd = CommittedWorkdir.of(workdir)
    path = artifact_path(wd.root, schema)
    recorded = recorded_inputs(wd, schema)
    for label, up in upstream.items():
        current = committed_fingerprint(wd, up)
        up_path = artifact_path(wd.root, up)
        if current is None:
            if os.path.lexists(up_path):
                wd.read(up.producer, up.filename, hint=_rerun(up, wd.root))
            raise StageInputError(_missing_message(up_path, up))
        if label not in recorded:
            raise StageInputError(
                f"{path} was made without {up.filename}; rerun "
                f"`heliocal {schema.producer} --workdir {path.parent}` first")
        if recorded[label] != current:
            raise StageInputError(
                f"{path} is stale: {up.filename} changed after it was written; rerun "
                f"`heliocal {schema.producer} --workdir {path.parent}` first")


def previous_run_matches(workdir: str | os.PathLike, stage: str) -> bool:
    """True when the last committed run of ``stage`` read the same inputs (same labels, same
    fingerprints) as the active run of ``stage`` has read so far: only then may the active run keep
    outputs of the previous one (a partial ``--heliostat`` run)."""
    txn = current_transaction(workdir, stage)
    if txn is None or txn.previous is None:
        return False
    return txn.previous.input_fingerprints() == txn.input_fingerprints()


def merge_with_previous(workdir: str | os.PathLike, schema: ArtifactSchema, new: pd.DataFrame,
                        replaced: Callable[[pd.DataFrame], pd.Series]) -> pd.DataFrame:
    """``new`` plus the rows of the previous committed ``schema`` artifact that this run does not
    replace (``replaced(old)`` is False), for a partial run of the artifact's producer.

    The previous rows are kept only if the previous run read the same inputs as this one
    (:func:`previous_run_matches`); otherwise they were made from other data, and are dropped with
    a warning (a complete rerun of the stage makes them again).
    """
    txn = current_transaction(workdir, schema.producer)
    if txn is None or txn.previous is None or schema.filename not in txn.previous.files:
        return new
    if not previous_run_matches(workdir, schema.producer):
        log.warning("%s was made from other inputs than this run read: its rows of other "
                    "heliostats or modes are dropped (rerun `heliocal %s` without --heliostat "
                    "to make them again)", artifact_path(workdir, schema), schema.producer)
        return new
    try:
        old = read_artifact(workdir, schema)
    except (SchemaError, StageInputError) as exc:  # e.g. written by an older heliocal
        log.warning("the previous %s cannot be read, so only this run's rows are kept: %s",
                    schema.filename, exc)
        return new
    keep = ~replaced(old).to_numpy(bool)
    return pd.concat([old[keep], new], ignore_index=True)


def artifact_present(workdir: str | os.PathLike, schema: ArtifactSchema) -> bool:
    """Whether ``schema``'s artifact is there to be read: committed by its producer's last run, or
    at least a file of its name (which :func:`read_artifact` then refuses with the reason)."""
    return CommittedWorkdir.of(workdir).present(schema.producer, schema.filename)
