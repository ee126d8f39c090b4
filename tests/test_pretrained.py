"""The pre-trained network (``pretrained-nn``, paper 002) and its ``residual`` variant (issue 20).

Data: two heliostats of sample_data/synthetic's calibration log. SS48 as simulated (a rigid body
plus noise: the coarse model is as good as it gets), SP13 with a known step error added to its
recorded axis-1 steps, ``INJECT_STEPS * sin(2 pi elevation / INJECT_PERIOD_DEG)`` (about 0.9 mrad;
periodic in the sun elevation, so no rigid-body parameter absorbs it, and a function of the
network's inputs, so a network can). The expected figures come from that construction:
- at epoch 0 the residual network's output layer is zero, so it *is* the coarse model: its
  step-space error equals the coarse model's error row by row up to second-order terms (measured
  differences below 0.13 %; asserted within 1 %);
- on SP13 it must learn part of the injected error: better than the coarse model by the sweep's
  20 % margin on validation (measured 0.399 vs 0.565 mrad) and not worse on test;
- the sweep with ``--select-pretrained`` chooses it for SP13 and keeps the coarse model for SS48.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.cli.main import app
from heliocal.pipeline.artifacts.schemas import (COARSE_PREDICTIONS, HELIOSTATS,
                                                 HYBRID_PREDICTIONS, MEASUREMENTS, SELECTION,
                                                 SWEEP)
from heliocal.pipeline.artifacts.store import read_artifact
from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.coarse import MeasurementBatch
from heliocal.pipeline.models.pretrained import PretrainConfig, PretrainedModel, fit_pretrained
from heliocal.pipeline.physics.metrics import error_mrad, measured_normal
from heliocal.pipeline.physics.parameters import HeliostatSpec
from heliocal.pipeline.stages.aim import load_model
from heliocal.pipeline.stages.fit_coarse import load_selected_parameters, load_split_labels
from heliocal.pipeline.models.config import PathConfig
from heliocal.pipeline.models.selection import SelectionRule
from heliocal.pipeline.stages import sweep as sweep_stage
from heliocal.pipeline.stages.sweep import MIN_IMPROVEMENT

ROOT = Path(__file__).resolve().parents[1]
SYNTHETIC = ROOT / "sample_data" / "synthetic"
INJECT_STEPS, INJECT_PERIOD_DEG = 40.0, 30.0

#: end to end (ingest, split-knn, fit-coarse and sweep through the CLI): `make test` runs it,
#: `make test-fast` skips it
pytestmark = pytest.mark.slow


def _ok(runner, args):
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output + str(result.exception)
    return result


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """Ingested, split and coarse-fitted workdir of SP13 (injected step error) and SS48."""
    from typer.testing import CliRunner

    tmp = tmp_path_factory.mktemp("pretrained")
    log = pd.read_csv(SYNTHETIC / "calibration_log.csv")
    log = log[log["heliostat_id"].isin(["SP13", "SS48"])].copy()
    sp13 = log["heliostat_id"] == "SP13"
    log.loc[sp13, "axis_1_motor_position"] = (
        log.loc[sp13, "axis_1_motor_position"]
        + INJECT_STEPS * np.sin(2 * np.pi * log.loc[sp13, "sun_elevation"] / INJECT_PERIOD_DEG)
    ).round().astype(int)
    src = tmp / "log"
    src.mkdir()
    log.to_csv(src / "calibration_log.csv", index=False)
    (src / "tower-measurements.json").write_bytes((SYNTHETIC / "tower-measurements.json").read_bytes())
    wd = tmp / "wd"
    runner = CliRunner()
    _ok(runner, ["ingest", str(src / "calibration_log.csv"), "--workdir", str(wd), "--quiet"])
    _ok(runner, ["split-knn", "--workdir", str(wd), "--quiet"])
    _ok(runner, ["fit-coarse", "--workdir", str(wd), "--quiet"])
    return wd


def _heliostat(wd: Path, hid: str):
    m = read_artifact(wd, MEASUREMENTS, heliostats=[hid])
    m["split"] = load_split_labels(wd, m).to_numpy()
    rows = m.reset_index(drop=True)
    hrow = read_artifact(wd, HELIOSTATS, heliostats=[hid]).iloc[0]
    return (load_selected_parameters(wd, [hid])[hid], HeliostatSpec.from_row(hrow), hrow, rows,
            MeasurementBatch.from_frame(rows))


def _errors(normal, position, data) -> np.ndarray:
    return error_mrad(normal, measured_normal(data.sun, position, data.focal_spot)).numpy()


def _coarse_errors(wd: Path, hid: str, preset: str, rows: pd.DataFrame) -> np.ndarray:
    p = read_artifact(wd, COARSE_PREDICTIONS, heliostats=[hid])
    p = p[p["model"] == preset].set_index("measurement_id")
    return p.reindex(rows["measurement_id"].astype(str))["error_mrad"].to_numpy()


def _mean(e, labels, split):
    return float(np.mean(e[labels == split]))


@pytest.mark.parametrize("hid", ["SS48", "SP13"])
def test_residual_at_epoch_zero_is_the_coarse_model(workdir, hid):
    sel, spec, hrow, rows, data = _heliostat(workdir, hid)
    model, info, normal, position = fit_pretrained(
        sel["params"], spec, hrow, rows, data, rows["split"].to_numpy(), 0,
        PretrainConfig(residual_epochs=0))
    assert info["finetune_best_epoch"] == 0 and info["unreachable_rows"] == 0
    ours = _errors(normal, position, data)
    coarse = _coarse_errors(workdir, hid, sel["preset"], rows)
    np.testing.assert_allclose(ours, coarse, rtol=0.01, atol=1e-4)
    # and its steps are the coarse inverse kinematics: aiming at a row's spot reproduces it
    steps = model.steps(data.sun, data.focal_spot, spec=spec)
    from heliocal.pipeline.physics.kinematics import inverse_kinematics
    np.testing.assert_allclose(steps.numpy(),
                               inverse_kinematics(sel["params"], spec, data.sun,
                                                  data.focal_spot).numpy(), rtol=0, atol=1e-9)


def test_a_fit_imports_neither_torch_compiler_nor_its_configuration(workdir):
    """A fresh process that fits the pre-trained network in both variants (as a sweep's worker
    does for the pretrained-nn baseline) never imports torch._dynamo or torch._inductor: its
    optimiser and scheduler are heliocal's (pipeline/models/adam.py, the same bits as torch's)."""
    import os
    import subprocess
    import sys

    script = (
        "import sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from pathlib import Path\n"
        "from heliocal.pipeline.models.pretrained import PretrainConfig, fit_pretrained\n"
        "from test_pretrained import _heliostat\n"
        f"sel, spec, hrow, rows, data = _heliostat(Path({str(workdir)!r}), 'SP13')\n"
        "for variant in ('residual', 'paper'):\n"
        "    config = PretrainConfig(variant=variant, n_samples=400, pretrain_epochs=3,\n"
        "                            finetune_epochs=5, residual_epochs=5)\n"
        "    model, info, normal, position = fit_pretrained(\n"
        "        sel['params'], spec, hrow, rows, data, rows['split'].to_numpy(), 0, config)\n"
        "    print(variant, bool(normal.isfinite().all()))\n"
        "print('torch._dynamo' in sys.modules, 'torch._inductor' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, PYTHONPATH=str(Path(__file__).parent)))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["residual", "True", "paper", "True", "False", "False"]


def test_residual_learns_the_injected_step_error_and_leaves_a_rigid_body_alone(workdir):
    out = {}
    for hid in ("SP13", "SS48"):
        sel, spec, hrow, rows, data = _heliostat(workdir, hid)
        labels = rows["split"].to_numpy()
        _, info, normal, position = fit_pretrained(sel["params"], spec, hrow, rows, data, labels,
                                                   0, PretrainConfig())
        ours = _errors(normal, position, data)
        coarse = _coarse_errors(workdir, hid, sel["preset"], rows)
        out[hid] = {s: (_mean(ours, labels, s), _mean(coarse, labels, s))
                    for s in ("train", "validation", "test")}
    r, c = zip(*out["SP13"].values())
    assert r[1] < (1 - MIN_IMPROVEMENT) * c[1], out      # learned: wins the sweep's margin
    assert r[0] < 0.7 * c[0], out                         # most of the injected error
    assert r[2] <= 1.05 * c[2], out                       # not worse where it extrapolates
    r, c = zip(*out["SS48"].values())
    assert r[2] <= 1.05 * c[2], out                       # a rigid body: stays the coarse model


def test_same_seed_same_model(workdir):
    sel, spec, hrow, rows, data = _heliostat(workdir, "SP13")
    labels = rows["split"].to_numpy()
    cfg = PretrainConfig(residual_epochs=60)
    a = fit_pretrained(sel["params"], spec, hrow, rows, data, labels, 3, cfg)
    b = fit_pretrained(sel["params"], spec, hrow, rows, data, labels, 3, cfg)
    for (wa, ba), (wb, bb) in zip(a[0].layers, b[0].layers):
        assert torch.equal(wa, wb) and torch.equal(ba, bb)
    assert torch.equal(a[2], b[2])


def test_paper_variant_is_kept_by_name(workdir):
    sel, spec, hrow, rows, data = _heliostat(workdir, "SS48")
    cfg = PretrainConfig(variant="paper", n_samples=400, pretrain_epochs=3, finetune_epochs=3)
    model, info, normal, position = fit_pretrained(sel["params"], spec, hrow, rows, data,
                                                   rows["split"].to_numpy(), 0, cfg)
    assert model.variant == "paper" and model.coarse_params is None
    assert info["pretrain_samples"] == 400 and np.isfinite(_errors(normal, position, data)).all()
    # a model file written before variants existed is the paper's
    legacy = {k: v for k, v in model.to_dict().items() if k != "variant"}
    assert PretrainedModel.from_dict(legacy, model.layers).variant == "paper"
    assert PretrainConfig.from_dict({"hidden": [6, 5, 4, 3]}).variant == "paper"
    with pytest.raises(ParameterError, match="variant must be one of residual, paper"):
        PretrainConfig(variant="papr")


def test_sweep_selects_pretrained_only_where_it_wins_and_aim_uses_it(workdir, runner, tmp_path):
    # hybrids held at the coarse model (weight decay 1e3) so the choice is pretrained-nn vs coarse
    # (and no GP: this is about the pre-trained network and the rule)
    args = ["sweep", "--workdir", str(workdir), "--select-pretrained", "--study", "0",
            "--wd-max", "1000", "--wd-min", "1000", "--no-octaves", "--stage-epochs", "20",
            "--no-gp", "--quiet"]
    _ok(runner, args)
    # SP13's network learns the injected error where the rows are: about 29 % on the plain
    # validation mean, but 14 % on the rows weighted toward the test rows' distances (and 4 % on
    # the test rows): the default rule keeps the coarse model (the networks' margin is 20 %)
    selection = read_artifact(workdir, SELECTION).set_index("heliostat_id")
    assert set(selection["model"]) == {"coarse"}
    rows = read_artifact(workdir, SWEEP)
    pre = rows[(rows["heliostat_id"] == "SP13") & (rows["model"] == "pretrained-nn")].iloc[0]
    sp13 = selection.loc["SP13"]
    assert pre["val_error_mrad"] < (1 - MIN_IMPROVEMENT) * sp13["coarse_val_error_mrad"]
    # with plain validation (no distance weighting) it wins, and the rest of the path is tested
    sweep_stage.run_sweep(workdir, select_pretrained=True, study=0, weight_decays=[1000.0],
                          extra_bands=(), path=PathConfig(stage_epochs=20), workers=1, gp=False,
                          rule=SelectionRule(match_k=0))
    selection = read_artifact(workdir, SELECTION).set_index("heliostat_id")
    assert selection.loc["SP13", "model"] == "pretrained-nn"
    assert selection.loc["SS48", "model"] == "coarse"
    rows = read_artifact(workdir, SWEEP)
    for hid, sel in selection.iterrows():
        r = rows[rows["heliostat_id"] == hid].set_index("model")
        pre_val = float(r.loc["pretrained-nn", "val_error_mrad"])
        if sel["model"] == "pretrained-nn":
            # the networks' margin on the (here unweighted) validation rows
            assert sel["weighted_val_error_mrad"] == pytest.approx(pre_val, rel=1e-12)
            assert pre_val <= (1 - MIN_IMPROVEMENT) * sel["coarse_val_error_mrad"]
            assert sel["val_error_mrad"] == pytest.approx(pre_val, rel=1e-12)
            assert math.isnan(sel["weight_decay"])

    # aim --model auto uses the selected network: its steps are the model's steps
    out = _ok(runner, ["aim", "--workdir", str(workdir), "--heliostat", "SP13", "--target",
                       "tower_target_upper", "--sun-azimuth", "10", "--sun-elevation", "40"])
    aimed = json.loads(out.stdout)
    assert aimed["model"] == "pretrained-nn"
    cfg, layers = load_model(workdir, "selected", "SP13")
    assert cfg["mode"] == "pretrained-nn" and cfg["variant"] == "residual"
    model = PretrainedModel.from_dict(cfg, layers)
    sel, spec, hrow, rows, data = _heliostat(workdir, "SP13")
    target = rows.loc[rows["target_name"] == "tower_target_upper",
                      ["target_e_m", "target_n_m", "target_u_m"]].median().to_numpy()
    from heliocal.pipeline.physics.sun import sun_vector_enu
    sun = torch.as_tensor(np.asarray(sun_vector_enu(10.0, 40.0), np.float64)).reshape(1, 3)
    expected = model.steps(sun, torch.tensor(target).reshape(1, 3), spec=spec)[0]
    assert aimed["axis_1_steps"] == pytest.approx(float(expected[0]), abs=1e-6)
    assert aimed["axis_2_steps"] == pytest.approx(float(expected[1]), abs=1e-6)
    coarse = json.loads(_ok(runner, ["aim", "--workdir", str(workdir), "--heliostat", "SP13",
                                     "--target", "tower_target_upper", "--sun-azimuth", "10",
                                     "--sun-elevation", "40", "--model", "coarse"]).stdout)
    # the correction is of the injected size: tens of steps, not zero, not thousands
    assert 1.0 < abs(aimed["axis_1_steps"] - coarse["axis_1_steps"]) < 3 * INJECT_STEPS


def test_the_margin_rule_holds_for_the_pretrained_candidate(workdir, tmp_path):
    """With a margin no candidate can meet (90 %), SP13's pre-trained network (about 30 % better
    on validation) is not selected: the candidate goes through the same rule as the hybrids."""
    import shutil

    from heliocal.pipeline.models.config import PathConfig
    from heliocal.pipeline.models.selection import SelectionRule
    from heliocal.pipeline.stages import sweep as sweep_stage

    wd = tmp_path / "wd"
    shutil.copytree(workdir, wd)
    sweep_stage.run_sweep(wd, select_pretrained=True, study=0, weight_decays=[1000.0],
                          extra_bands=(), path=PathConfig(stage_epochs=20), workers=1,
                          gp=False, rule=SelectionRule(min_improvement=0.9))
    selection = read_artifact(wd, SELECTION).set_index("heliostat_id")
    assert set(selection["model"]) == {"coarse"}
    rows = read_artifact(wd, SWEEP)
    pre = rows[(rows["heliostat_id"] == "SP13") & (rows["model"] == "pretrained-nn")]
    assert float(pre["val_error_mrad"].iloc[0]) < (1 - MIN_IMPROVEMENT) * float(
        selection.loc["SP13", "coarse_val_error_mrad"])   # 29 % better on the plain mean
