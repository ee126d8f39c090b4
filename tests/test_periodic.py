"""A periodic error in one axis's motor steps (models/periodic.py) and the GP's periodic term
(models/gp.py, models/gp_heliostat.py's aim).

Expected values come from residuals written out here: a sinusoid of known period in the steps
of one axis plus seeded Gaussian noise, or the noise alone (for the false-alarm rate, whose
stated probability is an upper bound: Baluev 2008).
"""

import json

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.pipeline.models.gp import GPConfig, GPInputs, fit_gp_correction, gp_correction
from heliocal.pipeline.models.periodic import find_periodic_error

PERIOD = 3000.0   # [steps]


def _gear_rows(n, seed):
    """Rows with sun angles, times and the steps of both axes (uniform over 50,000 steps), and
    their residuals (h, v) [mrad]: a gear error of PERIOD in axis 2's steps (amplitudes 0.4 and
    0.3 mrad) plus 0.05 mrad of noise."""
    rng = np.random.default_rng(seed)
    t = pd.Timestamp("2023-03-01", tz="UTC") + pd.to_timedelta(np.sort(rng.uniform(0, 100, n)), "D")
    rows = pd.DataFrame({"sun_azimuth_deg": rng.uniform(-80, 80, n),
                         "sun_elevation_deg": rng.uniform(15, 60, n), "timestamp": t,
                         "axis_1_steps": rng.uniform(0, 50_000, n),
                         "axis_2_steps": rng.uniform(0, 50_000, n)})
    return rows, _gear(rows["axis_2_steps"].to_numpy()) + rng.normal(0, 0.05, (n, 2))


def _gear(steps_2):
    phase = 2 * np.pi * steps_2 / PERIOD + 0.3
    return np.column_stack([0.4 * np.sin(phase), 0.3 * np.cos(phase)])


def test_a_sinusoid_in_one_axis_s_steps_is_found_at_its_period():
    rows, y = _gear_rows(80, 0)
    found = find_periodic_error(rows[["axis_1_steps", "axis_2_steps"]].to_numpy(), y)
    assert found is not None and found.axis == 2
    assert found.period_steps == pytest.approx(PERIOD, rel=0.005)
    assert found.power > 0.8 and found.false_alarm < 1e-9     # 0.4 mrad against 0.05 of noise
    # the same residuals against the steps of the other axis: nothing
    swapped = rows[["axis_2_steps", "axis_1_steps"]].to_numpy()
    assert find_periodic_error(swapped, y).axis == 1


def test_on_noise_the_stated_false_alarm_probability_is_an_upper_bound():
    # 400 draws of noise alone (60 rows): a stated 5 % is reached in at most 5 % of them (two
    # binomial standard errors: 7.2 %) and the bound is not idle (at least 1 %)
    rng = np.random.default_rng(1)
    hits = sum(find_periodic_error(rng.uniform(0, 60_000, (60, 2)), rng.normal(0, 0.2, (60, 2)),
                                   false_alarm=0.05) is not None for _ in range(400))
    assert 0.01 <= hits / 400 <= 0.072


def test_too_few_rows_or_steps_that_do_not_move_find_nothing():
    rows, y = _gear_rows(80, 2)
    steps = rows[["axis_1_steps", "axis_2_steps"]].to_numpy()
    assert find_periodic_error(steps[:9], y[:9]) is None
    assert find_periodic_error(np.full_like(steps, 1000.0), y) is None


def test_the_gp_follows_a_gear_error_the_sun_and_time_kernels_cannot():
    train, y = _gear_rows(120, 3)
    test, _ = _gear_rows(40, 4)
    truth = _gear(test["axis_2_steps"].to_numpy())
    config = GPConfig(structures=("sun", "sun+time"))
    with_term = fit_gp_correction(train, y, config)
    without = fit_gp_correction(train, y, GPConfig(structures=("sun", "sun+time"), periodic=False))
    assert with_term.inputs.periodic_axis == 2
    assert with_term.inputs.period_steps == pytest.approx(PERIOD, rel=0.005)
    assert without.inputs.periodic_axis == 0

    def rms(model):
        return float(np.sqrt(np.mean((model.predict_rows(test).mean_mrad - truth) ** 2)))

    # the truth's RMS over both components is 0.25 mrad: without the term the GP explains next
    # to none of it on new rows, with it all but a fraction of the noise (0.05)
    assert rms(with_term) < 0.05
    assert rms(without) > 0.2


def test_a_periodic_model_file_predicts_the_same_and_an_older_one_still_loads():
    train, y = _gear_rows(80, 5)
    test, _ = _gear_rows(10, 6)
    model = fit_gp_correction(train, y)
    config = json.loads(json.dumps({"gp": model.to_dict()}))
    again = gp_correction((config, {k: v.clone() for k, v in model.to_state().items()}), test)
    first = gp_correction(model, test)
    assert again.mean_mrad == pytest.approx(first.mean_mrad, abs=1e-10)
    assert again.variance_mrad2 == pytest.approx(first.variance_mrad2, abs=1e-10)
    # a model file written before the periodic term has no such keys: no steps input
    older = {k: v for k, v in config["gp"]["inputs"].items()
             if k not in ("periodic_axis", "period_steps", "fill_steps")}
    assert GPInputs.from_dict(older).n_inputs == 3


