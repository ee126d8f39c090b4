"""The Gaussian-process correction of one heliostat: fitted on top of its coarse model with the
fade length chosen on validation (``fit-hybrid --mode gp`` and the sweep's candidate), and the
steps that aim with it (``aim``). The model itself: :mod:`heliocal.pipeline.models.gp`.
"""

from __future__ import annotations

import json
import math
import time as _time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.lm import iterate_by_type
from ..physics.metrics import error_mrad, measured_normal, reflect
from ..physics.sun import sun_angles_from_vector
from .fade import FADE_LENGTHS_DEG
from .gp import (GPConfig, GPCorrection, GPPrediction, best_structure, correct_normals,
                 fit_gp_corrections, pointing_frame, pointing_residuals_mrad)
from .gp_map import MAP_KEY, MapGrid, map_figure_data, map_grid, map_section, structure_label
from .selection import choose_fade

__all__ = [
    "HeliostatGP",
    "GPAim",
    "coarse_normals",
    "fit_heliostat_gps",
    "fit_heliostat_gp",
    "gp_aim_steps",
    "gp_aims_steps",
    "GPAimJob",
    "correction_grid",
    "with_correction_map",
]


# ------------------------------------------------------------------------------------------------
# one heliostat: residuals of its coarse model, the fit, the fade chosen on validation
# ------------------------------------------------------------------------------------------------
@dataclass
class HeliostatGP:
    """The GP correction of one heliostat (one kernel structure) with every row's errors.

    Attributes
    ----------
    model : the fitted correction, its fade set to the chosen lengths.
    errors_by_length : (L, N) error_mrad of every row with each sun fade length of ``lengths``.
    lengths : the sun fade lengths tried [deg] (longest first); ``chosen`` the index kept.
    normal, position : (N, 3) the corrected normals at the chosen fade and the mirror centres.
    wall_time_s : seconds of its fit and predictions.
    """

    model: GPCorrection
    errors_by_length: np.ndarray
    lengths: tuple
    chosen: int
    normal: torch.Tensor
    position: torch.Tensor
    wall_time_s: float

    @property
    def errors(self) -> np.ndarray:
        return self.errors_by_length[self.chosen]

    @property
    def fade_length_deg(self) -> float:
        return float(self.lengths[self.chosen])


def coarse_normals(params_rows: torch.Tensor, spec, data) -> tuple[torch.Tensor, torch.Tensor,
                                                                      torch.Tensor]:
    """Predicted normals, mirror centres and measured normals (N, 3) of a heliostat's rows under
    per-row coarse parameters (N, 28) (a regime-aware model: each row its regime's)."""
    with torch.no_grad():
        params = params_rows if params_rows.dim() == 2 else params_rows.expand(len(data), -1)
        n, pos = forward_kinematics(params, spec, data.steps.unsqueeze(1))
        n, pos = n[:, 0], pos[:, 0]
        return n, pos, measured_normal(data.sun, pos, data.focal_spot)


