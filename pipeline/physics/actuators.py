"""Actuator laws: motor steps <-> joint angles, in torch (float64, differentiable, batched).

Two actuator types are modelled, both following ARTIST's conventions
(``artist/field/actuators_linear.py``, ``artist/field/actuators_ideal.py`` in
ARTIST-Association/ARTIST):

``ideal``
    A geared rotary drive: ``angle = steps / gear_ratio + angle_offset``.

``linear``
    A linear actuator (spindle) that pushes a lever. The stroke length follows the motor
    linearly, ``stroke = steps / increment + initial_stroke_length``; the lever angle
    follows from the triangle (actuator pivot, joint axis, lever pin) with the law of cosines::

        absolute_angle(steps) = arccos((offset**2 + pivot_radius**2 - stroke**2)
                                       / (2 * offset * pivot_radius))
        delta = absolute_angle(0) - absolute_angle(steps)
        angle = initial_angle + delta   if clockwise
                initial_angle - delta   otherwise

    so ``initial_angle`` is the joint angle at 0 steps and ``clockwise`` flips the sense in
    which a growing stroke turns the joint.

All functions broadcast over leading dimensions; every argument may be a tensor or a Python
number. Gradients flow to every float argument (not to the ``clockwise`` flag). No function
uses in-place operations, so all of them work under :mod:`torch.func` (``vmap``, ``jacrev``,
``jacfwd``).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "ACTUATOR_TYPES",
    "ideal_steps_to_angle",
    "ideal_angle_to_steps",
    "linear_steps_to_angle",
    "linear_angle_to_steps",
    "linear_stroke_length",
    "actuator_sign",
    "real_tensor",
]

ACTUATOR_TYPES = ("linear", "ideal")
"""Actuator types understood by :mod:`heliocal.pipeline.physics.kinematics`."""


def real_tensor(x, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Return ``x`` as a floating-point tensor: a float32 or float64 tensor keeps its dtype and
    graph; anything else (numbers, arrays, integer or bool tensors) becomes ``dtype``.

    The physics is float64 by convention; only the fine model's training feeds it float32
    tensors (``FineConfig.training_dtype``, docs/hybrid.md "Training precision"), and then every
    intermediate stays float32.
    """
    if isinstance(x, torch.Tensor):
        return x if x.dtype in (torch.float32, torch.float64) else x.to(dtype)
    # through numpy, which also reads pandas objects (a DataFrame's values, a Series)
    return torch.as_tensor(np.asarray(x, dtype=np.float32 if dtype == torch.float32 else np.float64))


_t = real_tensor


