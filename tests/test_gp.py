"""The Gaussian-process correction (models/gp.py, models/gp_heliostat.py, ``fit-hybrid --mode gp``,
``aim --model gp``).

Unit tests use residual fields written out here (a smooth sky pattern, a step in time) on sun
positions and times drawn with a fixed seed; the end-to-end tests use test_hybrid's synthetic
heliostat SYN1 (a static-6 rigid body plus a monthly tilt the rigid body cannot follow).
"""

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.gp import (GPConfig, GPCorrection, correct_normals,
                                         fit_gp_correction, gp_correction, pointing_frame,
                                         pointing_residuals_mrad)
from heliocal.pipeline.physics.metrics import error_mrad


def _rows(n, seed, az=(-80.0, 80.0), el=(15.0, 60.0), days=100.0):
    rng = np.random.default_rng(seed)
    t = pd.Timestamp("2023-03-01", tz="UTC") + pd.to_timedelta(np.sort(rng.uniform(0, days, n)), "D")
    return pd.DataFrame({"sun_azimuth_deg": rng.uniform(*az, n),
                         "sun_elevation_deg": rng.uniform(*el, n), "timestamp": t})


def _sky(rows):
    """A smooth pointing residual over the sky [mrad]: (sin(az / 10), 0.5 cos(el / 8)), the
    angles in degrees, so it varies over tens of degrees."""
    return np.column_stack([np.sin(rows["sun_azimuth_deg"].to_numpy() / 10),
                            0.5 * np.cos(rows["sun_elevation_deg"].to_numpy() / 8)])


def test_residual_components_and_correction_are_inverse():
    # a normal turned by 1 mrad along h and -2 mrad along v has residual (1, -2) mrad (to second
    # order: 1e-6 relative), and correcting the first by it gives the second (below 1e-5 mrad)
    n = torch.nn.functional.normalize(torch.tensor([[0.3, -0.8, 0.5], [0.0, -0.6, 0.8]],
                                                   dtype=torch.float64), dim=-1)
    h, v = pointing_frame(n)
    assert float((h * n).sum(-1).abs().max()) < 1e-15
    assert float(h[:, 2].abs().max()) < 1e-15                           # h is horizontal
    m = torch.nn.functional.normalize(n + 1e-3 * h - 2e-3 * v, dim=-1)
    r = pointing_residuals_mrad(n, m)
    assert r == pytest.approx(np.array([[1.0, -2.0]] * 2), rel=1e-5)
    assert error_mrad(correct_normals(n, r), m).max() < 1e-5


def test_the_gp_learns_a_sky_pattern_and_returns_to_the_coarse_model_far_away():
    train, test = _rows(150, 0), _rows(40, 1)
    noise = np.random.default_rng(2).normal(0, 0.05, (150, 2))
    model = fit_gp_correction(train, _sky(train) + noise, GPConfig(structures=("sun",)))
    inside = model.predict_rows(test)
    # interpolation between training rows: within 0.05 mrad RMS of the true pattern (noise 0.05)
    assert np.sqrt(np.mean((inside.mean_mrad - _sky(test)) ** 2)) < 0.05
    # 150 deg of azimuth away from every training row the prior mean (the coarse model) is back
    # and the variance is the prior's: 2 components x the fitted signal variance
    far = model.predict(model.inputs.encode([170.0], [40.0], [np.nan]))
    assert np.abs(far.mean_mrad).max() < 0.05           # of a pattern of amplitude 1 and 0.5
    signal = float(model._fitted().kernel_.k1.k1.constant_value) * model.y_scale_mrad ** 2
    assert far.variance_mrad2[0] == pytest.approx(2 * signal, rel=0.02)   # 1 - k(far, X): 1 %
    assert (inside.variance_mrad2 < 0.1 * far.variance_mrad2[0]).all()