def fit_heliostat_gps(rows: pd.DataFrame, labels: np.ndarray, spec, data,
                      params_rows: torch.Tensor, config: GPConfig, val_weights: np.ndarray, *,
                      lengths: Sequence[float] | None = None,
                      time_length_days: float = math.inf) -> dict[str, HeliostatGP]:
    """The GP corrections of one heliostat, one per structure of ``config``: fitted on its
    ``train`` rows, each structure's sun fade length chosen on its ``validation`` rows weighted
    by ``val_weights`` (in the rows' order; :func:`heliocal.pipeline.models.selection.choose_fade`).

    Parameters
    ----------
    rows, labels : the heliostat's rows (measurements.parquet) and their split labels (N,).
    spec, data : its :class:`HeliostatSpec` and :class:`MeasurementBatch` of ``rows``.
    params_rows : (N, 28) or (28,) the coarse model's parameters (the prior mean).
    config : :class:`GPConfig`.
    lengths : sun fade lengths [deg] to choose from (default
        :data:`heliocal.pipeline.models.fade.FADE_LENGTHS_DEG`).
    time_length_days : the time fade length of a structure with time [days].
    """
    t0 = _time.perf_counter()
    lengths = tuple(FADE_LENGTHS_DEG if lengths is None else lengths)
    labels = np.asarray(labels, dtype=object)
    train, val = labels == "train", labels == "validation"
    n, pos, meas = coarse_normals(params_rows, spec, data)
    models = fit_gp_corrections(rows[train], pointing_residuals_mrad(n, meas)[train], config)
    shared = (_time.perf_counter() - t0) / len(models)
    out = {}
    for structure, model in models.items():
        t1 = _time.perf_counter()
        days = time_length_days if model.uses_time else math.inf
        fades = [model.fade.with_lengths(length, days) for length in lengths]
        with torch.no_grad():
            mean = model.predict(model.inputs.encode_rows(rows)).mean_mrad
            normals = [correct_normals(n, f.weights_of_rows(rows)[:, None] * mean) for f in fades]
            errs = np.stack([error_mrad(c, meas).numpy() for c in normals])
        chosen = choose_fade([e[val] for e in errs], val_weights) if val.any() else 0
        out[structure] = HeliostatGP(model.with_fade(fades[chosen]), errs, lengths, chosen,
                                     normals[chosen], pos, shared + _time.perf_counter() - t1)
    return out


def fit_heliostat_gp(rows: pd.DataFrame, labels: np.ndarray, spec, data,
                     params_rows: torch.Tensor, config: GPConfig, val_weights: np.ndarray,
                     **kwargs) -> HeliostatGP:
    """:func:`fit_heliostat_gps`' structure of the highest log marginal likelihood."""
    fits = fit_heliostat_gps(rows, labels, spec, data, params_rows, config, val_weights, **kwargs)
    best = best_structure({k: f.model for k, f in fits.items()})
    return fits[best.structure]


# ------------------------------------------------------------------------------------------------
# aiming with the correction
# ------------------------------------------------------------------------------------------------
@dataclass
class GPAim:
    """Steps that aim with a GP-corrected coarse model (:func:`gp_aim_steps`), for K aims.

    Attributes
    ----------
    steps : (K, 2) motor steps (NaN where an aim is not reachable); iterations : (K,) the
    fixed-point iterations each aim used.
    normal, position : (K, 3) the corrected mirror normal and the mirror centre at ``steps``.
    prediction : the correction there (mean [mrad], variance [mrad^2], fade).
    """

    steps: torch.Tensor
    iterations: np.ndarray
    normal: torch.Tensor
    position: torch.Tensor
    prediction: GPPrediction


def gp_aim_steps(model: GPCorrection, params: torch.Tensor, spec, sun: torch.Tensor,
                 aim_point: torch.Tensor, time_s=None, env_values=None, *,
                 max_iterations: int = 50, tolerance_steps: float = 1e-6) -> GPAim:
    """Motor steps whose GP-corrected normal reflects the sun onto ``aim_point``, for K aims.

    The coarse model must point its normal at ``n_c`` with ``correct(n_c, g) = n*`` (``n*`` the
    bisector of the sun and the direction to the aim point): the coarse inverse kinematics aims
    at the point the normal ``n_c`` reflects the sun to, at the aim point's distance. The mirror
    centre moves with the steps, and a model with a periodic term's correction ``g`` with them
    too (the sun, the time and env fix the rest of it), so this is iterated, ``g`` taken at the
    latest steps, until the steps change by less than ``tolerance_steps``; each aim stops on its
    own (the K aims are a batch of independent fixed points: an aim's steps are those it would
    get alone), and one that becomes unreachable is NaN. Many heliostats' aims:
    :func:`gp_aims_steps`.

    Parameters
    ----------
    model : the heliostat's correction; params : (28,) its coarse parameters, or (K, 28) one
        vector per aim (a regime-aware model's).
    sun : (K, 3) unit vectors toward the sun; aim_point : (K, 3) [m] ENU.
    time_s : time of each aim [s since 1970 UTC], a number or (K,) (None or NaN: the median
        training time).
    env_values : (K, E) raw env values of the model's env inputs ((E,) for one aim).
    """
    job = GPAimJob(model, params, spec, sun, aim_point, time_s, env_values)
    return gp_aims_steps([job], max_iterations=max_iterations,
                         tolerance_steps=tolerance_steps)[0]


