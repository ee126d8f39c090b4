"""Tests of heliocal.pipeline.physics.kinematics: ARTIST reference values, conventions, invariants.

Reference values carry their source in a comment; fixtures are written out by hand (the BE36
actuator values are copied from PAINT's ``BE36-heliostat-properties.json``, with ARTIST's -pi/2
on axis 1's initial angle as ingest applies it).
"""

import math

import pandas as pd
import pytest
import torch
from torch.func import jacfwd, vmap

from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.physics.parameters import (IDEAL_UNUSED_PARAMETERS, KINEMATIC_PRESETS,
                                                  KINEMATIC_TYPES, PARAMETER_INDEX, PARAMETER_NAMES,
                                                  PRESET_NAMES, PRESETS, REFERENCE_NORMALS,
                                                  STONE_MAPPING, HeliostatSpec, nominal_parameters,
                                                  preset_mask, preset_parameters)
from heliocal.pipeline.physics.kinematics import (forward_kinematics, inverse_kinematics,
                                                  joint_angles, orientation_matrices, rotation_e,
                                                  rotation_n, rotation_u)
from heliocal.pipeline.physics.metrics import angle_between_mrad, reflect

F64 = torch.float64
I = PARAMETER_INDEX


def params_from(values: dict) -> torch.Tensor:
    p = torch.zeros(28, dtype=F64)
    for name, value in values.items():
        p[I[name]] = value
    return p


def linear_axes(increment, stroke, offset, radius, angle):
    out = {}
    for i in (1, 2):
        out[f"axis_{i}_increment"] = increment[i - 1]
        out[f"axis_{i}_initial_stroke_length_m"] = stroke[i - 1]
        out[f"axis_{i}_offset_m"] = offset[i - 1]
        out[f"axis_{i}_pivot_radius_m"] = radius[i - 1]
        out[f"axis_{i}_initial_angle_rad"] = angle[i - 1]
    return out


# Source: ARTIST-Association/ARTIST tests/field/test_kinematic_rigid_body.py (linear fixture):
# increment 154166.666, initial stroke 0.075, offset (0.34061, 0.3479), pivot radius
# (0.3204, 0.309), initial angle (-1.570796, 0.959931), clockwise (0, 1), position 0.
ARTIST_ACTUATORS = linear_axes((154166.666, 154166.666), (0.075, 0.075), (0.34061, 0.3479),
                               (0.3204, 0.309), (-1.570796, 0.959931))
ARTIST_SPEC = HeliostatSpec("juelich", "linear", clockwise=[False, True], min_steps=[0, 0],
                            max_steps=[80000, 80000], position_enu=[0.0, 0.0, 0.0])

# PAINT BE36-heliostat-properties.json (axis 1 initial angle 0.01366065 - pi/2).
BE36_ACTUATORS = linear_axes((154166.6667, 154166.6667), (0.075676335, 0.078387399),
                             (0.335308, 0.340771), (0.338095, 0.3191),
                             (0.01366065 - math.pi / 2, 0.937086489))


def test_parameter_names():
    assert len(PARAMETER_NAMES) == 28 == len(set(PARAMETER_NAMES))
    assert PARAMETER_NAMES[:6] == (
        "joint_1_translation_e_m", "joint_1_translation_n_m", "joint_1_translation_u_m",
        "joint_1_tilt_e_rad", "joint_1_tilt_n_rad", "joint_1_tilt_u_rad")
    assert PARAMETER_NAMES[12] == "concentrator_translation_e_m"
    assert PARAMETER_NAMES[17] == "concentrator_tilt_u_rad"
    assert PARAMETER_NAMES[18:23] == (
        "axis_1_increment", "axis_1_initial_stroke_length_m", "axis_1_offset_m",
        "axis_1_pivot_radius_m", "axis_1_initial_angle_rad")
    assert PARAMETER_NAMES[27] == "axis_2_initial_angle_rad"


