"""Exact residuals and Jacobian of the coarse fit, from the chain's geometry (no finite differences).

Autodiff through :func:`~heliocal.pipeline.physics.kinematics.forward_kinematics` (``torch.func.jacfwd``)
costs about 10 ms per Jacobian on 300 measurements, dominated by per-operation overhead. The
Jacobian of a rigid-body chain has a closed form (the robot manipulator's *geometric Jacobian*),
which this module evaluates with a handful of batched tensor operations:

* a rotation by angle ``phi`` about a world-frame unit axis ``w`` through the point ``o`` moves
  the mirror normal by ``dn/dphi = w x n`` and the mirror centre by ``dP/dphi = w x (P - o)``;
* a translation along a world-frame direction ``d`` moves the centre by ``dP/dt = d`` and leaves
  the normal alone;
* the actuator parameters act through the joint angles: ``dn/dq = (w_i x n) s_i dtheta_i/dq``,
  with ``dtheta_i/dq`` from torch autograd through the (elementwise) actuator law.

The chain (see :mod:`heliocal.pipeline.physics.kinematics`) is, for the mirror centre ``P`` and normal
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

from .parameters import PARAMETER_INDEX, HeliostatSpec, JOINT_AXES
from .kinematics import JOINT_SENSES, base_frame, rotation_chain, tilt_matrices, joint_angles
from .metrics import measured_normal

__all__ = ["residual_and_jacobian", "forward_state"]

def forward_state(params: torch.Tensor, spec: HeliostatSpec, steps: torch.Tensor):
    """Joint angles (N, 2), mirror normals (N, 3) and centres (N, 3): the forward pass that
    :func:`residual_and_jacobian` builds on (pass it back as ``state`` to avoid recomputing)."""
    angles = joint_angles(params, spec, steps)
    normal, position = rotation_chain(params, spec, angles)
    return angles, normal.squeeze(-1), position


def residual_and_jacobian(params: torch.Tensor, spec: HeliostatSpec, steps: torch.Tensor,
                          sun: torch.Tensor, focal_spot: torch.Tensor, state=None):
    """Residuals ``1000 (n_pred - n_meas)`` [mrad] and their exact Jacobian.

    Every tensor may carry a leading batch shape ``S`` (heliostats of one kinematic and actuator
    type, e.g. ``S = (H,)``, as :func:`heliocal.pipeline.physics.lm.solve_batched` uses it); ``S = ()``
    is one heliostat.

    Parameters
    ----------
    params : (*S, 28) parameter vector(s).
    spec : the heliostat(s) (batch shape ``S`` or ``()``).
    steps : (*S, N, 2) motor steps; sun : (*S, N, 3) unit sun vectors; focal_spot : (*S, N, 3)
        [m] ENU.
    state : :func:`forward_state` at ``params``, if already computed.

    Returns
    -------
    residual : (*S, N, 3) [mrad]
    jacobian : (*S, N, 3, 28) [mrad per parameter unit], columns in PARAMETER_NAMES order.
    """
    params = params.detach()
    batch = params.shape[:-1]
    n_meas = steps.shape[-2]
    kt = spec.kinematic_type
    (ax1, _), (ax2, _) = JOINT_AXES[kt]
    senses = JOINT_SENSES[kt]

    # joint angles and their derivatives w.r.t. the actuator parameters (closed form)
    angles, normal, position = state if state is not None else forward_state(params, spec, steps)
    dtheta = _actuator_derivatives(params, spec, steps)

    meas = measured_normal(sun, position, focal_spot)
    residual = 1000.0 * (normal - meas)

    tilts = tilt_matrices(params)  # (*S, 3 bodies, 3, 3)
    tilt_1, tilt_2, _ = tilts.unbind(-3)
    t_idx = [[PARAMETER_INDEX[f"{b}_translation_{d}_m"] for d in "enu"]
             for b in ("joint_1", "joint_2", "concentrator")]
    r_idx = [[PARAMETER_INDEX[f"{b}_tilt_{d}_rad"] for d in "enu"]
             for b in ("joint_1", "joint_2", "concentrator")]
    t1, t2 = params[..., t_idx[0]], params[..., t_idx[1]]  # (*S, 3)

    frame = base_frame(spec)
    a0 = torch.eye(3, dtype=torch.float64) if frame is None else frame
    a1 = a0 @ tilt_1  # (*S, 3, 3), same for all measurements
    phi = angles * senses  # (*S, N, 2)
    r1 = _axis_rotation(ax1, phi[..., 0])  # (*S, N, 3, 3)
    r2 = _axis_rotation(ax2, phi[..., 1])
    a2 = a1.unsqueeze(-3) @ r1  # (*S, N, 3, 3)
    a3 = a2 @ tilt_2.unsqueeze(-3)
    a4 = a3 @ r2

    pos0 = spec.position_enu.expand(*batch, 3)
    o1 = pos0 + (a1 @ t1.unsqueeze(-1)).squeeze(-1)  # (*S, 3) pivot of joint 1 and of joint-2 tilts
    o2 = o1.unsqueeze(-2) + (a3 @ t2[..., None, :, None]).squeeze(-1)  # (*S, N, 3) pivot of joint 2

    def per_measurement(v: torch.Tensor) -> torch.Tensor:
        """(*S, 3) or (*S, N, 3) -> (*S, N, 3)."""
        if v.dim() == len(batch) + 1:
            v = v.unsqueeze(-2)
        return v.expand(*batch, n_meas, 3)

    # every rotation parameter: (index, world axis, pivot or None); every translation: (index,
    # world direction); evaluated together with one batched cross product
    rot_idx, rot_axes, rot_pivots, rot_moves = [], [], [], []

    def rotation(idx: int, axis: torch.Tensor, pivot: torch.Tensor | None) -> None:
        rot_idx.append(idx)
        rot_axes.append(per_measurement(axis))
        rot_pivots.append(per_measurement(pivot if pivot is not None else pos0))
        rot_moves.append(pivot is not None)

    # Tilt(x) = R_e(x_e) R_n(x_n) R_u(x_u) after a prefix P: the three rotation axes in world
    # coordinates are P e, P R_e(x_e) n = P (0, cos x_e, sin x_e) and P Tilt u (R_u keeps u)
    def tilt_axes(prefix, tilt, angle_e):
        rolled_n = torch.stack([torch.zeros_like(angle_e), torch.cos(angle_e), torch.sin(angle_e)],
                               dim=-1)  # (*S, 3)
        per_row = prefix.dim() == len(batch) + 3  # prefix (*S, N, 3, 3)
        if per_row:
            rolled_n, tilt = rolled_n.unsqueeze(-2), tilt.unsqueeze(-3)
        return (prefix[..., 0], (prefix @ rolled_n.unsqueeze(-1)).squeeze(-1),
                (prefix @ tilt)[..., 2])

    # joint-1 tilts: rotate everything about the heliostat position
    for k, ax in enumerate(tilt_axes(a0, tilt_1, params[..., r_idx[0][0]])):
        rotation(r_idx[0][k], ax, pos0)
    # joint-2 tilts: about o1, axes after joint 1's rotation
    for k, ax in enumerate(tilt_axes(a2, tilt_2, params[..., r_idx[1][0]])):
        rotation(r_idx[1][k], ax, o1)
    # concentrator tilts: turn the mirror about its centre (normal only)
    for k, ax in enumerate(tilt_axes(a4, tilts[..., 2, :, :], params[..., r_idx[2][0]])):
        rotation(r_idx[2][k], ax, None)
    axes = torch.stack(rot_axes)  # (K, *S, N, 3)
    pivots = torch.stack(rot_pivots)
    moves = torch.tensor(rot_moves, dtype=torch.float64).view(-1, *([1] * (len(batch) + 2)))
    dn_rot = torch.linalg.cross(axes, normal.expand_as(axes), dim=-1)
    dp_rot = torch.linalg.cross(axes, position - pivots, dim=-1) * moves
    # translations: joint 1 (frame a1), joint 2 (frame a3), concentrator (frame a4)
    trans_idx = t_idx[0] + t_idx[1] + t_idx[2]
    dirs = torch.cat([a1.movedim(-1, 0).unsqueeze(-2).expand(3, *batch, n_meas, 3),
                      a3.movedim(-1, 0), a4.movedim(-1, 0)])  # (9, *S, N, 3): column k of each frame
    dn = torch.zeros(*batch, n_meas, 3, 28, dtype=torch.float64)
    dp = torch.zeros(*batch, n_meas, 3, 28, dtype=torch.float64)
    dn[..., rot_idx] = dn_rot.movedim(0, -1)
    dp[..., rot_idx] = dp_rot.movedim(0, -1)
    dp[..., trans_idx] = dirs.movedim(0, -1)
    # joints: through the actuator laws
    w1 = per_measurement(a1[..., ax1])
    w2 = a3[..., ax2]
    dn_dphi1 = torch.linalg.cross(w1, normal, dim=-1)
    dp_dphi1 = torch.linalg.cross(w1, position - o1.unsqueeze(-2), dim=-1)
    dn_dphi2 = torch.linalg.cross(w2, normal, dim=-1)
    dp_dphi2 = torch.linalg.cross(w2, position - o2, dim=-1)
    g1 = dtheta[0] * senses[0]  # (*S, N, 28) dphi1/dq
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
    dm_dp = -(proj_m @ proj_u) / (norm_su * dist).unsqueeze(-1)  # (*S, N, 3, 3)
    jac = 1000.0 * (dn - dm_dp @ dp)
    return residual, jac


def _actuator_derivatives(params: torch.Tensor, spec: HeliostatSpec, steps: torch.Tensor):
    """d(joint angle i)/d(parameters), closed form, as a list of two (*S, N, 28) tensors.

    Ideal: ``theta = steps / g + theta0``. Linear (law of cosines, see
    :func:`heliocal.pipeline.physics.actuators.linear_steps_to_angle`):
    ``theta = theta0 + sigma (A(s0) - A(s))``, ``s = steps / inc + s0``,
    ``A(x) = arccos(c(x))``, ``c(x) = (o^2 + r^2 - x^2) / (2 o r)``; where the cosine is clamped
    (a stroke that cannot close the triangle) the derivative is 0, as in the forward model.
    """
    from .actuators import actuator_sign

    shape = steps.shape[:-1]  # (*S, N)
    out = []

    def value(name: str) -> torch.Tensor:  # (*S, 1): broadcasts over the measurements
        return params[..., PARAMETER_INDEX[name]].unsqueeze(-1)

    for i in (1, 2):
        d = torch.zeros(*shape, 28, dtype=torch.float64)
        st = steps[..., i - 1]
        inc = value(f"axis_{i}_increment")
        d[..., PARAMETER_INDEX[f"axis_{i}_initial_angle_rad"]] = 1.0
        if spec.actuator_type == "ideal":
            d[..., PARAMETER_INDEX[f"axis_{i}_increment"]] = -st / inc**2
            out.append(d)
            continue
        s0 = value(f"axis_{i}_initial_stroke_length_m")
        o = value(f"axis_{i}_offset_m")
        r = value(f"axis_{i}_pivot_radius_m")
        sigma = actuator_sign(spec.clockwise[..., i - 1]).unsqueeze(-1)

        def parts(x):
            c = (o**2 + r**2 - x**2) / (2.0 * o * r)
            inside = c.abs() < 1.0
            da_dc = torch.where(inside, -1.0 / torch.sqrt(torch.clamp(1.0 - c**2, min=1e-300)),
                                torch.zeros_like(c))
            dc_dx = -x / (o * r)
            dc_do = (o**2 - r**2 + x**2) / (2.0 * o**2 * r)
            dc_dr = (r**2 - o**2 + x**2) / (2.0 * o * r**2)
            return da_dc * dc_dx, da_dc * dc_do, da_dc * dc_dr

        x = st / inc + s0
        ax, ao, ar = parts(x)
        bx, bo, br = parts(s0)
        d[..., PARAMETER_INDEX[f"axis_{i}_increment"]] = -sigma * ax * (-st / inc**2)
        d[..., PARAMETER_INDEX[f"axis_{i}_initial_stroke_length_m"]] = sigma * (bx - ax)
        d[..., PARAMETER_INDEX[f"axis_{i}_offset_m"]] = sigma * (bo - ao)
        d[..., PARAMETER_INDEX[f"axis_{i}_pivot_radius_m"]] = sigma * (br - ar)
        out.append(d)
    return out


def _axis_rotation(axis: int, angle: torch.Tensor) -> torch.Tensor:
    from .kinematics import rotation_matrix

    return rotation_matrix(axis, angle)
