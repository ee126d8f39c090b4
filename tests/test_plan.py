"""Tests of ``heliocal plan``: the design criterion (models.design), the slots and the greedy
schedule (models.schedule), the inputs a plan rests on (stages.plan_inputs) and the stage and CLI
(stages.plan, cli.plan).

Expected values and their sources:

* the gain of a row against the trace difference ``trace((C - C') M)`` with ``C'`` the direct
  inverse ``(C^-1 + J^T J / s^2)^-1`` (numpy), and against covariance_after;
* the greedy picks on a one-parameter toy computed by hand: a row ``a`` of a heliostat with
  variance ``c``, year information ``m`` and noise ``s`` gains ``c^2 a^2 m / (s^2 + c a^2)``
  and leaves ``c' = c s^2 / (s^2 + c a^2)`` (the scalar Woodbury identity);
* the solar day starts at UTC midnight minus longitude / 15 h (mean solar time);
* the sun's noon elevation at Jülich (50.9 deg N) on 21 December is 90 - 50.913 - 23.44 =
  15.6 deg, so no slot there has the sun above 20 deg;
* the logs' spacing from a log written out here: gaps of 100, 200, 300 s between two heliostats.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.cli.main import app
from heliocal.pipeline.models.design import (DesignInput, HeliostatDesign, gains_mrad2,
                                             heliostat_designs, year_information,
                                             year_variance_mrad2)
from heliocal.pipeline.models.schedule import (GridCandidates, Limits, RowCandidates,
                                               greedy_schedule, slot_grid, solar_day_start,
                                               year_sun_grid)
from heliocal.pipeline.models.simulator import JUELICH_REFERENCE
from heliocal.pipeline.models.uncertainty import (ParameterCovariance, aim_variance_mrad2,
                                                  covariance_after)

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data" / "juelich" / "paint"


# ------------------------------------------------------------------------------------------------
# the criterion
# ------------------------------------------------------------------------------------------------
def _spd(rng, p: int) -> np.ndarray:
    a = rng.normal(size=(p, p))
    return a @ a.T + 0.1 * np.eye(p)


def test_gain_is_the_trace_difference():
    rng = np.random.default_rng(0)
    c, m = _spd(rng, 5), _spd(rng, 5)
    cov = ParameterCovariance(np.arange(5), c, 0.3, 10)
    rows = rng.normal(size=(4, 3, 5))
    gains = gains_mrad2(cov, m, rows)
    for k in range(4):
        direct = np.linalg.inv(np.linalg.inv(c) + rows[k].T @ rows[k] / 0.3 ** 2)
        assert gains[k] == pytest.approx(np.trace((c - direct) @ m), rel=1e-9)
        after = covariance_after(cov, rows[k:k + 1])
        assert gains[k] == pytest.approx(year_variance_mrad2(cov, m)
                                         - year_variance_mrad2(after, m), rel=1e-9)
    # a row out of reach has no gain
    rows[2, 0, 0] = np.nan
    assert np.isnan(gains_mrad2(cov, m, rows)[2])


def test_year_variance_is_the_mean_aim_variance():
    rng = np.random.default_rng(1)
    cov = ParameterCovariance(np.arange(4), _spd(rng, 4), 0.2, 10)
    grid = rng.normal(size=(50, 3, 4))
    grid[7] = np.nan                                 # an aim out of reach is left out
    m = year_information(grid)
    ok = np.isfinite(grid).all(axis=(1, 2))
    assert year_variance_mrad2(cov, m) == pytest.approx(
        aim_variance_mrad2(grid[ok], cov).mean(), rel=1e-12)


# ------------------------------------------------------------------------------------------------
# the greedy schedule on a toy computed by hand
# ------------------------------------------------------------------------------------------------
def _toy(c: float, m: float, s: float) -> HeliostatDesign:
    return HeliostatDesign("H", ParameterCovariance(np.array([0]), np.array([[c]]), s, 0),
                           np.array([[m]]))


def _rows(*a: float) -> np.ndarray:
    out = np.zeros((len(a), 3, 1))
    out[:, 0, 0] = a
    return out


def test_greedy_picks_match_the_hand_computation():
    # A: c=4, m=1, s=1, rows a=1, a=2 -> gains 16/5 = 3.2 and 64/17 = 3.765
    # B: c=1, m=2, s=1, row a=3        -> gain 18/10 = 1.8
    designs = [_toy(4.0, 1.0, 1.0), _toy(1.0, 2.0, 1.0)]
    jac = [_rows(1.0, 2.0), _rows(3.0)]
    cands = RowCandidates(designs, jac, [np.zeros(2, int), np.zeros(1, int)])
    picks, covs = greedy_schedule(designs, cands, Limits(budget=3, days=1))
    # 1st: A's a=2 (64/17). A is left with c = 4/17: its a=1 row gains (4/17)^2 / (21/17) =
    # 16/357 = 0.0448, so 2nd: B's a=3 (1.8). 3rd: A's a=1, the only row left.
    assert [(p.heliostat, p.slot) for p in picks] == [(0, 1), (1, 0), (0, 0)]
    assert [p.gain_mrad2 for p in picks] == pytest.approx([64 / 17, 1.8, 16 / 357], rel=1e-12)
    # A after both rows: 1/c = 1/4 + 4 + 1 -> c = 4/21; B: 1/c = 1 + 9 -> c = 0.1
    assert covs[0].covariance[0, 0] == pytest.approx(4 / 21, rel=1e-12)
    assert covs[1].covariance[0, 0] == pytest.approx(0.1, rel=1e-12)


def test_greedy_respects_per_day_and_per_heliostat_limits():
    designs = [_toy(4.0, 1.0, 1.0), _toy(1.0, 2.0, 1.0)]
    jac = [_rows(1.0, 2.0, 2.0), _rows(3.0, 3.0)]
    days = [np.array([0, 0, 1]), np.array([0, 1])]
    # one row per day, at most one per heliostat: A's best on day 0, then B's on day 1
    picks, _ = greedy_schedule(designs, RowCandidates(designs, jac, days),
                               Limits(budget=5, days=2, per_day=1, max_per_heliostat=1))
    assert [(p.heliostat, p.slot, p.day) for p in picks] == [(0, 1, 0), (1, 1, 1)]


# ------------------------------------------------------------------------------------------------
# slots
# ------------------------------------------------------------------------------------------------
def test_solar_day_and_slots_at_juelich():
    lon = JUELICH_REFERENCE[1]
    assert solar_day_start("2024-06-21", lon) == (pd.Timestamp("2024-06-21", tz="UTC")
                                                 - pd.Timedelta(hours=lon / 15.0))
    grid = slot_grid(JUELICH_REFERENCE, "2024-06-21", 2, 180, 10, 10.0)
    t = pd.DatetimeIndex(grid.time)
    assert (grid.elevation_deg > 10.0).all() and set(grid.day) == {0, 1}
    assert ((t - t.normalize()).total_seconds() % 180 == 0).all()       # whole multiples
    steps = np.diff((t - t[0]).total_seconds())
    assert set(steps[steps < 3600]) == {180.0}                           # one run per day
    # nodes every 10th slot of a run plus its last slot; interpolation weights in [0, 1]
    assert grid.weight.min() >= 0.0 and grid.weight.max() < 1.0
    assert np.array_equal(grid.nodes[:3], [0, 10, 20])
    # 21 December: noon elevation 15.6 deg
    assert len(slot_grid(JUELICH_REFERENCE, "2024-12-21", 1, 180, 10, 20.0)) == 0
    assert len(slot_grid(JUELICH_REFERENCE, "2024-12-21", 1, 180, 10, 10.0)) > 0


def _one_heliostat():
    """A simulated static-6 heliostat with 8 rows as its fit's design input (true parameters as
    the fit), a day's slots at Jülich and its design on them."""
    from heliocal.pipeline.models.coarse import MeasurementBatch
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.physics.parameters import preset_mask

    f = simulate_field(1, seed=2, measurements=(8, 8), dynamic_fraction=0.0, deviations="static-6")
    h = next(iter(f.heliostats.values()))
    rows = MeasurementBatch.from_frame(f.measurements)
    free = preset_mask("static-6", h.actuator_type, h.kinematic_type).numpy()
    point = f.targets["tower_target_lower"]["center_enu"]
    item = DesignInput("H", h.spec, h.true, free, np.full(28, 0.1), rows, rows, point,
                       point[None])
    grid = slot_grid(JUELICH_REFERENCE, "2024-03-01", 1, 180, 10, 10.0)
    year = year_sun_grid(JUELICH_REFERENCE, "2024-03-01", 30, 60, 10.0)
    return item, grid, heliostat_designs([item], year, grid.sun[grid.nodes])[0]


