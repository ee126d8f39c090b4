"""``heliocal ingest`` on the real Jülich data and on the small fixtures in tests/data/good/."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from heliocal.cli.main import app

GOOD = Path(__file__).resolve().parent / "data" / "good"
BAD = Path(__file__).resolve().parent / "data" / "bad"
PLANT = "50.913421122592574,6.387824755874856,87.0"  # tower-measurements.json reference point


def _ingest(workdir: Path, *args: str) -> dict:
    result = CliRunner().invoke(app, ["ingest", *args, "--workdir", str(workdir), "--quiet"])
    assert result.exit_code == 0, result.stderr
    return {name: pd.read_parquet(workdir / f"{name}.parquet")
            for name in ("measurements", "heliostats", "rejected")}


# ------------------------------------------------------------------------------------------------
# real data (ingested once per module: ~2 s each)
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def paint(juelich_dir, tmp_path_factory):
    return _ingest(tmp_path_factory.mktemp("paint"), str(juelich_dir / "paint"))


@pytest.fixture(scope="module")
def juelich_log(juelich_dir, tmp_path_factory):
    return _ingest(tmp_path_factory.mktemp("log"), str(juelich_dir / "csv" / "juelich_calibration_log.csv"))


def test_paint_keeps_every_measurement(paint, juelich_dir):
    m, h, r = paint["measurements"], paint["heliostats"], paint["rejected"]
    # counts from the data README: BE36 177, BF41 170, BH35 149 calibration files
    assert m.groupby("heliostat_id").size().to_dict() == {"BE36": 177, "BF41": 170, "BH35": 149}
    assert len(r) == 0
    n_files = sum(1 for _ in (juelich_dir / "paint").glob("*/calibration/*.json"))
    assert len(m) == n_files == 496
    # BF41 230561's file has only a HeliOS spot: it falls back to helios, all others use UTIS
    assert m.groupby("focal_spot_source").size().to_dict() == {"helios": 1, "utis": 495}
    assert m.loc[m["focal_spot_source"] == "helios", "measurement_id"].tolist() == ["230561"]
    assert (m["sun_source"] == "log").all()
    # timestamps.json has 495 entries: BF41 228909 has none; kept with its logged sun, no SPA check
    no_time = m[m["timestamp"].isna()]
    assert no_time["measurement_id"].tolist() == ["228909"]
    assert no_time["qa_sun_spa_diff_deg"].isna().all()
    # PAINT's logged sun agrees with SPA: largest difference below the 0.1 deg tolerance
    assert m["qa_sun_spa_diff_deg"].max() < 0.1 and not m["qa_sun_mismatch"].any()
    assert h.set_index("heliostat_id")["n_measurements"].to_dict() == {"BE36": 177, "BF41": 170,
                                                                       "BH35": 149}


def test_paint_row_values(paint):
    m = paint["measurements"].set_index(["heliostat_id", "measurement_id"])
    row = m.loc[("BE36", "118671")]
    # paint/BE36/calibration/118671-calibration-properties.json and timestamps.json
    assert row["axis_1_steps"] == 45501 and row["axis_2_steps"] == 53811
    assert row["sun_azimuth_deg"] == pytest.approx(-48.91974860208279, abs=1e-12)
    assert row["sun_elevation_deg"] == pytest.approx(54.66615202629741, abs=1e-12)
    assert row["timestamp"] == pd.Timestamp("2022-06-12T13:27:37Z")
    assert row["target_name"] == "solar_tower_juelich_lower"
    # the lower target's centre is 35.88 m above the reference point and 3.24 m south of it
    # (tower-measurements.json; the same centre is in the CSV log's target_center columns)
    assert [row["target_e_m"], row["target_n_m"], row["target_u_m"]] == pytest.approx(
        [-0.0135, -3.2358, 35.8815], abs=1e-3)
    spot = np.array([row["focal_spot_e_m"], row["focal_spot_n_m"], row["focal_spot_u_m"]])
    target = np.array([row["target_e_m"], row["target_n_m"], row["target_u_m"]])
    # UTIS centroid vs target centre in the JSON files: dlon -3.672e-6 deg (x 70,200 m/deg at
    # 50.91 deg N = -0.258 m east), dlat ~0, dalt +0.107 m -> 0.279 m apart
    assert spot - target == pytest.approx([-0.258, 0.002, 0.107], abs=0.003)
    assert np.linalg.norm(spot - target) == pytest.approx(0.279, abs=0.003)


def test_paint_heliostat_properties(paint):
    h = paint["heliostats"].set_index("heliostat_id")
    assert set(h["kinematic_type"]) == {"juelich"} and set(h["actuator_type"]) == {"linear"}
    # every heliostat lies north of the tower (n > 0) within 300 m and near ground level
    assert (h["heliostat_n_m"] > 0).all() and (np.hypot(h["heliostat_e_m"], h["heliostat_n_m"]) < 300).all()
    assert (h["heliostat_u_m"].abs() < 10).all()
    # PAINT's renovation property (BE36, BF41, BH35: "2022-06-09"): midnight to midnight, UTC
    for hid in ("BE36", "BF41", "BH35"):
        assert h.loc[hid, "renovation_start"] == pd.Timestamp("2022-06-09", tz="UTC")
        assert h.loc[hid, "renovation_end"] == pd.Timestamp("2022-06-10", tz="UTC")


@pytest.mark.parametrize("text, first, last", [
    ("2020-10-26/2020-11-08", "2020-10-26", "2020-11-09"), ("2021-03-04", "2021-03-04", "2021-03-05"),
    (None, None, None), ("", None, None)])
def test_renovation_window(text, first, last):
    from heliocal.pipeline.io.paint import renovation_window

    w = renovation_window(text)
    for key, day in (("renovation_start", first), ("renovation_end", last)):
        assert (pd.isna(w[key]) if day is None else w[key] == pd.Timestamp(day, tz="UTC"))


@pytest.mark.parametrize("text", ["2021-13-01", "2021-03-04/2021-03-01", "a/b/c", "2021-03-04T10:00"])
def test_bad_renovation_is_refused(text):
    from heliocal.pipeline.io.paint import renovation_window

    with pytest.raises(ValueError):
        renovation_window(text)


def test_juelich_log_accounts_for_all_rows(juelich_log):
    m, r = juelich_log["measurements"], juelich_log["rejected"]
    # 5,618 data rows (data README); 4 heliostats have no position in the log: AM25 51, AY32 27,
    # BC43 52, BD69 13 rows (counted with awk on the file) -> 143 unknown_heliostat
    assert len(m) + len(r) == 5618
    assert len(r) == 143 and set(r["reason"]) == {"unknown_heliostat"}
    assert r.groupby("heliostat_id").size().to_dict() == {"AM25": 51, "AY32": 27, "BC43": 52, "BD69": 13}
    assert sorted(m["source_row"].tolist() + r["source_row"].tolist()) == list(range(1, 5619))
    assert m["heliostat_id"].nunique() == 116
    assert {"env_wind_speed", "env_dni", "env_temperature"} <= set(m.columns)
    assert not m["qa_sun_mismatch"].any()


# ------------------------------------------------------------------------------------------------
# --focal-spot
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def paint_small_by_detector(tmp_path_factory):
    # tests/data/good/paint_small: 118671 has both spots, 118750 only HeliOS, 118826 only UTIS
    return {d: _ingest(tmp_path_factory.mktemp(d), str(GOOD / "paint_small"), "--focal-spot", d)
            ["measurements"].set_index("measurement_id") for d in ("utis", "helios")}


def test_focal_spot_choice_and_fallback(paint_small_by_detector):
    utis, helios = paint_small_by_detector["utis"], paint_small_by_detector["helios"]
    assert utis["focal_spot_source"].to_dict() == {"118671": "utis", "118750": "helios", "118826": "utis"}
    assert helios["focal_spot_source"].to_dict() == {"118671": "helios", "118750": "helios",
                                                     "118826": "utis"}
    # 118671: HeliOS alt 123.03944 m, UTIS alt 122.98824 m (the JSON file) -> 0.0512 m apart in u
    du = helios.loc["118671", "focal_spot_u_m"] - utis.loc["118671", "focal_spot_u_m"]
    assert du == pytest.approx(123.0394382264574 - 122.98824310302734, abs=1e-3)
    # the fallback rows are the same point whatever was asked for
    for mid in ("118750", "118826"):
        assert helios.loc[mid, "focal_spot_e_m"] == pytest.approx(utis.loc[mid, "focal_spot_e_m"], abs=1e-9)


def test_focal_spot_rejects_unknown_detector(runner, tmp_path):
    result = runner.invoke(app, ["ingest", str(GOOD / "paint_small"), "--focal-spot", "camera",
                                 "--workdir", str(tmp_path)])
    assert result.exit_code == 1
    assert result.stderr == ("Error: The 'focal_spot' parameter of ingest must be one of "
                             "{'utis', 'helios'}. Got 'camera' instead.\n")


# ------------------------------------------------------------------------------------------------
# sun: SPA where missing, flagged where the log disagrees
# ------------------------------------------------------------------------------------------------
def test_enu_log_sun_computed_with_spa(tmp_path):
    m = _ingest(tmp_path, str(GOOD / "enu_log_timestamps.csv"), "--properties",
                str(GOOD / "enu_properties.toml"), "--location", PLANT)["measurements"]
    assert (m["sun_source"] == "spa").all() and m["qa_sun_spa_diff_deg"].isna().all()
    row = m.set_index("timestamp").loc[pd.Timestamp("2022-06-12T13:27:37Z")]
    # same time and place as PAINT's BE36 118671 (see test_sun.py): SPA gives -48.92049 / 54.66591
    assert row["sun_azimuth_deg"] == pytest.approx(-48.92049, abs=1e-4)
    assert row["sun_elevation_deg"] == pytest.approx(54.66591, abs=1e-4)
    assert [row["sun_e"], row["sun_n"], row["sun_u"]] == pytest.approx(
        [np.cos(np.radians(54.66591)) * np.sin(np.radians(-48.92049)),
         -np.cos(np.radians(54.66591)) * np.cos(np.radians(-48.92049)),
         np.sin(np.radians(54.66591))], abs=1e-5)


def test_enu_log_with_logged_sun_has_no_spa_without_location(tmp_path):
    m = _ingest(tmp_path, str(GOOD / "enu_log.csv"), "--properties",
                str(GOOD / "enu_properties.toml"))["measurements"]
    assert len(m) == 5 and (m["sun_source"] == "log").all()
    assert m.set_index(["heliostat_id", "measurement_id"]).loc[("H01", "1"), "sun_elevation_deg"] == 45.0


def _edited_small_log(tmp_path: Path, row: int, column: str, change) -> Path:
    """A copy of juelich_log_small.csv (with its tower file) with one cell changed."""
    text = (GOOD / "juelich_log_small.csv").read_text()
    rows = list(csv.reader(io.StringIO(text)))
    i = rows[0].index(column)
    rows[row][i] = change(rows[row][i])
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    (tmp_path / "log.csv").write_text(out.getvalue())
    shutil.copyfile(GOOD / "tower-measurements.json", tmp_path / "tower-measurements.json")
    return tmp_path / "log.csv"


def test_logged_sun_far_from_spa_is_flagged_not_dropped(tmp_path):
    src = _edited_small_log(tmp_path, 3, "sun_elevation", lambda v: repr(float(v) + 0.5))
    m = _ingest(tmp_path / "w", str(src))["measurements"].set_index("source_row")
    assert len(m) == 10
    assert m.index[m["qa_sun_mismatch"]].tolist() == [3]
    # 0.5 deg added to the elevation: the vectors are 0.5 deg apart (the unedited rows are within
    # 0.01 deg of SPA)
    assert m.loc[3, "qa_sun_spa_diff_deg"] == pytest.approx(0.5, abs=0.01)
    assert m.drop(index=3)["qa_sun_spa_diff_deg"].max() < 0.01
    assert (m["sun_source"] == "log").all()


def test_sun_tolerance_option(tmp_path):
    src = _edited_small_log(tmp_path, 3, "sun_elevation", lambda v: repr(float(v) + 0.5))
    m = _ingest(tmp_path / "w", str(src), "--sun-tolerance", "1.0")["measurements"]
    assert not m["qa_sun_mismatch"].any()


# ------------------------------------------------------------------------------------------------
# options that turn a corpus error or rejection into kept rows
# ------------------------------------------------------------------------------------------------
def test_timezone_option_localises_naive_timestamps(tmp_path):
    out = _ingest(tmp_path, str(BAD / "timestamps_without_zone.csv"), "--timezone", "Europe/Berlin")
    m = out["measurements"].set_index("source_row")
    assert len(m) == 10 and len(out["rejected"]) == 0
    # 2022-06-03T09:20:02 in Berlin (CEST, UTC+2) is 07:20:02 UTC
    assert m.loc[1, "timestamp"] == pd.Timestamp("2022-06-03T07:20:02Z")
    # the logged sun belongs to 09:20:02 UTC, two hours off: every row is flagged
    assert m["qa_sun_mismatch"].all()


def test_north_clockwise_azimuths_are_converted(tmp_path):
    m = _ingest(tmp_path, str(BAD / "azimuth_north_clockwise.csv"), "--azimuth-convention",
                "north-clockwise")["measurements"].set_index("source_row")
    # row 1 logged 180 - 54.442661206716764 deg (the Jülich log's value in PAINT's convention)
    assert m.loc[1, "sun_azimuth_deg"] == pytest.approx(54.442661206716764, abs=1e-9)
    assert not m["qa_sun_mismatch"].any()


def test_max_spot_distance_option(tmp_path):
    out = _ingest(tmp_path, str(BAD / "focal_spot_kilometres_away.csv"), "--max-spot-distance", "2000")
    assert len(out["measurements"]) == 10 and len(out["rejected"]) == 0


def test_duplicates_across_sources_are_rejected_from_the_second(tmp_path):
    log = str(GOOD / "juelich_log_small.csv")
    result = CliRunner().invoke(app, ["ingest", log, log, "--workdir", str(tmp_path), "--quiet"])
    assert result.exit_code == 0, result.stderr
    r = pd.read_parquet(tmp_path / "rejected.parquet")
    assert len(pd.read_parquet(tmp_path / "measurements.parquet")) == 10
    assert len(r) == 10 and set(r["reason"]) == {"duplicate_measurement_id"}


def test_failed_ingest_keeps_previous_artifacts(tmp_path):
    _ingest(tmp_path, str(GOOD / "juelich_log_small.csv"))
    before = (tmp_path / "measurements.parquet").read_bytes()
    result = CliRunner().invoke(app, ["ingest", str(BAD / "empty.csv"), "--workdir", str(tmp_path)])
    assert result.exit_code == 1
    assert (tmp_path / "measurements.parquet").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["heliostats.parquet", "ingest.manifest.json",
                                                         "measurements.parquet", "rejected.parquet"]


def test_a_duplicate_names_its_first_row_as_an_integer_beside_other_rejections(tmp_path):
    # juelich_log_small.csv's data row 4 takes row 2's sample id, and row 1's azimuth is text:
    # rows are numbered 1-based after the header, so the duplicate's detail names row 2 (it said
    # "row 2.0" when the chunk also held a rejected row)
    log = _edited_small_log(tmp_path, 1, "sun_azimuth", lambda v: "east")
    rows = list(csv.reader(io.StringIO(log.read_text())))
    sid = rows[0].index("sample_id")
    rows[4][sid] = rows[2][sid]
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    log.write_text(out.getvalue())
    rejected = _ingest(tmp_path / "wd", str(log))["rejected"].set_index("source_row")
    assert rejected.loc[1, "reason"] == "unparsable_number"
    assert rejected.loc[4, "reason"] == "duplicate_measurement_id"
    assert rejected.loc[4, "detail"] == (f"measurement id {rows[2][sid]!r} already seen in "
                                         "source row 2")
