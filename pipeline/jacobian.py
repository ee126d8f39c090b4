"""Exact residuals and Jacobian of the coarse fit, from the chain's geometry (no finite differences).

Autodiff through :func:`~heliocal.pipeline.kinematics.forward_kinematics` (``torch.func.jacfwd``)
costs about 10 ms per Jacobian on 300 measurements, dominated by per-operation overhead. The
Jacobian of a rigid-body chain has a closed form (the robot manipulator's *geometric Jacobian*),
which this module evaluates with a handful of batched tensor operations:

* a rotation by angle ``phi`` about a world-frame unit axis ``w`` through the point ``o`` moves
  the mirror normal by ``dn/dphi = w x n`` and the mirror centre by ``dP/dphi = w x (P - o)``;
* a translation along a world-frame direction ``d`` moves the centre by ``dP/dt = d`` and leaves
  the normal alone;
* the actuator parameters act through the joint angles: ``dn/dq = (w_i x n) s_i dtheta_i/dq``,
  with ``dtheta_i/dq`` from torch autograd through the (elementwise) actuator law.

The chain (see :mod:`heliocal.pipeline.kinematics`) is, for the mirror centre ``P`` and normal
``n``::

    P = pos + F Tilt1 ( R1 ( Tilt2 ( R2 tc + t2 ) ) + t1 )
    n = F Tilt1 R1 Tilt2 R2 TiltC n0,          Tilt(x) = R_e(x_e) R_n(x_n) R_u(x_u)

The residual of the fit is ``1000 (n - m)`` [mrad] per measurement, ``m`` the measured normal
(bisector of the sun and the direction from ``P`` to the focal spot ``f``), so
``dm/dP = -(I - m m^T)(I - u u^T) / (|s + u| |f - P|)`` with ``u = unit(f - P)``.
Agreement with autodiff is a test (``tests/test_jacobian.py``).
"""

from __future__ import annotations

import torch

from .kinematics import (PARAMETER_INDEX, HeliostatSpec, _JOINT_AXES, _N0, _SENSES, _base_frame,
                         _tilt_matrices, forward_kinematics, joint_angles, rotation_e, rotation_n)
from .metrics import measured_normal

__all__ = ["residual_and_jacobian"]

_E = torch.eye(3, dtype=torch.float64)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _tilt_axes(prefix: torch.Tensor, tilt_e: torch.Tensor, tilt_n: torch.Tensor) -> torch.Tensor:
    """World axes (3, 3) [rows e, n, u] of the three tilt rotations following ``prefix`` (3, 3)."""
    a_e = prefix @ _E[0]
    p_n = prefix @ rotation_e(tilt_e)
    a_n = p_n @ _E[1]
    a_u = p_n @ rotation_n(tilt_n) @ _E[2]
    return torch.stack([a_e, a_n, a_u])