@dataclass
class GPAimJob:
    """One heliostat's K aims for :func:`gp_aims_steps` (the arguments of
    :func:`gp_aim_steps`)."""

    model: GPCorrection
    params: torch.Tensor
    spec: object
    sun: torch.Tensor
    aim_point: torch.Tensor
    time_s: object = None
    env_values: object = None


class _GPIterate:
    """A :class:`GPAimJob` being solved: its inputs per aim, steps (K, 2), correction ``g``
    (K, 2) [mrad] and its prediction, iterations (K,) and the aims still iterating."""

    def __init__(self, job: GPAimJob):
        self.model = job.model
        self.sun = job.sun.reshape(-1, 3)
        k = len(self.sun)
        self.spec = job.spec
        self.aim_point = job.aim_point.reshape(-1, 3).expand(k, 3)
        self.params = job.params.reshape(-1, job.params.shape[-1]).expand(k, job.params.shape[-1])
        self.az, self.el = sun_angles_from_vector(self.sun.numpy())
        self.t = np.broadcast_to(np.asarray(np.nan if job.time_s is None else job.time_s,
                                            np.float64), (k,))
        self.env = (None if job.env_values is None
                    else np.asarray(job.env_values, np.float64).reshape(k, -1))
        self.fade = _fade_weights(job.model.fade, self.az, self.el, self.t)
        self.steps = inverse_kinematics(self.params, job.spec, self.sun[:, None],
                                        self.aim_point[:, None])[:, 0]
        self.iterations = np.zeros(k, np.int64)
        self.todo = torch.isfinite(self.steps).all(-1)
        self.predict()

    def predict(self) -> None:
        """The correction at the current steps (all K aims)."""
        self.pred = self.model.predict(self.model.inputs.encode(
            self.az, self.el, self.t, self.env, self.steps.numpy()), self.fade)
        self.g = torch.as_tensor(self.pred.mean_mrad, dtype=torch.float64)

    def result(self) -> GPAim:
        if self.model.inputs.periodic_axis:
            self.predict()
        with torch.no_grad():
            normal, position = forward_kinematics(self.params, self.spec, self.steps[:, None])
        return GPAim(self.steps, self.iterations, correct_normals(normal[:, 0], self.g.numpy()),
                     position[:, 0], self.pred)


def gp_aims_steps(jobs: list[GPAimJob], *, max_iterations: int = 50,
                  tolerance_steps: float = 1e-6) -> list[GPAim]:
    """:func:`gp_aim_steps` of many heliostats' aims (one :class:`GPAimJob` each), their fixed
    points iterating together: each iteration's kinematics one batched call for the aims of one
    kinematic and actuator type (each aim a batch of one with its heliostat's spec), each aim
    stopping on its own, so its steps are those it gets alone."""
    state = [_GPIterate(job) for job in jobs]

    def step(it: int, active: list, spec) -> None:
        for j, _ in active:
            if state[j].model.inputs.periodic_axis and it > 1:
                state[j].predict()
        new = _gp_step(torch.cat([state[j].params[idx] for j, idx in active]), spec,
                       torch.cat([state[j].sun[idx] for j, idx in active]),
                       torch.cat([state[j].aim_point[idx] for j, idx in active]),
                       torch.cat([state[j].g[idx] for j, idx in active]),
                       torch.cat([state[j].steps[idx] for j, idx in active]))
        for (j, idx), rows in zip(active, torch.split(new, [len(i) for _, i in active])):
            s = state[j]
            delta = (rows - s.steps[idx]).abs().amax(-1)
            s.steps[idx] = rows
            s.iterations[idx.numpy()] = it
            s.todo[idx[~torch.isfinite(rows).all(-1) | (delta < tolerance_steps)]] = False

    iterate_by_type([s.spec for s in state], [s.todo for s in state], step, max_iterations)
    return [s.result() for s in state]


