"""Rigid-body heliostat kinematics: motor steps -> mirror normal and mirror centre, and back.

The model is the "universal" 28-parameter rigid-body chain of Pargmann et al. (paper 000,
section 3.1), laid out like ARTIST's ``RigidBody`` kinematics
(``artist/field/kinematic_rigid_body.py`` in ARTIST-Association/ARTIST). In homogeneous form::

    M(steps) = T(heliostat position) . B
               . Tilt(joint_1) . T(joint_1 translation) . R_axis1(angle_1)
               . Tilt(joint_2) . T(joint_2 translation) . R_axis2(angle_2)
               . T(concentrator translation) . Tilt(concentrator)

    Tilt(x) = R_e(x_tilt_e) . R_n(x_tilt_n) . R_u(x_tilt_u)
    normal   = M . (reference normal, 0)       (unit vector, ENU)
    position = M . (0, 0, 0, 1)                (mirror centre, ENU metres)

``R_e``, ``R_n``, ``R_u`` are *right-handed* rotations about the east, north and up axes of the
parent frame (positive angle = counter-clockwise looking down the axis toward the origin). Angles
come from the actuators (:mod:`heliocal.pipeline.physics.actuators`). ``B`` is the identity except for the
target-aligned type. Everything is batched over heliostats and measurements, float64 (float32
inputs stay float32: the fine model's training, :func:`.actuators.real_tensor`) and
differentiable, and free of in-place operations so that :mod:`torch.func` (``vmap``, ``jacrev``,
``jacfwd``) works on :func:`forward_kinematics`.

Kinematic types (details, degeneracies and presets in ``docs/kinematics.md``):

``juelich``
    PAINT/ARTIST heliostats of the solar tower Juelich: two linear actuators, joint 1 turns about
    east, joint 2 about (its own) up axis, reference normal south ``(0, -1, 0)``. Identical to
    ARTIST's chain (with ARTIST's ``rotate_n`` sign flipped for our tilt_n, see below).
``az-el``
    Azimuth-elevation heliostat with ideal geared drives. Joint 1 = azimuth about up (0 = mirror
    facing south, positive toward east, like the sun azimuth); joint 2 = elevation of the normal
    above the horizon, i.e. a rotation by ``-angle_2`` about the (azimuth-turned) east axis.
    Reference normal south ``(0, -1, 0)``. With no tilts the normal is exactly
    ``(cos el sin az, -cos el cos az, sin el)``.
``target-aligned``
    Spinning-elevation heliostat (paper 003, section 2.1): the primary axis points from the
    heliostat at the target (spec column ``primary_axis_e/n/u``). ``B`` maps the local frame
    ``(e', n', u') = (unit(p x up), p x e', p)`` to ENU. Joint 1 spins about ``u' = p``; joint 2
    tilts the normal away from ``p`` about ``e'`` (for a horizontal ``p`` positive tilt lifts
    the normal). Reference normal ``u' = p``. If ``p`` is vertical, ``e'`` falls back to east.

Tilt sign convention: all tilts are right-handed about the parent-frame axis named in the
parameter. ARTIST's ``rotate_n`` is ``[[c, 0, -s], [0, 1, 0], [s, 0, c]]``, i.e. left-handed, so an
ARTIST ``*_tilt_n`` equals minus our ``*_tilt_n_rad``; ARTIST's ``rotate_e`` and ``rotate_u`` match
ours. ARTIST applies no concentrator tilts; ours act about the mirror centre (they do not move
it).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import ParameterError
from .actuators import (ideal_angle_to_steps, ideal_steps_to_angle, linear_angle_to_steps,
                        linear_steps_to_angle, real_tensor)
from .parameters import JOINT_AXES, PARAMETER_NAMES, REFERENCE_NORMALS, HeliostatSpec
from .vectors import unit_vector

__all__ = [
    "ParameterComponents",
    "rotation_e",
    "rotation_n",
    "rotation_u",
    "joint_angles",
    "forward_kinematics",
    "orientation_matrices",
    "inverse_kinematics",
    "JOINT_SENSES",
    "base_frame",
    "rotation_chain",
    "rotation_matrix",
    "solve_angles",
    "tilt_matrices",
]


def rotation_matrix(axis: int, angle) -> torch.Tensor:
    angle = real_tensor(angle)
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    if axis == 0:
        rows = ((one, zero, zero), (zero, c, -s), (zero, s, c))
    elif axis == 1:
        rows = ((c, zero, s), (zero, one, zero), (-s, zero, c))
    else:
        rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def rotation_e(angle_rad) -> torch.Tensor:
    """Right-handed rotation about east, shape (..., 3, 3): ``[[1,0,0],[0,c,-s],[0,s,c]]``."""
    return rotation_matrix(0, angle_rad)


def rotation_n(angle_rad) -> torch.Tensor:
    """Right-handed rotation about north, shape (..., 3, 3): ``[[c,0,s],[0,1,0],[-s,0,c]]``.

    ARTIST's ``rotate_n(x)`` equals ``rotation_n(-x)``.
    """
    return rotation_matrix(1, angle_rad)


def rotation_u(angle_rad) -> torch.Tensor:
    """Right-handed rotation about up, shape (..., 3, 3): ``[[c,-s,0],[s,c,0],[0,0,1]]``."""
    return rotation_matrix(2, angle_rad)


def _rotate_columns(m: torch.Tensor, axis: int, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Rotate the column vectors of ``m`` (..., 3, K) right-handedly about basis axis ``axis``.

    ``c``, ``s`` are the cosine and sine of the angle, shape (...) broadcastable with
    ``m.shape[:-2]``.
    """
    c = c.unsqueeze(-1)
    s = s.unsqueeze(-1)
    x, y, z = m.unbind(-2)
    if axis == 0:
        rows = (x, c * y - s * z, s * y + c * z)
    elif axis == 1:
        rows = (c * x + s * z, y, c * z - s * x)
    else:
        rows = (c * x - s * y, s * x + c * y, z)
    return torch.stack(torch.broadcast_tensors(*rows), dim=-2)


