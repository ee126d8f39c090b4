"""Incremental stage runs: which heliostats' inputs changed since a stage's last committed run.

A per-heliostat stage (``split-knn``, ``fit-coarse``) records in its manifest, beside the usual
provenance, the digest of each heliostat's inputs and one *field key*::

    "incremental": {"field_key": <sha256>, "code": <revision>, "heliostats": {<id>: <sha256>}}

* a heliostat's digest is the SHA-256 of its rows in every input table the stage reads for it
  (:func:`heliostat_digests`: each row hashed by value, in the order the stage reads them);
* the field key is the SHA-256 of everything that is not a heliostat's own: the stage, its
  options, the heliocal version and code (:func:`code_identity`), the column names of its inputs, and any
  field-wide value a heliostat's result depends on (a prior or a noise scale taken over the
  field would go there).

With ``--incremental`` a stage compares them with the previous run's (:func:`plan_increment`):
when the field key is the same, only heliostats whose digest differs (or that are new) are
computed again, the others' rows are taken from the previous committed artifacts, and heliostats
that are gone are dropped. When the field key moved (other options, other code, a field-wide
input), or the previous run recorded no digests, every heliostat is computed again. Either way
the run is one stage transaction like any other, and records the digests of what it read, so a
next ``--incremental`` run starts from it. A run whose upstream artifacts, options and code are
all those of the previous run reads nothing: it keeps the previous run's files
(:func:`carry_over_unchanged`, :mod:`.unchanged`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from .revision import code_identity
from .unchanged import INCREMENTAL_KEY, carry_over_unchanged, mark_rerunnable

__all__ = ["INCREMENTAL_KEY", "Increment", "heliostat_digests", "field_key", "plan_increment",
           "reused_rows", "carry_over_unchanged", "mark_rerunnable", "code_identity",
           "value_digest"]


def heliostat_digests(frames: Sequence[pd.DataFrame]) -> dict[str, str]:
    """heliostat id -> SHA-256 (hex) of its rows in every frame (each with a ``heliostat_id``
    column), hashed by value in the frames' row order; a heliostat absent from a frame hashes
    that absence. Column names are not part of it (they go into :func:`field_key`)."""
    parts: list[dict[str, bytes]] = []
    for df in frames:
        ids = df["heliostat_id"].astype(str).to_numpy()
        rows = pd.util.hash_pandas_object(df.reset_index(drop=True), index=False).to_numpy()
        order = np.argsort(ids, kind="stable")
        ids_sorted = ids[order]
        cuts = np.flatnonzero(ids_sorted[1:] != ids_sorted[:-1]) + 1
        starts = np.concatenate([[0], cuts]) if len(ids_sorted) else np.array([], int)
        ends = np.concatenate([cuts, [len(ids_sorted)]]) if len(ids_sorted) else np.array([], int)
        parts.append({ids_sorted[s]: rows[order[s:e]].tobytes() for s, e in zip(starts, ends)})
    out = {}
    for hid in sorted(set().union(*(p.keys() for p in parts))):
        h = hashlib.sha256()
        for k, p in enumerate(parts):
            data = p.get(hid, b"")
            h.update(f"{k}:{len(data)}:".encode())
            h.update(data)
        out[hid] = h.hexdigest()
    return out


def _hash_into(h, obj) -> None:
    """Feed ``obj`` into hash ``h`` by value, with its type and shape, so that different values
    never feed the same bytes: frames (column names, dtypes, every row hashed by value), series,
    indexes, arrays, tensors, mappings (keys sorted), sequences, and scalars by their exact
    ``repr``; anything else by its pickle, or, when it has none, by its identity (then it is
    never taken for an earlier value)."""
    import pickle

    if isinstance(obj, pd.DataFrame):
        h.update(f"frame:{obj.shape}:".encode())
        h.update(json.dumps([[str(c), str(t)] for c, t in obj.dtypes.items()]).encode())
        _hash_frame_values(h, obj)
    elif isinstance(obj, pd.Series):
        h.update(f"series:{obj.name!r}:{obj.dtype}:".encode())
        _hash_into(h, obj.index)
        _hash_into(h, obj.to_numpy())
    elif isinstance(obj, pd.Index):
        h.update(f"index:{obj.name!r}:{obj.dtype}:".encode())
        _hash_into(h, obj.to_numpy())
    elif isinstance(obj, np.ndarray):
        h.update(f"ndarray:{obj.dtype}:{obj.shape}:".encode())
        h.update(np.ascontiguousarray(obj).tobytes() if obj.dtype != object
                 else pickle.dumps(obj.tolist(), protocol=4))
    elif type(obj).__module__.startswith("torch") and hasattr(obj, "detach"):
        _hash_into(h, obj.detach().cpu().numpy())
    elif isinstance(obj, Mapping):
        h.update(f"mapping:{len(obj)}:".encode())
        for key in sorted(obj, key=repr):
            h.update(f"{key!r}=".encode())
            _hash_into(h, obj[key])
    elif isinstance(obj, (list, tuple)):
        h.update(f"{type(obj).__name__}:{len(obj)}:".encode())
        for x in obj:
            _hash_into(h, x)
    elif obj is None or isinstance(obj, (bool, int, float, complex, str, bytes, np.generic,
                                         pd.Timestamp, pd.Timedelta)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    else:
        try:
            h.update(b"pickle:" + pickle.dumps(obj, protocol=4))
        except Exception:  # noqa: BLE001 - an object without a pickle is hashed by identity
            h.update(f"id:{id(obj)}:{type(obj).__name__};".encode())


def _hash_frame_values(h, df: pd.DataFrame) -> None:
    """A frame's values (its header, with names and dtypes in order, is hashed apart), column by
    column, each tagged with its position and how it is hashed (:func:`_hash_column`). A column
    is taken with ``DataFrame.items`` (no indexer, no new frame): the sweep hashes some 1,200
    frames of 10-30 columns per run and the report some 30,000 small columns, where the cost is
    pandas' per-call overhead, not the bytes."""
    for i, (_, col) in enumerate(df.items()):
        _hash_column(h, i, col)


