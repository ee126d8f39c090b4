"""The steps of aims through a hybrid network: fixed points of the network's parameters.

A hybrid's parameters are the coarse base plus the network's deviations at the steps (times its
fade, :mod:`heliocal.pipeline.models.fade`), so the steps that aim a beam at a point solve
``steps = IK(params(steps))``: iterated from the coarse steps until an aim's steps change by
less than the tolerance [steps]. Aims are independent fixed points: many of them, of one
heliostat or of many, iterate together (each iteration's inverse kinematics one batched call
per kinematic and actuator type, each aim a batch of one with its heliostat's spec) and each
stops on its own, so an aim's steps are those it gets alone. :func:`.aim.aim_steps` solves one
aim, the batch aim (:mod:`.aim_fine`) a day of the field, with the same
:func:`solve_fixed_points`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch

from ..errors import FitError, ParameterError
from ..models.fade import fade_weights
from ..models.network import FeatureEncoder, Layers
from ..models.training import FineProblem, grouped_components
from ..physics.kinematics import inverse_kinematics
from ..physics.lm import iterate_by_type
from ..physics.parameters import HeliostatSpec
from ..physics.sun import sun_angles_from_vector

__all__ = ["HybridAims", "check_network_inputs", "fine_problem_from_config",
           "not_converged_error", "solve_fixed_points"]

def fine_problem_from_config(cfg: dict, spec: HeliostatSpec, nominal: torch.Tensor
                             ) -> FineProblem:
    """The network's problem (its base parameters, free mask, output scales and input encoder)
    from its model file's config; no data (an aim's inputs come from the aim)."""
    base = torch.tensor(cfg["base_params"], dtype=torch.float64)
    free = torch.tensor(cfg["free"], dtype=torch.bool)
    return FineProblem(spec, base, free, torch.tensor(cfg["scales"], dtype=torch.float64),
                       FeatureEncoder.from_dict(cfg["encoder"]), None, None)


def check_network_inputs(heliostat_id: str, chosen: str, encoder_env, time_utc,
                         env: Mapping[str, float]) -> None:
    """A network's aim needs every env input of its encoder (``encoder_env``) in ``env`` and
    a time (its inputs include the date): else :class:`ParameterError`."""
    missing = [e for e in encoder_env if e not in env]
    if missing:
        raise ParameterError(f"the {chosen} model of {heliostat_id} uses env inputs {missing}: "
                             "give them with --env NAME=VALUE")
    if time_utc is None:
        raise ParameterError(f"the {chosen} model of {heliostat_id} uses the date as input: "
                             "give --time")


def not_converged_error(heliostat_id: str, chosen: str, max_iterations: int, delta: float,
                        tolerance_steps: float) -> FitError:
    """The error of an aim whose fixed point still moved by ``delta`` [steps] after
    ``max_iterations``."""
    return FitError(f"the {chosen} model of {heliostat_id} did not converge to the aim steps: "
                    f"after {max_iterations} fixed-point iterations the steps still changed by "
                    f"{delta:.3g} steps (tolerance {tolerance_steps:g}); aim with --model "
                    "coarse, or refit the heliostat")


@dataclass
class HybridAims:
    """K aims of one heliostat through its network ``problem`` and ``layers``: their suns
    (K, 3) and aim points (K, 3) [m ENU], the network's context (K, C) at each aim's time and
    env, and its fade (K,) at each aim's sun and time."""

    problem: FineProblem
    layers: Layers
    spec: HeliostatSpec
    sun: torch.Tensor
    aim: torch.Tensor
    context: torch.Tensor
    fade: np.ndarray

    @classmethod
    def of(cls, fitted: tuple, spec: HeliostatSpec, nominal: torch.Tensor, heliostat_id: str,
           chosen: str, sun: torch.Tensor, aim: torch.Tensor, times_utc, envs) -> "HybridAims":
        """The aims of a heliostat (``spec``, its ``nominal`` parameters (28,)) through its
        network ``fitted`` (config, layers) at ``sun`` (K, 3), ``aim`` (K, 3), UTC
        ``times_utc`` (K,) and ``envs`` (K dicts; :func:`check_network_inputs`)."""
        cfg, layers = fitted
        problem = fine_problem_from_config(cfg, spec, nominal)
        enc = problem.encoder
        for time_utc, env in zip(times_utc, envs):
            check_network_inputs(heliostat_id, chosen, enc.env, time_utc, env)
        env_values = (np.array([[float(env[e]) for e in enc.env] for env in envs])
                      if enc.env else None)
        az, el = sun_angles_from_vector(sun.numpy())
        return cls(problem, layers, spec, sun, aim, enc.context(list(times_utc), env_values),
                   np.asarray(fade_weights(cfg, az, el, list(times_utc)), np.float64))

    def params_at(self, steps: torch.Tensor, idx=slice(None)) -> torch.Tensor:
        """(n, 28) the parameters of the aims ``idx`` at their ``steps`` (n, 2)."""
        with torch.no_grad():
            features = self.problem.encoder.encode(steps, self.context[idx])
            return grouped_components(self.problem, self.layers, features, None,
                                      self.fade[idx]).stacked()[0]


@dataclass
class _Iterate:
    """One heliostat's aims in :func:`solve_fixed_points`: steps (K, 2), iterations (K,), last
    change (K,) [steps] and the aims still iterating (K,)."""

    steps: torch.Tensor
    iterations: np.ndarray
    delta: np.ndarray
    todo: torch.Tensor

    @classmethod
    def start(cls, steps: torch.Tensor) -> "_Iterate":
        k = len(steps)
        return cls(steps.clone(), np.zeros(k, np.int64), np.full(k, np.inf),
                   torch.isfinite(steps).all(-1))

    def update(self, idx: torch.Tensor, new: torch.Tensor, iteration: int,
               tolerance_steps: float) -> None:
        change = (new - self.steps[idx]).abs().amax(-1)
        self.steps[idx] = new
        self.iterations[idx.numpy()] = iteration
        self.delta[idx.numpy()] = change.numpy()
        self.todo[idx[~torch.isfinite(new).all(-1) | (change < tolerance_steps)]] = False


def solve_fixed_points(hybrids: list[HybridAims], starts: list[torch.Tensor],
                       max_iterations: int, tolerance_steps: float) -> list[tuple]:
    """Per hybrid, (steps (K, 2), iterations (K,), last change (K,) [steps]) of its aims' fixed
    points from ``starts`` (K, 2) (the coarse steps), all aims of one kinematic and actuator
    type iterating together (:func:`heliocal.pipeline.physics.lm.iterate_by_type`), each
    stopping on its own (module docstring); an aim whose steps become non-finite stops there
    (NaN), one still moving after ``max_iterations`` has its last change in ``delta``."""
    state = [_Iterate.start(s) for s in starts]

    def step(iteration: int, active: list, spec: HeliostatSpec) -> None:
        params = torch.cat([hybrids[j].params_at(state[j].steps[idx], idx.numpy())
                            for j, idx in active])
        sun = torch.cat([hybrids[j].sun[idx] for j, idx in active])[:, None]
        aim = torch.cat([hybrids[j].aim[idx] for j, idx in active])[:, None]
        new = inverse_kinematics(params, spec, sun, aim)[:, 0]
        for (j, idx), rows in zip(active, torch.split(new, [len(i) for _, i in active])):
            state[j].update(idx, rows, iteration, tolerance_steps)

    iterate_by_type([h.spec for h in hybrids], [s.todo for s in state], step, max_iterations)
    return [(s.steps, s.iterations, s.delta) for s in state]