def test_one_heliostat_on_a_target_at_a_time():
    _, grid, design = _one_heliostat()
    designs = [design] * 4                     # four identical heliostats want the same slots
    cands = GridCandidates(grid, designs, [["tower_target_lower"]] * 4)
    picks, _ = greedy_schedule(designs, cands, Limits(budget=12, days=1))
    assert len(picks) == 12
    slots = [p.slot for p in picks]
    assert len(set(slots)) == 12                                        # one target: no slot twice
    t = pd.DatetimeIndex(grid.time[slots])
    times = np.sort((t - t.min()).total_seconds())
    assert np.diff(times).min() >= 180.0
    # identical heliostats: the first four picks are the four best slots, one per heliostat
    assert sorted(p.heliostat for p in picks[:4]) == [0, 1, 2, 3]


def test_interpolated_gains_are_close_to_exact():
    """Node Jacobians every 30 minutes: the gain at every slot within 1 % of the largest gain
    of exact Jacobians (docs/plan.md quotes the measured difference)."""
    from heliocal.pipeline.models.design import aim_rows

    item, grid, d = _one_heliostat()
    interpolated = gains_mrad2(d.covariance, d.information,
                               grid.interpolate(d.node_jacobian[0], np.arange(len(grid))))
    _, exact_j = aim_rows([item], grid.sun, np.broadcast_to(item.year_aim, grid.sun.shape)[None])
    exact = gains_mrad2(d.covariance, d.information, exact_j[0])
    # a slot next to a node out of reach is no candidate; none out of reach is one
    both = np.isfinite(interpolated)
    assert both.sum() > 0.8 * len(grid) and np.isfinite(exact[both]).all()
    assert np.max(np.abs(interpolated[both] - exact[both])) < 0.01 * np.nanmax(exact)


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
def test_log_spacing_from_the_gaps_between_heliostats():
    from heliocal.pipeline.stages.plan_inputs import DEFAULT_SPACING_S, log_spacing_s

    t0 = pd.Timestamp("2024-05-01T08:00Z")
    rows = []
    for k in range(30):        # per session: A, B after 100 s, A after 200 s more, B after 300 s
        base = t0 + pd.Timedelta(hours=2 * k)
        for off, hid in ((0, "A"), (100, "B"), (300, "A"), (600, "B")):
            rows.append({"timestamp": base + pd.Timedelta(seconds=off), "heliostat_id": hid,
                         "target_name": "T"})
    spacing, source = log_spacing_s(pd.DataFrame(rows))
    assert spacing == 180 and "200 s" in source        # median 200 s, to the nearest minute
    few = pd.DataFrame(rows[:8])
    assert log_spacing_s(few)[0] == DEFAULT_SPACING_S
    # heliostats measured now and then (gaps of 800, 1600, 2400 s): no session's pace
    sparse = pd.DataFrame(rows).assign(timestamp=lambda d: t0 + (d["timestamp"] - t0) * 8)
    spacing, source = log_spacing_s(sparse)
    assert spacing == DEFAULT_SPACING_S and "1600 s" in source


