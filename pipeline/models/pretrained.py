"""The pre-trained network of paper 002 (``pretrained-nn``) in two variants.

Both map the paper's inputs, the sun vector (3) and the focal spot's east and up offset from a
reference point (2), to the motor steps of one axis with a SELU network 5-(6-5-4-3)-1 per axis
(:attr:`PretrainConfig.hidden`), Huber loss and AdaMax, and convert predicted steps to a mirror
normal through the coarse model's kinematics (:func:`fit_pretrained`).

``paper`` (:attr:`PretrainVariant.paper`, paper 002 section 2.3): the network is pre-trained on
:attr:`PretrainConfig.n_samples` calibrations simulated from the coarse model (sun positions of
the training period, aim points within the training spread), then fine-tuned on the real
training rows. Its accuracy is bounded by how well the small network imitates the coarse
model's inverse kinematics: 4-5 mrad with the paper's budget, ~1.2 mrad at best for this
network size (docs/experiments/pretrained.md).

``residual`` (:attr:`PretrainVariant.residual`, the default): the same network learns the
*correction* to the coarse model in step space, ``steps = IK_coarse(sun, spot) + s * f(x)``, with
``s`` the training residuals' spread per axis (:attr:`PretrainedModel.out_std`). The output layer
starts at zero, so the untrained network is the coarse model exactly (the limit of a perfect
pre-training, which makes the simulated pre-training unnecessary), and fine-tuning on the
training rows (full batch, early stopping on the validation rows, epoch 0 a candidate) only
learns what the rigid body misses. Rows the coarse inverse kinematics cannot reach keep the
coarse model's prediction.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import pandas as pd
import torch

from ..errors import FitError
from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import error_mrad, measured_normal
from ..physics.parameters import HeliostatSpec
from ..physics.vectors import unit_vector
from ..runtime.process_state import single_threaded
from ..vocabulary import PretrainVariant
from .adam import Adamax, ReduceOnPlateau
from .coarse import MeasurementBatch
from .network import Layers, init_mlp, layers_to_state, mlp_forward

__all__ = [
    "PretrainConfig",
    "PretrainedModel",
    "fit_pretrained",
    "rotate_between",
    "simulate_pretraining",
    "huber",
]

# ------------------------------------------------------------------------------------------------
# pretrained-nn (paper 002)
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PretrainConfig:
    """Settings of the pre-trained network (``pretrained-nn``).

    Attributes
    ----------
    variant : ``residual`` (default) or ``paper`` (:class:`PretrainVariant`, module docstring).
    hidden : hidden layer widths (paper 002: 6-5-4-3), both variants.
    n_samples : simulated pre-training samples (paper 002: 4,000; 90:10 train/holdout).
    pretrain_lr : AdaMax step size of the pre-training (reduced on plateaus).
    pretrain_epochs : epoch budget of the pre-training (mini-batches of ``batch_size``).
    batch_size : pre-training mini-batch size.
    finetune_lr : AdaMax step size of the fine-tuning on real rows (small, to keep the
        pre-training; paper 002 uses 1e-5 with many more epochs).
    finetune_epochs : epoch budget of the fine-tuning (full batch).
    patience : epochs without improvement before pre-training / fine-tuning stops.
    huber_delta : Huber transition, in units of the normalised steps.
    residual_lr : AdaMax step size of the ``residual`` variant (full batch).
    residual_epochs : epoch budget of the ``residual`` variant.
    residual_patience : epochs without a validation improvement before it stops.
    residual_huber_steps : its Huber transition [motor steps].

    ``n_samples`` .. ``huber_delta`` are the ``paper`` variant's; the ``residual_*`` settings
    were chosen on the validation rows of a simulated field (docs/experiments/pretrained.md).
    """

    variant: str = PretrainVariant.residual.value

    hidden: tuple[int, ...] = (6, 5, 4, 3)
    n_samples: int = 4000
    pretrain_lr: float = 1e-2
    pretrain_epochs: int = 150
    batch_size: int = 200
    finetune_lr: float = 1e-4
    finetune_epochs: int = 400
    patience: int = 30
    huber_delta: float = 0.01
    residual_lr: float = 1e-2
    residual_epochs: int = 1000
    residual_patience: int = 100
    residual_huber_steps: float = 5.0

    def __post_init__(self):
        if self.variant not in PretrainVariant.values():
            from ..errors import ParameterError
            raise ParameterError(f"The pre-trained network's variant must be one of "
                                 f"{', '.join(PretrainVariant.values())}. Got {self.variant!r} "
                                 "instead.")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "PretrainConfig":
        d = dict(d)
        d.setdefault("variant", PretrainVariant.paper.value)  # files written before variants
        d["hidden"] = tuple(int(h) for h in d.get("hidden", (6, 5, 4, 3)))
        return cls(**d)


def rotate_between(a: torch.Tensor, b: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Apply to ``v`` the smallest rotation that turns unit ``a`` into unit ``b`` (Rodrigues)."""
    axis = torch.linalg.cross(a, b, dim=-1)
    s = torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    c = (a * b).sum(-1, keepdim=True)
    k = axis / s.clamp_min(1e-300)
    kxv = torch.linalg.cross(k, v, dim=-1)
    kdv = (k * v).sum(-1, keepdim=True)
    out = v * c + kxv * s + k * kdv * (1 - c)
    return torch.where(s > 0, out, v)


