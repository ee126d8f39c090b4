"""The sweep stage: one source of truth with fit-coarse, the worst-case guarantee, the
training-size study, and the model `aim` uses.

Data: the synthetic field of sample_data/synthetic (written by `heliocal simulate`, seed 7; its
ground_truth.json says SP13 and SQ04 are static: only focal-spot noise is left after a
rigid-body fit; SS48 and ST20 are dynamic), and heliostats simulated here whose PAINT
properties file states a nominal geometry far from the truth (like PAINT's BF41).
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from heliocal.pipeline.artifacts.store import read_provenance
from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, COARSE_PREDICTIONS
from heliocal.pipeline.stages.fit_coarse import coarse_fit_options, run_fit_coarse
from heliocal.pipeline.models.config import FineConfig
from heliocal.pipeline.models.gp import GPConfig
from heliocal.pipeline.stages.aim import aim_models, aim_steps
from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
from heliocal.pipeline.io.staged import IngestOptions
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.stages.simulate import write_field
from heliocal.pipeline.stages.split import run_split
from heliocal.pipeline.stages.sweep import (MIN_IMPROVEMENT, default_ladder, run_sweep,
                                            study_heliostats, weight_decay_grid)
from heliocal.pipeline.models.config import PathConfig, ScreenConfig
from heliocal.pipeline.models.selection import SelectionRule
from heliocal.pipeline.artifacts.schemas import SELECTED_PREDICTIONS, SELECTION, SWEEP

#: end-to-end runs of the stages: `make test` runs them, `make test-fast` skips them
pytestmark = pytest.mark.slow

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
    # (the paper's worst-case guarantee). The screen is off: this is the rule's test, so the
    # network must be trained (tests/test_sweep_screen.py: the screen would skip it).
    run_sweep(static_workdir, n_train=[10_000], weight_decays=[0.0], presets=("static-20",),
              baselines=(), config=FineConfig(max_epochs=150, patience=150),
              heliostats=["SP13"], study=0, screen=ScreenConfig(enabled=False))
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
              config=FineConfig(max_epochs=20, patience=20), heliostats=["SP13"],
              screen=ScreenConfig(enabled=False))   # the production path's rows are counted
    sweep = pd.read_parquet(static_workdir / SWEEP.filename)
    counts = sweep.groupby("model").size().to_dict()
    # the study's sizes are 10, 40 and the full one (fit-coarse's training rows). Presets: 3
    # sizes each (static-20 at the full size is fit-coarse's own fit; static-6 and stone-8,
    # which fit-coarse did not fit, are fitted at the full size too). Hybrid, once with the
    # config's Fourier bands and once with octaves: 2 sizes x 2 weight decays x 2 seeds in the
    # study plus 2 weight decays x 2 seeds of the production selection at the full size.
    # nn-only: 3 sizes x 2 seeds. The GP: the 2 study sizes and the production one (plus, at the
    # full size, its sun structure when the best one has time: gp-sun).
    assert counts.pop("gp-sun", 1) == 1
    assert counts == {"static-6": 3, "stone-8": 3, "static-20": 3, "hybrid": 12,
                      "hybrid-octaves": 12, "nn-only": 6, "gp": 3}
    # fewer training rows (the largest kNN distances kept) lie farther from the test set
    d = sweep[sweep["model"] == "static-6"].set_index("n_train")["test_train_distance_deg"]
    assert d[10] > d[40]
    sel = pd.read_parquet(static_workdir / SELECTION.filename)
    assert (sel["val_error_mrad"] <= sel["coarse_val_error_mrad"]).all()
    assert np.isfinite(sweep["test_error_mrad"]).all()


def test_selected_predictions_match_the_selection(static_workdir):
    # the per-measurement predictions of the selected model reproduce the selection's means
    # (same model, same rows): a check that the right member, ensemble and base were used. A
    # negative margin forces a hybrid choice on this static heliostat.
    from heliocal.pipeline.artifacts.schemas import SELECTED_PREDICTIONS

    # every hybrid passes (no margin, no significance screen, plain validation, the best kept)
    force = SelectionRule(min_improvement=-1.0, alpha=1.0, match_k=0, one_se=False)
    run_sweep(static_workdir, n_train=[10, 10_000], weight_decays=[1e-3, 0.0], presets=("static-20",),
              baselines=(), config=FineConfig(max_epochs=60, patience=60), heliostats=["SP13"],
              gp=False, rule=force)
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
    from heliocal.pipeline.io.staged import IngestOptions

    w = tmp_path_factory.mktemp("sweep_env")
    log = SYNTHETIC.parent / "calibration_log.csv"
    run_ingest([log], w, IngestOptions(properties=SYNTHETIC))
    run_split(w)
    run_fit_coarse(w, heliostats=["SS48", "SQ04"])
    return w


def test_static_heliostat_whose_validation_improves_keeps_coarse(temperature_workdir):
    # SQ04 is static. The unregularised ensemble improves its validation error by about 15 %
    # (interpolating the coarse fit's residual structure) while its test error gets worse
    # (docs/hybrid.md, "Selection"); the 20 % margin keeps the coarse model.
    config = FineConfig(env=("temperature",))
    run_sweep(temperature_workdir, n_train=[10_000], weight_decays=[0.0], baselines=(),
              config=config, heliostats=["SQ04"], extra_bands=(), study=0,
              screen=ScreenConfig(enabled=False))   # the rule's test: the path must be trained
    sel = pd.read_parquet(temperature_workdir / SELECTION.filename).iloc[0]
    sweep = pd.read_parquet(temperature_workdir / SWEEP.filename)
    hyb = sweep[sweep["model"] == "hybrid"].iloc[0]
    assert hyb["val_error_mrad"] < 0.95 * sel["coarse_val_error_mrad"]     # a real val gain ...
    assert hyb["test_error_mrad"] > sel["coarse_test_error_mrad"]          # ... that does not hold
    assert sel["model"] == "coarse"
    assert sel["test_error_mrad"] == sel["coarse_test_error_mrad"]


# ------------------------------------------------------------------------------------------------
# one source of truth: the sweep's coarse model is fit-coarse's
# ------------------------------------------------------------------------------------------------
FAST = FineConfig(max_epochs=20, patience=20, ensemble=2)


def _simulated_workdir(root: Path, seed: int, n: int, *, angle_shift=(0.0, 0.0),
                       stroke_shift=(0.0, 0.0), dynamic: bool = False, **fit_coarse) -> Path:
    """One simulated juelich heliostat (static-20 deviations, 0.2 mrad noise) whose PAINT
    properties state a nominal geometry shifted from the truth by ``angle_shift`` [rad] and
    ``stroke_shift`` [m] (actuators 1, 2); ingested, kNN split, fit-coarse (its defaults unless
    given; without the rolling-origin evaluation, which the sweep does not read)."""
    field = simulate_field(1, seed=seed, measurements=(n, n),
                           dynamic_fraction=1.0 if dynamic else 0.0)
    write_field(field, root / "sim")
    for path in (root / "sim" / "paint").glob("*/*-heliostat-properties.json"):
        props = json.loads(path.read_text())
        for actuator, da, ds in zip(props["kinematics_properties"]["actuators"], angle_shift,
                                    stroke_shift):
            actuator["initial_angle"] += da
            actuator["initial_stroke_length"] += ds
        path.write_text(json.dumps(props))
    w = root / "run"
    run_ingest([root / "sim" / "paint"], w)
    run_split(w)
    run_fit_coarse(w, **{"rolling_origins": 0, **fit_coarse})
    return w


def _fit_coarse_selected(w: Path) -> pd.Series:
    p = pd.read_parquet(w / COARSE_PARAMS.filename)
    return p[p["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")


def _assert_one_source_of_truth(w: Path) -> pd.DataFrame:
    """selection.parquet's coarse errors are fit-coarse's selected preset's to the last digit,
    the full-size preset rows of sweep.parquet are fit-coarse's, and where the coarse model is
    selected its per-measurement predictions are coarse_predictions.parquet's."""
    sel = pd.read_parquet(w / SELECTION.filename).set_index("heliostat_id")
    fc = _fit_coarse_selected(w)
    for hid, row in sel.iterrows():
        assert row["preset"] == fc.loc[hid, "preset"]
        assert row["coarse_val_error_mrad"] == fc.loc[hid, "val_error_mrad"]      # exact
        assert row["coarse_test_error_mrad"] == fc.loc[hid, "test_error_mrad"]    # exact
        assert row["val_error_mrad"] <= fc.loc[hid, "val_error_mrad"]
    params = pd.read_parquet(w / COARSE_PARAMS.filename).drop_duplicates(["heliostat_id", "preset"])
    sweep = pd.read_parquet(w / SWEEP.filename)
    for _, p in params.iterrows():
        if p["heliostat_id"] not in sel.index:
            continue
        r = sweep[(sweep["heliostat_id"] == p["heliostat_id"]) & (sweep["model"] == p["preset"])
                  & (sweep["n_train"] == sel.loc[p["heliostat_id"], "n_train"])]
        assert len(r) == 1
        for col in ("train_error_mrad", "val_error_mrad", "test_error_mrad"):
            assert r[col].iloc[0] == p[col], (p["heliostat_id"], p["preset"], col)
    pred = pd.read_parquet(w / SELECTED_PREDICTIONS.filename)
    coarse = pd.read_parquet(w / COARSE_PREDICTIONS.filename)
    coarse = coarse[coarse["selected"]].set_index(["heliostat_id", "measurement_id"])
    for hid, row in sel.iterrows():
        mine = pred[pred["heliostat_id"] == hid].set_index(["heliostat_id", "measurement_id"])
        if row["model"] == "coarse":
            theirs = coarse.loc[mine.index]
            assert np.array_equal(mine["error_mrad"].to_numpy(), theirs["error_mrad"].to_numpy())
        else:   # the hybrid was trained on top of fit-coarse's parameters
            cfg = json.loads((w / "hybrid" / "selected" / f"{hid}.json").read_text())
            fitted = params[(params["heliostat_id"] == hid)]
            full = pd.read_parquet(w / COARSE_PARAMS.filename)
            full = full[(full["heliostat_id"] == hid) & full["selected"]].sort_values("parameter_index")
            assert cfg["base_params"] == full["fitted"].tolist() and len(fitted)
    return sel


