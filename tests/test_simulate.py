"""Tests of pipeline/simulate.py and `heliocal simulate`.

Expected values and their sources are stated next to each check: most are the simulator's own
definitions (docstring of pipeline/simulate.py), read back through the files and ``ingest``;
the committed sample is checked against a regeneration with the command in sample_data/README.md.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import heliocal.cli.ingest  # noqa: F401  (registers ingest on the app)
import heliocal.cli.simulate  # noqa: F401  (registers simulate on the app)
from heliocal.cli.app import app
from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.report.golden import compare_trees
from heliocal.pipeline.io.staged import IngestOptions
from heliocal.pipeline.stages.ingest import ingest
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX, preset_parameters
from heliocal.pipeline.models.disturbances import DEVIATION_SIZES
from heliocal.pipeline.models.simulator import SimulatedField, simulate_field
from heliocal.pipeline.stages.simulate import write_field
from heliocal.pipeline.physics.sun import spa_sun_position

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_data" / "synthetic"
#: The command that generated sample_data/synthetic (sample_data/README.md).
SAMPLE_ARGS = ["simulate", "--out", "{out}", "--heliostats", "4", "--measurements", "140,160",
               "--seed", "7", "--noise-mrad", "0.2", "--dynamic-fraction", "0.5",
               "--types", "juelich"]

SPOT = ["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"]


@pytest.fixture(scope="module")
def mixed(tmp_path_factory) -> tuple[SimulatedField, Path]:
    """4 heliostats: juelich static, az-el static, juelich dynamic, az-el dynamic (round-robin
    types, the last half dynamic), 40-60 measurements each, 0.2 mrad noise; written out."""
    field = simulate_field(4, seed=5, measurements=(40, 60), kinematic_types=("juelich", "az-el"),
                           dynamic_fraction=0.5, noise_mrad=0.2)
    out = tmp_path_factory.mktemp("mixed") / "sim"
    write_field(field, out)
    return field, out


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------------------------
# the field
# --------------------------------------------------------------------------------------------
def test_types_and_dynamics_are_assigned_as_documented(mixed):
    field, _ = mixed
    got = [(h.kinematic_type, h.actuator_type, h.dynamic) for h in field.heliostats.values()]
    assert got == [("juelich", "linear", False), ("az-el", "ideal", False),
                   ("juelich", "linear", True), ("az-el", "ideal", True)]
    counts = field.measurements.groupby("heliostat_id").size()
    assert counts.between(40, 60).all()
    # ids are unique and increase with time over the whole field, like PAINT's
    ids = field.measurements["measurement_id"].astype(int)
    assert ids.is_unique and ids.is_monotonic_increasing
    assert field.measurements["timestamp"].is_monotonic_increasing


def test_layout_is_north_of_the_tower(mixed):
    field, _ = mixed
    for h in field.heliostats.values():
        e, n, u = (h.row[f"heliostat_{a}_m"] for a in "enu")
        # rows at 30 m to 182 m within +-55 deg of north (_layout); pedestals 1.5 to 2.6 m high
        assert 30.0 - 1e-6 <= math.hypot(e, n) <= 182.0 + 1e-6
        assert n > 0 and abs(math.degrees(math.atan2(e, n))) <= 55.0 + 1e-9
        assert 1.5 < u < 2.6


def test_calibration_times_are_daylight_days_spread_over_the_year(mixed):
    field, _ = mixed
    m = field.measurements
    # sun elevation > 10 deg (SPA, pvlib) at every time, recomputed here
    _, el = spa_sun_position(m["timestamp"], *field.reference)
    assert (el > 10.0).all()
    np.testing.assert_array_equal(el, m["sun_elevation_deg"].to_numpy())
    assert (m["timestamp"] >= pd.Timestamp("2023-01-01", tz="UTC")).all()
    assert (m["timestamp"] < pd.Timestamp("2024-01-01", tz="UTC")).all()
    for _, g in m.groupby("heliostat_id"):
        per_day = g.groupby(g["timestamp"].dt.date).size()
        assert per_day.max() <= 8  # 2 to 8 per calibration day (_schedule)
        assert len(per_day) >= len(g) / 8
        span = g["timestamp"].max() - g["timestamp"].min()
        assert span > pd.Timedelta(days=180)  # random days over the whole year


def test_true_geometry_is_nominal_plus_preset_deviations(mixed):
    field, _ = mixed
    for h in field.heliostats.values():
        assert h.deviated == preset_parameters("static-20", h.actuator_type, h.kinematic_type)
        dev = (h.true - h.nominal).numpy()
        changed = {n for n in h.deviated}
        for name, i in PARAMETER_INDEX.items():
            if name not in changed:
                assert dev[i] == 0.0
                continue
            kind = ("increment" if name.endswith("_increment") else "initial_angle"
                    if name.endswith("_initial_angle_rad") else "tilt" if "_tilt_" in name
                    else "translation" if "_translation_" in name else "length")
            size = abs(dev[i] / float(h.nominal[i])) if kind == "increment" else abs(dev[i])
            low, high = DEVIATION_SIZES[kind]
            assert low * (1 - 1e-9) <= size <= high * (1 + 1e-9), name


def test_spots_follow_the_true_model_and_the_stated_noise():
    field = simulate_field(1, seed=2, measurements=(800, 800), dynamic_fraction=0.0, noise_mrad=0.5)
    m = field.measurements
    h = next(iter(field.heliostats.values()))
    # the true model's inverse kinematics aims at the target centre: the noiseless spot misses it
    # only by the rounding of the steps (1 step ~ 6.5 um of stroke ~ 20 urad ~ 4 mm at 200 m)
    miss = np.linalg.norm(m[[f"true_spot_{a}_m" for a in "enu"]].to_numpy()
                          - m[["target_e_m", "target_n_m", "target_u_m"]].to_numpy(), axis=1)
    assert miss.max() < 0.02
    assert (m[["axis_1_steps", "axis_2_steps"]] % 1 == 0).all().all()
    # noise: per target axis (east, up for these north-facing targets) std = distance * 0.5 mrad
    offset = (m[SPOT].to_numpy() - m[[f"true_spot_{a}_m" for a in "enu"]].to_numpy())
    angle_mrad = 1000 * offset / m["distance_m"].to_numpy()[:, None]
    assert np.abs(angle_mrad[:, 1]).max() < 1e-9  # no noise out of the target plane
    for axis in (0, 2):  # sample std of 800 normal draws: within 10 % (5 standard errors)
        assert angle_mrad[:, axis].std() == pytest.approx(0.5, rel=0.10)
    # noise floor ~ noise / 2 * sqrt(pi / 2) (Rayleigh mean of the normal's error)
    assert h.noise_floor_mrad == pytest.approx(0.25 * math.sqrt(math.pi / 2), rel=0.10)
    assert h.error_true_static_mrad == h.noise_floor_mrad  # static: nothing else


def test_noiseless_field_has_zero_noise_floor():
    field = simulate_field(2, seed=4, measurements=(20, 20), kinematic_types=("juelich", "az-el"),
                           dynamic_fraction=0.5, noise_mrad=0.0)
    for h in field.heliostats.values():
        assert h.noise_floor_mrad < 1e-9
    np.testing.assert_array_equal(field.measurements[SPOT].to_numpy(),
                                  field.measurements[[f"true_spot_{a}_m" for a in "enu"]].to_numpy())


def test_dynamic_disturbances_follow_their_laws(mixed):
    field, _ = mixed
    m = field.measurements
    for h in field.heliostats.values():
        rows = m[m["heliostat_id"] == h.heliostat_id]
        params = h.params.numpy()
        if not h.dynamic:
            assert (rows[["seasonal_tilt_rad", "actuator_drift_m", "actuator_drift_rad",
                          "gear_error_rad", "temperature_tilt_rad"]] == 0).all().all()
            assert (params == h.true.numpy()).all()
            continue
        d = h.disturbances
        assert set(d) == {"seasonal_tilt", "actuator_drift", "gear_error", "temperature_tilt"}
        doy = rows["timestamp"].dt.day_of_year.to_numpy(float)
        season = d["seasonal_tilt"]["amplitude"] * np.cos(
            2 * np.pi * (doy - d["seasonal_tilt"]["peak_day_of_year"]) / 365.25)
        years = (rows["timestamp"] - pd.Timestamp("2023-01-01", tz="UTC")).dt.total_seconds() / (
            365.25 * 86400)
        drift = d["actuator_drift"]["rate"] * years.to_numpy()
        gear = d["gear_error"]["amplitude"] * np.sin(
            2 * np.pi * rows["axis_2_steps"].to_numpy() / d["gear_error"]["period_steps"]
            + d["gear_error"]["phase_rad"])
        thermal = d["temperature_tilt"]["coefficient"] * (rows["temperature_c"].to_numpy() - 15.0)
        true = h.true.numpy()
        for kind, expected in (("seasonal_tilt", season), ("actuator_drift", drift),
                               ("gear_error", gear), ("temperature_tilt", thermal)):
            i = PARAMETER_INDEX[d[kind]["parameter"]]
            np.testing.assert_allclose(params[:, i] - true[i], expected, rtol=0, atol=1e-15)
        # Stone's alpha and delta of each type carry the tilts (kinematics.STONE_MAPPING)
        alpha, delta = (("joint_1_tilt_n_rad", "concentrator_tilt_e_rad") if h.kinematic_type == "juelich"
                        else ("joint_1_tilt_e_rad", "concentrator_tilt_u_rad"))
        assert d["seasonal_tilt"]["parameter"] == alpha
        assert d["temperature_tilt"]["parameter"] == delta
        # a static rigid body (the true geometry without disturbances) misses the floor
        assert h.error_true_static_mrad > 2 * h.noise_floor_mrad


# --------------------------------------------------------------------------------------------
# the files, through ingest
# --------------------------------------------------------------------------------------------
def _check_ingested(field, measurements, helio, info, ids):
    sim = field.measurements[field.measurements["heliostat_id"].isin(ids)]
    assert info["rows_read"] == len(sim) == info["kept"] and info["rejected"] == 0
    assert info["sun_mismatch_rows"] == 0
    j = measurements.merge(sim, on=["heliostat_id", "measurement_id"], suffixes=("", "_sim"))
    assert len(j) == len(sim)
    # geodesy round trip (ENU -> WGS84 written -> ENU read): below 1 mm (issue), ~1e-8 m in fact
    spot_diff = j[SPOT].to_numpy() - j[[c + "_sim" for c in SPOT]].to_numpy()
    assert np.abs(spot_diff).max() < 1e-3
    for c in ("axis_1_steps", "axis_2_steps", "sun_azimuth_deg", "sun_elevation_deg",
              "target_e_m", "target_n_m", "target_u_m"):
        np.testing.assert_allclose(j[c], j[c + "_sim"], rtol=0, atol=1e-9)
    assert (j["timestamp"] == j["timestamp_sim"]).all()
    for _, row in helio.iterrows():
        h = field.heliostats[row["heliostat_id"]]
        assert row["kinematic_type"] == h.kinematic_type
        assert row["n_measurements"] == (sim["heliostat_id"] == h.heliostat_id).sum()
        for a in "enu":
            assert row[f"heliostat_{a}_m"] == pytest.approx(h.row[f"heliostat_{a}_m"], abs=1e-9)
    return j


def test_paint_folder_ingests_completely(mixed):
    field, out = mixed
    ids = [h for h, v in field.heliostats.items() if v.kinematic_type == "juelich"]
    measurements, helio, _, info = ingest([out / "paint"])
    _check_ingested(field, measurements, helio, info, ids)
    assert info["sources"] == {str(out / "paint"): "paint"}


def test_wgs84_log_ingests_completely_with_temperature(mixed):
    field, out = mixed
    ids = [h for h, v in field.heliostats.items() if v.kinematic_type == "juelich"]
    measurements, helio, _, info = ingest([out / "calibration_log.csv"],
                                          IngestOptions(properties=out / "paint"))
    j = _check_ingested(field, measurements, helio, info, ids)
    assert info["env_columns"] == ["env_temperature"]
    np.testing.assert_array_equal(j["env_temperature"], j["temperature_c"])


def test_enu_log_ingests_completely_with_temperature(mixed):
    field, out = mixed
    ids = [h for h, v in field.heliostats.items() if v.kinematic_type == "az-el"]
    measurements, helio, _, info = ingest([out / "enu_log.csv"],
                                          IngestOptions(properties=out / "enu_properties.toml"))
    j = _check_ingested(field, measurements, helio, info, ids)
    np.testing.assert_array_equal(j["env_temperature"], j["temperature_c"])


def test_simulate_folder_ingests_as_it_is(mixed, tmp_path):
    """`heliocal ingest DIR` of a simulate output: every simulated measurement once (the PAINT
    copy of the Jülich-type ones is not read twice), both kinematic types, env_temperature,
    and sun positions checked against SPA at the ground truth's reference point."""
    field, out = mixed
    measurements, helio, _, info = ingest([out])
    j = _check_ingested(field, measurements, helio, info, list(field.heliostats))
    assert info["rows_read"] == len(field.measurements) == len(measurements)
    assert info["sources"] == {str(out / "calibration_log.csv"): "wgs84-log",
                               str(out / "enu_log.csv"): "enu-log"}
    np.testing.assert_array_equal(j["env_temperature"], j["temperature_c"])
    assert sorted(helio["kinematic_type"]) == ["az-el", "az-el", "juelich", "juelich"]
    # az-el rows were compared with SPA (reference point from ground_truth.json): no mismatch
    azel = measurements["heliostat_id"].isin(helio.loc[helio["kinematic_type"] == "az-el",
                                                       "heliostat_id"])
    assert measurements.loc[azel, "qa_sun_spa_diff_deg"].notna().all()
    assert measurements.loc[azel, "qa_sun_spa_diff_deg"].max() < 0.01
    # the command line, as documented; --properties is refused for such a folder
    runner = CliRunner()
    result = runner.invoke(app, ["ingest", str(out), "--workdir", str(tmp_path / "wd"), "--quiet"])
    assert result.exit_code == 0, result.stderr
    assert len(pd.read_parquet(tmp_path / "wd" / "measurements.parquet")) == len(field.measurements)
    result = runner.invoke(app, ["ingest", str(out), "--properties", str(out / "paint"),
                                 "--workdir", str(tmp_path / "wd2")])
    assert result.exit_code == 1 and result.stderr.splitlines() == [
        f"Error: {out}: a heliocal simulate folder brings its own heliostat properties (paint/, "
        "enu_properties.toml); drop --properties, or give its logs one by one"]


