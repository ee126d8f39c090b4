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

from dataclasses import dataclass

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
    # joint angles and their derivatives w.r.t. the actuator parameters (closed form)
    angles, normal, position = state if state is not None else forward_state(params, spec, steps)
    dtheta = _actuator_derivatives(params, spec, steps)

    meas = measured_normal(sun, position, focal_spot)
    residual = 1000.0 * (normal - meas)

    chain = _chain_frames(params, spec, angles)
    dn, dp = _body_columns(params, chain, normal, position)
    dn, dp = _joint_columns(dn, dp, chain, dtheta, normal, position)
    jac = 1000.0 * (dn - _measured_normal_by_centre(sun, position, focal_spot, meas) @ dp)
    return residual, jac


#: Parameter indices of each body's (joint 1, joint 2, concentrator) translation e/n/u [m] and
#: tilt e/n/u [rad].
_TRANSLATION_INDEX = [[PARAMETER_INDEX[f"{b}_translation_{d}_m"] for d in "enu"]
                      for b in ("joint_1", "joint_2", "concentrator")]
_TILT_INDEX = [[PARAMETER_INDEX[f"{b}_tilt_{d}_rad"] for d in "enu"]
               for b in ("joint_1", "joint_2", "concentrator")]


@dataclass
class _Chain:
    """The chain's frames in world coordinates: ``a0`` the base frame, ``a1 = a0 Tilt1``,
    ``a2 = a1 R1``, ``a3 = a2 Tilt2``, ``a4 = a3 R2`` (a0, a1: (*S, 3, 3); the others per
    measurement (*S, N, 3, 3)); the pivots ``pos0`` (heliostat position), ``o1`` (joint 1 and
    the joint-2 tilts, (*S, 3)), ``o2`` (joint 2, (*S, N, 3)); ``tilts`` (*S, 3 bodies, 3, 3)."""

    spec: HeliostatSpec
    batch: tuple                # the leading batch shape S
    n_meas: int
    tilts: torch.Tensor
    a0: torch.Tensor
    a1: torch.Tensor
    a2: torch.Tensor
    a3: torch.Tensor
    a4: torch.Tensor
    pos0: torch.Tensor
    o1: torch.Tensor
    o2: torch.Tensor

    def per_measurement(self, v: torch.Tensor) -> torch.Tensor:
        """(*S, 3) or (*S, N, 3) -> (*S, N, 3)."""
        if v.dim() == len(self.batch) + 1:
            v = v.unsqueeze(-2)
        return v.expand(*self.batch, self.n_meas, 3)


def _chain_frames(params: torch.Tensor, spec: HeliostatSpec, angles: torch.Tensor) -> _Chain:
    batch = params.shape[:-1]
    kt = spec.kinematic_type
    (ax1, _), (ax2, _) = JOINT_AXES[kt]
    tilts = tilt_matrices(params)  # (*S, 3 bodies, 3, 3)
    tilt_1, tilt_2, _ = tilts.unbind(-3)
    t1, t2 = params[..., _TRANSLATION_INDEX[0]], params[..., _TRANSLATION_INDEX[1]]  # (*S, 3)
    frame = base_frame(spec)
    a0 = torch.eye(3, dtype=torch.float64) if frame is None else frame
    a1 = a0 @ tilt_1  # (*S, 3, 3), same for all measurements
    phi = angles * JOINT_SENSES[kt]  # (*S, N, 2)
    r1 = _axis_rotation(ax1, phi[..., 0])  # (*S, N, 3, 3)
    r2 = _axis_rotation(ax2, phi[..., 1])
    a2 = a1.unsqueeze(-3) @ r1  # (*S, N, 3, 3)
    a3 = a2 @ tilt_2.unsqueeze(-3)
    a4 = a3 @ r2
    pos0 = spec.position_enu.expand(*batch, 3)
    o1 = pos0 + (a1 @ t1.unsqueeze(-1)).squeeze(-1)  # (*S, 3) pivot of joint 1 and of joint-2 tilts
    o2 = o1.unsqueeze(-2) + (a3 @ t2[..., None, :, None]).squeeze(-1)  # (*S, N, 3) pivot of joint 2
    return _Chain(spec, batch, angles.shape[-2], tilts, a0, a1, a2, a3, a4, pos0, o1, o2)


def _tilt_axes(prefix: torch.Tensor, tilt: torch.Tensor, angle_e: torch.Tensor, batch: tuple):
    """The world axes of Tilt(x) = R_e(x_e) R_n(x_n) R_u(x_u) after a prefix P: P e,
    P R_e(x_e) n = P (0, cos x_e, sin x_e) and P Tilt u (R_u keeps u)."""
    rolled_n = torch.stack([torch.zeros_like(angle_e), torch.cos(angle_e), torch.sin(angle_e)],
                           dim=-1)  # (*S, 3)
    per_row = prefix.dim() == len(batch) + 3  # prefix (*S, N, 3, 3)
    if per_row:
        rolled_n, tilt = rolled_n.unsqueeze(-2), tilt.unsqueeze(-3)
    return (prefix[..., 0], (prefix @ rolled_n.unsqueeze(-1)).squeeze(-1),
            (prefix @ tilt)[..., 2])