@pytest.fixture(scope="module")
def robust_workdir(tmp_path_factory):
    """A heliostat whose nominal geometry needs the robust start: the properties file's
    actuator zero points are off by 0.24 and 0.58 rad and its initial strokes by 0.2 and 0.16 m
    (about what fit-coarse corrects on PAINT's BF41); nominal test error about 560 mrad."""
    return _simulated_workdir(tmp_path_factory.mktemp("robust"), 13, 90,
                              angle_shift=(0.24, 0.58), stroke_shift=(0.2, 0.16))


def test_full_size_coarse_is_fit_coarse_with_a_ladder_from_5_rows(robust_workdir):
    # The study starts at 5 training rows, whose robust start is not the full set's. Before,
    # the sweep refitted every size with one start cache, smallest size first, and on this
    # heliostat its full-size coarse test error was 1.515 mrad against fit-coarse's 0.199
    # (measured with the previous sweep.py); now the full size is fit-coarse's fit itself.
    fc = _fit_coarse_selected(robust_workdir).iloc[0]
    assert fc["test_error_mrad"] < 0.3          # fit-coarse recovers the geometry (noise 0.2)
    run_sweep(robust_workdir, n_train=[5, 20], weight_decays=[1e-2, 0.0], baselines=(),
              config=FAST, extra_bands=(), study=1)
    sel = _assert_one_source_of_truth(robust_workdir)
    assert sel["coarse_test_error_mrad"].iloc[0] == fc["test_error_mrad"]
    sweep = pd.read_parquet(robust_workdir / SWEEP.filename)
    assert sorted(sweep["n_train"].unique()) == [5, 20, int(fc["n_train"])]


