"""``sweep --incremental``: which training chunks of the sweep to train again, and the previous
sweep's rows and models it keeps for the others.

The sweep trains heliostats of one kinematic type, actuator type and coarse preset together, in
chunks of ``batch_size`` (one batched torch program per weight decay). A heliostat's networks
depend on its chunk, not only on its own rows: the chunk's padding and the position of its
networks in the batched tensors decide which of torch's vectorised or scalar kernels computes
each element, and the rounding that follows is amplified by hundreds of Adam steps
(docs/experiments/incremental-updates.md). So the unit of reuse is the chunk, and the chunks are
made so that they do not move when another heliostat gains rows (:func:`sweep_chunks`): a chunk
whose heliostats all have the inputs of the previous run is the previous run's chunk, trained on
the same inputs, and its results are those a full rerun would compute, bit for bit.

What a heliostat's results depend on besides its chunk is its own :class:`SweepInputs` (rows with
their split, heliostats.parquet row, fit-coarse's selected fit and predictions, the time-split
fit): :func:`sweep_digests` hashes all of it. What the whole field shares goes into the field key
(:func:`heliocal.pipeline.artifacts.incremental.field_key`): the options and seeds, the code, the
study's heliostats (a seeded choice among the field's ids) and fit-coarse's solver options that the
study refits with. The GP candidates, the pre-trained network and the study are computed per
heliostat, so they follow their heliostat's chunk.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import pandas as pd

from ..artifacts.incremental import INCREMENTAL_KEY, code_identity, reused_rows, value_digest
from ..artifacts.manifests import current_transaction
from ..artifacts.modelfiles import read_model, write_model
from ..artifacts.schemas import SELECTED_PREDICTIONS, SELECTION, SWEEP
from ..artifacts.store import (merge_with_previous, previous_run_matches, read_artifact,
                               write_artifact)

__all__ = ["ROW_BAND", "SweepPlan", "sweep_chunks", "sweep_digests", "plan_sweep",
           "write_sweep_outputs"]

#: Rows per band of :func:`sweep_chunks`: a group larger than one chunk is cut into chunks within
#: bands of this many measurement rows, so that a chunk's heliostats have similar row counts
#: (little padding) and a heliostat that gains a day's rows stays in its band.
ROW_BAND = 100


def sweep_digests(items: Mapping) -> dict[str, str]:
    """heliostat id -> SHA-256 (hex) of everything the sweep reads for it (its
    :class:`~.sweep_inputs.SweepInputs`: rows, split rows, heliostats.parquet row, selected coarse
    fit with its regimes, coarse predictions and errors, time-split fit)."""
    return {hid: value_digest(vars(items[hid])) for hid in sorted(items)}


def sweep_chunks(items: Mapping, selected: Mapping, helio: pd.DataFrame,
                 batch_size: int) -> list[list[str]]:
    """The sweep's training chunks: heliostats that share kinematic type, actuator type and free
    parameters, at most ``batch_size`` per chunk, each chunk ordered by row count then id.

    A group of at most ``batch_size`` heliostats is one chunk. A larger group is cut, band by band
    of :data:`ROW_BAND` measurement rows, into chunks of consecutive ids, so a chunk's membership
    does not depend on the other heliostats' row counts: a heliostat that gains rows changes only
    its own chunk (and, when it crosses into another band, the chunks after it in both bands).
    """
    groups: dict = {}
    for hid in sorted(items):
        h = helio.loc[hid]
        key = (str(h["kinematic_type"]), str(h["actuator_type"]),
               tuple(bool(x) for x in selected[hid]["free"].tolist()))
        groups.setdefault(key, []).append(hid)
    size = lambda hid: (len(items[hid].rows), hid)  # noqa: E731
    chunks = []
    for key in sorted(groups):
        members = groups[key]
        if len(members) <= batch_size:
            chunks.append(sorted(members, key=size))
            continue
        bands: dict[int, list[str]] = {}
        for hid in members:
            bands.setdefault(len(items[hid].rows) // ROW_BAND, []).append(hid)
        for band in sorted(bands):
            ids = bands[band]
            chunks += [sorted(ids[i:i + batch_size], key=size)
                       for i in range(0, len(ids), batch_size)]
    return chunks


def _chunk_digest(chunk: Sequence[str], digests: Mapping[str, str]) -> str:
    return hashlib.sha256(json.dumps([[h, digests[h]] for h in chunk]).encode()).hexdigest()


@dataclass
class SweepPlan:
    """The chunks a sweep trains and those it keeps from the previous run."""

    compute: list[list[str]]                 # chunks trained in this run
    reuse: list[list[str]] = field(default_factory=list)   # chunks kept from the previous run
    removed: list[str] = field(default_factory=list)       # heliostats of the previous run gone
    why: str = ""                            # why every chunk is trained, when it is

    @property
    def partial(self) -> bool:
        return bool(self.reuse) or bool(self.removed)

    @property
    def reused_ids(self) -> list[str]:
        return sorted(h for c in self.reuse for h in c)

    def everything(self, why: str) -> "SweepPlan":
        """The plan that trains every chunk, for ``why``."""
        return SweepPlan(self.compute + self.reuse, [], [], why)

    def summary(self) -> dict:
        return {"unchanged": False, "computed": sum(map(len, self.compute)),
                "reused": sum(map(len, self.reuse)), "removed": len(self.removed),
                "chunks_computed": len(self.compute), "chunks_reused": len(self.reuse),
                "why_all": self.why or None}


def plan_sweep(txn, key: str, digests: Mapping[str, str], chunks: Sequence[Sequence[str]],
               incremental: bool) -> SweepPlan:
    """Record ``key``, the heliostats' ``digests`` and the ``chunks`` (by digest) in the run's
    manifest and decide which chunks to train: all of them unless ``incremental`` and the previous
    committed sweep recorded the same field key; then a chunk whose digest (its heliostats, in
    order, with their digests) the previous run recorded is kept."""
    by_digest = {_chunk_digest(c, digests): list(c) for c in chunks}
    txn.extra[INCREMENTAL_KEY] = {"field_key": key, "code": code_identity(),
                                  "heliostats": dict(sorted(digests.items())),
                                  "chunks": sorted(by_digest)}
    everything = SweepPlan([list(c) for c in chunks])
    if not incremental:
        return everything.everything("not --incremental")
    prev = txn.previous.data.get(INCREMENTAL_KEY) if txn.previous is not None else None
    if (not isinstance(prev, dict) or not isinstance(prev.get("chunks"), list)
            or not isinstance(prev.get("heliostats"), dict)):
        return everything.everything("the previous sweep recorded no per-chunk inputs")
    if prev.get("field_key") != key:
        return everything.everything("a field-wide input changed (options, seeds, code, the "
                                     "study's heliostats or fit-coarse's solver options)")
    kept = set(prev["chunks"])
    return SweepPlan([c for d, c in by_digest.items() if d not in kept],
                     [c for d, c in by_digest.items() if d in kept],
                     sorted(str(h) for h in prev["heliostats"] if h not in digests))


def _previous_tables(workdir: Path, plan: SweepPlan) -> dict:
    """The previous sweep's rows of the heliostats ``plan`` keeps, per artifact."""
    ids = plan.reused_ids
    return {s: reused_rows(read_artifact(workdir, s), ids)
            for s in (SWEEP, SELECTION, SELECTED_PREDICTIONS)}


def _keep_models(workdir: Path, txn, ids: Sequence[str], hashes: dict) -> None:
    """Write the previous sweep's selected models of ``ids`` again in this run, their weights as
    they are and their configuration recording this run's inputs (``hashes``), as a full rerun
    would record them; a heliostat whose selection is coarse has none."""
    for hid in ids:
        got = read_model(workdir, "sweep", "selected", hid,
                         hint=f"`heliocal sweep --workdir {workdir}`")
        if got is None:
            continue
        cfg, state = got
        cfg = {k: v for k, v in cfg.items() if k != "weights_sha256"}
        write_model(txn, "selected", hid, state, {**cfg, "inputs": hashes})


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
