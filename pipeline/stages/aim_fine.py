"""Many aims of one heliostat through its fine model, solved together (the batch aim's rows,
:mod:`.aim_field`).

A fine model's steps are a fixed point (:mod:`.aim`: the parameters, or a GP's correction,
depend on the steps), so each aim needs its own iterations. They are independent: the aims of a
heliostat iterate as one batch, each stopping on its own, so that an aim's steps are those
:func:`.aim.aim_steps` gives it alone (within the fixed point's tolerance). A row's own failure
(its env inputs, an unreachable aim, a fixed point that does not converge) is its entry; one
of the heliostat (no fit, a stale model) is every row's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np
import torch

from ..artifacts.manifests import CommittedWorkdir
from ..errors import HeliocalError
from ..models.fade import epoch_seconds
from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import error_mrad, reflect
from ..physics.vectors import unit_vector as _unit
from .aim import (AimHeliostat, HybridAims, check_env, check_network_inputs, choose_model,
                  gp_env_values, gp_model_aim_steps, not_converged_error, read_heliostat,
                  solve_aim, unreachable_error, utc_time)
from .fit_coarse import coarse_row_parameters

__all__ = ["FineAim", "heliostat_aims"]

#: The fixed points' iteration limit and tolerance [steps], as :func:`.aim.aim_steps`'s defaults.
MAX_ITERATIONS = 50
TOLERANCE_STEPS = 1e-6


@dataclass(frozen=True)
class FineAim:
    """One aim through a fine model: its steps (2,) and, through a GP, its predictive variance's
    part of the expected error (:func:`.aim_budget.fine_level_mrad`'s ``explained_mrad2`` and
    ``noise_mrad2`` [mrad^2]; 0 for other models)."""

    steps: np.ndarray
    explained_mrad2: float = 0.0
    noise_mrad2: float = 0.0


def heliostat_aims(workdir, heliostat_id: str, model: str, sun_enu: np.ndarray,
                   aim_point_enu: np.ndarray, times_utc, envs: list[Mapping[str, float]],
                   choice: dict | None = None, heliostat: AimHeliostat | None = None
                   ) -> list[FineAim | HeliocalError]:
    """The steps (2,) of many aims of one heliostat, as :func:`.aim.aim_steps` gives them, with
    its heliostat and model read once, as :class:`FineAim` (module docstring). ``sun_enu``
    (N, 3) unit vectors toward the sun, ``aim_point_enu`` (N, 3) [m] ENU, ``times_utc`` and
    ``envs`` per aim. What the caller has read already: ``choice``, the heliostat's entry of
    :func:`.aim_choice.aim_models` (``model`` ``auto``), and ``heliostat``
    (:func:`.aim.heliostat_of`, with fit-coarse's freshness checked)."""
    wd = CommittedWorkdir.of(workdir)
    try:
        h = read_heliostat(wd, heliostat_id) if heliostat is None else replace(heliostat)
        chosen, fitted = choose_model(wd, h, model, choice)
    except HeliocalError as exc:
        return [exc] * len(sun_enu)
    if chosen == "gp":
        return _gp_aims(wd, h, fitted, sun_enu, aim_point_enu, times_utc, envs)
    if chosen not in ("coarse", "nominal", "pretrained-nn"):     # a network's fixed point
        return _hybrid_aims(wd, h, chosen, fitted, sun_enu, aim_point_enu, times_utc, envs)
    out: list[FineAim | HeliocalError] = []
    for sun, point, time_utc, env in zip(sun_enu, aim_point_enu, times_utc, envs):
        try:
            steps, _, _ = solve_aim(replace(h), chosen, fitted,
                                    _unit(torch.tensor(sun, dtype=torch.float64).reshape(1, 3)),
                                    torch.tensor(point, dtype=torch.float64).reshape(1, 3),
                                    utc_time(time_utc), check_env(wd, env))
            out.append(FineAim(steps[0].numpy()))
        except HeliocalError as exc:
            out.append(exc)
    return out


def _coarse_at(h: AimHeliostat, times: list) -> torch.Tensor:
    """(K, 28) the coarse parameters of each aim: the selected fit's, or a regime-aware model's
    at each aim's time (as :func:`.aim.solve_aim` takes them; an aim without a time: the latest
    regime's)."""
    params = h.coarse.expand(len(times), h.coarse.shape[-1]).clone()
    timed = [k for k, t in enumerate(times) if t is not None]
    if timed and h.selected.get("regime_table") is not None:
        params[timed] = coarse_row_parameters(h.selected, [times[k] for k in timed])
    return params


def _checked_rows(n: int, check) -> tuple[list, list]:
    """(out, ok): ``out`` (n,) each row's :class:`HeliocalError` from ``check(i)`` or None, and
    the values ``check`` returned for the rows that passed, in order."""
    out, ok = [None] * n, []
    for i in range(n):
        try:
            ok.append(check(i))
        except HeliocalError as exc:
            out[i] = exc
    return out, ok


def _hybrid_aims(wd: CommittedWorkdir, h: AimHeliostat, chosen: str, fitted, sun_enu,
                 aim_point_enu, times_utc, envs) -> list[FineAim | HeliocalError]:
    """:func:`heliostat_aims` of a hybrid network: its fixed points solved together
    (:meth:`.aim.HybridAims.fixed_points`), after each aim's inputs are checked as
    :func:`.aim.aim_steps` checks them."""
    encoder_env = tuple(fitted[0]["encoder"].get("env", ()))

    def check(i):
        time_utc, env = utc_time(times_utc[i]), check_env(wd, envs[i])
        check_network_inputs(h, chosen, encoder_env, time_utc, env)
        return i, time_utc, env

    out, rows = _checked_rows(len(sun_enu), check)
    if not rows:
        return out
    ok, times, env_rows = (list(v) for v in zip(*rows))
    sun = _unit(torch.tensor(np.asarray(sun_enu, np.float64)[ok]))
    aim = torch.tensor(np.asarray(aim_point_enu, np.float64)[ok])
    coarse = _coarse_at(h, times)
    start = inverse_kinematics(coarse, h.spec, sun[:, None], aim[:, None])[:, 0]
    hybrid = HybridAims.of(h, chosen, fitted, sun, aim, times, env_rows)
    steps, iterations, delta = hybrid.fixed_points(start, MAX_ITERATIONS, TOLERANCE_STEPS)
    with torch.no_grad():
        normal, position = forward_kinematics(hybrid.params_at(steps), h.spec, steps[:, None])
        residual = error_mrad(reflect(-sun, normal[:, 0]), aim - position[:, 0]).numpy()
    for k, i in enumerate(ok):
        if not (bool(torch.isfinite(steps[k]).all()) and math.isfinite(residual[k])):
            out[i] = unreachable_error(h.id)
        elif iterations[k] == MAX_ITERATIONS and not delta[k] < TOLERANCE_STEPS:
            out[i] = not_converged_error(h.id, chosen, MAX_ITERATIONS, float(delta[k]),
                                    TOLERANCE_STEPS)
        else:
            out[i] = FineAim(steps[k].numpy())
    return out


def _gp_aims(wd: CommittedWorkdir, h: AimHeliostat, fitted, sun_enu, aim_point_enu, times_utc,
             envs) -> list[FineAim | HeliocalError]:
    """:func:`heliostat_aims` of a GP correction: its fixed points solved together
    (:func:`heliocal.pipeline.models.gp_heliostat.gp_aim_steps`, each aim on its own), after each
    aim's inputs are checked as :func:`.aim._gp_solve` checks them."""
    cfg, state = fitted

    def check(i):
        time_utc = utc_time(times_utc[i])
        return i, time_utc, gp_env_values(h, cfg, check_env(wd, envs[i]), time_utc)

    out, rows = _checked_rows(len(sun_enu), check)
    if not rows:
        return out
    ok, times, env_rows = (list(v) for v in zip(*rows))
    timed = [k for k, t in enumerate(times) if t is not None]
    time_s = np.full(len(times), np.nan)
    if timed:
        time_s[timed] = epoch_seconds([times[k] for k in timed])
    sun = _unit(torch.tensor(np.asarray(sun_enu, np.float64)[ok]))
    aim = torch.tensor(np.asarray(aim_point_enu, np.float64)[ok])
    fit = gp_model_aim_steps(cfg, state, _coarse_at(h, times), h.spec, sun, aim, time_s,
                        np.array(env_rows) if env_rows[0] else None)
    with torch.no_grad():
        residual = error_mrad(reflect(-sun, fit.normal), aim - fit.position)
    explained = fit.prediction.explained_variance_mrad2
    for k, i in enumerate(ok):
        reachable = bool(torch.isfinite(fit.steps[k]).all()) and math.isfinite(residual[k])
        out[i] = (FineAim(fit.steps[k].numpy(), float(explained[k]), fit.prediction.noise_mrad2)
                  if reachable else unreachable_error(h.id))
    return out
