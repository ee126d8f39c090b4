"""The field prior (issue 34): MAP fits under a Gaussian prior, the empirical-Bayes estimate, its
leave-out rule, what does not match, and the simulator's field mounting.

Expected values and their sources:

* MAP under a Gaussian prior on noiseless data: the data residuals vanish at the true
  parameters, so to first order the MAP fit is ``x_true + (J'J + D)^-1 D (m - x_true)`` with ``J``
  the data Jacobian at the truth, ``D = diag(1 / sigma^2)`` and ``m`` the prior mean (the
  closed-form Gaussian posterior of the linearised problem). The shift is 0.2 prior sigma, so
  the second-order term is far below the 2 % tolerance;
* a prior sigma of 1e-9 pins its parameter at the prior mean (the data would move it by the
  shift, 1e-4 rad or more, opposed by a curvature 1e18 times that of the data's);
* the estimate: deviations drawn from N(mu, tau^2) plus fit noise N(0, s^2) (known), so the
  median is within 4 standard errors (1.2533 sqrt(tau^2 + s^2) / sqrt(n)) of mu and the noise-free
  spread sqrt(scale^2 - s^2) within 15 % of tau for n = 400 (the MAD's relative standard error
  is about 1.65 / sqrt(n) = 8 %... of scale; 15 % of tau covers 1.9 of them);
* leave-out: with at most MAX_FOLDS heliostats each is its own fold, so its own deviation cannot
  change its prior at all (equality, not a tolerance).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.pipeline.models.coarse import MeasurementBatch, fit_heliostat
from heliocal.pipeline.models.field_prior import (MAX_FOLDS, MIN_HELIOSTATS, FitSample,
                                                  GroupPrior, default_sigma, estimate_prior)
from heliocal.pipeline.models.mounting import CORRELATION_LENGTH_M, MOUNTING_PARAMETERS
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.physics.jacobian import residual_and_jacobian
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX, PARAMETER_NAMES
from heliocal.pipeline.stages.coarse_prior import (PRIOR_ROUNDS, _estimate, _estimate_from_rows,
                                                   _from_table)

N = len(PARAMETER_NAMES)


def _simulated(n: int = 60, seed: int = 3):
    """One noiseless static heliostat: (spec, nominal (28,), true (28,), its rows as a batch),
    straight from the simulator (its spots are where the true geometry sends the beam)."""
    field = simulate_field(1, seed=seed, measurements=(n, n), kinematic_types=("juelich",),
                           dynamic_fraction=0.0, noise_mrad=0.0, deviations="static-6")
    sim = next(iter(field.heliostats.values()))
    return sim.spec, sim.nominal, sim.true, MeasurementBatch.from_frame(field.measurements)


@pytest.fixture(scope="module")
def heliostat():
    return _simulated()


def test_map_fit_is_the_closed_form_gaussian_posterior(heliostat):
    spec, nominal, true, data = heliostat
    free = np.flatnonzero(fit_heliostat(spec, nominal, data, "static-6", loss="linear",
                                        robust_start=False, prior_weight=0.0).free)
    sigma = 0.05 * default_sigma(nominal.numpy())
    mean = true.numpy().copy()
    mean[free] += 0.2 * sigma[free] * np.where(np.arange(len(free)) % 2, 1.0, -1.0)
    fit = fit_heliostat(spec, nominal, data, "static-6", loss="linear", robust_start=False,
                        prior=(mean, sigma), tolerance=1e-14)
    _, J = residual_and_jacobian(true, spec, data.steps, data.sun, data.focal_spot)
    J = J.reshape(-1, N).numpy()[:, free]
    D = np.diag(1.0 / sigma[free] ** 2)
    expected = true.numpy()[free] + np.linalg.solve(J.T @ J + D, D @ (mean - true.numpy())[free])
    shift = expected - true.numpy()[free]
    got = fit.params.numpy()[free] - true.numpy()[free]
    assert np.all(np.abs(shift) > 1e-7)          # the prior does pull
    np.testing.assert_allclose(got, shift, rtol=0.02, atol=1e-3 * np.abs(shift).max())


def test_a_prior_with_zero_scale_pins_its_parameter(heliostat):
    spec, nominal, true, data = heliostat
    i = PARAMETER_INDEX["axis_1_initial_angle_rad"]
    mean, sigma = true.numpy().copy(), default_sigma(nominal.numpy())
    mean[i] += 1e-3          # 1 mrad off the truth the data point to
    sigma[i] = 1e-9
    fit = fit_heliostat(spec, nominal, data, "static-6", loss="linear", robust_start=False,
                        prior=(mean, sigma))
    assert abs(float(fit.params[i]) - mean[i]) < 1e-8
    # and without the pin the data take it back to the truth
    sigma[i] = default_sigma(nominal.numpy())[i]
    free = fit_heliostat(spec, nominal, data, "static-6", loss="linear", robust_start=False,
                         prior=(mean, sigma), prior_weight=1e-12)
    assert abs(float(free.params[i]) - float(true[i])) < 1e-7


def _sample(n: int, mu: np.ndarray, tau: np.ndarray, s: np.ndarray, seed: int = 0,
            determined: np.ndarray | None = None) -> FitSample:
    rng = np.random.default_rng(seed)
    dev = mu + tau * rng.standard_normal((n, N)) + s * rng.standard_normal((n, N))
    det = np.ones((n, N), bool) if determined is None else np.broadcast_to(determined, (n, N))
    return FitSample(np.array([f"H{k:04d}" for k in range(n)], dtype=object), dev,
                     np.broadcast_to(s, (n, N)).copy(), det.copy(),
                     rng.uniform(0, 200, (n, 2)))


def test_estimate_recovers_the_generating_distribution():
    mu = np.linspace(-2e-3, 2e-3, N)
    tau, s = np.full(N, 1e-3), np.full(N, 0.5e-3)
    n = 400
    est = estimate_prior(_sample(n, mu, tau, s))
    se = 1.2533 * np.sqrt(tau ** 2 + s ** 2) / np.sqrt(n)
    assert np.all(np.abs(est.mean - mu) < 4 * se)
    np.testing.assert_allclose(est.tau, tau, rtol=0.15)
    # the sigma a heliostat gets adds the median's own uncertainty: a little above tau
    assert np.all(est.sigma > est.tau) and np.all(est.sigma < 1.05 * est.tau)
    assert np.all(est.n == n)


def test_a_parameter_without_enough_determined_heliostats_keeps_the_default_prior():
    mu, tau, s = np.zeros(N), np.full(N, 1e-3), np.full(N, 1e-4)
    det = np.ones(N, bool)
    det[5] = False
    sample = _sample(MIN_HELIOSTATS, mu, tau, s, determined=det)
    est = estimate_prior(sample)
    assert not est.used[5] and est.used[4]
    # one heliostat fewer: no parameter has a prior (the stage then fits as --prior none)
    fewer = estimate_prior(sample, keep=np.arange(MIN_HELIOSTATS) > 0)
    assert not fewer.used.any()
    nominal = np.ones(N)
    mean, sigma, noise, _ = est.heliostat_prior(nominal)
    assert sigma[5] == default_sigma(nominal)[5] and mean[5] == nominal[5]
    assert noise[5] == 1.0      # the default prior keeps its 1 mrad scale


def test_a_heliostats_own_fit_never_enters_its_own_prior():
    n = MAX_FOLDS     # leave-one-out
    sample = _sample(n, np.zeros(N), np.full(N, 1e-3), np.full(N, 1e-4), seed=2)
    nominal = np.zeros(N)
    before = GroupPrior.estimate(sample, posterior=False).prior_of("H0003", nominal)
    sample.deviations[3] += 1.0   # a wildly different fit of its own
    group = GroupPrior.estimate(sample, posterior=False)
    after = group.prior_of("H0003", nominal)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
    # ... while the others' priors (and the field's) do see it
    assert not np.array_equal(group.whole.mean,
                              GroupPrior.estimate(_sample(n, np.zeros(N), np.full(N, 1e-3),
                                                          np.full(N, 1e-4), seed=2),
                                                  posterior=False).whole.mean)


def _helio(ids, kt="juelich", at="ideal", source="paint"):
    return pd.DataFrame({"heliostat_id": ids, "kinematic_type": kt, "actuator_type": at,
                         "properties_source": source,
                         "heliostat_e_m": np.arange(len(ids), dtype=float),
                         "heliostat_n_m": 0.0}).set_index("heliostat_id", drop=False)


def test_a_type_with_one_heliostat_gets_a_note_and_no_prior():
    helio = _helio(["A1"])
    calls = []

    def fit_sample(samples, priors):
        calls.append(samples)
        return {}

    estimates, notes = _estimate(helio, {"A1": pd.DataFrame({"split": ["train"] * 30})},
                                 {("juelich", "ideal", "properties"): ["A1"]}, ("static-6",),
                                 spatial=False, fit_sample=fit_sample)
    # one sample fit per round, each of no heliostat (a sample of one teaches nothing)
    assert estimates == {} and calls == [{}] * PRIOR_ROUNDS
    assert len(notes) == 1 and "no field prior for the 1 heliostats of type juelich/ideal" in notes[0]
    assert "fitted with the default prior" in notes[0]


def _prior_table(kt="juelich", at="linear", preset="static-6", parameters=PARAMETER_NAMES):
    return pd.DataFrame({"kinematic_type": kt, "actuator_type": at, "geometry_source": "properties",
                         "preset": preset, "parameter": list(parameters),
                         "parameter_index": np.arange(len(parameters)), "mean": 0.0,
                         "scale": 1e-3, "n_heliostats": 20})


def test_a_prior_from_another_plant_or_preset_is_refused_with_a_reason():
    helio = _helio(["A1", "A2"], at="linear")
    groups = {("juelich", "linear", "properties"): ["A1", "A2"]}
    # another plant: its only group is an az-el type
    est, notes = _from_table(_prior_table(kt="az-el"), groups, ("static-6",), helio, "OTHER")
    assert est == {} and "the prior of OTHER has no heliostats of type juelich/linear" in notes[0]
    assert "(it has az-el/linear/properties)" in notes[0]
    # the preset's parameters do not match: a scale on every parameter, static-6 frees few
    table = _prior_table()
    est, why = _estimate_from_rows(table, "static-6", ("juelich", "linear", "properties"))
    assert est is None and "which the preset does not fit on type juelich/linear" in why
    # a table with a parameter missing
    est, why = _estimate_from_rows(table.iloc[:-1], "static-6", ("juelich", "linear", "properties"))
    assert est is None and "does not list the 28 parameters once each" in why


def test_field_mounting_is_systematic_per_type_and_spatially_correlated():
    field = simulate_field(150, seed=5, measurements=(3, 3), kinematic_types=("juelich",),
                           dynamic_fraction=0.0, deviations="static-20", mounting="field")
    sims = list(field.heliostats.values())
    name = MOUNTING_PARAMETERS["juelich"][0]
    i = PARAMETER_INDEX[name]
    dev = np.array([float(h.true[i] - h.nominal[i]) for h in sims])
    pos = np.array([h.spec.position_enu[:2].numpy() for h in sims])
    d = np.sqrt(((pos[:, None] - pos[None]) ** 2).sum(-1))
    diff2 = (dev[:, None] - dev[None]) ** 2
    near = diff2[(d > 0) & (d < CORRELATION_LENGTH_M / 4)].mean()
    far = diff2[d > 3 * CORRELATION_LENGTH_M].mean()
    # neighbours differ by the individual part only; far pairs by the spatial part too
    assert near < 0.5 * far
    independent = simulate_field(150, seed=5, measurements=(3, 3), kinematic_types=("juelich",),
                                 dynamic_fraction=0.0, deviations="static-20")
    dev_i = np.array([float(h.true[i] - h.nominal[i]) for h in independent.heliostats.values()])
    diff_i = (dev_i[:, None] - dev_i[None]) ** 2
    assert diff_i[(d > 0) & (d < CORRELATION_LENGTH_M / 4)].mean() > 0.5 * diff_i[d > 3 * CORRELATION_LENGTH_M].mean()


def test_the_prior_is_weighed_against_the_measurements_noise():
    """A field prior is a statement in parameter units; the data rows are in mrad, so it must be
    weighed against the measurements' noise ``s``. Expected value: in the linearised Gaussian
    problem a prior N(m, sigma^2) on one parameter moves its estimate from the fit without it,
    ``x`` (standard error ``se``), by ``se^2 / (se^2 + sigma^2) (m - x)`` (the precision-weighted
    mean of two Gaussians); with ``sigma = se`` that is half the way. Stated against 1 mrad
    instead of the actual 0.1 mrad the prior would be 100 times too strong: 0.99 of the way."""
    field = simulate_field(1, seed=4, measurements=(80, 80), kinematic_types=("juelich",),
                           dynamic_fraction=0.0, noise_mrad=0.1, deviations="static-6")
    sim = next(iter(field.heliostats.values()))
    spec, nominal = sim.spec, sim.nominal
    data = MeasurementBatch.from_frame(field.measurements)
    plain = fit_heliostat(spec, nominal, data, "static-6", loss="linear", robust_start=False)
    j = PARAMETER_INDEX["concentrator_tilt_e_rad"]
    x, se, s = plain.params.numpy(), plain.std_error, plain.noise_mrad
    # the simulator's 0.1 mrad of beam noise: the normal (the bisector) moves by half of it,
    # spread over the residual's three components
    assert 0.02 < s < 0.1
    mean = x.copy()
    mean[j] += 3 * se[j]
    sigma = default_sigma(nominal.numpy())
    sigma[j] = se[j]
    noise = np.ones(N)
    noise[j] = s
    fit = fit_heliostat(spec, nominal, data, "static-6", loss="linear", robust_start=False,
                        prior=(mean, sigma, noise))
    moved = (fit.params.numpy()[j] - x[j]) / (3 * se[j])
    assert moved == pytest.approx(0.5, abs=0.03)


def test_each_heliostat_weighs_the_field_prior_against_its_own_noise():
    """Two heliostats, one measured five times more precisely than the other, get the same field
    prior N(m, sigma^2) on one parameter, weighed against the field's noise ``s_f`` (the two
    heliostats' mean noise). Expected value (the precision-weighted mean of two Gaussians, the
    linearised posterior): from its fit without the prior ``x`` (standard error ``se`` for noise
    ``s``) a heliostat moves by ``se'^2 / (se'^2 + sigma^2) (m - x)`` with ``se' = se s' / s``,
    ``s'`` its own noise as prior_noise estimates it (``sqrt((d0 s_f^2 + RSS) / (d0 + dof))``
    from the residuals, within 25 % of ``s`` here, and at most ``s_f``). With ``sigma = se`` of
    the precise one and ``m - x = 3 se``, the precise heliostat (s 0.019 mrad) moves 0.60 of the
    way; the noisy one (0.094 mrad, above ``s_f`` = 0.056 mrad, so it keeps ``s_f``) 0.90, as
    both did before each was weighed against its own noise. Tolerance 0.03 of the
    way: the MAP fit's residuals and dof differ a little from the plain fit's."""
    from heliocal.pipeline.models.coarse_presets import fit_presets
    from heliocal.pipeline.models.prior_noise import NOISE_PRIOR_DOF, HeliostatPrior

    j = PARAMETER_INDEX["concentrator_tilt_e_rad"]
    sims = []
    for name, noise in (("PRECISE", 0.04), ("NOISY", 0.2)):
        field = simulate_field(1, seed=4, measurements=(150, 150), kinematic_types=("juelich",),
                               dynamic_fraction=0.0, noise_mrad=noise, deviations="static-6")
        sim = next(iter(field.heliostats.values()))
        sims.append((dataclasses.replace(sim.spec, heliostat_id=name), sim.nominal,
                     MeasurementBatch.from_frame(field.measurements)))
    options = dict(solver="batched", loss="linear", robust_start=False)
    plain = [f[0] for f in fit_presets(*zip(*sims), ["static-6"], **options)]
    s_field = float(np.mean([f.noise_mrad for f in plain]))
    precise = plain[0]
    sigma_j = precise.std_error[j]
    priors, expected = {}, []
    for k, ((spec, nominal, data), fit) in enumerate(zip(sims, plain)):
        x, se, s = fit.params.numpy(), fit.std_error[j], fit.noise_mrad
        rss = s ** 2 * (3 * len(data) - int(fit.free.sum()))
        s_own = np.sqrt((NOISE_PRIOR_DOF * s_field ** 2 + rss) / (NOISE_PRIOR_DOF
                                                                 + 3 * len(data) - fit.free.sum()))
        assert abs(s_own / s - 1) < 0.25
        se_own = se * min(s_own, s_field) / s    # never above the field's noise
        expected.append(se_own ** 2 / (se_own ** 2 + sigma_j ** 2))
        mean, sigma = x.copy(), default_sigma(nominal.numpy())
        mean[j] += 3 * sigma_j
        sigma[j] = sigma_j
        mask = np.zeros(N, bool)
        mask[j] = True
        priors[spec.heliostat_id] = {"static-6": HeliostatPrior(
            mean, sigma, np.where(mask, s_field, 1.0), mask)}
    assert len(priors) == 2 and plain[1].noise_mrad > 3 * precise.noise_mrad
    fits = [f[0] for f in fit_presets(*zip(*sims), ["static-6"], priors=priors, **options)]
    moved = [(f.params.numpy()[j] - p.params.numpy()[j]) / (3 * sigma_j)
             for f, p in zip(fits, plain)]
    assert expected[0] == pytest.approx(0.60, abs=0.05)
    assert expected[1] == pytest.approx(0.90, abs=0.01)
    np.testing.assert_allclose(moved, expected, atol=0.03)


def test_only_field_entries_are_reweighed_and_only_beyond_the_factor():
    """reweighed: the moderated own noise ``sqrt((d0 s_f^2 + RSS) / (d0 + dof))`` replaces the
    field's noise on the field's entries only (the default prior stays stated against 1 mrad),
    and only when it differs from ``s_f`` by more than NOISE_REFIT_FACTOR. With d0 = 30, s_f =
    0.2 mrad and 300 dof at 0.1 mrad (RSS 3.0 mrad^2): sqrt((1.2 + 3.0) / 330) = 0.1128 mrad."""
    from types import SimpleNamespace

    from heliocal.pipeline.models.prior_noise import (NOISE_PRIOR_DOF, HeliostatPrior,
                                                      reweighed)

    assert NOISE_PRIOR_DOF == 30.0
    mask = np.zeros(N, bool)
    mask[:4] = True
    prior = HeliostatPrior(np.zeros(N), np.ones(N), np.where(mask, 0.2, 1.0), mask)
    precise = SimpleNamespace(data_rss_mrad2=3.0, data_dof=300.0)
    got = reweighed(prior, precise)
    np.testing.assert_allclose(got.noise[mask], np.sqrt(4.2 / 330), rtol=1e-12)
    np.testing.assert_array_equal(got.noise[~mask], 1.0)
    # like the field's (0.19 mrad), or noisier (at most the field's noise counts): no second
    # solve; no field mask, or no residuals: none either
    assert reweighed(prior, SimpleNamespace(data_rss_mrad2=0.19 ** 2 * 300, data_dof=300.0)) is None
    assert reweighed(prior, SimpleNamespace(data_rss_mrad2=1.0 ** 2 * 300, data_dof=300.0)) is None
    assert reweighed(prior._replace(field=None), precise) is None
    assert reweighed(tuple(prior[:3]), precise) is None
    assert reweighed(prior, SimpleNamespace(data_rss_mrad2=float("nan"), data_dof=0.0)) is None
