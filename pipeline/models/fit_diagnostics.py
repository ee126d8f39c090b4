"""What a coarse fit's Jacobian at the solution says about its parameters: standard errors, which
parameters the data determine, and the condition number (:func:`fit_diagnostics`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..physics.parameters import PARAMETER_NAMES
from ..vocabulary import STD_ERROR_PSEUDO_INVERSE

__all__ = ["FitDiagnostics", "fit_diagnostics", "loss_weights"]


@dataclass
class FitDiagnostics:
    """:func:`fit_diagnostics` of one fit."""

    std_error: np.ndarray       # (28,) standard errors; NaN where fixed
    determined: np.ndarray      # (28,) bool: the data, not the prior, pin the parameter
    condition_number: float     # of the scaled data Jacobian
    pseudo_inverse: bool        # J^T J was singular: std_error from its pseudo-inverse
    noise_mrad: float = float("nan")  # s: RMS data residual per component [mrad], on the dof
    data_rss_mrad2: float = float("nan")  # data residuals' squares, loss-weighted [mrad^2]
    data_dof: float = float("nan")  # their effective degrees of freedom (see fit_diagnostics)

    def flag_status(self, status: str) -> str:
        """The fit's status, with :data:`~heliocal.pipeline.vocabulary.STD_ERROR_PSEUDO_INVERSE`
        appended when the standard errors are not trustworthy."""
        return f"{status}; {STD_ERROR_PSEUDO_INVERSE}" if self.pseudo_inverse else status


def loss_weights(r: np.ndarray, loss: str = "linear", f_scale_mrad: float = 1.0) -> np.ndarray:
    """The weight ``rho'`` the fit's loss gives each residual ``r`` [mrad] at the solution (scipy's
    losses: 1 for ``linear``; ``(1 + z)^-1/2`` for ``soft_l1`` and ``min(1, z^-1/2)`` for
    ``huber``, ``z = (r / f_scale)^2``): the rows of the weighted least-squares problem the
    robust fit solves there (iteratively reweighted least squares)."""
    z = (np.asarray(r, np.float64) / f_scale_mrad) ** 2
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))
    return np.ones_like(z)


def fit_diagnostics(J: np.ndarray | None, r: np.ndarray | None, n_data: int,
                    free_idx: np.ndarray, sigma: np.ndarray, loss: str = "linear",
                    f_scale_mrad: float = 1.0) -> FitDiagnostics:
    """Standard errors, the 'determined' flags and the condition number from the Jacobian ``J``
    (data rows, then prior rows; columns the free parameters ``free_idx``) and residuals ``r``
    at the solution; ``sigma`` (28,) the prior sigmas, which scale the columns.

    ``cov = s^2 (J^T J)^-1`` with ``s^2`` the data residual variance. When ``J^T J`` cannot be
    inverted the pseudo-inverse stands in and ``pseudo_inverse`` says so: such standard errors
    are finite but not trustworthy (a direction the data and the prior both leave free gets
    none).

    ``data_dof``: the data rows minus their share of the fitted parameters, the trace of the data
    rows' block of the hat matrix ``J (J^T J)^-1 J^T`` (the prior rows take the rest): ``n_data -
    P`` without a prior, up to ``n_data`` where the prior pins every parameter. ``data_rss_mrad2 /
    data_dof`` estimates the noise variance of a MAP fit, which ``noise_mrad`` (on ``n_data - P``)
    underestimates when the prior, not the data, fixes some parameters. Its squares are weighed as
    the fit's ``loss`` weighs the rows (:func:`loss_weights`): under a robust loss a residual
    far above ``f_scale_mrad`` counts about linearly, as it pulls the fit, not squared."""
    std = np.full(len(PARAMETER_NAMES), np.nan)
    determined = np.ones(len(PARAMETER_NAMES), bool)
    cond = float("nan")
    pseudo = False
    s2 = rss = dof_eff = float("nan")
    if J is not None:
        dof = max(n_data - len(free_idx), 1)
        s2 = float((r[:n_data] ** 2).sum()) / dof
        rss = float((loss_weights(r[:n_data], loss, f_scale_mrad) * r[:n_data] ** 2).sum())
        scale = sigma[free_idx]
        Js = J * scale  # scaled columns: comparable units
        # singular values of the scaled data Jacobian from the small normal matrix (a tall SVD
        # is slow with a multithreaded BLAS under load)
        try:
            ev = np.linalg.eigvalsh(Js[:n_data].T @ Js[:n_data])
            cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
        except np.linalg.LinAlgError:
            cond = float("inf")
        JtJ = Js.T @ Js
        try:
            cov_scaled = np.linalg.inv(JtJ)
        except np.linalg.LinAlgError:
            cov_scaled, pseudo = np.linalg.pinv(JtJ), True
        # data-noise covariance; the prior rows stay in (they keep it invertible)
        std_free = np.sqrt(np.clip(np.diag(cov_scaled), 0, None) * max(s2, 1e-300)) * scale
        dof_eff = n_data - float(((Js[:n_data] @ cov_scaled) * Js[:n_data]).sum())
        std[free_idx] = std_free
        # "determined": the data alone pin the parameter to well within its prior sigma, for a
        # unit (1 mrad) measurement noise; otherwise the prior, not the data, fixes it.
        Jd = Js[:n_data]
        try:
            eig, vec = np.linalg.eigh(Jd.T @ Jd)
            tol = max(eig.max(), 1e-300) * 1e-12
            inv = (vec / np.where(eig > tol, eig, np.inf)) @ vec.T
            data_only = np.sqrt(np.clip(np.diag(inv), 0, None))
            null = (vec[:, eig <= tol] ** 2).sum(axis=1) > 1e-6
        except np.linalg.LinAlgError:  # pragma: no cover
            data_only, null = np.full(len(free_idx), np.inf), np.ones(len(free_idx), bool)
        determined[free_idx] = (data_only < 0.5) & ~null
    return FitDiagnostics(std, determined, cond, pseudo, math.sqrt(s2), rss, dof_eff)
