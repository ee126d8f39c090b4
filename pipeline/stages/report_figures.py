"""The report's figures, drawn, or with ``report --incremental`` kept from the previous report
when nothing a figure is drawn from has changed.

A figure is a :class:`~heliocal.pipeline.report.render.FigureTask`: its kind, file name, caption,
heliostat and arguments (the small frames and numbers it is drawn from) are everything the drawing
reads besides the code. So a figure's digest is the by-value digest of its task, the code of
``pipeline/`` and the matplotlib version (:func:`figure_digest`), and the report's manifest records
each figure's digest with its outcome (drawn, or why not). An incremental report draws the figures
whose digest is new and takes the others' PNG bytes from the previous committed report (checked
against that report's manifest); a field figure (the error distribution, paper 000's figures
across the field) is drawn again whenever one heliostat's numbers in it moved, a heliostat's own
figures only when its own data did. Pages, tables and metrics.json are always computed again:
they are made from the whole field and cost little beside the figures.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Sequence

from ..artifacts.incremental import INCREMENTAL_KEY, code_identity, value_digest
from ..artifacts.manifests import CommittedWorkdir
from ..artifacts.paths import safe_name
from ..errors import HeliocalError
from ..report.render import FigureTask, render_task
from ..runtime.parallel import map_tasks

__all__ = ["figure_digest", "drawn_or_kept"]

log = logging.getLogger("heliocal.report")

#: Fewer figures than this are drawn in this process: starting worker processes (each imports
#: matplotlib) costs more than it saves.
MIN_PARALLEL_FIGURES = 40

#: At most about this many figures go to a worker at once: a task carries its heliostat's rows,
#: so a chunk of a thousand (a quarter of a worker's share of 8,000 figures) held a gigabyte in
#: each worker.
FIGURES_PER_CHUNK = 50


def figure_digest(task: FigureTask) -> str:
    """SHA-256 (hex) of everything a figure is drawn from: its task by value, the code and the
    matplotlib version."""
    import matplotlib

    return value_digest({"kind": task.kind, "filename": task.filename, "caption": task.caption,
                         "heliostat": task.heliostat, "args": task.args,
                         "code": code_identity(), "matplotlib": matplotlib.__version__})


def _previous(txn, out: Path, digests: dict[str, str]) -> dict[str, tuple]:
    """file name -> ``(png or None, why)`` of the previous report's figures whose recorded digest
    is this run's, their PNG bytes read through the previous report's manifest; a figure whose
    file cannot be read (removed, changed since) is drawn again."""
    prev = txn.previous.data.get(INCREMENTAL_KEY) if txn.previous is not None else None
    recorded = prev.get("figures") if isinstance(prev, dict) else None
    if not isinstance(recorded, dict):
        return {}
    committed = CommittedWorkdir.of(out)
    kept = {}
    for name, digest in digests.items():
        rec = recorded.get(name)
        if not (isinstance(rec, dict) and rec.get("digest") == digest):
            continue
        why = rec.get("why")
        if why is not None:
            kept[name] = (None, str(why))
            continue
        try:
            kept[name] = (committed.read("report", f"figures/{safe_name(name)}").data, None)
        except HeliocalError as exc:   # gone or changed since: drawn again
            log.info("figure %s of the previous report is drawn again: %s", name, exc)
    return kept


def drawn_or_kept(txn, out: Path, tasks: Sequence[FigureTask], workers: int,
                  incremental: bool) -> tuple[dict[str, tuple], dict]:
    """Every task's ``(png or None, why)`` by file name, and how many were drawn and kept.

    Records each figure's digest and outcome in the report's manifest (``txn``: the report's
    transaction on ``out``); with ``incremental``, a figure the previous report recorded with
    the same digest is taken from it instead of drawn."""
    digests = {t.filename: figure_digest(t) for t in tasks}
    kept = _previous(txn, out, digests) if incremental else {}
    todo = [t for t in tasks if t.filename not in kept]
    n_workers = workers if len(todo) >= MIN_PARALLEL_FIGURES else 1
    per_worker = max(4, math.ceil(len(todo) / (n_workers * FIGURES_PER_CHUNK)))
    drawn = dict(zip((t.filename for t in todo),
                     map_tasks(render_task, todo, workers=n_workers,
                               chunks_per_worker=per_worker, torch_threads=False)
                     if todo else []))
    results = {t.filename: kept[t.filename] if t.filename in kept else drawn[t.filename]
               for t in tasks}
    txn.extra[INCREMENTAL_KEY] = {
        "code": code_identity(),
        "figures": {name: {"digest": digests[name], "why": results[name][1]}
                    for name in sorted(digests)}}
    return results, {"drawn": len(todo), "kept": len(kept)}