def residual_and_jacobian(params: torch.Tensor, spec: HeliostatSpec, steps: torch.Tensor,
                          sun: torch.Tensor, focal_spot: torch.Tensor):
    """Residuals ``1000 (n_pred - n_meas)`` [mrad] and their exact Jacobian for one heliostat.

    Parameters
    ----------
    params : (28,) parameter vector.
    spec : the heliostat (batch shape ``()``).
    steps : (N, 2) motor steps; sun : (N, 3) unit sun vectors; focal_spot : (N, 3) [m] ENU.

    Returns
    -------
    residual : (N, 3) [mrad]
    jacobian : (N, 3, 28) [mrad per parameter unit], columns in PARAMETER_NAMES order.
    """
    params = params.detach()
    n_meas = steps.shape[0]
    kt = spec.kinematic_type
    (ax1, _), (ax2, _) = _JOINT_AXES[kt]
    senses = _SENSES[kt]

    # joint angles and their derivatives w.r.t. each measurement's own copy of the parameters
    p_rows = params.expand(n_meas, -1).clone().requires_grad_(True)
    angles = joint_angles(p_rows, spec, steps.unsqueeze(-2)).squeeze(-2)  # (N, 2)
    dtheta = []
    for i in range(2):
        (g,) = torch.autograd.grad(angles[:, i].sum(), p_rows, retain_graph=i == 0)
        dtheta.append(torch.nan_to_num(g))  # (N, 28)
    angles = angles.detach()

    normal, position = forward_kinematics(params, spec, steps)
    meas = measured_normal(sun, position, focal_spot)
    residual = 1000.0 * (normal - meas)

    tilts = _tilt_matrices(params)  # (3 bodies, 3, 3)
    tilt_1, tilt_2, _ = tilts.unbind(0)
    t_idx = [[PARAMETER_INDEX[f"{b}_translation_{d}_m"] for d in "enu"]
             for b in ("joint_1", "joint_2", "concentrator")]
    r_idx = [[PARAMETER_INDEX[f"{b}_tilt_{d}_rad"] for d in "enu"]
             for b in ("joint_1", "joint_2", "concentrator")]
    t1, t2 = params[t_idx[0]], params[t_idx[1]]

    frame = _base_frame(spec)
    a0 = torch.eye(3, dtype=torch.float64) if frame is None else frame
    a1 = a0 @ tilt_1  # (3, 3), same for all measurements
    phi = angles * senses  # (N, 2)
    r1 = _axis_rotation(ax1, phi[:, 0])  # (N, 3, 3)
    r2 = _axis_rotation(ax2, phi[:, 1])
    a2 = a1 @ r1  # (N, 3, 3)
    a3 = a2 @ tilt_2
    a4 = a3 @ r2

    pos0 = spec.position_enu
    o1 = pos0 + a1 @ t1  # (3,) pivot of joint 1 and of joint-2 tilts
    o2 = o1 + a3 @ t2  # (N, 3) pivot of joint 2

    dn = torch.zeros(n_meas, 3, 28, dtype=torch.float64)
    dp = torch.zeros(n_meas, 3, 28, dtype=torch.float64)

    def rotation(idx: int, axis: torch.Tensor, pivot: torch.Tensor | None) -> None:
        axis = axis.expand(n_meas, 3)
        dn[:, :, idx] = torch.linalg.cross(axis, normal, dim=-1)
        if pivot is not None:
            dp[:, :, idx] = torch.linalg.cross(axis, position - pivot, dim=-1)

    # joint-1 tilts: rotate everything about the heliostat position
    for k, ax in enumerate(_tilt_axes(a0, params[r_idx[0][0]], params[r_idx[0][1]])):
        rotation(r_idx[0][k], ax, pos0)
    # joint-1 translation
    for k in range(3):
        dp[:, :, t_idx[0][k]] = a1[:, k].expand(n_meas, 3)
    # joint-2 tilts: about o1, axes after joint 1's rotation
    te2, tn2 = params[r_idx[1][0]], params[r_idx[1][1]]
    ax_e2 = a2 @ _E[0]
    p_n2 = a2 @ rotation_e(te2)
    ax_n2 = p_n2 @ _E[1]
    ax_u2 = p_n2 @ rotation_n(tn2) @ _E[2]
    for k, ax in enumerate((ax_e2, ax_n2, ax_u2)):
        rotation(r_idx[1][k], ax, o1)
    # joint-2 translation
    for k in range(3):
        dp[:, :, t_idx[1][k]] = a3[..., k]
    # concentrator translation
    for k in range(3):
        dp[:, :, t_idx[2][k]] = a4[..., k]
    # concentrator tilts: turn the mirror about its centre (normal only)
    tec, tnc = params[r_idx[2][0]], params[r_idx[2][1]]
    ax_ec = a4 @ _E[0]
    p_nc = a4 @ rotation_e(tec)
    ax_nc = p_nc @ _E[1]
    ax_uc = p_nc @ rotation_n(tnc) @ _E[2]
    for k, ax in enumerate((ax_ec, ax_nc, ax_uc)):
        rotation(r_idx[2][k], ax, None)
    # joints: through the actuator laws
    w1 = a1[:, ax1].expand(n_meas, 3)
    w2 = a3[..., ax2]
    dn_dphi1 = torch.linalg.cross(w1, normal, dim=-1)
    dp_dphi1 = torch.linalg.cross(w1, position - o1, dim=-1)
    dn_dphi2 = torch.linalg.cross(w2, normal, dim=-1)
    dp_dphi2 = torch.linalg.cross(w2, position - o2, dim=-1)
    g1 = dtheta[0] * senses[0]  # (N, 28) dphi1/dq
    g2 = dtheta[1] * senses[1]
    dn = dn + dn_dphi1.unsqueeze(-1) * g1.unsqueeze(-2) + dn_dphi2.unsqueeze(-1) * g2.unsqueeze(-2)
    dp = dp + dp_dphi1.unsqueeze(-1) * g1.unsqueeze(-2) + dp_dphi2.unsqueeze(-1) * g2.unsqueeze(-2)

    # measured normal's dependence on the mirror centre
    v = focal_spot - position
    dist = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    u = v / dist
    s_plus_u = sun + u
    norm_su = torch.linalg.vector_norm(s_plus_u, dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    proj_u = eye - u.unsqueeze(-1) * u.unsqueeze(-2)
    proj_m = eye - meas.unsqueeze(-1) * meas.unsqueeze(-2)
    dm_dp = -(proj_m @ proj_u) / (norm_su * dist).unsqueeze(-1)  # (N, 3, 3)
    jac = 1000.0 * (dn - dm_dp @ dp)
    return residual, jac


def _axis_rotation(axis: int, angle: torch.Tensor) -> torch.Tensor:
    from .kinematics import _rotation_matrix

    return _rotation_matrix(axis, angle)
