"""The Gaussian-process correction of one heliostat: fitted on top of its coarse model with the
fade length chosen on validation (``fit-hybrid --mode gp`` and the sweep's candidate), and the
steps that aim with it (``aim``). The model itself: :mod:`heliocal.pipeline.models.gp`.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import error_mrad, measured_normal, reflect
from ..physics.sun import sun_angles_from_vector
from .fade import FADE_LENGTHS_DEG
from .gp import (GPConfig, GPCorrection, GPPrediction, correct_normals, fit_gp_correction,
                 pointing_frame, pointing_residuals_mrad)
from .selection import choose_fade

__all__ = [
    "HeliostatGP",
    "GPAim",
    "coarse_normals",
    "fit_heliostat_gp",
    "gp_aim_steps",
]


# ------------------------------------------------------------------------------------------------
# one heliostat: residuals of its coarse model, the fit, the fade chosen on validation
# ------------------------------------------------------------------------------------------------
@dataclass
class HeliostatGP:
    """The GP correction of one heliostat with every row's errors.

    Attributes
    ----------
    model : the fitted correction, its fade set to the chosen lengths.
    errors_by_length : (L, N) error_mrad of every row with each sun fade length of ``lengths``.
    lengths : the sun fade lengths tried [deg] (longest first); ``chosen`` the index kept.
    normal, position : (N, 3) the corrected normals at the chosen fade and the mirror centres.
    static_errors : (N,) error_mrad of the correction without its time component (the sun
        part of an additive ``sun+time`` model at the chosen fade; the model itself for one
        without time): the static alternative issue 33's forward-in-time check falls back to.
    wall_time_s : seconds of the fit and the predictions.
    """

    model: GPCorrection
    errors_by_length: np.ndarray
    lengths: tuple
    chosen: int
    normal: torch.Tensor
    position: torch.Tensor
    static_errors: np.ndarray
    wall_time_s: float

    @property
    def errors(self) -> np.ndarray:
        return self.errors_by_length[self.chosen]


def coarse_normals(params_rows: torch.Tensor, spec, data) -> tuple[torch.Tensor, torch.Tensor,
                                                                      torch.Tensor]:
    """Predicted normals, mirror centres and measured normals (N, 3) of a heliostat's rows under
    per-row coarse parameters (N, 28) (a regime-aware model: each row its regime's)."""
    with torch.no_grad():
        params = params_rows if params_rows.dim() == 2 else params_rows.expand(len(data), -1)
        n, pos = forward_kinematics(params, spec, data.steps.unsqueeze(1))
        n, pos = n[:, 0], pos[:, 0]
        return n, pos, measured_normal(data.sun, pos, data.focal_spot)


def _static_part(model: GPCorrection, x: np.ndarray) -> np.ndarray:
    """(N, 2) posterior mean of the sun part alone of an additive ``sun+time`` model [mrad] (the
    additive GP's mean splits into one term per kernel: ``K_sun(x, X) alpha``)."""
    gp = model._fitted()
    sun_term = gp.kernel_.k1.k1           # (C sun + C time) + noise -> C sun
    if model.inputs.env:
        sun_term = gp.kernel_.k1.k1.k1
    return sun_term(x, model.x_train) @ gp.alpha_ * model.y_scale_mrad


def fit_heliostat_gp(rows: pd.DataFrame, labels: np.ndarray, spec, data, params_rows: torch.Tensor,
                     config: GPConfig, val_weights: np.ndarray, *,
                     lengths: Sequence[float] | None = None,
                     time_length_days: float = math.inf) -> HeliostatGP:
    """The GP correction of one heliostat: fitted on its ``train`` rows, the sun fade length
    chosen on its ``validation`` rows (weighted by ``val_weights``, in the rows' order;
    :func:`heliocal.pipeline.models.selection.choose_fade`).

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
    residuals = pointing_residuals_mrad(n, meas)
    model = fit_gp_correction(rows[train], residuals[train], config)
    x = model.inputs.encode_rows(rows)
    days = time_length_days if model.uses_time else math.inf
    fades = [model.fade.with_lengths(L, days) for L in lengths]
    with torch.no_grad():
        raw = model.predict(x)
        errs = np.stack([error_mrad(correct_normals(n, f.weights_of_rows(rows)[:, None]
                                                    * raw.mean_mrad), meas).numpy()
                         for f in fades])
    chosen = choose_fade([e[val] for e in errs], val_weights) if val.any() else 0
    model = model.with_fade(fades[chosen])
    w = fades[chosen].weights_of_rows(rows)[:, None]
    with torch.no_grad():
        normal = correct_normals(n, w * raw.mean_mrad)
        static = errs[chosen]
        if model.uses_time and model.structure == "sun+time":
            sun_only = fades[chosen].with_lengths(lengths[chosen], math.inf).weights_of_rows(rows)
            static = error_mrad(correct_normals(n, sun_only[:, None] * _static_part(model, x)),
                                meas).numpy()
    return HeliostatGP(model, errs, lengths, chosen, normal, pos, static,
                       _time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------------
# aiming with the correction
# ------------------------------------------------------------------------------------------------
@dataclass
class GPAim:
    """Steps that aim with a GP-corrected coarse model (:func:`gp_aim_steps`).

    Attributes
    ----------
    steps : (1, 2) motor steps; iterations : fixed-point iterations used.
    normal, position : (1, 3) the corrected mirror normal and the mirror centre at ``steps``.
    prediction : the correction there (mean [mrad], variance [mrad^2], fade).
    """

    steps: torch.Tensor
    iterations: int
    normal: torch.Tensor
    position: torch.Tensor
    prediction: GPPrediction


def gp_aim_steps(model: GPCorrection, params: torch.Tensor, spec, sun: torch.Tensor,
                 aim_point: torch.Tensor, time_s: float | None, env_values=None, *,
                 max_iterations: int = 50, tolerance_steps: float = 1e-6) -> GPAim:
    """Motor steps whose GP-corrected normal reflects the sun onto ``aim_point``.

    The correction ``g`` depends on the sun, the time and env, not on the steps, so the coarse
    model must point its normal at ``n_c`` with ``correct(n_c, g) = n*`` (``n*`` the bisector of
    the sun and the direction to the aim point): the coarse inverse kinematics aims at the point
    the normal ``n_c`` reflects the sun to, at the aim point's distance. The mirror centre moves
    with the steps, so this is iterated until the steps change by less than ``tolerance_steps``.

    Parameters
    ----------
    model : the heliostat's correction; params : (28,) its coarse parameters.
    sun : (1, 3) unit vector toward the sun; aim_point : (1, 3) [m] ENU.
    time_s : time of the aim [s since 1970 UTC] (None: the median training time).
    env_values : (E,) raw env values of the model's env inputs.
    """
    sun = sun.reshape(1, 3)
    az, el = (float(a[0]) for a in sun_angles_from_vector(sun.numpy()))
    t = np.array([np.nan if time_s is None else float(time_s)])
    x = model.inputs.encode([az], [el], t, None if env_values is None
                            else np.asarray(env_values, np.float64).reshape(1, -1))
    pred = model.predict(x, model.fade.weights([az], [el], None if time_s is None else t))
    g = torch.as_tensor(pred.mean_mrad, dtype=torch.float64)
    steps = inverse_kinematics(params, spec, sun, aim_point)
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        with torch.no_grad():
            _, position = forward_kinematics(params, spec, steps)
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
            new = inverse_kinematics(params, spec, sun, target)
        if not bool(torch.isfinite(new).all()):
            return GPAim(new, iterations, torch.full((1, 3), float("nan")), position, pred)
        delta = float((new - steps).abs().max())
        steps = new
        if delta < tolerance_steps:
            break
    with torch.no_grad():
        normal, position = forward_kinematics(params, spec, steps)
    return GPAim(steps, iterations, correct_normals(normal, g.numpy()), position, pred)
