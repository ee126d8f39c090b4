"""``update``: a day's new calibration rows through every stage a work directory has run, in one
process.

``heliocal update NEW_LOG --workdir W`` does what a plant would otherwise type as six commands:
``ingest NEW_LOG --workdir W --append``, then ``split-knn``, ``fit-coarse``, ``fit-hybrid``,
``sweep`` and ``report`` with ``--incremental``. Each later stage runs only where ``W`` holds a
committed run of it, and with the options that run recorded in its manifest (``options``, the
very dictionary ``--incremental`` compares), so every stage recomputes the heliostats whose inputs
changed and keeps the others, and the artifacts are those of the six commands
(``tests/test_update.py`` compares them). The new log is read with the ingest options ``W``'s
last ingest recorded. Without a log the stages alone run: after a failed update (its rows are
then ingested already) or after a code change.

What the one process saves over six: the imports (torch, pandas, scikit-learn, heliocal) happen
once, one pool of worker processes serves every stage, its fork server importing every
stage's modules once (:func:`heliocal.pipeline.runtime.parallel.warm_up`), and an artifact that
several stages read with the same request is decoded once
(:func:`heliocal.pipeline.artifacts.store.kept_reads`).

Paths in the recorded options (``--properties``, ``--tower``, ``--prior-from``) are used as
recorded: run the update from the folder the stages were run from, as ``make`` does. Options that
decide no result are not recorded and take their defaults (``fit-coarse --batch-size``,
``ingest --batch-rows``, the scheduler); ``workers`` applies to every stage.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from ..artifacts.manifests import load_manifest
from ..artifacts.store import kept_reads
from ..errors import InputError, check_int
from ..runtime.parallel import STAGE_PRELOADS, default_workers, shared_pool, warm_up

__all__ = ["UPDATE_STAGES", "StageRun", "recorded_runs", "run_update"]

#: The stages an update runs after ``ingest --append``, in pipeline order.
UPDATE_STAGES = ("split-knn", "fit-coarse", "fit-hybrid", "sweep", "report")

#: Where each stage's manifest lives, relative to the work directory (the report's: in its
#: default folder; a report written elsewhere with ``--out`` is not updated).
_MANIFEST_FOLDER = {"report": "report"}


@dataclass(frozen=True)
class StageRun:
    """A stage's committed run, to be run again: its name and the keyword arguments of its
    ``run_*`` function that repeat the recorded options."""

    stage: str
    kwargs: dict


def _recorded(workdir: Path, stage: str) -> tuple[dict, int | None] | None:
    """The recorded options and seed of ``stage``'s committed run in ``workdir``, or ``None``
    when it never ran there."""
    manifest = load_manifest(workdir / _MANIFEST_FOLDER.get(stage, ""), stage)
    if manifest is None:
        return None
    return manifest.data.get("options") or {}, manifest.data.get("seed")


def _refuse_partial(workdir: Path, stage: str, options: dict) -> None:
    """An update recomputes whole stages; a committed run of some heliostats cannot be one."""
    if options.get("heliostats"):
        raise InputError(f"{workdir}'s last {stage} ran on some heliostats only (--heliostat); an "
                         f"update keeps whole stages up to date: run `heliocal {stage} --workdir "
                         f"{workdir}` without --heliostat once, then update")


def _refuse_other_modes(workdir: Path, mode: str) -> None:
    """fit-hybrid's manifest records its last mode only; the models of another mode would stay
    those of the old rows, so an update refuses a work directory that holds them."""
    from ..artifacts.schemas import HYBRID_PREDICTIONS
    from ..artifacts.store import artifact_present, read_artifact

    if not artifact_present(workdir, HYBRID_PREDICTIONS):
        return
    modes = sorted(set(read_artifact(workdir, HYBRID_PREDICTIONS, columns=["model"])["model"]))
    others = [m for m in modes if m != mode]
    if others:
        raise InputError(f"{workdir} holds fit-hybrid models of the modes {', '.join(modes)}, "
                         f"and an update repeats the last fit-hybrid run only ({mode}): update "
                         "stage by stage (`heliocal ingest NEW_LOG --append`, then each stage "
                         "with --incremental, fit-hybrid once per mode)")


def _split_kwargs(workdir: Path, o: dict, seed: int | None) -> dict:
    return {k: o[k] for k in ("method", "k", "n_test", "n_val", "n_train", "metric", "seed")}


def _coarse_kwargs(workdir: Path, o: dict, seed: int | None) -> dict:
    kwargs = {k: o[k] for k in ("preset", "loss", "f_scale_mrad", "robust_start", "solver",
                                "rolling_origins", "prior", "prior_from")}
    # "none": a run without regimes, which only a measurement switch gives (not an option)
    kwargs["regime_steps"] = o["regime_steps"] if o["regime_steps"] != "none" else "candidates"
    return kwargs


def _hybrid_kwargs(workdir: Path, o: dict, seed: int | None) -> dict:
    from ..models.config import FineConfig
    from ..models.pretrained import PretrainConfig

    _refuse_other_modes(workdir, o["mode"])
    return {"mode": o["mode"], "weight_decay": o["weight_decay"], "seed": seed,
            "config": FineConfig.from_dict(o["fine_config"]),
            "pretrain_config": PretrainConfig.from_dict(o["pretrain_config"]),
            "batch_size": o["batch_size"]}


def _sweep_kwargs(workdir: Path, o: dict, seed: int | None) -> dict:
    from ..models.config import FineConfig, PathConfig, ScreenConfig
    from ..models.gp import GPConfig
    from ..models.pretrained import PretrainConfig
    from ..models.selection import SelectionRule

    study = o["study"]
    return {"n_train": None if o["n_train"] == "ladder" else o["n_train"],
            "weight_decays": o["weight_decays"], "seeds": o["seeds"],
            "presets": None if o["presets"] == "fit-coarse's" else o["presets"],
            "baselines": o["baselines"], "extra_bands": [tuple(b) for b in o["extra_bands"]],
            "config": FineConfig.from_dict(o["fine_config"]),
            "pretrain_config": PretrainConfig.from_dict(o["pretrain_config"]),
            "study": study if study is None or isinstance(study, int) else list(study),
            "study_seed": o["study_seed"], "path": PathConfig(**o["path"]),
            "batch_size": o["batch_size"], "select_pretrained": o["select_pretrained"],
            "time_split": o["time_split"], "gp": o["gp_config"] is not None,
            "gp_config": GPConfig.from_dict(o["gp_config"]) if o["gp_config"] else None,
            "rule": SelectionRule(**o["rule"]), "screen": ScreenConfig(**o["screen"])}


def _report_kwargs(workdir: Path, o: dict, seed: int | None) -> dict:
    return {"out_dir": workdir / "report", "alert_mrad": o["alert_mrad"],
            "floor_mrad": o["floor_mrad"], "figures": o["figures"],
            "figures_for": o["figures_for"]}


#: Per stage: its recorded options -> its run function's keyword arguments.
_KWARGS: dict[str, Callable[[Path, dict, int | None], dict]] = {
    "split-knn": _split_kwargs, "fit-coarse": _coarse_kwargs, "fit-hybrid": _hybrid_kwargs,
    "sweep": _sweep_kwargs, "report": _report_kwargs}


def recorded_runs(workdir: str | Path) -> list[StageRun]:
    """The stages of :data:`UPDATE_STAGES` that ``workdir`` holds a committed run of, in pipeline
    order, each with its recorded options as keyword arguments. An :class:`InputError` when one
    of them ran on some heliostats only or its manifest lacks an option (a run by an older
    heliocal: run that stage by hand once)."""
    workdir = Path(workdir)
    runs = []
    for stage in UPDATE_STAGES:
        recorded = _recorded(workdir, stage)
        if recorded is None:
            continue
        options, seed = recorded
        _refuse_partial(workdir, stage, options)
        try:
            kwargs = _KWARGS[stage](workdir, options, seed)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{workdir}'s {stage} manifest does not record the options an update "
                             f"repeats ({type(exc).__name__}: {exc}); run `heliocal {stage} "
                             f"--workdir {workdir}` once by hand, then update") from None
        runs.append(StageRun(stage, kwargs))
    return runs


def _ingest_options(workdir: Path):
    """The :class:`~heliocal.pipeline.io.staged.IngestOptions` of ``workdir``'s last ingest."""
    from ..io.staged import IngestOptions

    recorded = _recorded(workdir, "ingest")
    if recorded is None:
        raise InputError(f"{workdir} has no ingested measurements to update: run `heliocal ingest "
                         f"SOURCE --workdir {workdir}` and the stages first")
    o = {k: v for k, v in recorded[0].items() if k not in ("sources", "append")}
    for key in ("tower", "properties"):
        o[key] = None if o.get(key) is None else Path(o[key])
    o["location"] = None if o.get("location") is None else tuple(o["location"])
    try:
        return IngestOptions(**o)
    except TypeError as exc:
        raise InputError(f"{workdir}'s ingest manifest does not record the options an update "
                         f"repeats ({exc}); run `heliocal ingest ... --append` by hand") from None