def _tilt_angles(params: torch.Tensor) -> torch.Tensor:
    """Tilt angles of joint_1, joint_2, concentrator as a view (..., body, e/n/u) [rad].

    The parameter order (:data:`PARAMETER_NAMES`) keeps each body's translation and tilt in
    six consecutive slots, so the per-body blocks are strided *views* of ``params`` (no gather:
    gathers and their scatter backward dominate batched training).
    """
    return params[..., :18].unflatten(-1, (3, 6))[..., 3:]


JOINT_SENSES = {kt: torch.tensor([axes[0][1], axes[1][1]], dtype=torch.float64)
           for kt, axes in JOINT_AXES.items()}


_N0 = {kt: torch.tensor(v, dtype=torch.float64) for kt, v in REFERENCE_NORMALS.items()}


class ParameterComponents(tuple):
    """The 28 parameters as separate tensors, each broadcastable to the batch shape ``(...)``
    of an equivalent (..., 28) ``params`` tensor.

    Accepted wherever the forward kinematics takes ``params``. A parameter that is the same
    for every row can stay (M, 1) while the others are (M, N): the hybrid's fine network moves
    only the free parameters per row, and the kinematics then does no per-row work for the
    rest.
    """

    def __new__(cls, components):
        components = tuple(real_tensor(c) for c in components)
        if len(components) != len(PARAMETER_NAMES):
            raise ParameterError("ParameterComponents needs one tensor per parameter (28). "
                                 f"Got {len(components)} instead.")
        return super().__new__(cls, components)

    def stacked(self) -> torch.Tensor:
        """The equivalent (..., 28) tensor."""
        return torch.stack(torch.broadcast_tensors(*self), dim=-1)


def _components(params) -> tuple:
    """28 tensors of shape (..., 1) (a trailing axis that broadcasts over N rows)."""
    if isinstance(params, ParameterComponents):
        return tuple(c.unsqueeze(-1) for c in params)
    return params.unsqueeze(-1).unbind(-2)


def _check_params(params):
    if isinstance(params, ParameterComponents):
        return params
    if not isinstance(params, torch.Tensor):
        params = torch.as_tensor(np.asarray(params, dtype=np.float64))
    if params.shape[-1:] != (len(PARAMETER_NAMES),):
        raise ParameterError("The 'params' parameter of the kinematics must have a last "
                             f"dimension of 28. Got shape {tuple(params.shape)!r} instead.")
    return params


