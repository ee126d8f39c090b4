"""Training the fine model: the stacked problem of many heliostats and ensemble members, batched
Adam training with early stopping on validation, and the predictions of the trained members.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import pandas as pd
import torch

from ..errors import ParameterError
from ..physics.kinematics import ParameterComponents, forward_kinematics
from ..physics.lm import SPEC_TENSORS, stack_specs
from ..physics.metrics import error_mrad, measured_normal
from ..physics.parameters import HeliostatSpec, nominal_parameters
from ..runtime.process_state import single_threaded
from .adam import LeafAdam
from .coarse import MeasurementBatch, metrics_frame
from .network import (FeatureEncoder, Layers, flatten_layers, init_mlp, layer_views, mlp_columns,
                      output_scales)
from .config import FineConfig

__all__ = [
    "FineProblem",
    "MemberResult",
    "build_problem",
    "train_members",
    "predict_members",
    "member_errors_mrad",
    "predict_ensembles",
    "ensemble_errors_mrad",
    "faded_errors_mrad",
    "predictions_frame",
    "take_rows",
    "grouped_components",
    "stack_problems",
    "problem_as",
    "MEMBER_ALIGN",
]

#: Rows of a stacked problem and parameters of a network, a multiple of this in
#: :func:`stack_problems` and :func:`train_members` with ``align``. torch's elementwise kernels
#: compute a contiguous tensor in vector blocks (AVX-512: 32 float32 elements per step) and its
#: last ``size % step`` elements one by one, with other rounding (``exp`` in the SELU among them);
#: its reductions over the rows and MKL's matrix products group a row's terms by the row count.
#: With every per-network block of rows and parameters a multiple of 32, the scalar tail is empty
#: and a row count that is a multiple of 32 gives a network the same bits whatever the count, so
#: a network trains to the same bits alone or beside any others, at any position
#: (docs/experiments/incremental-updates.md; tests/test_sweep_independence.py).
MEMBER_ALIGN = 32


def _aligned(n: int, align: int) -> int:
    """``n`` rounded up to a multiple of ``align``."""
    return -(-int(n) // int(align)) * int(align)


# ------------------------------------------------------------------------------------------------
# one heliostat's fine problem
# ------------------------------------------------------------------------------------------------
@dataclass
class FineProblem:
    """Everything the fine model of one heliostat needs besides its weights.

    Attributes
    ----------
    spec : the heliostat's fixed description.
    base : (28,) parameters the deviations are added to (coarse fit or nominal), or (N, 28):
        each row its own (a regime-aware coarse model: each row at its regime's parameters).
    free : bool (28,) parameters that get a deviation (the network's outputs, in order).
    scales : (P,) deviation per unit output (:func:`output_scales`).
    encoder : the input encoding.
    data : the measurements (N rows).
    context : (N, 4 + E) time, season and env features of the rows.
    cached_features : the encoded inputs of ``data`` (set by :func:`stack_problems`, whose
        heliostats each have their own encoder).

    :func:`stack_problems` makes one problem of M heliostats: every tensor above then has a
    leading member axis (spec batch (M, 1), base (M, 1, 28) or per row (M, N, 28), scales
    (M, P), data (M, N, ...)).
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
    def per_row_base(self) -> bool:
        """True when ``base`` has a row axis ((N, 28) or (M, N, 28))."""
        return self.base.dim() >= 2 and self.base.shape[-2] > 1

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


def take_rows(problem: FineProblem, rows: torch.Tensor) -> FineProblem:
    """The problem (single or stacked) on the rows where ``rows`` (N,) is true, features kept."""
    take = lambda t: t[..., rows, :]
    features = problem.features()
    d = problem.data
    data = MeasurementBatch(d.measurement_id[..., rows.numpy()], take(d.steps), take(d.sun),
                            take(d.focal_spot), take(d.target_center), take(d.target_normal))
    base = take(problem.base) if problem.per_row_base else problem.base
    return dataclasses.replace(problem, base=base, data=data, context=take(problem.context),
                               cached_features=take(features))


def _take_members(problem: FineProblem, keep: torch.Tensor) -> FineProblem:
    """The members where ``keep`` (M,) is true: a problem's per-member tensors (stacked data,
    spec, inputs and scales, per-member base) are sliced; shared ones are kept as they are."""
    if problem.base.dim() == 3:
        problem = dataclasses.replace(problem, base=problem.base[keep])
    if problem.data.steps.dim() != 3:            # one heliostat: only the base is per member
        return problem
    spec = copy.copy(problem.spec)
    for name in SPEC_TENSORS:
        object.__setattr__(spec, name, getattr(spec, name)[keep])
    d = problem.data
    data = MeasurementBatch(d.measurement_id[keep.numpy()], d.steps[keep], d.sun[keep],
                            d.focal_spot[keep], d.target_center[keep], d.target_normal[keep])
    return dataclasses.replace(problem, spec=spec, data=data, context=problem.context[keep],
                               scales=problem.scales[keep],
                               cached_features=problem.features()[keep])


def problem_as(problem: FineProblem, dtype: torch.dtype) -> FineProblem:
    """The problem with every floating-point tensor (spec, base, scales, measurements, context,
    encoded inputs) in ``dtype``; the training's precision (``FineConfig.training_dtype``)."""
    if problem.base.dtype == dtype:
        return problem
    cast = lambda t: t if t is None or not t.is_floating_point() else t.to(dtype)
    spec = copy.copy(problem.spec)
    for name in SPEC_TENSORS:
        object.__setattr__(spec, name, cast(getattr(spec, name)))
    d = problem.data
    data = MeasurementBatch(d.measurement_id, cast(d.steps), cast(d.sun), cast(d.focal_spot),
                            cast(d.target_center), cast(d.target_normal))
    return dataclasses.replace(problem, spec=spec, data=data, base=cast(problem.base),
                               scales=cast(problem.scales), context=cast(problem.context),
                               cached_features=cast(problem.features()))


def _pad_rows(t: torch.Tensor, n: int) -> torch.Tensor:
    """Pad (N, ...) to (n, ...) by repeating the last row (finite values for masked rows)."""
    if t.shape[0] == n:
        return t
    return torch.cat([t, t[-1:].expand(n - t.shape[0], *t.shape[1:])])


def stack_problems(problems: Sequence[FineProblem],
                   align: int = 1) -> tuple[FineProblem, torch.Tensor]:
    """One problem of M heliostats (member m = heliostat m) for :func:`train_members`.

    The heliostats must share kinematic type, actuator type, free parameters and input size.
    Shorter heliostats are padded to the longest (their last row repeated), and every heliostat
    to a multiple of ``align`` rows (:data:`MEMBER_ALIGN`: the stacked problem's layout then does
    not depend on the other heliostats); the returned ``valid`` (M, N) mask is false on padding,
    and the training and validation masks must be and-ed with it. Each heliostat keeps its own
    encoder, spec, base and scales.
    """
    free = problems[0].free
    if any(not torch.equal(p.free, free) for p in problems):
        raise ParameterError("The 'problems' parameter of stack_problems must share the free "
                             "parameters (one coarse preset).")
    n = _aligned(max(len(p.data) for p in problems), align)
    spec = stack_specs([p.spec for p in problems])
    for name in SPEC_TENSORS:
        object.__setattr__(spec, name, getattr(spec, name).unsqueeze(1))   # batch (M, 1)
    pad = lambda get: torch.stack([_pad_rows(get(p), n) for p in problems])
    data = MeasurementBatch(
        measurement_id=np.array([np.resize(p.data.measurement_id, n) for p in problems]),
        steps=pad(lambda p: p.data.steps), sun=pad(lambda p: p.data.sun),
        focal_spot=pad(lambda p: p.data.focal_spot),
        target_center=pad(lambda p: p.data.target_center),
        target_normal=pad(lambda p: p.data.target_normal))
    valid = torch.stack([torch.arange(n) < len(p.data) for p in problems])
    if any(p.per_row_base for p in problems):   # (M, N, 28): every row its own base
        base = pad(lambda p: p.base if p.per_row_base else p.base.expand(len(p.data), -1))
    else:
        base = torch.stack([p.base for p in problems]).unsqueeze(1)
    stacked = FineProblem(spec, base, free,
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
    return _components(problem, mlp_columns(layers, features) * problem.scales.unsqueeze(-1))


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


def grouped_components(problem: FineProblem, layers: Layers, features: torch.Tensor,
             ensemble: int | None, fade=None) -> ParameterComponents:
    """Components of G = M / K models whose K networks are consecutive members (K =
    ``ensemble``; None: all M networks are one model). ``fade`` (N,) scales every row's
    deviation (:mod:`heliocal.pipeline.models.fade`; None: 1)."""
    out = mlp_columns(layers, features) * problem.scales.unsqueeze(-1)   # (M, P, N)
    m = out.shape[0]
    k = m if ensemble is None else int(ensemble)
    if k < 1 or m % k:
        raise ParameterError(f"The 'ensemble' parameter must divide the {m} networks. Got {k} "
                             "instead.")
    out = out.reshape(m // k, k, *out.shape[1:]).mean(1)                  # (G, P, N)
    if fade is not None:
        out = out * torch.as_tensor(np.asarray(fade, np.float64), dtype=out.dtype)
    base = problem.base
    if base.dim() == 3 and base.shape[0] == m:                            # per-member bases
        base = base[::k]
    return _components(dataclasses.replace(problem, base=base), out)


def predict_ensembles(problem: FineProblem, layers: Layers, ensemble: int | None = None,
                      steps: torch.Tensor | None = None, context: torch.Tensor | None = None,
                      fade=None):
    """Mirror normals and centres (G, N, 3) of models made of ``ensemble`` consecutive
    networks each (G = M / ensemble; default: all of ``layers`` is one model), whose deviation
    is the mean of their networks' deviations, times ``fade`` (N,) (None: 1). Steps and context
    as :func:`predict_members`."""
    steps = problem.data.steps if steps is None else steps
    return _kinematics(problem, grouped_components(problem, layers, problem.features(steps, context),
                                         ensemble, fade), steps)


def ensemble_errors_mrad(problem: FineProblem, layers: Layers, ensemble: int | None = None,
                         fade=None):
    """error_mrad (G, N) of the models of :func:`predict_ensembles` on the problem's rows."""
    return _errors(problem, *predict_ensembles(problem, layers, ensemble, fade=fade))


def faded_errors_mrad(problem: FineProblem, layers: Layers, ensemble: int | None,
                      fade_weights: Sequence) -> np.ndarray:
    """error_mrad (L, G, N) of the models of :func:`predict_ensembles` under each of L fades
    (each (N,) weights of the problem's rows, :meth:`heliocal.pipeline.models.fade.Fade.weights`);
    an all-ones fade is the model itself. The sweep and ``fit-hybrid`` choose a fade length on
    validation from these (:func:`heliocal.pipeline.models.selection.choose_fade`)."""
    with torch.no_grad():
        return np.stack([ensemble_errors_mrad(problem, layers, ensemble,
                                              None if np.all(w == 1.0) else w).numpy()
                         for w in fade_weights])


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


def _used_rows(train_mask: torch.Tensor, val_mask: torch.Tensor, align: int) -> torch.Tensor:
    """(N,) the rows a training keeps: those some member trains or stops on; with ``align`` > 1
    every row up to the last such row's, rounded up to a multiple of ``align`` (the aligned
    layout of :func:`stack_problems`; its padding rows are at the end)."""
    used = (train_mask | val_mask).any(0)
    if align <= 1 or not bool(used.any()):
        return used
    end = _aligned(int(torch.nonzero(used).max()) + 1, align)
    return torch.arange(len(used)) < end


@single_threaded
def train_members(problem: FineProblem, train_mask, val_mask, weight_decays, seeds,
                  config: FineConfig = FineConfig(), *, initial: Layers | None = None,
                  progress: Callable[[int, int], None] | None = None,
                  align: int = 1) -> MemberResult:
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
    align : keep the rows a multiple of ``align`` (a problem of :func:`stack_problems` with the
        same ``align``) and pad each network's parameters to one (zeros no layer reads): with
        :data:`MEMBER_ALIGN` a member's result does not depend on the other members.

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
    used = _used_rows(tm, vm, align)
    if not bool(used.all()):  # rows no member trains or stops on (test rows) cost per epoch
        problem, tm, vm = take_rows(problem, used), tm[:, used], vm[:, used]
    dtype = getattr(torch, config.training_dtype)
    problem, wd = problem_as(problem, dtype), wd.to(dtype)
    layers = initial if initial is not None else init_mlp(problem.sizes(config), seeds)
    layers = [(w.to(dtype), b.to(dtype)) for w, b in layers]
    theta = flatten_layers(layers).detach()                                 # (L, T), L live
    theta = torch.cat([theta, theta.new_zeros(len(theta), _aligned(theta.shape[1], align)
                                              - theta.shape[1])], 1).requires_grad_(True)
    cur = layer_views(theta, layers)
    opt = LeafAdam(theta, lr=config.learning_rate)
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
            theta, opt = opt.keep_rows(keep)
            cur = layer_views(theta, layers)
        err = _errors_from_features(run_problem, cur, features)          # (L, N)
        sq = torch.where(run_tm, torch.nan_to_num(err, nan=0.0) ** 2, torch.zeros_like(err))
        train_mse = sq.sum(-1) / run_n
        with torch.no_grad():
            val = torch.full((m,), float("nan"), dtype=torch.float64)
            val[live] = _masked_mean(torch.nan_to_num(err.detach(), nan=1e6), run_vm).to(val.dtype)
            mse = torch.full((m,), float("nan"), dtype=torch.float64)
            mse[live] = train_mse.detach().to(mse.dtype)
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
        opt.zero_grad()
        loss.backward()
        with torch.no_grad():
            theta.grad.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
        opt.step()
        if progress:
            progress(epoch + 1, config.max_epochs)
    # the kept weights in float64, the precision every prediction and reported error uses
    best = [(w.to(torch.float64, copy=True), b.to(torch.float64, copy=True))
            for w, b in layer_views(best, layers)]
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