def _regimes(step_mrad: float) -> pd.DataFrame:
    return pd.DataFrame({
        "heliostat_id": "H", "kind": ["regime", "regime"], "regime": [0, 1],
        "start": pd.to_datetime(["2024-01-01", "2024-02-01"], utc=True),
        "end": pd.to_datetime(["2024-01-31", "2024-03-01"], utc=True),
        "cause": ["start", "detected"], "step_mrad": [np.nan, step_mrad]})


@pytest.mark.parametrize("step, regime_aware, expected", [
    (2.0, False, [False, False, True, True]),     # a real step: only the young regime's rows
    (0.2, False, [True, True, True, True]),       # a tenth of a mrad on few rows: noise
    (0.2, True, [False, False, True, True]),      # fit-coarse modelled the regimes
])
def test_young_regime_rows(step, regime_aware, expected):
    from heliocal.pipeline.stages.plan_inputs import (YOUNG_REGIME_MIN_STEP_MRAD,
                                                      current_regime_rows, regime_breaks)

    assert YOUNG_REGIME_MIN_STEP_MRAD == 1.0
    times = pd.to_datetime(["2024-01-05", "2024-01-20", "2024-02-02", "2024-02-20"], utc=True)
    starts, spans = regime_breaks(_regimes(step), {"H"} if regime_aware else set())
    current, episode = current_regime_rows(times, starts.get("H"), spans.get("H", []))
    assert current.tolist() == expected and not episode.any()