@dataclass
class PretrainedModel:
    """The two per-axis networks with their input/output normalisation.

    ``paper``: steps = ``f(x) * out_std + out_mean``. ``residual``: steps =
    ``IK_coarse(sun, spot) + f(x) * out_std + out_mean`` with the coarse parameters
    ``coarse_params`` (``out_mean`` is zero).
    """

    layers: Layers               # M = 2 (axis 1, axis 2), each 5 -> hidden -> 1
    reference_m: list            # (3,) focal-spot reference point [m] ENU
    in_mean: list                # (5,)
    in_std: list                 # (5,)
    out_mean: list               # (2,) [steps]
    out_std: list                # (2,) [steps per output unit]
    variant: str = PretrainVariant.paper.value
    coarse_params: list | None = None   # (28,) residual variant: the coarse model it corrects

    def inputs(self, sun: torch.Tensor, spot: torch.Tensor) -> torch.Tensor:
        off = spot - torch.as_tensor(self.reference_m, dtype=torch.float64)
        x = torch.cat([unit_vector(sun), off[..., 0:1], off[..., 2:3]], dim=-1)
        return (x - torch.as_tensor(self.in_mean)) / torch.as_tensor(self.in_std)

    def steps(self, sun: torch.Tensor, spot: torch.Tensor, layers: Layers | None = None, *,
              spec: HeliostatSpec | None = None, base: torch.Tensor | None = None) -> torch.Tensor:
        """Predicted motor steps (N, 2) for sun vectors and focal spots (N, 3) [m] ENU.

        The ``residual`` variant adds the coarse inverse kinematics: ``base`` (N, 2) if given,
        else computed from ``coarse_params`` and ``spec`` (NaN where the coarse model cannot
        reach the spot)."""
        y = mlp_forward(self.layers if layers is None else layers, self.inputs(sun, spot))  # (2, N, 1)
        y = y.squeeze(-1).T
        out = y * torch.as_tensor(self.out_std) + torch.as_tensor(self.out_mean)
        if self.variant == PretrainVariant.residual.value:
            if base is None:
                if spec is None or self.coarse_params is None:
                    raise ValueError("the residual variant needs the heliostat's spec and its "
                                     "coarse parameters")
                base = inverse_kinematics(torch.as_tensor(self.coarse_params, dtype=torch.float64),
                                          spec, sun, spot)
            out = base + out
        return out

    def to_state(self) -> dict:
        return layers_to_state(self.layers)

    def to_dict(self) -> dict:
        d = {"reference_m": list(map(float, self.reference_m)), "in_mean": list(map(float, self.in_mean)),
             "in_std": list(map(float, self.in_std)), "out_mean": list(map(float, self.out_mean)),
             "out_std": list(map(float, self.out_std)), "variant": self.variant}
        if self.coarse_params is not None:
            d["coarse_params"] = list(map(float, self.coarse_params))
        return d

    @classmethod
    def from_dict(cls, d: Mapping, layers: Layers) -> "PretrainedModel":
        """The model of a fitted config (:meth:`to_dict`) and its weights."""
        return cls(layers, d["reference_m"], d["in_mean"], d["in_std"], d["out_mean"],
                   d["out_std"], d.get("variant", PretrainVariant.paper.value),
                   d.get("coarse_params"))