def test_paint_properties_hold_the_unshifted_initial_angle_and_no_facets(mixed):
    field, out = mixed
    truth = json.loads((out / "ground_truth.json").read_text())
    for hid, h in field.heliostats.items():
        if h.kinematic_type != "juelich":
            assert not (out / "paint" / hid).exists()
            continue
        props = json.loads((out / "paint" / hid / f"{hid}-heliostat-properties.json").read_text())
        assert "facet_properties" not in props
        written = props["kinematics_properties"]["actuators"][0]["initial_angle"]
        # PAINT stores axis 1 without ARTIST's -pi/2 shift (ingest adds it, docs/input_formats.md)
        assert truth["heliostats"][hid]["nominal"]["axis_1_initial_angle_rad"] == written - math.pi / 2


def test_ground_truth_file(mixed):
    field, out = mixed
    truth = json.loads((out / "ground_truth.json").read_text())
    assert truth["noise_mrad"] == 0.2
    assert truth["settings"]["seed"] == 5
    assert set(truth["heliostats"]) == set(field.heliostats)
    for hid, g in truth["heliostats"].items():
        h = field.heliostats[hid]
        assert g["dynamic"] == h.dynamic and g["kinematic_type"] == h.kinematic_type
        assert g["noise_floor_mrad"] == h.noise_floor_mrad
        assert g["written_as"] == ("paint" if h.kinematic_type == "juelich" else "enu-log")
        for name, value in g["true"].items():
            assert value == float(h.true[PARAMETER_INDEX[name]])
            assert value == pytest.approx(g["nominal"][name] + g["deviation"].get(name, 0.0),
                                          rel=1e-12, abs=1e-15)
        assert bool(g["disturbances"]) == h.dynamic
    per_measurement = pd.read_csv(out / "ground_truth_disturbances.csv", dtype={"measurement_id": str})
    assert len(per_measurement) == len(field.measurements)
    assert list(per_measurement.columns) == [
        "heliostat_id", "measurement_id", "timestamp", "temperature_c", "seasonal_tilt_rad",
        "actuator_drift_m", "actuator_drift_rad", "gear_error_rad", "temperature_tilt_rad"]


