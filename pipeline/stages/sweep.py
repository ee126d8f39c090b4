"""``sweep``: the model every heliostat's ``aim`` uses, and the training-size study.

Two parts with different purposes:

**Production selection** (every heliostat, its full training set, i.e. the ``train`` rows of
split.parquet that ``fit-coarse`` fitted on). The coarse candidate *is* ``fit-coarse``'s
selected fit, read from coarse_params.parquet and not refitted: its errors in sweep.parquet and
selection.parquet are ``fit-coarse``'s, computed from the same predictions
(coarse_predictions.parquet). The hybrid is trained on top of it, for every Fourier band set
(:func:`hybrid_variants`), weight decay and seed, each an ensemble of ``FineConfig.ensemble``
networks whose deviations are averaged (:func:`heliocal.pipeline.models.network.ensemble_seeds`).
Heliostats of one kinematic type, actuator type and coarse preset train together, ``batch_size``
at a time, as one batched torch program per weight decay (as ``fit-hybrid`` does, with
:func:`heliocal.pipeline.models.training.stack_problems`); the weight decays are trained along a path
from strong to weak (:func:`~.sweep_path.train_path`, :class:`PathConfig`). The selection
(``selection.parquet``) is the candidate ensemble with the lowest mean validation error, where
the coarse model is always a candidate, so the selected model is never worse than
``fit-coarse``'s on validation. A hybrid must beat the coarse model's validation error by
:data:`MIN_IMPROVEMENT` (relative) to be chosen; why that margin is in docs/hybrid.md
("Selection"). The selected ensemble's weights are written to ``DIR/hybrid/selected/<HID>.pt``
(+ JSON), in the layout of ``fit-hybrid``, for ``aim`` and ``report``.

**Training-size study** (paper 000, figs. 6 and 9a; a seeded sample of ``study`` heliostats,
:func:`study_heliostats`). Per training size below the full one (the ``n_train`` training rows
with the largest kNN distance, :func:`heliocal.pipeline.stages.split.restrict_training`) every coarse
preset is refitted with :func:`heliocal.pipeline.models.coarse_presets.fit_presets`, the function
``fit-coarse`` fits with, with the solver and options ``fit-coarse`` recorded in
coarse_params.parquet, under the field prior ``fit-coarse`` gave the heliostat (if any) and
each size its own robust start, so a study point is what ``fit-coarse`` would give with that
many rows; with a field prior each preset is also refitted without it, model
``<preset>+no-field-prior`` (:mod:`.study_prior`). The hybrid of each size trains on that size's
refit of the selected preset; the ``nn-only`` baseline (all sizes) and the paper-002
``pretrained-nn`` baseline are trained for the study heliostats only. The full-size hybrid
points of a study heliostat are its production rows.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.incremental import carry_over_unchanged, field_key, mark_rerunnable
from ..artifacts.manifests import current_transaction
from ..artifacts.schemas import SELECTION
from ..artifacts.store import read_artifact
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..errors import ParameterError, check_float, check_int
from ..models.config import FineConfig, PathConfig, ScreenConfig, ensemble_seeds
from ..models.fade import TIME_FADE_DAYS
from ..models.gp import GPConfig
from ..models.gp_heliostat import fit_heliostat_gps
from ..models.pretrained import PretrainConfig
from ..models.selection import SelectionRule
from ..models.training import build_problem, ensemble_errors_mrad
from ..runtime.parallel import default_workers, map_tasks, warm_up_stage
from ..runtime.process_state import deterministic_torch, restores_process_state
from ..vocabulary import (DEFAULT_STUDY, HYBRID_BATCH_SIZE, MIN_IMPROVEMENT, OCTAVE_BANDS,
                          NeuralBaseline)
from .fit_coarse import coarse_fit_options, coarse_row_parameters
from .forward import add_sweep_time_split
from .selection import CandidatePool, apply_forward_checks, study_gps
from .split import restrict_training
from .study_prior import heliostat_priors, prior_rows_of, study_coarse_rows
from .sweep_path import path_order, train_candidates, train_path
from .sweep_increment import (SweepPlan, chunk_size, plan_sweep, sweep_chunks,
                              write_sweep_outputs)
from .sweep_inputs import (SweepHeliostat, SweepInputs, SweepInputsTable, fit_pretrained_errors,
                           read_sweep_inputs, sweep_row)

__all__ = ["default_ladder", "weight_decay_grid", "run_sweep", "hybrid_variants", "MIN_IMPROVEMENT",
           "train_path", "study_heliostats"]

log = logging.getLogger("heliocal.sweep")

LADDER = (5, 10, 20, 40, 60, 100, 150, 200, 300, 400)


def default_ladder(n_available: int, minimum: int = 5) -> list[int]:
    """Training sizes 5, 10, 20, 40, 60, 100, 150, ... below ``n_available``, plus all of them."""
    sizes = [n for n in LADDER if minimum <= n < n_available]
    return sizes + [n_available]


def weight_decay_grid(wd_max: float = 1.0, wd_min: float = 1e-6, per_decade: int = 1) -> list[float]:
    """Log-spaced weight decays from ``wd_max`` down to ``wd_min`` (``per_decade`` per decade), plus 0."""
    decades = math.log10(wd_max / wd_min)
    n = int(round(decades * per_decade)) + 1
    return [float(x) for x in np.logspace(math.log10(wd_max), math.log10(wd_min), n)] + [0.0]


def hybrid_variants(config: FineConfig, extra_bands: Sequence[tuple] = (OCTAVE_BANDS,)):
    """The swept hybrids: ``("hybrid", config)`` and, per extra band set that differs from the
    config's, ``("hybrid-octaves", ...)`` for :data:`OCTAVE_BANDS`, else ``("hybrid-bands-<i>",
    ...)``. The band set is a hyperparameter like the weight decay: every variant is a
    candidate of the selection."""
    out = [("hybrid", config)]
    for i, bands in enumerate(extra_bands, start=1):
        bands = tuple(float(b) for b in bands)
        if bands == tuple(config.fourier_bands) or any(c.fourier_bands == bands for _, c in out):
            continue
        name = "hybrid-octaves" if bands == OCTAVE_BANDS else f"hybrid-bands-{i}"
        out.append((name, dataclasses.replace(config, fourier_bands=bands)))
    return out


# ------------------------------------------------------------------------------------------------
# production selection: a chunk of heliostats, full training size
# ------------------------------------------------------------------------------------------------
def _select_chunk(items: Sequence[SweepInputs], variants, weight_decays, seeds, path,
                  pretrain_config: PretrainConfig | None = None,
                  gp_config: GPConfig | None = None,
                  rule: SelectionRule = SelectionRule(),
                  screen: ScreenConfig = ScreenConfig(enabled=False)) -> list[dict]:
    """The full-size candidates and the selection of a chunk of heliostats that share one
    kinematic type, actuator type and coarse preset (one batched program per weight decay);
    with ``gp_config`` the GP correction, with ``pretrain_config`` the pre-trained network (first
    seed) are candidates too. With ``screen`` enabled only the heliostats whose screen passes
    train the whole weight-decay path (:func:`~.sweep_path.train_candidates`).
    Each heliostat's choice is its :class:`CandidatePool`'s."""
    helios = [SweepHeliostat.of(item) for item in items]
    pools = [CandidatePool(h, rule) for h in helios]
    out_rows: list[list[dict]] = [[] for _ in helios]
    for h, rows in zip(helios, out_rows):
        # the coarse presets exactly as fit-coarse fitted them (its predictions)
        for model, frame in h.coarse.items():
            if model == "nominal":
                continue
            rows.append(sweep_row(h.hid, model, h.n_full, float("nan"), 0,
                             frame["error_mrad"].to_numpy(np.float64), h.labels, h.train,
                             h.test_distance, model, 0.0))
    verdicts = train_candidates(helios, pools, out_rows, variants, weight_decays, seeds, path,
                                 screen, rule)
    for pool, verdict in zip(pools, verdicts):
        pool.screen, pool.screen_gain = verdict.status, verdict.gain
    for i, h in enumerate(helios):
        if gp_config is not None:
            fits = fit_heliostat_gps(h.rows, h.labels, h.spec, h.data, coarse_row_parameters(
                h.selected, h.rows["timestamp"]), gp_config, pools[i].weights,
                time_length_days=TIME_FADE_DAYS)
            for name, fit in pools[i].add_gp(fits, gp_config):
                out_rows[i].append(sweep_row(h.hid, name, h.n_full, float("nan"), gp_config.seed,
                                             fit.errors, h.labels, h.train, h.test_distance,
                                             h.selected["preset"], fit.wall_time_s,
                                             fit.fade_length_deg))
        if pretrain_config is not None:
            model, info, normal, position, err, wall = fit_pretrained_errors(
                h, h.selected["params"], h.labels, seeds[0], pretrain_config)
            out_rows[i].append(sweep_row(h.hid, "pretrained-nn", h.n_full, float("nan"), seeds[0],
                                         err, h.labels, h.train, h.test_distance,
                                         h.selected["preset"], wall))
            pools[i].add_pretrained(model, info, normal, position, err, seeds[0], pretrain_config)
    results = []
    for rows, pool in zip(out_rows, pools):
        choice = pool.choose()
        results.append({"rows": rows, "selection": choice.selection,
                        "selected_state": choice.state, "predictions": choice.predictions,
                        "choice": choice})
    return results


# ------------------------------------------------------------------------------------------------
# the training-size study: one heliostat, every size
# ------------------------------------------------------------------------------------------------
def _study_heliostat(item, sizes, presets, variants, weight_decays, seeds, path,
                     pretrain_config, baselines, coarse_options, gp_config: GPConfig | None = None,
                     rule: SelectionRule = SelectionRule(), prior_rows=None) -> dict:
    """Study rows of one heliostat: every size below the full one (refits with fit-coarse's
    function, options and field prior, ``prior_rows``: :func:`~.study_prior.prior_rows_of`'s
    frame of it; the hybrids, with ``gp_config`` the GP correction), and the baselines at
    every size."""
    h = SweepHeliostat.of(item)
    hid, labels = h.hid, h.labels
    out_rows: list[dict] = []
    masks, dists = {}, {}
    order = pd.Series(np.arange(len(h.rows)), index=h.rows["measurement_id"].to_numpy())
    for n in sizes:
        restricted = restrict_training(h.split_rows, n)
        train_ids = restricted.loc[restricted["split"] == "train", "measurement_id"]
        m = np.zeros(len(h.rows), bool)
        m[order.loc[train_ids].to_numpy()] = True
        masks[n] = m
        test = restricted["split"] == "test"
        dists[n] = (float(restricted.loc[test, "nearest_train_distance_deg"].mean())
                    if test.any() else float("nan"))
    base_preset = h.selected["base_preset"]   # a regime-aware model's preset (refitted plain)
    small = [n for n in sizes if n < h.n_full]
    fitted = tuple(dict.fromkeys(tuple(presets) + (base_preset,)))
    # coarse presets: each size its own fit-coarse (own robust start; under the field prior
    # fit-coarse gave the heliostat, and without it, :mod:`.study_prior`)
    rows, bases = study_coarse_rows(h, small, fitted, masks, dists, base_preset, coarse_options,
                                    heliostat_priors(prior_rows, h.nominal))
    out_rows += rows
    bases[h.n_full] = h.selected["params"]
    val_mask = labels == "validation"
    if gp_config is not None and small:
        for n, fit in study_gps(h, {n: masks[n] for n in small}, bases, gp_config, rule).items():
            out_rows.append(sweep_row(hid, "gp", n, float("nan"), gp_config.seed, fit.errors,
                                      labels, masks[n], dists[n], base_preset, fit.wall_time_s,
                                      fit.fade_length_deg))

    def train(kind, cfg, members, base_of, wds, path_=path):
        """members (n, seed): ensembles of K networks, trained along the weight-decay path."""
        k_ens = cfg.ensemble
        nets = [m for m in members for _ in range(k_ens)]
        problem = build_problem(h.rows, h.hrow, h.selected["params"], h.selected["free"], cfg)
        problem.base = torch.stack([base_of(n) for n, _ in nets]).unsqueeze(-2)   # (M K, 1, 28)
        tm = np.stack([masks[n] for n, _ in nets])
        seeds_ = [x for _, s in members for x in ensemble_seeds(s, k_ens)]
        for wd, result in train_path(problem, tm, val_mask, seeds_, wds, cfg, path_):
            wall = result.wall_time_s / len(members)
            with torch.no_grad():
                err = ensemble_errors_mrad(problem, result.layers, k_ens).numpy()
            for k, (n, s) in enumerate(members):
                out_rows.append(sweep_row(hid, kind, n, wd if kind.startswith("hybrid") else float("nan"),
                                     s, err[k], labels, masks[n], dists[n], base_preset, wall))

    members = [(n, s) for n in small for s in seeds]
    if members:
        for kind, cfg in variants:
            train(kind, cfg, members, lambda n: bases[n], weight_decays)
    if "nn-only" in baselines:
        train("nn-only", variants[0][1], [(n, s) for n in sizes for s in seeds],
              lambda n: h.nominal, [0.0])
    if "pretrained-nn" in baselines:
        for n in sizes:
            lab = np.where(masks[n], "train", np.where(labels == "train", "unused", labels))
            for s in seeds:
                *_, e, wall = fit_pretrained_errors(h, bases[n], lab, int(s), pretrain_config)
                out_rows.append(sweep_row(hid, "pretrained-nn", n, float("nan"), s, e, labels,
                                     masks[n], dists[n], base_preset, wall))
    return {"rows": out_rows}


def _sweep_task(task):
    """One task of the sweep for :func:`map_tasks`: a production chunk or a study heliostat."""
    deterministic_torch()
    kind, args = task
    if kind == "select":
        return _select_chunk(*args)
    return [_study_heliostat(*args)]


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------


def study_heliostats(ids: Sequence[str], study: int | Sequence[str] | None,
                     seed: int = 0) -> list[str]:
    """The heliostats of the training-size study: ``study`` ids given, or a seeded random choice
    of ``study`` of ``ids`` (all of them when there are no more; ``None``: all; 0: none)."""
    ids = sorted(ids)
    if study is None:
        return ids
    if not isinstance(study, (int, np.integer)):
        chosen = sorted(set(str(h) for h in study))
        unknown = [h for h in chosen if h not in ids]
        if unknown:
            raise ParameterError(f"The 'study' parameter of sweep must name heliostats of the "
                                 f"sweep. Got {unknown!r} instead.")
        return chosen
    k = check_int(study, "study", "sweep", 0)
    if k >= len(ids):
        return ids
    rng = np.random.default_rng(check_int(seed, "study_seed", "sweep", 0))
    return sorted(rng.choice(np.array(ids, dtype=object), size=k, replace=False).tolist())


def _checked_seeds(seeds: Sequence[int]) -> list[int]:
    seeds = [check_int(s, "seeds", "sweep", 0) for s in seeds]
    if not seeds:
        raise ParameterError("The 'seeds' parameter of sweep must list at least one seed. Got "
                             "[] instead.")
    return seeds


def _checked_baselines(baselines: Sequence[str]) -> tuple[str, ...]:
    for b in baselines:
        if b not in NeuralBaseline.values():
            raise ParameterError(f"The 'baselines' parameter of sweep must list "
                                 f"{' and/or '.join(NeuralBaseline.values())}. Got {b!r} instead.")
    return tuple(baselines)


def _checked_weight_decays(weight_decays: Sequence[float] | None) -> list[float]:
    """The weight decays (default :func:`weight_decay_grid`) in path order, each checked."""
    weight_decays = path_order(weight_decays if weight_decays is not None
                                else weight_decay_grid())
    for wd in weight_decays:
        check_float(wd, "weight_decays", "sweep", 0.0, None)
    if not weight_decays:
        raise ParameterError("The 'weight_decays' parameter of sweep must list at least one "
                             "weight decay. Got [] instead.")
    return weight_decays


def _study_sizes(item: SweepInputs, n_train: Sequence[int] | None) -> list[int]:
    """The study's training sizes of one heliostat: ``n_train`` capped at its training rows
    (which are always one of them), else :func:`default_ladder`."""
    n_full = int((item.split_rows["split"] == "train").sum())
    return (sorted({min(check_int(n, "n_train", "sweep", 2), n_full) for n in n_train} | {n_full})
            if n_train else default_ladder(n_full))


def _study_presets(item: SweepInputs, presets: Sequence[str] | None) -> tuple[str, ...]:
    """The coarse presets the study refits: ``presets``, else those fit-coarse fitted (no
    regime-aware models)."""
    return tuple(presets) if presets else tuple(
        m for m in item.coarse if m != "nominal" and "+" not in m)


def _study_tasks(workdir: Path, items: dict, studied: Sequence[str], computed: set[str],
                 n_train, presets, shared: tuple) -> list[tuple]:
    """The study's tasks of the heliostats ``studied`` that the run trains (``computed``),
    each with its field-prior rows (:func:`~.study_prior.prior_rows_of`; None without one).
    ``shared``: :func:`_study_heliostat`'s arguments from ``variants`` to ``rule``."""
    ids = [h for h in studied if h in computed]
    prior_rows = prior_rows_of(workdir, ids)
    return [("study", (items[h], _study_sizes(items[h], n_train),
                       _study_presets(items[h], presets), *shared, prior_rows.get(h)))
            for h in ids]


