"""Artifacts: declared schemas, atomic writes, provenance and freshness checks.

Every stage reads its inputs from a work directory and writes its outputs there under fixed
names (the *workdir contract*). Each Parquet artifact has a declared :class:`ArtifactSchema`
(declared once, in the module of the stage that writes it) that is checked on write and on read.

Writes are transactional (:mod:`heliocal.pipeline.transaction`): inside a stage run every
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
import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping, Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from . import __version__
from .errors import SchemaError, StageInputError, UnsafePathError
from .transaction import (committed_entry, current_transaction, load_manifest, read_committed,
                          sha256_of_file, transaction)

__all__ = [
    "SCHEMA_VERSION",
    "committed_fingerprint",
    "parse_provenance",
    "recorded_inputs",
    "Column",
    "ArtifactSchema",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "write_artifact",
    "artifact_writer",
    "ArtifactWriter",
    "read_artifact",
    "read_provenance",
    "file_sha256",
    "table_fingerprint",
    "check_fresh",
    "artifact_present",
    "previous_run_matches",
    "merge_with_previous",
    "artifact_path",
    "git_revision",
    "safe_child",
    "safe_name",
    "MAX_NAME_BYTES",
]

log = logging.getLogger("heliocal.artifacts")

#: Version of the artifact layout. Bump when a column changes meaning or a required one is added.
SCHEMA_VERSION = 2
_META_KEY = b"heliocal"

_ARROW_TYPES = {
    "string": pa.string(),
    "float64": pa.float64(),
    "int64": pa.int64(),
    "bool": pa.bool_(),
    "timestamp": pa.timestamp("us", tz="UTC"),
}


@dataclass(frozen=True)
class Column:
    """One column of an artifact.

    Parameters
    ----------
    name : column name, with its unit as suffix where it has one (``_deg``, ``_m``, ``_mrad``).
    dtype : one of ``string``, ``float64``, ``int64``, ``bool``, ``timestamp`` (UTC).
    unit : unit in plain text (``deg``, ``m``, ``mrad``, ``1``, ``steps``) or ``""``.
    description : meaning, one sentence.
    nullable : whether missing values are allowed.
    """

    name: str
    dtype: str
    unit: str
    description: str
    nullable: bool = False


@dataclass(frozen=True)
class ArtifactSchema:
    """Declared layout of one Parquet artifact of the workdir contract.

    ``producer`` is the subcommand that writes it; it is named in "run ... first" messages.
    Columns whose names start with one of ``extra_prefixes`` may be added freely (for example
    ``env_*`` inputs of the fine model and ``qa_*`` flags). ``volatile`` columns measure the run,
    not its result (wall-clock seconds): they are left out of the content fingerprint, so a rerun
    that computes the same result does not make downstream artifacts stale.
    """

    name: str
    filename: str
    producer: str
    columns: tuple[Column, ...]
    extra_prefixes: tuple[str, ...] = ()
    sort_by: tuple[str, ...] = ()
    description: str = ""
    volatile: tuple[str, ...] = ()
    _by_name: dict = field(default_factory=dict, compare=False, repr=False)

    def column_names(self) -> list[str]:
        return [c.name for c in self.columns]

    def arrow_schema(self, extra: Mapping[str, pa.DataType] | None = None) -> pa.Schema:
        fields = [pa.field(c.name, _ARROW_TYPES[c.dtype], nullable=c.nullable) for c in self.columns]
        for name, typ in (extra or {}).items():
            fields.append(pa.field(name, typ, nullable=True))
        return pa.schema(fields)


def artifact_path(workdir: str | os.PathLike, schema: ArtifactSchema) -> Path:
    """Path of ``schema``'s artifact inside ``workdir``."""
    return Path(workdir) / schema.filename


#: Longest file name (bytes of its UTF-8 encoding) that common file systems accept (NAME_MAX).
MAX_NAME_BYTES = 255


def safe_name(name: str, where: str = "the work directory") -> str:
    """``name`` itself if it can be used as a plain file name (the rules of :func:`safe_child`,
    without a folder to resolve against: for names staged in a stage transaction), else
    :class:`~heliocal.pipeline.errors.UnsafePathError`."""
    why = _unsafe_name_reason(name)
    if why is not None:
        raise UnsafePathError(_unsafe_message(name, where, why))
    return name


def _unsafe_message(name, where, why: str) -> str:
    return (f"{name!r} cannot be used as a file name in {where}: {why}; names taken from the "
            "data must be plain file names (heliostat ids: letters, digits, '_', '-', '.', see "
            "docs/input_formats.md; rerun `heliocal ingest`, which rejects other ids)")


