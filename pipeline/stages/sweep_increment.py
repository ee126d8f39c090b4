"""``sweep --incremental``: which heliostats the sweep trains again, and the previous sweep's
rows and models it keeps for the others.

The sweep trains heliostats of one kinematic type, actuator type and coarse preset together, in
chunks of ``batch_size`` (one batched torch program per weight decay). The chunk's tensors are laid
out so that a heliostat's networks do not depend on its chunk
(:data:`heliocal.pipeline.models.training.MEMBER_ALIGN`: rows and parameters padded to multiples
of 32, so no network's elements fall in torch's scalar tail and a row count's reductions do not
depend on the others' rows): a heliostat trains to the same bits alone or beside any others, at
any position (tests/test_sweep_independence.py). So the unit of reuse is the heliostat: an
update trains the heliostats whose inputs changed, in chunks of their own, and keeps the
others' results, which are those a full rerun computes, bit for bit.

What a heliostat's results depend on is its own :class:`~.sweep_inputs.SweepInputs` (rows with
their split, heliostats.parquet row, fit-coarse's selected fit and predictions, the time-split
fit): :func:`~.sweep_inputs.sweep_digests` hashes the heliostat's rows of every table those are
taken from, at once for the field. What the whole field shares goes into the field key
(:func:`heliocal.pipeline.artifacts.incremental.field_key`): the options and seeds, the code, the
study's heliostats (a seeded choice among the field's ids) and fit-coarse's solver options that the
study refits with. The GP candidates, the pre-trained network and the study are computed per
heliostat, so they follow their heliostat.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import pandas as pd

from ..artifacts.incremental import INCREMENTAL_KEY, code_identity, reused_rows
from ..artifacts.manifests import CommittedWorkdir, current_transaction
from ..artifacts.modelfiles import read_model_config, rewrite_model_config, write_model
from ..artifacts.schemas import SELECTED_PREDICTIONS, SELECTION, SWEEP
from ..artifacts.store import (merge_with_previous, previous_run_matches, read_artifact,
                               write_artifact)

__all__ = ["SweepPlan", "chunk_size", "sweep_chunks", "plan_sweep",
           "write_sweep_outputs"]

def chunk_size(n_heliostats: int, batch_size: int, workers: int) -> int:
    """Heliostats per training chunk when ``n_heliostats`` are trained on ``workers`` processes:
    ``batch_size``, or fewer when that many would leave a worker idle (an update of 20
    heliostats on 2 workers: 2 chunks of 10, not 1 of 20). A heliostat's results do not depend
    on its chunk (the module's docstring), so this changes the time, not the results."""
    return max(1, min(int(batch_size), -(-int(n_heliostats) // max(1, int(workers)))))


#: A training chunk's cost per epoch in heliostat-rows (one heliostat's networks over one padded
#: row): a fixed part for the program's per-epoch overhead plus one per heliostat and row of the
#: chunk's longest heliostat. Measured (benchmarks/chunk_cost.py, one process, one thread, idle
#: machine): 3.9 ms per epoch for 1 heliostat of 224 rows, 68.1 ms for 64 of 288 rows, so about
#: 3.1 ms for the program and 3.5 us per heliostat-row: the fixed part is about 870 heliostat-rows.
CHUNK_OVERHEAD_ROWS = 870


def _piece_sizes(lengths: Sequence[int], k: int, batch_size: int) -> list[int]:
    """Sizes of consecutive pieces of the ascending row counts ``lengths``, at most ``k`` pieces
    of at most ``batch_size``, such that the costliest piece (:data:`CHUNK_OVERHEAD_ROWS` + its
    heliostats x its longest one's rows) costs as little as it can."""
    def sizes_within(limit: int) -> list[int]:
        sizes, end = [], len(lengths)
        while end > 0:
            top, size = lengths[end - 1], 1
            while (size < min(batch_size, end)
                   and CHUNK_OVERHEAD_ROWS + (size + 1) * top <= limit):
                size += 1
            sizes.append(size)
            end -= size
        return sizes[::-1]

    lo = CHUNK_OVERHEAD_ROWS + max(lengths)                 # one heliostat per piece
    hi = CHUNK_OVERHEAD_ROWS + batch_size * max(lengths)    # always within k pieces
    while lo < hi:
        mid = (lo + hi) // 2
        if len(sizes_within(mid)) <= k:
            hi = mid
        else:
            lo = mid + 1
    return sizes_within(lo)


def sweep_chunks(items: Mapping, selected: Mapping, helio: pd.DataFrame,
                 batch_size: int, workers: int = 1, size: int | None = None) -> list[list[str]]:
    """The sweep's training chunks: heliostats that share kinematic type, actuator type and free
    parameters, at most ``batch_size`` per chunk, each chunk ordered by row count then id; the
    costliest chunk first.

    A group of at most ``size`` heliostats (default ``batch_size``; the sweep passes
    :func:`chunk_size`) is one chunk. A larger group, in row-count order, is cut into
    consecutive pieces of at most ``batch_size``, as many as pieces of ``size`` would be but a
    whole number of rounds of the ``workers`` (200 heliostats at 32 on 2 workers: 8 chunks, not 7
    that leave a worker idle for the last one; an update of 20 at size 10: 2), of about equal
    cost per epoch
    (:data:`CHUNK_OVERHEAD_ROWS` + heliostats x the longest one's rows: the pieces of shorter
    heliostats hold more of them). Consecutive heliostats in row-count order have similar row
    counts, so little padding. A heliostat's results do not depend on its chunk (the module's
    docstring): the chunks decide the time, not the results. Costliest first, so that a pool of
    workers starts the longest chunks first and ends with short ones.
    """
    groups: dict = {}
    for hid in sorted(items):
        h = helio.loc[hid]
        key = (str(h["kinematic_type"]), str(h["actuator_type"]),
               tuple(bool(x) for x in selected[hid]["free"].tolist()))
        groups.setdefault(key, []).append(hid)
    order = lambda hid: (len(items[hid].rows), hid)  # noqa: E731
    batch_size, workers = max(1, int(batch_size)), max(1, int(workers))
    size = min(batch_size, max(1, int(size or batch_size)))
    chunks = []
    for key in sorted(groups):
        members = sorted(groups[key], key=order)
        k = -(-len(members) // size)
        if k > 1:
            k = min(len(members), -(-k // workers) * workers)
        start = 0
        for n in _piece_sizes([len(items[h].rows) for h in members], k, batch_size):
            chunks.append(members[start:start + n])
            start += n
    cost = lambda c: (-len(c) * len(items[c[-1]].rows), c[0])  # noqa: E731
    return sorted(chunks, key=cost)


@dataclass
class SweepPlan:
    """The chunks a sweep trains and the heliostats it keeps from the previous run."""

    compute: list[list[str]]                 # chunks trained in this run
    reuse: list[str] = field(default_factory=list)         # heliostats kept from the previous run
    removed: list[str] = field(default_factory=list)       # heliostats of the previous run gone
    why: str = ""                            # why every heliostat is trained, when it is

    @property
    def partial(self) -> bool:
        return bool(self.reuse) or bool(self.removed)

    @property
    def reused_ids(self) -> list[str]:
        return sorted(self.reuse)

    def summary(self) -> dict:
        return {"unchanged": False, "computed": sum(map(len, self.compute)),
                "reused": len(self.reuse), "removed": len(self.removed),
                "chunks_computed": len(self.compute), "why_all": self.why or None}


def plan_sweep(txn, key: str, digests: Mapping[str, str],
               chunks_of: Callable[[Sequence[str]], list[list[str]]],
               incremental: bool) -> SweepPlan:
    """Record ``key`` and the heliostats' ``digests`` in the run's manifest and decide which
    heliostats to train, in the chunks ``chunks_of(ids)`` makes of them: all of them unless
    ``incremental`` and the previous committed sweep recorded the same field key; then a
    heliostat whose digest the previous run recorded is kept, and the others are trained."""
    txn.extra[INCREMENTAL_KEY] = {"field_key": key, "code": code_identity(),
                                  "heliostats": dict(sorted(digests.items()))}
    ids = sorted(digests)
    if not incremental:
        return SweepPlan(chunks_of(ids), why="not --incremental")
    prev = txn.previous.data.get(INCREMENTAL_KEY) if txn.previous is not None else None
    if not isinstance(prev, dict) or not isinstance(prev.get("heliostats"), dict):
        return SweepPlan(chunks_of(ids),
                         why="the previous sweep recorded no per-heliostat inputs")
    if prev.get("field_key") != key:
        return SweepPlan(chunks_of(ids), why="a field-wide input changed (options, seeds, code, "
                                             "the study's heliostats or fit-coarse's solver "
                                             "options)")
    before = prev["heliostats"]
    changed = [h for h in ids if before.get(h) != digests[h]]
    return SweepPlan(chunks_of(changed), [h for h in ids if before.get(h) == digests[h]],
                     sorted(str(h) for h in before if h not in digests))


def _previous_tables(workdir: Path, plan: SweepPlan) -> dict:
    """The previous sweep's rows of the heliostats ``plan`` keeps, per artifact."""
    ids = plan.reused_ids
    return {s: reused_rows(read_artifact(workdir, s), ids)
            for s in (SWEEP, SELECTION, SELECTED_PREDICTIONS)}


def _keep_models(workdir: Path, txn, ids: Sequence[str], hashes: dict) -> None:
    """Stage the previous sweep's selected models of ``ids`` again in this run: their weights
    files as they are (carried over, verified against the manifest, not loaded) and their
    configuration recording this run's inputs (``hashes``), as a full rerun would record them; a
    heliostat whose selection is coarse has none. One :class:`CommittedWorkdir` reads them all,
    so the sweep's manifest (two entries per model) is loaded and checked once, not per model."""
    committed = CommittedWorkdir.of(workdir)
    hint = f"`heliocal sweep --workdir {workdir}`"
    for hid in ids:
        found = read_model_config(committed, "sweep", "selected", hid, hint=hint)
        if found is not None:
            rewrite_model_config(txn, found, "selected", hid, {**found.config, "inputs": hashes})


def _by_heliostat(df: pd.DataFrame) -> pd.DataFrame:
    """``df``'s rows grouped by heliostat id (stable: each heliostat's rows keep their order)."""
    if df.empty:
        return df
    return df.sort_values("heliostat_id", kind="mergesort").reset_index(drop=True)


def write_sweep_outputs(workdir: Path, results: list[dict], chosen: list[dict],
                        heliostats: Sequence[str] | None, plan: SweepPlan | None, opts: dict,
                        seed: int) -> pd.DataFrame:
    """Write the selected models, sweep.parquet, selection.parquet and
    selected_predictions.parquet of a run's results, with the previous run's rows and models of
    the chunks ``plan`` keeps; return the selection."""
    txn = current_transaction(workdir, "sweep")
    hashes = txn.input_fingerprints()  # what this run read: the selected models' recorded inputs
    for res in chosen:
        st = res["selected_state"]
        if st is not None:
            write_model(txn, "selected", st["config"]["heliostat_id"], st["state"],
                        {**st["config"], "inputs": hashes})
    tables = {SWEEP: pd.DataFrame([r for res in results for r in res["rows"]]),
              SELECTION: pd.DataFrame([res["selection"] for res in chosen]),
              SELECTED_PREDICTIONS: (pd.concat([res["predictions"] for res in chosen],
                                               ignore_index=True) if chosen else pd.DataFrame())}
    if plan is not None and plan.reuse:
        previous = _previous_tables(workdir, plan)
        tables = {s: pd.concat([p for p in (previous[s], df) if len(p)] or [df],
                               ignore_index=True) for s, df in tables.items()}
        _keep_models(workdir, txn, plan.reused_ids, hashes)
    tables = {s: _by_heliostat(df) for s, df in tables.items()}
    selection = tables[SELECTION]
    # a partial run (--heliostat) keeps the other heliostats' rows and selected models when the
    # previous sweep read the same inputs (artifacts.merge_with_previous)
    if heliostats:
        requested = set(heliostats)
        replaced = lambda old: old["heliostat_id"].isin(requested)  # noqa: E731
        tables = {s: merge_with_previous(workdir, s, df, replaced) for s, df in tables.items()}
        if previous_run_matches(workdir, "sweep"):
            txn.carry_over(r for r in txn.previous_files("hybrid/selected")
                           if r.rsplit("/", 1)[-1].rsplit(".", 1)[0] not in requested)
    for schema, df in tables.items():
        write_artifact(df, workdir, schema, stage="sweep", options=opts, seed=seed)
    return selection
