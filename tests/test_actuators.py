"""Tests of heliocal.pipeline.physics.actuators (ideal and linear actuator laws)."""

import math

import pytest
import torch
from torch.func import jacfwd, vmap

from heliocal.pipeline.physics.actuators import (ideal_angle_to_steps, ideal_steps_to_angle,
                                                 linear_angle_to_steps, linear_steps_to_angle,
                                                 linear_stroke_length)

F64 = torch.float64

# Source: ARTIST-Association/ARTIST, tests/field/test_actuators.py (linear case): clockwise
# (0, 1), increment 1.5417e5, offset (0.33531, 0.34077), pivot radius (0.3381, 0.3191),
# initial angle (-1.5318, 0.94392), initial stroke length (0.077413, 0.077522).
ARTIST_LINEAR = dict(
    increment_steps_per_m=torch.tensor([1.5417e5, 1.5417e5], dtype=F64),
    initial_stroke_length_m=torch.tensor([0.077413, 0.077522], dtype=F64),
    offset_m=torch.tensor([0.33531, 0.34077], dtype=F64),
    pivot_radius_m=torch.tensor([0.3381, 0.3191], dtype=F64),
    initial_angle_rad=torch.tensor([-1.5318, 0.94392], dtype=F64),
    clockwise=torch.tensor([False, True]),
)


def test_linear_matches_artist_reference():
    # Same source: motor steps (28061, 47874) -> joint angles (-0.971173584461, -0.085735797882)
    # rad. ARTIST computes in float32 (its assert_close uses float32 tolerances); our float64
    # result differs by < 2e-7 rad.
    steps = torch.tensor([28061.0, 47874.0], dtype=F64)
    angles = linear_steps_to_angle(steps, **ARTIST_LINEAR)
    expected = torch.tensor([-0.971173584461, -0.085735797882], dtype=F64)
    torch.testing.assert_close(angles, expected, atol=1e-6, rtol=0)


def test_linear_zero_steps_give_initial_angle():
    angles = linear_steps_to_angle(torch.zeros(2, dtype=F64), **ARTIST_LINEAR)
    torch.testing.assert_close(angles, ARTIST_LINEAR["initial_angle_rad"], atol=1e-15, rtol=0)


def test_linear_clockwise_flips_the_sense():
    kwargs = {k: v[0] for k, v in ARTIST_LINEAR.items() if k != "clockwise"}
    steps = torch.tensor(30000.0, dtype=F64)
    a_cw = linear_steps_to_angle(steps, clockwise=True, **kwargs)
    a_ccw = linear_steps_to_angle(steps, clockwise=False, **kwargs)
    initial = kwargs["initial_angle_rad"]
    torch.testing.assert_close(a_cw - initial, -(a_ccw - initial))
    # A longer stroke opens the lever angle, so delta = abs(0) - abs(steps) < 0 and the
    # clockwise joint turns toward smaller angles.
    assert a_cw < initial < a_ccw


def test_linear_law_of_cosines_closed_form():
    # Hand-built triangle: offset 3, pivot radius 4, stroke 5 -> right angle at the joint.
    # increment 1 step/m, initial stroke 5 m, 0 steps: absolute angle pi/2.
    # At 2 steps (stroke 7 = offset + pivot radius) the lever is stretched: absolute angle pi.
    angle = linear_steps_to_angle(torch.tensor([0.0, 2.0], dtype=F64), 1.0, 5.0, 3.0, 4.0, 0.0,
                                  False)
    torch.testing.assert_close(angle, torch.tensor([0.0, math.pi / 2], dtype=F64))
    assert float(linear_stroke_length(2.0, 1.0, 5.0)) == 7.0


@pytest.mark.parametrize("clockwise", [False, True])
def test_linear_round_trip(clockwise):
    kwargs = {k: v[1] for k, v in ARTIST_LINEAR.items() if k != "clockwise"}
    steps = torch.linspace(0.0, 75000.0, 101, dtype=F64)
    angles = linear_steps_to_angle(steps, clockwise=clockwise, **kwargs)
    back = linear_angle_to_steps(angles, clockwise=clockwise, **kwargs)
    torch.testing.assert_close(back, steps, atol=1e-7, rtol=0)


def test_ideal_closed_form_and_round_trip():
    # 1000 steps/rad, offset 0.1 rad: 500 steps -> 0.6 rad; 0.6 rad -> 500 steps.
    assert float(ideal_steps_to_angle(500.0, 1000.0, 0.1)) == pytest.approx(0.6, abs=1e-15)
    assert float(ideal_angle_to_steps(0.6, 1000.0, 0.1)) == pytest.approx(500.0, abs=1e-9)
    steps = torch.linspace(-1e5, 1e5, 11, dtype=F64)
    back = ideal_angle_to_steps(ideal_steps_to_angle(steps, 12345.6, -0.3), 12345.6, -0.3)
    torch.testing.assert_close(back, steps, atol=1e-8, rtol=0)


def test_broadcasting_over_heliostats_and_measurements():
    # parameters (H=2, 1) against steps (H=2, N=5)
    steps = torch.linspace(0, 60000, 10, dtype=F64).reshape(2, 5)
    kwargs = {k: v.unsqueeze(-1) for k, v in ARTIST_LINEAR.items()}
    batched = linear_steps_to_angle(steps, **kwargs)
    assert batched.shape == (2, 5)
    for h in range(2):
        single = linear_steps_to_angle(steps[h], **{k: v[h] for k, v in ARTIST_LINEAR.items()})
        torch.testing.assert_close(batched[h], single, atol=0, rtol=0)


def test_gradcheck_linear():
    steps = torch.tensor([1000.0, 30000.0], dtype=F64)
    inputs = tuple(ARTIST_LINEAR[k][1].clone().requires_grad_(True)
                   for k in ("increment_steps_per_m", "initial_stroke_length_m", "offset_m",
                             "pivot_radius_m", "initial_angle_rad"))

    def f(*args):
        return linear_steps_to_angle(steps, *args, True)

    assert torch.autograd.gradcheck(f, inputs)


def test_torch_func_jacfwd_and_vmap():
    def angle(params, steps):
        return linear_steps_to_angle(steps, params[0], params[1], params[2], params[3], params[4],
                                     True)

    params = torch.stack([ARTIST_LINEAR[k][1] for k in
                          ("increment_steps_per_m", "initial_stroke_length_m", "offset_m",
                           "pivot_radius_m", "initial_angle_rad")])
    steps = torch.tensor([100.0, 20000.0, 50000.0], dtype=F64)
    jac = jacfwd(angle)(params, steps)
    assert jac.shape == (3, 5)
    assert torch.all(torch.isfinite(jac))
    # d angle / d initial angle is exactly 1
    torch.testing.assert_close(jac[:, 4], torch.ones(3, dtype=F64))
    per_item = vmap(angle, in_dims=(None, 0))(params, steps)
    torch.testing.assert_close(per_item, angle(params, steps))