def _tilt_entries(angle_e, angle_n, angle_u):
    """Entries of ``R_e(angle_e) R_n(angle_n) R_u(angle_u)`` as a nested 3 x 3 tuple of tensors.

    The kinematics works on *components* (one tensor per vector or matrix entry, all of the
    batch shape) rather than on (..., 3, 3) stacks: a batch of tiny matrix products costs far
    more than a few elementwise operations on long contiguous arrays, forward and backward.
    """
    ca, cb, cg = torch.cos(angle_e), torch.cos(angle_n), torch.cos(angle_u)
    sa, sb, sg = torch.sin(angle_e), torch.sin(angle_n), torch.sin(angle_u)
    sasb, casb = sa * sb, ca * sb
    return ((cb * cg, -cb * sg, sb),
            (ca * sg + sasb * cg, ca * cg - sasb * sg, -sa * cb),
            (sa * sg - casb * cg, sa * cg + casb * sg, ca * cb))


def tilt_matrices(params: torch.Tensor) -> torch.Tensor:
    """``R_e(te) R_n(tn) R_u(tu)`` for joint_1, joint_2, concentrator: (..., 3, 3, 3)."""
    entries = _tilt_entries(*_tilt_angles(params).unbind(-1))
    return torch.stack([e for row in entries for e in row], dim=-1).unflatten(-1, (3, 3))


def _matvec(mat, vec):
    """Matrix (nested 3 x 3 tuple of tensors) times vector (3-tuple of tensors or floats)."""
    out = []
    for row in mat:
        acc = None
        for m_ij, v_j in zip(row, vec):
            if isinstance(v_j, float) and v_j == 0.0:
                continue
            term = m_ij * v_j
            acc = term if acc is None else acc + term
        out.append(acc if acc is not None else torch.zeros_like(row[0]))
    return tuple(out)


def _rotate_vec(vec, axis: int, c, s):
    """Rotate the vector ``vec`` (3-tuple of tensors) right-handedly about basis axis ``axis``."""
    x, y, z = vec
    if axis == 0:
        return (x, c * y - s * z, s * y + c * z)
    if axis == 1:
        return (c * x + s * z, y, c * z - s * x)
    return (c * x - s * y, s * x + c * y, z)


def _actuator_values(params: torch.Tensor):
    """(increment, initial_stroke, offset, pivot_radius, initial_angle), each (..., 1, 2)."""
    if isinstance(params, ParameterComponents):
        return tuple(torch.stack(torch.broadcast_tensors(params[18 + f], params[23 + f]), dim=-1)
                     .unsqueeze(-2) for f in range(5))
    return params[..., 18:].unflatten(-1, (2, 5)).transpose(-1, -2).unsqueeze(-3).unbind(-2)


def _clockwise(spec: HeliostatSpec) -> torch.Tensor:
    return spec.clockwise.unsqueeze(-2)


def joint_angles(params, spec: HeliostatSpec, steps) -> torch.Tensor:
    """Joint angles from motor steps through the actuator laws.

    Parameters
    ----------
    params : float64 (..., 28) parameter vectors.
    spec : :class:`HeliostatSpec` (batch shape broadcastable with ``params[..., 0]``).
    steps : (..., N, 2) motor positions of axis 1 and axis 2 [steps].

    Returns
    -------
    torch.Tensor
        (..., N, 2) joint angles [rad].
    """
    params = _check_params(params)
    steps = real_tensor(steps)
    increment, stroke0, offset, radius, angle0 = _actuator_values(params)
    if spec.actuator_type == "ideal":
        return ideal_steps_to_angle(steps, increment, angle0)
    return linear_steps_to_angle(steps, increment, stroke0, offset, radius, angle0, _clockwise(spec))


def _angles_to_steps(params, spec: HeliostatSpec, angles) -> torch.Tensor:
    """Inverse of :func:`joint_angles` (no wrapping, no limit check)."""
    increment, stroke0, offset, radius, angle0 = _actuator_values(params)
    if spec.actuator_type == "ideal":
        return ideal_angle_to_steps(angles, increment, angle0)
    return linear_angle_to_steps(angles, increment, stroke0, offset, radius, angle0, _clockwise(spec))


