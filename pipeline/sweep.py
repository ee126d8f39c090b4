"""``sweep``: the regularization sweep and the training-size study (paper 000, figs. 6, 8, 9a).

Per heliostat and training size ``n_train`` (the ``n_train`` training rows with the largest kNN
distance, :func:`heliocal.pipeline.split.restrict_training`):

* every coarse preset is fitted (:func:`heliocal.pipeline.coarse.fit_heliostat`);
* the hybrid is trained on top of the coarse fit of the heliostat's selected preset, for every
  weight decay (log-spaced from ``wd_max`` down to ``wd_min``, plus 0) and seed. Each (n_train,
  weight decay, seed) is an ensemble of ``FineConfig.ensemble`` networks whose deviations are
  averaged (:func:`heliocal.pipeline.hybrid.ensemble_seeds`); all networks of a heliostat train
  together as ONE batched torch program (:func:`heliocal.pipeline.hybrid.train_members` with
  per-member training masks, weight decays, seeds and base parameters);
* the ``nn-only`` baseline (all n_train and seeds batched the same way, ensembles too) and the
  paper-002 ``pretrained-nn`` baseline.

The selection (``selection.parquet``) is made at the full training size: the hybrid ensemble
(weight decay, seed) with the lowest mean validation error, where the coarse model itself is
always a candidate, so the selected model is never worse than the coarse one on validation. A
hybrid must beat the coarse model's validation error by :data:`MIN_IMPROVEMENT` (20 %,
relative) to be chosen; why 20 % and not less is in docs/hybrid.md ("Selection"). The selected
ensemble's weights are written to ``DIR/hybrid/selected/<HID>.pt`` (+ JSON), in the layout of
``fit-hybrid``, for ``aim`` and ``report``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from .artifacts import (ArtifactSchema, Column as C, check_fresh, merge_with_previous,
                        previous_run_matches, read_artifact, write_artifact)
from .coarse import (AUTO_PRESETS, COARSE_PARAMS, COARSE_PREDICTIONS, MeasurementBatch,
                     fit_heliostat, load_selected_parameters, normal_errors_mrad, predict)
from .errors import FitError, check_float, check_int
from .hybrid import (FineConfig, PretrainConfig, _layers_to_state, build_problem, fit_pretrained,
                     ensemble_errors_mrad, ensemble_seeds, predict_ensembles, predictions_frame,
                     train_members)
from .kinematics import HeliostatSpec, nominal_parameters
from .metrics import error_mrad, measured_normal
from .parallel import map_tasks
from .schemas import HELIOSTATS, MEASUREMENTS
from .modelfiles import write_model
from .split import SPLIT, restrict_training
from .transaction import current_transaction, stage_transaction

__all__ = ["SWEEP", "SELECTION", "SELECTED_PREDICTIONS", "SCHEMAS", "default_ladder", "weight_decay_grid", "sweep_heliostat",
           "run_sweep", "hybrid_variants", "OCTAVE_BANDS", "MIN_IMPROVEMENT"]

log = logging.getLogger("heliocal.sweep")

SWEEP = ArtifactSchema(
    name="sweep", filename="sweep.parquet", producer="sweep",
    sort_by=("heliostat_id", "model", "n_train", "weight_decay", "seed"),
    volatile=("wall_time_s",),
    description="One row per heliostat, model, training size, weight decay and seed: mean and "
                "median error_mrad per split (means over the split's rows).",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("model", "string", "", "Coarse preset name, `hybrid` (the config's Fourier bands), "
          "`hybrid-octaves` (octave bands), `nn-only` or `pretrained-nn`."),
        C("n_train", "int64", "", "Training rows (largest kNN distance first)."),
        C("weight_decay", "float64", "", "Weight decay of the hybrid (NaN for other models).",
          nullable=True),
        C("seed", "int64", "", "Seed of the network's initial weights (0 for coarse presets)."),
        C("train_error_mrad", "float64", "mrad", "Mean error on the training rows."),
        C("train_median_error_mrad", "float64", "mrad", "Median error on the training rows."),
        C("val_error_mrad", "float64", "mrad", "Mean error on the validation rows.", nullable=True),
        C("val_median_error_mrad", "float64", "mrad", "Median on validation.", nullable=True),
        C("test_error_mrad", "float64", "mrad", "Mean error on the test rows.", nullable=True),
        C("test_median_error_mrad", "float64", "mrad", "Median on test.", nullable=True),
        C("test_train_distance_deg", "float64", "deg", "Mean distance of the test rows to their "
          "nearest training row (sun angles).", nullable=True),
        C("base_preset", "string", "", "Coarse preset under the hybrid / the preset itself."),
        C("wall_time_s", "float64", "s", "Wall time of this member's share of the training."),
    ),
)

SELECTION = ArtifactSchema(
    name="selection", filename="selection.parquet", producer="sweep", sort_by=("heliostat_id",),
    description="Per heliostat the model used by aim and report: the hybrid member with the best "
                "validation error at the full training size, or the coarse model if it is better.",
    columns=(
        C("heliostat_id", "string", "", "Heliostat."),
        C("model", "string", "", "`hybrid`, `hybrid-octaves` or `coarse`."),
        C("preset", "string", "", "Coarse preset (of the coarse model under the hybrid)."),
        C("weight_decay", "float64", "", "Selected weight decay (NaN for coarse).", nullable=True),
        C("seed", "int64", "", "Seed of the selected member (0 for coarse)."),
        C("n_train", "int64", "", "Training rows."),
        C("val_error_mrad", "float64", "mrad", "Mean validation error of the selected model."),
        C("test_error_mrad", "float64", "mrad", "Mean test error of the selected model.", nullable=True),
        C("coarse_val_error_mrad", "float64", "mrad", "Mean validation error of the coarse model."),
        C("coarse_test_error_mrad", "float64", "mrad", "Mean test error of the coarse model.",
          nullable=True),
    ),
)

SELECTED_PREDICTIONS = ArtifactSchema(
    name="selected_predictions", filename="selected_predictions.parquet", producer="sweep",
    sort_by=COARSE_PREDICTIONS.sort_by, columns=COARSE_PREDICTIONS.columns,
    description="Per measurement the errors of the model selection.parquet chose (model = "
                "`selected`): the selected hybrid member, or the coarse model.")

SCHEMAS = (SWEEP, SELECTION, SELECTED_PREDICTIONS)

#: Relative validation improvement a hybrid needs to be selected over the coarse model. The
#: validation rows lie between the training rows in sun position while the kNN test rows lie at
#: the edge; a network that interpolates the coarse fit's residual structure improves validation
#: by up to about 15 % on static heliostats without improving (or while worsening) the test rows,
#: whereas the dynamic disturbances the fine model is for improve it by 25-45 % (docs/hybrid.md).
MIN_IMPROVEMENT = 0.20

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


def _stats(err: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    if not mask.any():
        return float("nan"), float("nan")
    v = err[mask]
    return float(v.mean()), float(np.median(v))


def _row(hid, model, n_train, wd, seed, err, labels, train_mask, dist, base_preset, wall):
    tr = _stats(err, train_mask)
    va = _stats(err, labels == "validation")
    te = _stats(err, labels == "test")
    return {"heliostat_id": hid, "model": model, "n_train": int(n_train),
            "weight_decay": wd, "seed": int(seed),
            "train_error_mrad": tr[0], "train_median_error_mrad": tr[1],
            "val_error_mrad": va[0], "val_median_error_mrad": va[1],
            "test_error_mrad": te[0], "test_median_error_mrad": te[1],
            "test_train_distance_deg": dist, "base_preset": base_preset, "wall_time_s": wall}


#: Fourier bands of the ``hybrid-octaves`` candidate: Tancik et al.'s octaves 1, 2, 4, ..., 32.
OCTAVE_BANDS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)


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


def sweep_heliostat(task) -> dict:
    """The sweep of one heliostat (a picklable task for :func:`map_tasks`)."""
    (hid, hrow, rows, split_rows, sizes, presets, base_preset, weight_decays, seeds, config,
     pretrain_config, baselines, coarse_kwargs, extra_bands) = task
    hrow = pd.Series(hrow)
    rows = rows.reset_index(drop=True)
    spec = HeliostatSpec.from_row(hrow)
    nominal = nominal_parameters(hrow)
    data = MeasurementBatch.from_frame(rows)
    labels_full = rows["split"].to_numpy()
    out_rows = []
    # training masks and test distances per size
    masks, dists = {}, {}
    order = pd.Series(np.arange(len(rows)), index=rows["measurement_id"].to_numpy())
    for n in sizes:
        restricted = restrict_training(split_rows, n)
        train_ids = restricted.loc[restricted["split"] == "train", "measurement_id"]
        m = np.zeros(len(rows), bool)
        m[order.loc[train_ids].to_numpy()] = True
        masks[n] = m
        test = restricted["split"] == "test"
        dists[n] = float(restricted.loc[test, "nearest_train_distance_deg"].mean()) if test.any() else float("nan")
    # coarse presets per size
    bases = {}
    start_cache: dict = {}
    fitted = tuple(presets) + ((base_preset,) if base_preset not in presets else ())
    for n in sizes:
        train = data.subset(masks[n])
        for preset in fitted:
            t0 = time.perf_counter()
            fit = fit_heliostat(spec, nominal, train, preset, start_cache=start_cache, **coarse_kwargs)
            with torch.no_grad():
                err = normal_errors_mrad(fit.params, spec, data).numpy()
            out_rows.append(_row(hid, preset, n, float("nan"), 0, err, labels_full, masks[n],
                                 dists[n], preset, time.perf_counter() - t0))
            if preset == base_preset:
                bases[n] = (fit.params, torch.as_tensor(fit.free))
    free = bases[sizes[-1]][1]
    members = [(n, wd, s) for n in sizes for wd in weight_decays for s in seeds]
    val_mask = labels_full == "validation"
    selected_state = None
    k_ens = config.ensemble

    def run_members(kind: str, members, base_of, wds, cfg=config):
        # every member (n, wd, seed) is an ensemble of K networks: networks k*K .. k*K+K-1
        nets = [m for m in members for _ in range(k_ens)]
        base = torch.stack([base_of(n) for n, _, _ in nets]).unsqueeze(-2)  # (M K, 1, 28)
        problem = build_problem(rows, hrow, bases[sizes[-1]][0], free, cfg)
        problem.base = base
        tm = np.stack([masks[n] for n, _, _ in nets])
        t0 = time.perf_counter()
        result = train_members(problem, tm, val_mask, [w for w in wds for _ in range(k_ens)],
                               [x for _, _, s in members for x in ensemble_seeds(s, k_ens)], cfg)
        wall = (time.perf_counter() - t0) / len(members)
        with torch.no_grad():
            err = ensemble_errors_mrad(problem, result.layers, k_ens).numpy()
        for k, (n, wd, s) in enumerate(members):
            out_rows.append(_row(hid, kind, n, wd if kind.startswith("hybrid") else float("nan"),
                                 s, err[k], labels_full, masks[n], dists[n], base_preset, wall))
        return problem, result, err

    # selection at the full training size; the coarse model is a candidate
    coarse_err = normal_errors_mrad(bases[sizes[-1]][0], spec, data).detach().numpy()
    coarse_val, coarse_test = _stats(coarse_err, val_mask)[0], _stats(coarse_err, labels_full == "test")[0]
    best = {"model": "coarse", "weight_decay": float("nan"), "seed": 0, "val": coarse_val,
            "test": coarse_test}
    full = [k for k, (n, _, _) in enumerate(members) if n == sizes[-1]]
    # a hybrid replaces the coarse model only if it is better on validation by more than
    # MIN_IMPROVEMENT (relative); see its comment
    threshold = coarse_val * (1.0 - MIN_IMPROVEMENT)
    # the swept hybrid, once per Fourier band set: one batched program for every (n_train,
    # weight decay, seed) and ensemble network
    trained = {}
    for kind, cfg in hybrid_variants(config, extra_bands):
        trained[kind] = (cfg, *run_members(kind, members, lambda n: bases[n][0],
                                           [wd for _, wd, _ in members], cfg))
        err = trained[kind][3]
        for k in full:
            v, t = _stats(err[k], val_mask)[0], _stats(err[k], labels_full == "test")[0]
            if math.isnan(v) or (not math.isnan(threshold) and v >= threshold):
                continue
            if best["model"] == "coarse" or v < best["val"]:
                best = {"model": kind, "weight_decay": members[k][1], "seed": members[k][2],
                        "val": v, "test": t, "member": k}
    if best["model"] != "coarse":
        k = best["member"]
        cfg, problem, result, _ = trained[best["model"]]
        nets = slice(k * k_ens, (k + 1) * k_ens)
        layers = [(w[nets], b[nets]) for w, b in result.layers]
        selected_state = {
            "state": _layers_to_state(layers),
            "config": {"mode": "hybrid", "heliostat_id": hid, "seed": int(members[k][2]),
                       "weight_decay": float(members[k][1]), "fine_config": cfg.to_dict(),
                       "encoder": problem.encoder.to_dict(), "variant": best["model"],
                       "base_params": bases[sizes[-1]][0].tolist(), "free": free.tolist(),
                       "scales": problem.scales.tolist(), "coarse_preset": base_preset,
                       "sizes": problem.sizes(cfg), "selected_by": "sweep"}}
        single = dataclasses.replace(problem, base=problem.base[nets])  # that member's base
        with torch.no_grad():
            normal, position = predict_ensembles(single, layers)
        sel_pred = predictions_frame(problem, normal[0], position[0])
    else:
        sel_pred = predict(bases[sizes[-1]][0], spec, data).drop(columns=["measurement_id"])
    sel_pred["measurement_id"] = rows["measurement_id"].astype(str).to_numpy()
    sel_pred["heliostat_id"], sel_pred["split"] = hid, labels_full
    sel_pred["model"], sel_pred["selected"] = "selected", True
    selection = {"heliostat_id": hid, "model": best["model"], "preset": base_preset,
                 "weight_decay": best["weight_decay"], "seed": int(best["seed"]),
                 "n_train": int(sizes[-1]), "val_error_mrad": best["val"],
                 "test_error_mrad": best["test"], "coarse_val_error_mrad": coarse_val,
                 "coarse_test_error_mrad": coarse_test}
    if "nn-only" in baselines:
        nn_members = [(n, 0.0, s) for n in sizes for s in seeds]
        run_members("nn-only", nn_members, lambda n: nominal, [0.0] * len(nn_members))
    if "pretrained-nn" in baselines:
        for n in sizes:
            labels = np.where(masks[n], "train", np.where(labels_full == "train", "unused", labels_full))
            for s in seeds:
                t0 = time.perf_counter()
                _, _, normal, position = fit_pretrained(bases[n][0], spec, hrow, rows, data, labels,
                                                        int(s), pretrain_config)
                with torch.no_grad():
                    e = error_mrad(normal, measured_normal(data.sun, position, data.focal_spot)).numpy()
                out_rows.append(_row(hid, "pretrained-nn", n, float("nan"), s, e, labels_full,
                                     masks[n], dists[n], base_preset, time.perf_counter() - t0))
    return {"rows": out_rows, "selection": selection, "selected_state": selected_state,
            "predictions": sel_pred}


@stage_transaction("sweep")
def run_sweep(workdir: str | Path, *, n_train: Sequence[int] | None = None,
              weight_decays: Sequence[float] | None = None, seeds: Sequence[int] = (0,),
              presets: Sequence[str] = AUTO_PRESETS, baselines: Sequence[str] = ("nn-only", "pretrained-nn"),
              config: FineConfig | None = None, pretrain_config: PretrainConfig | None = None,
              heliostats: Sequence[str] | None = None, workers: int | None = 1,
              scheduler: str = "local", dask_address: str | None = None, progress=None,
              extra_bands: Sequence[Sequence[float]] = (OCTAVE_BANDS,)) -> dict:
    """The ``sweep`` stage: write sweep.parquet and selection.parquet, return a summary.

    ``extra_bands``: Fourier band sets swept besides ``config.fourier_bands`` (default: the
    octaves, model ``hybrid-octaves``; see :func:`hybrid_variants`); ``()`` sweeps only the
    config's bands."""
    workdir = Path(workdir)
    seeds = [check_int(s, "seeds", "sweep", 0) for s in seeds]
    weight_decays = list(weight_decays) if weight_decays is not None else weight_decay_grid()
    for wd in weight_decays:
        check_float(wd, "weight_decays", "sweep", 0.0, None)
    config = (config or FineConfig()).validated()
    pretrain_config = pretrain_config or PretrainConfig()
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=heliostats).set_index("heliostat_id", drop=False)
    check_fresh(workdir, SPLIT, {"measurements": MEASUREMENTS})
    check_fresh(workdir, COARSE_PARAMS, {"measurements": MEASUREMENTS, "split": SPLIT})
    split = read_artifact(workdir, SPLIT, heliostats=heliostats)
    selected = load_selected_parameters(workdir, heliostats)
    merged = measurements.merge(split[["heliostat_id", "measurement_id", "split"]],
                                on=["heliostat_id", "measurement_id"], how="inner")
    tasks = []
    rows_of = dict(tuple(merged.groupby("heliostat_id", sort=False)))   # not a scan per heliostat
    split_of = dict(tuple(split.groupby("heliostat_id", sort=False)))
    for hid in sorted(selected):
        rows = rows_of.get(hid, merged.iloc[:0])
        srows = split_of.get(hid, split.iloc[:0])
        n_avail = int(((srows["split"] == "train") | (srows["split"] == "unused")).sum())
        if n_avail == 0 or hid not in helio.index:
            continue
        sizes = sorted({min(int(n), n_avail) for n in n_train}) if n_train else default_ladder(n_avail)
        for n in sizes:
            check_int(n, "n_train", "sweep", 2)
        tasks.append((hid, helio.loc[hid].to_dict(), rows, srows, sizes, tuple(presets),
                      selected[hid]["preset"], weight_decays, seeds, config, pretrain_config,
                      tuple(baselines), {"loss": "soft_l1", "robust_start": "auto"},
                      tuple(extra_bands)))
    if not tasks:
        raise FitError(f"no heliostat in {workdir} has a coarse fit and training rows; run "
                       f"`heliocal fit-coarse --workdir {workdir}` first")
    results = map_tasks(sweep_heliostat, tasks, workers=workers, scheduler=scheduler,
                        dask_address=dask_address,
                        progress=(lambda d, t: progress(d, t, None)) if progress else None)
    rows = [r for res in results for r in res["rows"]]
    selection = pd.DataFrame([res["selection"] for res in results])
    txn = current_transaction(workdir, "sweep")
    hashes = txn.input_fingerprints()  # what this run read: the selected models' recorded inputs
    for res in results:
        st = res["selected_state"]
        if st is None:
            continue
        hid = st["config"]["heliostat_id"]
        write_model(txn, "selected", hid, st["state"], {**st["config"], "inputs": hashes})
    opts = {"n_train": list(n_train) if n_train else "ladder", "weight_decays": weight_decays,
            "seeds": seeds, "presets": list(presets), "baselines": list(baselines),
            "extra_bands": [list(b) for b in extra_bands],
            "fine_config": config.to_dict(), "pretrain_config": pretrain_config.to_dict(),
            "heliostats": list(heliostats) if heliostats else None}
    # a partial run (--heliostat) keeps the other heliostats' rows and selected models when the
    # previous sweep read the same inputs (artifacts.merge_with_previous)
    tables = {SWEEP: pd.DataFrame(rows), SELECTION: selection,
              SELECTED_PREDICTIONS: pd.concat([res["predictions"] for res in results],
                                              ignore_index=True)}
    if heliostats:
        requested = set(heliostats)
        replaced = lambda old: old["heliostat_id"].isin(requested)  # noqa: E731
        tables = {s: merge_with_previous(workdir, s, df, replaced) for s, df in tables.items()}
        if previous_run_matches(workdir, "sweep"):
            txn.carry_over(r for r in txn.previous_files("hybrid/selected")
                           if r.rsplit("/", 1)[-1].rsplit(".", 1)[0] not in requested)
    for schema, df in tables.items():
        write_artifact(df, workdir, schema, stage="sweep", options=opts, seed=seeds[0])
    return {"workdir": str(workdir), "selection": selection.to_dict("records"),
            "members_per_heliostat": {t[0]: len(t[4]) * len(weight_decays) * len(seeds)
                                      * len(hybrid_variants(config, extra_bands)) for t in tasks}}