def test_artist_reference_normals_and_origin():
    # Source: the brief's ARTIST reference (ARTIST kinematic test, concentrator n = 0.175 m, all
    # other translations 0). Agreement 5e-4 as in ARTIST's assert_close.
    p = params_from({**ARTIST_ACTUATORS, "concentrator_translation_n_m": 0.175})
    steps = torch.tensor([[0.0, 0.0], [5.0, 1000.0], [10.0, 40.0]], dtype=F64)
    normals, positions = forward_kinematics(p, ARTIST_SPEC, steps)
    expected = torch.tensor([[0.81915, 0.0, 0.57358], [0.80578, -6e-5, 0.59221],
                             [0.81862, -1.2e-4, 0.57434]], dtype=F64)
    torch.testing.assert_close(normals, expected, atol=5e-4, rtol=5e-4)
    torch.testing.assert_close(positions[0], torch.tensor([-0.14335, 0.0, -0.10038], dtype=F64),
                               atol=5e-4, rtol=5e-4)


@pytest.mark.parametrize("steps, expected", [
    # Source: ARTIST-Association/ARTIST tests/field/test_kinematic_rigid_body.py,
    # test_motor_positions_to_orientations, "kinematic_model_linear" (second joint translation
    # u = 0.315, concentrator translation n = -0.17755, u = -0.4045): orientation matrices,
    # rows e, n, u; last column = mirror centre. Initial orientation (0, -1, 0) makes ARTIST's
    # orientation offset the identity.
    ((0.0, 0.0), [[5.7358e-01, -8.1915e-01, 0.0, 1.4544e-01],
                  [2.5715e-07, 1.8006e-07, 1.0, -8.9500e-02],
                  [-8.1915e-01, -5.7358e-01, 3.1392e-07, 1.0184e-01]]),
    ((5.0, 1000.0), [[5.9221e-01, -8.0578e-01, 0.0, 1.4307e-01],
                     [8.2862e-05, 6.0899e-05, 1.0, -8.9511e-02],
                     [-8.0578e-01, -5.9221e-01, 1.0283e-04, 1.0514e-01]]),
    ((10.0, 40.0), [[5.7434e-01, -8.1862e-01, 0.0, 1.4535e-01],
                    [1.6830e-04, 1.1808e-04, 1.0, -8.9521e-02],
                    [-8.1862e-01, -5.7434e-01, 2.0559e-04, 1.0196e-01]]),
])
def test_artist_orientation_matrices(steps, expected):
    p = params_from({**ARTIST_ACTUATORS, "joint_2_translation_u_m": 0.315,
                     "concentrator_translation_n_m": -0.17755,
                     "concentrator_translation_u_m": -0.4045})
    rotations, positions = orientation_matrices(p, ARTIST_SPEC, torch.tensor([steps], dtype=F64))
    got = torch.cat([rotations[0], positions[0].unsqueeze(-1)], dim=-1)
    torch.testing.assert_close(got, torch.tensor(expected, dtype=F64), atol=5e-4, rtol=5e-4)


def test_rotation_matrices_orthonormal_and_artist_signs():
    angles = torch.linspace(-3.0, 3.0, 13, dtype=F64)
    for rot in (rotation_e, rotation_n, rotation_u):
        r = rot(angles)
        torch.testing.assert_close(r.transpose(-1, -2) @ r, torch.eye(3, dtype=F64).expand(13, 3, 3))
        torch.testing.assert_close(torch.linalg.det(r), torch.ones(13, dtype=F64))
    x = torch.tensor(0.3, dtype=F64)
    c, s = math.cos(0.3), math.sin(0.3)
    # Source: ARTIST artist/util/utils.py rotate_e / rotate_n / rotate_u (3x3 blocks).
    artist_e = torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=F64)
    artist_n = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=F64)
    artist_u = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=F64)
    torch.testing.assert_close(rotation_e(x), artist_e)
    torch.testing.assert_close(rotation_u(x), artist_u)
    torch.testing.assert_close(rotation_n(-x), artist_n)   # ARTIST's tilt_n = -ours


