"""How well a coarse fit knows its parameters, and what that does to an aim.

A coarse fit minimises the data residuals ``r = 1000 (n_pred - n_meas)`` [mrad] (three
components per row) plus its prior rows ``(x - mean) / sigma``
(:mod:`heliocal.pipeline.models.coarse`). Linearised at the solution, with ``J`` the data
Jacobian of the free parameters [mrad per parameter unit] and ``s`` the data residuals' scale
[mrad per component], the free parameters' posterior covariance is

    C = (J^T J / s^2 + diag(1 / sigma^2))^-1        [parameter units squared]

(the Gauss-Newton form of a Gaussian likelihood with a Gaussian prior). An aim at steps ``a`` for
sun ``e`` and aim point ``p`` is off by the residual of the same chain with ``p`` in place of the
focal spot; its Jacobian ``J_a`` (3, P) turns ``C`` into the covariance of the aim's normal
error, whose trace is the expected squared error of the mirror normal [mrad^2]:

    var_aim = trace(J_a C J_a^T)

The same ``C`` and ``J_a`` give the gain of a planned measurement (a rank-one-per-component
update of ``C``, :func:`covariance_after`). Units: angles in mrad, parameters in their own
units (:data:`heliocal.pipeline.physics.parameters.PARAMETER_UNITS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..physics.jacobian import forward_state, residual_and_jacobian
from ..physics.metrics import error_mrad, measured_normal
from ..physics.parameters import HeliostatSpec
from .coarse import MeasurementBatch

__all__ = [
    "ParameterCovariance",
    "coarse_covariance",
    "covariance_from_rows",
    "RowTerms",
    "fit_row_terms",
    "aim_jacobian",
    "aim_variance_mrad2",
    "covariance_after",
]


@dataclass(frozen=True)
class ParameterCovariance:
    """The posterior covariance of a coarse fit's free parameters (module docstring).

    Attributes
    ----------
    free_idx : (P,) indices of the free parameters in PARAMETER_NAMES order.
    covariance : (P, P) [parameter units squared].
    noise_mrad : s, the scale of one residual component of the training rows [mrad].
    n_rows : training rows the covariance rests on.
    """

    free_idx: np.ndarray
    covariance: np.ndarray
    noise_mrad: float
    n_rows: int


def _data_jacobian(params: torch.Tensor, spec: HeliostatSpec, data: MeasurementBatch,
                   free_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 3) [mrad] and the free parameters' Jacobian (N, 3, P) of ``data``; rows
    whose chain is not finite are dropped."""
    with torch.no_grad():
        r, j = residual_and_jacobian(params.to(torch.float64), spec, data.steps, data.sun,
                                     data.focal_spot)
    r, j = r.numpy(), j.numpy()[..., free_idx]
    ok = np.isfinite(r).all(axis=1) & np.isfinite(j).all(axis=(1, 2))
    return r[ok], j[ok]


def coarse_covariance(spec: HeliostatSpec, params: torch.Tensor, free, train: MeasurementBatch,
                      prior_sigma_free, *, noise_mrad: float | None = None) -> ParameterCovariance:
    """The free parameters' posterior covariance of a coarse fit on its training rows.

    Parameters
    ----------
    spec, params : the heliostat and its fitted parameters (28,).
    free : (28,) bool, the preset's free parameters.
    train : the training rows the fit used.
    prior_sigma_free : (P,) the prior sigma of each free parameter [its unit].
    noise_mrad : the residual scale s [mrad per component]; default: the training residuals'
        root mean square with ``2 N - P`` degrees of freedom (at least 1): the residual of a
        row is the difference of two unit vectors, so it lies (to first order) in the plane of
        the normal and only two of its three components carry noise.
    """
    free_idx = np.flatnonzero(np.asarray(free, bool))
    r, j = _data_jacobian(params, spec, train, free_idx)
    return covariance_from_rows(r, j, free_idx, prior_sigma_free, noise_mrad=noise_mrad)


def covariance_from_rows(r: np.ndarray, j: np.ndarray, free_idx: np.ndarray, prior_sigma_free,
                         *, noise_mrad: float | None = None) -> ParameterCovariance:
    """:func:`coarse_covariance` from the training rows' finite residuals ``r`` (N, 3) [mrad]
    and the free parameters' Jacobian ``j`` (N, 3, P) [mrad per parameter unit]."""
    n_rows = len(r)
    if noise_mrad is None:
        # a row's residual lies in the plane of the normal: two components carry its noise
        dof = max(2 * n_rows - len(free_idx), 1)
        noise_mrad = float(np.sqrt((r ** 2).sum() / dof)) if n_rows else float("nan")
    s2 = max(float(noise_mrad), 1e-6) ** 2
    jf = j.reshape(-1, len(free_idx))
    information = jf.T @ jf / s2 + np.diag(1.0 / np.asarray(prior_sigma_free, float) ** 2)
    return ParameterCovariance(free_idx, _inverse_spd(information), float(noise_mrad), n_rows)