# --------------------------------------------------------------------------------------------
# determinism, CLI, sample data
# --------------------------------------------------------------------------------------------
def test_same_seed_gives_byte_identical_files(tmp_path):
    runner = CliRunner()
    args = ["simulate", "--heliostats", "2", "--measurements", "10,20", "--types", "juelich,az-el",
            "--seed", "3"]
    for name in ("a", "b"):
        result = runner.invoke(app, args + ["--out", str(tmp_path / name), "--json"])
        assert result.exit_code == 0, result.stderr
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert len(a) >= 15 and a == b  # 1 PAINT heliostat (10-20 files) + 6 other files
    result = runner.invoke(app, args[:-1] + ["4", "--out", str(tmp_path / "c")])
    assert result.exit_code == 0
    assert _files(tmp_path / "c")["ground_truth.json"] != a["ground_truth.json"]


def test_cli_json_summary(tmp_path):
    result = CliRunner().invoke(app, ["simulate", "--out", str(tmp_path / "x"), "--heliostats", "1",
                                      "--measurements", "12,12", "--dynamic-fraction", "0", "--json"])
    assert result.exit_code == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["measurements"] == 12 and summary["seed"] == 0 and summary["noise_mrad"] == 0.2
    assert summary["heliostats"][0]["dynamic"] is False
    assert summary["files"]["ground_truth"] == "ground_truth.json"