def test_tilt_sign_convention_right_handed():
    # Juelich chain with ideal actuators (gear 1 step/rad, offset 0) for clean angles.
    spec = HeliostatSpec("juelich", "ideal", clockwise=[False, False], min_steps=[-9, -9],
                         max_steps=[9, 9], position_enu=[0.0, 0.0, 0.0])
    d = 0.01
    base = {"axis_1_increment": 1.0, "axis_2_increment": 1.0}
    # joint_1_tilt_u = +d turns the south-facing zero normal counter-clockwise (toward east).
    n, _ = forward_kinematics(params_from({**base, "joint_1_tilt_u_rad": d}), spec,
                              torch.zeros(1, 2, dtype=F64))
    torch.testing.assert_close(n[0], torch.tensor([math.sin(d), -math.cos(d), 0.0], dtype=F64))
    # joint_1_tilt_n = +d tips an up-facing normal (axis 1 at -pi/2) toward east.
    n, _ = forward_kinematics(params_from({**base, "joint_1_tilt_n_rad": d}), spec,
                              torch.tensor([[-math.pi / 2, 0.0]], dtype=F64))
    torch.testing.assert_close(n[0], torch.tensor([math.sin(d), 0.0, math.cos(d)], dtype=F64))


def test_orientation_matrices_orthonormal_random():
    gen = torch.Generator().manual_seed(11)
    p = params_from(BE36_ACTUATORS) + 0.05 * torch.randn(28, generator=gen, dtype=F64) * (
        torch.arange(28) < 18)
    steps = torch.rand(50, 2, generator=gen, dtype=F64) * 70000
    spec = HeliostatSpec("juelich", "linear", [False, True], [0, 0], [69001, 75454], [0.0, 0, 0])
    r, x = orientation_matrices(p, spec, steps)
    torch.testing.assert_close(r.transpose(-1, -2) @ r, torch.eye(3, dtype=F64).expand(50, 3, 3))
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(50, dtype=F64))
    n, x2 = forward_kinematics(p, spec, steps)
    torch.testing.assert_close(r @ torch.tensor(REFERENCE_NORMALS["juelich"], dtype=F64), n)
    torch.testing.assert_close(x, x2)


def test_az_el_closed_form():
    # No tilts or translations: normal = (cos el sin az, -cos el cos az, sin el), the same
    # formula as the sun vector (azimuth 0 = south, positive toward east).
    g = 10000.0
    spec = HeliostatSpec("az-el", "ideal", [False, False], [-4e4, -1e3], [4e4, 2e4], [1.0, 2.0, 3.0])
    p = params_from({"axis_1_increment": g, "axis_2_increment": g})
    az = torch.tensor([0.0, 0.5, -1.2, 3.0], dtype=F64)
    el = torch.tensor([0.3, 1.0, 0.05, 1.5], dtype=F64)
    n, x = forward_kinematics(p, spec, torch.stack([az * g, el * g], -1))
    expected = torch.stack([torch.cos(el) * torch.sin(az), -torch.cos(el) * torch.cos(az),
                            torch.sin(el)], -1)
    torch.testing.assert_close(n, expected)
    torch.testing.assert_close(x, torch.tensor([1.0, 2.0, 3.0], dtype=F64).expand(4, 3))


def test_target_aligned_closed_form():
    spec = HeliostatSpec("target-aligned", "ideal", [False, False], [-4, -2], [4, 2], [0.0, 0, 0],
                         primary_axis=[0.0, -2.0, 0.0])         # normalised to (0, -1, 0)
    p = params_from({"axis_1_increment": 1.0, "axis_2_increment": 1.0})
    # No tilt: the normal is the primary axis whatever the spin.
    n, _ = forward_kinematics(p, spec, torch.tensor([[0.0, 0.0], [1.0, 0.0], [-2.5, 0.0]], dtype=F64))
    torch.testing.assert_close(n, torch.tensor([0.0, -1.0, 0.0], dtype=F64).expand(3, 3))
    # Positive tilt at zero spin lifts the normal of a horizontal primary axis.
    n, _ = forward_kinematics(p, spec, torch.tensor([[0.0, 0.4]], dtype=F64))
    torch.testing.assert_close(n[0], torch.tensor([0.0, -math.cos(0.4), math.sin(0.4)], dtype=F64))
    # Spinning by pi/2 moves that tilt into the horizontal plane, still at 0.4 rad from p.
    n, _ = forward_kinematics(p, spec, torch.tensor([[math.pi / 2, 0.4]], dtype=F64))
    assert float(angle_between_mrad(n[0], spec.primary_axis)) == pytest.approx(400.0)
    assert float(n[0, 2]) == pytest.approx(0.0, abs=1e-15)