def test_study_point_is_what_fit_coarse_gives_with_that_many_rows(robust_workdir, tmp_path):
    # fit-coarse run on a split restricted to 5 (and 20) training rows, with the same kNN
    # split otherwise, must give the study's numbers: the same function, options and a robust
    # start of its own (tolerance: the batched program holds the sizes together, which changes
    # the rounding of its sums, not the solution)
    run_sweep(robust_workdir, n_train=[5, 20], weight_decays=[0.0], baselines=(), config=FAST,
              extra_bands=(), study=1)
    sweep = pd.read_parquet(robust_workdir / SWEEP.filename)
    for n in (5, 20):
        w = Path(shutil.copytree(robust_workdir, tmp_path / f"n{n}"))
        run_split(w, n_train=n)
        run_fit_coarse(w, rolling_origins=0)
        params = pd.read_parquet(w / COARSE_PARAMS.filename).drop_duplicates("preset")
        for _, p in params.iterrows():
            r = sweep[(sweep["model"] == p["preset"]) & (sweep["n_train"] == n)].iloc[0]
            assert r["val_error_mrad"] == pytest.approx(p["val_error_mrad"], rel=1e-6, abs=1e-9)
            assert r["test_error_mrad"] == pytest.approx(p["test_error_mrad"], rel=1e-6, abs=1e-9)