def test_a_step_in_time_is_found_by_the_marginal_likelihood():
    # the same sky pattern plus a 1 mrad step of the h component after day 50: the additive
    # sun+time kernel explains it, the sun kernel alone cannot (log marginal likelihood)
    train = _rows(150, 3)
    days = (train["timestamp"] - train["timestamp"].min()).dt.total_seconds() / 86400
    y = _sky(train) + np.random.default_rng(4).normal(0, 0.05, (150, 2))
    y[:, 0] += np.where(days > 50, 1.0, 0.0)
    sun = fit_gp_correction(train, y, GPConfig(structures=("sun",)))
    both = fit_gp_correction(train, y, GPConfig(structures=("sun", "sun+time")))
    assert both.structure == "sun+time"
    assert both.log_marginal_likelihood > sun.log_marginal_likelihood + 50


def test_the_model_file_predicts_the_same():
    train = _rows(80, 5)
    model = fit_gp_correction(train, _sky(train), GPConfig())
    config = {"gp": model.to_dict()}
    state = {k: v.clone() for k, v in model.to_state().items()}
    again = gp_correction((json.loads(json.dumps(config)), state), _rows(10, 6))
    first = gp_correction(model, _rows(10, 6))
    assert again.mean_mrad == pytest.approx(first.mean_mrad, abs=1e-10)
    assert again.variance_mrad2 == pytest.approx(first.variance_mrad2, abs=1e-10)
    # the fit is seeded: the same rows and settings give the same hyperparameters
    assert fit_gp_correction(train, _sky(train), GPConfig()).theta.tolist() == model.theta.tolist()


def test_settings_are_checked():
    with pytest.raises(ParameterError, match=r"The 'structures' parameter of fit_gp_correction "
                                             r"must list structures of sun, sun\+time, sun\*time. "
                                             r"Got 'time' instead."):
        GPConfig(structures=("time",)).validated()
    with pytest.raises(ParameterError, match=r"one \(h, v\) row per training row"):
        fit_gp_correction(_rows(5, 0), np.zeros((4, 2)))
    assert isinstance(fit_gp_correction(_rows(5, 0), np.zeros((5, 2))), GPCorrection)


# --------------------------------------------------------------------------------------------
# fit-hybrid --mode gp and aim --model gp on SYN1 (test_hybrid's synthetic heliostat)
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def gp_workdir(tmp_path_factory):
    from test_hybrid import HELIOSTAT_ROW, synthetic_measurements

    from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS
    from heliocal.pipeline.artifacts.store import write_artifact
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
    from heliocal.pipeline.stages.split import run_split

    wd = tmp_path_factory.mktemp("gp")
    rows = synthetic_measurements()
    write_artifact(rows, wd, MEASUREMENTS, stage="test")
    write_artifact(pd.DataFrame([dict(HELIOSTAT_ROW, n_measurements=len(rows))]), wd, HELIOSTATS,
                   stage="test")
    run_split(wd, n_test=30, n_val=20)
    run_fit_coarse(wd, preset="static-6", robust_start=False, regime_steps="detect")
    return wd, run_fit_hybrid(wd, mode="gp", seed=0)


@pytest.mark.slow
def test_gp_mode_corrects_the_monthly_tilt(gp_workdir):
    # SYN1's monthly tilt (test_hybrid.SEASONAL_AMPLITUDE_RAD) is smooth in time: the additive
    # time kernel follows it and the corrected model beats the rigid body on every split
    _, summary = gp_workdir
    h = summary["heliostats"][0]
    assert h["mode"] == "gp"
    for split in ("validation", "test"):
        assert h["gp"][split] < 0.9 * h["coarse"][split], h