def safe_child(directory: str | os.PathLike, name: str) -> Path:
    """``directory / name`` for a file name that comes from the data (a heliostat id, say).

    Every writer and reader that puts a data value into a path goes through here, so that no
    value can reach a file outside its folder, whatever ingest let through. Refused, with
    :class:`~heliocal.pipeline.errors.UnsafePathError`: a non-string or empty name; ``.``, ``..``
    and any name starting with ``.`` (hidden: the prefix of heliocal's temporary files); ``/`` or
    ``\\`` anywhere (so no absolute path and no sub-folder); NUL and other control characters;
    names longer than :data:`MAX_NAME_BYTES` bytes in UTF-8; and a name whose resolved path
    (symbolic links followed) is not directly inside ``directory``.

    Returns the path unresolved (``Path(directory) / name``).
    """
    why = _unsafe_name_reason(name)
    if why is None:
        folder = Path(directory)
        path = folder / name
        if path.resolve().parent != folder.resolve():
            why = "it resolves outside the folder (a symbolic link?)"
    if why is not None:
        raise UnsafePathError(_unsafe_message(name, directory, why))
    return path


def _unsafe_name_reason(name) -> str | None:
    if not isinstance(name, str):
        return f"it is a {type(name).__name__}, not text"
    if not name:
        return "it is empty"
    if name in (".", ".."):
        return "it names the folder itself or its parent"
    if name.startswith("."):
        return "it starts with '.' (hidden)"
    if "/" in name or "\\" in name:
        return "it contains a path separator"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "it contains a control character"
    if len(name.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES:
        return f"it is longer than {MAX_NAME_BYTES} bytes"
    return None


# --------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it into place atomically.

    On any exception (or a kill) the temporary file is removed or left under a hidden
    ``.<name>.tmp-*`` name that no stage reads, and ``path`` keeps its previous content.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; artifacts are ordinary files
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


# --------------------------------------------------------------------------------------------
# provenance
# --------------------------------------------------------------------------------------------
def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, or of a folder's files (relative names and bytes, sorted)."""
    path = Path(path)
    h = hashlib.sha256()
    if path.is_dir():
        for p in sorted(q for q in path.rglob("*") if q.is_file()):
            h.update(str(p.relative_to(path)).encode())
            h.update(b"\0")
            h.update(sha256_of_file(p).encode())
    else:
        return sha256_of_file(path)
    return h.hexdigest()




_GIT_REV: str | None = None


def git_revision() -> str:
    """Git revision of the heliocal source tree (``unknown`` outside a checkout)."""
    global _GIT_REV
    if _GIT_REV is None:
        try:
            out = subprocess.run(
                ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                capture_output=True, text=True, timeout=5, check=False)
            _GIT_REV = out.stdout.strip() or "unknown"
            if _GIT_REV != "unknown":
                dirty = subprocess.run(
                    ["git", "status", "--porcelain", "--untracked-files=no"],
                    cwd=Path(__file__).resolve().parent, capture_output=True, text=True,
                    timeout=5, check=False).stdout.strip()
                if dirty:
                    _GIT_REV += "-dirty"
        except (OSError, subprocess.SubprocessError):
            _GIT_REV = "unknown"
    return _GIT_REV


def _provenance(schema: ArtifactSchema, stage: str, options: Mapping | None, seed: int | None,
                inputs: Mapping[str, str | None]) -> dict:
    """The ``heliocal`` metadata of an artifact; ``inputs`` maps label -> fingerprint (hex)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "artifact": schema.name,
        "stage": stage,
        "heliocal_version": __version__,
        "git_revision": git_revision(),
        "command": _command_line(stage),
        "options": _jsonable(dict(options or {})),
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


def _command_line(stage: str) -> str:
    """The heliocal command line of this run (``heliocal <stage>`` for in-process library calls)."""
    try:
        import click

        ctx = click.get_current_context(silent=True)
    except ImportError:  # pragma: no cover
        ctx = None
    if ctx is not None or Path(sys.argv[0]).name == "heliocal":
        return "heliocal " + " ".join(sys.argv[1:])
    return f"heliocal {stage} (library call)"


def _jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


# --------------------------------------------------------------------------------------------
# write / read
# --------------------------------------------------------------------------------------------
def _to_table(df: pd.DataFrame, schema: ArtifactSchema) -> pa.Table:
    missing = [c for c in schema.column_names() if c not in df.columns]
    if missing:
        raise SchemaError(
            f"cannot write {schema.filename}: required columns {missing} are missing "
            "(this is a bug in heliocal; please report it)")
    extras = [c for c in df.columns if c not in schema.column_names()]
    bad = [c for c in extras if not c.startswith(schema.extra_prefixes or ("\0",))]
    if bad:
        raise SchemaError(
            f"cannot write {schema.filename}: undeclared columns {bad} "
            "(this is a bug in heliocal; please report it)")
    df = df.reset_index(drop=True)
    if schema.sort_by:
        df = df.sort_values(list(schema.sort_by), kind="mergesort").reset_index(drop=True)
    arrays, fields = [], []
    for c in schema.columns:
        typ = _ARROW_TYPES[c.dtype]
        values = df[c.name]
        if c.dtype == "timestamp":
            values = pd.to_datetime(values, utc=True)
        elif c.dtype == "string":
            values = values.astype(object).where(values.notna(), None)
            values = values.map(lambda v: v if v is None else str(v))
        try:
            arr = pa.array(values, type=typ, from_pandas=True)
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
            raise SchemaError(
                f"cannot write {schema.filename}: column {c.name!r} is not {c.dtype} ({exc}); "
                "this is a bug in heliocal, please report it") from exc
        if not c.nullable and arr.null_count:
            raise SchemaError(
                f"cannot write {schema.filename}: column {c.name!r} has {arr.null_count} missing "
                "values but is declared non-nullable (this is a bug in heliocal; please report it)")
        arrays.append(arr)
        fields.append(pa.field(c.name, typ, nullable=c.nullable))
    for name in extras:
        arr = pa.array(df[name], from_pandas=True)
        arrays.append(arr)
        fields.append(pa.field(name, arr.type, nullable=True))
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


class _Fingerprint:
    """SHA-256 of a table's data, fed chunk by chunk; see :func:`table_fingerprint`.

    The data are put in a canonical form before hashing, so equal data give equal fingerprints
    however they were chunked or stored: every column becomes its values with nulls filled by the
    type's zero plus a non-null validity column, the rows are cut into record batches of
    :attr:`BATCH_ROWS`, and the batches are hashed as an Arrow IPC stream (without the schema's
    metadata and without the schema's volatile columns).
    """

    BATCH_ROWS = 65536

    def __init__(self, arrow_schema: pa.Schema, schema: ArtifactSchema):
        self._names = [f.name for f in arrow_schema if f.name not in schema.volatile]
        fields = []
        for f in arrow_schema:
            if f.name in schema.volatile:
                continue
            if not pa.types.is_null(f.type):
                fields.append(pa.field(f.name, f.type, nullable=False))
            fields.append(pa.field(f.name + "\0valid", pa.bool_(), nullable=False))
        self._schema = pa.schema(fields)
        self._hash = hashlib.sha256()
        self._writer = pa.ipc.new_stream(self, self._schema)
        self._pending: list[pa.Table] = []
        self._rows = 0

    # the file-like interface pyarrow writes the stream to
    closed = False

    def write(self, data) -> int:
        self._hash.update(data)
        return len(data)

    def flush(self) -> None:
        pass

    def _canonical(self, table: pa.Table) -> pa.Table:
        import pyarrow.compute as pc

        arrays = []
        for name in self._names:
            col = table.column(name)
            if not pa.types.is_null(col.type):
                arrays.append(pc.fill_null(col, pa.scalar(_zero(col.type), type=col.type))
                              if col.null_count else col)
            arrays.append(pc.is_valid(col))
        return pa.Table.from_arrays(arrays, schema=self._schema)

    def _emit(self, n: int) -> None:
        table = pa.concat_tables(self._pending)
        self._writer.write_table(table.slice(0, n).combine_chunks())
        rest = table.slice(n)
        self._pending, self._rows = ([rest] if rest.num_rows else []), rest.num_rows

    def add(self, table: pa.Table) -> None:
        if not table.num_rows:
            return
        self._pending.append(self._canonical(table))
        self._rows += table.num_rows
        while self._rows >= self.BATCH_ROWS:
            self._emit(self.BATCH_ROWS)

    def hexdigest(self) -> str:
        if self._rows:
            self._emit(self._rows)
        self._writer.close()
        return self._hash.hexdigest()


def _zero(typ: pa.DataType):
    if pa.types.is_string(typ) or pa.types.is_large_string(typ):
        return ""
    if pa.types.is_binary(typ) or pa.types.is_large_binary(typ):
        return b""
    if pa.types.is_boolean(typ):
        return False
    if pa.types.is_floating(typ):
        return 0.0
    return 0  # integers, timestamps, dates, durations


def table_fingerprint(table: pa.Table, schema: ArtifactSchema) -> str:
    """Content fingerprint of an artifact's table: what freshness compares.

    The SHA-256 of the table's data in a canonical form (:class:`_Fingerprint`), without the
    provenance metadata and without ``schema.volatile`` columns, so the command line, the git
    revision and wall-clock times do not make downstream artifacts stale; the data do. Equal data
    give equal fingerprints however they were chunked, written or read back.
    """
    fp = _Fingerprint(table.schema, schema)
    fp.add(table)
    return fp.hexdigest()


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

    Inside a stage run (:func:`heliocal.pipeline.transaction.transaction`) the file is staged and
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
    table = _to_table(df, schema)
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
        self.fingerprint = _Fingerprint(arrow_schema, schema)

    def write(self, df: pd.DataFrame) -> None:
        """Check ``df`` against the schema, sort it by ``schema.sort_by`` and append it.

        Chunks must come in ``sort_by`` order (each one sorted within itself here), so the file
        is sorted as :func:`write_artifact` would sort the whole table.
        """
        table = _to_table(df, self.schema)
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
    try:
        meta = pq.read_schema(path).metadata or {}
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
    """The provenance dict of an artifact from its metadata value ``text`` (JSON object), else a
    :class:`SchemaError` naming ``path``."""
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


def read_artifact(workdir: str | os.PathLike, schema: ArtifactSchema, *,
                  columns: Sequence[str] | None = None,
                  heliostats: Iterable[str] | None = None) -> pd.DataFrame:
    """Read and check ``schema``'s artifact from ``workdir``.

    Only the file the last complete run of ``schema.producer`` committed is read, and only if its
    bytes still have the SHA-256 recorded in the producer's manifest. Inside a stage run the read is
    recorded as an input of the run (with the file's content fingerprint).

    Parameters
    ----------
    columns : read only these columns (default all).
    heliostats : read only rows of these heliostat ids (uses Parquet row-group statistics, so a
        large field is not decoded whole).

    Raises
    ------
    StageInputError : the file is missing or not committed (the message names the stage to run).
    SchemaError : it was changed after its run, was written by an incompatible schema version, or
        lacks declared columns.
    """
    workdir = Path(workdir)
    path = artifact_path(workdir, schema)
    committed = read_committed(workdir, schema.producer, schema.filename,
                               hint=_rerun(schema, workdir),
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
    filters = None
    if heliostats is not None:
        filters = [("heliostat_id", "in", list(heliostats))]
    try:
        table = pq.read_table(pa.BufferReader(committed.data),
                              columns=list(columns) if columns else None, filters=filters)
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path} is not a readable Parquet file ({' '.join(str(exc).split())}); "
                          f"rerun {_rerun(schema, workdir)}") from exc
    df = table.to_pandas()
    for c in schema.columns:
        if c.name in df.columns and c.dtype == "string":
            df[c.name] = df[c.name].astype(object)
    return df


def committed_fingerprint(workdir: str | os.PathLike, schema: ArtifactSchema) -> str | None:
    """The content fingerprint of ``schema``'s artifact as its producer's last run committed it
    (``None`` if it did not)."""
    m = load_manifest(workdir, schema.producer)
    entry = m.files.get(schema.filename) if m is not None else None
    return None if entry is None else entry.get("fingerprint")


def recorded_inputs(workdir: str | os.PathLike, schema: ArtifactSchema) -> dict:
    """label -> fingerprint of the inputs ``schema``'s committed artifact was made from.

    Raises
    ------
    StageInputError : the artifact is not committed.
    """
    workdir = Path(workdir)
    path = artifact_path(workdir, schema)
    m = load_manifest(workdir, schema.producer)
    if m is None or schema.filename not in m.files:
        if path.exists():
            read_committed(workdir, schema.producer, schema.filename, hint=_rerun(schema, workdir))
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
    workdir = Path(workdir)
    path = artifact_path(workdir, schema)
    recorded = recorded_inputs(workdir, schema)
    for label, up in upstream.items():
        current = committed_fingerprint(workdir, up)
        up_path = artifact_path(workdir, up)
        if current is None:
            if up_path.exists():
                read_committed(workdir, up.producer, up.filename, hint=_rerun(up, workdir))
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
    m = load_manifest(workdir, schema.producer)
    return (m is not None and schema.filename in m.files) or artifact_path(workdir, schema).exists()
