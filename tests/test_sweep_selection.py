"""The sweep's selection of one heliostat (stages/selection.py): the forward-in-time check of
every chosen fine model and its fallback to the static choice (issue 33, item 3).

The unit tests' heliostat and its errors are written out here: ten rows whose split.parquet
``time_split`` labels are four train, three validation and three test rows; the coarse model's
time-split errors are 1 mrad on every row. The GP tests simulate a static heliostat (150 rows of
a year, 0.1 mrad noise) and add a sky pattern to its focal spots that lasts the whole year or
only its first 100 rows, the time split's training rows.
"""

import math
import shutil

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.stages.selection import (CandidatePool, HeliostatChoice,
                                                apply_forward_checks, time_labels)

IDS = [f"m{i}" for i in range(10)]
TIME = ["train"] * 4 + ["validation"] * 3 + ["test"] * 3


class _Item:
    """The parts of a SweepInputs the check reads."""

    def __init__(self):
        self.rows = pd.DataFrame({"measurement_id": IDS})
        self.split_rows = pd.DataFrame({"measurement_id": IDS[::-1], "time_split": TIME[::-1]})
        self.selected = {"preset": "static-6"}
        self.coarse = {"static-6": pd.DataFrame({"time_error_mrad": np.ones(10)})}


def _choice(model, time_errors=None, fallback=None):
    predictions = pd.DataFrame({"measurement_id": IDS, "error_mrad": np.zeros(10)})
    return HeliostatChoice({"heliostat_id": "H1", "model": model, "forward_check": ""}, None,
                           predictions, fallback, time_errors)


def _result(hybrid_time_val: float):
    """A chosen hybrid whose forward pass gave ``hybrid_time_val`` on the time-validation rows,
    with the coarse model as its static fallback."""
    fallback = _choice("coarse", time_errors=np.full(10, 1.0))
    choice = _choice("hybrid", fallback=fallback)
    choice.predictions["time_error_mrad"] = hybrid_time_val
    return {"selection": choice.selection, "selected_state": {"state": "hybrid"},
            "predictions": choice.predictions, "choice": choice}


def test_time_labels_follow_the_rows_order():
    labels = time_labels(_Item().rows, _Item().split_rows)
    assert labels.tolist() == TIME


def test_a_hybrid_no_worse_forward_in_time_is_kept():
    res = _result(0.9)                 # 0.9 against the coarse model's 1.0 on time validation
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid"
    assert res["selection"]["forward_check"] == "passed"
    assert res["selection"]["time_val_error_mrad"] == 0.9
    assert res["selection"]["coarse_time_val_error_mrad"] == 1.0


def test_a_tie_within_the_tolerance_is_not_worse():
    # 1.005 against 1.0: within FORWARD_TOLERANCE (1 %)
    res = _result(1.005)
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid" and res["selection"]["forward_check"] == "passed"


def test_a_hybrid_worse_forward_in_time_falls_back_to_the_static_choice():
    res = _result(1.2)
    apply_forward_checks([res], {"H1": _Item()})
    sel = res["selection"]
    assert sel["model"] == "coarse" and res["selected_state"] is None
    assert sel["forward_check"].startswith("failed (hybrid)")
    assert (sel["time_val_error_mrad"], sel["coarse_time_val_error_mrad"]) == (1.2, 1.0)
    # the fallback's own forward-in-time errors are what the selection reports now
    assert res["predictions"]["time_error_mrad"].tolist() == [1.0] * 10
    assert sel["time_test_error_mrad"] == 1.0 and sel["coarse_time_test_error_mrad"] == 1.0


def test_without_its_time_split_training_a_hybrid_is_kept_and_says_so():
    res = _result(float("nan"))        # a sweep without --time-split
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid"
    assert res["selection"]["forward_check"] == "not checked (no time-split training)"
    assert math.isnan(res["selection"]["time_val_error_mrad"])


def test_a_choice_checked_at_its_choice_is_not_checked_again():
    res = _result(1.2)
    res["choice"].fallback = None       # a GP: CandidatePool.choose checked it already
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid" and res["selection"]["forward_check"] == ""


def test_the_pretrained_network_without_date_inputs_is_checked_too():
    res = _result(1.2)                 # pretrained-nn: trained on the time split by the forward pass
    res["selection"]["model"] = "pretrained-nn"
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "coarse"
    assert res["selection"]["forward_check"].startswith("failed (pretrained-nn)")


