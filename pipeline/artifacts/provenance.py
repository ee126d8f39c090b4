"""Provenance of an artifact: the code revision, command line and parameters of the run that
wrote it, and content fingerprints of tables (the basis of every freshness check).
"""

from __future__ import annotations

import hashlib

import pyarrow as pa

from .revision import command_line, git_revision, jsonable, source_revision
from .table import ArtifactSchema

__all__ = [
    "Fingerprint",
    "table_fingerprint",
    "git_revision",
    "source_revision",
    "command_line",
    "jsonable",
]


class Fingerprint:
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

    The SHA-256 of the table's data in a canonical form (:class:`Fingerprint`), without the
    provenance metadata and without ``schema.volatile`` columns, so the command line, the git
    revision and wall-clock times do not make downstream artifacts stale; the data do. Equal data
    give equal fingerprints however they were chunked, written or read back.
    """
    fp = Fingerprint(table.schema, schema)
    fp.add(table)
    return fp.hexdigest()
