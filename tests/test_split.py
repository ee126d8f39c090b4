"""Tests of pipeline/split.py and `heliocal split-knn`.

Expected values are computed by hand (stated next to each) or from a closed form; the random
inputs of the property tests only feed invariants.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import heliocal.cli.split  # noqa: F401  (registers split-knn on the app)
from heliocal.cli.app import app
from heliocal.pipeline.artifacts.store import read_artifact, read_provenance, write_artifact
from heliocal.pipeline.errors import FitError, InputError, ParameterError
from heliocal.pipeline.artifacts.schemas import MEASUREMENTS
from heliocal.pipeline.stages.split import (METHODS, knn_distance_deg, required_measurements,
                                            restrict_training, split_measurements)
from heliocal.pipeline.artifacts.schemas import SPLIT

# --------------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------------
LINE_AZ = [0.0, 1.0, 3.0, 7.0, 15.0]  # five sun positions on a line at elevation 10 deg


def _frame(heliostat, az, el, ids=None, start="2023-01-01T10:00Z", step_h=25):
    n = len(az)
    return pd.DataFrame({
        "heliostat_id": heliostat,
        "measurement_id": ids if ids is not None else [f"m{i}" for i in range(n)],
        "timestamp": pd.date_range(start, periods=n, freq=f"{step_h}h"),
        "sun_azimuth_deg": np.asarray(az, float),
        "sun_elevation_deg": np.asarray(el, float),
    })


def _full_measurements(frame: pd.DataFrame) -> pd.DataFrame:
    """Complete MEASUREMENTS rows around the sun columns (other values are placeholders)."""
    df = frame.copy()
    az, el = np.radians(df["sun_azimuth_deg"]), np.radians(df["sun_elevation_deg"])
    df["sun_e"], df["sun_n"], df["sun_u"] = np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)
    for c in MEASUREMENTS.columns:
        if c.name in df.columns:
            continue
        df[c.name] = {"float64": 0.0, "string": "x", "int64": 1, "bool": False}[c.dtype]
    df["qa_sun_spa_diff_deg"] = np.nan
    return df


def _grid(n, heliostat="H1"):
    """n distinct sun positions (az from -100 to 100 deg, el 10 to 60 deg), written out."""
    i = np.arange(n)
    return _frame(heliostat, -100 + (i * 37) % 200 + 0.1 * i, 10 + (i * 13) % 50)


# --------------------------------------------------------------------------------------------
# kNN distance: hand-computed cases
# --------------------------------------------------------------------------------------------
def test_knn_distance_hand_computed_line():
    # azimuths 0, 1, 3, 7, 15 at equal elevation. Nearest-neighbour gaps by hand:
    # 0->1: 1, 1->0: 1, 3->1: 2, 7->3: 4, 15->7: 8.  Two nearest: 0: (1+3)/2 = 2,
    # 1: (1+2)/2 = 1.5, 3: (2+3)/2 = 2.5 (to 1 and 0), 7: (4+6)/2 = 5, 15: (8+12)/2 = 10.
    el = [10.0] * 5
    np.testing.assert_allclose(knn_distance_deg(LINE_AZ, el, k=1), [1, 1, 2, 4, 8])
    np.testing.assert_allclose(knn_distance_deg(LINE_AZ, el, k=2), [2, 1.5, 2.5, 5, 10])
    # three nearest of 0: 1, 3, 7 -> 11/3; of 15: 8, 12, 14 -> 34/3
    np.testing.assert_allclose(knn_distance_deg(LINE_AZ, el, k=3)[[0, 4]], [11 / 3, 34 / 3])


def test_knn_distance_duplicate_is_a_neighbour_at_zero():
    np.testing.assert_allclose(knn_distance_deg([5, 5, 9], [20, 20, 20], k=1), [0, 0, 4])


def test_great_circle_equals_euclidean_on_the_horizon():
    # at elevation 0 the azimuth difference is the great-circle angle exactly
    az, el = [0.0, 0.5, 2.0], [0.0, 0.0, 0.0]
    np.testing.assert_allclose(knn_distance_deg(az, el, 1, "great-circle"),
                               knn_distance_deg(az, el, 1, "euclidean"), atol=1e-9)
    # along a meridian (same azimuth) both are the elevation difference
    np.testing.assert_allclose(knn_distance_deg([30, 30], [10, 12], 1, "great-circle"), [2, 2],
                               atol=1e-9)


def test_great_circle_and_euclidean_differ_near_the_zenith():
    # two suns at elevation 89 deg, azimuths 180 deg apart: the arc through the zenith is
    # 1 + 1 = 2 deg, while the (azimuth, elevation) plane puts them 180 deg apart.
    az, el = [-90.0, 90.0], [89.0, 89.0]
    np.testing.assert_allclose(knn_distance_deg(az, el, 1, "great-circle"), [2, 2], atol=1e-9)
    np.testing.assert_allclose(knn_distance_deg(az, el, 1, "euclidean"), [180, 180])
    # 10 deg of azimuth at elevation 80: cos(theta) = sin^2(80) + cos^2(80) cos(10) (spherical
    # law of cosines), theta = 1.7343 deg (small-angle: cos(80) * 10 = 1.7365), not 10.
    e = math.radians(80)
    theta = math.degrees(math.acos(math.sin(e) ** 2 + math.cos(e) ** 2 * math.cos(math.radians(10))))
    np.testing.assert_allclose(knn_distance_deg([0, 10], [80, 80], 1, "great-circle"), [theta] * 2,
                               rtol=1e-7)
    assert theta == pytest.approx(1.7343, abs=1e-4)


def test_knn_distance_rejects_bad_options():
    with pytest.raises(ParameterError, match=r"The 'k' parameter of split_knn must be an int in "
                                             r"\[1, 3\]. Got 4 instead."):
        knn_distance_deg([0, 1, 2, 3, 4], [1] * 5, k=4)
    with pytest.raises(ParameterError, match="'metric'"):
        knn_distance_deg([0, 1], [1, 1], k=1, metric="manhattan")
    with pytest.raises(ParameterError, match="needs at least 4 sun positions"):
        knn_distance_deg([0, 1, 2], [1, 1, 1], k=3)


# --------------------------------------------------------------------------------------------
# the kNN split: hand-computed
# --------------------------------------------------------------------------------------------
def test_knn_split_hand_computed():
    # k=1 distances (above): m0 1, m1 1, m2 2, m3 4, m4 8. Ranks: m4 0, m3 1, m2 2, and the tie
    # m0/m1 goes by id: m0 3, m1 4. n_test=1 -> m4 test; n_val=1 -> m3 validation.
    table, skipped = split_measurements(_frame("H", LINE_AZ, [10.0] * 5), k=1, n_test=1, n_val=1)
    assert skipped == []
    t = table.set_index("measurement_id")
    assert t["split"].to_dict() == {"m0": "train", "m1": "train", "m2": "train",
                                    "m3": "validation", "m4": "test"}
    assert t["knn_rank"].to_dict() == {"m0": 3, "m1": 4, "m2": 2, "m3": 1, "m4": 0}
    # nearest training row: m0->m1 1, m1->m0 1, m2->m1 2, m3(7)->m2(3) 4, m4(15)->m2(3) 12
    assert t["nearest_train_distance_deg"].tolist() == [1, 1, 2, 4, 12]
    assert set(table["method"]) == {"knn"} and set(table["metric"]) == {"euclidean"}


def test_knn_split_n_train_drops_smallest_distance_first():
    # train candidates m2 (2), m0 (1), m1 (1); n_train=2 keeps m2 and, of the tie, m0 (id order).
    table, _ = split_measurements(_frame("H", LINE_AZ, [10.0] * 5), k=1, n_test=1, n_val=1,
                                  n_train=2)
    t = table.set_index("measurement_id")
    assert t["split"].to_dict() == {"m0": "train", "m1": "unused", "m2": "train",
                                    "m3": "validation", "m4": "test"}
    # recomputed: m0(0)<->m2(3) 3, m1(1)->m0 1, m3(7)->m2 4, m4(15)->m2 12
    assert t["nearest_train_distance_deg"].tolist() == [3, 1, 3, 4, 12]


def test_restrict_training_is_idempotent_and_reversible():
    table, _ = split_measurements(_grid(40), k=2, n_test=5, n_val=5)
    small = restrict_training(table, 10)
    assert (small["split"] == "train").sum() == 10
    pd.testing.assert_frame_equal(restrict_training(small, 10), small)
    pd.testing.assert_frame_equal(restrict_training(small, None), table)


def test_restrict_training_too_few_candidates():
    table, _ = split_measurements(_grid(12), k=1, n_test=3, n_val=3)
    with pytest.raises(FitError, match="too few training candidates for n_train=7: H1 has 6"):
        restrict_training(table, 7)


def test_comparison_methods_hand_computed():
    # ten measurements m0..m9, one per month from 2023-01-21 (monthly on the 21st), azimuth
    # increasing with the index except m2, which has the largest azimuth.
    ts = pd.to_datetime([f"2023-{month:02d}-21T12:00Z" for month in range(1, 11)])
    az = [0, 10, 95, 30, 40, 50, 60, 70, 80, 90]
    f = pd.DataFrame({"heliostat_id": "H", "measurement_id": [f"m{i}" for i in range(10)],
                      "timestamp": ts, "sun_azimuth_deg": az, "sun_elevation_deg": 30.0})

    def sets(method):
        t, _ = split_measurements(f, method=method, k=1, n_test=2, n_val=2)
        return {s: sorted(t.loc[t["split"] == s, "measurement_id"]) for s in ("test", "validation")}

    # time: the last two are test, the two before validation
    assert sets("time") == {"test": ["m8", "m9"], "validation": ["m6", "m7"]}
    # azimuth: largest azimuths test (95, 90), next (80, 70) validation
    assert sets("azimuth") == {"test": ["m2", "m9"], "validation": ["m7", "m8"]}
    # solstice: 21 June is m5 (0 days); 21 May / 21 July (m4, m6) are 31 / 30 days away, 21 April
    # / 21 August (m3, m7) 61 / 61 days: test m5, m6; validation m4 (31 d), then the tie m3/m7
    # at 61 days goes by id to m3.
    assert sets("solstice") == {"test": ["m5", "m6"], "validation": ["m3", "m4"]}


def test_time_methods_keep_untimed_rows_as_training(caplog):
    f = _grid(10)
    f.loc[9, "timestamp"] = pd.NaT  # the latest measurement loses its time
    table, _ = split_measurements(f, method="time", k=1, n_test=2, n_val=2)
    t = table.set_index("measurement_id")["split"]
    assert t["m9"] == "train"
    assert sorted(t[t == "test"].index) == ["m7", "m8"]
    assert "heliostat H1: 1 measurement(s) without timestamp (ids m9)" in caplog.text
    f.loc[:6, "timestamp"] = pd.NaT
    with pytest.raises(InputError, match=r"method 'solstice' needs timestamps for the 2 test and "
                                         r"2 validation measurements, but only 2 of heliostat "
                                         r"H1's 10 have one"):
        split_measurements(f, method="solstice", k=1, n_test=2, n_val=2)


def test_time_split_beside_the_knn_split_hand_computed(caplog):
    # the comparison table above (m0..m9 monthly, m9 latest) with the default kNN method: the
    # split column is the kNN split, time_split the time split of the same sizes
    ts = pd.to_datetime([f"2023-{month:02d}-21T12:00Z" for month in range(1, 11)])
    f = pd.DataFrame({"heliostat_id": "H", "measurement_id": [f"m{i}" for i in range(10)],
                      "timestamp": ts[::-1], "sun_azimuth_deg": [0, 10, 95, 30, 40, 50, 60, 70, 80, 90],
                      "sun_elevation_deg": 30.0})   # m0 is the latest, m9 the earliest
    knn, _ = split_measurements(f, k=1, n_test=2, n_val=2)
    table, _ = split_measurements(f, k=1, n_test=2, n_val=3, n_train=2)
    t = table.set_index("measurement_id")
    # the latest two (m0, m1) test, the three before (m2, m3, m4) validation, the earlier five
    # train candidates; n_train=2 keeps the two with the largest kNN distance (k=1, azimuths
    # 50..90 step 10: all 10; the tie goes by id: m5, m6), the kNN rule of --n-train
    assert t["time_split"].to_dict() == {
        "m0": "test", "m1": "test", "m2": "validation", "m3": "validation", "m4": "validation",
        "m5": "train", "m6": "train", "m7": "unused", "m8": "unused", "m9": "unused"}
    # the selection split is the kNN one: the time split only sits beside it
    assert set(knn["method"]) == {"knn"}
    # k=1 distances: 5 for m2 (95 -> 90) and m9 (90 -> 95), 10 for all others; ties by id:
    # kNN test m0, m1 and validation m3, m4, while the time split's validation is m2, m3
    k = knn.set_index("measurement_id")
    assert sorted(k.index[k["split"] == "validation"]) == ["m3", "m4"]
    assert sorted(k.index[k["time_split"] == "validation"]) == ["m2", "m3"]
    same, _ = split_measurements(f, method="time", k=1, n_test=2, n_val=3, n_train=2)
    assert same["split"].tolist() == table["time_split"].tolist()
    # no timestamps at all: no time split, n/a, never an error
    bare, _ = split_measurements(f.drop(columns="timestamp"), k=1, n_test=2, n_val=2)
    assert bare["time_split"].isna().all() and (bare["split"] == knn["split"]).all()
    # one untimed row: it cannot be placed in time and gets no label; too few timed rows: none
    g = f.copy()
    g.loc[0, "timestamp"] = pd.NaT
    t = split_measurements(g, k=1, n_test=2, n_val=2)[0].set_index("measurement_id")["time_split"]
    assert pd.isna(t["m0"]) and sorted(t[t == "test"].index) == ["m1", "m2"]
    g.loc[:5, "timestamp"] = pd.NaT
    t = split_measurements(g, k=1, n_test=2, n_val=2)[0]["time_split"]
    assert t.isna().all()
    assert "heliostat H has no time split (4 of its measurements have a timestamp, the time " \
           "split needs 6)" in caplog.text


def test_skipped_and_none_left():
    f = pd.concat([_grid(30, "BIG"), _grid(9, "SMALL")], ignore_index=True)
    table, skipped = split_measurements(f, k=3, n_test=5, n_val=3)
    assert skipped == [("SMALL", 9)] and set(table["heliostat_id"]) == {"BIG"}
    assert required_measurements(3, 5, 3) == 10
    with pytest.raises(FitError) as err:
        split_measurements(f, n_test=30, n_val=20)
    assert str(err.value) == (
        "no heliostat has enough measurements for this split: each needs at least 52 (30 test + "
        "20 validation + 2 training), but BIG has 30, SMALL has 9; lower --n-test, --n-val or "
        "--n-train")


# --------------------------------------------------------------------------------------------
# property tests
# --------------------------------------------------------------------------------------------
@st.composite
def _measurements(draw, min_n=6, max_n=45):
    n_test = draw(st.integers(0, 6))
    n_val = draw(st.integers(0, 6))
    k = draw(st.integers(1, 3))
    n = draw(st.integers(max(min_n, n_test + n_val + 2, k + 1), max_n))
    az = draw(st.lists(st.floats(-120, 120, allow_nan=False), min_size=n, max_size=n))
    # a coarse elevation grid makes exact distance ties likely, to exercise the tie-breaking
    el = draw(st.lists(st.integers(1, 17).map(lambda v: 5.0 * v), min_size=n, max_size=n))
    hours = draw(st.lists(st.integers(0, 24 * 800), min_size=n, max_size=n, unique=True))
    ids = draw(st.lists(st.integers(0, 10**6).map(str), min_size=n, max_size=n, unique=True))
    f = pd.DataFrame({"heliostat_id": "H", "measurement_id": ids,
                      "timestamp": pd.Timestamp("2022-01-01", tz="UTC") + pd.to_timedelta(hours, "h"),
                      "sun_azimuth_deg": az, "sun_elevation_deg": el})
    return f, k, n_test, n_val


_PROP = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_PROP
@given(data=_measurements(), method=st.sampled_from(METHODS),
       metric=st.sampled_from(["euclidean", "great-circle"]), seed=st.integers(0, 2**16))
def test_property_disjoint_complete_and_sized(data, method, metric, seed):
    f, k, n_test, n_val = data
    table, skipped = split_measurements(f, method=method, k=k, n_test=n_test, n_val=n_val,
                                        metric=metric, seed=seed)
    assert skipped == []
    # disjoint and complete: every input measurement exactly once, one label each
    assert sorted(table["measurement_id"]) == sorted(f["measurement_id"])
    assert table["measurement_id"].is_unique
    counts = table["split"].value_counts().to_dict()
    assert counts.get("test", 0) == n_test and counts.get("validation", 0) == n_val
    assert counts.get("train", 0) == len(f) - n_test - n_val and counts.get("unused", 0) == 0
    assert sorted(table["knn_rank"]) == list(range(len(f)))
    assert (table["nearest_train_distance_deg"] >= 0).all()
    if method == "knn":
        # the test rows are the n_test largest kNN distances (rank = sorted position)
        assert set(table.loc[table["split"] == "test", "knn_rank"]) == set(range(n_test))
    # the result does not depend on the input row order
    shuffled, _ = split_measurements(f.sample(frac=1, random_state=seed), method=method, k=k,
                                     n_test=n_test, n_val=n_val, metric=metric, seed=seed)
    pd.testing.assert_frame_equal(shuffled, table)


@_PROP
@given(data=_measurements(min_n=8), method=st.sampled_from(METHODS), n_train=st.integers(2, 40))
def test_property_n_train_keeps_largest_distances(data, method, n_train):
    f, k, n_test, n_val = data
    n_train = min(n_train, len(f) - n_test - n_val)
    assume(n_train >= 2)  # a discarded example, not a pass: hypothesis fails if too few are left
    full, _ = split_measurements(f, method=method, k=k, n_test=n_test, n_val=n_val)
    cut, _ = split_measurements(f, method=method, k=k, n_test=n_test, n_val=n_val, n_train=n_train)
    pd.testing.assert_frame_equal(cut[["measurement_id", "knn_distance_deg", "knn_rank"]],
                                  full[["measurement_id", "knn_distance_deg", "knn_rank"]])
    assert (cut["split"] == "train").sum() == n_train
    assert (cut["split"] == "unused").sum() == (full["split"] == "train").sum() - n_train
    # test and validation are untouched
    held = full["split"].isin(["test", "validation"])
    assert (cut.loc[held, "split"] == full.loc[held, "split"]).all()
    # kept training rows = the n_train largest kNN distances among the full training rows
    # (ties by measurement id)
    expected = (full[full["split"] == "train"]
                .sort_values(["knn_distance_deg", "measurement_id"], ascending=[False, True])
                .head(n_train)["measurement_id"])
    assert set(cut.loc[cut["split"] == "train", "measurement_id"]) == set(expected)


@settings(max_examples=15, deadline=None)
@given(data=_measurements(), seed=st.integers(0, 2**31 - 1), method=st.sampled_from(["random", "balanced"]))
def test_property_same_seed_same_split(data, seed, method):
    f, k, n_test, n_val = data
    a, _ = split_measurements(f, method=method, k=k, n_test=n_test, n_val=n_val, seed=seed)
    b, _ = split_measurements(f, method=method, k=k, n_test=n_test, n_val=n_val, seed=seed)
    pd.testing.assert_frame_equal(a, b)


def test_different_seed_changes_random_split():
    f = _grid(40)
    a, _ = split_measurements(f, method="random", n_test=10, n_val=10, seed=0)
    b, _ = split_measurements(f, method="random", n_test=10, n_val=10, seed=1)
    assert not a["split"].equals(b["split"])


def test_random_split_of_a_heliostat_ignores_other_heliostats():
    one = _grid(30, "A")
    both = pd.concat([one, _grid(30, "B")], ignore_index=True)
    a, _ = split_measurements(one, method="random", n_test=5, n_val=5, seed=3)
    b, _ = split_measurements(both, method="random", n_test=5, n_val=5, seed=3)
    pd.testing.assert_frame_equal(a, b[b["heliostat_id"] == "A"].reset_index(drop=True))


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------
runner = CliRunner()


def _write(workdir, frame):
    write_artifact(_full_measurements(frame), workdir, MEASUREMENTS, stage="ingest")


def _one_line(text: str) -> str:
    return " ".join(text.split())


def test_cli_writes_split_and_warns_about_small_heliostat(tmp_path):
    _write(tmp_path, pd.concat([_grid(60, "BIG"), _grid(10, "SMALL")], ignore_index=True))
    res = runner.invoke(app, ["split-knn", "--workdir", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert ("skipped heliostat SMALL: it has 10 measurements, the split needs at least 52 (30 "
            "test + 20 validation + 2 training)") in _one_line(res.stderr)
    assert "BIG" in res.stdout and "SMALL" not in res.stdout
    split = read_artifact(tmp_path, SPLIT)
    assert len(split) == 60 and split["split"].value_counts().to_dict() == {
        "test": 30, "validation": 20, "train": 10}
    prov = read_provenance(tmp_path / "split.parquet")
    assert prov["stage"] == "split-knn" and prov["options"]["k"] == 3
    assert prov["inputs"]["measurements"] is not None


def test_cli_json(tmp_path):
    _write(tmp_path, _grid(20))
    res = runner.invoke(app, ["split-knn", "-w", str(tmp_path), "--n-test", "4", "--n-val", "3",
                              "--n-train", "5", "--metric", "great-circle", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    (h,) = out["heliostats"]
    assert h["counts"] == {"train": 5, "validation": 3, "test": 4, "unused": 8}
    assert out["metric"] == "great-circle" and out["skipped"] == []
    assert h["mean_test_to_train_distance_deg"] > 0


def test_cli_none_left(tmp_path):
    _write(tmp_path, _grid(10))
    res = runner.invoke(app, ["split-knn", "--workdir", str(tmp_path)])
    assert res.exit_code == 1
    assert res.stderr == (
        "Error: no heliostat has enough measurements for this split: each needs at least 52 (30 "
        "test + 20 validation + 2 training), but H1 has 10; lower --n-test, --n-val or "
        "--n-train\n")
    assert not (tmp_path / "split.parquet").exists()


def test_cli_missing_measurements(tmp_path):
    res = runner.invoke(app, ["split-knn", "--workdir", str(tmp_path)])
    assert res.exit_code == 1
    assert res.stderr == (f"Error: {tmp_path}/measurements.parquet is missing: run `heliocal "
                          f"ingest SOURCE... --workdir {tmp_path}` first\n")


def test_cli_usage_errors(tmp_path):
    res = runner.invoke(app, ["split-knn", "-w", str(tmp_path), "--method", "nope"])
    assert res.exit_code == 2 and "'nope' is not one of" in res.stderr
    res = runner.invoke(app, ["split-knn", "-w", str(tmp_path), "--k", "4"])
    assert res.exit_code == 2


def test_cli_help():
    res = runner.invoke(app, ["split-knn", "--help"])
    assert res.exit_code == 0
    for option in ("--method", "--k", "--n-test", "--n-val", "--n-train", "--metric", "--seed",
                   "--json", "--quiet"):
        assert option in res.stdout
