"""Error metrics, defined once for every stage: measured normals, angles, beam and spot errors.

Conventions
-----------
* All positions are ENU metres relative to the plant reference point; all directions are ENU
  vectors (they need not be unit length: every function normalises what it uses).
* ``sun_vector``: from the heliostat toward the sun (e = cos(el) sin(az), n = -cos(el) cos(az),
  u = sin(el); azimuth 0 = south, positive toward east).
* The measured mirror normal is the bisector of the direction to the sun and the direction from
  the mirror centre to the focal-spot centroid (PAINT/ARTIST; paper 002 eq. 3 uses the same
  bisector idea).
* Angles are returned in milliradians.

Every function works on torch tensors (float64, or float32 kept as float32; differentiable,
batched over leading dimensions, usable under :mod:`torch.func`) and also accepts numpy arrays / lists: if no argument is a torch
tensor, the result is returned as numpy (a tuple of numpy arrays for :func:`spot_offset_m`).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from .actuators import real_tensor
from .vectors import unit_vector

__all__ = [
    "reflect",
    "measured_normal",
    "angle_between_mrad",
    "error_mrad",
    "beam_error_mrad",
    "spot_offset_m",
    "mean_or_nan",
]


def _numpy_friendly(func):
    """Convert array-likes to tensors (:func:`~heliocal.pipeline.physics.actuators.real_tensor`:
    float64; a float32 tensor stays float32); return numpy when no input was a tensor."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        any_tensor = any(isinstance(a, torch.Tensor) for a in (*args, *kwargs.values()))
        args = tuple(real_tensor(a) for a in args)
        kwargs = {k: real_tensor(v) for k, v in kwargs.items()}
        out = func(*args, **kwargs)
        if any_tensor:
            return out
        if isinstance(out, tuple):
            return tuple(o.detach().numpy() for o in out)
        return out.detach().numpy()

    return wrapper


def _unit_components(x, y, z):
    """Unit vector of (x, y, z) given as separate tensors (cheaper than (..., 3) reductions
    when the batch is large and the vectors are views of other stacks)."""
    inv = torch.rsqrt(x * x + y * y + z * z)
    return x * inv, y * inv, z * inv


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


@_numpy_friendly
def reflect(incoming, normal):
    """Mirror reflection of a ray direction: ``d - 2 (d . n) n`` with ``n`` normalised.

    Parameters
    ----------
    incoming : (..., 3) propagation direction of the incident ray (from the source toward the
        mirror, i.e. ``-sun_vector`` for sunlight). Its length is kept.
    normal : (..., 3) mirror normal (either orientation; the result does not depend on its sign).

    Returns
    -------
    (..., 3) propagation direction of the reflected ray.
    """
    n = unit_vector(normal)
    return incoming - 2.0 * _dot(incoming, n).unsqueeze(-1) * n


@_numpy_friendly
def measured_normal(sun_vector, concentrator_position, focal_spot):
    """Measured mirror normal: unit bisector of the sun direction and mirror-centre -> spot.

    Parameters
    ----------
    sun_vector : (..., 3) direction from the heliostat toward the sun.
    concentrator_position : (..., 3) mirror centre [m] ENU.
    focal_spot : (..., 3) focal-spot centroid on the target [m] ENU.

    Returns
    -------
    (..., 3) unit normal, ENU.
    """
    sun = _unit_components(*sun_vector.unbind(-1))
    spot = _unit_components(*(focal_spot - concentrator_position).unbind(-1))
    return torch.stack(_unit_components(*(a + b for a, b in zip(sun, spot))), dim=-1)


@_numpy_friendly
def angle_between_mrad(a, b):
    """Angle between two directions [mrad], ``atan2(|a x b|, a . b)`` (accurate near 0 and pi).

    Parameters
    ----------
    a, b : (..., 3) vectors (any length).

    Returns
    -------
    (...) angle [mrad] in [0, 1000 pi].
    """
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    # vector_norm (not sqrt of the sum of squares): its gradient at a zero angle is 0, not NaN
    sin = torch.linalg.vector_norm(torch.stack((cx, cy, cz), dim=-1), dim=-1)
    return 1000.0 * torch.atan2(sin, ax * bx + ay * by + az * bz)


@_numpy_friendly
def error_mrad(predicted_normal, measured_normal):
    """Normal error [mrad]: angle between the predicted and the measured mirror normal.

    A normal error e turns the reflected beam by up to 2 e (see :func:`beam_error_mrad`).
    """
    return angle_between_mrad(predicted_normal, measured_normal)


@_numpy_friendly
def beam_error_mrad(sun_vector, predicted_normal, concentrator_position, focal_spot):
    """Beam error [mrad]: angle between the beam reflected by the predicted normal and the
    direction from the mirror centre to the measured focal spot.

    Parameters
    ----------
    sun_vector : (..., 3) direction toward the sun.
    predicted_normal : (..., 3) predicted mirror normal.
    concentrator_position : (..., 3) mirror centre [m] ENU.
    focal_spot : (..., 3) measured focal-spot centroid [m] ENU.
    """
    beam = reflect(-sun_vector, predicted_normal)
    return angle_between_mrad(beam, focal_spot - concentrator_position)


@_numpy_friendly
def spot_offset_m(sun_vector, predicted_normal, concentrator_position, focal_spot,
                  target_center, target_normal):
    """Offset on the target plane between the predicted and the measured focal spot [m].

    The beam reflected by ``predicted_normal`` from ``concentrator_position`` is intersected with
    the plane through ``target_center`` with normal ``target_normal``; the measured
    ``focal_spot`` is projected onto the same plane. The difference (predicted minus measured) is
    expressed in the plane's axes:

    * horizontal: ``unit(target_normal x up)``; for a target facing north (normal +n, as the
      Juelich targets) this is +east, i.e. positive = the predicted spot lies east of the
      measured one;
    * vertical: ``horizontal x target_normal`` (points up for any non-horizontal-facing target),
      positive = predicted spot above the measured one.

    Parameters
    ----------
    sun_vector, predicted_normal, concentrator_position, focal_spot : (..., 3) as in
        :func:`beam_error_mrad`.
    target_center : (..., 3) a point of the target plane [m] ENU.
    target_normal : (..., 3) target plane normal (not vertical).

    Returns
    -------
    (horizontal_m, vertical_m, magnitude_m) : three (...) tensors [m]. Beams parallel to the
    plane or pointing away from it give inf/NaN or a hit behind the mirror (not clipped).
    """
    nt = unit_vector(target_normal)
    beam = reflect(-sun_vector, predicted_normal)
    distance = _dot(target_center - concentrator_position, nt) / _dot(beam, nt)
    hit = concentrator_position + distance.unsqueeze(-1) * beam
    diff = hit - focal_spot
    diff = diff - _dot(diff, nt).unsqueeze(-1) * nt
    up = torch.zeros_like(nt) + torch.tensor([0.0, 0.0, 1.0], dtype=nt.dtype)
    horizontal_axis = unit_vector(torch.linalg.cross(nt, up, dim=-1))
    vertical_axis = torch.linalg.cross(horizontal_axis, nt, dim=-1)
    horizontal = _dot(diff, horizontal_axis)
    vertical = _dot(diff, vertical_axis)
    return horizontal, vertical, torch.sqrt(horizontal**2 + vertical**2)


def mean_or_nan(values) -> float:
    """Mean of an array of errors (e.g. ``error_mrad`` of a split's rows); NaN, without numpy's
    empty-slice warning, when there are none (a heliostat without validation rows)."""
    return float(np.mean(values)) if len(values) else float("nan")