@pytest.mark.slow
def test_aim_with_the_gp_puts_the_corrected_beam_on_the_aim_point(gp_workdir):
    from test_hybrid import HELIOSTAT_ROW, HID

    from heliocal.pipeline.physics.kinematics import forward_kinematics
    from heliocal.pipeline.physics.metrics import reflect
    from heliocal.pipeline.physics.parameters import HeliostatSpec
    from heliocal.pipeline.physics.sun import spa_sun_position, sun_vector_enu
    from heliocal.pipeline.stages.aim import aim_steps, load_model

    wd, _ = gp_workdir
    aim, when = np.array([0.5, -3.235754, 36.5]), pd.Timestamp("2023-05-03T11:00Z")
    out = aim_steps(wd, HID, aim_point_enu=aim, time_utc=when, model="gp")
    coarse = aim_steps(wd, HID, aim_point_enu=aim, time_utc=when, model="coarse")
    assert out["model"] == "gp" and out["inverse_residual_mrad"] < 0.01
    # independently: the coarse normal at the returned steps, corrected by the model file's GP
    # at that sun and time, reflects the sun onto the aim point
    cfg, state = load_model(wd, "gp", HID)
    spec = HeliostatSpec.from_row(pd.Series(HELIOSTAT_ROW))
    steps = torch.tensor([[out["axis_1_steps"], out["axis_2_steps"]]], dtype=torch.float64)
    normal, position = forward_kinematics(torch.tensor(cfg["base_params"]), spec, steps)
    az, el = spa_sun_position([when], 50.915305, 6.387838, 88.7)
    row = pd.DataFrame({"sun_azimuth_deg": az, "sun_elevation_deg": el, "timestamp": [when]})
    g = gp_correction((cfg, state), row)
    assert 0.05 < np.abs(g.mean_mrad).max() and g.variance_mrad2[0] > 0
    beam = reflect(-torch.tensor(sun_vector_enu(az, el)), correct_normals(normal, g.mean_mrad))
    assert float(error_mrad(beam, torch.tensor(aim) - position)[0]) < 0.01
    # the correction moved the steps (a fraction of a mrad is tens of steps on these actuators)
    assert abs(out["axis_1_steps"] - coarse["axis_1_steps"]) + \
        abs(out["axis_2_steps"] - coarse["axis_2_steps"]) > 1


@pytest.fixture(scope="module")
def gp_swept_workdir(gp_workdir, tmp_path_factory):
    """gp_workdir after a sweep that selects SYN1's GP correction (the hybrids held at the coarse
    model by a weight decay of 1000): ``hybrid/selected/SYN1`` is a GP model. Tests that write
    into it (a report) copy it first."""
    import shutil

    from heliocal.pipeline.models.config import PathConfig
    from heliocal.pipeline.stages.sweep import run_sweep

    wd = tmp_path_factory.mktemp("gp-swept") / "wd"
    shutil.copytree(gp_workdir[0], wd)
    run_sweep(wd, study=0, weight_decays=[1000.0], extra_bands=(), workers=1,
              path=PathConfig(stage_epochs=20))
    return wd


