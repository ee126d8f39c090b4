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
fast); the reported ``aim_error_mrad`` is the angle between the beam reflected by the forward
model at the returned steps and the direction to the aim point.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd
import torch

from ..artifacts.store import (artifact_path, artifact_present, check_fresh, committed_fingerprint,
                               merge_with_previous, previous_run_matches, read_artifact,
                               write_artifact)
from ..artifacts.schemas import COARSE_PARAMS
from .coarse import (MeasurementBatch, _kind, _load_split, load_selected_parameters, metrics_frame,
                     predict)
from ..errors import (FitError, InputError, ParameterError, StageInputError, check_choice,
                      check_float, check_int)
from ..physics.kinematics import (PARAMETER_NAMES, HeliostatSpec, ParameterComponents,
                                  forward_kinematics, inverse_kinematics, nominal_parameters)
from ..physics.metrics import error_mrad, measured_normal, reflect
from ..physics.lm import _SPEC_TENSORS, stack_specs
from ..artifacts.modelfiles import model_files, read_model, write_model
from ..runtime.parallel import map_tasks
from ..artifacts.schemas import HELIOSTATS, MEASUREMENTS
from ..artifacts.transaction import (current_transaction, load_manifest, read_committed,
                                     stage_transaction)
from ..artifacts.workdir_lock import locks_workdir
from ..artifacts.schemas import HYBRID_PREDICTIONS

__all__ = [
    "MODES",
    "OUTPUT_SCALE",
    "FineConfig",
    "PretrainConfig",
    "FeatureEncoder",
    "FineProblem",
    "MemberResult",
    "init_mlp",
    "mlp_forward",
    "output_scales",
    "build_problem",
    "train_members",
    "predict_members",
    "member_errors_mrad",
    "predict_ensembles",
    "ensemble_errors_mrad",
    "ensemble_seeds",
    "DEFAULT_FOURIER_BANDS",
    "predictions_frame",
    "run_fit_hybrid",
    "load_model",
    "aim_models",
    "aim_steps",
]

log = logging.getLogger("heliocal.hybrid")

#: Modes of ``fit-hybrid``.
MODES = ("hybrid", "nn-only", "pretrained-nn")

#: Output scale per parameter kind: one unit of network output is this deviation. Angles [rad],
#: translations [m], actuator lengths [m]; increments relative to the nominal increment.
OUTPUT_SCALE = {"angle": 1e-3, "translation": 1e-2, "length": 3e-4, "increment": 1e-3}


_FUNC = "fit_hybrid"