@pytest.mark.parametrize("args, message", [
    (["--heliostats", "0"], "Error: The 'n_heliostats' parameter of simulate_field must be an int "
                            "in [1, 500]. Got 0 instead."),
    (["--measurements", "a,b"], "Error: The 'measurements' parameter of simulate must be MIN,MAX "
                                "(two integers, e.g. 120,180). Got 'a,b' instead."),
    (["--measurements", "50,20"], "Error: The 'measurements' parameter of simulate_field must be "
                                  "(MIN, MAX) integers with 3 <= MIN <= MAX <= 5000. Got (50, 20) "
                                  "instead."),
    (["--noise-mrad", "-1"], "Error: The 'noise_mrad' parameter of simulate_field must be a float in "
                             "[0, 100]. Got -1.0 instead."),
    (["--dynamic-fraction", "1.5"], "Error: The 'dynamic_fraction' parameter of simulate_field must "
                                    "be a float in [0, 1]. Got 1.5 instead."),
    (["--types", "juelich,heliogon"], "Error: The 'kinematic_types' parameter of simulate_field must "
                                      "be one of {'juelich', 'az-el'}. Got 'heliogon' instead."),
    (["--deviations", "static-99"], "Error: The 'deviations' parameter of simulate_field must be one "
                                    "of {'none', 'static-6', 'static-14', 'static-20', 'static-28', "
                                    "'stone-8'}. Got 'static-99' instead."),
    (["--disturbances", "wind"], "Error: The 'disturbances' parameter of simulate_field must be one "
                                 "of {'seasonal_tilt', 'actuator_drift', 'gear_error', "
                                 "'temperature_tilt'}. Got 'wind' instead."),
    (["--start", "2023-06-01", "--end", "2023-06-01"],
     "Error: The 'end' parameter of simulate_field must be at least one day after 'start'. Got start "
     "'2023-06-01', end '2023-06-01' instead."),
])
def test_cli_bad_options_give_one_line_errors(tmp_path, args, message):
    result = CliRunner().invoke(app, ["simulate", "--out", str(tmp_path / "x"), *args])
    assert result.exit_code == 1
    assert result.stderr == message + "\n"
    assert not (tmp_path / "x").exists()


