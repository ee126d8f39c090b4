"""What a coarse fit's Jacobian at the solution says about its parameters: standard errors, which
parameters the data determine, the condition number and how much each parameter leans on its
prior (:func:`fit_diagnostics`, :func:`prior_shrinkage`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..physics.parameters import PARAMETER_NAMES
from ..vocabulary import STD_ERROR_PSEUDO_INVERSE

__all__ = ["FitDiagnostics", "fit_diagnostics", "loss_weights", "prior_shrinkage"]


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
    #: (28,) the prior's share of each parameter's fit, in [0, 1] (:func:`prior_shrinkage`);
    #: NaN where fixed or without prior rows
    prior_shrinkage: np.ndarray = field(
        default_factory=lambda: np.full(len(PARAMETER_NAMES), np.nan))
    #: (28,) the standard error the data alone give each parameter at the fit's own noise
    #: (``noise_mrad``; 1 mrad when the fit has no residual degrees of freedom) [parameter
    #: units]; NaN where fixed or where the data do not see the parameter alone (null space)
    data_only_std_error: np.ndarray = field(
        default_factory=lambda: np.full(len(PARAMETER_NAMES), np.nan))

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


def prior_shrinkage(J: np.ndarray, r: np.ndarray, n_data: int, loss: str = "linear",
                    f_scale_mrad: float = 1.0) -> np.ndarray | None:
    """How much each free parameter's fit leans on its prior: (P,) in [0, 1], 0 = the data alone
    fix it, 1 = the data say nothing about it (the fit is the prior's mean); None without prior
    rows.

    ``J`` (n_data + P, P) and ``r`` are the fit's rows at the solution: the data rows [mrad],
    then one prior row per free parameter, ``(p_j - mean_j) / sigma'_j`` with ``sigma'_j =
    sigma_j / s`` (the prior weighed against the noise ``s`` of the data rows; ``J``'s prior
    block is ``diag(1 / sigma')``). The last Gauss-Newton system of the fit weighs every row
    by the loss's ``rho'`` (:func:`loss_weights`; all ones for ``linear``; the iteratively
    reweighted system of :mod:`~heliocal.pipeline.physics.lm`, whose cost scipy's ``trf``
    minimises too), so its curvature is ``H = J^T W J = H_data + H_prior`` with ``H_prior =
    diag(w_j / sigma'_j^2)``. The shrinkage of parameter ``j`` is::

        shrinkage_j = [H^-1]_jj * [H_prior]_jj

    which is at once (i) the derivative of the fitted value by the prior's mean, ``d p_j / d
    mean_j`` of the linearised MAP solution ``p = H^-1 (J_d^T W_d y + H_prior mean)``; (ii) the
    Gaussian posterior's variance of ``p_j`` over its prior variance (``H / s^2`` is the
    posterior precision, ``s`` cancels); (iii) the leverage of ``j``'s prior row, its diagonal
    entry of the hat matrix ``J H^-1 J^T W``, so the data rows' leverages sum to ``P - sum_j
    shrinkage_j`` (:func:`fit_diagnostics`' ``data_dof`` is ``n_data`` minus that, unweighted).

    Not the diagonal ratio ``[H_prior]_jj / H_jj``: that is the shrinkage of ``p_j`` with every
    other parameter held fixed, near 0 whenever the data move ``p_j`` at all, also when they
    move it only together with another parameter (two parameters that enter only through their
    sum: the data fix the sum, the prior decides how it splits; ``[H^-1]_jj`` gives each 1/2
    for equal priors, the diagonal ratio about 0). The two agree when the data Jacobian's
    columns are orthogonal.
    """
    n_free = J.shape[1]
    if J.shape[0] < n_data + n_free or n_free == 0:
        return None
    w = loss_weights(r, loss, f_scale_mrad)
    # columns scaled to unit prior curvature: the ratio is invariant, the inverse well-conditioned
    scale = 1.0 / np.sqrt(np.maximum(np.diag(J[n_data:]) ** 2, 1e-300))
    Jw = J * scale * np.sqrt(w)[:, None]
    H = Jw.T @ Jw
    h_prior = (Jw[n_data:] ** 2).sum(axis=0)
    try:
        inv_diag = np.diag(np.linalg.inv(H))
    except np.linalg.LinAlgError:  # pragma: no cover - the prior rows keep H positive definite
        inv_diag = np.diag(np.linalg.pinv(H))
    return np.clip(inv_diag * h_prior, 0.0, 1.0)


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
    far above ``f_scale_mrad`` counts about linearly, as it pulls the fit, not squared.

    ``determined`` and ``data_only_std_error`` are what the data rows alone say, without the
    prior: ``sqrt([(J_d^T J_d)^-1]_jj)`` per unit noise (pseudo-inverse; NaN for a parameter with
    a component in the data's null space). ``determined`` states it for 1 mrad of noise (below
    half the prior sigma), ``data_only_std_error`` for the fit's own noise ``noise_mrad`` (on
    ``n_data - P``; 1 mrad without residual degrees of freedom): on data measured to 0.08 mrad a
    parameter the data pin to 5 % of its prior sigma is not ``determined`` at 1 mrad."""
    std = np.full(len(PARAMETER_NAMES), np.nan)
    determined = np.ones(len(PARAMETER_NAMES), bool)
    cond = float("nan")
    pseudo = False
    s2 = rss = dof_eff = float("nan")
    shrinkage = np.full(len(PARAMETER_NAMES), np.nan)
    data_std = np.full(len(PARAMETER_NAMES), np.nan)
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
        own = math.sqrt(s2) if n_data > len(free_idx) else 1.0
        data_std[free_idx] = np.where(null, np.nan, data_only * own * scale)
        share = prior_shrinkage(J, r, n_data, loss, f_scale_mrad)
        if share is not None:
            shrinkage[free_idx] = share
    return FitDiagnostics(std, determined, cond, pseudo, math.sqrt(s2), rss, dof_eff, shrinkage,
                          data_std)
