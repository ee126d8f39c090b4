"""Declared tables: a :class:`Column` (name, dtype, unit, meaning), an :class:`ArtifactSchema` (the
columns, sort order and producer of one artifact file) and :func:`to_table`, the one conversion
of a DataFrame to an Arrow table of that schema (types checked, rows sorted).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from ..errors import SchemaError

__all__ = [
    "to_table",
    "Column",
    "ArtifactSchema",
]


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


# --------------------------------------------------------------------------------------------
# write / read
# --------------------------------------------------------------------------------------------
def _all_strings(values: pd.Series) -> bool:
    """Is every present value of the column a str already (a string dtype, or an object column
    of str and missing values)? Then arrow takes it as it is; a Python call per value to
    convert it took 2 s of writing coarse_predictions at 2,000 heliostats."""
    return (isinstance(values.dtype, pd.StringDtype)
            or pd.api.types.infer_dtype(values, skipna=True) in ("string", "empty"))


def to_table(df: pd.DataFrame, schema: ArtifactSchema) -> pa.Table:
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
    arrays, fields = [], []
    for c in schema.columns:
        typ = _ARROW_TYPES[c.dtype]
        values = df[c.name]
        if c.dtype == "timestamp":
            values = pd.to_datetime(values, utc=True)
        elif c.dtype == "string" and not _all_strings(values):
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
    table = pa.Table.from_arrays(arrays, schema=pa.schema(fields))
    if schema.sort_by:   # arrow's stable sort, missing values last (as pandas' mergesort)
        try:
            order = pc.sort_indices(table, sort_keys=[(k, "ascending", "at_end")
                                                      for k in schema.sort_by])
        except (TypeError, ValueError, pa.ArrowInvalid):   # pyarrow < 25: one placement for all
            order = pc.sort_indices(table, sort_keys=[(k, "ascending") for k in schema.sort_by],
                                    null_placement="at_end")
        table = table.take(order)
    return table