def test_study_uses_the_solver_and_options_fit_coarse_recorded(static_workdir, tmp_path):
    # fit-coarse with the scipy solver and the huber loss: the study reads both from
    # coarse_params.parquet's provenance and its 20-row point equals fit-coarse's on 20 rows
    w = Path(shutil.copytree(static_workdir, tmp_path / "w"))
    run_fit_coarse(w, preset="static-6", heliostats=["SP13"], solver="scipy", loss="huber",
                   f_scale_mrad=0.5)
    assert coarse_fit_options(w) == {"solver": "scipy", "loss": "huber", "f_scale_mrad": 0.5,
                                     "robust_start": "auto"}
    run_sweep(w, n_train=[20], weight_decays=[0.0], baselines=(), config=FAST, extra_bands=(),
              heliostats=["SP13"], study=1)
    assert read_provenance(w / SWEEP.filename)["options"]["coarse_options"]["solver"] == "scipy"
    r = pd.read_parquet(w / SWEEP.filename)
    r = r[(r["model"] == "static-6") & (r["n_train"] == 20)].iloc[0]
    run_split(w, n_train=20)
    run_fit_coarse(w, preset="static-6", heliostats=["SP13"], solver="scipy", loss="huber",
                   f_scale_mrad=0.5)
    p = pd.read_parquet(w / COARSE_PARAMS.filename).iloc[0]
    assert r["test_error_mrad"] == pytest.approx(p["test_error_mrad"], rel=1e-9)
    # the default (batched, soft_l1) lands elsewhere: the options matter on these 20 rows
    run_fit_coarse(w, preset="static-6", heliostats=["SP13"])
    q = pd.read_parquet(w / COARSE_PARAMS.filename).iloc[0]
    assert abs(q["test_error_mrad"] - p["test_error_mrad"]) > 1e-6


@settings(max_examples=5, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(70, 130), dynamic=st.booleans(),
       shifted=st.booleans())
def test_selection_never_worse_than_fit_coarse_on_validation(tmp_path_factory, seed, n, dynamic,
                                                             shifted):
    # property: on any heliostat (static or dynamic, nominal geometry right or a radian-scale
    # zero point off, 70-130 measurements) and a study ladder from 5 rows, the selected model's
    # mean validation error is at most fit-coarse's selected preset's, whose errors
    # selection.parquet repeats exactly. A negative margin makes every hybrid that is better on
    # validation at all win, the hardest case for the guarantee.
    root = tmp_path_factory.mktemp("prop")
    shift = {"angle_shift": (0.24, 0.58), "stroke_shift": (0.2, 0.16)} if shifted else {}
    w = _simulated_workdir(root, seed, n, dynamic=dynamic, **shift)
    run_sweep(w, n_train=[5], weight_decays=[1e-2, 0.0], baselines=(), config=FAST,
              extra_bands=(), study=1,
              rule=SelectionRule(min_improvement=-0.5, min_improvement_gp=-0.5, alpha=1.0))
    sel = _assert_one_source_of_truth(w)
    fc = _fit_coarse_selected(w)
    assert (sel["val_error_mrad"] <= fc.loc[sel.index, "val_error_mrad"]).all()


def test_study_heliostats_is_a_seeded_choice():
    ids = [f"H{k:02d}" for k in range(20)]
    a = study_heliostats(ids, 5, seed=3)
    assert len(a) == 5 and a == sorted(a) and set(a) <= set(ids)
    assert study_heliostats(ids, 5, seed=3) == a            # same seed, same choice
    assert study_heliostats(ids, 5, seed=4) != a            # (a collision has odds 1 / 15504)
    assert study_heliostats(ids, 50) == ids and study_heliostats(ids, 0) == []
    assert study_heliostats(ids, None) == ids
    assert study_heliostats(ids, ["H03", "H01"]) == ["H01", "H03"]