# ------------------------------------------------------------------------------------------------
# the stage and the CLI
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ingested(tmp_path_factory) -> Path:
    from heliocal.pipeline.stages.ingest import run_ingest

    wd = tmp_path_factory.mktemp("plan") / "work"
    run_ingest([SAMPLE], wd)
    return wd


@pytest.mark.parametrize("args, message", [
    (["--start", "2024-12-21", "--days", "2", "--min-elevation", "20"],
     "Error: no daylight in the plan: the sun stays below 20 deg at the site (50.915, 6.388) "
     "for 2 days from 2024-12-21; choose other dates or a lower --min-elevation"),
    (["--start", "2024-06-01", "--heliostat", "XX99"],
     "Error: heliostat 'XX99' is not in {wd}/heliostats.parquet (3 heliostats; `heliocal info "
     "{wd}` lists them)"),
    (["--start", "2024-06-01"],
     "Error: {wd} has no coarse fit (coarse_params.parquet): run `heliocal fit-coarse "
     "--workdir {wd}` first"),
    (["--start", "2024-06-31"],
     "Error: The 'start' parameter of plan must be a date like 2024-06-01. Got '2024-06-31' "
     "instead."),
])
def test_bad_input_gives_one_error_line(runner, ingested, args, message):
    result = runner.invoke(app, ["plan", "--workdir", str(ingested), *args])
    assert result.exit_code == 1
    assert result.stderr == message.format(wd=ingested) + "\n"
    assert not (ingested / "plan.parquet").exists()


@pytest.mark.slow
def test_plan_end_to_end(runner, ingested, tmp_path):
    from heliocal.pipeline.artifacts.schemas import PLAN
    from heliocal.pipeline.artifacts.store import read_artifact

    wd = tmp_path / "work"
    shutil.copytree(ingested, wd)
    for argv in (["split-knn", "--workdir", str(wd)],
                 ["fit-coarse", "--workdir", str(wd), "--preset", "static-6", "--workers", "1",
                  "--rolling-origins", "0"]):   # plan reads no rolling-origin rows
        assert runner.invoke(app, argv).exit_code == 0
    result = runner.invoke(app, ["plan", "--workdir", str(wd), "--start", "2024-06-01",
                                 "--days", "2", "--per-day", "5", "--spacing", "5", "--json",
                                 "--workers", "1"])
    assert result.exit_code == 0, result.stderr
    summary = json.loads(result.stdout)
    plan = read_artifact(wd, PLAN)
    assert len(plan) == summary["planned_rows"] == 10 and summary["spacing_s"] == 300
    assert plan["rank"].tolist() == list(range(1, 11))
    assert plan.groupby("day").size().tolist() == [5, 5]
    for _, g in plan.groupby("target"):                   # one heliostat on a target at a time
        t = np.sort((g["time_utc"] - g["time_utc"].min()).dt.total_seconds().to_numpy())
        assert (np.diff(t) >= 300).all()
    assert (plan["sun_elevation_deg"] > 10).all() and (plan["expected_gain_mrad2"] > 0).all()
    # per heliostat the errors chain: each row starts where the one before it ended
    for _, g in plan.sort_values("rank").groupby("heliostat_id"):
        np.testing.assert_allclose(g["expected_error_before_mrad"].to_numpy()[1:],
                                   g["expected_error_after_mrad"].to_numpy()[:-1], rtol=1e-9)
        gain = g["expected_error_before_mrad"] ** 2 - g["expected_error_after_mrad"] ** 2
        np.testing.assert_allclose(gain, g["expected_gain_mrad2"], rtol=1e-9)
    assert summary["expected_error_after_plan_mrad"] < summary["expected_error_now_mrad"]
    csv = pd.read_csv(wd / "plan.csv")
    assert len(csv) == 10 and csv["time_utc"].is_monotonic_increasing
    assert set(csv["heliostat_id"]) <= {"BE36", "BF41", "BH35"}
    # the report shows it
    assert runner.invoke(app, ["report", "--workdir", str(wd), "--workers", "1"]).exit_code == 0
    page = (wd / "report" / "plan.html").read_text()
    assert "Measurement plan" in page and f"{len(plan)} measurements" in page
    assert "plan.html" in (wd / "report" / "index.html").read_text()
    # retrospective: rows already measured, none of them a test row
    result = runner.invoke(app, ["plan", "--workdir", str(wd), "--start", "2022-06-01",
                                 "--days", "62", "--from-existing", "--budget", "12",
                                 "--max-per-heliostat", "4", "--json", "--workers", "1"])
    assert result.exit_code == 0, result.stderr
    chosen = read_artifact(wd, PLAN)
    split = pd.read_parquet(wd / "split.parquet")
    labels = dict(zip(split["heliostat_id"] + "/" + split["measurement_id"], split["split"]))
    assert chosen["measurement_id"].notna().all() and len(chosen) <= 12
    assert chosen.groupby("heliostat_id").size().max() <= 4
    assert {labels[f"{h}/{m}"] for h, m in zip(chosen["heliostat_id"], chosen["measurement_id"])
            } <= {"train", "validation"}
    # the fourth bad input: --from-existing over days without rows (the sample's logs end on
    # 2024-06-07); one line, and the plan of the run before stays as it was
    result = runner.invoke(app, ["plan", "--workdir", str(wd), "--start", "2030-01-01",
                                 "--days", "62", "--from-existing", "--workers", "1"])
    assert result.exit_code == 1
    assert result.stderr == (f"Error: no measured rows outside the test set from 2030-01-01 for "
                             f"62 days in {wd} to choose from (--from-existing); choose dates "
                             f"of the logs\n")
    pd.testing.assert_frame_equal(read_artifact(wd, PLAN), chosen)


