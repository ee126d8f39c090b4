"""Artifacts: declared schemas, atomic writes, provenance and freshness checks.

Every stage reads its inputs from a work directory and writes its outputs there under fixed
names (the *workdir contract*). Each Parquet artifact has a declared :class:`ArtifactSchema`
(declared once, in the module of the stage that writes it) that is checked on write and on read.

Writes are atomic: the table goes to a temporary file in the same folder and is renamed into
place with :func:`os.replace`, so a killed stage leaves the previous artifact intact or none at
all, never a half-written file.

Each artifact carries its provenance in the Parquet key-value metadata under the key
``heliocal``: schema version, artifact name, stage, heliocal version and git revision, the
command line and its resolved options, the seed, and SHA-256 content hashes of its inputs. A
stage that reads an artifact checks that it was made from the current version of *its* inputs
(:func:`check_fresh`), so a stale artifact is refused with the stage to rerun.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Mapping, Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from . import __version__
from .errors import SchemaError, StageInputError, UnsafePathError

__all__ = [
    "SCHEMA_VERSION",
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
    "check_fresh",
    "artifact_path",
    "git_revision",
    "safe_child",
    "MAX_NAME_BYTES",
]

#: Version of the artifact layout. Bump when a column changes meaning or a required one is added.
SCHEMA_VERSION = 1
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
    ``env_*`` inputs of the fine model and ``qa_*`` flags).
    """

    name: str
    filename: str
    producer: str
    columns: tuple[Column, ...]
    extra_prefixes: tuple[str, ...] = ()
    sort_by: tuple[str, ...] = ()
    description: str = ""
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
        raise UnsafePathError(
            f"{name!r} cannot be used as a file name in {directory}: {why}; names taken from the "
            "data must be plain file names (heliostat ids: letters, digits, '_', '-', '.', see "
            "docs/input_formats.md; rerun `heliocal ingest`, which rejects other ids)")
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
            h.update(_sha_bytes(p).encode())
    else:
        return _sha_bytes(path)
    return h.hexdigest()


def _sha_bytes(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
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
                inputs: Mapping[str, str | os.PathLike] | None) -> dict:
    hashes = {}
    for label, p in (inputs or {}).items():
        hashes[label] = file_sha256(p) if Path(p).exists() else None
    return {
        "schema_version": SCHEMA_VERSION,
        "artifact": schema.name,
        "stage": stage,
        "heliocal_version": __version__,
        "git_revision": git_revision(),
        "command": _command_line(stage),
        "options": _jsonable(dict(options or {})),
        "seed": seed,
        "inputs": hashes,
    }


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


def write_artifact(df: pd.DataFrame, workdir: str | os.PathLike, schema: ArtifactSchema, *,
                   stage: str, options: Mapping | None = None, seed: int | None = None,
                   inputs: Mapping[str, str | os.PathLike] | None = None,
                   row_group_size: int | None = None) -> Path:
    """Check ``df`` against ``schema`` and write it atomically to ``workdir/schema.filename``.

    Parameters
    ----------
    df : the table; columns are cast to the declared types and rows sorted by ``schema.sort_by``.
    workdir : the work directory.
    stage : the subcommand writing it (recorded in the provenance).
    options : resolved options of the run (recorded).
    seed : the seed of the run, if it has random steps.
    inputs : label -> path of every input file or folder; their SHA-256 is recorded and later
        compared by :func:`check_fresh`.
    row_group_size : rows per Parquet row group (default: pyarrow's).

    Returns
    -------
    The artifact's path.
    """
    table = _to_table(df, schema)
    meta = dict(table.schema.metadata or {})
    meta[_META_KEY] = json.dumps(_provenance(schema, stage, options, seed, inputs),
                                 sort_keys=True).encode()
    table = table.replace_schema_metadata(meta)
    path = artifact_path(workdir, schema)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, row_group_size=row_group_size, compression="zstd")
    return path


class ArtifactWriter:
    """Appends DataFrame chunks to one artifact being written (see :func:`artifact_writer`)."""

    def __init__(self, writer: pq.ParquetWriter, schema: ArtifactSchema, arrow_schema: pa.Schema,
                 row_group_size: int | None):
        self._writer = writer
        self.schema = schema
        self.arrow_schema = arrow_schema
        self.row_group_size = row_group_size
        self.rows = 0

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
        self.rows += table.num_rows