@dataclass(frozen=True)
class RowTerms:
    """One heliostat's training rows at its fitted parameters: ``residual`` (N, 3) [mrad],
    ``jacobian`` (N, 3, 28) [mrad per parameter unit] (both as :func:`coarse_covariance` takes
    them, before the non-finite rows are dropped) and ``error_mrad`` (N,) (the angle between
    the predicted and the measured normal, :func:`heliocal.pipeline.models.coarse.normal_errors_mrad`)."""

    residual: np.ndarray
    jacobian: np.ndarray
    error_mrad: np.ndarray

    def finite(self, free_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(residuals, free parameters' Jacobian) of the rows whose chain is finite, as
        :func:`coarse_covariance` uses them."""
        j = self.jacobian[..., free_idx]
        ok = np.isfinite(self.residual).all(axis=1) & np.isfinite(j).all(axis=(1, 2))
        return self.residual[ok], j[ok]


#: Rows (heliostats times their padded row count) per batched chain evaluation of
#: :func:`fit_row_terms`: large enough that torch's per-call cost vanishes, small enough that the
#: Jacobian (rows x 3 x 28 float64) stays near 40 MB.
ROW_TERMS_CHUNK_ROWS = 20_000


def fit_row_terms(specs: Sequence[HeliostatSpec], params: Sequence[torch.Tensor],
                  data: Sequence[MeasurementBatch]) -> list[RowTerms]:
    """:class:`RowTerms` of many heliostats (``specs``, fitted ``params`` (28,) and rows
    ``data``, one each), evaluated in batches of one kinematic and actuator type (rows padded
    with copies of the heliostat's first row and cut off again): the same chain as one
    heliostat at a time, without torch's cost per call for each."""
    out: list[RowTerms | None] = [None] * len(specs)
    groups: dict[tuple, list[int]] = {}
    for k, spec in enumerate(specs):
        if len(data[k]) == 0:
            out[k] = RowTerms(np.zeros((0, 3)), np.zeros((0, 3, 28)), np.zeros(0))
        else:
            groups.setdefault((spec.kinematic_type, spec.actuator_type), []).append(k)
    for members in groups.values():
        members = sorted(members, key=lambda k: len(data[k]))    # similar lengths: little padding
        start = 0
        while start < len(members):
            stop = start + 1
            while (stop < len(members)
                   and (stop + 1 - start) * len(data[members[stop]]) <= ROW_TERMS_CHUNK_ROWS):
                stop += 1
            chunk = members[start:stop]
            for k, terms in zip(chunk, _row_terms_batch([specs[k] for k in chunk],
                                                        [params[k] for k in chunk],
                                                        [data[k] for k in chunk])):
                out[k] = terms
            start = stop
    return out


def _row_terms_batch(specs, params, data) -> list[RowTerms]:
    """:func:`fit_row_terms` of heliostats of one type in one batched evaluation."""
    from ..physics.lm import stack_specs

    n_rows = [len(d) for d in data]
    n_max = max(n_rows)

    def padded(field: str) -> torch.Tensor:
        return torch.stack([torch.cat([getattr(d, field), getattr(d, field)[:1].expand(
            n_max - n, -1)]) if n < n_max else getattr(d, field) for d, n in zip(data, n_rows)])

    spec = stack_specs(list(specs))
    p = torch.stack([x.to(torch.float64) for x in params]).detach()
    steps, sun, spot = padded("steps"), padded("sun"), padded("focal_spot")
    with torch.no_grad():
        state = forward_state(p, spec, steps)
        r, j = residual_and_jacobian(p, spec, steps, sun, spot, state=state)
        e = error_mrad(state[1], measured_normal(sun, state[2], spot))
    r, j, e = r.numpy(), j.numpy(), e.numpy()
    return [RowTerms(r[h, :n], j[h, :n], e[h, :n]) for h, n in enumerate(n_rows)]


def _inverse_spd(a: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix through its eigenvalues (the prior keeps
    it definite; tiny negative rounding is clipped)."""
    w, v = np.linalg.eigh((a + a.T) / 2.0)
    w = np.clip(w, max(w.max(), 1e-300) * 1e-15, None)
    return (v / w) @ v.T


def aim_jacobian(spec: HeliostatSpec, params: torch.Tensor, free_idx: np.ndarray,
                 steps: torch.Tensor, sun: torch.Tensor, aim_point_enu: torch.Tensor) -> np.ndarray:
    """(M, 3, P) [mrad per parameter unit]: how the normal error of aims at ``steps`` (M, 2) for
    unit sun vectors ``sun`` (M, 3) and aim points (M, 3) [m ENU] moves with the free
    parameters; NaN rows where the chain is not finite."""
    with torch.no_grad():
        _, j = residual_and_jacobian(params.to(torch.float64), spec, steps.to(torch.float64),
                                     sun.to(torch.float64), aim_point_enu.to(torch.float64))
    return j.numpy()[..., free_idx]


def aim_variance_mrad2(jacobian: np.ndarray, cov: ParameterCovariance) -> np.ndarray:
    """(M,) expected squared normal error [mrad^2] of aims with ``jacobian`` (M, 3, P) from the
    parameters' uncertainty alone: ``trace(J_a C J_a^T)``."""
    return np.einsum("mip,pq,miq->m", jacobian, cov.covariance, jacobian)


def covariance_after(cov: ParameterCovariance, jacobian_rows: np.ndarray) -> ParameterCovariance:
    """The covariance once rows with Jacobians ``jacobian_rows`` (K, 3, P) are measured too
    (with the fit's noise scale): ``(C^-1 + J^T J / s^2)^-1``, in the Woodbury form
    ``C - C J^T (s^2 I + J C J^T)^-1 J C``."""
    jf = np.asarray(jacobian_rows, float).reshape(-1, len(cov.free_idx))
    if not len(jf):
        return cov
    c = cov.covariance
    s2 = max(cov.noise_mrad, 1e-6) ** 2
    gain = np.linalg.solve(s2 * np.eye(len(jf)) + jf @ c @ jf.T, jf @ c)
    updated = c - c @ jf.T @ gain
    return ParameterCovariance(cov.free_idx, (updated + updated.T) / 2.0, cov.noise_mrad,
                               cov.n_rows + len(jacobian_rows))