# ------------------------------------------------------------------------------------------------
# the model aim uses, and `heliocal info` saying so
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def aim_workdir(tmp_path_factory):
    """The synthetic sample with every source of aim's model: the sweep over SS48 (gear error:
    hybrid) and SQ04 (static: coarse kept), a fit-hybrid hybrid for ST20 (not swept), and SP13
    with fit-coarse only. The sweep's GP has no periodic term here: these tests are about the
    networks' answer to a gear error (their integer bands represent its period); with the
    term the GP represents it better still (tests/test_periodic.py, SS48)."""
    w = tmp_path_factory.mktemp("aim")
    log = SYNTHETIC.parent / "calibration_log.csv"
    run_ingest([log], w, IngestOptions(properties=SYNTHETIC))
    run_split(w)
    run_fit_coarse(w)
    config = FineConfig(env=("temperature",))
    run_fit_hybrid(w, mode="hybrid", weight_decay=1e-3, heliostats=["ST20"],
                   config=FineConfig(env=("temperature",), max_epochs=50, ensemble=2))
    # one weight decay of the grid (the one the full sweep selects on SS48), trained from scratch
    # with the full budget of FineConfig, so the fixture runs in seconds
    run_sweep(w, weight_decays=[1e-2], baselines=(), config=config, heliostats=["SS48", "SQ04"],
              extra_bands=(), study=0, path=PathConfig(warm_start=False), time_split=True,
              gp_config=GPConfig(env=("temperature",), periodic=False))
    return w


def test_gear_error_heliostat_gets_the_hybrid(aim_workdir):
    # SS48 carries a gear error of period 4000 steps (1/18.86 of max_steps; ground_truth.json).
    # docs/hybrid.md measures the default sweep at 0.70 x coarse and independent trainings of
    # the grid at 0.64-0.68 x (must-show: <= 0.7 x); here one weight decay of the grid and the
    # default encoding (aim_workdir), so it runs in seconds. The octave bands cannot represent
    # that period (test_hybrid), so this test fails with them. SQ04, static, trained in the same
    # batched program, keeps the coarse model.
    sel = _assert_one_source_of_truth(aim_workdir)
    assert sel.loc["SS48", "model"] == "hybrid"
    assert sel.loc["SS48", "test_error_mrad"] <= 0.7 * sel.loc["SS48", "coarse_test_error_mrad"]
    assert sel.loc["SQ04", "model"] == "coarse"


def test_info_names_the_model_aim_uses(aim_workdir, runner):
    from heliocal.cli.main import app
    import heliocal.cli.info  # noqa: F401 - registers `info`

    res = runner.invoke(app, ["info", str(aim_workdir), "--json"])
    assert res.exit_code == 0, res.stderr
    info = {m["heliostat_id"]: m for m in json.loads(res.stdout)["aim_models"]}
    sel = pd.read_parquet(aim_workdir / SELECTION.filename).set_index("heliostat_id")
    fc = _fit_coarse_selected(aim_workdir)
    # where each answer comes from: the expected values are read from the artifacts directly
    assert (info["SS48"]["model"], info["SS48"]["variant"], info["SS48"]["source"]) == (
        "hybrid", "hybrid", "sweep")
    assert info["SS48"]["weight_decay"] == 1e-2
    assert info["SS48"]["test_error_mrad"] == sel.loc["SS48", "test_error_mrad"]
    assert (info["SQ04"]["model"], info["SQ04"]["source"]) == ("coarse", "sweep")
    assert info["SQ04"]["test_error_mrad"] == fc.loc["SQ04", "test_error_mrad"]
    assert (info["ST20"]["model"], info["ST20"]["source"]) == ("hybrid", "fit-hybrid")
    assert info["ST20"]["weight_decay"] == 1e-3
    hp = pd.read_parquet(aim_workdir / "hybrid_predictions.parquet")
    hp = hp[(hp["heliostat_id"] == "ST20") & (hp["split"] == "test")]
    assert info["ST20"]["test_error_mrad"] == pytest.approx(hp["error_mrad"].mean(), rel=1e-12)
    assert (info["SP13"]["model"], info["SP13"]["source"]) == ("coarse", "fit-coarse")
    assert info["SP13"]["preset"] == fc.loc["SP13", "preset"]
    assert info["SP13"]["val_error_mrad"] == fc.loc["SP13", "val_error_mrad"]
    # aim --model auto uses exactly that model
    for hid, m in info.items():
        out = aim_steps(aim_workdir, hid, aim_point_enu=(0.0, 0.0, 30.0),
                        time_utc="2023-06-21T11:00:00Z", env={"temperature": 20.0})
        assert out["model"] == m["model"], hid
    # and the same hybrid: aim's steps through the sweep's selected ensemble differ from the
    # fit-hybrid or coarse answer
    a = aim_steps(aim_workdir, "SS48", aim_point_enu=(0.0, 0.0, 30.0),
                  time_utc="2023-06-21T11:00:00Z", env={"temperature": 20.0})
    c = aim_steps(aim_workdir, "SS48", aim_point_enu=(0.0, 0.0, 30.0),
                  time_utc="2023-06-21T11:00:00Z", model="coarse")
    assert abs(a["axis_2_steps"] - c["axis_2_steps"]) > 0.5
    assert aim_models(aim_workdir)["SS48"]["model_dir"] == "selected"
    # the human table says the same
    res = runner.invoke(app, ["info", str(aim_workdir)])
    line = next(l for l in res.stdout.splitlines() if l.strip().startswith("SS48"))
    assert "hybrid on" in line and "0.01" in line and "sweep" in line