def actuator_sign(clockwise, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """+1 for clockwise, -1 otherwise (``dtype``, broadcastable)."""
    cw = clockwise if isinstance(clockwise, torch.Tensor) else torch.as_tensor(clockwise)
    return torch.where(cw.to(torch.bool), 1.0, -1.0).to(dtype)


def ideal_steps_to_angle(steps, gear_ratio_steps_per_rad, angle_offset_rad) -> torch.Tensor:
    """Joint angle of an ideal geared actuator.

    Parameters
    ----------
    steps : motor position [steps].
    gear_ratio_steps_per_rad : gear ratio [steps/rad].
    angle_offset_rad : joint angle at 0 steps [rad].

    Returns
    -------
    torch.Tensor
        ``steps / gear_ratio + angle_offset`` [rad], broadcast shape of the inputs.
    """
    return _t(steps) / _t(gear_ratio_steps_per_rad) + _t(angle_offset_rad)


def ideal_angle_to_steps(angle_rad, gear_ratio_steps_per_rad, angle_offset_rad) -> torch.Tensor:
    """Motor position of an ideal geared actuator; inverse of :func:`ideal_steps_to_angle`.

    Parameters
    ----------
    angle_rad : joint angle [rad] (not wrapped: add multiples of 2 pi before calling if needed).
    gear_ratio_steps_per_rad : gear ratio [steps/rad].
    angle_offset_rad : joint angle at 0 steps [rad].

    Returns
    -------
    torch.Tensor
        ``(angle - angle_offset) * gear_ratio`` [steps] (real-valued, not rounded).
    """
    return (_t(angle_rad) - _t(angle_offset_rad)) * _t(gear_ratio_steps_per_rad)


def linear_stroke_length(steps, increment_steps_per_m, initial_stroke_length_m) -> torch.Tensor:
    """Stroke length of a linear actuator: ``steps / increment + initial_stroke_length`` [m].

    Parameters
    ----------
    steps : motor position [steps].
    increment_steps_per_m : motor steps per metre of stroke [steps/m] (PAINT's ``increment``).
    initial_stroke_length_m : stroke length at 0 steps [m].
    """
    return _t(steps) / _t(increment_steps_per_m) + _t(initial_stroke_length_m)


def _absolute_angle(stroke_m, offset_m, pivot_radius_m) -> torch.Tensor:
    """Lever angle opposite the stroke in the (offset, pivot radius, stroke) triangle [rad].

    The cosine is clamped to [-1, 1] as in ARTIST, so a stroke that cannot close the triangle
    gives 0 or pi (with zero gradient) rather than NaN.
    """
    cos_angle = (offset_m**2 + pivot_radius_m**2 - stroke_m**2) / (2.0 * offset_m * pivot_radius_m)
    return torch.arccos(torch.clamp(cos_angle, -1.0, 1.0))


def linear_steps_to_angle(steps, increment_steps_per_m, initial_stroke_length_m, offset_m,
                          pivot_radius_m, initial_angle_rad, clockwise) -> torch.Tensor:
    """Joint angle of a linear actuator (ARTIST's law of cosines).

    Parameters
    ----------
    steps : motor position [steps].
    increment_steps_per_m : motor steps per metre of stroke [steps/m].
    initial_stroke_length_m : stroke length at 0 steps [m].
    offset_m : distance from the joint axis to the actuator's fixed pivot [m].
    pivot_radius_m : distance from the joint axis to the point where the actuator pushes [m].
    initial_angle_rad : joint angle at 0 steps [rad], in ARTIST's internal convention (for the
        Juelich axis 1 that is PAINT's ``initial_angle`` minus pi/2; ingest applies it).
    clockwise : bool (or bool tensor): True if a longer stroke increases the joint angle
        (PAINT's ``clockwise_axis_movement`` = 1).

    Returns
    -------
    torch.Tensor
        Joint angle [rad], broadcast shape of the inputs.

    Notes
    -----
    Reference (ARTIST test ``tests/field/test_actuators.py``): clockwise (0, 1), increment
    1.5417e5, offset (0.33531, 0.34077), pivot radius (0.3381, 0.3191), initial angle
    (-1.5318, 0.94392), initial stroke length (0.077413, 0.077522): steps (28061, 47874) give
    (-0.971173584461, -0.085735797882) rad.
    """
    offset_m = _t(offset_m)
    pivot_radius_m = _t(pivot_radius_m)
    increment = _t(increment_steps_per_m)
    initial_stroke = _t(initial_stroke_length_m)
    absolute = _absolute_angle(linear_stroke_length(steps, increment, initial_stroke),
                               offset_m, pivot_radius_m)
    absolute_initial = _absolute_angle(initial_stroke, offset_m, pivot_radius_m)
    delta = absolute_initial - absolute
    return _t(initial_angle_rad) + actuator_sign(clockwise, delta.dtype) * delta


def linear_angle_to_steps(angle_rad, increment_steps_per_m, initial_stroke_length_m, offset_m,
                          pivot_radius_m, initial_angle_rad, clockwise) -> torch.Tensor:
    """Motor position of a linear actuator; inverse of :func:`linear_steps_to_angle`.

    Parameters are those of :func:`linear_steps_to_angle`, with ``angle_rad`` the joint angle
    [rad] instead of the steps.

    Returns
    -------
    torch.Tensor
        Motor position [steps] (real-valued, not rounded).

    Notes
    -----
    Like ARTIST's ``angles_to_motor_positions`` this assumes the angle is reachable: the lever
    angle ``absolute_angle(0) - delta`` must lie in [0, pi]. Outside that interval the cosine
    folds back and the returned steps belong to a different angle; callers that are not sure
    should check ``linear_steps_to_angle(result) == angle`` (as
    :func:`heliocal.pipeline.physics.kinematics.inverse_kinematics` does).
    """
    offset_m = _t(offset_m)
    pivot_radius_m = _t(pivot_radius_m)
    increment = _t(increment_steps_per_m)
    initial_stroke = _t(initial_stroke_length_m)
    delta = (_t(angle_rad) - _t(initial_angle_rad))
    delta = actuator_sign(clockwise, delta.dtype) * delta
    absolute = _absolute_angle(initial_stroke, offset_m, pivot_radius_m) - delta
    stroke_sq = offset_m**2 + pivot_radius_m**2 - 2.0 * offset_m * pivot_radius_m * torch.cos(absolute)
    stroke = torch.sqrt(torch.clamp(stroke_sq, min=0.0))
    return (stroke - initial_stroke) * increment