def _fade_weights(fade, az, el, t: np.ndarray) -> np.ndarray:
    """The fade at each aim: with its time where it has one, else by the sun alone."""
    w = fade.weights(az, el, None)
    timed = np.isfinite(t)
    if timed.any():
        w[timed] = fade.weights(az[timed], el[timed], t[timed])
    return w


def _gp_step(params, spec, sun, aim_point, g, steps) -> torch.Tensor:
    """One fixed-point update (K, 2) of :func:`gp_aim_steps` for K aims (each a batch of one)."""
    with torch.no_grad():
        _, position = forward_kinematics(params, spec, steps[:, None])
        position = position[:, 0]
        to_aim = aim_point - position
        wanted = sun + to_aim / torch.linalg.vector_norm(to_aim, dim=-1, keepdim=True)
        wanted = wanted / torch.linalg.vector_norm(wanted, dim=-1, keepdim=True)
        coarse_normal = wanted
        for _ in range(3):            # the frame of n_c, not of n*: second order, converges
            h, v = pointing_frame(coarse_normal)
            coarse_normal = wanted - 1e-3 * (g[:, :1] * h + g[:, 1:] * v)
            coarse_normal = coarse_normal / torch.linalg.vector_norm(coarse_normal, dim=-1,
                                                                     keepdim=True)
        beam = reflect(-sun, coarse_normal)
        target = position + torch.linalg.vector_norm(to_aim, dim=-1, keepdim=True) * beam
        return inverse_kinematics(params, spec, sun[:, None], target[:, None])[:, 0]


def correction_grid(model: GPCorrection, time_s: float | None = None, *, n_azimuth: int = 64,
                    n_elevation: int = 40, margin_deg: float = 15.0) -> dict:
    """The faded correction of ``model`` on a grid of sun positions around its training rows
    (``margin_deg`` beyond them, elevation within 0-90 deg) at the time ``time_s`` [s since 1970]
    (default: its latest training row's): what the report's correction map draws
    (:func:`heliocal.pipeline.report.figures.plot_gp_correction`;
    :func:`heliocal.pipeline.models.gp_map.map_figure_data`)."""
    grid = map_grid(model.fade, time_s, n_azimuth=n_azimuth, n_elevation=n_elevation,
                    margin_deg=margin_deg)
    return map_figure_data(grid, model.fade, _grid_mean_mrad(model, grid),
                           structure_label(model.to_dict()))


def with_correction_map(config: dict, state: dict) -> dict:
    """``config`` of a GP model with its correction map stored (:mod:`.gp_map`), computed from
    the model as its files give it back (the configuration through a JSON round trip, the
    tensors as they are), so the stored map is the one the report would compute from them."""
    model = GPCorrection.from_model(json.loads(json.dumps(config)), state)
    grid = map_grid(model.fade)
    return {**config, MAP_KEY: map_section(grid, _grid_mean_mrad(model, grid))}


def _grid_mean_mrad(model: GPCorrection, grid: MapGrid) -> np.ndarray:
    """(E * A, 2) the faded correction [mrad] at the grid's points (env inputs at 0)."""
    az, el, t = grid.points()
    env = np.zeros((az.size, len(model.inputs.env))) if model.inputs.env else None
    return model.predict(model.inputs.encode(az, el, t, env),
                         model.fade.weights(az, el, t)).mean_mrad
