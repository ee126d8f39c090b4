"""How much a coarse fit leans on its prior (``prior_shrinkage``, issue 34; docs/field_prior.md).

Expected values and their sources:

* hand-made Jacobians, where ``[H^-1]_jj [H_prior]_jj`` has a closed form: one data column of
  curvature ``a`` beside a prior of curvature ``l`` gives ``l / (a + l)``; a zero data column
  gives exactly 1; two parameters the data see only through their sum (equal prior curvature
  ``l``, data curvature ``a`` on the sum) give ``1 - a / (l + 2a)``, which tends to 1/2;
* a noiseless simulated heliostat (spots exactly where the true geometry sends the beam):
  ``concentrator_tilt_n_rad``, a roll about the mirror normal, does not move the normal, so its
  data column is zero (norm ~1e-13 against ~7e3 of the other tilts) and its shrinkage is 1 up to
  ~1e-30; static-6 on 120 rows is fully determined: weighed against 0.2 mrad its shrinkage was
  0.02-0.07 (measured; the tilts and zero points are correlated), and it scales with the prior's
  curvature, ``(noise / sigma)^2``, so a heliostat ten times as precise (0.02 mrad) stays below
  0.001 (0.01 asserted);
* every fit's value equals the formula evaluated here from the Jacobian of
  :func:`~heliocal.pipeline.physics.jacobian.residual_and_jacobian` at the solution, the prior
  rows and the loss weights written out (not the module's code);
* the noise a field prior is weighed against: on noiseless rows the own estimate is
  ``s_f sqrt(30 / (30 + dof))`` (RSS ~ 0, :mod:`~heliocal.pipeline.models.prior_noise`) with
  ``n_data - P <= dof <= n_data``, more than 1.25x below ``s_f``, so the fit is solved again
  under it.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from heliocal.pipeline.models.coarse import (MeasurementBatch, fit_heliostat,
                                             fit_heliostats_batched, prior_sigma)
from heliocal.pipeline.models.coarse_presets import fit_presets
from heliocal.pipeline.models.fit_diagnostics import prior_shrinkage
from heliocal.pipeline.models.prior_noise import HeliostatPrior
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.physics.jacobian import residual_and_jacobian
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX, HeliostatSpec, nominal_parameters
from heliocal.pipeline.stages.ingest import ingest
from heliocal.pipeline.stages.simulate import write_field

FIELD_NOISE_MRAD = 0.2


def test_closed_forms_of_hand_made_jacobians():
    lam, a = 4.0, 9.0
    # one determined column, one the data do not see: l / (a + l) and 1
    J = np.vstack([np.array([[3.0, 0.0]]), np.diag([2.0, 2.0])])  # data row, prior rows
    share = prior_shrinkage(J, np.zeros(3), 1)
    assert share[0] == pytest.approx(lam / (a + lam), abs=1e-12)
    assert share[1] == pytest.approx(1.0, abs=1e-12)
    # two parameters seen only through their sum: 1 - a / (l + 2 a), -> 1/2 for a >> l
    for a_sum in (9.0, 1e8):
        J = np.vstack([np.array([[np.sqrt(a_sum), np.sqrt(a_sum)]]), np.diag([2.0, 2.0])])
        expected = 1.0 - a_sum / (lam + 2.0 * a_sum)
        assert prior_shrinkage(J, np.zeros(3), 1) == pytest.approx([expected] * 2, abs=1e-9)
    # no prior rows: no shrinkage
    assert prior_shrinkage(np.ones((3, 2)), np.zeros(3), 3) is None


@pytest.fixture(scope="module")
def heliostat(tmp_path_factory):
    field = simulate_field(1, seed=3, measurements=(120, 120), kinematic_types=("juelich",),
                           dynamic_fraction=0.0, noise_mrad=0.0, deviations="static-6")
    out = tmp_path_factory.mktemp("shrink") / "sim"
    write_field(field, out)
    measurements, helio, _, _ = ingest([out / "paint"])
    row = helio.iloc[0]
    true = field.heliostats[row["heliostat_id"]].true
    return (HeliostatSpec.from_row(row), nominal_parameters(row),
            MeasurementBatch.from_frame(measurements), true)


def _prior(nominal, true, field=True, noise_mrad=FIELD_NOISE_MRAD):
    """A field-like prior centred on the true geometry (so the noiseless fit is the truth and
    every residual 0): 1 mrad for angles, a tenth of the default elsewhere, weighed against
    ``noise_mrad``."""
    sigma = np.where(prior_sigma(nominal) >= 0.05, 1e-3, prior_sigma(nominal) * 0.1)
    noise = np.full(28, noise_mrad)
    return HeliostatPrior(true.numpy().copy(), sigma, noise,
                          np.ones(28, bool) if field else None)


def _expected(fit, spec, data, prior, loss):
    """[H^-1]_jj [H_prior]_jj from the data Jacobian at the solution, written out here."""
    free = np.flatnonzero(fit.free)
    r, jac = residual_and_jacobian(fit.params, spec, data.steps, data.sun, data.focal_spot)
    jd = jac.reshape(-1, 28)[:, free].numpy()
    rd = r.reshape(-1).numpy()
    scale = prior.noise[free] / prior.sigma[free]          # prior rows' d r / d p
    rp = (fit.params.numpy()[free] - prior.mean[free]) * scale
    weight = (lambda x: 1.0 / np.sqrt(1.0 + x ** 2)) if loss == "soft_l1" else np.ones_like
    h_data = jd.T @ (weight(rd)[:, None] * jd)
    h_prior = np.diag(weight(rp) * scale ** 2)
    return np.diag(np.linalg.inv(h_data + h_prior)) * np.diag(h_prior)


def test_a_roll_the_data_do_not_see_leans_wholly_on_the_prior(heliostat):
    spec, nominal, data, true = heliostat
    prior = _prior(nominal, true)
    fit = fit_heliostat(spec, nominal, data, "static-28", loss="linear", robust_start=False,
                        prior=prior)
    free = np.flatnonzero(fit.free)
    roll = PARAMETER_INDEX["concentrator_tilt_n_rad"]
    assert roll in free
    assert fit.prior_shrinkage[roll] == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(fit.prior_shrinkage[free], _expected(fit, spec, data, prior,
                                                                    "linear"), atol=1e-6)
    assert np.isnan(fit.prior_shrinkage[~fit.free]).all()


@pytest.mark.parametrize("loss", ["linear", "soft_l1"])
def test_many_precise_rows_leave_determined_parameters_to_the_data(heliostat, loss):
    spec, nominal, data, true = heliostat
    prior = _prior(nominal, true, noise_mrad=0.02)
    fit = fit_heliostats_batched([spec], [nominal], [data], "static-6", loss=loss,
                                 robust_start=False, priors=[prior])[0]
    free = np.flatnonzero(fit.free)
    assert fit.determined[free].all()
    assert (fit.prior_shrinkage[free] < 0.01).all(), fit.prior_shrinkage[free]
    assert (fit.prior_shrinkage[free] > 0).all()
    np.testing.assert_allclose(fit.prior_shrinkage[free],
                               _expected(fit, spec, data, prior, loss), rtol=1e-4, atol=1e-9)


def test_the_noise_the_prior_is_weighed_against_is_recorded(heliostat):
    spec, nominal, data, true = heliostat
    fit = fit_presets([spec], [nominal], [data], ["static-6"], loss="linear",
                      robust_start="never", priors={spec.heliostat_id: {
                          "static-6": _prior(nominal, true)}})[0][0]
    n_data, p = 3 * len(data), 6
    low = FIELD_NOISE_MRAD * np.sqrt(30.0 / (30.0 + n_data))
    high = FIELD_NOISE_MRAD * np.sqrt(30.0 / (30.0 + n_data - p))
    assert low * (1 - 1e-6) <= fit.own_noise_mrad <= high * (1 + 1e-6)
    assert fit.prior_noise_mrad == fit.own_noise_mrad   # 3.5x below the field's: solved again
    # a prior without field entries (the field's noise unknown) records none
    plain = fit_presets([spec], [nominal], [data], ["static-6"], loss="linear",
                        robust_start="never", priors={spec.heliostat_id: {
                            "static-6": _prior(nominal, true, field=False)}})[0][0]
    assert np.isnan(plain.own_noise_mrad) and np.isnan(plain.prior_noise_mrad)
    assert np.isfinite(plain.prior_shrinkage[plain.free]).all()