def _hash_column(h, i: int, col: pd.Series) -> None:
    """Column ``i``'s values by value: a numpy dtype's as its bytes; a time-zone-aware
    datetime's as its int64 nanoseconds or microseconds (the unit and zone are in the header's
    dtype); strings (every value a ``str``) as their lengths and UTF-8 bytes, which tell any
    two sequences apart; anything else (missing values, mixed or other objects) through
    :func:`_hash_into` of its values as objects."""
    dtype = col.dtype
    if isinstance(dtype, np.dtype) and dtype != object:
        h.update(f"{i}:{dtype.str}:".encode())
        h.update(np.ascontiguousarray(col.to_numpy()).tobytes())
        return
    if isinstance(dtype, pd.DatetimeTZDtype):
        h.update(f"{i}:tz:".encode())
        h.update(np.ascontiguousarray(col.array.asi8).tobytes())
        return
    values = col.to_numpy(dtype=object)
    if pd.api.types.infer_dtype(values, skipna=False) == "string":
        h.update(f"{i}:str:{len(values)}:".encode())
        h.update(np.fromiter(map(len, values), np.int64, len(values)).tobytes())
        h.update("".join(values).encode("utf-8", "surrogatepass"))
        return
    h.update(f"{i}:obj:".encode())
    _hash_into(h, values)


def value_digest(obj) -> str:
    """SHA-256 (hex) of ``obj`` by value (:func:`_hash_into`): equal digests, equal values."""
    h = hashlib.sha256()
    _hash_into(h, obj)
    return h.hexdigest()


def field_key(stage: str, options: Mapping, frames: Sequence[pd.DataFrame],
              field_inputs: Mapping | None = None) -> str:
    """The SHA-256 (hex) of what every heliostat's result of ``stage`` shares: its options, the
    code (heliocal version and git revision), the inputs' column names and dtypes, and
    ``field_inputs`` (field-wide values, JSON-able)."""
    from .. import __version__
    from .revision import jsonable

    text = json.dumps({"stage": stage, "options": jsonable(dict(options)),
                       "version": __version__, "revision": code_identity(),
                       "columns": [[f"{c}:{t}" for c, t in df.dtypes.astype(str).items()]
                                   for df in frames],
                       "field": jsonable(dict(field_inputs or {}))}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass
class Increment:
    """What an incremental run computes again and what it takes from the previous run."""

    compute: list[str]                 # heliostats computed in this run (sorted)
    reuse: list[str]                   # heliostats whose previous rows are kept (sorted)
    removed: list[str] = field(default_factory=list)  # heliostats of the previous run now gone
    why: str = ""                      # why everything is computed, when it is

    @property
    def partial(self) -> bool:
        return bool(self.reuse) or bool(self.removed)

    def summary(self) -> dict:
        return {"computed": len(self.compute), "reused": len(self.reuse),
                "removed": len(self.removed), "why_all": self.why or None}


def plan_increment(txn, key: str, digests: Mapping[str, str], incremental: bool) -> Increment:
    """Record ``key`` and ``digests`` in the run's manifest (``txn``: the active
    :class:`~.transaction.StageTransaction`) and decide which heliostats to compute: all of them
    unless ``incremental`` and the previous committed run recorded the same field key."""
    txn.extra[INCREMENTAL_KEY] = {"field_key": key, "code": code_identity(),
                                  "heliostats": dict(sorted(digests.items()))}
    everything = sorted(digests)
    if not incremental:
        return Increment(everything, [], why="not --incremental")
    prev = txn.previous.data.get(INCREMENTAL_KEY) if txn.previous is not None else None
    if not isinstance(prev, dict) or not isinstance(prev.get("heliostats"), dict):
        return Increment(everything, [], why="the previous run recorded no per-heliostat inputs")
    if prev.get("field_key") != key:
        return Increment(everything, [], why="a field-wide input changed (options, code or a "
                                             "value every heliostat shares)")
    old = prev["heliostats"]
    compute = [h for h in everything if old.get(h) != digests[h]]
    reuse = [h for h in everything if old.get(h) == digests[h]]
    removed = sorted(h for h in old if h not in digests)
    return Increment(compute, reuse, removed)


def reused_rows(previous: pd.DataFrame, reuse: Sequence[str]) -> pd.DataFrame:
    """The rows of the heliostats in ``reuse`` of a previous artifact."""
    return previous[previous["heliostat_id"].astype(str).isin(set(reuse))]