@contextlib.contextmanager
def _one_thread():
    """Run torch on one thread: the networks are tiny, and with several threads the per-call
    overhead of the intra-op pool dominates (a 177 x 2 x 2 ``bmm`` takes 2 us on one thread and
    up to milliseconds on two busy ones). Restores the previous setting."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _single_threaded(func):
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with _one_thread():
            return func(*args, **kwargs)
    return wrapper


# ------------------------------------------------------------------------------------------------
# configuration
# ------------------------------------------------------------------------------------------------
#: Default Fourier bands of the steps: every integer 1..32 [1 / max_steps].
DEFAULT_FOURIER_BANDS = tuple(float(b) for b in range(1, 33))


def ensemble_seeds(seed: int, ensemble: int) -> list[int]:
    """Seeds of the ``ensemble`` networks of the model with seed ``seed``:
    ``seed * ensemble + k`` for k = 0 .. ensemble - 1 (one network: the seed itself; different
    seeds never share a network)."""
    return [int(seed) * int(ensemble) + k for k in range(int(ensemble))]


@dataclass(frozen=True)
class FineConfig:
    """Settings of the fine network and its training (``__init__`` only stores them).

    Attributes
    ----------
    depth : hidden layers (paper 000: 14).
    width : neurons per hidden layer (paper 000: 2).
    fourier_bands : frequencies ``b`` of the Fourier features of the normalised steps [1/range].
    env : names of ``env_*`` columns (without the prefix) used as extra inputs.
    learning_rate : Adam step size.
    max_epochs : epoch budget (full batch: one step per epoch).
    patience : epochs without a validation improvement before a member stops.
    output_scale_factor : multiplies :data:`OUTPUT_SCALE` (1 for ``hybrid``).
    fourier_decay : the Fourier feature of band ``b`` has amplitude ``b ** -fourier_decay``
        (0: all 1, Tancik et al.; > 0: a smoothness prior, see :class:`FeatureEncoder`).
    ensemble : networks per model; the model's deviation is their mean (see
        :func:`ensemble_seeds`). Averaging removes most of the dependence on the initial
        weights, which for a 14 x 2 network is large (docs/hybrid.md, "Ensembles").

    The default bands are every integer 1..32: a complete Fourier series of the normalised
    steps, so a disturbance with any period of at least ``max_steps / 32`` steps (a gear or
    worm period, say) is a linear function of the inputs. Octave bands (1, 2, 4, ..., 32) can
    only express periods near ``max_steps / 2**k`` (docs/hybrid.md, "Why SS48 missed").
    """

    depth: int = 14
    width: int = 2
    fourier_bands: tuple[float, ...] = DEFAULT_FOURIER_BANDS
    env: tuple[str, ...] = ()
    learning_rate: float = 3e-3
    max_epochs: int = 800
    patience: int = 200
    output_scale_factor: float = 1.0
    fourier_decay: float = 0.0
    ensemble: int = 4

    def validated(self) -> "FineConfig":
        check_int(self.depth, "depth", _FUNC, 0)
        check_int(self.width, "width", _FUNC, 1)
        check_float(self.learning_rate, "learning_rate", _FUNC, 0.0, None, low_inclusive=False)
        check_int(self.max_epochs, "max_epochs", _FUNC, 0)
        check_int(self.patience, "patience", _FUNC, 1)
        check_float(self.output_scale_factor, "output_scale_factor", _FUNC, 0.0, None,
                    low_inclusive=False)
        for b in self.fourier_bands:
            check_float(b, "fourier_bands", _FUNC, 0.0, None, low_inclusive=False)
        check_float(self.fourier_decay, "fourier_decay", _FUNC, 0.0, None)
        check_int(self.ensemble, "ensemble", _FUNC, 1)
        return self

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["fourier_bands"] = list(self.fourier_bands)
        d["env"] = list(self.env)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "FineConfig":
        d = dict(d)
        d["fourier_bands"] = tuple(float(b) for b in d.get("fourier_bands", ()))
        d["env"] = tuple(d.get("env", ()))
        return cls(**d)


@dataclass(frozen=True)
class PretrainConfig:
    """Settings of the paper-002 baseline (``pretrained-nn``).

    Attributes
    ----------
    hidden : hidden layer widths (paper 002: 6-5-4-3).
    n_samples : simulated pre-training samples (paper 002: 4,000; 90:10 train/holdout).
    pretrain_lr : AdaMax step size of the pre-training (reduced on plateaus).
    pretrain_epochs : epoch budget of the pre-training (mini-batches of ``batch_size``).
    batch_size : pre-training mini-batch size.
    finetune_lr : AdaMax step size of the fine-tuning on real rows (small, to keep the
        pre-training; paper 002 uses 1e-5 with many more epochs).
    finetune_epochs : epoch budget of the fine-tuning (full batch).
    patience : epochs without improvement before pre-training / fine-tuning stops.
    huber_delta : Huber transition, in units of the normalised steps.
    """

    hidden: tuple[int, ...] = (6, 5, 4, 3)
    n_samples: int = 4000
    pretrain_lr: float = 1e-2
    pretrain_epochs: int = 150
    batch_size: int = 200
    finetune_lr: float = 1e-4
    finetune_epochs: int = 400
    patience: int = 30
    huber_delta: float = 0.01

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "PretrainConfig":
        d = dict(d)
        d["hidden"] = tuple(int(h) for h in d.get("hidden", (6, 5, 4, 3)))
        return cls(**d)


def output_scales(free: torch.Tensor, nominal: torch.Tensor, factor: float = 1.0) -> torch.Tensor:
    """Deviation per unit of network output for each free parameter, shape (P,).

    Parameters
    ----------
    free : bool (28,) free parameters (their order is the network's output order).
    nominal : (28,) nominal parameters (increments scale relative to them).
    factor : multiplier of :data:`OUTPUT_SCALE`.
    """
    scales = []
    for i in torch.nonzero(free).flatten().tolist():
        kind = _kind(PARAMETER_NAMES[i])
        s = OUTPUT_SCALE[kind]
        if kind == "increment":
            s *= abs(float(nominal[i])) or 1.0
        scales.append(s * factor)
    return torch.tensor(scales, dtype=torch.float64)


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
def _epoch_seconds(timestamps) -> np.ndarray:
    ts = pd.to_datetime(pd.Series(timestamps), utc=True)
    out = (ts - pd.Timestamp("1970-01-01", tz="UTC")).dt.total_seconds().to_numpy(np.float64)
    return out


def _month_position(timestamps) -> np.ndarray:
    """Month as a continuous position in the year, in [0, 12)."""
    ts = pd.to_datetime(pd.Series(timestamps), utc=True)
    days = np.where(ts.dt.is_leap_year, 366.0, 365.0)
    frac = (ts.dt.day_of_year.to_numpy(np.float64) - 1.0
            + (ts.dt.hour * 3600 + ts.dt.minute * 60 + ts.dt.second).to_numpy(np.float64) / 86400.0)
    return 12.0 * frac / days


@dataclass
class FeatureEncoder:
    """The fine network's input encoding (paper 000 section 3.3); all constants are stored so
    that :meth:`to_dict` / :meth:`from_dict` rebuild it exactly.

    Attributes
    ----------
    step_scale : (2,) divisor of the steps [steps] (the actuators' maximum steps).
    bands : Fourier frequency bands.
    t0_s, t1_s : first and last measurement time [s since 1970-01-01 UTC] (eq. 1).
    env : env column names (without ``env_``); env_mean, env_std : their standardisation.
    fill_time_s : time used for rows without a timestamp (the median time).
    """

    step_scale: list
    bands: tuple
    t0_s: float
    t1_s: float
    fill_time_s: float
    env: tuple = ()
    env_mean: list = field(default_factory=list)
    env_std: list = field(default_factory=list)
    decay: float = 0.0

    @property
    def n_features(self) -> int:
        return 2 + 4 * len(self.bands) + 4 + len(self.env)

    @classmethod
    def fit(cls, rows: pd.DataFrame, spec: HeliostatSpec, bands: Sequence[float],
            env: Sequence[str] = (), decay: float = 0.0) -> "FeatureEncoder":
        """Normalisation constants from all rows of one heliostat (inputs only)."""
        steps = rows[["axis_1_steps", "axis_2_steps"]].to_numpy(np.float64)
        scale = []
        for axis in (0, 1):
            hi = float(spec.max_steps[axis])
            if not math.isfinite(hi) or hi <= 0:
                hi = float(np.nanmax(np.abs(steps[:, axis]))) or 1.0
            scale.append(hi)
        t = _epoch_seconds(rows["timestamp"]) if "timestamp" in rows else np.array([np.nan])
        finite = t[np.isfinite(t)]
        if len(finite):
            t0, t1, fill = float(finite.min()), float(finite.max()), float(np.median(finite))
        else:
            t0, t1, fill = 0.0, 1.0, 0.0
        means, stds = [], []
        for name in env:
            col = f"env_{name}"
            if col not in rows.columns:
                avail = sorted(c[4:] for c in rows.columns if c.startswith("env_"))
                raise InputError(f"measurements.parquet has no column {col!r} for --env "
                                 f"{name}; available env columns: {avail or 'none'}")
            v = pd.to_numeric(rows[col], errors="coerce").to_numpy(np.float64)
            v = v[np.isfinite(v)]
            means.append(float(v.mean()) if len(v) else 0.0)
            stds.append(float(v.std()) if len(v) and v.std() > 0 else 1.0)
        return cls(scale, tuple(float(b) for b in bands), t0, t1, fill, tuple(env), means, stds,
                   float(decay))

    def context(self, timestamps, env_values: np.ndarray | None = None) -> torch.Tensor:
        """Time, season and env features (N, 4 + E) for UTC ``timestamps`` (NaT -> median time)
        and ``env_values`` (N, E) raw values (NaN -> the mean)."""
        t = _epoch_seconds(timestamps)
        missing = ~np.isfinite(t)
        if missing.any():
            t = np.where(missing, self.fill_time_s, t)
        span = self.t1_s - self.t0_s
        dt = (t - self.t0_s) / span if span > 0 else np.zeros_like(t)
        ts = pd.to_datetime(pd.Series(t), unit="s", utc=True)
        month = _month_position(ts)
        cols = [np.sin(math.pi * dt), np.cos(math.pi * dt),
                np.sin(2 * math.pi * month / 12.0), np.cos(2 * math.pi * month / 12.0)]
        if self.env:
            env_values = np.asarray(env_values, np.float64).reshape(len(t), len(self.env))
            z = (env_values - np.asarray(self.env_mean)) / np.asarray(self.env_std)
            cols += list(np.nan_to_num(z, nan=0.0).T)
        return torch.tensor(np.stack(cols, axis=-1), dtype=torch.float64)

    def context_from_frame(self, rows: pd.DataFrame) -> torch.Tensor:
        env = rows[[f"env_{e}" for e in self.env]].apply(pd.to_numeric, errors="coerce") \
            .to_numpy(np.float64) if self.env else None
        return self.context(rows["timestamp"], env)

    def step_features(self, steps: torch.Tensor) -> torch.Tensor:
        """Normalised steps and their Fourier features (..., 2 + 4 B), differentiable."""
        a = steps / torch.as_tensor(self.step_scale, dtype=torch.float64)
        feats = [a]
        for b in self.bands:
            amp = b ** -self.decay if self.decay else 1.0
            feats += [amp * torch.sin(2 * math.pi * b * a), amp * torch.cos(2 * math.pi * b * a)]
        return torch.cat(feats, dim=-1)

    def encode(self, steps: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """All inputs (..., N, n_features) from steps (..., N, 2) and context (N, 4 + E)."""
        sf = self.step_features(steps)
        return torch.cat([sf, context.expand(*sf.shape[:-1], context.shape[-1])], dim=-1)

    def to_dict(self) -> dict:
        return {"step_scale": list(map(float, self.step_scale)), "bands": list(self.bands),
                "t0_s": self.t0_s, "t1_s": self.t1_s, "fill_time_s": self.fill_time_s,
                "env": list(self.env), "env_mean": list(self.env_mean),
                "env_std": list(self.env_std), "decay": float(self.decay)}

    @classmethod
    def from_dict(cls, d: Mapping) -> "FeatureEncoder":
        return cls(list(d["step_scale"]), tuple(d["bands"]), float(d["t0_s"]), float(d["t1_s"]),
                   float(d["fill_time_s"]), tuple(d.get("env", ())), list(d.get("env_mean", ())),
                   list(d.get("env_std", ())), float(d.get("decay", 0.0)))


# ------------------------------------------------------------------------------------------------
# the batched self-normalizing MLP
# ------------------------------------------------------------------------------------------------
Layers = list  # [(W (M, out, in), b (M, out)), ...]


def init_mlp(sizes: Sequence[int], seeds: Sequence[int], *, zero_last: bool = True) -> Layers:
    """LeCun-normal weights (std 1/sqrt(fan_in)), zero biases, for ``len(seeds)`` members.

    Member ``m`` draws from its own ``torch.Generator`` seeded with ``seeds[m]`` (layer by layer),
    so a member's initial weights do not depend on the other members. With ``zero_last`` the
    output layer is all zeros (the untrained hybrid equals its base model exactly).
    """
    per_member = []
    for seed in seeds:
        g = torch.Generator().manual_seed(int(seed))
        layers = []
        for k, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            w = torch.randn(fan_out, fan_in, generator=g, dtype=torch.float64) / math.sqrt(fan_in)
            if zero_last and k == len(sizes) - 2:
                w = torch.zeros_like(w)
            layers.append((w, torch.zeros(fan_out, dtype=torch.float64)))
        per_member.append(layers)
    return [(torch.stack([m[k][0] for m in per_member]), torch.stack([m[k][1] for m in per_member]))
            for k in range(len(sizes) - 1)]


def mlp_forward(layers: Layers, x: torch.Tensor) -> torch.Tensor:
    """Apply the member networks: x (M, N, in) or (N, in) -> (M, N, out). SELU between layers,
    linear output."""
    return _mlp_columns(layers, x).transpose(1, 2)


def _mlp_columns(layers: Layers, x: torch.Tensor) -> torch.Tensor:
    """:func:`mlp_forward` with the rows as columns: returns (M, out, N).

    Activations are kept as (M, width, N) so every layer is one batched ``W @ H`` whose long
    dimension (the N rows) is contiguous; the row-major (M, N, width) layout makes the batched
    matrix products of a narrow network several times slower.
    """
    w0, b0 = layers[0]
    h = torch.matmul(w0, x.transpose(-1, -2)) + b0.unsqueeze(-1)       # (M, width, N)
    for w, b in layers[1:]:
        h = torch.baddbmm(b.unsqueeze(-1), w, torch.nn.functional.selu(h))
    return h


def _flatten_layers(layers: Layers) -> torch.Tensor:
    """All weights and biases of each member in one row: (M, T)."""
    m = layers[0][0].shape[0]
    return torch.cat([t.reshape(m, -1) for w, b in layers for t in (w, b)], dim=1)


def _layer_views(theta: torch.Tensor, like: Layers) -> Layers:
    """Views of the flat (M, T) tensor shaped like ``like`` (inverse of :func:`_flatten_layers`).

    Training keeps one flat leaf tensor so that the optimiser, the weight-decay penalty, the
    gradient clean-up and the best-state bookkeeping are one operation each, not one per layer.
    """
    views, offset = [], 0
    for w, b in like:
        (_, o, i), nb = w.shape, b.shape[1]
        views.append((theta[:, offset:offset + o * i].view(-1, o, i),
                      theta[:, offset + o * i:offset + o * i + nb]))
        offset += o * i + nb
    return views


def _layers_to_state(layers: Layers, member: int | None = None) -> dict:
    state = {}
    for k, (w, b) in enumerate(layers):
        state[f"layers.{k}.weight"] = (w if member is None else w[member:member + 1]).detach().clone()
        state[f"layers.{k}.bias"] = (b if member is None else b[member:member + 1]).detach().clone()
    return state


def _state_to_layers(state: Mapping) -> Layers:
    n = len([k for k in state if k.endswith(".weight")])
    return [(state[f"layers.{k}.weight"].to(torch.float64), state[f"layers.{k}.bias"].to(torch.float64))
            for k in range(n)]


# ------------------------------------------------------------------------------------------------
# one heliostat's fine problem
# ------------------------------------------------------------------------------------------------
@dataclass
class FineProblem:
    """Everything the fine model of one heliostat needs besides its weights.

    Attributes
    ----------
    spec : the heliostat's fixed description.
    base : (28,) parameters the deviations are added to (coarse fit or nominal).
    free : bool (28,) parameters that get a deviation (the network's outputs, in order).
    scales : (P,) deviation per unit output (:func:`output_scales`).
    encoder : the input encoding.
    data : the measurements (N rows).
    context : (N, 4 + E) time, season and env features of the rows.
    cached_features : the encoded inputs of ``data`` (set by :func:`stack_problems`, whose
        heliostats each have their own encoder).

    :func:`stack_problems` makes one problem of M heliostats: every tensor above then has a
    leading member axis (spec batch (M, 1), base (M, 1, 28), scales (M, P), data (M, N, ...)).
    """

    spec: HeliostatSpec
    base: torch.Tensor
    free: torch.Tensor
    scales: torch.Tensor
    encoder: FeatureEncoder | None
    data: MeasurementBatch
    context: torch.Tensor
    cached_features: torch.Tensor | None = None

    @property
    def free_index(self) -> torch.Tensor:
        return torch.nonzero(self.free).flatten()

    def sizes(self, config: FineConfig) -> list[int]:
        n_in = (self.cached_features.shape[-1] if self.cached_features is not None
                else self.encoder.n_features)
        return [n_in] + [config.width] * config.depth + [int(self.free.sum())]

    def features(self, steps: torch.Tensor | None = None, context: torch.Tensor | None = None):
        if steps is None and context is None and self.cached_features is not None:
            return self.cached_features
        steps = self.data.steps if steps is None else steps
        return self.encoder.encode(steps, self.context if context is None else context)


def _take_rows(problem: FineProblem, rows: torch.Tensor) -> FineProblem:
    """The problem (single or stacked) on the rows where ``rows`` (N,) is true, features kept."""
    take = lambda t: t[..., rows, :]
    features = problem.features()
    d = problem.data
    data = MeasurementBatch(d.measurement_id[..., rows.numpy()], take(d.steps), take(d.sun),
                            take(d.focal_spot), take(d.target_center), take(d.target_normal))
    return dataclasses.replace(problem, data=data, context=take(problem.context),
                               cached_features=take(features))


def _take_members(problem: FineProblem, keep: torch.Tensor) -> FineProblem:
    """The members where ``keep`` (M,) is true: a problem's per-member tensors (stacked data,
    spec, inputs and scales, per-member base) are sliced; shared ones are kept as they are."""
    if problem.base.dim() == 3:
        problem = dataclasses.replace(problem, base=problem.base[keep])
    if problem.data.steps.dim() != 3:            # one heliostat: only the base is per member
        return problem
    spec = copy.copy(problem.spec)
    for name in _SPEC_TENSORS:
        object.__setattr__(spec, name, getattr(spec, name)[keep])
    d = problem.data
    data = MeasurementBatch(d.measurement_id[keep.numpy()], d.steps[keep], d.sun[keep],
                            d.focal_spot[keep], d.target_center[keep], d.target_normal[keep])
    return dataclasses.replace(problem, spec=spec, data=data, context=problem.context[keep],
                               scales=problem.scales[keep],
                               cached_features=problem.features()[keep])


def _keep_rows_of_leaf(theta: torch.Tensor, opt: torch.optim.Adam, keep: torch.Tensor, lr: float):
    """A new (L', T) leaf of the kept rows and an Adam that continues from their moments (Adam
    is elementwise, so the kept members follow exactly the path they would have followed)."""
    state = opt.state[theta]
    new = theta.detach()[keep].clone().requires_grad_(True)
    new_opt = torch.optim.Adam([new], lr=lr)
    if state:
        new_opt.state[new] = {"step": state["step"].clone(),
                              "exp_avg": state["exp_avg"][keep].clone(),
                              "exp_avg_sq": state["exp_avg_sq"][keep].clone()}
    return new, new_opt


def _pad_rows(t: torch.Tensor, n: int) -> torch.Tensor:
    """Pad (N, ...) to (n, ...) by repeating the last row (finite values for masked rows)."""
    if t.shape[0] == n:
        return t
    return torch.cat([t, t[-1:].expand(n - t.shape[0], *t.shape[1:])])


def stack_problems(problems: Sequence[FineProblem]) -> tuple[FineProblem, torch.Tensor]:
    """One problem of M heliostats (member m = heliostat m) for :func:`train_members`.

    The heliostats must share kinematic type, actuator type, free parameters and input size.
    Shorter heliostats are padded to the longest (their last row repeated); the returned
    ``valid`` (M, N) mask is false on padding, and the training and validation masks must be
    and-ed with it. Each heliostat keeps its own encoder, spec, base and scales, so member m
    trains exactly as heliostat m would alone.
    """
    free = problems[0].free
    if any(not torch.equal(p.free, free) for p in problems):
        raise ParameterError("The 'problems' parameter of stack_problems must share the free "
                             "parameters (one coarse preset).")
    n = max(len(p.data) for p in problems)
    spec = stack_specs([p.spec for p in problems])
    for name in _SPEC_TENSORS:
        object.__setattr__(spec, name, getattr(spec, name).unsqueeze(1))   # batch (M, 1)
    pad = lambda get: torch.stack([_pad_rows(get(p), n) for p in problems])
    data = MeasurementBatch(
        measurement_id=np.array([np.resize(p.data.measurement_id, n) for p in problems]),
        steps=pad(lambda p: p.data.steps), sun=pad(lambda p: p.data.sun),
        focal_spot=pad(lambda p: p.data.focal_spot),
        target_center=pad(lambda p: p.data.target_center),
        target_normal=pad(lambda p: p.data.target_normal))
    valid = torch.stack([torch.arange(n) < len(p.data) for p in problems])
    stacked = FineProblem(spec, torch.stack([p.base for p in problems]).unsqueeze(1), free,
                          torch.stack([p.scales for p in problems]), problems[0].encoder, data,
                          pad(lambda p: p.context), pad(lambda p: p.features()))
    return stacked, valid


def build_problem(rows: pd.DataFrame, hrow: pd.Series, base: torch.Tensor, free: torch.Tensor,
                  config: FineConfig) -> FineProblem:
    """The fine problem of one heliostat from its measurement rows and heliostats.parquet row.

    Parameters
    ----------
    rows : this heliostat's rows of measurements.parquet (all splits; normalisation uses all).
    hrow : its row of heliostats.parquet.
    base : (28,) coarse parameters (``hybrid``) or nominal (``nn-only``).
    free : bool (28,) free parameters of the selected coarse preset.
    """
    spec = HeliostatSpec.from_row(hrow)
    nominal = nominal_parameters(hrow)
    encoder = FeatureEncoder.fit(rows, spec, config.fourier_bands, config.env, config.fourier_decay)
    data = MeasurementBatch.from_frame(rows)
    return FineProblem(spec, base.to(torch.float64), free.to(torch.bool),
                       output_scales(free, nominal, config.output_scale_factor), encoder, data,
                       encoder.context_from_frame(rows))


def member_components(problem: FineProblem, layers: Layers,
                      features: torch.Tensor) -> ParameterComponents:
    """Per-member, per-row parameters as :class:`ParameterComponents`: base + scaled network
    deviations, (M, N) for the free parameters and (M, 1) for the fixed ones (no per-row
    kinematics work for those)."""
    return _components(problem, _mlp_columns(layers, features) * problem.scales.unsqueeze(-1))


def _components(problem: FineProblem, out: torch.Tensor) -> ParameterComponents:
    """Base parameters plus scaled deviations ``out`` (M, P, N) as components."""
    base = problem.base                                                   # (28,) or (M, 1, 28)
    base = base.unsqueeze(-1) if base.dim() == 1 else base.transpose(-1, -2)  # (28, 1) | (M, 28, 1)
    comps = list(base.unbind(-2))                                         # 28 x (1,) | (M, 1)
    # unbind, not out[:, j]: the backward of P separate selects zero-fills a full (M, P, N)
    # gradient per parameter (P^2 M N work, most of an epoch at M = 128); unbind's is one stack
    for k, col in zip(problem.free_index.tolist(), out.unbind(1)):
        comps[k] = comps[k] + col
    return ParameterComponents(comps)


def member_parameters(problem: FineProblem, layers: Layers, features: torch.Tensor) -> torch.Tensor:
    """Per-member, per-row parameters (M, N, 28) = base + scaled network deviations."""
    return member_components(problem, layers, features).stacked()


def predict_members(problem: FineProblem, layers: Layers, steps: torch.Tensor | None = None,
                    context: torch.Tensor | None = None):
    """Mirror normals and centres (M, N, 3) of every member at ``steps`` (N, 2) (default: the
    problem's measured steps and contexts).

    ``forward_kinematics`` broadcasts parameters (M, N, 28) against steps of shape (N, 1, 2)
    (each row its own parameter vector, one step pair each); steps (N, 2) would pair every
    parameter vector with every row.
    """
    steps = problem.data.steps if steps is None else steps
    return _forward(problem, layers, problem.features(steps, context), steps)


def _grouped(problem: FineProblem, layers: Layers, features: torch.Tensor,
             ensemble: int | None) -> ParameterComponents:
    """Components of G = M / K models whose K networks are consecutive members (K =
    ``ensemble``; None: all M networks are one model)."""
    out = _mlp_columns(layers, features) * problem.scales.unsqueeze(-1)   # (M, P, N)
    m = out.shape[0]
    k = m if ensemble is None else int(ensemble)
    if k < 1 or m % k:
        raise ParameterError(f"The 'ensemble' parameter must divide the {m} networks. Got {k} "
                             "instead.")
    out = out.reshape(m // k, k, *out.shape[1:]).mean(1)                  # (G, P, N)
    base = problem.base
    if base.dim() == 3 and base.shape[0] == m:                            # per-member bases
        base = base[::k]
    return _components(dataclasses.replace(problem, base=base), out)


def predict_ensembles(problem: FineProblem, layers: Layers, ensemble: int | None = None,
                      steps: torch.Tensor | None = None, context: torch.Tensor | None = None):
    """Mirror normals and centres (G, N, 3) of models made of ``ensemble`` consecutive
    networks each (G = M / ensemble; default: all of ``layers`` is one model), whose deviation
    is the mean of their networks' deviations. Steps and context as :func:`predict_members`."""
    steps = problem.data.steps if steps is None else steps
    return _kinematics(problem, _grouped(problem, layers, problem.features(steps, context),
                                         ensemble), steps)


def ensemble_errors_mrad(problem: FineProblem, layers: Layers, ensemble: int | None = None):
    """error_mrad (G, N) of the models of :func:`predict_ensembles` on the problem's rows."""
    return _errors(problem, *predict_ensembles(problem, layers, ensemble))


def _kinematics(problem: FineProblem, params: ParameterComponents, steps: torch.Tensor):
    """Normals and centres (M, N, 3) for per-row parameters (M, N) and their steps (N, 2)."""
    normal, position = forward_kinematics(params, problem.spec, steps.unsqueeze(-2))
    return normal.squeeze(-2), position.squeeze(-2)


def _errors(problem: FineProblem, normal: torch.Tensor, position: torch.Tensor) -> torch.Tensor:
    """error_mrad of predicted normals and mirror centres on the problem's measurements."""
    return error_mrad(normal, measured_normal(problem.data.sun, position, problem.data.focal_spot))


def _forward(problem: FineProblem, layers: Layers, features: torch.Tensor, steps: torch.Tensor):
    """Normals and centres (M, N, 3) of every member for encoded inputs and their steps."""
    return _kinematics(problem, member_components(problem, layers, features), steps)


def member_errors_mrad(problem: FineProblem, layers: Layers) -> torch.Tensor:
    """error_mrad (M, N) of every member on every row of the problem."""
    return _errors_from_features(problem, layers, problem.features())


def _errors_from_features(problem: FineProblem, layers: Layers, features: torch.Tensor):
    return _errors(problem, *_forward(problem, layers, features, problem.data.steps))


@dataclass
class MemberResult:
    """Result of :func:`train_members` (M members).

    Attributes
    ----------
    layers : best-validation weights of every member, [(W (M, out, in), b (M, out)), ...].
    best_epoch : (M,) epoch of the kept state (0 = untrained, the base model).
    best_val_mrad : (M,) mean validation error of the kept state (NaN without validation rows).
    epochs_run : (M,) epochs each member trained before it stopped.
    history_train, history_val : (E, M) mean squared train error and mean validation error
        after each epoch (row 0 = before training); NaN once a member has stopped and left the
        program (the program drops stopped members when a quarter of it has stopped).
    wall_time_s : wall time.
    """

    layers: Layers
    best_epoch: torch.Tensor
    best_val_mrad: torch.Tensor
    epochs_run: torch.Tensor
    history_train: torch.Tensor
    history_val: torch.Tensor
    wall_time_s: float

    def member(self, m: int) -> Layers:
        return [(w[m:m + 1], b[m:m + 1]) for w, b in self.layers]


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    n = mask.sum(-1)
    total = torch.where(mask, values, torch.zeros_like(values)).sum(-1)
    return torch.where(n > 0, total / n.clamp_min(1), torch.full_like(total, float("nan")))


@_single_threaded
def train_members(problem: FineProblem, train_mask, val_mask, weight_decays, seeds,
                  config: FineConfig = FineConfig(), *, initial: Layers | None = None,
                  progress: Callable[[int, int], None] | None = None) -> MemberResult:
    """Train M fine networks at once (one batched torch program, full-batch Adam).

    Parameters
    ----------
    problem : the heliostat's :class:`FineProblem` (N rows).
    train_mask, val_mask : bool (M, N) or (N,) rows each member trains / early-stops on.
    weight_decays : (M,) L2 penalty coefficients [mrad^2 per unit squared weight].
    seeds : (M,) integer seeds of the members' initial weights.
    config : :class:`FineConfig`.
    initial : start from these weights instead of a seeded initialisation.
    progress : optional ``progress(epoch, max_epochs)``.

    Returns
    -------
    :class:`MemberResult`. A member without validation rows keeps its last state.
    """
    config = config.validated()
    t_start = time.perf_counter()
    seeds = [int(s) for s in np.atleast_1d(np.asarray(seeds))]
    m = len(seeds)
    n = problem.data.steps.shape[-2]
    tm = torch.as_tensor(np.asarray(train_mask, bool)).reshape(-1, n).expand(m, n)
    vm = torch.as_tensor(np.asarray(val_mask, bool)).reshape(-1, n).expand(m, n)
    wd = torch.as_tensor(np.asarray(weight_decays, np.float64)).reshape(-1).expand(m).clone()
    if bool((wd < 0).any()) or not bool(torch.isfinite(wd).all()):
        raise ParameterError(f"The 'weight_decays' parameter of train_members must be finite "
                             f"floats >= 0. Got {wd.tolist()!r} instead.")
    used = (tm | vm).any(0)
    if not bool(used.all()):  # rows no member trains or stops on (test rows) cost per epoch
        problem, tm, vm = _take_rows(problem, used), tm[:, used], vm[:, used]
    layers = initial if initial is not None else init_mlp(problem.sizes(config), seeds)
    theta = _flatten_layers(layers).detach().clone().requires_grad_(True)     # (L, T), L live
    cur = _layer_views(theta, layers)
    opt = torch.optim.Adam([theta], lr=config.learning_rate)
    features = problem.features()                     # inputs do not change during training
    features = features.transpose(-1, -2).contiguous().transpose(-1, -2)  # rows contiguous
    has_val = vm.any(-1)
    n_train = tm.sum(-1).clamp_min(1)
    best = theta.detach().clone()
    best_val = torch.full((m,), math.inf, dtype=torch.float64)
    best_epoch = torch.zeros(m, dtype=torch.long)
    active = torch.ones(m, dtype=torch.bool)
    stopped_at = torch.full((m,), config.max_epochs, dtype=torch.long)
    hist_train, hist_val = [], []
    live = torch.arange(m)          # members still in the program (stopped ones are dropped)
    run_problem, run_tm, run_vm, run_wd, run_n = problem, tm, vm, wd, n_train
    for epoch in range(config.max_epochs + 1):
        keep = active[live]
        if 4 * int((~keep).sum()) >= len(live):  # a quarter has stopped: drop them
            live = live[keep]
            run_problem = _take_members(run_problem, keep)
            run_tm, run_vm, run_wd, run_n = run_tm[keep], run_vm[keep], run_wd[keep], run_n[keep]
            if features.dim() == 3:
                features = features[keep]
            theta, opt = _keep_rows_of_leaf(theta, opt, keep, config.learning_rate)
            cur = _layer_views(theta, layers)
        err = _errors_from_features(run_problem, cur, features)          # (L, N)
        sq = torch.where(run_tm, torch.nan_to_num(err, nan=0.0) ** 2, torch.zeros_like(err))
        train_mse = sq.sum(-1) / run_n
        with torch.no_grad():
            val = torch.full((m,), float("nan"), dtype=torch.float64)
            val[live] = _masked_mean(torch.nan_to_num(err.detach(), nan=1e6), run_vm)
            mse = torch.full((m,), float("nan"), dtype=torch.float64)
            mse[live] = train_mse.detach()
            hist_train.append(mse)
            hist_val.append(val.clone())
            improved = active & (torch.where(has_val, val, -torch.ones_like(val)) < best_val)
            improved |= active & ~has_val  # no validation rows: keep the latest state
            if bool(improved.any()):
                best[live] = torch.where(improved[live, None], theta.detach(), best[live])
                best_val = torch.where(improved & has_val, val, best_val)
                best_epoch = torch.where(improved, torch.full_like(best_epoch, epoch), best_epoch)
            newly = active & has_val & (epoch - best_epoch >= config.patience)
            stopped_at = torch.where(newly, torch.full_like(stopped_at, epoch), stopped_at)
            active &= ~newly
        if epoch == config.max_epochs or not bool(active.any()):
            break
        loss = (train_mse + run_wd * (theta ** 2).sum(-1)).sum()
        opt.zero_grad(set_to_none=False)
        loss.backward()
        with torch.no_grad():
            theta.grad.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
        opt.step()
        if progress:
            progress(epoch + 1, config.max_epochs)
    best = [(w.clone(), b.clone()) for w, b in _layer_views(best, layers)]
    best_val = torch.where(has_val, best_val, torch.full_like(best_val, float("nan")))
    return MemberResult(best, best_epoch, best_val, torch.minimum(stopped_at, torch.tensor(epoch)),
                        torch.stack(hist_train), torch.stack(hist_val),
                        time.perf_counter() - t_start)


# ------------------------------------------------------------------------------------------------
# prediction tables
# ------------------------------------------------------------------------------------------------
def predictions_frame(problem: FineProblem, normal: torch.Tensor, position: torch.Tensor) -> pd.DataFrame:
    """The coarse_predictions columns (metrics only) for predicted normals/centres (N, 3)."""
    return metrics_frame(problem.data, normal, position)


# ------------------------------------------------------------------------------------------------
# pretrained-nn (paper 002)
# ------------------------------------------------------------------------------------------------
def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _rotate_between(a: torch.Tensor, b: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
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
    """The two per-axis networks of paper 002 with their input/output normalisation."""

    layers: Layers               # M = 2 (axis 1, axis 2), each 5 -> hidden -> 1
    reference_m: list            # (3,) focal-spot reference point [m] ENU
    in_mean: list                # (5,)
    in_std: list                 # (5,)
    out_mean: list               # (2,)
    out_std: list                # (2,)

    def inputs(self, sun: torch.Tensor, spot: torch.Tensor) -> torch.Tensor:
        off = spot - torch.as_tensor(self.reference_m, dtype=torch.float64)
        x = torch.cat([_unit(sun), off[..., 0:1], off[..., 2:3]], dim=-1)
        return (x - torch.as_tensor(self.in_mean)) / torch.as_tensor(self.in_std)

    def steps(self, sun: torch.Tensor, spot: torch.Tensor, layers: Layers | None = None) -> torch.Tensor:
        """Predicted motor steps (N, 2) for sun vectors and focal spots (N, 3)."""
        y = mlp_forward(self.layers if layers is None else layers, self.inputs(sun, spot))  # (2, N, 1)
        y = y.squeeze(-1).T
        return y * torch.as_tensor(self.out_std) + torch.as_tensor(self.out_mean)

    def to_state(self) -> dict:
        return _layers_to_state(self.layers)

    def to_dict(self) -> dict:
        return {"reference_m": list(map(float, self.reference_m)), "in_mean": list(map(float, self.in_mean)),
                "in_std": list(map(float, self.in_std)), "out_mean": list(map(float, self.out_mean)),
                "out_std": list(map(float, self.out_std))}


def _simulate_pretraining(coarse: torch.Tensor, spec: HeliostatSpec, hrow, rows: pd.DataFrame,
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


def _huber(pred, target, delta):
    return torch.nn.functional.huber_loss(pred, target, delta=delta, reduction="none")


@_single_threaded
def fit_pretrained(coarse: torch.Tensor, spec: HeliostatSpec, hrow, rows: pd.DataFrame,
                   data: MeasurementBatch, labels: np.ndarray, seed: int,
                   config: PretrainConfig = PretrainConfig()):
    """Pre-train on the coarse model and fine-tune on the training rows (paper 002 section 2.3).

    Returns (model, info dict, normals (N, 3), positions (N, 3)) where normals/positions are the
    predicted normals converted through the coarse kinematics (see the module docstring).
    """
    rng = np.random.default_rng(seed)
    torch_gen = torch.Generator().manual_seed(int(seed))
    train = labels == "train"
    val = labels == "validation"
    sun, spot, steps = _simulate_pretraining(coarse, spec, hrow, rows, train, config.n_samples, rng)
    reference = data.focal_spot[torch.as_tensor(train)].mean(0)
    x_raw = torch.cat([_unit(sun), (spot - reference)[:, 0:1], (spot - reference)[:, 2:3]], -1)
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
    opt = torch.optim.Adamax(leaves, lr=config.pretrain_lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=5)
    best, best_loss, since, epochs = None, math.inf, 0, 0
    for epoch in range(config.pretrain_epochs):
        perm = torch.randperm(len(x_tr), generator=torch_gen)
        for start in range(0, len(x_tr), config.batch_size):
            idx = perm[start:start + config.batch_size]
            loss = _huber(mlp_forward(cur, x_tr[idx]), y_tr[:, idx], config.huber_delta).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            hold = float(_huber(mlp_forward(cur, x_ho), y_ho, config.huber_delta).mean())
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
        return _rotate_between(n_c_meas, n_c_pred, n_meas), pred_steps

    x_real = model.inputs(data.sun, data.focal_spot)
    y_real = ((data.steps - torch.as_tensor(model.out_mean)) / torch.as_tensor(model.out_std)).T.unsqueeze(-1)
    tr_idx = torch.as_tensor(np.flatnonzero(train))
    leaves = [t.clone().requires_grad_(True) for wb in pre_layers for t in wb]
    cur = [(leaves[2 * k], leaves[2 * k + 1]) for k in range(len(layers))]
    opt = torch.optim.Adamax(leaves, lr=config.finetune_lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=config.patience // 3)
    best = [(w.detach().clone(), b.detach().clone()) for w, b in cur]
    with torch.no_grad():
        nrm, _ = normals_for(best)
        errs = error_mrad(nrm, n_meas)
    best_val = float(errs[torch.as_tensor(val)].mean()) if val.any() else math.inf
    best_epoch, since = 0, 0
    for epoch in range(1, config.finetune_epochs + 1):
        loss = _huber(mlp_forward(cur, x_real[tr_idx]), y_real[:, tr_idx], config.huber_delta).mean()
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


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
def _mean(values) -> float:
    values = np.asarray(values, np.float64)
    return float(values.mean()) if len(values) else float("nan")


def _split_means(err: np.ndarray, labels: np.ndarray) -> dict:
    return {sp: _mean(err[labels == sp]) for sp in ("train", "validation", "test")}


def _current_inputs(workdir: Path) -> dict:
    """label -> committed content fingerprint of every input a fine model is made from (the labels
    its run recorded: the artifacts it read)."""
    from ..artifacts.schemas import SPLIT

    out = {}
    for label, schema in (("measurements", MEASUREMENTS), ("heliostats", HELIOSTATS),
                          ("coarse_params", COARSE_PARAMS), ("split", SPLIT)):
        fp = committed_fingerprint(workdir, schema)
        if fp is not None:
            out[label] = fp
    return out


def _check_inputs(workdir: Path) -> None:
    from ..artifacts.schemas import SPLIT

    if not artifact_present(workdir, COARSE_PARAMS):
        raise StageInputError(f"{artifact_path(workdir, COARSE_PARAMS)} is missing: run "
                              f"`heliocal fit-coarse --workdir {workdir}` first")
    upstream = {"measurements": MEASUREMENTS, "heliostats": HELIOSTATS}
    if artifact_present(workdir, SPLIT):
        upstream["split"] = SPLIT
    check_fresh(workdir, COARSE_PARAMS, upstream)


#: Heliostats per batched training program of ``fit-hybrid`` (one task for the workers).
HYBRID_BATCH_SIZE = 32


@_single_threaded
def _hybrid_chunk_task(task):
    """Heliostats of ``fit-hybrid`` that train as one batched program (a picklable task for
    :func:`map_tasks`). pretrained-nn heliostats are fitted one by one."""
    items, mode, weight_decay, seed, config, pretrain_config = task
    torch.use_deterministic_algorithms(True, warn_only=True)
    t0 = time.perf_counter()
    prepared = []
    for hid, rows, hrow, sel in items:
        hrow = pd.Series(hrow)
        rows = rows[rows["split"] != "excluded"].reset_index(drop=True)
        spec = HeliostatSpec.from_row(hrow)
        data = MeasurementBatch.from_frame(rows)
        prepared.append((hid, rows, hrow, sel, rows["split"].to_numpy(), spec, data,
                         predict(sel["params"], spec, data)))
    out = []
    if mode == "pretrained-nn":
        for hid, rows, hrow, sel, labels, spec, data, coarse_pred in prepared:
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
    for hid, rows, hrow, sel, labels, spec, data, coarse_pred in prepared:
        base = sel["params"] if mode == "hybrid" else sel["nominal"]
        problems.append(build_problem(rows, hrow, base, sel["free"], config))
    # train on the rows that matter (train and validation); test rows are predicted afterwards.
    # Member h * K + j is network j of heliostat h's ensemble of K.
    k_ens = config.ensemble
    fitting = [np.isin(p[4], ("train", "validation")) for p in prepared]
    taken = [_take_rows(pr, torch.as_tensor(f)) for pr, f in zip(problems, fitting)]
    stacked, valid = stack_problems([t for t in taken for _ in range(k_ens)])
    n = stacked.data.steps.shape[1]
    labels_fit = np.array([np.resize(p[4][f], n) for p, f in zip(prepared, fitting)
                           for _ in range(k_ens)])
    result = train_members(stacked, torch.as_tensor(labels_fit == "train") & valid,
                           torch.as_tensor(labels_fit == "validation") & valid,
                           [weight_decay] * len(labels_fit),
                           ensemble_seeds(seed, k_ens) * len(problems), config)
    wall = (time.perf_counter() - t0) / len(problems)
    for h, ((hid, rows, hrow, sel, labels, spec, data, coarse_pred), problem) in enumerate(
            zip(prepared, problems)):
        nets = slice(h * k_ens, (h + 1) * k_ens)
        layers = [(w[nets], b[nets]) for w, b in result.layers]
        with torch.no_grad():
            normal, position = predict_ensembles(problem, layers)
        info = {"best_epoch": result.best_epoch[nets].tolist(),
                "epochs": result.epochs_run[nets].tolist()}
        cfg = {"mode": mode, "heliostat_id": hid, "seed": seed, "weight_decay": weight_decay,
               "fine_config": config.to_dict(), "encoder": problem.encoder.to_dict(),
               "base_params": problem.base.tolist(), "free": sel["free"].tolist(),
               "scales": problem.scales.tolist(), "coarse_preset": sel["preset"],
               "sizes": problem.sizes(config), **info}
        out.append(_hybrid_outputs(hid, mode, sel, labels, problem, normal[0], position[0],
                                   coarse_pred, _layers_to_state(layers), cfg, info, wall))
    return out


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


def _hybrid_chunks(ids, selected, helio, batch_size: int):
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
def run_fit_hybrid(workdir: str | Path, *, mode: str = "hybrid", weight_decay: float = 0.0,
                   seed: int = 0, config: FineConfig | None = None,
                   pretrain_config: PretrainConfig | None = None,
                   heliostats: Sequence[str] | None = None, progress=None,
                   workers: int | None = 1, scheduler: str = "local",
                   dask_address: str | None = None, batch_size: int = HYBRID_BATCH_SIZE) -> dict:
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
    """
    check_choice(mode, "mode", _FUNC, MODES)
    weight_decay = check_float(weight_decay, "weight_decay", _FUNC, 0.0, None)
    seed = check_int(seed, "seed", _FUNC, 0)
    config = (config or FineConfig()).validated()
    pretrain_config = pretrain_config or PretrainConfig()
    workdir = Path(workdir)
    _check_inputs(workdir)
    torch.use_deterministic_algorithms(True, warn_only=True)
    measurements = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=heliostats).set_index("heliostat_id", drop=False)
    measurements["split"] = _load_split(workdir, measurements).to_numpy()
    selected = load_selected_parameters(workdir, heliostats)
    with_train = set(measurements.loc[measurements["split"] == "train", "heliostat_id"])
    ids = [h for h in sorted(selected) if h in helio.index and h in with_train]
    if not ids:
        raise FitError(f"no heliostat in {workdir} has a coarse fit with training rows; run "
                       f"`heliocal fit-coarse --workdir {workdir}` first")
    txn = current_transaction(workdir, "fit-hybrid")
    input_hashes = txn.input_fingerprints()  # what this run read: the models' recorded inputs
    batch_size = check_int(batch_size, "batch_size", _FUNC, 1)
    groups = dict(tuple(measurements.groupby("heliostat_id", sort=True)))
    ids = sorted(ids, key=lambda h: (len(groups[h]), h))
    tasks = [([(hid, groups[hid], helio.loc[hid].to_dict(), selected[hid]) for hid in chunk],
              mode, weight_decay, seed, config, pretrain_config)
             for chunk in _hybrid_chunks(ids, selected, helio, batch_size)]
    results = [r for chunk in map_tasks(
        _hybrid_chunk_task, tasks, workers=workers, scheduler=scheduler, dask_address=dask_address,
        progress=(lambda d, t: progress(d, t, None)) if progress else None) for r in chunk]
    results.sort(key=lambda r: r[1]["heliostat_id"])
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
    opts = {"mode": mode, "weight_decay": weight_decay, "fine_config": config.to_dict(),
            "pretrain_config": pretrain_config.to_dict(),
            "heliostats": list(heliostats) if heliostats else None}
    write_artifact(new, workdir, HYBRID_PREDICTIONS, stage="fit-hybrid", options=opts, seed=seed)
    return {"workdir": str(workdir), "mode": mode, "weight_decay": weight_decay, "seed": seed,
            "heliostats": summaries}


# ------------------------------------------------------------------------------------------------
# loading a fitted model and aiming
# ------------------------------------------------------------------------------------------------
def load_model(workdir: str | Path, mode: str, heliostat_id: str) -> tuple[dict, Layers] | None:
    """Config dict and weights of a fitted mode for one heliostat (``None`` if not fitted).

    ``mode`` ``selected`` is the sweep's selected model (``DIR/hybrid/selected/``). The files are
    read through their stage's manifest and checked (:func:`heliocal.pipeline.artifacts.modelfiles.read_model`):
    a changed, corrupt or foreign file gives a one-line error naming it and the command to rerun.
    """
    workdir = Path(workdir)
    if mode == "selected":
        stage, hint = "sweep", f"`heliocal sweep --workdir {workdir}`"
    else:
        stage, hint = "fit-hybrid", f"`heliocal fit-hybrid --workdir {workdir} --mode {mode}`"
    found = read_model(workdir, stage, mode, heliostat_id, hint=hint)
    if found is None:
        return None
    cfg, state = found
    return cfg, _state_to_layers(state)


def _model_committed(workdir: Path, mode: str, heliostat_id: str) -> bool:
    """Whether the stage that writes ``mode``'s models committed one for the heliostat (both its
    files listed in the stage's manifest; :func:`load_model` checks their content)."""
    cfg_rel, pt_rel = model_files(mode, heliostat_id)
    m = load_manifest(workdir, "sweep" if mode == "selected" else "fit-hybrid")
    return m is not None and cfg_rel in m.files and pt_rel in m.files


def aim_models(workdir: str | Path, heliostats: Sequence[str] | None = None, *,
               strict: bool = False) -> dict:
    """Per heliostat the model ``aim --model auto`` uses, and its mean validation and test error.

    The one decision both :func:`aim_steps` and ``heliocal info WORKDIR`` use: the sweep's
    selection (selection.parquet) where the sweep ran: its coarse model, or its selected hybrid
    ensemble (``hybrid/selected/``) if that was written; without a selection row for the
    heliostat, the ``fit-hybrid`` hybrid (``hybrid/hybrid/``) where fitted; otherwise (and when a
    selected hybrid's files are missing) the coarse model, ``fit-coarse``'s selected preset.
    Every artifact and model is read through its stage's manifest. With ``strict`` (``aim``),
    selection.parquet must also be fresh and a selected hybrid's model committed, else a
    one-line :class:`StageInputError` says what to rerun (``info`` shows what is there).

    Returns
    -------
    dict heliostat_id -> {``model`` (``coarse`` or ``hybrid``), ``variant`` (``hybrid`` or
    ``hybrid-octaves`` ...; None for coarse), ``source`` (the stage that chose it: ``sweep``,
    ``fit-hybrid`` or ``fit-coarse``), ``preset`` (the coarse preset, also under a hybrid),
    ``weight_decay`` (None for coarse), ``val_error_mrad``, ``test_error_mrad`` (NaN without
    such rows), ``model_dir`` (the folder under ``hybrid/`` with its weights; None for coarse)};
    empty without coarse_params.parquet.
    """
    from ..artifacts.schemas import SPLIT
    from ..artifacts.schemas import SELECTION

    workdir = Path(workdir)
    if not artifact_present(workdir, COARSE_PARAMS):
        return {}
    params = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats,
                           columns=["heliostat_id", "preset", "selected", "val_error_mrad",
                                    "test_error_mrad"])
    coarse = params[params["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")
    selection = None
    if artifact_present(workdir, SELECTION):
        selection = read_artifact(workdir, SELECTION, heliostats=heliostats)  # a committed sweep's
        if strict:
            check_fresh(workdir, SELECTION, {"measurements": MEASUREMENTS, "heliostats": HELIOSTATS,
                                             "split": SPLIT, "coarse_params": COARSE_PARAMS})
        selection = selection.drop_duplicates("heliostat_id").set_index("heliostat_id")
    fit_hybrid_errors = None
    out = {}
    for hid in sorted(coarse.index):
        c = coarse.loc[hid]
        entry = {"heliostat_id": hid, "model": "coarse", "variant": None, "source": "fit-coarse",
                 "preset": str(c["preset"]), "weight_decay": None,
                 "val_error_mrad": float(c["val_error_mrad"]),
                 "test_error_mrad": float(c["test_error_mrad"]), "model_dir": None}
        choice = (str(selection.loc[hid, "model"])
                  if selection is not None and hid in selection.index else None)
        if choice == "coarse":
            row = selection.loc[hid]
            entry.update(source="sweep", val_error_mrad=float(row["coarse_val_error_mrad"]),
                         test_error_mrad=float(row["coarse_test_error_mrad"]))
        elif choice is not None and choice.startswith("hybrid"):
            if _model_committed(workdir, "selected", hid):
                row = selection.loc[hid]
                entry.update(model="hybrid", variant=choice, source="sweep",
                             weight_decay=float(row["weight_decay"]),
                             val_error_mrad=float(row["val_error_mrad"]),
                             test_error_mrad=float(row["test_error_mrad"]), model_dir="selected")
            elif strict:
                raise StageInputError(f"{workdir}/selection.parquet selects {choice} for {hid}, "
                                      f"but the sweep committed no model for it; rerun `heliocal "
                                      f"sweep --workdir {workdir}`")
        elif _model_committed(workdir, "hybrid", hid):
            cfg_rel = model_files("hybrid", hid)[0]
            cfg = json.loads(read_committed(
                workdir, "fit-hybrid", cfg_rel,
                hint=f"`heliocal fit-hybrid --workdir {workdir} --mode hybrid`").data)
            if fit_hybrid_errors is None:
                fit_hybrid_errors = _fit_hybrid_errors(workdir)
            val, test = fit_hybrid_errors.get(hid, (float("nan"), float("nan")))
            entry.update(model="hybrid", variant="hybrid", source="fit-hybrid",
                         weight_decay=float(cfg.get("weight_decay", float("nan"))),
                         val_error_mrad=val, test_error_mrad=test, model_dir="hybrid")
        out[hid] = entry
    return out


def _fit_hybrid_errors(workdir: Path) -> dict:
    """Mean validation and test error_mrad of fit-hybrid's ``hybrid`` mode per heliostat."""
    if not artifact_present(workdir, HYBRID_PREDICTIONS):
        return {}
    p = read_artifact(workdir, HYBRID_PREDICTIONS,
                      columns=["heliostat_id", "split", "model", "error_mrad"])
    p = p[p["model"] == "hybrid"]
    means = p.groupby(["heliostat_id", "split"])["error_mrad"].mean()
    return {str(h): (float(means.get((h, "validation"), float("nan"))),
                     float(means.get((h, "test"), float("nan"))))
            for h in p["heliostat_id"].unique()}


def _fine_problem_from_config(cfg: dict, spec: HeliostatSpec, nominal: torch.Tensor) -> FineProblem:
    base = torch.tensor(cfg["base_params"], dtype=torch.float64)
    free = torch.tensor(cfg["free"], dtype=torch.bool)
    return FineProblem(spec, base, free, torch.tensor(cfg["scales"], dtype=torch.float64),
                       FeatureEncoder.from_dict(cfg["encoder"]), None, None)


@_single_threaded
def aim_steps(workdir: str | Path, heliostat_id: str, *, aim_point_enu, sun_vector_enu=None,
              time_utc=None, env: Mapping[str, float] | None = None, model: str = "auto",
              max_iterations: int = 50, tolerance_steps: float = 1e-6) -> dict:
    """Motor steps that reflect the sun onto ``aim_point_enu`` with the best fitted model.

    Parameters
    ----------
    aim_point_enu : (3,) aim point [m] ENU.
    sun_vector_enu : (3,) direction toward the sun; default from NREL SPA at ``time_utc``.
    time_utc : time of the aim (needed by models with time inputs, and for the sun by default).
    env : values of the model's env inputs (name without ``env_`` -> value).
    model : ``auto`` (the sweep's selection where ``sweep`` ran, else the fit-hybrid hybrid where
        fitted, else coarse), ``coarse``, ``hybrid``, ``nn-only`` or
        ``pretrained-nn``.

    Returns
    -------
    dict with ``axis_1_steps``, ``axis_2_steps``, ``model``, ``iterations``, ``aim_error_mrad``
    (angle between the forward model's reflected beam at those steps and the direction to the aim
    point), ``sun_azimuth_deg``, ``sun_elevation_deg``.
    """
    from ..physics.sun import spa_sun_position, sun_angles_from_vector, sun_vector_enu as _sunvec

    check_choice(model, "model", "aim", ("auto", "coarse") + MODES)
    workdir = Path(workdir)
    _check_inputs(workdir)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=[heliostat_id])
    if helio.empty:
        raise InputError(f"heliostat {heliostat_id!r} is not in {workdir}/heliostats.parquet")
    hrow = helio.iloc[0]
    selected = load_selected_parameters(workdir, [heliostat_id])
    if heliostat_id not in selected:
        raise StageInputError(f"heliostat {heliostat_id!r} has no coarse fit: run `heliocal "
                              f"fit-coarse --workdir {workdir}` first")
    spec = HeliostatSpec.from_row(hrow)
    if sun_vector_enu is None:
        if time_utc is None:
            raise ParameterError("aim needs the sun: give a time or a sun azimuth and elevation")
        lat, lon = hrow["latitude_deg"], hrow["longitude_deg"]
        if lat is None or not np.isfinite(lat):
            raise InputError(f"heliostat {heliostat_id!r} has no WGS84 location, so the sun cannot "
                             "be computed from the time: give --sun-azimuth and --sun-elevation")
        alt = hrow["altitude_m"] if hrow["altitude_m"] is not None and np.isfinite(hrow["altitude_m"]) else 0.0
        az, el = spa_sun_position([time_utc], float(lat), float(lon), float(alt))
        sun_vector_enu = _sunvec(az[0], el[0])
    sun = _unit(torch.as_tensor(np.asarray(sun_vector_enu, np.float64)).reshape(1, 3))
    if float(sun[0, 2]) <= 0:
        raise InputError("the sun is below the horizon at that time")
    aim = torch.as_tensor(np.asarray(aim_point_enu, np.float64)).reshape(1, 3)
    coarse = selected[heliostat_id]["params"]
    chosen = model
    fitted = None
    rerun = None
    if model == "auto":
        choice = aim_models(workdir, [heliostat_id], strict=True).get(heliostat_id, {})
        if choice.get("model") == "hybrid":
            fitted = load_model(workdir, choice["model_dir"], heliostat_id)
            if choice["source"] == "sweep":
                rerun = f"`heliocal sweep --workdir {workdir}`"
        chosen = "hybrid" if fitted is not None else "coarse"
    elif model != "coarse":
        fitted = load_model(workdir, model, heliostat_id)
        if fitted is None:
            raise StageInputError(f"no {model} model for {heliostat_id}: run `heliocal fit-hybrid "
                                  f"--workdir {workdir} --mode {model}` first")
    if fitted is not None:
        cfg = fitted[0]
        current = _current_inputs(workdir)
        if any(cfg.get("inputs", {}).get(k) != v for k, v in current.items()):
            rerun = rerun or f"`heliocal fit-hybrid --workdir {workdir} --mode {chosen}`"
            raise StageInputError(f"the {chosen} model of {heliostat_id} is stale (its inputs "
                                  f"changed): rerun {rerun} first")
    steps = inverse_kinematics(coarse, spec, sun, aim)
    iterations = 0
    if not bool(torch.isfinite(steps).all()):
        raise FitError(f"the aim point is not reachable by {heliostat_id} within its actuator "
                       "limits for this sun position")
    if chosen == "coarse":
        params = coarse
    elif chosen == "pretrained-nn":
        cfg, layers = fitted
        pm = PretrainedModel(layers, cfg["reference_m"], cfg["in_mean"], cfg["in_std"],
                             cfg["out_mean"], cfg["out_std"])
        with torch.no_grad():
            steps = pm.steps(sun, aim)
        params = coarse
    else:
        cfg, layers = fitted
        problem = _fine_problem_from_config(cfg, spec, nominal_parameters(hrow))
        enc = problem.encoder
        if enc.env:
            env = env or {}
            missing = [e for e in enc.env if e not in env]
            if missing:
                raise ParameterError(f"the {chosen} model of {heliostat_id} uses env inputs "
                                     f"{missing}: give them with --env NAME=VALUE")
        if time_utc is None:
            raise ParameterError(f"the {chosen} model of {heliostat_id} uses the date as input: "
                                 "give --time")
        context = enc.context([time_utc], np.array([[float((env or {})[e]) for e in enc.env]])
                              if enc.env else None)

        def params_at(s):
            with torch.no_grad():
                return _grouped(problem, layers, enc.encode(s, context), None).stacked()[0, 0]

        for iterations in range(1, max_iterations + 1):
            params = params_at(steps)
            new = inverse_kinematics(params, spec, sun, aim)
            if not bool(torch.isfinite(new).all()):
                raise FitError(f"the aim point is not reachable by {heliostat_id} within its "
                               "actuator limits for this sun position")
            delta = float((new - steps).abs().max())
            steps = new
            if delta < tolerance_steps:
                break
        params = params_at(steps)
    with torch.no_grad():
        normal, position = forward_kinematics(params, spec, steps)
        beam = reflect(-sun, normal)
        aim_err = float(error_mrad(beam, aim - position)[0])
    az, el = sun_angles_from_vector(sun.numpy())
    return {"heliostat_id": heliostat_id, "model": chosen,
            "time_utc": None if time_utc is None else str(pd.Timestamp(time_utc)),
            "sun_azimuth_deg": float(az[0]), "sun_elevation_deg": float(el[0]),
            "aim_point_enu_m": aim[0].tolist(), "axis_1_steps": float(steps[0, 0]),
            "axis_2_steps": float(steps[0, 1]), "iterations": iterations,
            "aim_error_mrad": aim_err}