#: Each stage's run function: (module of this package, function).
_RUN_FUNCTIONS = {"split-knn": ("split", "run_split"),
                  "fit-coarse": ("fit_coarse", "run_fit_coarse"),
                  "fit-hybrid": ("fit_hybrid", "run_fit_hybrid"),
                  "sweep": ("sweep", "run_sweep"), "report": ("report", "run_report")}


def _stage_function(stage: str) -> Callable:
    """The ``run_*`` function of ``stage`` (its module imported when it runs)."""
    module, name = _RUN_FUNCTIONS[stage]
    return getattr(importlib.import_module(f"{__package__}.{module}"), name)


def _computed(summary: dict) -> dict:
    """What a stage's summary says it recomputed (its ``incremental`` entry; the report's
    figures)."""
    inc = summary.get("incremental") or {}
    if inc.get("unchanged"):
        return {"unchanged": True}
    if "figures_drawn" in summary:
        return {"figures_drawn": summary["figures_drawn"], "figures_kept": summary["figures_kept"]}
    return {k: inc[k] for k in ("computed", "reused", "removed") if k in inc} or {
        "unchanged": False}


def run_update(sources: Sequence[str | Path], workdir: str | Path, *,
               workers: int | None = None) -> dict:
    """Add the rows of ``sources`` to ``workdir`` (``ingest --append`` with the work directory's
    ingest options; none: no ingest) and run every stage ``workdir`` has run again, with its
    recorded options and ``incremental``; return a summary (the ingest's, and per stage its
    seconds and what it recomputed).

    Every check that can fail before anything is written runs first (the recorded runs, the
    ingest options). A stage that fails leaves the stages before it committed (each stage is one
    transaction) and the later ones as they were: ``run_update([], workdir)`` finishes them."""
    workdir = Path(workdir)
    sources = [Path(s) for s in sources]
    workers = default_workers() if workers is None else check_int(workers, "workers", "update", 1)
    ingest_options = _ingest_options(workdir)   # also: was anything ingested here at all
    runs = recorded_runs(workdir)
    t_start = time.perf_counter()
    out: dict = {"workdir": str(workdir), "ingest": None, "stages": []}
    with shared_pool(), kept_reads():   # the stages read the same artifacts in turn
        warm_up(list(dict.fromkeys(m for run in runs for m in STAGE_PRELOADS.get(run.stage, ()))),
                workers=workers)
        if sources:
            from .ingest import run_ingest

            t0 = time.perf_counter()
            out["ingest"] = {**run_ingest(sources, workdir, ingest_options, append=True),
                             "seconds": time.perf_counter() - t0}
        for run in runs:
            t0 = time.perf_counter()
            extra = {} if run.stage == "split-knn" else {"workers": workers}
            summary = _stage_function(run.stage)(workdir, **run.kwargs, **extra,
                                                 incremental=True)
            out["stages"].append({"stage": run.stage, "seconds": time.perf_counter() - t0,
                                  **_computed(summary)})
    out["seconds"] = time.perf_counter() - t_start
    return out