def test_a_network_standing_in_for_a_refused_gp_names_both_checks():
    res = _result(0.9)
    res["choice"].refused = "gp"
    apply_forward_checks([res], {"H1": _Item()})
    assert res["selection"]["model"] == "hybrid"
    assert res["selection"]["forward_check"] == "failed (gp), then passed (hybrid)"
    worse = _result(1.2)
    worse["choice"].refused = "gp"
    apply_forward_checks([worse], {"H1": _Item()})
    assert worse["selection"]["model"] == "coarse"
    assert worse["selection"]["forward_check"] == ("failed (gp), then failed (hybrid): fell back "
                                                   "to the static choice")


# ------------------------------------------------------------------------------------------------
# a GP without time input, chosen on the kNN split, refitted on the time split
# ------------------------------------------------------------------------------------------------
def _sky_pattern_heliostat(root, lasting: bool):
    """The sweep's view of a simulated static heliostat whose focal spots carry the sky pattern
    (sin(az / 10 deg), 0.5 cos(el / 8 deg)) mrad along the target plane's (horizontal, vertical)
    axes: on every row (``lasting``), or on its first 100 rows only (the time split's training
    rows; the latest 30 are its test rows, the 20 before them its validation rows)."""
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.simulator import simulate_field, target_plane_axes
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.simulate import write_field
    from heliocal.pipeline.stages.split import run_split
    from heliocal.pipeline.stages.sweep_inputs import SweepHeliostat, read_sweep_inputs

    field = simulate_field(1, seed=11, measurements=(150, 150), dynamic_fraction=0.0,
                           noise_mrad=0.1)
    m = field.measurements                          # rows in time order
    az, el = m["sun_azimuth_deg"].to_numpy(), m["sun_elevation_deg"].to_numpy()
    pattern = np.column_stack([np.sin(az / 10), 0.5 * np.cos(el / 8)])
    if not lasting:
        pattern[100:] = 0.0
    horizontal, vertical = target_plane_axes(
        m[["target_normal_e", "target_normal_n", "target_normal_u"]].to_numpy())
    metres = m["distance_m"].to_numpy()[:, None] / 1000.0
    shift = metres * (pattern[:, :1] * horizontal + pattern[:, 1:] * vertical)
    for i, axis in enumerate("enu"):
        m[f"focal_spot_{axis}_m"] += shift[:, i]
    write_field(field, root / "field")
    work = root / "work"
    run_ingest([root / "field" / "paint"], work, IngestOptions())
    run_split(work)
    run_fit_coarse(work, rolling_origins=3)
    return SweepHeliostat.of(next(iter(read_sweep_inputs(work, None).values())))


def _gp_without_time_pool(h) -> CandidatePool:
    """The heliostat's candidates: the coarse model and a GP of the sun alone (no date input)."""
    from heliocal.pipeline.models.fade import TIME_FADE_DAYS
    from heliocal.pipeline.models.gp import GPConfig
    from heliocal.pipeline.models.gp_heliostat import fit_heliostat_gps
    from heliocal.pipeline.stages.fit_coarse import coarse_row_parameters

    pool = CandidatePool(h)
    config = GPConfig(structures=("sun",))
    fits = fit_heliostat_gps(h.rows, h.labels, h.spec, h.data,
                             coarse_row_parameters(h.selected, h.rows["timestamp"]), config,
                             pool.weights, time_length_days=TIME_FADE_DAYS)
    pool.add_gp(fits, config)
    assert [c.info["date_inputs"] for c in pool.candidates] == [False]
    return pool


@pytest.fixture(scope="module")
def sky_pattern_pools(tmp_path_factory):
    root = tmp_path_factory.mktemp("sky-pattern")
    pools = {lasting: _gp_without_time_pool(_sky_pattern_heliostat(root / str(lasting), lasting))
             for lasting in (True, False)}
    yield pools
    shutil.rmtree(root, ignore_errors=True)


@pytest.mark.slow
def test_a_gp_without_time_worse_forward_falls_back_to_the_coarse_model(sky_pattern_pools):
    pool = sky_pattern_pools[False]
    # on the kNN split, whose rows mix the months, the GP wins: the rule alone would choose it
    assert pool._pick(pool.candidates)[0].model == "gp"
    sel = pool.choose().selection
    assert sel["model"] == "coarse"
    assert sel["forward_check"] == "failed (gp): fell back to the static choice"
    # forward in time the pattern is gone: the coarse model refitted on the first 100 rows errs
    # by the noise there (0.1 mrad per axis: a mean of 0.1 sqrt(pi / 2) = 0.125 mrad), while the
    # GP refitted on them carries the pattern it learnt into the later rows
    assert sel["coarse_time_val_error_mrad"] == pytest.approx(0.125, abs=0.04)
    assert sel["time_val_error_mrad"] > 2 * sel["coarse_time_val_error_mrad"]


