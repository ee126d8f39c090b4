"""``fit-hybrid`` and ``aim``: the fine model (a self-normalizing network of parameter deviations),
its batched training, the paper-002 baseline, and the inverse problem a plant controller needs.

The hybrid model (Pargmann et al., paper 000, sections 3.3 and 4)
--------------------------------------------------------------------
For every measurement ``n`` the 28 kinematic parameters are::

    p_n = p_base + S . f(x_n)          (only the coarse fit's free parameters get a deviation)

``p_base`` is the selected coarse fit (mode ``hybrid``) or the nominal geometry (mode ``nn-only``,
the paper's "neural network" baseline); ``f`` is a self-normalizing MLP (SELU activations,
LeCun-normal initialisation, default 14 hidden layers of width 2 as in the paper) whose output
layer starts at zero, so the untrained hybrid *is* the coarse model; ``S`` scales each output to
a physical unit (:data:`OUTPUT_SCALE`: angles 1 mrad, translations 1 cm, actuator lengths 0.3 mm,
increments 0.1 % of nominal). The inputs ``x_n`` (:class:`FeatureEncoder`) are

* the actuator steps divided by their maximum, plus Fourier features ``sin(2 pi b a)``,
  ``cos(2 pi b a)`` for the frequency bands ``b`` (Tancik et al. 2020);
* the normalised duration since the first measurement (paper 000 eq. 1),
  ``dt = (t - t0) / (t1 - t0)``, encoded as ``sin(pi dt)``, ``cos(pi dt)`` (half a turn over the
  measurement period, so t0 and t1 stay apart);
* the position in the year as the month ``m`` in [0, 12) (continuous: day of year / days of year
  * 12), encoded as ``sin(2 pi m / 12)``, ``cos(2 pi m / 12)``;
* any ``env_*`` columns named by the user, standardised.

Normalisation constants come from *all* rows of the heliostat (inputs only, never the measured
focal spots), so every training-size mask of a sweep sees the same features.

Training minimises, per member ``m``::

    L_m = mean_{n in train_m} error_mrad(n)^2 + weight_decay_m * sum(theta_m^2)

(``error_mrad`` from :mod:`heliocal.pipeline.physics.metrics`, exactly as ``fit-coarse`` defines it; the
explicit L2 penalty covers every weight and bias, so a large weight decay pulls the network to
zero output, i.e. the hybrid back to the coarse model, paper 000 section 4). Adam, full batch,
float64. After every epoch the validation error (mean error_mrad on the validation rows) is
checked; each member keeps its best-validation state (epoch 0 = the coarse model is a candidate,
so the hybrid is never worse than the coarse model on validation) and stops after ``patience``
epochs without improvement.

Everything is batched over a leading member dimension ``M`` (weights ``(M, out, in)`` applied
with :func:`torch.baddbmm`; per-member weight decay, seed, train and validation masks), so a
weight-decay sweep is one torch program: :func:`train_members`, :func:`predict_members`.

The pretrained network of paper 002 (section 2.3)
-------------------------------------------------
Mode ``pretrained-nn``: per axis a SELU network 5-(6-5-4-3)-1 maps the sun vector (3) and the
focal-spot offset (east, up) [m] from a reference point (the mean training focal spot) to the
motor steps of that axis. It is pre-trained on :attr:`PretrainConfig.n_samples` samples simulated
with the selected coarse model (sun positions from NREL SPA at random times between the first and
last training measurement, no lower than the lowest training sun; aim points around the training
targets; steps from the coarse inverse kinematics), then fine-tuned on the real training rows with
the Huber loss, AdaMax, a plateau learning-rate schedule and a small learning rate, with early
stopping on the validation rows. Paper 002 uses one target; the focal-spot offsets here refer all
targets to one reference point so several targets can be used.

Its step errors are converted to the common ``error_mrad`` through the coarse model's kinematics:
with ``R`` the rotation that turns the coarse normal at the measured steps into the coarse normal
at the predicted steps, the predicted normal is ``R n_meas`` (``n_meas`` the measured normal), so
``error_mrad`` is the angle the step error turns the mirror by, and the beam and spot metrics
follow from it as for the other models.

``aim``
-------
:func:`aim_steps` returns the motor steps that reflect the sun onto an aim point according to the
best fitted model (``hybrid`` where fitted, else the coarse model). Through the fine model the
parameters depend on the steps, so the inverse is a fixed point ``s_{k+1} = IK(p(s_k))`` started
at the coarse solution (the deviations change by far less than a step per step, so it contracts
fast); the reported ``inverse_residual_mrad`` is the angle between the beam reflected by the forward
model at the returned steps and the direction to the aim point.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.incremental import carry_over_unchanged, mark_rerunnable
from ..artifacts.manifests import current_transaction
from ..artifacts.modelfiles import check_fine_model_inputs, write_model
from ..artifacts.schemas import HELIOSTATS, HYBRID_PREDICTIONS, MEASUREMENTS
from ..artifacts.store import (merge_with_previous, previous_run_matches, read_artifact,
                               write_artifact)
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..errors import FitError, check_choice, check_float, check_int
from ..models.coarse import MeasurementBatch
from ..models.regime_fit import predict_parameters
from ..models.network import MODES, layers_to_state
from ..models.config import FineConfig, ensemble_seeds
from ..models.pretrained import PretrainConfig, fit_pretrained
from ..models.fade import (FADE_LENGTHS_DEG, NETWORK_TIME_FADE_DAYS, NO_FADE, TIME_FADE_DAYS,
                           Fade)
from ..models.gp import GPConfig
from ..models.gp_heliostat import fit_heliostat_gp, with_correction_map
from ..models.selection import SelectionRule, choose_fade, row_validation_weights
from ..models.training import (FineProblem, build_problem, faded_errors_mrad, predict_ensembles,
                               predictions_frame, stack_problems, take_rows, train_members)
from ..physics.parameters import HeliostatSpec
from ..runtime.parallel import map_tasks, warm_up_stage
from .fit_coarse import coarse_row_parameters, load_selected_parameters, load_split_labels
from ..vocabulary import HYBRID_BATCH_SIZE
from .forward import load_time_labels, load_time_parameters
from ..runtime.process_state import deterministic_torch, restores_process_state, single_threaded

__all__ = [
    "run_fit_hybrid",
    "hybrid_chunks",
]

_FUNC = "fit_hybrid"

#: Prefix of the id under which a heliostat's time-split training runs in a chunk (not an id
#: ingest would keep: it starts with NUL).
_TIME_MARK = "\0time:"


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
def _mean(values) -> float:
    values = np.asarray(values, np.float64)
    return float(values.mean()) if len(values) else float("nan")


def _split_means(err: np.ndarray, labels: np.ndarray) -> dict:
    return {sp: _mean(err[labels == sp]) for sp in ("train", "validation", "test")}




@single_threaded
def _hybrid_chunk_task(task):
    """Heliostats of ``fit-hybrid`` that train as one batched program (a picklable task for
    :func:`map_tasks`). pretrained-nn heliostats are fitted one by one."""
    items, mode, weight_decay, seed, config, pretrain_config = task
    deterministic_torch()
    t0 = time.perf_counter()
    prepared = []
    for hid, rows, hrow, sel in items:
        hrow = pd.Series(hrow)
        rows = rows[rows["split"] != "excluded"].reset_index(drop=True)
        spec = HeliostatSpec.from_row(hrow)
        data = MeasurementBatch.from_frame(rows)
        coarse = coarse_row_parameters(sel, rows["timestamp"])   # each row at its regime's
        prepared.append((hid, rows, hrow, sel, rows["split"].to_numpy(), spec, data,
                         predict_parameters(coarse, spec, data), coarse))
    if mode == "gp":
        return [_gp_outputs(*p, GPConfig(env=config.env, seed=seed)) for p in prepared]
    out = []
    if mode == "pretrained-nn":
        for hid, rows, hrow, sel, labels, spec, data, coarse_pred, _ in prepared:
            t1 = time.perf_counter()
            model, info, normal, position = fit_pretrained(
                sel["params"], spec, hrow, rows, data, labels, seed, pretrain_config)
            problem = FineProblem(spec, sel["params"], sel["free"], torch.zeros(0),
                                  None, data, torch.zeros(0))
            cfg = {"mode": mode, "heliostat_id": hid, "seed": seed,
                   "pretrain_config": pretrain_config.to_dict(), **model.to_dict(),
                   "coarse_params": sel["params"].tolist(), "coarse_preset": sel["preset"], **info}
            out.append(_hybrid_outputs(hid, mode, sel, labels, problem, normal, position,
                                       coarse_pred, model.to_state(), cfg, info,
                                       time.perf_counter() - t1))
        return out
    problems = []
    for hid, rows, hrow, sel, labels, spec, data, coarse_pred, coarse in prepared:
        base = coarse if mode == "hybrid" else sel["nominal"]
        problems.append(build_problem(rows, hrow, base, sel["free"], config))
    # train on the rows that matter (train and validation); test rows are predicted afterwards.
    # Member h * K + j is network j of heliostat h's ensemble of K.
    k_ens = config.ensemble
    fitting = [np.isin(p[4], ("train", "validation")) for p in prepared]
    taken = [take_rows(pr, torch.as_tensor(f)) for pr, f in zip(problems, fitting)]
    stacked, valid = stack_problems([t for t in taken for _ in range(k_ens)])
    n = stacked.data.steps.shape[1]
    labels_fit = np.array([np.resize(p[4][f], n) for p, f in zip(prepared, fitting)
                           for _ in range(k_ens)])
    result = train_members(stacked, torch.as_tensor(labels_fit == "train") & valid,
                           torch.as_tensor(labels_fit == "validation") & valid,
                           [weight_decay] * len(labels_fit),
                           ensemble_seeds(seed, k_ens) * len(problems), config)
    wall = (time.perf_counter() - t0) / len(problems)
    for h, ((hid, rows, hrow, sel, labels, spec, data, coarse_pred, _), problem) in enumerate(
            zip(prepared, problems)):
        nets = slice(h * k_ens, (h + 1) * k_ens)
        layers = [(w[nets], b[nets]) for w, b in result.layers]
        fade = _network_fade(rows, labels, problem, layers) if mode == "hybrid" else NO_FADE
        with torch.no_grad():
            normal, position = predict_ensembles(problem, layers,
                                                 fade=fade.weights_of_rows(rows))
        info = {"best_epoch": result.best_epoch[nets].tolist(),
                "epochs": result.epochs_run[nets].tolist(),
                "fade_length_deg": None if fade is NO_FADE else fade.to_dict()["length_deg"]}
        cfg = {"mode": mode, "heliostat_id": hid, "seed": seed, "weight_decay": weight_decay,
               "fine_config": config.to_dict(), "encoder": problem.encoder.to_dict(),
               # aim's base: the latest regime's parameters under a regime-aware coarse model
               "base_params": (sel["params"] if problem.per_row_base else problem.base).tolist(),
               "free": sel["free"].tolist(),
               "scales": problem.scales.tolist(), "coarse_preset": sel["preset"],
               "sizes": problem.sizes(config), "fade": fade.to_dict(), **info}
        out.append(_hybrid_outputs(hid, mode, sel, labels, problem, normal[0], position[0],
                                   coarse_pred, layers_to_state(layers), cfg, info, wall))
    return out


def _weights(rows, labels) -> np.ndarray:
    """The validation rows' weights as the sweep's default rule weighs them (their distances
    to training matched to the test rows'; models.selection)."""
    rule = SelectionRule()
    return row_validation_weights(rows, labels, rule.match_k, rule.match_share)


def _network_fade(rows, labels, problem, layers) -> Fade:
    """The hybrid's fade: the sun fade length of :data:`FADE_LENGTHS_DEG` with the lowest mean
    error on the validation rows weighted by their distance to training (the sweep's rule,
    :mod:`heliocal.pipeline.models.selection`), the time fade :data:`NETWORK_TIME_FADE_DAYS` (the
    network has date inputs); no validation rows: no sun fade."""
    base = Fade.of_rows(rows[labels == "train"], length_days=NETWORK_TIME_FADE_DAYS)
    fades = [base.with_lengths(length) for length in FADE_LENGTHS_DEG]
    val = labels == "validation"
    if not val.any():
        return fades[0]
    errors = faded_errors_mrad(problem, layers, None, [f.weights_of_rows(rows) for f in fades])
    return fades[choose_fade([e[0][val] for e in errors], _weights(rows, labels))]


def _gp_outputs(hid, rows, hrow, sel, labels, spec, data, coarse_pred, coarse,
                gp_config: GPConfig):
    """One heliostat's GP correction (``--mode gp``): fitted on its training rows on top of its
    coarse model, the fade length chosen on its validation rows weighted by their distance to
    training (:func:`heliocal.pipeline.models.gp.fit_heliostat_gp`); outputs as
    :func:`_hybrid_outputs`'."""
    weights = _weights(rows, labels)
    fit = fit_heliostat_gp(rows, labels, spec, data, coarse, gp_config, weights,
                           time_length_days=TIME_FADE_DAYS)
    problem = FineProblem(spec, sel["params"], sel["free"], torch.zeros(0), None, data,
                          torch.zeros(0))
    cfg = {"mode": "gp", "heliostat_id": hid, "seed": gp_config.seed,
           "gp_config": gp_config.to_dict(), "gp": fit.model.to_dict(),
           "base_params": sel["params"].tolist(), "free": sel["free"].tolist(),
           "coarse_preset": sel["preset"]}
    state = fit.model.to_state()
    info = {"structure": fit.model.structure, "fade_length_deg": fit.lengths[fit.chosen]}
    return _hybrid_outputs(hid, "gp", sel, labels, problem, fit.normal, fit.position, coarse_pred,
                           state, with_correction_map(cfg, state), info, fit.wall_time_s)


def _hybrid_outputs(hid, mode, sel, labels, problem, normal, position, coarse_pred, state, cfg,
                    info, wall_time_s):
    """One heliostat's predictions frame, summary, state dict and config."""
    pred = predictions_frame(problem, normal, position)
    pred["heliostat_id"], pred["split"], pred["model"] = hid, labels, mode
    pred["selected"] = mode == "hybrid"
    test = labels == "test"
    summary = {
        "heliostat_id": hid, "mode": mode, "coarse_preset": sel["preset"],
        "n_train": int((labels == "train").sum()),
        "coarse": _split_means(coarse_pred["error_mrad"].to_numpy(), labels),
        mode: _split_means(pred["error_mrad"].to_numpy(), labels),
        "test_median": {"coarse": float(np.median(coarse_pred["error_mrad"].to_numpy()[test]))
                        if test.any() else None,
                        mode: float(np.median(pred["error_mrad"].to_numpy()[test]))
                        if test.any() else None},
        **info, "wall_time_s": wall_time_s}
    return pred, summary, state, cfg


def hybrid_chunks(ids, selected, helio, batch_size: int):
    """Group heliostats that can share one batched program (kinematic and actuator type, free
    parameters) and cut each group, ordered by row count (little padding), into chunks. The
    chunks depend only on the data, so local and Dask runs train the same programs."""
    groups: dict = {}
    for hid in ids:
        h = helio.loc[hid]
        key = (str(h["kinematic_type"]), str(h["actuator_type"]),
               tuple(bool(x) for x in selected[hid]["free"].tolist()))
        groups.setdefault(key, []).append(hid)
    chunks = []
    for key in sorted(groups):
        members = groups[key]
        chunks += [members[i:i + batch_size] for i in range(0, len(members), batch_size)]
    return chunks


@locks_workdir("fit-hybrid")
@stage_transaction("fit-hybrid")
@restores_process_state
def run_fit_hybrid(workdir: str | Path, *, mode: str = "hybrid", weight_decay: float = 0.0,
                   seed: int = 0, config: FineConfig | None = None,
                   pretrain_config: PretrainConfig | None = None,
                   heliostats: Sequence[str] | None = None, progress=None,
                   workers: int | None = 1, scheduler: str = "local",
                   dask_address: str | None = None, batch_size: int = HYBRID_BATCH_SIZE,
                   incremental: bool = False) -> dict:
    """The ``fit-hybrid`` stage for one mode; writes ``DIR/hybrid/<mode>/`` and merges the mode's
    rows into ``DIR/hybrid_predictions.parquet``.

    Heliostats of one kinematic type, actuator type and coarse preset train ``batch_size`` at a
    time as one batched program (:func:`stack_problems`); each chunk is one task for the
    workers or the Dask cluster.

    Parameters
    ----------
    mode : one of :data:`MODES`.
    weight_decay : L2 penalty coefficient (fine modes) [mrad^2 per unit squared weight].
    seed : seed of the initial weights (and of the pre-training samples).
    config, pretrain_config : :class:`FineConfig` (hybrid, nn-only), :class:`PretrainConfig`.
    heliostats : restrict to these ids (other heliostats' rows of this mode are kept).
    progress : optional ``progress(done, total, heliostat_id)``.
    incremental : keep the previous run as it is when it was this mode with these options, seed
        and code on the inputs now committed (nothing is read or trained); otherwise train every
        heliostat (a heliostat's networks depend on the others in its batch).
    """
    check_choice(mode, "mode", _FUNC, MODES)
    weight_decay = check_float(weight_decay, "weight_decay", _FUNC, 0.0, None)
    seed = check_int(seed, "seed", _FUNC, 0)
    config = (config or FineConfig()).validated()
    pretrain_config = pretrain_config or PretrainConfig()
    batch_size = check_int(batch_size, "batch_size", _FUNC, 1)
    workdir = Path(workdir)
    opts = {"mode": mode, "weight_decay": weight_decay, "fine_config": config.to_dict(),
            "pretrain_config": pretrain_config.to_dict(), "batch_size": batch_size,
            "heliostats": list(heliostats) if heliostats else None}
    txn = current_transaction(workdir, "fit-hybrid")
    if incremental and not heliostats and carry_over_unchanged(txn, opts, seed=seed):
        return {"workdir": str(workdir), "mode": mode, "weight_decay": weight_decay, "seed": seed,
                "heliostats": [], "incremental": {"unchanged": True}}
    mark_rerunnable(txn)
    warm_up_stage("fit-hybrid", workers=workers, scheduler=scheduler, dask_address=dask_address)
    check_fine_model_inputs(workdir)
    deterministic_torch()
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=heliostats).set_index("heliostat_id", drop=False)
    measurements["split"] = load_split_labels(workdir, measurements).to_numpy()
    selected = load_selected_parameters(workdir, heliostats)
    with_train = set(measurements.loc[measurements["split"] == "train", "heliostat_id"])
    ids = [h for h in sorted(selected) if h in helio.index and h in with_train]
    if not ids:
        raise FitError(f"no heliostat in {workdir} has a coarse fit with training rows; run "
                       f"`heliocal fit-coarse --workdir {workdir}` first")
    input_hashes = txn.input_fingerprints()  # what this run read: the models' recorded inputs
    groups = dict(tuple(measurements.groupby("heliostat_id", sort=True)))
    ids = sorted(ids, key=lambda h: (len(groups[h]), h))
    # forward in time: every heliostat with a time split is trained a second time, the same mode,
    # weight decay and seed, on the time split's training rows on top of fit-coarse's
    # time-split fit, as one more member of the same batched program (its networks are tiny, so
    # a program's cost is mostly per epoch, not per member); its models are not kept
    time_params = load_time_parameters(workdir, heliostats)
    time_labels = pd.Series(load_time_labels(workdir, measurements), index=measurements.index)
    labels_of = {h: time_labels.loc[groups[h].index].to_numpy(dtype=object)
                 for h in ids if h in time_params}
    labels_of = {h: v for h, v in labels_of.items() if (v == "train").sum() >= 2}

    def time_item(hid):
        rows = groups[hid].assign(split=np.where(pd.isna(labels_of[hid]), "excluded",
                                                 labels_of[hid]))
        return (_TIME_MARK + hid, rows, helio.loc[hid].to_dict(),
                {**selected[hid], "params": time_params[hid]})

    tasks = [([(hid, groups[hid], helio.loc[hid].to_dict(), selected[hid]) for hid in chunk]
              + [time_item(hid) for hid in chunk if hid in labels_of],
              mode, weight_decay, seed, config, pretrain_config)
             for chunk in hybrid_chunks(ids, selected, helio, batch_size)]
    results = [r for chunk in map_tasks(
        _hybrid_chunk_task, tasks, workers=workers, scheduler=scheduler, dask_address=dask_address,
        progress=(lambda d, t: progress(d, t, None)) if progress else None) for r in chunk]
    time_err = {r[1]["heliostat_id"][len(_TIME_MARK):]: r[0].set_index("measurement_id")["error_mrad"]
                for r in results if r[1]["heliostat_id"].startswith(_TIME_MARK)}
    results = sorted((r for r in results if not r[1]["heliostat_id"].startswith(_TIME_MARK)),
                     key=lambda r: r[1]["heliostat_id"])
    for pred, summary, _, _ in results:
        hid = summary["heliostat_id"]
        err = time_err.get(hid)
        pred["time_error_mrad"] = (np.nan if err is None else
                                   err.reindex(pred["measurement_id"].to_numpy()).to_numpy(float))
        summary["time_test"] = None
        if err is not None:
            label = dict(zip(groups[hid]["measurement_id"], labels_of[hid]))
            test = np.array([label.get(m) == "test" for m in pred["measurement_id"]], dtype=bool)
            summary["time_test"] = _mean(pred["time_error_mrad"].to_numpy(float)[test])
    preds, summaries = [], []
    for pred, summary, state, cfg in results:
        hid = summary["heliostat_id"]
        cfg["inputs"] = input_hashes
        preds.append(pred)
        summaries.append(summary)
        write_model(txn, mode, hid, state, cfg)
    # rows and models of other modes and heliostats are kept when they were made from the same
    # inputs (the run merges into the previous one); otherwise they are dropped
    new = merge_with_previous(workdir, HYBRID_PREDICTIONS, pd.concat(preds, ignore_index=True),
                              lambda old: (old["model"] == mode) & old["heliostat_id"].isin(ids))
    if previous_run_matches(workdir, "fit-hybrid"):
        txn.carry_over(txn.previous_files("hybrid"))
    write_artifact(new, workdir, HYBRID_PREDICTIONS, stage="fit-hybrid", options=opts, seed=seed)
    return {"workdir": str(workdir), "mode": mode, "weight_decay": weight_decay, "seed": seed,
            "heliostats": summaries, "incremental": None}