def test_documented_degeneracies_juelich():
    spec = HeliostatSpec("juelich", "linear", [False, True], [0, 0], [69001, 75454], [0.0, 0, 0])
    p = params_from({**BE36_ACTUATORS, "concentrator_translation_n_m": 0.175,
                     "joint_1_tilt_n_rad": 0.003, "joint_2_tilt_n_rad": -0.002})
    steps = torch.rand(20, 2, generator=torch.Generator().manual_seed(5), dtype=F64) * 60000
    d = 0.004

    def shifted(name):
        q = p.clone()
        q[I[name]] += d
        return forward_kinematics(q, spec, steps)

    # joint_2_tilt_e sits right after the axis-1 rotation about e: identical to an axis-1 offset.
    for a, b in zip(shifted("joint_2_tilt_e_rad"), shifted("axis_1_initial_angle_rad")):
        torch.testing.assert_close(a, b)
    # concentrator_tilt_n turns the mirror about its own (south) normal: no effect on normals.
    torch.testing.assert_close(shifted("concentrator_tilt_n_rad")[0], forward_kinematics(p, spec, steps)[0])
    # concentrator_translation_u is along axis 2: same as joint_2_translation_u (always exact);
    # joint_2_translation_e equals joint_1_translation_e only while joint_2's tilts are 0.
    torch.testing.assert_close(shifted("concentrator_translation_u_m")[1],
                               shifted("joint_2_translation_u_m")[1])
    p[I["joint_2_tilt_n_rad"]] = 0.0
    torch.testing.assert_close(shifted("joint_2_translation_e_m")[1],
                               shifted("joint_1_translation_e_m")[1])


def make_case(kinematic_type, seed):
    """Random but physically plausible heliostat: (params, spec, target)."""
    gen = torch.Generator().manual_seed(seed)

    def r(scale, n=()):
        return scale * (2 * torch.rand(n, generator=gen, dtype=F64) - 1)

    position = torch.stack([r(60.0), 60.0 + r(40.0), r(1.0)])
    target = torch.tensor([0.0, 0.0, 36.0], dtype=F64)
    tilts = {f"{b}_tilt_{d}_rad": float(r(0.005)) for b in ("joint_1", "joint_2", "concentrator")
             for d in "enu"}
    if kinematic_type == "juelich":
        values = {**BE36_ACTUATORS, **tilts, "concentrator_translation_n_m": 0.175,
                  "joint_2_translation_u_m": float(r(0.05))}
        spec = HeliostatSpec("juelich", "linear", [False, True], [0, 0], [69001, 75454], position)
    else:
        g = 20000.0
        values = {**tilts, "axis_1_increment": g * (1 + float(r(0.01))),
                  "axis_2_increment": g * (1 + float(r(0.01))),
                  "axis_1_initial_angle_rad": float(r(0.01)), "axis_2_initial_angle_rad": float(r(0.01)),
                  "joint_2_translation_u_m": 1.2, "concentrator_translation_e_m": float(r(0.05))}
        if kinematic_type == "az-el":
            values["concentrator_translation_n_m"] = -0.25
            spec = HeliostatSpec("az-el", "ideal", [False, False], [-math.pi * g, 0.0],
                                 [math.pi * g, math.pi / 2 * g], position)
        else:
            values["concentrator_translation_u_m"] = 0.25
            spec = HeliostatSpec("target-aligned", "ideal", [False, False], [-math.pi * g, 0.0],
                                 [math.pi * g, math.pi / 2 * g], position,
                                 primary_axis=target - position)
    return params_from(values), spec, target


def physical_steps(params, spec, target, seed, count=40):
    """Random steps within the limits whose sun (making the beam hit ``target``) is up."""
    gen = torch.Generator().manual_seed(seed)
    low, high = spec.min_steps, spec.max_steps
    steps = low + (high - low) * (0.02 + 0.96 * torch.rand(2000, 2, generator=gen, dtype=F64))
    n, x = forward_kinematics(params, spec, steps)
    to_target = torch.nn.functional.normalize(target - x, dim=-1)
    sun = -reflect(to_target, n)
    ok = ((sun * n).sum(-1) > 0.1) & (sun[:, 2] > 0.05) & ((to_target * n).sum(-1) > 0.1)
    assert int(ok.sum()) >= count
    return steps[ok][:count], sun[ok][:count]


