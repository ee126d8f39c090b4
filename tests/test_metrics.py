"""Tests of heliocal.pipeline.physics.metrics: closed-form cases written out by hand."""

import math

import numpy as np
import pytest
import torch

from heliocal.pipeline.physics.metrics import (angle_between_mrad, beam_error_mrad, error_mrad,
                                               measured_normal, reflect, spot_offset_m)

F64 = torch.float64
S2 = math.sqrt(0.5)


def t(*values):
    return torch.tensor(values, dtype=F64)


def test_reflect_normal_at_45_deg_turns_the_beam_by_90_deg():
    # Light falling straight down onto a mirror whose normal points 45 deg between south and up
    # leaves horizontally toward south.
    out = reflect(t(0.0, 0.0, -1.0), t(0.0, -S2, S2))
    torch.testing.assert_close(out, t(0.0, -1.0, 0.0), atol=1e-15, rtol=0)
    assert float(angle_between_mrad(out, t(0.0, 0.0, -1.0))) == pytest.approx(1000 * math.pi / 2)


def test_reflect_ignores_normal_sign_and_length():
    d = t(0.3, -0.2, -0.9)
    n = t(0.1, -0.5, 0.8)
    torch.testing.assert_close(reflect(d, n), reflect(d, -3.0 * n))


def test_angle_between_one_mrad():
    a = t(1.0, 0.0, 0.0)
    b = t(math.cos(1e-3), math.sin(1e-3), 0.0)
    assert float(angle_between_mrad(a, b)) == pytest.approx(1.0, abs=1e-12)
    assert float(error_mrad(a, 5.0 * b)) == pytest.approx(1.0, abs=1e-12)


def test_angle_between_is_accurate_near_zero_and_pi():
    # acos(a.b) would lose everything below ~1e-8 rad; atan2 keeps it.
    a = t(0.0, 0.0, 1.0)
    b = t(math.sin(1e-10), 0.0, math.cos(1e-10))
    assert float(angle_between_mrad(a, b)) == pytest.approx(1e-7, rel=1e-9)
    assert float(angle_between_mrad(a, -a)) == pytest.approx(1000 * math.pi)
    assert float(angle_between_mrad(a, a)) == 0.0


def test_measured_normal_is_the_bisector():
    # Sun at the zenith, spot 100 m due south at mirror height: normal at 45 deg south-up.
    normal = measured_normal(t(0.0, 0.0, 1.0), t(5.0, 10.0, 1.0), t(5.0, -90.0, 1.0))
    torch.testing.assert_close(normal, t(0.0, -S2, S2), atol=1e-15, rtol=0)


def test_beam_error_is_twice_an_in_plane_normal_error():
    sun = t(0.0, 0.0, 1.0)
    position = t(0.0, 0.0, 0.0)
    spot = t(0.0, -100.0, 0.0)
    exact = measured_normal(sun, position, spot)
    assert float(beam_error_mrad(sun, exact, position, spot)) == pytest.approx(0.0, abs=1e-9)
    # Tilt the normal by 0.5 mrad in the plane of incidence (about east).
    c, s = math.cos(5e-4), math.sin(5e-4)
    tilted = torch.stack([exact[0], c * exact[1] - s * exact[2], s * exact[1] + c * exact[2]])
    assert float(error_mrad(tilted, exact)) == pytest.approx(0.5, abs=1e-9)
    assert float(beam_error_mrad(sun, tilted, position, spot)) == pytest.approx(1.0, abs=1e-9)


def test_spot_offset_axes_and_signs():
    # Target facing north (+n, as the Juelich targets) with centre 100 m south of the mirror.
    # The sun is behind the mirror's view such that the exact normal sends the beam to the
    # centre; the measured spot is 0.3 m west and 0.2 m below the centre, so the predicted
    # spot is 0.3 m east (+horizontal) and 0.2 m above (+vertical) the measured one.
    sun = t(0.0, 0.0, 1.0)
    position = t(0.0, 0.0, 0.0)
    centre = t(0.0, -100.0, 0.0)
    normal = measured_normal(sun, position, centre)
    spot = centre + t(-0.3, 0.0, -0.2)
    h, v, m = spot_offset_m(sun, normal, position, spot, centre, t(0.0, 1.0, 0.0))
    assert float(h) == pytest.approx(0.3, abs=1e-12)
    assert float(v) == pytest.approx(0.2, abs=1e-12)
    assert float(m) == pytest.approx(math.hypot(0.3, 0.2), abs=1e-12)


def test_spot_offset_small_angle_matches_distance_times_beam_error():
    sun = t(0.2, -0.3, 0.9)
    position = t(10.0, 80.0, 1.5)
    centre = t(0.0, 0.0, 60.0)
    normal = measured_normal(sun, position, centre)
    # Rotate the normal by 0.1 mrad about up: the beam swings horizontally.
    c, s = math.cos(1e-4), math.sin(1e-4)
    turned = torch.stack([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1], normal[2]])
    h, v, m = spot_offset_m(sun, turned, position, centre, centre, t(0.0, 1.0, 0.0))
    beam = float(beam_error_mrad(sun, turned, position, centre)) / 1000.0
    slant = float(torch.linalg.vector_norm(centre - position))
    # The target plane is oblique to the beam, so the offset exceeds slant * angle a little.
    assert slant * beam <= float(m) <= 1.5 * slant * beam


def test_numpy_in_numpy_out_and_batching():
    a = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    b = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    out = angle_between_mrad(a, b)
    assert isinstance(out, np.ndarray)
    np.testing.assert_allclose(out, [1000 * math.pi / 2, 0.0], atol=1e-12)
    h, v, m = spot_offset_m([0, 0, 1], [0, -S2, S2], [0, 0, 0], [0, -100, 0], [0, -100, 0],
                            [0, 1, 0])
    assert all(isinstance(x, np.ndarray) for x in (h, v, m))
    assert isinstance(angle_between_mrad(torch.tensor(a), b), torch.Tensor)


def test_gradcheck_metrics():
    gen = torch.Generator().manual_seed(3)
    sun = torch.nn.functional.normalize(torch.rand(4, 3, generator=gen, dtype=F64) + t(0, 0, 1), dim=-1)
    position = torch.rand(4, 3, generator=gen, dtype=F64).requires_grad_(True)
    normal = (torch.rand(4, 3, generator=gen, dtype=F64) + t(0, -1, 1)).requires_grad_(True)
    spot = t(0.0, -100.0, 50.0) + torch.rand(4, 3, generator=gen, dtype=F64)
    centre = t(0.0, -100.0, 50.0)
    nt = t(0.0, 1.0, 0.0)
    assert torch.autograd.gradcheck(
        lambda n, x: beam_error_mrad(sun, n, x, spot), (normal, position))
    assert torch.autograd.gradcheck(
        lambda n, x: error_mrad(n, measured_normal(sun, x, spot)), (normal, position))
    assert torch.autograd.gradcheck(
        lambda n, x: spot_offset_m(sun, n, x, spot, centre, nt)[:2], (normal, position))