def test_forward_in_time_errors_come_from_the_selected_model_trained_on_the_past(aim_workdir,
                                                                                 tmp_path):
    # SQ04 keeps the coarse model: its forward-in-time figures are fit-coarse's time-split fit's
    from heliocal.pipeline.artifacts.schemas import HYBRID_PREDICTIONS, SPLIT
    from heliocal.pipeline.artifacts.store import read_artifact

    sel = pd.read_parquet(aim_workdir / SELECTION.filename).set_index("heliostat_id")
    fc = _fit_coarse_selected(aim_workdir)
    assert sel.loc["SQ04", "time_test_error_mrad"] == fc.loc["SQ04", "time_test_error_mrad"]
    for hid in ("SQ04", "SS48"):   # the coarse model's, whatever was selected (exact)
        assert sel.loc[hid, "coarse_time_test_error_mrad"] == fc.loc[hid, "time_test_error_mrad"]
    pred = read_artifact(aim_workdir, SELECTED_PREDICTIONS).merge(
        read_artifact(aim_workdir, SPLIT, columns=["heliostat_id", "measurement_id", "time_split"]))
    for hid in ("SQ04", "SS48"):
        p = pred[(pred["heliostat_id"] == hid) & (pred["time_split"] == "test")]
        assert len(p) == 30
        assert p["time_error_mrad"].mean() == pytest.approx(sel.loc[hid, "time_test_error_mrad"],
                                                            rel=1e-12)
    # SS48's hybrid trained again on the time split: the same model as fit-hybrid trains with
    # the selected weight decay and seed on the time split (one weight decay, no warm start:
    # train_members from the seeded weights in both), on another code path: equal numbers
    w = tmp_path / "copy"
    shutil.copytree(aim_workdir, w)
    assert sel.loc["SS48", "model"] == "hybrid" and sel.loc["SS48", "weight_decay"] == 1e-2
    run_fit_hybrid(w, mode="hybrid", weight_decay=1e-2, seed=int(sel.loc["SS48", "seed"]),
                   heliostats=["SS48"], config=FineConfig(env=("temperature",)))
    hyb = read_artifact(w, HYBRID_PREDICTIONS)
    hyb = hyb[(hyb["heliostat_id"] == "SS48") & (hyb["model"] == "hybrid")]
    ss = pred[pred["heliostat_id"] == "SS48"].set_index("measurement_id")
    mine = hyb.set_index("measurement_id")["time_error_mrad"].reindex(ss.index)
    # float32 training: the two programs differ in batch composition, so they round apart in
    # the last bits (measured 4e-9 mrad, 1e-7 relative); 1e-5 mrad is far below any model change
    np.testing.assert_allclose(mine.to_numpy(), ss["time_error_mrad"].to_numpy(), rtol=0,
                               atol=1e-5)
    # and it is another model than the kNN-trained one (it did not see the latest rows)
    assert not np.allclose(ss["time_error_mrad"], ss["error_mrad"])
