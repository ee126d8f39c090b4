"""Many aims through fine models, solved together (the batch aim's rows, :mod:`.aim_field`).

A fine model's steps are a fixed point (:mod:`.aim`: the parameters, or a GP's correction,
depend on the steps), so each aim needs its own iterations. They are independent: the hybrid
aims of all heliostats iterate together (:func:`.aim_network.solve_fixed_points`), and so do
their GP aims (:func:`heliocal.pipeline.models.gp_heliostat.gp_aims_steps`), each aim stopping
on its own, so that an aim's steps are those :func:`.aim.aim_steps` gives it alone (within the
fixed point's tolerance). A row's own failure
(its env inputs, an unreachable aim, a fixed point that does not converge) is its entry; one
of the heliostat (no fit, a stale model) is every row's of that heliostat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np
import torch

from ..artifacts.manifests import CommittedWorkdir
from ..errors import HeliocalError
from ..models.fade import epoch_seconds
from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import error_mrad, reflect
from ..physics.parameters import nominal_parameters
from ..physics.vectors import unit_vector as _unit
from .aim import (AimHeliostat, check_env, choose_model, gp_env_values, read_heliostat,
                  solve_aim, unreachable_error, utc_time)
from .aim_network import (HybridAims, check_network_inputs, not_converged_error,
                          solve_fixed_points)
from .fit_coarse import coarse_row_parameters

__all__ = ["AimRequest", "FineAim", "fine_aims"]

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


@dataclass
class AimRequest:
    """One heliostat's aims for :func:`fine_aims`: ``sun_enu`` (N, 3) unit vectors toward the
    sun, ``aim_point_enu`` (N, 3) [m] ENU, ``times_utc`` and ``envs`` per aim, through
    ``model`` (``auto``: aim's choice); what the caller has read already: ``choice``, the
    heliostat's :func:`.aim_choice.aim_models` entry (strict), and ``heliostat``
    (:func:`.aim.heliostat_of`, fit-coarse's freshness checked)."""

    heliostat_id: str
    model: str
    sun_enu: np.ndarray
    aim_point_enu: np.ndarray
    times_utc: list
    envs: list[Mapping[str, float]]
    choice: dict | None = None
    heliostat: AimHeliostat | None = None


def fine_aims(workdir, requests: list[AimRequest]) -> list[list[FineAim | HeliocalError]]:
    """Per request, the steps (2,) of its aims as :func:`.aim.aim_steps` gives them, as
    :class:`FineAim` or the row's error (module docstring); each heliostat and model read once,
    the hybrid aims of all requests solved together, and their GP aims."""
    wd = CommittedWorkdir.of(workdir)
    out: list = []
    jobs: list[_HybridJob] = []
    gps: list[_GPJob] = []
    for req in requests:
        try:
            h = (read_heliostat(wd, req.heliostat_id) if req.heliostat is None
                 else replace(req.heliostat))
            chosen, fitted = choose_model(wd, h, req.model, req.choice)
        except HeliocalError as exc:
            out.append([exc] * len(req.sun_enu))
            continue
        if chosen == "gp":
            gps.append(_GPJob.of(wd, h, fitted, req))
            out.append(gps[-1].out)
        elif chosen in ("coarse", "nominal", "pretrained-nn"):
            out.append(_aims_one_by_one(wd, h, chosen, fitted, req))
        else:                                           # a network's fixed point
            jobs.append(_HybridJob.of(wd, h, chosen, fitted, req))
            out.append(jobs[-1].out)
    _solve_hybrid_jobs(jobs)
    _solve_gp_jobs(gps)
    return out


def _aims_one_by_one(wd: CommittedWorkdir, h: AimHeliostat, chosen: str, fitted,
                     req: AimRequest) -> list[FineAim | HeliocalError]:
    """The aims of a model without a fixed point of its own to share (the pre-trained network),
    each :func:`.aim.solve_aim`."""
    out: list[FineAim | HeliocalError] = []
    for sun, point, time_utc, env in zip(req.sun_enu, req.aim_point_enu, req.times_utc,
                                         req.envs):
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


@dataclass
class _HybridJob:
    """One heliostat's hybrid aims in :func:`fine_aims`: ``out`` each row's result (None until
    solved), ``ok`` the rows whose inputs passed, their :class:`.aim_network.HybridAims` and
    coarse steps to start from (None without such rows)."""

    h: AimHeliostat
    chosen: str
    out: list
    ok: list = field(default_factory=list)
    hybrid: HybridAims | None = None
    start: torch.Tensor | None = None

    @classmethod
    def of(cls, wd: CommittedWorkdir, h: AimHeliostat, chosen: str, fitted,
           req: AimRequest) -> "_HybridJob":
        encoder_env = tuple(fitted[0]["encoder"].get("env", ()))

        def check(i):
            time_utc, env = utc_time(req.times_utc[i]), check_env(wd, req.envs[i])
            check_network_inputs(h.id, chosen, encoder_env, time_utc, env)
            return i, time_utc, env

        out, rows = _checked_rows(len(req.sun_enu), check)
        job = cls(h, chosen, out)
        if rows:
            job.ok, times, envs = (list(v) for v in zip(*rows))
            sun = _unit(torch.tensor(np.asarray(req.sun_enu, np.float64)[job.ok]))
            aim = torch.tensor(np.asarray(req.aim_point_enu, np.float64)[job.ok])
            job.start = inverse_kinematics(_coarse_at(h, times), h.spec, sun[:, None],
                                           aim[:, None])[:, 0]
            job.hybrid = HybridAims.of(fitted, h.spec, nominal_parameters(h.row), h.id, chosen,
                                       sun, aim, times, envs)
        return job

    def finish(self, steps: torch.Tensor, iterations: np.ndarray, delta: np.ndarray) -> None:
        """Each solved row's :class:`FineAim`, or why it has none (unreachable, not
        converged), into ``out``."""
        hybrid = self.hybrid
        with torch.no_grad():
            normal, position = forward_kinematics(hybrid.params_at(steps), self.h.spec,
                                                  steps[:, None])
            residual = error_mrad(reflect(-hybrid.sun, normal[:, 0]),
                                  hybrid.aim - position[:, 0]).numpy()
        for k, i in enumerate(self.ok):
            if not (bool(torch.isfinite(steps[k]).all()) and math.isfinite(residual[k])):
                self.out[i] = unreachable_error(self.h.id)
            elif iterations[k] == MAX_ITERATIONS and not delta[k] < TOLERANCE_STEPS:
                self.out[i] = not_converged_error(self.h.id, self.chosen, MAX_ITERATIONS,
                                                  float(delta[k]), TOLERANCE_STEPS)
            else:
                self.out[i] = FineAim(steps[k].numpy())


def _solve_hybrid_jobs(jobs: list[_HybridJob]) -> None:
    """The fixed points of every job's aims, together (:func:`.aim_network.solve_fixed_points`),
    into each job's ``out``."""
    todo = [job for job in jobs if job.hybrid is not None]
    solved = solve_fixed_points([job.hybrid for job in todo], [job.start for job in todo],
                                MAX_ITERATIONS, TOLERANCE_STEPS)
    for job, result in zip(todo, solved):
        job.finish(*result)


@dataclass
class _GPJob:
    """One heliostat's GP aims in :func:`fine_aims`: ``out`` each row's result (None until
    solved), ``ok`` the rows whose inputs passed and their
    :class:`heliocal.pipeline.models.gp_heliostat.GPAimJob` (None without such rows)."""

    h: AimHeliostat
    out: list
    ok: list = field(default_factory=list)
    job: object = None

    @classmethod
    def of(cls, wd: CommittedWorkdir, h: AimHeliostat, fitted, req: AimRequest) -> "_GPJob":
        """The aims' inputs checked as :func:`.aim.aim_steps` checks them."""
        from ..models.gp import GPCorrection
        from ..models.gp_heliostat import GPAimJob

        cfg, state = fitted

        def check(i):
            time_utc = utc_time(req.times_utc[i])
            return i, time_utc, gp_env_values(h, cfg, check_env(wd, req.envs[i]), time_utc)

        out, rows = _checked_rows(len(req.sun_enu), check)
        gp = cls(h, out)
        if rows:
            gp.ok, times, env_rows = (list(v) for v in zip(*rows))
            timed = [k for k, t in enumerate(times) if t is not None]
            time_s = np.full(len(times), np.nan)
            if timed:
                time_s[timed] = epoch_seconds([times[k] for k in timed])
            gp.job = GPAimJob(GPCorrection.from_model(cfg, state), _coarse_at(h, times), h.spec,
                              _unit(torch.tensor(np.asarray(req.sun_enu, np.float64)[gp.ok])),
                              torch.tensor(np.asarray(req.aim_point_enu, np.float64)[gp.ok]),
                              time_s, np.array(env_rows) if env_rows[0] else None)
        return gp

    def finish(self, fit) -> None:
        """Each solved row's :class:`FineAim` with the GP's part of its expected error, or
        unreachable, into ``out`` (``fit``: its GPAim)."""
        with torch.no_grad():
            residual = error_mrad(reflect(-self.job.sun, fit.normal),
                                  self.job.aim_point - fit.position)
        explained = fit.prediction.explained_variance_mrad2
        for k, i in enumerate(self.ok):
            reachable = bool(torch.isfinite(fit.steps[k]).all()) and math.isfinite(residual[k])
            self.out[i] = (FineAim(fit.steps[k].numpy(), float(explained[k]),
                                   fit.prediction.noise_mrad2)
                           if reachable else unreachable_error(self.h.id))


def _solve_gp_jobs(jobs: list[_GPJob]) -> None:
    """The GP aims' fixed points of every job, together
    (:func:`heliocal.pipeline.models.gp_heliostat.gp_aims_steps`), into each job's ``out``."""
    todo = [gp for gp in jobs if gp.job is not None]
    if not todo:
        return
    from ..models.gp_heliostat import gp_aims_steps

    for gp, fit in zip(todo, gp_aims_steps([gp.job for gp in todo], max_iterations=MAX_ITERATIONS,
                                           tolerance_steps=TOLERANCE_STEPS)):
        gp.finish(fit)