def test_aim_solves_the_steps_and_a_periodic_correction_together():
    """SYN1 (test_hybrid's synthetic heliostat) with a GP whose only term that matters is a
    periodic error in axis 2's steps: at the steps aim returns, the coarse normal corrected by
    the GP *at those steps* reflects the sun onto the aim point. Taking the correction at the
    coarse model's steps instead (one evaluation) misses by the change of the periodic error
    between the two."""
    from test_hybrid import HELIOSTAT_ROW, TARGET_ENU, synthetic_measurements

    from heliocal.pipeline.models.gp import correct_normals
    from heliocal.pipeline.models.gp_heliostat import gp_aim_steps
    from heliocal.pipeline.physics.kinematics import forward_kinematics, inverse_kinematics
    from heliocal.pipeline.physics.metrics import error_mrad, reflect
    from heliocal.pipeline.physics.parameters import HeliostatSpec, nominal_parameters

    rows = synthetic_measurements()
    span = float(np.ptp(rows["axis_2_steps"]))
    period = span / 15.0
    phase = 2 * np.pi * rows["axis_2_steps"].to_numpy() / period
    y = np.column_stack([0.8 * np.sin(phase), 0.6 * np.cos(phase)])
    y += np.random.default_rng(7).normal(0, 0.02, y.shape)
    model = fit_gp_correction(rows, y, GPConfig(structures=("sun",)))
    assert model.inputs.periodic_axis == 2
    assert model.inputs.period_steps == pytest.approx(period, rel=0.01)

    hrow = pd.Series(HELIOSTAT_ROW)
    spec, params = HeliostatSpec.from_row(hrow), nominal_parameters(hrow).to(torch.float64)
    az, el = np.radians([20.0, -35.0]), np.radians([40.0, 25.0])
    sun = torch.tensor(np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az),
                                 np.sin(el)], -1))
    aim = torch.tensor(TARGET_ENU, dtype=torch.float64).expand(2, 3)
    out = gp_aim_steps(model, params, spec, sun, aim)
    steps = out.steps

    def beam_error(at_steps, g_steps):
        normal, position = forward_kinematics(params.expand(2, 28), spec, at_steps[:, None])
        x = model.inputs.encode(np.degrees(az), np.degrees(el), None, None, g_steps.numpy())
        g = model.predict(x).mean_mrad
        beam = reflect(-sun, correct_normals(normal[:, 0], g))
        return error_mrad(beam, aim - position[:, 0]).numpy()

    assert beam_error(steps, steps).max() < 1e-4
    coarse = inverse_kinematics(params.expand(2, 28), spec, sun[:, None], aim[:, None])[:, 0]
    assert beam_error(steps, coarse).max() > 0.01     # the correction moved with the steps
    assert out.iterations.max() > 1


@pytest.mark.slow
def test_the_synthetic_sample_s_gear_error_heliostat_gets_its_period(tmp_path):
    """SS48 of the synthetic sample (sample_data/synthetic) carries a gear error of 4,000 steps
    in axis 2 (its ground_truth.json). fit-hybrid's GP (with the logged temperature) finds that
    period within 1 % and corrects the coarse model's test error to below half of it (the
    sweep's candidate: 0.174 against 0.395 mrad, docs/experiments/fine-selection.md)."""
    from pathlib import Path

    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.config import FineConfig
    from heliocal.pipeline.stages.aim import load_model
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.split import run_split

    sample = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic"
    truth = json.loads((sample / "ground_truth.json").read_text())
    gear = truth["heliostats"]["SS48"]["disturbances"]["gear_error"]
    run_ingest([sample / "calibration_log.csv"], tmp_path,
               IngestOptions(properties=sample / "paint"))
    run_split(tmp_path)
    run_fit_coarse(tmp_path)
    summary = run_fit_hybrid(tmp_path, mode="gp", heliostats=["SS48"],
                             config=FineConfig(env=("temperature",)))
    h = summary["heliostats"][0]
    cfg, _ = load_model(tmp_path, "gp", "SS48")
    inputs = cfg["gp"]["inputs"]
    assert inputs["periodic_axis"] == 2
    assert inputs["period_steps"] == pytest.approx(gear["period_steps"], rel=0.01)
    assert h["gp"]["test"] < 0.5 * h["coarse"]["test"]


def test_the_correction_map_names_the_period():
    """The report's map title (gp_map.structure_label, the same from the model and from its
    stored configuration) names a periodic term's axis and period; a GP without one keeps its
    structure's name."""
    from heliocal.pipeline.models.gp_heliostat import correction_grid
    from heliocal.pipeline.models.gp_map import structure_label

    train, y = _gear_rows(80, 8)
    model = fit_gp_correction(train, y, GPConfig(structures=("sun",)))
    period = f"{model.inputs.period_steps:,.0f}"
    assert correction_grid(model)["structure"] == f"sun, periodic in axis 2: {period} steps"
    assert structure_label(json.loads(json.dumps(model.to_dict()))) == \
        f"sun, periodic in axis 2: {period} steps"
    plain = fit_gp_correction(train, y, GPConfig(structures=("sun",), periodic=False))
    assert correction_grid(plain)["structure"] == "sun"