@pytest.mark.parametrize("kinematic_type", KINEMATIC_TYPES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_inverse_kinematics_round_trip(kinematic_type, seed):
    params, spec, target = make_case(kinematic_type, seed)
    steps, sun = physical_steps(params, spec, target, seed)
    solved = inverse_kinematics(params, spec, sun, target)
    assert torch.all(torch.isfinite(solved))
    n, x = forward_kinematics(params, spec, solved)
    beam = reflect(-sun, n)
    error_rad = angle_between_mrad(beam, target - x) / 1000.0
    assert float(error_rad.max()) < 1e-9
    # The limits admit one solution here, so the original steps come back.
    torch.testing.assert_close(solved, steps, atol=1e-5, rtol=0)


def test_inverse_kinematics_both_branches_and_limits():
    params, spec, target = make_case("az-el", 4)
    steps, sun = physical_steps(params, spec, target, 4, count=10)
    wide = HeliostatSpec("az-el", "ideal", [False, False], [-1e6, -1e6], [1e6, 1e6],
                         spec.position_enu)
    both, within = inverse_kinematics(params, wide, sun, target, return_both=True)
    assert both.shape == (10, 2, 2) and within.shape == (10, 2)
    assert bool(within.all())
    for branch in (0, 1):
        n, x = forward_kinematics(params, wide, both[:, branch])
        err = angle_between_mrad(reflect(-sun, n), target - x) / 1000.0
        assert float(err.max()) < 1e-9
    # The second solution flips over the zenith: elevation beyond pi/2.
    el = joint_angles(params, wide, both)[..., 1]
    assert bool(((el[:, 0] > math.pi / 2) != (el[:, 1] > math.pi / 2)).all())
    # Without tilts and translations the flip is exact: the normal R_u(az) R_e(el) (0, -1, 0) is
    # the same at (az + pi, pi - el), and the mirror centre does not move, so both branches are
    # that pair of angles (to rounding).
    straight = params.clone()
    for name in PARAMETER_NAMES:
        if "_tilt_" in name or "_translation_" in name:
            straight[I[name]] = 0.0
    both, within = inverse_kinematics(straight, wide, sun, target, return_both=True)
    assert bool(within.all())
    angles = joint_angles(straight, wide, both)
    torch.testing.assert_close(angles[:, 0, 1] + angles[:, 1, 1], torch.full((10,), math.pi, dtype=F64),
                               atol=1e-9, rtol=0)
    turn = torch.remainder(angles[:, 1, 0] - angles[:, 0, 0], 2 * math.pi)
    torch.testing.assert_close(turn, torch.full((10,), math.pi, dtype=F64), atol=1e-9, rtol=0)
    # With the real limits (elevation in [0, pi/2]) exactly one branch is valid and chosen.
    both_lim, within_lim = inverse_kinematics(params, spec, sun, target, return_both=True)
    assert bool((within_lim.sum(-1) == 1).all())
    chosen = inverse_kinematics(params, spec, sun, target)
    torch.testing.assert_close(chosen, steps, atol=1e-5, rtol=0)


def test_inverse_kinematics_nan_when_out_of_limits():
    params, spec, target = make_case("juelich", 7)
    # Sun due north and low: the mirror would have to face north; the Juelich axes cannot.
    sun = torch.tensor([[0.0, 0.9, 0.1]], dtype=F64)
    solved = inverse_kinematics(params, spec, sun, target)
    assert bool(torch.isnan(solved).all())


def batched_case():
    cases = [make_case("juelich", s) for s in range(3)]
    params = torch.stack([c[0] for c in cases])
    spec = HeliostatSpec("juelich", "linear", torch.tensor([[False, True]] * 3),
                         torch.tensor([[0.0, 0.0]] * 3), torch.tensor([[69001.0, 75454.0]] * 3),
                         torch.stack([c[1].position_enu for c in cases]))
    steps = torch.rand(3, 7, 2, generator=torch.Generator().manual_seed(9), dtype=F64) * 60000
    return cases, params, spec, steps


def test_batching_equals_loop():
    cases, params, spec, steps = batched_case()
    normals, positions = forward_kinematics(params, spec, steps)
    assert normals.shape == positions.shape == (3, 7, 3)
    for h, (p, s, _) in enumerate(cases):
        for k in range(7):
            n1, x1 = forward_kinematics(p, s, steps[h, k:k + 1])
            torch.testing.assert_close(normals[h, k], n1[0], atol=1e-15, rtol=0)
            torch.testing.assert_close(positions[h, k], x1[0], atol=1e-13, rtol=0)


def test_torch_func_vmap_and_jacfwd():
    cases, params, spec, steps = batched_case()

    def single(p, s, pos):
        one = HeliostatSpec("juelich", "linear", [False, True], [0, 0], [69001, 75454], pos)
        n, x = forward_kinematics(p, one, s)
        return torch.cat([n, x], -1)

    mapped = vmap(single)(params, steps, spec.position_enu)
    n, x = forward_kinematics(params, spec, steps)
    torch.testing.assert_close(mapped, torch.cat([n, x], -1))
    jac = jacfwd(lambda p: single(p, steps[0], spec.position_enu[0]))(params[0])
    assert jac.shape == (7, 6, 28)
    ref = torch.autograd.functional.jacobian(lambda p: single(p, steps[0], spec.position_enu[0]),
                                             params[0])
    torch.testing.assert_close(jac, ref)


@pytest.mark.parametrize("kinematic_type", KINEMATIC_TYPES)
def test_gradcheck_forward(kinematic_type):
    params, spec, _ = make_case(kinematic_type, 3)
    low, high = spec.min_steps, spec.max_steps
    steps = low + (high - low) * torch.tensor([[0.3, 0.6], [0.7, 0.2]], dtype=F64)
    p = params.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: forward_kinematics(q, spec, steps), (p,))