def base_frame(spec: HeliostatSpec):
    """Matrix (S, 3, 3) with columns (e', n', u') of the local frame in ENU; None = identity."""
    if spec.kinematic_type != "target-aligned":
        return None
    p = spec.primary_axis
    up = torch.tensor([0.0, 0.0, 1.0], dtype=p.dtype).expand_as(p)
    east = torch.tensor([1.0, 0.0, 0.0], dtype=p.dtype).expand_as(p)
    e = torch.linalg.cross(p, up, dim=-1)
    norm = torch.linalg.vector_norm(e, dim=-1, keepdim=True)
    e = torch.where(norm > 1e-9, e / norm.clamp_min(1e-300), east)
    n = torch.linalg.cross(p, e, dim=-1)
    return torch.stack([e, n, p], dim=-1)


def rotation_chain(params, spec: HeliostatSpec, angles, directions=None):
    """Directions and mirror-centre positions (ENU) for joint ``angles`` (..., N, 2).

    ``directions``: local direction vectors as columns (3, K), default the reference normal.
    Returns ((..., N, 3, K) directions, (..., N, 3) positions).

    Evaluated on components (see :func:`_tilt_entries`): every parameter is a (..., 1) tensor
    that broadcasts over the N joint-angle pairs.
    """
    (ax1, _), (ax2, _) = JOINT_AXES[spec.kinematic_type]
    phi = angles * JOINT_SENSES[spec.kinematic_type].to(angles.dtype)
    c1, c2 = torch.cos(phi).unbind(-1)
    s1, s2 = torch.sin(phi).unbind(-1)
    comps = _components(params)                                         # 28 x (..., 1)
    t_1, t_2, t_c = (comps[6 * b:6 * b + 3] for b in range(3))
    tilt_1, tilt_2, tilt_c = (_tilt_entries(*comps[6 * b + 3:6 * b + 6]) for b in range(3))
    if directions is None:
        directions = _N0[spec.kinematic_type].unsqueeze(-1)
    columns = [tuple(float(x) for x in col) for col in directions.T.tolist()]
    vectors = [_matvec(tilt_c, col) for col in columns] + [t_c]        # K directions + centre
    vectors = [_rotate_vec(v, ax2, c2, s2) for v in vectors]
    vectors[-1] = tuple(x + t for x, t in zip(vectors[-1], t_2))
    vectors = [_matvec(tilt_2, v) for v in vectors]
    vectors = [_rotate_vec(v, ax1, c1, s1) for v in vectors]
    vectors[-1] = tuple(x + t for x, t in zip(vectors[-1], t_1))
    vectors = [_matvec(tilt_1, v) for v in vectors]
    frame = base_frame(spec)
    if frame is not None:
        f = [[frame[..., i, j].unsqueeze(-1) for j in range(3)] for i in range(3)]
        vectors = [_matvec(f, v) for v in vectors]
    normals = torch.stack([torch.stack(torch.broadcast_tensors(*v), dim=-1) for v in vectors[:-1]],
                          dim=-1)
    position = spec.position_enu.unsqueeze(-2) + torch.stack(
        torch.broadcast_tensors(*vectors[-1]), dim=-1)
    return normals, position


def forward_kinematics(params, spec: HeliostatSpec, steps) -> tuple[torch.Tensor, torch.Tensor]:
    """Mirror normals and mirror-centre positions for motor steps.

    Parameters
    ----------
    params : float64 (..., 28) parameter vectors (:data:`PARAMETER_NAMES` order); leading
        dimensions batch heliostats (or parameter candidates).
    spec : :class:`HeliostatSpec` whose batch shape broadcasts with ``params.shape[:-1]``.
    steps : (..., N, 2) motor positions [steps] of axis 1 and axis 2.

    Returns
    -------
    normals : torch.Tensor
        (..., N, 3) unit mirror normals, ENU.
    positions : torch.Tensor
        (..., N, 3) mirror-centre (concentrator origin) positions [m], ENU relative to the plant
        reference point.

    Notes
    -----
    Reference (ARTIST ``tests/field/test_kinematic_rigid_body.py``): Juelich type, all
    translations 0 except concentrator n = 0.175 m, clockwise (0, 1), increment 154166.666,
    offset (0.34061, 0.3479), pivot radius (0.3204, 0.309), initial angle (-1.570796, 0.959931),
    initial stroke length 0.075: steps (0, 0) give normal (0.81915, 0, 0.57358) and mirror
    centre (-0.14335, 0, -0.10038).
    """
    params = _check_params(params)
    angles = joint_angles(params, spec, steps)
    normals, positions = rotation_chain(params, spec, angles)
    return normals.squeeze(-1), positions