def _body_columns(params: torch.Tensor, c: _Chain, normal: torch.Tensor,
                  position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """d(normal)/d(parameters) and d(centre)/d(parameters), (*S, N, 3, 28) each, with the
    columns of the bodies' tilts and translations filled (the joints' come later)."""
    batch, n_meas = c.batch, c.n_meas
    # every rotation parameter: (index, world axis, pivot or None), evaluated together with one
    # batched cross product
    rot_idx, rot_axes, rot_pivots, rot_moves = [], [], [], []

    def rotation(idx: int, axis: torch.Tensor, pivot: torch.Tensor | None) -> None:
        rot_idx.append(idx)
        rot_axes.append(c.per_measurement(axis))
        rot_pivots.append(c.per_measurement(pivot if pivot is not None else c.pos0))
        rot_moves.append(pivot is not None)

    tilt_1, tilt_2, tilt_c = c.tilts.unbind(-3)
    # joint-1 tilts: rotate everything about the heliostat position
    for k, ax in enumerate(_tilt_axes(c.a0, tilt_1, params[..., _TILT_INDEX[0][0]], batch)):
        rotation(_TILT_INDEX[0][k], ax, c.pos0)
    # joint-2 tilts: about o1, axes after joint 1's rotation
    for k, ax in enumerate(_tilt_axes(c.a2, tilt_2, params[..., _TILT_INDEX[1][0]], batch)):
        rotation(_TILT_INDEX[1][k], ax, c.o1)
    # concentrator tilts: turn the mirror about its centre (normal only)
    for k, ax in enumerate(_tilt_axes(c.a4, tilt_c, params[..., _TILT_INDEX[2][0]], batch)):
        rotation(_TILT_INDEX[2][k], ax, None)
    axes = torch.stack(rot_axes)  # (K, *S, N, 3)
    pivots = torch.stack(rot_pivots)
    moves = torch.tensor(rot_moves, dtype=torch.float64).view(-1, *([1] * (len(batch) + 2)))
    dn_rot = torch.linalg.cross(axes, normal.expand_as(axes), dim=-1)
    dp_rot = torch.linalg.cross(axes, position - pivots, dim=-1) * moves
    # translations: joint 1 (frame a1), joint 2 (frame a3), concentrator (frame a4)
    trans_idx = _TRANSLATION_INDEX[0] + _TRANSLATION_INDEX[1] + _TRANSLATION_INDEX[2]
    dirs = torch.cat([c.a1.movedim(-1, 0).unsqueeze(-2).expand(3, *batch, n_meas, 3),
                      c.a3.movedim(-1, 0), c.a4.movedim(-1, 0)])  # (9, *S, N, 3): column k of each frame
    dn = torch.zeros(*batch, n_meas, 3, 28, dtype=torch.float64)
    dp = torch.zeros(*batch, n_meas, 3, 28, dtype=torch.float64)
    dn[..., rot_idx] = dn_rot.movedim(0, -1)
    dp[..., rot_idx] = dp_rot.movedim(0, -1)
    dp[..., trans_idx] = dirs.movedim(0, -1)
    return dn, dp


def _joint_columns(dn: torch.Tensor, dp: torch.Tensor, c: _Chain, dtheta, normal: torch.Tensor,
                   position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``dn``, ``dp`` plus what every parameter moves through the joint angles (the actuator
    laws' derivatives ``dtheta``)."""
    kt = c.spec.kinematic_type
    (ax1, _), (ax2, _) = JOINT_AXES[kt]
    senses = JOINT_SENSES[kt]
    w1 = c.per_measurement(c.a1[..., ax1])
    w2 = c.a3[..., ax2]
    dn_dphi1 = torch.linalg.cross(w1, normal, dim=-1)
    dp_dphi1 = torch.linalg.cross(w1, position - c.o1.unsqueeze(-2), dim=-1)
    dn_dphi2 = torch.linalg.cross(w2, normal, dim=-1)
    dp_dphi2 = torch.linalg.cross(w2, position - c.o2, dim=-1)
    g1 = dtheta[0] * senses[0]  # (*S, N, 28) dphi1/dq
    g2 = dtheta[1] * senses[1]
    dn = dn + dn_dphi1.unsqueeze(-1) * g1.unsqueeze(-2) + dn_dphi2.unsqueeze(-1) * g2.unsqueeze(-2)
    dp = dp + dp_dphi1.unsqueeze(-1) * g1.unsqueeze(-2) + dp_dphi2.unsqueeze(-1) * g2.unsqueeze(-2)
    return dn, dp


def _measured_normal_by_centre(sun: torch.Tensor, position: torch.Tensor,
                               focal_spot: torch.Tensor, meas: torch.Tensor) -> torch.Tensor:
    """d(measured normal)/d(mirror centre) (*S, N, 3, 3):
    ``-(I - m m^T)(I - u u^T) / (|s + u| |f - P|)`` with ``u = unit(f - P)``."""
    v = focal_spot - position
    dist = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    u = v / dist
    s_plus_u = sun + u
    norm_su = torch.linalg.vector_norm(s_plus_u, dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    proj_u = eye - u.unsqueeze(-1) * u.unsqueeze(-2)
    proj_m = eye - meas.unsqueeze(-1) * meas.unsqueeze(-2)
    return -(proj_m @ proj_u) / (norm_su * dist).unsqueeze(-1)


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
