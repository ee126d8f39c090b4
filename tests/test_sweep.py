"""The sweep stage: the worst-case guarantee, the training-size study, and the batched program.

Data: the synthetic field of sample_data/synthetic (written by `heliocal simulate`, seed 7; its
ground_truth.json says SP13 is static: only focal-spot noise is left after a rigid-body fit).
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.coarse import run_fit_coarse
from heliocal.pipeline.hybrid import FineConfig
from heliocal.pipeline.ingest import run_ingest
from heliocal.pipeline.split import run_split
from heliocal.pipeline.sweep import (MIN_IMPROVEMENT, SELECTION, SWEEP, default_ladder, run_sweep,
                                     weight_decay_grid)

SYNTHETIC = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic" / "paint"


def test_weight_decay_grid_and_ladder():
    # closed form: one value per decade from 1 to 1e-6 is 7 values, plus 0
    assert weight_decay_grid() == pytest.approx([1, 0.1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 0.0])
    assert default_ladder(127) == [5, 10, 20, 40, 60, 100, 127]
    assert default_ladder(8) == [5, 8]


@pytest.fixture(scope="module")
def static_workdir(tmp_path_factory):
    w = tmp_path_factory.mktemp("sweep")
    run_ingest([SYNTHETIC], w)
    run_split(w)
    # static-20 frees every parameter the simulator deviated (deviations="static-20")
    run_fit_coarse(w, preset="static-20", heliostats=["SP13"], robust_start="never")
    return w


def test_network_that_can_only_overfit_falls_back_to_coarse(static_workdir):
    # SP13 is static: the rigid body fitted on all its training rows reaches the noise floor,
    # so an unregularised network can only fit noise; the selection must keep the coarse model
    # (the paper's worst-case guarantee).
    run_sweep(static_workdir, n_train=[10_000], weight_decays=[0.0], presets=("static-20",),
              baselines=(), config=FineConfig(max_epochs=150, patience=150),
              heliostats=["SP13"])
    sel = pd.read_parquet(static_workdir / SELECTION.filename)
    assert list(sel["model"]) == ["coarse"]
    row = sel.iloc[0]
    assert row["val_error_mrad"] == row["coarse_val_error_mrad"]
    sweep = pd.read_parquet(static_workdir / SWEEP.filename)
    hyb = sweep[sweep["model"] == "hybrid"].iloc[0]
    # the hybrid member was trained (it fits its training rows at least as well) ...
    coarse = sweep[sweep["model"] == "static-20"].iloc[0]
    assert hyb["train_error_mrad"] <= coarse["train_error_mrad"]
    # ... but does not generalise by the required margin (it does improve validation a little:
    # interpolating the coarse fit's residual structure helps rows between training rows)
    assert hyb["val_error_mrad"] > (1.0 - MIN_IMPROVEMENT) * row["coarse_val_error_mrad"]


def test_training_size_study_rows(static_workdir):
    run_sweep(static_workdir, n_train=[10, 40], weight_decays=[1.0, 0.0], seeds=[0, 1],
              presets=("static-6", "stone-8"), baselines=("nn-only",),
              config=FineConfig(max_epochs=20, patience=20), heliostats=["SP13"])
    sweep = pd.read_parquet(static_workdir / SWEEP.filename)
    counts = sweep.groupby("model").size().to_dict()
    # 2 sizes x 2 presets; 2 sizes x 2 weight decays x 2 seeds, once with the config's Fourier
    # bands and once with octaves; 2 sizes x 2 seeds (the selected preset static-20 is always
    # fitted too: it is the hybrid's base)
    assert counts == {"static-6": 2, "stone-8": 2, "static-20": 2, "hybrid": 8,
                      "hybrid-octaves": 8, "nn-only": 4}
    # fewer training rows (the largest kNN distances kept) lie farther from the test set
    d = sweep[sweep["model"] == "static-6"].set_index("n_train")["test_train_distance_deg"]
    assert d[10] > d[40]
    sel = pd.read_parquet(static_workdir / SELECTION.filename)
    assert (sel["val_error_mrad"] <= sel["coarse_val_error_mrad"]).all()
    assert np.isfinite(sweep["test_error_mrad"]).all()


def test_selected_predictions_match_the_selection(static_workdir, monkeypatch):
    # the per-measurement predictions of the selected model reproduce the selection's means
    # (same model, same rows): a check that the right member, ensemble and base were used. A
    # negative margin forces a hybrid choice on this static heliostat.
    from heliocal.pipeline import sweep as sweep_module
    from heliocal.pipeline.sweep import SELECTED_PREDICTIONS

    monkeypatch.setattr(sweep_module, "MIN_IMPROVEMENT", -1.0)
    run_sweep(static_workdir, n_train=[10, 10_000], weight_decays=[1e-3, 0.0], presets=("static-20",),
              baselines=(), config=FineConfig(max_epochs=60, patience=60), heliostats=["SP13"])
    sel = pd.read_parquet(static_workdir / SELECTION.filename).iloc[0]
    assert sel["model"] in ("hybrid", "hybrid-octaves")
    sweep = pd.read_parquet(static_workdir / SWEEP.filename)
    full = sweep[sweep["model"].str.startswith("hybrid") & (sweep["n_train"] > 10)]
    assert sel["val_error_mrad"] == full["val_error_mrad"].min()   # the best on validation
    pred = pd.read_parquet(static_workdir / SELECTED_PREDICTIONS.filename)
    assert set(pred["model"]) == {"selected"}
    for split, col in (("validation", "val_error_mrad"), ("test", "test_error_mrad")):
        mean = pred.loc[pred["split"] == split, "error_mrad"].mean()
        assert mean == pytest.approx(sel[col], rel=1e-9)


@pytest.fixture(scope="module")
def temperature_workdir(tmp_path_factory):
    """The synthetic sample as the accuracy figures in docs/hybrid.md use it: the log with the
    PAINT properties (temperature as env_temperature), split-knn, the auto-selected preset."""
    from heliocal.pipeline.ingest import IngestOptions

    w = tmp_path_factory.mktemp("sweep_env")
    log = SYNTHETIC.parent / "calibration_log.csv"
    run_ingest([log], w, IngestOptions(properties=SYNTHETIC))
    run_split(w)
    run_fit_coarse(w, heliostats=["SS48", "SQ04"])
    return w


def test_gear_error_heliostat_gets_the_hybrid(temperature_workdir):
    # SS48 carries a gear error of period 4000 steps (1/18.86 of max_steps; ground_truth.json).
    # docs/hybrid.md measures the default sweep at 0.65 x coarse (must-show: <= 0.7 x); here one
    # weight decay of the grid (the one the full sweep selects) and the default encoding, so it
    # runs in seconds. The octave bands cannot represent that period (test_hybrid), so this test
    # fails with them.
    config = FineConfig(env=("temperature",))
    run_sweep(temperature_workdir, n_train=[10_000], weight_decays=[1e-2], baselines=(),
              config=config, heliostats=["SS48"], extra_bands=())
    sel = pd.read_parquet(temperature_workdir / SELECTION.filename).iloc[0]
    assert sel["model"] == "hybrid"
    assert sel["test_error_mrad"] <= 0.7 * sel["coarse_test_error_mrad"]


def test_static_heliostat_whose_validation_improves_keeps_coarse(temperature_workdir):
    # SQ04 is static. The unregularised ensemble improves its validation error by about 15 %
    # (interpolating the coarse fit's residual structure) while its test error gets worse
    # (docs/hybrid.md, "Selection"); the 20 % margin keeps the coarse model.
    config = FineConfig(env=("temperature",))
    run_sweep(temperature_workdir, n_train=[10_000], weight_decays=[0.0], baselines=(),
              config=config, heliostats=["SQ04"], extra_bands=())
    sel = pd.read_parquet(temperature_workdir / SELECTION.filename).iloc[0]
    sweep = pd.read_parquet(temperature_workdir / SWEEP.filename)
    hyb = sweep[sweep["model"] == "hybrid"].iloc[0]
    assert hyb["val_error_mrad"] < 0.95 * sel["coarse_val_error_mrad"]     # a real val gain ...
    assert hyb["test_error_mrad"] > sel["coarse_test_error_mrad"]          # ... that does not hold
    assert sel["model"] == "coarse"
    assert sel["test_error_mrad"] == sel["coarse_test_error_mrad"]