def _in_fresh_process(code: str):
    """The JSON that ``code`` prints last, run in a fresh Python process (``json`` and ``sys``
    imported): what it imports is its own, not the test process's."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "import json, sys\n" + code],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _copy(workdir, tmp_path):
    import shutil

    shutil.copytree(workdir, tmp_path / "wd")
    return tmp_path / "wd"


@pytest.mark.slow
def test_the_sweep_selects_the_gp_aim_uses_it_and_the_report_maps_it(gp_swept_workdir, tmp_path,
                                                                      monkeypatch):
    # SYN1's monthly tilt: the GP correction wins the selection against the coarse model (the
    # hybrids held at it by a weight decay of 1000); aim --model auto aims with it; the report
    # draws its correction map
    from test_hybrid import HID

    from heliocal.pipeline.artifacts.schemas import SELECTION
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.stages.aim import aim_steps
    from heliocal.pipeline.stages.report import run_report

    wd = _copy(gp_swept_workdir, tmp_path)
    sel = read_artifact(wd, SELECTION).set_index("heliostat_id").loc[HID]
    assert sel["model"] in ("gp", "gp-sun"), sel.to_dict()
    assert sel["weighted_val_error_mrad"] <= 0.9 * sel["coarse_weighted_val_error_mrad"]
    assert sel["test_error_mrad"] < sel["coarse_test_error_mrad"]
    aim = {"aim_point_enu": [0.5, -3.235754, 36.5], "time_utc": "2023-05-03T11:00Z"}
    out = aim_steps(wd, HID, **aim)
    assert out["model"] == "gp" and out["inverse_residual_mrad"] < 0.01
    # near its data the GP expects less than the coarse model's aim; held to a floor of the
    # whole coarse level (its held-out rows no better than the coarse model's) it expects what
    # the coarse aim does (the parameters' term at the GP's steps, 1e-3 away)
    import heliocal.pipeline.stages.aim_budget as aim_budget

    coarse = aim_steps(wd, HID, model="coarse", **aim)["expected_error_mrad"]
    assert out["expected_error_mrad"] < 0.99 * coarse
    with monkeypatch.context() as m:
        m.setattr(aim_budget, "_rms_ratio", lambda rows, column: 1.0)
        held = aim_steps(wd, HID, **aim)["expected_error_mrad"]
    assert held == pytest.approx(coarse, rel=1e-3)
    # benchmarks/expected_error.py's GP table: the heliostat's 30 kNN test rows (split-knn
    # n_test=30) and its time split's test rows, the expected error through the GP's variance
    # never above the coarse budget alone, and below it somewhere on the kNN rows (near the data)
    # but never below the GP's held-out rows' share r of it: sqrt(var + level^2) times r is at
    # most sqrt(var + (r level)^2) for r <= 1 (aim_budget.fine_level_ratios; aim takes the
    # same floor for a GP the sweep selected)
    from heliocal.pipeline.stages.aim_budget import _fine_floor, fine_level_ratios
    from heliocal.pipeline.stages.aim_calibration import gp_calibration_rows
    from heliocal.pipeline.stages.aim_choice import aim_models

    assert aim_models(wd)[HID]["source"] == "sweep"
    ratios = fine_level_ratios(wd, [HID])[HID]
    for setting, n in (("knn", 30), ("forward", None)):
        rows = gp_calibration_rows(wd, setting)
        assert set(rows["heliostat_id"]) == {HID} and len(rows) == (n or len(rows)) > 0
        assert (rows["expected_mrad"] <= rows["expected_before_mrad"] * (1 + 1e-12)).all()
        r = _fine_floor(ratios, "validation" if setting == "knn" else "time-split validation")
        assert 0.0 < r <= 1.0
        assert (rows["expected_mrad"] >= r * rows["expected_before_mrad"] * (1 - 1e-12)).all()
        if setting == "knn":
            assert (rows["expected_mrad"] < rows["expected_before_mrad"]).any()
    summary = run_report(wd, workers=1)
    assert any(f.endswith(f"gp_correction_{HID}.png") for f in summary["figures"])


# --------------------------------------------------------------------------------------------
# the correction map the report draws: stored with the model by its stage (models/gp_map.py)
# --------------------------------------------------------------------------------------------
def _assert_same_map(got: dict, want: dict):
    """Every array of the two maps bit for bit, every other entry equal."""
    assert sorted(got) == sorted(want)
    for key, value in want.items():
        if isinstance(value, np.ndarray):
            assert got[key].shape == value.shape and np.array_equal(got[key], value), key
        else:
            assert got[key] == value, key


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["gp", "selected"])
def test_the_stored_gp_map_is_the_one_computed_from_the_model(gp_workdir, gp_swept_workdir,
                                                              mode):
    # fit-hybrid --mode gp (hybrid/gp/) and the sweep (hybrid/selected/) store the map that
    # correction_grid computes from the model as its files give it back: the same bits
    from test_hybrid import HID

    from heliocal.pipeline.models.gp_heliostat import correction_grid
    from heliocal.pipeline.models.gp_map import MAP_KEY, stored_correction_map
    from heliocal.pipeline.stages.aim import load_model

    wd = gp_workdir[0] if mode == "gp" else gp_swept_workdir
    cfg, state = load_model(wd, mode, HID)
    assert cfg["mode"] == "gp" and cfg[MAP_KEY]["n_azimuth"] == 64
    stored = stored_correction_map(cfg)
    _assert_same_map(stored, correction_grid(GPCorrection.from_model(cfg, state)))
    assert stored["mean_h"].shape == (40, 64) and np.abs(stored["mean_h"]).max() > 0.01


@pytest.mark.slow
def test_the_report_draws_a_stored_gp_map_without_importing_torch(gp_swept_workdir, tmp_path):
    # a fresh process: the report (its figures drawn in that process) reads the stored map with
    # numpy and json; torch and scikit-learn (about 1.5 s of a report's CPU) stay unimported
    from test_hybrid import HID

    wd = _copy(gp_swept_workdir, tmp_path)
    figures, heavy = _in_fresh_process(
        "from heliocal.pipeline.stages.report import run_report\n"
        f"summary = run_report({str(wd)!r}, workers=1)\n"
        "print(json.dumps([[f.rsplit('/', 1)[-1] for f in summary['figures']], "
        "sorted(m for m in ('torch', 'sklearn') if m in sys.modules)]))")
    assert f"gp_correction_{HID}.png" in figures
    assert heavy == []


@pytest.mark.slow
@pytest.mark.parametrize("model, imports_sklearn", [("coarse", False), ("gp", True)])
def test_only_an_aim_through_the_gp_imports_its_modules(gp_swept_workdir, model, imports_sklearn):
    # a fresh process: aiming the coarse model leaves the GP's modules (scikit-learn, about 0.9 s
    # of every aim call) unimported; aiming the GP loads them, so the probe can see them
    from test_hybrid import HID

    assert _in_fresh_process(
        "from heliocal.pipeline.stages.aim import aim_steps\n"
        f"out = aim_steps({str(gp_swept_workdir)!r}, {HID!r}, aim_point_enu=[0.5, -3.2, 36.5], "
        f"time_utc='2023-05-03T11:00Z', model={model!r})\n"
        "print(json.dumps([out['model'], 'sklearn' in sys.modules]))") == [model, imports_sklearn]


@pytest.mark.slow
def test_a_gp_model_without_a_stored_map_has_its_map_computed(gp_swept_workdir, tmp_path):
    # a model written before maps were stored: the report computes the map from the model, the
    # same arrays and the same figure; a malformed stored map is a one-line error naming the file
    from test_hybrid import HID
    from workdir_tools import recommit

    from heliocal.pipeline.errors import SchemaError
    from heliocal.pipeline.models.gp_map import MAP_KEY
    from heliocal.pipeline.stages.aim_choice import aim_models
    from heliocal.pipeline.stages.report import _gp_maps, run_report

    wd = _copy(gp_swept_workdir, tmp_path)
    png = wd / "report" / "figures" / f"gp_correction_{HID}.png"
    stored = _gp_maps(wd, aim_models(wd))
    run_report(wd, workers=1)
    drawn = png.read_bytes()
    rel = f"hybrid/selected/{HID}.json"
    cfg = json.loads((wd / rel).read_text())

    def rewrite(section):
        new = {k: v for k, v in cfg.items() if k != MAP_KEY}
        if section is not None:
            new[MAP_KEY] = section
        (wd / rel).write_text(json.dumps(new, indent=1, sort_keys=True))
        recommit(wd, rel)

    rewrite(None)
    computed = _gp_maps(wd, aim_models(wd))
    assert list(computed) == [HID]
    _assert_same_map(computed[HID], stored[HID])
    png.unlink()
    run_report(wd, workers=1)
    assert png.read_bytes() == drawn
    rewrite({**cfg[MAP_KEY], "mean_h_mrad": cfg[MAP_KEY]["mean_h_mrad"][:-12]})
    with pytest.raises(SchemaError, match=rf"{HID}.json holds no readable correction map .*"
                                          r"rerun `heliocal sweep"):
        run_report(wd, workers=1)


# --------------------------------------------------------------------------------------------
# the predictive variance aim's expected error reads (issue 33)
# --------------------------------------------------------------------------------------------
def test_the_prediction_s_variances_are_the_kernel_s_closed_form():
    """Independently of scikit-learn's predict: the posterior variance of a zero-mean GP is
    ``k(x, x) - k_x^T K^-1 k_x`` (K the training kernel with the white noise on its diagonal,
    k_x the noise-free cross-covariances), its prior ``k(x, x)`` without the noise; both
    components share the kernel, so both are summed as twice one, in units of the fitted
    scale squared. The explained variance is ``w (2 - w) (prior - latent)``."""
    train = _rows(60, 7)
    noise = np.random.default_rng(8).normal(0, 0.05, (60, 2))
    model = fit_gp_correction(train, _sky(train) + noise, GPConfig(structures=("sun",)))
    kernel = model._fitted().kernel_
    signal, white = kernel.k1, float(kernel.k2.noise_level)
    x = model.inputs.encode([10.0, -30.0, 170.0], [40.0, 25.0, 40.0], [np.nan] * 3)
    big_k = signal(model.x_train) + white * np.eye(len(model.x_train))
    k_x = signal(model.x_train, x)
    prior = np.diag(signal(x))
    latent = prior - np.einsum("ij,ij->j", k_x, np.linalg.solve(big_k, k_x))
    scale2 = 2.0 * model.y_scale_mrad ** 2
    w = np.array([1.0, 0.5, 0.0])
    got = model.predict(x, w)
    assert got.prior_variance_mrad2 == pytest.approx(scale2 * prior, rel=1e-9)
    assert got.latent_variance_mrad2 == pytest.approx(scale2 * latent, rel=1e-6, abs=1e-12)
    assert got.noise_mrad2 == pytest.approx(scale2 * white, rel=1e-12)
    assert got.explained_variance_mrad2 == pytest.approx(
        w * (2 - w) * scale2 * (prior - latent), rel=1e-6, abs=1e-12)
    # the faded correction's expected squared error: the latent variance plus the square of
    # what the fade takes away, |(1 - w) g|^2 with g the unfaded mean (a half here)
    unfaded = model.predict(x).mean_mrad
    assert got.variance_mrad2 == pytest.approx(
        scale2 * latent + (((1 - w)[:, None] * unfaded) ** 2).sum(-1), rel=1e-6, abs=1e-12)
    # inside the training rows most of the prior is explained; 150 deg away none of it
    assert got.explained_variance_mrad2[0] > 0.9 * got.prior_variance_mrad2[0]
    assert got.explained_variance_mrad2[2] == 0.0


@pytest.mark.slow
def test_aim_s_expected_error_takes_the_gp_s_variance_and_is_the_coarse_one_far_away(gp_workdir):
    """An aim through the GP expects the coarse budget with its level lowered by what the GP
    explains at that aim (aim_budget.fine_level_mrad), recomputed here from the model file's
    prediction at the aim's sun and time; three years after the data the fade is 0, nothing is
    explained and the aim expects what the coarse model's aim at that time expects."""
    from test_hybrid import HELIOSTAT_ROW, HID

    from heliocal.pipeline.physics.parameters import HeliostatSpec
    from heliocal.pipeline.physics.sun import sun_vector_enu
    from heliocal.pipeline.stages.aim import aim_steps, load_model
    from heliocal.pipeline.stages.aim_budget import error_budgets, expected_error_mrad
    from heliocal.pipeline.stages.fit_coarse import load_selected_parameters

    wd, _ = gp_workdir
    aim, when = [0.5, -3.235754, 36.5], pd.Timestamp("2023-05-03T11:00Z")
    near = aim_steps(wd, HID, aim_point_enu=aim, time_utc=when, model="gp")
    coarse = aim_steps(wd, HID, aim_point_enu=aim, time_utc=when, model="coarse")
    cfg, state = load_model(wd, "gp", HID)
    row = pd.DataFrame({"sun_azimuth_deg": [near["sun_azimuth_deg"]],
                        "sun_elevation_deg": [near["sun_elevation_deg"]], "timestamp": [when]})
    g = gp_correction((cfg, state), row)
    explained = float(g.explained_variance_mrad2[0])
    assert explained > 0.0
    # the coarse budget's level at the aim's age, and its parameters' term at the GP's steps
    selected = load_selected_parameters(wd, [HID])
    spec = HeliostatSpec.from_row(pd.Series(HELIOSTAT_ROW))
    budget = error_budgets(wd, {HID: spec}, selected, {HID: {"model": "coarse"}})[HID]
    level = float(budget.level_at([near["days_after_last_measurement"]])[0])
    steps = torch.tensor([[near["axis_1_steps"], near["axis_2_steps"]]], dtype=torch.float64)
    sun = torch.tensor(sun_vector_enu(near["sun_azimuth_deg"], near["sun_elevation_deg"]),
                       dtype=torch.float64).reshape(1, 3)
    without = float(expected_error_mrad(budget, spec, selected[HID]["params"], steps, sun,
                                        torch.tensor([aim], dtype=torch.float64),
                                        [near["days_after_last_measurement"]])[0])
    parameters = without ** 2 - level ** 2
    want = math.sqrt(parameters + max(level ** 2 - explained, min(g.noise_mrad2, level ** 2)))
    assert near["expected_error_mrad"] == pytest.approx(want, rel=1e-9)
    assert near["expected_error_mrad"] < coarse["expected_error_mrad"]
    later = when + pd.Timedelta(days=3 * 365)
    far = aim_steps(wd, HID, aim_point_enu=aim, time_utc=later, model="gp")
    far_coarse = aim_steps(wd, HID, aim_point_enu=aim, time_utc=later, model="coarse")
    assert far["expected_error_mrad"] == pytest.approx(far_coarse["expected_error_mrad"],
                                                       rel=1e-9)