def test_presets_nested_and_sized():
    for kinematic_type in KINEMATIC_TYPES:
        presets = KINEMATIC_PRESETS[kinematic_type]
        sizes = {name: len(presets[name]) for name in PRESET_NAMES}
        assert sizes == {"static-6": 6, "static-14": 14, "static-20": 20, "static-28": 28,
                         "stone-8": 8}
        chain = [set(presets[n]) for n in ("static-6", "static-14", "static-20", "static-28")]
        assert all(a < b for a, b in zip(chain, chain[1:]))
        assert set(presets["static-6"]) < set(presets["stone-8"]) <= set(presets["static-14"])
        assert set(presets["static-28"]) == set(PARAMETER_NAMES)
        assert set(STONE_MAPPING[kinematic_type].values()) == set(presets["stone-8"])
    assert PRESETS is KINEMATIC_PRESETS["juelich"]
    # Stone's alpha, beta, gamma, delta for the Juelich type (see docs/kinematics.md).
    assert set(PRESETS["static-6"]) == {
        "joint_1_tilt_n_rad", "joint_1_tilt_u_rad", "joint_2_tilt_n_rad", "concentrator_tilt_e_rad",
        "axis_1_initial_angle_rad", "axis_2_initial_angle_rad"}


def test_preset_masks_never_free_unused_ideal_slots():
    for kinematic_type in KINEMATIC_TYPES:
        for name in PRESET_NAMES:
            mask = preset_mask(name, "ideal", kinematic_type)
            assert mask.dtype == torch.bool and mask.shape == (28,)
            assert not any(mask[I[n]] for n in IDEAL_UNUSED_PARAMETERS)
            linear = preset_mask(name, "linear", kinematic_type)
            assert int(linear.sum()) == len(KINEMATIC_PRESETS[kinematic_type][name])
    assert int(preset_mask("static-28", "ideal").sum()) == 22
    assert preset_parameters("static-20", "ideal") == preset_parameters("static-14", "ideal")
    with pytest.raises(ParameterError, match="The 'name' parameter of preset_parameters must be"):
        preset_mask("static-7", "linear")


