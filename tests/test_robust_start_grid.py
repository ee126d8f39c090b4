"""The robust start's grid of actuator zero points (pipeline/models/coarse.py).

``_grid_joint_angles`` runs an axis's actuator law once per initial stroke and adds each grid
angle afterwards. The reference is the direct way: :func:`joint_angles` once per (angle, stroke)
pair of the grid, with that pair set in the parameters. Both laws add the zero-point angle last,
so the two must agree to the bit, for linear and ideal actuators and for either axis.
"""

from __future__ import annotations

import math

import pytest
import torch

from heliocal.pipeline.models.coarse import _grid_joint_angles
from heliocal.pipeline.physics.kinematics import joint_angles
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX, HeliostatSpec

F64 = torch.float64

#: PAINT BE36's actuators (its heliostat-properties.json; axis 1's angle shifted by -pi/2 as
#: ingest does)
BE36 = {"increment": (154166.6667, 154166.6667), "initial_stroke_length_m": (0.075676335, 0.078387399),
        "offset_m": (0.335308, 0.340771), "pivot_radius_m": (0.338095, 0.3191),
        "initial_angle_rad": (0.01366065 - math.pi / 2, 0.937086489)}


def _params(actuator_type: str) -> torch.Tensor:
    p = torch.zeros(28, dtype=F64)
    for field, values in BE36.items():
        for axis in (1, 2):
            value = values[axis - 1] if actuator_type == "linear" or field in (
                "increment", "initial_angle_rad") else 0.0
            p[PARAMETER_INDEX[f"axis_{axis}_{field}"]] = value
    return p


def _pair_by_pair(p0, spec, steps, axis, angles, strokes) -> torch.Tensor:
    """The reference: the actuator law once per (angle, stroke) pair, in meshgrid "ij" order."""
    ga, gs = torch.meshgrid(angles, strokes, indexing="ij")
    cand = p0.unsqueeze(0).repeat(ga.numel(), 1)
    cand[:, PARAMETER_INDEX[f"axis_{axis}_initial_angle_rad"]] = ga.reshape(-1)
    cand[:, PARAMETER_INDEX[f"axis_{axis}_initial_stroke_length_m"]] = gs.reshape(-1)
    return joint_angles(cand, spec, steps)[..., axis - 1]


@pytest.mark.parametrize("actuator_type", ["linear", "ideal"])
@pytest.mark.parametrize("axis", [1, 2])
def test_grid_angles_equal_the_law_run_once_per_grid_pair(actuator_type, axis):
    spec = HeliostatSpec("juelich", actuator_type, clockwise=[False, True], min_steps=[0, 0],
                         max_steps=[80000, 80000], position_enu=[0.0, 0.0, 0.0])
    p0 = _params(actuator_type)
    steps = torch.stack([torch.linspace(0, 80000, 37, dtype=F64),
                         torch.linspace(75000, 3000, 37, dtype=F64)], dim=-1)
    angles = torch.linspace(-math.pi, math.pi, 181, dtype=F64)[:-1]
    strokes = (torch.linspace(0.0, 0.68, 61, dtype=F64) if actuator_type == "linear"
               else p0[PARAMETER_INDEX[f"axis_{axis}_initial_stroke_length_m"]].reshape(1))
    fast = _grid_joint_angles(p0, spec, steps, axis, angles, strokes)
    reference = _pair_by_pair(p0, spec, steps, axis, angles, strokes)
    assert fast.shape == reference.shape == (len(angles) * len(strokes), 37)
    assert torch.equal(torch.isnan(fast), torch.isnan(reference))
    torch.testing.assert_close(fast, reference, rtol=0.0, atol=0.0, equal_nan=True)