def simulate_pretraining(coarse: torch.Tensor, spec: HeliostatSpec, hrow, rows: pd.DataFrame,
                          train: np.ndarray, n: int, rng: np.random.Generator):
    """Sun vectors, focal spots and coarse-model steps of ``n`` simulated calibrations."""
    from ..physics.sun import spa_sun_position, sun_vector_enu

    tr = rows[train]
    el_min = float(tr["sun_elevation_deg"].min())
    lat, lon = hrow.get("latitude_deg"), hrow.get("longitude_deg")
    times = pd.to_datetime(tr["timestamp"], utc=True).dropna()
    suns = []
    have_site = lat is not None and lon is not None and np.isfinite(lat) and np.isfinite(lon)
    if have_site and len(times) >= 2:
        t0, t1 = times.min().value, times.max().value
        alt = float(hrow.get("altitude_m") or 0.0)
        for _ in range(20):
            draw = pd.to_datetime(rng.uniform(t0, t1, 4 * n).astype(np.int64), utc=True)
            az, el = spa_sun_position(draw, float(lat), float(lon), alt if np.isfinite(alt) else 0.0)
            keep = el >= el_min
            suns.append(sun_vector_enu(az[keep], el[keep]))
            if sum(len(s) for s in suns) >= 2 * n:
                break
        sun = np.concatenate(suns)
    else:  # no site or times: jitter the training sun positions by 5 deg
        k = rng.integers(0, len(tr), 4 * n)
        az = tr["sun_azimuth_deg"].to_numpy()[k] + rng.normal(0, 5, 4 * n)
        el = np.clip(tr["sun_elevation_deg"].to_numpy()[k] + rng.normal(0, 5, 4 * n), el_min, 89.0)
        sun = sun_vector_enu(az, el)
    sun = sun[rng.permutation(len(sun))]
    # aim points: a training row's target centre plus an offset within the training spread
    centre = tr[["target_e_m", "target_n_m", "target_u_m"]].to_numpy(np.float64)
    spot = tr[["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"]].to_numpy(np.float64)
    spread = np.abs(spot - centre).max(axis=0)
    spread[1] = 0.0  # stay in the target plane (north-facing targets)
    k = rng.integers(0, len(tr), len(sun))
    aim = centre[k] + rng.uniform(-1, 1, (len(sun), 3)) * spread
    sun_t, aim_t = torch.tensor(sun), torch.tensor(aim)
    steps = inverse_kinematics(coarse, spec, sun_t, aim_t)
    ok = torch.isfinite(steps).all(-1)
    idx = torch.nonzero(ok).flatten()[:n]
    if len(idx) < n // 2:
        raise FitError(f"{spec.heliostat_id}: only {len(idx)} of the simulated pre-training "
                       "calibrations are reachable with the coarse model; check the coarse fit")
    return sun_t[idx], aim_t[idx], steps[idx]


def huber(pred, target, delta):
    """Element-wise Huber loss (quadratic below ``delta``, linear above)."""
    return torch.nn.functional.huber_loss(pred, target, delta=delta, reduction="none")


@single_threaded
def fit_pretrained(coarse: torch.Tensor, spec: HeliostatSpec, hrow, rows: pd.DataFrame,
                   data: MeasurementBatch, labels: np.ndarray, seed: int,
                   config: PretrainConfig = PretrainConfig()):
    """Fit the pre-trained network of one heliostat on its ``train`` rows (early stopping on its
    ``validation`` rows), in the variant ``config.variant`` (module docstring).

    Parameters
    ----------
    coarse : (28,) the coarse model's parameters (fit-coarse's selected preset).
    spec, hrow, rows, data : the heliostat, its heliostats.parquet row, its measurement rows (in
        the order of ``data`` and ``labels``) and their tensors.
    labels : (N,) split label per row (``train``, ``validation``, ``test``, other: unused).
    seed : seed of the network's initial weights and the pre-training's draws.

    Returns
    -------
    (model, info dict, normals (N, 3), positions (N, 3)): the predicted mirror normals of every
    row, converted from predicted steps through the coarse kinematics: the measured normal turned
    by the rotation between the coarse model's normals at the measured and at the predicted steps,
    so a row's error is the angle by which the step error turns the mirror.
    """
    if config.variant == PretrainVariant.residual.value:
        return _fit_residual(coarse, spec, data, labels, seed, config)
    return _fit_paper(coarse, spec, hrow, rows, data, labels, seed, config)