# Three calibration targets as at Juelich (lower, upper, multi-focus tower) [m] ENU.
TARGETS = torch.tensor([[0.0, 0.0, 36.0], [0.0, 0.0, 43.0], [-17.0, 0.0, 52.0]], dtype=F64)


def beam_jacobian(params, spec, free, extra=()):
    """Column-normalised Jacobian of the beam residual (reflected beam minus direction to the
    target) over 3 x 30 measurements on the three targets."""
    steps, suns, aims = [], [], []
    for j, target in enumerate(TARGETS):
        st, sun = physical_steps(params, spec, target, 6 + j, count=30)
        steps.append(st)
        suns.append(sun)
        aims.append(target.expand(30, 3))
    steps, suns, aims = torch.cat(steps), torch.cat(suns), torch.cat(aims)
    free = torch.cat([free, torch.tensor(list(extra), dtype=torch.long)])

    def residual(z):
        q = params.index_put((free,), z)
        n, x = forward_kinematics(q, spec, steps)
        return (reflect(-suns, n) - torch.nn.functional.normalize(aims - x, dim=-1)).reshape(-1)

    jac = jacfwd(residual)(params[free])
    return jac / torch.linalg.vector_norm(jac, dim=0)


@pytest.mark.parametrize("kinematic_type", KINEMATIC_TYPES)
@pytest.mark.parametrize("preset", ["static-6", "stone-8", "static-14"])
def test_presets_are_identifiable(kinematic_type, preset):
    # The beam residual depends on the normals and, via the mirror centre, on translations. With
    # measurements on several targets these presets give a well-conditioned Jacobian.
    params, spec, _ = make_case(kinematic_type, 6)
    free = torch.nonzero(preset_mask(preset, spec.actuator_type, kinematic_type)).ravel()
    s = torch.linalg.svdvals(beam_jacobian(params, spec, free))
    assert float(s[-1] / s[0]) > 1e-3
    if kinematic_type == "juelich":
        # Adding joint_2_tilt_e (exactly an axis-1 offset for this type) breaks the rank.
        s = torch.linalg.svdvals(beam_jacobian(params, spec, free, [I["joint_2_tilt_e_rad"]]))
        assert float(s[-1] / s[0]) < 1e-10


def test_linear_actuator_scale_degeneracy():
    # Scaling offset, pivot radius and initial stroke by k and the increment by 1/k leaves every
    # angle unchanged (the law of cosines only sees ratios): static-20 has one exact null
    # direction per linear axis (see docs/kinematics.md).
    spec = HeliostatSpec("juelich", "linear", [False, True], [0, 0], [69001, 75454], [0.0, 0, 0])
    p = params_from(BE36_ACTUATORS)
    q = p.clone()
    k = 1.3
    for i in (1, 2):
        for f in ("initial_stroke_length_m", "offset_m", "pivot_radius_m"):
            q[I[f"axis_{i}_{f}"]] *= k
        q[I[f"axis_{i}_increment"]] /= k
    steps = torch.rand(30, 2, generator=torch.Generator().manual_seed(2), dtype=F64) * 60000
    torch.testing.assert_close(joint_angles(q, spec, steps), joint_angles(p, spec, steps))


BE36_ROW = {
    # Written out from PAINT BE36-heliostat-properties.json in heliostats.parquet's layout
    # (ENU position made up; axis 1 initial angle already in ARTIST's convention).
    "heliostat_id": "BE36", "kinematic_type": "juelich", "actuator_type": "linear",
    "heliostat_e_m": -3.5, "heliostat_n_m": 132.0, "heliostat_u_m": 1.7,
    "initial_orientation_e": 0.0, "initial_orientation_n": -1.0, "initial_orientation_u": 0.0,
    "joint_1_translation_e_m": 0.0, "joint_1_translation_n_m": 0.0, "joint_1_translation_u_m": 0.0,
    "joint_2_translation_e_m": 0.0, "joint_2_translation_n_m": 0.0, "joint_2_translation_u_m": 0.0,
    "concentrator_translation_e_m": 0.0, "concentrator_translation_n_m": 0.175,
    "concentrator_translation_u_m": 0.0,
    "axis_1_increment": 154166.6667, "axis_1_initial_stroke_length_m": 0.075676335,
    "axis_1_offset_m": 0.335308, "axis_1_pivot_radius_m": 0.338095,
    "axis_1_initial_angle_rad": -1.557135677, "axis_1_clockwise": False,
    "axis_1_min_steps": 0, "axis_1_max_steps": 69001,
    "axis_1_gear_ratio_steps_per_rad": float("nan"), "axis_1_angle_offset_rad": float("nan"),
    "axis_2_increment": 154166.6667, "axis_2_initial_stroke_length_m": 0.078387399,
    "axis_2_offset_m": 0.340771, "axis_2_pivot_radius_m": 0.3191,
    "axis_2_initial_angle_rad": 0.937086489, "axis_2_clockwise": True,
    "axis_2_min_steps": 0, "axis_2_max_steps": 75454,
    "axis_2_gear_ratio_steps_per_rad": float("nan"), "axis_2_angle_offset_rad": float("nan"),
    "primary_axis_e": float("nan"), "primary_axis_n": float("nan"), "primary_axis_u": float("nan"),
}