@contextlib.contextmanager
def artifact_writer(workdir: str | os.PathLike, schema: ArtifactSchema, *, stage: str,
                    extra: Mapping[str, pa.DataType] | None = None,
                    options: Mapping | None = None, seed: int | None = None,
                    inputs: Mapping[str, str | os.PathLike] | None = None,
                    row_group_size: int | None = None) -> Iterator[ArtifactWriter]:
    """Write ``schema``'s artifact chunk by chunk, atomically, with provenance metadata.

    The streaming twin of :func:`write_artifact`: yields an :class:`ArtifactWriter` whose
    ``write(df)`` checks and appends one chunk. The file goes to a hidden temporary name and
    replaces ``workdir/schema.filename`` only when the ``with`` block ends without an exception;
    on an exception the temporary file is removed and the previous artifact is left as it was.

    Parameters
    ----------
    extra : name -> Arrow type of the extra columns (``env_*``, ``qa_*``) the chunks may hold; a
        chunk without one of them gets it empty.
    row_group_size : rows per Parquet row group at most (a chunk never shares a row group with
        the next one).
    """
    arrow_schema = schema.arrow_schema(extra)
    meta = {_META_KEY: json.dumps(_provenance(schema, stage, options, seed, inputs),
                                  sort_keys=True).encode()}
    arrow_schema = arrow_schema.with_metadata(meta)
    path = artifact_path(workdir, schema)
    with atomic_path(path) as tmp:
        with pq.ParquetWriter(tmp, arrow_schema, compression="zstd") as writer:
            yield ArtifactWriter(writer, schema, arrow_schema, row_group_size)


def read_provenance(path: str | os.PathLike) -> dict:
    """The provenance dictionary stored in a heliocal Parquet artifact."""
    path = Path(path)
    try:
        meta = pq.read_schema(path).metadata or {}
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path} is not a readable Parquet file ({exc}); rerun the stage "
                          "that writes it") from exc
    if _META_KEY not in meta:
        raise SchemaError(f"{path} was not written by heliocal (no provenance metadata); rerun "
                          "the stage that writes it")
    return json.loads(meta[_META_KEY])


def _missing_message(path: Path, schema: ArtifactSchema) -> str:
    args = " SOURCE..." if schema.producer == "ingest" else ""
    return (f"{path} is missing: run `heliocal {schema.producer}{args} --workdir {path.parent}` "
            "first")


def read_artifact(workdir: str | os.PathLike, schema: ArtifactSchema, *,
                  columns: Sequence[str] | None = None,
                  heliostats: Iterable[str] | None = None) -> pd.DataFrame:
    """Read and check ``schema``'s artifact from ``workdir``.

    Parameters
    ----------
    columns : read only these columns (default all).
    heliostats : read only rows of these heliostat ids (uses Parquet row-group statistics, so a
        large field is not loaded whole).

    Raises
    ------
    StageInputError : the file is missing (the message names the stage to run).
    SchemaError : it was written by an incompatible schema version or lacks declared columns.
    """
    path = artifact_path(workdir, schema)
    if not path.exists():
        raise StageInputError(_missing_message(path, schema))
    try:
        prov = read_provenance(path)
    except SchemaError as exc:
        raise SchemaError(f"{exc}: `heliocal {schema.producer} --workdir {path.parent}`") from exc
    if prov.get("artifact") != schema.name:
        raise SchemaError(f"{path} holds a {prov.get('artifact')!r} artifact, not "
                          f"{schema.name!r}; rerun `heliocal {schema.producer}`")
    if prov.get("schema_version") != SCHEMA_VERSION:
        raise SchemaError(
            f"{path} was written by heliocal {prov.get('heliocal_version')} with schema version "
            f"{prov.get('schema_version')}, but this heliocal reads version {SCHEMA_VERSION}: "
            f"rerun `heliocal {schema.producer} --workdir {path.parent}`")
    file_schema = pq.read_schema(path)
    absent = [c for c in schema.column_names() if c not in file_schema.names]
    if absent:
        raise SchemaError(f"{path} lacks columns {absent}: rerun `heliocal {schema.producer} "
                          f"--workdir {path.parent}`")
    filters = None
    if heliostats is not None:
        filters = [("heliostat_id", "in", list(heliostats))]
    table = pq.read_table(path, columns=list(columns) if columns else None, filters=filters)
    df = table.to_pandas()
    for c in schema.columns:
        if c.name in df.columns and c.dtype == "string":
            df[c.name] = df[c.name].astype(object)
    return df


def check_fresh(workdir: str | os.PathLike, schema: ArtifactSchema,
                upstream: Mapping[str, ArtifactSchema]) -> None:
    """Raise :class:`StageInputError` if ``schema``'s artifact was made from older inputs.

    ``upstream`` maps the input labels recorded at write time (see :func:`write_artifact`) to the
    schemas of the artifacts they name; each recorded hash must equal the current file's hash.
    """
    path = artifact_path(workdir, schema)
    if not path.exists():
        raise StageInputError(_missing_message(path, schema))
    recorded = read_provenance(path).get("inputs", {})
    for label, up in upstream.items():
        up_path = artifact_path(workdir, up)
        if not up_path.exists():
            raise StageInputError(_missing_message(up_path, up))
        if label not in recorded:
            raise StageInputError(
                f"{path} was made without {up.filename}; rerun "
                f"`heliocal {schema.producer} --workdir {path.parent}` first")
        if recorded[label] != file_sha256(up_path):
            raise StageInputError(
                f"{path} is stale: {up.filename} changed after it was written; rerun "
                f"`heliocal {schema.producer} --workdir {path.parent}` first")