def test_cli_refuses_a_non_empty_folder_and_overwrites_only_its_own_files(tmp_path):
    runner = CliRunner()
    out = tmp_path / "x"
    base = ["simulate", "--out", str(out), "--measurements", "8,8", "--dynamic-fraction", "0"]
    assert runner.invoke(app, base + ["--heliostats", "3"]).exit_code == 0
    (out / "notes.txt").write_text("mine")
    before = sorted(p.name for p in (out / "paint").iterdir())
    result = runner.invoke(app, base + ["--heliostats", "1"])
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {out}: the folder is not empty; choose an empty or new folder, "
                             "or pass --overwrite to replace a previous simulation there\n")
    result = runner.invoke(app, base + ["--heliostats", "1", "--seed", "1", "--overwrite"])
    assert result.exit_code == 0, result.stderr
    after = sorted(p.name for p in (out / "paint").iterdir())
    assert len(before) == 4 and len(after) == 2  # 3 or 1 heliostat folders + timestamps.json
    assert (out / "notes.txt").read_text() == "mine"
    measurements, _, _, info = ingest([out / "paint"])
    assert info["kept"] == 8 and info["rejected"] == 0


def test_simulate_field_rejects_bad_arguments():
    with pytest.raises(ParameterError, match="'kinematic_types' parameter of simulate_field"):
        simulate_field(2, kinematic_types="juelich")
    with pytest.raises(ParameterError, match="'deviations' parameter"):
        simulate_field(2, deviations=["joint_1_tilt_x_rad"])


