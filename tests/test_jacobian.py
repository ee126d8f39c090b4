"""The closed-form (geometric) Jacobian of the coarse fit against torch autodiff.

Reference: ``torch.func.jacfwd`` through :func:`forward_kinematics` and
:func:`measured_normal` (forward-mode autodiff, exact to rounding). Agreement to 1e-9 relative
per column, for every kinematic type, on random parameter vectors around a nominal geometry.
"""

import numpy as np
import pytest
import torch

from heliocal.pipeline.physics.jacobian import residual_and_jacobian
from heliocal.pipeline.physics.parameters import PARAMETER_NAMES, HeliostatSpec, nominal_parameters
from heliocal.pipeline.physics.kinematics import forward_kinematics
from heliocal.pipeline.physics.metrics import measured_normal

JUELICH = {
    "heliostat_id": "T1", "kinematic_type": "juelich", "actuator_type": "linear",
    "heliostat_e_m": 3.0, "heliostat_n_m": 150.0, "heliostat_u_m": 1.7,
    "concentrator_translation_n_m": 0.175,
    "axis_1_increment": 154166.666, "axis_1_initial_stroke_length_m": 0.075,
    "axis_1_offset_m": 0.34061, "axis_1_pivot_radius_m": 0.3204,
    "axis_1_initial_angle_rad": -1.570796, "axis_1_clockwise": False,
    "axis_1_min_steps": 0.0, "axis_1_max_steps": 70000.0,
    "axis_2_increment": 154166.666, "axis_2_initial_stroke_length_m": 0.075,
    "axis_2_offset_m": 0.3479, "axis_2_pivot_radius_m": 0.309,
    "axis_2_initial_angle_rad": 0.959931, "axis_2_clockwise": True,
    "axis_2_min_steps": 0.0, "axis_2_max_steps": 75000.0,
}
IDEAL = {
    "heliostat_id": "T2", "actuator_type": "ideal",
    "heliostat_e_m": -20.0, "heliostat_n_m": 80.0, "heliostat_u_m": 1.0,
    "concentrator_translation_u_m": 0.3, "joint_2_translation_n_m": 0.05,
    "axis_1_gear_ratio_steps_per_rad": 20000.0, "axis_1_angle_offset_rad": 0.1,
    "axis_2_gear_ratio_steps_per_rad": -15000.0, "axis_2_angle_offset_rad": 0.9,
    "axis_1_min_steps": -60000.0, "axis_1_max_steps": 60000.0,
    "axis_2_min_steps": -30000.0, "axis_2_max_steps": 30000.0,
    "primary_axis_e": 0.1, "primary_axis_n": -0.9, "primary_axis_u": 0.4,
}


def _case(row, steps_lo, steps_hi, seed):
    g = torch.Generator().manual_seed(seed)
    spec = HeliostatSpec.from_row(row)
    nominal = nominal_parameters(row)
    scale = torch.tensor([0.02] * 18 + [50.0, 1e-3, 1e-3, 1e-3, 0.01] * 2, dtype=torch.float64)
    if row["actuator_type"] == "ideal":
        scale[18:] = torch.tensor([50.0, 0, 0, 0, 0.01] * 2, dtype=torch.float64)
    params = nominal + scale * torch.randn(28, generator=g, dtype=torch.float64)
    n = 40
    steps = steps_lo + (steps_hi - steps_lo) * torch.rand(n, 2, generator=g, dtype=torch.float64)
    az = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2.0
    el = 0.2 + 0.9 * torch.rand(n, generator=g, dtype=torch.float64)
    sun = torch.stack([torch.cos(el) * torch.sin(az), -torch.cos(el) * torch.cos(az), torch.sin(el)], -1)
    spot = spec.position_enu + torch.tensor([0.0, -120.0, 40.0], dtype=torch.float64) \
        + torch.randn(n, 3, generator=g, dtype=torch.float64)
    return spec, params, steps, sun, spot


@pytest.mark.parametrize("kinematic_type,row,lo,hi", [
    ("juelich", JUELICH, torch.tensor([20000.0, 10000.0]), torch.tensor([60000.0, 70000.0])),
    ("az-el", IDEAL, torch.tensor([-50000.0, 2000.0]), torch.tensor([50000.0, 20000.0])),
    ("target-aligned", IDEAL, torch.tensor([-50000.0, -20000.0]), torch.tensor([50000.0, 20000.0])),
])
@pytest.mark.parametrize("seed", [0, 1])
def test_geometric_jacobian_equals_autodiff(kinematic_type, row, lo, hi, seed):
    row = {**row, "kinematic_type": kinematic_type}
    spec, params, steps, sun, spot = _case(row, lo, hi, seed)

    def residual(p):
        normal, position = forward_kinematics(p, spec, steps)
        return 1000.0 * (normal - measured_normal(sun, position, spot))

    expected = torch.func.jacfwd(residual)(params)
    r, jac = residual_and_jacobian(params, spec, steps, sun, spot)
    assert torch.isfinite(expected).all()
    assert torch.equal(r, residual(params))
    # columns that are zero in exact arithmetic (e.g. a tilt about the reference normal) hold only
    # rounding noise: compare them on an absolute scale of 1 (mrad per unit)
    col_scale = expected.abs().amax(dim=(0, 1)).clamp_min(1.0)
    rel = ((jac - expected).abs().amax(dim=(0, 1)) / col_scale).numpy()
    worst = int(np.argmax(rel))
    assert rel.max() < 1e-9, f"{PARAMETER_NAMES[worst]}: relative difference {rel.max():.2e}"