# ------------------------------------------------------------------------------------------------
# the hyperparameter search's likelihood (models/gp_likelihood.py) against scikit-learn's
# ------------------------------------------------------------------------------------------------
def _gp_inputs(n: int = 60, n_env: int = 1, seed: int = 3):
    """Encoded inputs like GPInputs' (azimuth, elevation, days, env) and two residual columns."""
    rng = np.random.default_rng(seed)
    x = np.c_[rng.uniform(-80, 80, n), rng.uniform(10, 60, n), np.sort(rng.uniform(0, 300, n)),
              rng.normal(size=(n, n_env))]
    x[5] = x[4]                 # two rows at one input: zero distances (nu 0.5's 0/0 case)
    return x, rng.normal(size=(n, 2))


@pytest.mark.parametrize("structure", ["sun", "sun+time", "sun*time"])
@pytest.mark.parametrize("n_env", [0, 1])
@pytest.mark.parametrize("time_nu", [0.5, 1.5, 2.5])
def test_the_kernel_walk_and_the_likelihood_gradient_are_scikit_learn_s(structure, n_env,
                                                                       time_nu):
    """The reference is scikit-learn itself: its kernel's ``(K, gradient)`` and its regressor's
    ``log_marginal_likelihood(theta, eval_gradient=True)`` at the start and at a moved theta,
    against models/gp_likelihood.py's walk and regressor; equal to rounding (1e-12 relative,
    the gradient's entries to 1e-9 of its largest)."""
    from heliocal.pipeline.models.gp import _kernel

    x, y = _gp_inputs(n_env=n_env)
    _assert_the_walk_is_scikit_learn_s(_kernel(structure, n_env, time_nu), x, y)