def test_help_text():
    result = CliRunner().invoke(app, ["simulate", "--help"])
    assert result.exit_code == 0
    for option in ("--out", "--heliostats", "--measurements", "--seed", "--noise-mrad",
                   "--dynamic-fraction", "--types", "--json"):
        assert option in result.stdout


def test_committed_sample_is_reproducible(tmp_path):
    """sample_data/synthetic is what the command in sample_data/README.md writes: the same files,
    keys, columns, dtypes, row order and strings, and numbers within relative 1e-9
    (heliocal.pipeline.report.golden says why); not the same bytes, which a library update may change."""
    out = tmp_path / "synthetic"
    result = CliRunner().invoke(app, [a.format(out=out) for a in SAMPLE_ARGS])
    assert result.exit_code == 0, result.stderr
    assert compare_trees(out, SAMPLE) == []
    readme = (REPO / "sample_data" / "README.md").read_text()
    assert "heliocal " + " ".join(SAMPLE_ARGS).format(out="sample_data/synthetic") in readme
    # small enough for the sample pipeline: < 3 MB, 4 heliostats, 2 static + 2 dynamic
    assert sum(len(b) for b in _files(SAMPLE).values()) < 3_000_000
    truth = json.loads((SAMPLE / "ground_truth.json").read_text())
    assert sorted(h["dynamic"] for h in truth["heliostats"].values()) == [False, False, True, True]


def test_calibration_files_reach_the_disk_with_one_sync_before_their_index(tmp_path, monkeypatch):
    """A PAINT folder holds one file per measurement: each is renamed into place whole (a killed
    run leaves none half-written), and all of them reach the disk with one ``sync`` before
    timestamps.json, the index that lists them, is written; only the few index and truth files
    are fsynced one by one. (An fsync per measurement file took 1.8 of 2.9 s to write this
    field; checked: writing the calibration files durably makes the count below fail.)"""
    import os
    from heliocal.pipeline.artifacts import paths

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(paths.os, "fsync", lambda fd: (events.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(paths.os, "sync", lambda: events.append("sync"))
    monkeypatch.setattr(paths.os, "replace",
                        lambda a, b: (events.append(Path(b).name), real_replace(a, b))[1])
    field_ = simulate_field(2, seed=1, measurements=(30, 30))
    write_field(field_, tmp_path / "f")
    calibration = [e for e in events if e.endswith("-calibration-properties.json")]
    assert len(calibration) == 60                      # 2 heliostats x 30 measurements
    assert events.count("sync") == 1
    sync_at = events.index("sync")
    last_calibration = max(i for i, e in enumerate(events) if e in calibration)
    assert last_calibration < sync_at < events.index("timestamps.json")
    # fsync only for the files written one by one: not one per measurement
    assert events.count("fsync") == len([e for e in events if e not in ("fsync", "sync")]) - 60
    assert events.count("fsync") < 12
