"""Which fits inform the field prior (issue 34): a parameter counts where the fit's data alone
pin it at the fit's *own* noise, not at the 1 mrad the 'determined' flag assumes.

Expected values and their sources:

* the data-only standard error of a linear least-squares problem is ``s sqrt([(J'J)^-1]_jj)``
  with ``s^2 = RSS / (n - P)``; for the data rows ``[1, 1, 0, 0]`` and ``[0, 0, 2, 2]`` (two
  parameters) ``J'J = diag(2, 8)``, so per unit noise ``1/sqrt(2)`` and ``1/sqrt(8)``; the
  residuals ``(0.1, -0.1, 0.2, -0.2)`` over ``4 - 3`` degrees of freedom give ``s^2 = 0.1``. A
  third parameter the data rows do not see has none (NaN). Without residual degrees of freedom
  the noise is unknown and 1 mrad stands in (the convention of the default prior);
* a simulated field measured to 0.1 mrad per axis (fits' noise about 0.04 mrad per residual
  component): at 1 mrad the data-only standard error of axis 1's zero point is above half the
  default prior sigma on most of its 60-row heliostats, at their own noise it is 25 times
  smaller; so under the 1 mrad rule fewer than MIN_HELIOSTATS of the 12 heliostats determine it
  and it keeps the default prior, under the own-noise rule it gets the field's. The prior's mean
  is the median of 11 fits (standard error about 1.25 x 1.1 mrad / sqrt(11) = 0.4 mrad), so it
  lies within one true field standard deviation (1.0 mrad) of the true median deviation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from heliocal.pipeline.models.coarse import MeasurementBatch
from heliocal.pipeline.models.coarse_presets import fit_presets
from heliocal.pipeline.models.field_prior import (MIN_HELIOSTATS, FitSample, estimate_prior,
                                                  informs)
from heliocal.pipeline.models.fit_diagnostics import fit_diagnostics
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX, PARAMETER_NAMES

N = len(PARAMETER_NAMES)


def _linear_case(n_rows: int):
    """(J, r) of a linear problem with 3 free parameters: the data rows (``n_rows`` of the four
    below), then one prior row per parameter (unit sigma, at the solution)."""
    data = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 2.0, 0.0]])[:n_rows]
    J = np.vstack([data, np.eye(3)])
    r = np.concatenate([np.array([0.1, -0.1, 0.2, -0.2])[:n_rows], np.zeros(3)])
    return J, r


def test_the_data_only_standard_error_is_at_the_fits_own_noise():
    J, r = _linear_case(4)
    d = fit_diagnostics(J, r, 4, np.array([0, 1, 2]), np.ones(N))
    s = math.sqrt(0.1)
    np.testing.assert_allclose(d.data_only_std_error[:2], [s / math.sqrt(2), s / math.sqrt(8)],
                               rtol=1e-9)
    assert np.isnan(d.data_only_std_error[2])              # the data do not see it
    assert np.isnan(d.data_only_std_error[3:]).all()       # fixed
    # the 'determined' flag states the same for 1 mrad: 1/sqrt(2) is above half the sigma of 1
    assert list(d.determined[:3]) == [False, True, False]
    # no residual degrees of freedom (3 rows, 3 parameters): the noise is unknown, 1 mrad
    J3, r3 = _linear_case(3)
    d3 = fit_diagnostics(J3, r3, 3, np.array([0, 1, 2]), np.ones(N))
    np.testing.assert_allclose(d3.data_only_std_error[:2], [1 / math.sqrt(2), 1.0 / 2.0],
                               rtol=1e-9)


@pytest.fixture(scope="module")
def precise_field():
    """12 static heliostats of one type, 60 rows each, measured to 0.1 mrad, their deviations
    from the type's distribution (``mounting="field"``); each fitted with static-20 under the
    default prior, as the field prior's sample is."""
    field = simulate_field(12, seed=5, measurements=(60, 60), kinematic_types=("juelich",),
                           dynamic_fraction=0.0, noise_mrad=0.1, deviations="static-20",
                           mounting="field")
    ids = sorted(field.heliostats)
    sims = [field.heliostats[h] for h in ids]
    rows = field.measurements
    trains = [MeasurementBatch.from_frame(rows[rows["heliostat_id"] == h]) for h in ids]
    fits = [f[0] for f in fit_presets([s.spec for s in sims], [s.nominal for s in sims], trains,
                                      ["static-20"])]
    return ids, sims, fits


def test_a_precise_field_informs_the_prior_of_what_1_mrad_calls_undetermined(precise_field):
    ids, sims, fits = precise_field
    i = PARAMETER_INDEX["axis_1_initial_angle_rad"]
    determined = sum(bool(f.determined[i]) for f in fits)
    informed = sum(bool(informs(f)[i]) for f in fits)
    assert determined < MIN_HELIOSTATS <= informed
    sample = FitSample.of(ids, fits, np.zeros((len(ids), 2)))
    est = estimate_prior(sample)
    assert est.used[i]
    true = np.array([float(s.true[i] - s.nominal[i]) for s in sims])
    assert abs(est.mean[i] - np.median(true)) < true.std()
    # the rule at 1 mrad (the fits' 'determined' flags) leaves it to the default prior
    at_1_mrad = np.stack([f.free & f.determined for f in fits])
    old = estimate_prior(FitSample(sample.heliostat_ids, sample.deviations, sample.std_errors,
                                   at_1_mrad, sample.positions, sample.noise_mrad))
    assert not old.used[i]
    # every parameter the 1 mrad rule gives a prior keeps one
    assert np.all(est.used[old.used])


def test_a_fit_without_the_data_only_error_falls_back_to_its_determined_flags(precise_field):
    _, _, fits = precise_field
    fit = fits[0]
    bare = type(fit)(**{**fit.__dict__, "data_only_std_error": None})
    np.testing.assert_array_equal(informs(bare), fit.free & fit.determined)