@locks_workdir("sweep")
@stage_transaction("sweep")
@restores_process_state
def run_sweep(workdir: str | Path, *, n_train: Sequence[int] | None = None,
              weight_decays: Sequence[float] | None = None, seeds: Sequence[int] = (0,),
              presets: Sequence[str] | None = None, baselines: Sequence[str] = ("nn-only",),
              config: FineConfig | None = None, pretrain_config: PretrainConfig | None = None,
              heliostats: Sequence[str] | None = None, workers: int | None = 1,
              scheduler: str = "local", dask_address: str | None = None, progress=None,
              extra_bands: Sequence[Sequence[float]] = (OCTAVE_BANDS,),
              study: int | Sequence[str] | None = DEFAULT_STUDY, study_seed: int = 0,
              path: PathConfig | None = None, batch_size: int = HYBRID_BATCH_SIZE,
              select_pretrained: bool = False, time_split: bool = False, gp: bool = True,
              gp_config: GPConfig | None = None, rule: SelectionRule | None = None,
              incremental: bool = False, screen: ScreenConfig | None = None) -> dict:
    """The ``sweep`` stage: write sweep.parquet, selection.parquet and selected_predictions.parquet
    (and ``hybrid/selected/``), return a summary.

    Parameters
    ----------
    n_train : training sizes of the study (default :func:`default_ladder`); the full training
        set is always one of them, and a larger size means the full one.
    weight_decays : the path (default :func:`weight_decay_grid`), trained strong to weak.
    seeds : seeds of the ensembles (each ``config.ensemble`` networks).
    presets : coarse presets refitted in the study (default: those ``fit-coarse`` fitted).
    baselines : ``nn-only`` and/or ``pretrained-nn``, for the study heliostats.
    config, pretrain_config : the fine network and the paper-002 baseline.
    extra_bands : Fourier band sets swept besides ``config.fourier_bands`` (default: the octaves,
        model ``hybrid-octaves``; see :func:`hybrid_variants`); ``()`` sweeps only the config's.
    study, study_seed : the study's heliostats (:func:`study_heliostats`); 0 skips the study.
    path : how the weight-decay path is trained (:class:`PathConfig`).
    batch_size : heliostats per batched program of the production selection, at most (fewer
        to keep every worker busy, :func:`~.sweep_increment.chunk_size`).
    select_pretrained : the pre-trained network (first seed) is a production candidate too.
    time_split : also train the selected hybrids forward in time (:mod:`.forward`): their
        forward-in-time check (:func:`heliocal.pipeline.stages.selection.apply_forward_checks`)
        needs it; without it a selected hybrid is kept unchecked.
    gp, gp_config : the GP correction is a candidate and a line of the study (settings: default
        :class:`GPConfig` with the config's env columns and the first seed).
    rule : the selection rule (:class:`heliocal.pipeline.models.selection.SelectionRule`).
    screen : the screen that decides per heliostat whether its weight-decay path is trained
        (default :class:`ScreenConfig`, on; ``ScreenConfig(enabled=False)`` trains every path;
        :mod:`.sweep_screen`).
    workers, scheduler, dask_address, progress : as for ``fit-hybrid``.
    incremental : keep the previous sweep as it is when its inputs, options, seeds and code are
        this run's (nothing is read or trained); otherwise train again only the chunks holding a
        heliostat whose inputs changed, and keep the others' rows and models
        (:mod:`.sweep_increment`; with another option, seed or code, or with ``time_split``,
        every chunk). The summary's ``incremental`` says which.
    """
    workdir = Path(workdir)
    if heliostats and incremental:
        raise ParameterError("--incremental works out itself which heliostats to train again; "
                             "leave out --heliostat, or leave out --incremental")
    seeds, weight_decays = _checked_seeds(seeds), _checked_weight_decays(weight_decays)
    baselines = _checked_baselines(baselines)
    config = (config or FineConfig()).validated()
    pretrain_config = pretrain_config or PretrainConfig()
    path = (path or PathConfig()).validated()
    batch_size = check_int(batch_size, "batch_size", "sweep", 1)
    variants = hybrid_variants(config, extra_bands)
    gp_config = (gp_config or GPConfig(env=config.env, seed=seeds[0])).validated() if gp else None
    rule = (rule or SelectionRule()).validated()
    screen = (screen or ScreenConfig()).validated()
    request = {"n_train": list(n_train) if n_train else "ladder", "weight_decays": weight_decays,
               "seeds": seeds, "presets": list(presets) if presets else "fit-coarse's",
               "baselines": list(baselines), "extra_bands": [list(b) for b in extra_bands],
               "fine_config": config.to_dict(), "pretrain_config": pretrain_config.to_dict(),
               "study": (study if study is None or isinstance(study, (int, np.integer))
                         else list(study)),
               "study_seed": study_seed, "path": path.to_dict(), "batch_size": batch_size,
               "select_pretrained": bool(select_pretrained), "time_split": bool(time_split),
               "gp_config": gp_config.to_dict() if gp_config else None, "rule": rule.to_dict(),
               "screen": screen.to_dict(),
               "heliostats": list(heliostats) if heliostats else None}
    txn = current_transaction(workdir, "sweep")
    if incremental and not heliostats and carry_over_unchanged(txn, request):
        return _kept_summary(workdir, txn)
    mark_rerunnable(txn)
    warm_up_stage("sweep", workers=workers, scheduler=scheduler, dask_address=dask_address)
    items = read_sweep_inputs(workdir, heliostats)
    studied = study_heliostats(list(items), study, study_seed)
    coarse_options = coarse_fit_options(workdir)
    chunks_of = _chunker(items, batch_size, workers)
    plan = _plan(txn, request, items, chunks_of, studied, coarse_options, incremental,
                 heliostats, time_split)
    tasks = [("select", ([items[h] for h in chunk], variants, weight_decays, seeds, path,
                         pretrain_config if select_pretrained else None, gp_config, rule,
                         screen))
             for chunk in plan.compute]
    tasks += _study_tasks(workdir, items, studied, {h for chunk in plan.compute for h in chunk},
                          n_train, presets, (variants, weight_decays, seeds, path, pretrain_config,
                                             baselines, coarse_options, gp_config, rule))
    parts = map_tasks(_sweep_task, tasks, workers=workers, scheduler=scheduler,
                      dask_address=dask_address,
                      progress=(lambda d, t: progress(d, t, None)) if progress else None)
    results = [r for part in parts for r in part]
    chosen = sorted((r for r in results if "selection" in r),
                    key=lambda r: r["selection"]["heliostat_id"])
    add_sweep_time_split(workdir, chosen, items, variants, weight_decays, path, pretrain_config,
                         train_path, time_split, batch_size=batch_size, workers=workers,
                         scheduler=scheduler, dask_address=dask_address)
    apply_forward_checks(chosen, items)
    opts = {**request, "study_heliostats": studied, "coarse_options": coarse_options}
    selection = write_sweep_outputs(workdir, results, chosen, heliostats,
                                    plan if not heliostats else None, opts, seed=seeds[0])
    return {"workdir": str(workdir), "selection": selection.to_dict("records"),
            "study_heliostats": studied,
            "members_per_heliostat": {   # ensembles trained (seed x band set x weight decay)
                res["selection"]["heliostat_id"]: sum(
                    row["model"].startswith("hybrid") for row in res["rows"])
                for res in chosen},
            "incremental": plan.summary()}