def _assert_the_walk_is_scikit_learn_s(kernel, x, y):
    """The walk's kernel and gradient and the regressor's likelihood gradient against
    scikit-learn's, at the kernel's theta and at a moved one (1e-12 relative; the gradient's
    entries to 1e-9 of its largest)."""
    from sklearn.gaussian_process import GaussianProcessRegressor

    from heliocal.pipeline.models.gp_likelihood import Regressor, kernel_and_gradient

    thetas = [kernel.theta, kernel.theta + np.random.default_rng(1).normal(
        scale=0.5, size=len(kernel.theta))]
    ours, ref = (cls(kernel, optimizer=None).fit(x, y)
                 for cls in (Regressor, GaussianProcessRegressor))
    for theta in thetas:
        k = kernel.clone_with_theta(theta)
        (K, G), (K_ref, G_ref) = kernel_and_gradient(k, x), k(x, eval_gradient=True)
        np.testing.assert_allclose(K, K_ref, rtol=1e-12, atol=1e-14)
        assert G.shape == G_ref.shape == (len(x), len(x), len(theta))
        np.testing.assert_allclose(G, G_ref, rtol=1e-12, atol=1e-12 * np.abs(G_ref).max())
        (lml, grad), (lml_ref, grad_ref) = (r.log_marginal_likelihood(theta, eval_gradient=True)
                                            for r in (ours, ref))
        assert lml == pytest.approx(lml_ref, rel=1e-12)
        np.testing.assert_allclose(grad, grad_ref, rtol=0, atol=1e-9 * np.abs(grad_ref).max())