def _fit_residual(coarse: torch.Tensor, spec: HeliostatSpec, data: MeasurementBatch,
                  labels: np.ndarray, seed: int, config: PretrainConfig):
    """The ``residual`` variant: fine-tune ``IK_coarse + s f(x)`` with ``f`` starting at zero."""
    train = torch.as_tensor(labels == "train")
    val = torch.as_tensor(labels == "validation")
    with torch.no_grad():
        n_c_meas, pos_meas = forward_kinematics(coarse, spec, data.steps)
        n_meas = measured_normal(data.sun, pos_meas, data.focal_spot)
        base = inverse_kinematics(coarse, spec, data.sun, data.focal_spot)    # (N, 2) [steps]
    reachable = torch.isfinite(base).all(-1)
    fit = train & reachable
    if not bool(fit.any()):
        raise FitError(f"{spec.heliostat_id}: the coarse model reaches none of the training rows' "
                       "focal spots; check the coarse fit")
    reference = data.focal_spot[train].mean(0)
    x_raw = torch.cat([unit_vector(data.sun), (data.focal_spot - reference)[:, 0:1],
                       (data.focal_spot - reference)[:, 2:3]], -1)
    in_mean, in_std = x_raw[train].mean(0), x_raw[train].std(0).nan_to_num(1.0).clamp_min(1e-9)
    resid = data.steps - base                        # what the coarse inverse kinematics misses
    scale = resid[fit].std(0).nan_to_num(1.0).clamp_min(1.0)   # [steps per output unit]
    model = PretrainedModel(None, reference.tolist(), in_mean.tolist(), in_std.tolist(),
                            [0.0, 0.0], scale.tolist(), PretrainVariant.residual.value,
                            coarse.tolist())
    x = model.inputs(data.sun, data.focal_spot)
    y = (resid / scale).T.unsqueeze(-1)                                          # (2, N, 1)
    delta = config.residual_huber_steps / float(scale.mean())                   # [output units]
    base_ok = torch.where(reachable[:, None], base, data.steps)

    def normals_for(layers_):
        with torch.no_grad():
            pred = model.steps(data.sun, data.focal_spot, layers_, base=base_ok)
            n_c_pred, _ = forward_kinematics(coarse, spec, pred)
            normal = rotate_between(n_c_meas, n_c_pred, n_meas)
        # unreachable rows keep the coarse model's prediction (its normal at the measured steps)
        return torch.where(reachable[:, None], normal, n_c_meas)

    def val_error(layers_):
        if not bool(val.any()):
            return math.inf
        return float(error_mrad(normals_for(layers_), n_meas)[val].mean())

    layers = init_mlp([5, *config.hidden, 1], [seed, seed + 1], zero_last=True)
    leaves = [t.clone().requires_grad_(True) for wb in layers for t in wb]
    cur = [(leaves[2 * k], leaves[2 * k + 1]) for k in range(len(layers))]
    opt = Adamax(leaves, lr=config.residual_lr)
    best = [(w.detach().clone(), b.detach().clone()) for w, b in cur]
    best_val, best_epoch, since, epoch = val_error(best), 0, 0, 0
    idx = torch.nonzero(fit).flatten()
    for epoch in range(1, config.residual_epochs + 1):
        loss = huber(mlp_forward(cur, x[idx]), y[:, idx], delta).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        v = val_error([(w.detach(), b.detach()) for w, b in cur])
        if v < best_val:
            best_val, best_epoch, since = v, epoch, 0
            best = [(w.detach().clone(), b.detach().clone()) for w, b in cur]
        else:
            since += 1
            if since >= config.residual_patience:
                break
    model.layers = best
    info = {"finetune_best_epoch": best_epoch, "finetune_epochs": epoch,
            "unreachable_rows": int((~reachable).sum())}
    return model, info, normals_for(best), pos_meas