# ------------------------------------------------------------------------------------------------
# checking a plan against ground truth (models.plan_check)
# ------------------------------------------------------------------------------------------------
def test_simulated_rows_and_year_error_against_the_truth():
    """A noiseless row's spot is where the true chain sends the beam at the row's (rounded)
    steps, so the true geometry's error on it is zero (< 1e-9 mrad); the true geometry's
    year-round aim error is zero too (to the inverse kinematics' tolerance) and the nominal
    one's is the size of the simulated deviations (10.6 mrad here; > 0.5 asserted)."""
    from heliocal.pipeline.models.coarse import MeasurementBatch, normal_errors_mrad
    from heliocal.pipeline.models.plan_check import simulated_rows, year_error_mrad
    from heliocal.pipeline.models.simulator import simulate_field

    f = simulate_field(1, seed=4, measurements=(5, 5), dynamic_fraction=0.0, noise_mrad=0.0)
    h = next(iter(f.heliostats.values()))
    times = pd.date_range("2024-05-02T06:00Z", periods=6, freq="2h")
    rows = simulated_rows(f, h, times, ["tower_target_lower", "tower_target_upper"] * 3,
                          np.random.default_rng(0))
    assert len(rows) == 6 and set(rows.columns) >= set(f.measurements.columns)
    with torch.no_grad():
        err = normal_errors_mrad(h.true, h.spec, MeasurementBatch.from_frame(rows)).numpy()
    assert err.max() < 1e-9
    sun = year_sun_grid(f.reference, "2024-01-01", 30, 60, 10.0)
    aim = f.targets["tower_target_lower"]["center_enu"]
    assert year_error_mrad(h.true, h, sun, aim)[0] < 1e-6
    assert year_error_mrad(h.nominal, h, sun, aim)[0] > 0.5


def test_noise_from_heliostats_with_degrees_of_freedom():
    """A heliostat's own noise scale needs 2 N - P >= 10; the others take the field's median;
    when none has 10, those with at least one; when none has one, every heliostat with rows."""
    from types import SimpleNamespace

    from heliocal.pipeline.stages.plan import MIN_NOISE_DOF, _noise_groups

    assert MIN_NOISE_DOF == 10
    field = lambda *dof: [SimpleNamespace(noise_dof=d) for d in dof]  # noqa: E731
    assert _noise_groups(field(14, 0, None, 10)) == ([0, 3], [1, 2])
    assert _noise_groups(field(4, 0, None)) == ([0], [1, 2])
    assert _noise_groups(field(0, -2, None)) == ([0, 1], [2])
    assert _noise_groups(field(None)) == ([], [0])