def orientation_matrices(params, spec: HeliostatSpec, steps) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation matrices (local frame -> ENU) and mirror-centre positions for motor steps.

    Returns
    -------
    rotations : torch.Tensor
        (..., N, 3, 3); ``rotations @ REFERENCE_NORMALS[kinematic_type]`` is the mirror normal.
    positions : torch.Tensor
        (..., N, 3) [m], as in :func:`forward_kinematics`.
    """
    params = _check_params(params)
    angles = joint_angles(params, spec, steps)
    return rotation_chain(params, spec, angles, directions=torch.eye(3, dtype=torch.float64))


def solve_angles(params, spec: HeliostatSpec, normal_enu, branch: int) -> torch.Tensor:
    """Closed-form joint angles (..., N, 2) that turn the reference normal onto ``normal_enu``.

    Two-axis (Paden-Kahan) sub-problem: a rotation about axis 1 keeps the component along
    axis 1, which fixes angle 2 up to two solutions (``branch`` 0 or 1); angle 1 then follows
    from the remaining rotation about axis 1. Exact for any tilts (translations do not turn
    normals). Rows without a solution are NaN.
    """
    (ax1, sense1), (ax2, sense2) = JOINT_AXES[spec.kinematic_type]
    tilt_1, tilt_2, tilt_c = tilt_matrices(params).unbind(-3)
    frame = base_frame(spec)
    outer = tilt_1 if frame is None else frame @ tilt_1
    v = (outer.unsqueeze(-3).transpose(-1, -2) @ normal_enu.unsqueeze(-1)).squeeze(-1)
    c = (tilt_c @ _N0[spec.kinematic_type]).unsqueeze(-2)              # (..., 1, 3)
    eye = torch.eye(3, dtype=torch.float64)
    k1, k2 = eye[ax1], eye[ax2]
    k1p = (tilt_2.transpose(-1, -2) @ k1).unsqueeze(-2)                 # axis 1 in joint-2 frame
    c_par = c[..., ax2:ax2 + 1] * k2
    c_perp = c - c_par
    c_cross = torch.linalg.cross(k2.expand_as(c), c, dim=-1)
    a = (k1p * c_perp).sum(-1)
    b = (k1p * c_cross).sum(-1)
    d = v[..., ax1] - (k1p * c_par).sum(-1)
    ratio = d / torch.sqrt(a**2 + b**2)
    ratio = torch.where(ratio.abs() <= 1.0 + 1e-12, ratio.clamp(-1.0, 1.0), torch.nan)
    phi2 = torch.atan2(b, a) + (1.0 if branch == 0 else -1.0) * torch.arccos(ratio)
    rotated = _rotate_columns(c.unsqueeze(-1), ax2, torch.cos(phi2), torch.sin(phi2))
    w = (tilt_2.unsqueeze(-3) @ rotated).squeeze(-1)                    # (..., N, 3)
    k1w = k1.expand_as(w)
    phi1 = torch.atan2((k1w * torch.linalg.cross(w, v, dim=-1)).sum(-1),
                       (w * v).sum(-1) - w[..., ax1] * v[..., ax1])
    return torch.stack([phi1 / sense1, phi2 / sense2], dim=-1)


def _wrap_to(angle, centre):
    """``angle`` plus a multiple of 2 pi, within pi of ``centre``."""
    return angle + 2.0 * math.pi * torch.round((centre - angle) / (2.0 * math.pi))


def inverse_kinematics(params, spec: HeliostatSpec, sun_vector_enu, aim_point_enu, *,
                       return_both: bool = False, max_iterations: int = 100,
                       tolerance_m: float = 1e-12):
    """Motor steps that reflect the sun from the mirror centre onto the aim point.

    The wanted normal is the bisector of the sun direction and the direction from the mirror
    centre to the aim point; the mirror centre moves with the orientation, so the closed-form
    two-axis solution is iterated (fixed point on the mirror centre, contraction ~ lever arm /
    distance to the aim point) until the centre moves less than ``tolerance_m``. Each of the two
    solution branches is iterated on its own. Not differentiable (runs under ``no_grad``).

    Parameters
    ----------
    params : float64 (..., 28) parameter vectors.
    spec : :class:`HeliostatSpec`.
    sun_vector_enu : (..., N, 3) unit vectors from the heliostat toward the sun (normalised
        here).
    aim_point_enu : (..., N, 3) or (3,) aim points [m] ENU.
    return_both : if True return both branches and their validity instead of one choice.
    max_iterations : cap on the fixed-point iterations.
    tolerance_m : convergence threshold on the mirror-centre update [m].

    Returns
    -------
    steps : torch.Tensor
        (..., N, 2) motor steps (real-valued). Where both branches are within the actuator limits
        the one nearest the middle of the step ranges is returned (smallest sum of squared
        distances to the range centres, each in units of the half range); where exactly one is,
        that one; where none is (no solution, unreachable linear-actuator angle, or outside the
        limits) the row is NaN.
    If ``return_both``: ``(steps_both, within_limits)`` with shapes (..., N, 2 branches, 2 axes)
    and (..., N, 2 branches) instead.
    """
    params = _check_params(params)
    with torch.no_grad():
        params = params.detach()
        sun = unit_vector(torch.as_tensor(sun_vector_enu, dtype=torch.float64))
        aim = torch.as_tensor(aim_point_enu, dtype=torch.float64)
        sun, aim = torch.broadcast_tensors(sun, aim)
        low = torch.nan_to_num(spec.min_steps, nan=-math.inf)
        high = torch.nan_to_num(spec.max_steps, nan=math.inf)
        bounded = torch.isfinite(low) & torch.isfinite(high)
        centre = torch.where(bounded, 0.5 * (low + high), torch.zeros_like(low))
        half = torch.where(bounded, (0.5 * (high - low)).clamp_min(1.0), torch.full_like(low, 1e12))
        centre_angles = joint_angles(params, spec, centre.unsqueeze(-2))     # (..., 1, 2)
        _, start = rotation_chain(params, spec, centre_angles)
        start = start.expand_as(sun)

        results, valid = [], []
        for branch in (0, 1):
            position = start
            angles = None
            for _ in range(max_iterations):
                wanted = unit_vector(sun + unit_vector(aim - position))
                angles = solve_angles(params, spec, wanted, branch)
                _, new_position = rotation_chain(params, spec, angles)
                step = torch.linalg.vector_norm(new_position - position, dim=-1)
                position = new_position
                if not bool(torch.any(step > tolerance_m)):
                    break
            angles = _wrap_to(angles, centre_angles)
            steps = _angles_to_steps(params, spec, angles)
            back = joint_angles(params, spec, steps)
            ok = (torch.isfinite(steps).all(-1)
                  & ((back - angles).abs() < 1e-9).all(-1)
                  & (steps >= low.unsqueeze(-2) - 1e-6).all(-1)
                  & (steps <= high.unsqueeze(-2) + 1e-6).all(-1))
            results.append(steps)
            valid.append(ok)
        both = torch.stack(results, dim=-2)
        within = torch.stack(valid, dim=-1)
        if return_both:
            return both, within
        score = (((both - centre.unsqueeze(-2).unsqueeze(-2)) / half.unsqueeze(-2).unsqueeze(-2)) ** 2).sum(-1)
        score = torch.where(within, torch.nan_to_num(score, nan=math.inf), math.inf)
        pick = torch.argmin(score, dim=-1, keepdim=True)                    # (..., N, 1)
        chosen = torch.gather(both, -2, pick.unsqueeze(-1).expand(*pick.shape, 2)).squeeze(-2)
        any_ok = within.any(-1, keepdim=True)
        return torch.where(any_ok, chosen, torch.nan)