def test_spec_and_nominal_parameters_from_row():
    row = pd.Series(BE36_ROW)
    spec = HeliostatSpec.from_row(row)
    assert spec.kinematic_type == "juelich" and spec.actuator_type == "linear"
    assert spec.clockwise.tolist() == [False, True]
    assert spec.max_steps.tolist() == [69001.0, 75454.0]
    assert spec.position_enu.tolist() == [-3.5, 132.0, 1.7]
    p = nominal_parameters(row)
    assert p.dtype == F64 and p.shape == (28,)
    assert float(p[I["concentrator_translation_n_m"]]) == 0.175
    assert float(p[I["axis_2_pivot_radius_m"]]) == 0.3191
    assert float(p[I["axis_1_initial_angle_rad"]]) == -1.557135677
    assert float(p[[I[f"{b}_tilt_{d}_rad"] for b in ("joint_1", "joint_2", "concentrator")
                    for d in "enu"]].abs().sum()) == 0.0


def test_spec_from_row_ideal_and_target_aligned():
    row = dict(BE36_ROW, heliostat_id="X1", kinematic_type="target-aligned", actuator_type="ideal",
               axis_1_gear_ratio_steps_per_rad=5000.0, axis_1_angle_offset_rad=0.01,
               axis_2_gear_ratio_steps_per_rad=6000.0, axis_2_angle_offset_rad=-0.02,
               primary_axis_e=0.0, primary_axis_n=-3.0, primary_axis_u=4.0)
    spec = HeliostatSpec.from_row(pd.Series(row))
    torch.testing.assert_close(spec.primary_axis, torch.tensor([0.0, -0.6, 0.8], dtype=F64))
    p = nominal_parameters(pd.Series(row))
    assert float(p[I["axis_1_increment"]]) == 5000.0
    assert float(p[I["axis_2_initial_angle_rad"]]) == -0.02
    assert all(float(p[I[n]]) == 0.0 for n in IDEAL_UNUSED_PARAMETERS)
    with pytest.raises(ParameterError, match="primary_axis"):
        HeliostatSpec.from_row(pd.Series(dict(row, primary_axis_n=float("nan"))))


def test_spec_from_frame_batches_and_rejects_mixed_types():
    frame = pd.DataFrame([BE36_ROW, dict(BE36_ROW, heliostat_id="B2", heliostat_e_m=5.0)])
    spec = HeliostatSpec.from_frame(frame)
    assert spec.batch_shape == (2,) and spec.heliostat_id == ("BE36", "B2")
    params = nominal_parameters(frame)
    assert params.shape == (2, 28)
    steps = torch.tensor([[[1000.0, 2000.0]], [[1000.0, 2000.0]]], dtype=F64)
    n, x = forward_kinematics(params, spec, steps)
    torch.testing.assert_close(n[0], n[1])
    torch.testing.assert_close(x[1] - x[0], torch.tensor([[8.5, 0.0, 0.0]], dtype=F64))
    mixed = pd.DataFrame([BE36_ROW, dict(BE36_ROW, actuator_type="ideal")])
    with pytest.raises(ParameterError, match="group the rows"):
        HeliostatSpec.from_frame(mixed)
