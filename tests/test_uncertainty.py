"""Tests of heliocal.pipeline.models.uncertainty: a coarse fit's parameter covariance and the
aim error it implies.

Expected values and their sources:

* the Woodbury update of :func:`covariance_after` against the direct inverse
  ``(C^-1 + J^T J / s^2)^-1`` (a reference computed here with numpy);
* the covariance against a Monte Carlo reference: one simulated static heliostat (ground truth
  from the simulator), its noiseless spots disturbed 40 times with Gaussian noise of a known
  sigma per target axis, each replica fitted by the batched coarse fit; the mean squared normal
  error of aims made with the fitted parameters (the true chain at the steps the fit chose,
  against the required normal) must match ``trace(J_a C J_a^T)`` averaged over the aims. With
  40 replicas the relative standard error of a mean of squares is about sqrt(2/40) = 22 % per
  aim and less averaged over 30 aims, so 0.7-1.4 is a fair band.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from heliocal.pipeline.models.coarse import MeasurementBatch, fit_heliostats_batched, prior_sigma
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.models.uncertainty import (ParameterCovariance, aim_jacobian,
                                                  aim_variance_mrad2, coarse_covariance,
                                                  covariance_after)
from heliocal.pipeline.physics.jacobian import residual_and_jacobian
from heliocal.pipeline.physics.kinematics import inverse_kinematics


def test_covariance_after_is_the_information_update():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(5, 5))
    c = a @ a.T + 0.1 * np.eye(5)
    cov = ParameterCovariance(np.arange(5), c, 0.3, 10)
    rows = rng.normal(size=(2, 3, 5))
    after = covariance_after(cov, rows)
    jf = rows.reshape(-1, 5)
    reference = np.linalg.inv(np.linalg.inv(c) + jf.T @ jf / 0.3 ** 2)
    np.testing.assert_allclose(after.covariance, reference, rtol=1e-9, atol=1e-12)
    assert after.n_rows == 12 and after.noise_mrad == 0.3
    # nothing measured: nothing changes
    assert covariance_after(cov, np.zeros((0, 3, 5))) is cov


def _plane_noise(rng, normals: np.ndarray, distance_m: np.ndarray, sigma_mrad: float) -> np.ndarray:
    """Gaussian spot noise [m] in each target's plane: sigma_mrad per axis times the distance."""
    u = np.cross(normals, [0.0, 0.0, 1.0])
    u[np.linalg.norm(u, axis=1) < 1e-9] = [1.0, 0.0, 0.0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    k = rng.normal(size=(len(normals), 2)) * (sigma_mrad * 1e-3 * distance_m)[:, None]
    return k[:, :1] * u + k[:, 1:] * v


@pytest.mark.slow
def test_aim_variance_matches_monte_carlo_refits():
    field = simulate_field(1, seed=3, measurements=(90, 90), dynamic_fraction=0.0,
                           noise_mrad=0.0, deviations="static-6")
    h = next(iter(field.heliostats.values()))
    rows = field.measurements.reset_index(drop=True)
    train, aims = rows.iloc[:60].reset_index(drop=True), rows.iloc[60:].reset_index(drop=True)
    sigma_mrad = 0.5
    base = MeasurementBatch.from_frame(train)
    distance = train["distance_m"].to_numpy()
    normals = train[["target_normal_e", "target_normal_n", "target_normal_u"]].to_numpy()
    rng = np.random.default_rng(1)
    replicas = []
    for _ in range(40):
        spots = base.focal_spot.numpy() + _plane_noise(rng, normals, distance, sigma_mrad)
        replicas.append(MeasurementBatch(base.measurement_id, base.steps, base.sun,
                                         torch.from_numpy(spots), base.target_center,
                                         base.target_normal))
    fits = fit_heliostats_batched([h.spec] * len(replicas), [h.nominal] * len(replicas), replicas,
                                  "static-6", loss="linear", robust_start=False)
    free = fits[0].free
    sun = torch.from_numpy(aims[["sun_e", "sun_n", "sun_u"]].to_numpy(copy=True))
    aim_point = torch.from_numpy(aims[["target_e_m", "target_n_m", "target_u_m"]].to_numpy(copy=True))
    squared = []
    for fit in fits:
        steps = inverse_kinematics(fit.params, h.spec, sun, aim_point)
        with torch.no_grad():
            r, _ = residual_and_jacobian(h.true, h.spec, steps, sun, aim_point)
        squared.append((r.numpy() ** 2).sum(axis=1))
    empirical = np.mean(squared, axis=0)                                  # (M,) [mrad^2]
    # the covariance of one replica's fit, with the noise scale it estimates itself
    sig = prior_sigma(h.nominal)[np.flatnonzero(free)]
    cov = coarse_covariance(h.spec, fits[0].params, free, replicas[0], sig)
    steps = inverse_kinematics(fits[0].params, h.spec, sun, aim_point)
    predicted = aim_variance_mrad2(aim_jacobian(h.spec, fits[0].params, cov.free_idx, steps, sun,
                                                aim_point), cov)
    # the noise estimate: the normal's angle error is half the beam's, sigma_mrad / 2 per axis
    assert cov.noise_mrad == pytest.approx(sigma_mrad / 2, rel=0.25)
    ratio = float(empirical.mean() / predicted.mean())
    assert 0.7 < ratio < 1.4, ratio
