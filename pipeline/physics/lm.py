"""Levenberg-Marquardt for many heliostats at once: one vectorized torch program per batch.

:func:`solve_batched` minimises, for each of ``H`` heliostats of one kinematic and actuator type
and one preset (the same free parameters), the objective of the scipy path of
:func:`heliocal.pipeline.models.coarse.fit_heliostat`:

* residuals ``1000 (n_pred - n_meas)`` [mrad] of the heliostat's measurements (NaN, where an
  actuator leaves its geometric range, replaced by 1e4 as there), followed by the prior rows
  ``(x - x_prior) / sigma``;
* cost ``0.5 sum rho(r)``: ``rho(r) = r^2`` for the ``linear`` loss; for ``soft_l1`` and ``huber``
  scipy's robust losses with scale ``f_scale`` (``rho = f_scale^2 rho_0((r / f_scale)^2)``),
  applied, as in scipy, to every residual including the prior rows.

The robust loss enters the Gauss-Newton model by iterative reweighting: residuals and Jacobian
rows are multiplied by ``sqrt(rho')``, so the linear least-squares model has exactly the
gradient of the robust cost, ``J^T diag(rho') r``, and the curvature ``J^T diag(rho') J``. The
objective, its gradient and hence its minimum are scipy's; only the model's curvature differs
from scipy's ``scale_for_robust_loss_function`` (``J^T diag(rho' + 2 rho'' r^2) J``), which for
the concave soft_l1 and huber losses is much smaller for large residuals and makes the first
steps from a poor start overshoot (on a static-20 fit from the nominal geometry: 6 instead of
about 20 Jacobian evaluations). For those losses the reweighted model majorises the cost, so
its steps are rarely rejected.

Rows of heliostats with fewer measurements than the longest in the batch are padded and masked
(residual and Jacobian rows zero), so they add nothing. Every heliostat has its own damping
``lambda`` (Levenberg's ``lambda I`` in the variables scaled by ``x_scale``, where the weak
prior keeps every curvature >= 1; Nielsen's update), its own
step acceptance and its own convergence test; converged heliostats drop out of the batch, so the
work per iteration shrinks as the batch converges. The normal equations (H, P, P) are solved by a
batched Cholesky factorisation (least squares where a matrix is not positive definite).

Termination per heliostat (tolerances as scipy's ``xtol``, ``ftol``, ``gtol``, in the variables
scaled by ``x_scale``): an accepted step lowering the cost by less than ``ftol`` relative, a step
shorter than ``xtol (xtol + |x|)``, a gradient below ``gtol`` (max norm), or ``max_nfev``
residual evaluations.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from ..errors import check_choice
from .jacobian import forward_state, residual_and_jacobian
from .parameters import HeliostatSpec
from .metrics import measured_normal
from ..vocabulary import CoarseLoss

__all__ = ["BatchedProblem", "BatchedSolution", "stack_specs", "take_spec", "iterate_by_type",
           "solve_batched",
           "robust_loss", "normal_residuals_mrad", "NAN_RESIDUAL_MRAD",
           "LOSSES", "SPEC_TENSORS"]

LOSSES = CoarseLoss.values()
#: residual that replaces NaN (an actuator outside its range), as in the scipy path [mrad]
NAN_RESIDUAL_MRAD = 1e4

SPEC_TENSORS = ("clockwise", "min_steps", "max_steps", "position_enu", "initial_orientation",
                 "primary_axis")


def stack_specs(specs: list[HeliostatSpec]) -> HeliostatSpec:
    """One spec of batch shape (H,) from H single-heliostat specs of one type.

    The fields are stacked as they are (no re-normalisation of ``primary_axis``), so every
    heliostat sees bit-for-bit the geometry it has alone.
    """
    types = {(s.kinematic_type, s.actuator_type) for s in specs}
    if len(types) != 1:
        from ..errors import ParameterError

        raise ParameterError("The 'specs' parameter of stack_specs must share one kinematic_type "
                             f"and actuator_type. Got {sorted(types)!r} instead.")
    out = copy.copy(specs[0])
    for name in SPEC_TENSORS:
        object.__setattr__(out, name, torch.stack([getattr(s, name) for s in specs]))
    object.__setattr__(out, "heliostat_id", tuple(s.heliostat_id for s in specs))
    return out


def iterate_by_type(specs: list[HeliostatSpec], todo: list[torch.Tensor], step,
                    max_iterations: int) -> None:
    """Iterations of many heliostats' independent fixed points (an aim's steps through a fine
    model, say), the rows of one kinematic and actuator type together: heliostat ``j`` (of
    spec ``specs[j]``) has rows ``todo[j]`` (K_j,) bool still iterating, and each iteration
    calls ``step(iteration, active, spec)`` once per type with ``active`` [(j, idx)] its
    heliostats' rows still iterating (in that order) and ``spec`` the rows' spec (each row a
    batch of one with its heliostat's: :func:`take_spec` of :func:`stack_specs`; one
    heliostat's own spec when it is the type's only one). ``step`` updates its state and
    ``todo`` in place; a type stops when none of its rows is left or after
    ``max_iterations``."""
    groups: dict[tuple, list[int]] = {}
    for j, spec in enumerate(specs):
        groups.setdefault((spec.kinematic_type, spec.actuator_type), []).append(j)
    for members in groups.values():
        stacked = stack_specs([specs[j] for j in members]) if len(members) > 1 else None
        for iteration in range(1, max_iterations + 1):
            active = [(k, j, torch.nonzero(todo[j]).flatten())
                      for k, j in enumerate(members) if bool(todo[j].any())]
            if not active:
                break
            which = torch.cat([torch.full((len(idx),), k, dtype=torch.long)
                               for k, _, idx in active])
            spec = specs[members[0]] if stacked is None else take_spec(stacked, which)
            step(iteration, [(j, idx) for _, j, idx in active], spec)


def normal_residuals_mrad(params: torch.Tensor, spec: HeliostatSpec, steps: torch.Tensor,
                          sun: torch.Tensor, focal_spot: torch.Tensor):
    """The coarse fit's residuals ``1000 (n_pred - n_meas)`` [mrad], (..., N, 3), a non-finite
    one as :data:`NAN_RESIDUAL_MRAD`, and the forward state at ``params`` (what
    :func:`~heliocal.pipeline.physics.jacobian.residual_and_jacobian` reuses)."""
    state = forward_state(params, spec, steps)
    meas = measured_normal(sun, state[2], focal_spot)
    return torch.nan_to_num(1000.0 * (state[1] - meas), nan=NAN_RESIDUAL_MRAD), state


def take_spec(spec: HeliostatSpec, idx: torch.Tensor) -> HeliostatSpec:
    """The heliostats ``idx`` of a batched spec (:func:`stack_specs`): batch shape ``idx.shape``
    (an index may repeat, e.g. one entry per measurement row)."""
    out = copy.copy(spec)
    for name in SPEC_TENSORS:
        object.__setattr__(out, name, getattr(spec, name)[idx])
    object.__setattr__(out, "heliostat_id", None)
    return out


def robust_loss(residual: torch.Tensor, loss: str, f_scale: float):
    """scipy's ``rho`` of a loss, scaled by ``f_scale``: (rho, rho', rho'') per residual."""
    if loss == "linear":
        one = torch.ones_like(residual)
        return residual**2, one, torch.zeros_like(residual)
    z = (residual / f_scale) ** 2
    if loss == "soft_l1":
        t = 1.0 + z
        rho0, rho1, rho2 = 2.0 * (t.sqrt() - 1.0), t.rsqrt(), -0.5 * t.pow(-1.5)
    else:  # huber
        small = z <= 1.0
        zs = torch.where(small, torch.ones_like(z), z)  # keeps the unused branch finite
        rho0 = torch.where(small, z, 2.0 * zs.sqrt() - 1.0)
        rho1 = torch.where(small, torch.ones_like(z), zs.rsqrt())
        rho2 = torch.where(small, torch.zeros_like(z), -0.5 * zs.pow(-1.5))
    return rho0 * f_scale**2, rho1, rho2 / f_scale**2


@dataclass
class BatchedProblem:
    """H heliostats' fits with the same free parameters (one kinematic/actuator type, one preset).

    Attributes
    ----------
    spec : batch shape (H,) (:func:`stack_specs`).
    base : (H, 28) full parameter vectors at the start; the free entries are the variables.
    free_idx : (P,) indices of the free parameters.
    steps, sun, focal_spot : (H, N, 2), (H, N, 3), (H, N, 3) padded measurements.
    row_mask : (H, N) bool, True for real measurements.
    prior_mean, prior_scale : (H, P) prior rows ``(x - prior_mean) * prior_scale``; no prior rows
        when ``prior_scale`` is None.
    x_scale : (H, P) characteristic scale of each variable (scipy's ``x_scale``).
    """

    spec: HeliostatSpec
    base: torch.Tensor
    free_idx: torch.Tensor
    steps: torch.Tensor
    sun: torch.Tensor
    focal_spot: torch.Tensor
    row_mask: torch.Tensor
    prior_mean: torch.Tensor
    prior_scale: torch.Tensor | None
    x_scale: torch.Tensor

    @property
    def n_rows(self) -> int:
        """Residual rows per heliostat (padded data rows, then prior rows)."""
        prior = 0 if self.prior_scale is None else int(self.free_idx.numel())
        return 3 * int(self.steps.shape[1]) + prior

    def residuals(self, idx: torch.Tensor, x: torch.Tensor):
        """Residual rows (h, M) at free values ``x`` (h, P) of heliostats ``idx``, plus what the
        Jacobian at the same point reuses."""
        p = self.base[idx].clone()
        p[:, self.free_idx] = x
        spec = take_spec(self.spec, idx)
        r, state = normal_residuals_mrad(p, spec, self.steps[idx], self.sun[idx],
                                         self.focal_spot[idx])
        r = (r * self.row_mask[idx].unsqueeze(-1)).flatten(-2)
        if self.prior_scale is not None:
            r = torch.cat([r, (x - self.prior_mean[idx]) * self.prior_scale[idx]], dim=-1)
        return r, (p, spec, state)

    def jacobian(self, idx: torch.Tensor, point) -> torch.Tensor:
        """Jacobian (h, M, P) of :meth:`residuals` at ``point`` (its second return value)."""
        p, spec, state = point
        _, jac = residual_and_jacobian(p, spec, self.steps[idx], self.sun[idx],
                                       self.focal_spot[idx], state=state)
        jf = torch.nan_to_num(jac[..., self.free_idx], nan=0.0, posinf=0.0, neginf=0.0)
        jf = (jf * self.row_mask[idx][..., None, None]).flatten(-3, -2)
        if self.prior_scale is not None:
            jf = torch.cat([jf, torch.diag_embed(self.prior_scale[idx])], dim=-2)
        return jf


@dataclass
class BatchedSolution:
    """Result of :func:`solve_batched` (per heliostat)."""

    x: torch.Tensor  # (H, P) free values at the solution
    cost: torch.Tensor  # (H,) 0.5 sum rho(r)
    residual: torch.Tensor  # (H, M) plain residual rows at x (padded rows zero)
    jacobian: torch.Tensor  # (H, M, P) plain Jacobian at x
    nfev: torch.Tensor  # (H,) residual evaluations
    njev: torch.Tensor  # (H,) Jacobian evaluations
    status: list[str]


def _cost(r: torch.Tensor, loss: str, f_scale: float) -> torch.Tensor:
    return 0.5 * robust_loss(r, loss, f_scale)[0].sum(-1)


def _model(r: torch.Tensor, jac: torch.Tensor, loss: str, f_scale: float):
    """Gradient (h, P) and Gauss-Newton matrix (h, P, P) of the (robust) cost."""
    if loss != "linear":  # iteratively reweighted: weights rho'(r^2) on rows and residuals
        weight = robust_loss(r, loss, f_scale)[1].sqrt()
        r = r * weight
        jac = jac * weight.unsqueeze(-1)
    jt = jac.transpose(-1, -2)
    return (jt @ r.unsqueeze(-1)).squeeze(-1), jt @ jac


def _solve_damped(a: torch.Tensor, g: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Step ``-(A + lambda I)^-1 g`` for each heliostat, in the scaled variables (Cholesky; least
    squares where the damped matrix is not numerically positive definite)."""
    m = a + torch.diag_embed(lam.unsqueeze(-1).expand(a.shape[:-1]))
    chol, info = torch.linalg.cholesky_ex(m)
    step = torch.cholesky_solve(-g.unsqueeze(-1), chol).squeeze(-1)
    bad = (info != 0) | ~torch.isfinite(step).all(-1)
    if bool(bad.any()):
        step[bad] = torch.linalg.lstsq(m[bad], -g[bad].unsqueeze(-1),
                                       driver="gelsd").solution.squeeze(-1)
    return step


def solve_batched(problem: BatchedProblem, x0: torch.Tensor, *, loss: str = "linear",
                  f_scale: float = 1.0, max_nfev: int = 200, tolerance: float = 1e-10,
                  initial_lambda: float = 1e-3) -> BatchedSolution:
    """Batched Levenberg-Marquardt from ``x0`` (H, P); see the module docstring.

    ``tolerance`` is xtol = ftol = gtol; ``max_nfev`` bounds the residual evaluations per
    heliostat.
    """
    check_choice(loss, "loss", "solve_batched", LOSSES)
    h_all, n_par = x0.shape
    everyone = torch.arange(h_all)
    x = x0.clone().to(torch.float64)
    r, point = problem.residuals(everyone, x)
    jac = problem.jacobian(everyone, point)
    cost = _cost(r, loss, f_scale)
    lam = torch.full((h_all,), float(initial_lambda), dtype=torch.float64)
    nu = torch.full((h_all,), 2.0, dtype=torch.float64)
    nfev = torch.ones(h_all, dtype=torch.int64)
    njev = torch.ones(h_all, dtype=torch.int64)
    active = torch.ones(h_all, dtype=torch.bool)
    status = [""] * h_all
    scale = problem.x_scale.to(torch.float64)

    def finish(which: torch.Tensor, message: str) -> None:
        for k in which.tolist():
            status[k] = message
        active[which] = False

    if n_par == 0:
        finish(everyone, "nothing to fit")
    while bool(active.any()):
        idx = active.nonzero().squeeze(-1)
        s = scale[idx]
        g, a = _model(r[idx], jac[idx], loss, f_scale)
        g_s = g * s  # gradient and normal matrix in the scaled variables x / x_scale
        a_s = a * s.unsqueeze(-1) * s.unsqueeze(-2)
        small_g = g_s.abs().amax(-1) < tolerance
        if bool(small_g.any()):
            finish(idx[small_g], "`gtol` termination condition is satisfied.")
            keep = ~small_g
            idx, s, g_s, a_s = idx[keep], s[keep], g_s[keep], a_s[keep]
            if idx.numel() == 0:
                break
        step_s = _solve_damped(a_s, g_s, lam[idx])
        x_new = x[idx] + step_s * s
        r_new, point_new = problem.residuals(idx, x_new)
        nfev[idx] += 1
        cost_new = _cost(r_new, loss, f_scale)
        predicted = -((g_s * step_s).sum(-1)
                      + 0.5 * (step_s.unsqueeze(-2) @ a_s @ step_s.unsqueeze(-1)).view(-1))
        actual = cost[idx] - cost_new
        accept = (actual > 0) & (predicted > 0) & torch.isfinite(cost_new)
        x_norm = (x[idx] / s).norm(dim=-1)
        step_norm = step_s.norm(dim=-1)
        small_x = step_norm < tolerance * (tolerance + x_norm)
        small_f = accept & (actual < tolerance * cost[idx])

        # damping per heliostat (Nielsen): shrink on a good step, grow on a rejected one
        gain = actual / torch.where(predicted > 0, predicted, torch.ones_like(predicted))
        shrink = torch.clamp(1.0 - (2.0 * gain - 1.0) ** 3, min=1.0 / 3.0)
        lam[idx] = torch.where(accept, lam[idx] * shrink, lam[idx] * nu[idx])
        nu[idx] = torch.where(accept, torch.full_like(nu[idx], 2.0), nu[idx] * 2.0)

        if bool(accept.any()):
            acc = idx[accept]
            x[acc] = x_new[accept]
            r[acc] = r_new[accept]
            cost[acc] = cost_new[accept]
            p, spec, state = point_new
            sub = accept.nonzero().squeeze(-1)
            jac[acc] = problem.jacobian(acc, (p[sub], take_spec(spec, sub),
                                              tuple(t[sub] for t in state)))
            njev[acc] += 1
        done_f = small_f
        done_x = small_x & ~done_f
        finish(idx[done_f & small_x], "`ftol` and `xtol` termination conditions are satisfied.")
        finish(idx[done_f & ~small_x], "`ftol` termination condition is satisfied.")
        finish(idx[done_x], "`xtol` termination condition is satisfied.")
        still = active[idx]
        out_of_budget = still & (nfev[idx] >= max_nfev)
        finish(idx[out_of_budget], "The maximum number of function evaluations is exceeded.")
        stuck = active[idx] & (lam[idx] > 1e30)
        finish(idx[stuck], "damping exceeded 1e30 without a decrease of the cost.")
    return BatchedSolution(x, cost, r, jac, nfev, njev, status)