@pytest.mark.parametrize("structure", ["sun", "sun+time", "sun*time"])
@pytest.mark.parametrize("n_env", [0, 1])
def test_the_walk_of_a_periodic_term_of_fixed_period_is_scikit_learn_s(structure, n_env):
    """The same reference with the periodic term (models/periodic.py): its period fixed, so the
    walk evaluates it (not left to scikit-learn) and gives scikit-learn's kernel, gradient and
    likelihood gradient to rounding, at the start and at a moved theta."""
    from heliocal.pipeline.models.gp import _kernel
    from heliocal.pipeline.models.gp_likelihood import walks

    x, y = _gp_inputs(n_env=n_env)
    x = np.c_[x, np.random.default_rng(2).uniform(0, 50_000, len(x))]     # axis 2's steps
    kernel = _kernel(structure, n_env, 0.5, 3000.0)
    assert walks(kernel)
    _assert_the_walk_is_scikit_learn_s(kernel, x, y)


def test_a_kernel_the_walk_does_not_know_is_scikit_learn_s():
    """An exponentiated kernel is not one of the walk's nodes: scikit-learn evaluates it (the
    same arrays, not a near copy)."""
    from sklearn.gaussian_process.kernels import Exponentiation, RBF

    from heliocal.pipeline.models.gp_likelihood import kernel_and_gradient

    x, _ = _gp_inputs(n=20, n_env=0)
    kernel = Exponentiation(RBF(10.0), 2.0)
    (K, G), (K_ref, G_ref) = kernel_and_gradient(kernel, x), kernel(x, eval_gradient=True)
    assert np.array_equal(K, K_ref) and np.array_equal(G, G_ref)


def test_a_matern_without_a_closed_form_is_left_to_scikit_learn():
    """nu = 2 has no closed form here (scikit-learn evaluates Bessel functions): the regressor
    searches with scikit-learn's kernel and reaches scikit-learn's likelihood."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import Matern, WhiteKernel

    from heliocal.pipeline.models.gp_likelihood import Regressor, walks

    x, y = _gp_inputs(n=30, n_env=0)
    kernel = Matern([20.0, 20.0, 30.0], (1.0, 1e3), nu=2.0) + WhiteKernel(0.5, (1e-4, 1e1))
    assert not walks(kernel) and walks(Matern(1.0, nu=1.5) + WhiteKernel())
    theta = kernel.theta + 0.2
    ours, ref = (cls(kernel, optimizer=None).fit(x, y).log_marginal_likelihood(
        theta, eval_gradient=True) for cls in (Regressor, GaussianProcessRegressor))
    assert ours[0] == pytest.approx(ref[0], rel=1e-12)
    np.testing.assert_allclose(ours[1], ref[1], rtol=1e-9, atol=1e-9 * np.abs(ref[1]).max())