def _chunker(items: SweepInputsTable, batch_size: int, workers: int | None):
    """``chunks_of(ids)``: the training chunks of the heliostats ``ids``, at most ``batch_size``
    each, enough to keep ``workers`` busy and a whole number of rounds of them
    (:func:`~.sweep_increment.chunk_size`, :func:`~.sweep_increment.sweep_chunks`)."""
    spread = default_workers() if workers is None else workers

    def chunks_of(ids: Sequence[str]) -> list[list[str]]:
        some = {h: items[h] for h in ids}
        helio = pd.DataFrame([item.hrow for item in some.values()], index=list(some))
        return sweep_chunks(some, {h: item.selected for h, item in some.items()}, helio,
                            batch_size, spread, chunk_size(len(ids), batch_size, spread))
    return chunks_of


def _plan(txn, request: dict, items: SweepInputsTable, chunks_of, studied: list[str],
          coarse_options: dict, incremental: bool, heliostats, time_split: bool) -> SweepPlan:
    """Which heliostats the run trains, in the chunks ``chunks_of(ids)`` makes
    (:mod:`.sweep_increment`): all of them without ``incremental``, for a run restricted to
    ``heliostats`` (which records no digests) and with ``time_split`` (the forward-in-time
    training batches the field's selected hybrids together)."""
    if heliostats:
        return SweepPlan(chunks_of(list(items)), why="a run of some heliostats (--heliostat)")
    key = field_key("sweep", request, items.schemas, {"study_heliostats": studied,
                                                      "coarse_options": coarse_options})
    plan = plan_sweep(txn, key, items.digests, chunks_of, incremental)
    if plan.partial and time_split:
        return SweepPlan(chunks_of(list(items)), why=(
            "--time-split trains the field's selected hybrids forward in time in batches of one "
            "another: every heliostat is trained again"))
    return plan


def _kept_summary(workdir: Path, txn) -> dict:
    """The summary of a run that kept the previous sweep (:func:`carry_over_unchanged`)."""
    selection = read_artifact(workdir, SELECTION)
    return {"workdir": str(workdir), "selection": selection.to_dict("records"),
            "study_heliostats": list(txn.options.get("study_heliostats") or []),
            "members_per_heliostat": {}, "incremental": {"unchanged": True}}