class _StandInModel:
    """The parts of a pre-trained network the selection writes (its state is not used here)."""

    def to_dict(self):
        return {}

    def to_state(self):
        return {}


@pytest.mark.slow
def test_a_network_stands_in_for_a_gp_refused_forward(sky_pattern_pools):
    """The rule's next choice replaces the refused GP, a network included: a stand-in whose
    validation errors are the GP's x 1.1 (so the rule prefers the GP first; the stand-in still
    beats the coarse model by the margin, a 21 % gain on the weighted validation rows). The
    network's forward check is still to come, so it carries the static choice (the coarse model:
    the GP is refused) and the name of the GP it stands in for."""
    pool = sky_pattern_pools[False]
    gp = pool.candidates[0]
    fit = gp.info["fit"]
    pool.candidates.append(type(gp)(
        "pretrained-nn", 1.1 * gp.val_errors, (3, 0, 0, 0),
        {"kind": "pretrained", "weight_decay": math.nan, "seed": 0,
         "errors": 1.1 * fit.errors, "model": _StandInModel(), "info": {}, "normal": fit.normal,
         "position": fit.position, "pretrain_config": _StandInModel(), "date_inputs": False}))
    try:
        assert pool._pick(pool.candidates)[0].model == "gp"
        choice = pool.choose()
    finally:
        pool.candidates.pop()
    assert choice.selection["model"] == "pretrained-nn" and choice.refused == "gp"
    assert choice.selection["forward_check"] == "failed (gp): pretrained-nn stands in"
    assert choice.fallback.selection["model"] == "coarse"
    # the figures are the refused GP's until the network's own check replaces them
    assert choice.selection["time_val_error_mrad"] > 2 * choice.selection[
        "coarse_time_val_error_mrad"]


@pytest.mark.slow
def test_a_gp_without_time_no_worse_forward_is_kept(sky_pattern_pools):
    # the pattern lasts: the GP refitted on the first 100 rows still corrects the later ones,
    # down to near the noise (0.125 mrad), where the coarse model misses the pattern
    sel = sky_pattern_pools[True].choose().selection
    assert sel["model"] == "gp" and sel["forward_check"] == "passed"
    assert sel["time_val_error_mrad"] == pytest.approx(0.125, abs=0.04)
    assert sel["coarse_time_val_error_mrad"] > 2 * sel["time_val_error_mrad"]


def test_a_regime_aware_model_s_gp_is_refitted_forward_on_its_latest_regime_s_rows():
    """fit-coarse's time-split parameters of a regime-aware model are its latest regime's, so the
    GP's forward refit trains on that regime's training rows only. One row a day for 30 days:
    24 training, 3 validation, 3 test rows; the latest regime starts on day 10 (an episode on
    day 24 is not a regime): training rows 0-9 are left out, the other 20 rows kept. With fewer
    than MIN_REGIME_ROWS (10) training rows in the latest regime (from day 16: 8), or a static
    model, nothing is left out."""
    from heliocal.pipeline.models.regime_fit import MIN_REGIME_ROWS
    from heliocal.pipeline.stages.selection import latest_regime_labels

    assert MIN_REGIME_ROWS == 10
    times = pd.Series(pd.date_range("2024-01-01", periods=30, freq="D", tz="UTC"))
    labels = np.array(["train"] * 24 + ["validation"] * 3 + ["test"] * 3, dtype=object)

    def regimes(latest):
        return pd.DataFrame({"kind": ["regime", "regime", "episode"], "regime": [0, 1, 1],
                             "start": pd.to_datetime(["2024-01-01", latest, "2024-01-25"],
                                                     utc=True)})

    aware = {"regime_table": pd.DataFrame({"model": ["static-20+drift"]})}
    out = latest_regime_labels({**aware, "regimes": regimes("2024-01-11")}, times, labels)
    assert list(out[:10]) == ["unused"] * 10 and list(out[10:]) == list(labels[10:])
    few = latest_regime_labels({**aware, "regimes": regimes("2024-01-17")}, times, labels)
    assert list(few) == list(labels)
    static = {"regime_table": None, "regimes": regimes("2024-01-11")}
    assert list(latest_regime_labels(static, times, labels)) == list(labels)