def _fit_paper(coarse: torch.Tensor, spec: HeliostatSpec, hrow, rows: pd.DataFrame,
               data: MeasurementBatch, labels: np.ndarray, seed: int, config: PretrainConfig):
    """The ``paper`` variant: pre-train on the coarse model, fine-tune on the training rows."""
    rng = np.random.default_rng(seed)
    torch_gen = torch.Generator().manual_seed(int(seed))
    train = labels == "train"
    val = labels == "validation"
    sun, spot, steps = simulate_pretraining(coarse, spec, hrow, rows, train, config.n_samples, rng)
    reference = data.focal_spot[torch.as_tensor(train)].mean(0)
    x_raw = torch.cat([unit_vector(sun), (spot - reference)[:, 0:1], (spot - reference)[:, 2:3]], -1)
    model = PretrainedModel(None, reference.tolist(), x_raw.mean(0).tolist(),
                            x_raw.std(0).clamp_min(1e-9).tolist(), steps.mean(0).tolist(),
                            steps.std(0).clamp_min(1e-9).tolist())
    x = model.inputs(sun, spot)
    y = ((steps - torch.as_tensor(model.out_mean)) / torch.as_tensor(model.out_std)).T.unsqueeze(-1)
    n_hold = max(len(x) // 10, 1)
    x_tr, y_tr, x_ho, y_ho = x[n_hold:], y[:, n_hold:], x[:n_hold], y[:, :n_hold]
    sizes = [5, *config.hidden, 1]
    layers = init_mlp(sizes, [seed, seed + 1], zero_last=False)
    leaves = [t.clone().requires_grad_(True) for wb in layers for t in wb]
    cur = [(leaves[2 * k], leaves[2 * k + 1]) for k in range(len(layers))]
    opt = Adamax(leaves, lr=config.pretrain_lr)
    sched = ReduceOnPlateau(opt, factor=0.5, patience=5)
    best, best_loss, since, epochs = None, math.inf, 0, 0
    for epoch in range(config.pretrain_epochs):
        perm = torch.randperm(len(x_tr), generator=torch_gen)
        for start in range(0, len(x_tr), config.batch_size):
            idx = perm[start:start + config.batch_size]
            loss = huber(mlp_forward(cur, x_tr[idx]), y_tr[:, idx], config.huber_delta).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            hold = float(huber(mlp_forward(cur, x_ho), y_ho, config.huber_delta).mean())
        sched.step(hold)
        epochs = epoch + 1
        if hold < best_loss - 1e-12:
            best_loss, since = hold, 0
            best = [(w.detach().clone(), b.detach().clone()) for w, b in cur]
        else:
            since += 1
            if since >= config.patience:
                break
    pre_layers = best
    info = {"pretrain_epochs": epochs, "pretrain_holdout_huber": best_loss,
            "pretrain_samples": int(len(x))}

    # fine-tuning on the real training rows (full batch), early stopping on validation error_mrad
    with torch.no_grad():
        n_c_meas, pos_meas = forward_kinematics(coarse, spec, data.steps)
        n_meas = measured_normal(data.sun, pos_meas, data.focal_spot)

    def normals_for(layers_):
        model.layers = layers_
        pred_steps = model.steps(data.sun, data.focal_spot)
        n_c_pred, _ = forward_kinematics(coarse, spec, pred_steps)
        return rotate_between(n_c_meas, n_c_pred, n_meas), pred_steps

    x_real = model.inputs(data.sun, data.focal_spot)
    y_real = ((data.steps - torch.as_tensor(model.out_mean)) / torch.as_tensor(model.out_std)).T.unsqueeze(-1)
    tr_idx = torch.as_tensor(np.flatnonzero(train))
    leaves = [t.clone().requires_grad_(True) for wb in pre_layers for t in wb]
    cur = [(leaves[2 * k], leaves[2 * k + 1]) for k in range(len(layers))]
    opt = Adamax(leaves, lr=config.finetune_lr)
    sched = ReduceOnPlateau(opt, factor=0.5, patience=config.patience // 3)
    best = [(w.detach().clone(), b.detach().clone()) for w, b in cur]
    with torch.no_grad():
        nrm, _ = normals_for(best)
        errs = error_mrad(nrm, n_meas)
    best_val = float(errs[torch.as_tensor(val)].mean()) if val.any() else math.inf
    best_epoch, since = 0, 0
    for epoch in range(1, config.finetune_epochs + 1):
        loss = huber(mlp_forward(cur, x_real[tr_idx]), y_real[:, tr_idx], config.huber_delta).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            nrm, _ = normals_for([(w.detach(), b.detach()) for w, b in cur])
            errs = error_mrad(nrm, n_meas)
            v = float(errs[torch.as_tensor(val)].mean()) if val.any() else float(loss)
        sched.step(v)
        if v < best_val or not val.any():
            best_val, best_epoch, since = v, epoch, 0
            best = [(w.detach().clone(), b.detach().clone()) for w, b in cur]
        else:
            since += 1
            if since >= config.patience:
                break
    model.layers = best
    with torch.no_grad():
        normal, _ = normals_for(best)
    info.update({"finetune_best_epoch": best_epoch, "finetune_epochs": epoch})
    return model, info, normal, pos_meas
