"""Tests of heliocal.pipeline.stages.report and ``heliocal report``.

Every input is a small fake work directory written out here (two heliostats, 40 measurements
each, errors chosen by hand), so the expected numbers are known without running the pipeline;
the real sample data is covered by the committed baseline (tests/baseline/metrics_sample.json,
checked against the schema below and by .ci/run's regression run).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import heliocal.cli.report  # noqa: F401 - registers `heliocal report` on the app
from heliocal.cli.app import app
from heliocal.pipeline.artifacts.store import write_artifact
from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, COARSE_PREDICTIONS
from heliocal.pipeline.errors import StageInputError
from heliocal.pipeline.report.metrics import column_of as _col
from heliocal.pipeline.stages.report import run_report
from heliocal.pipeline.report.metrics import compute_metrics, metrics_json
from heliocal.pipeline.report.inputs import load_inputs
from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS, REJECTED, all_schemas
from heliocal.pipeline.artifacts.schemas import REGIMES, SPLIT

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = json.loads((ROOT / "docs" / "metrics_schema.json").read_text())
BASELINE = ROOT / "tests" / "baseline" / "metrics_sample.json"

HIDS = ("AA01", "AB02")
N = 40  # measurements per heliostat: 20 train, 10 validation, 10 test
SPLITS = ["train"] * 20 + ["validation"] * 10 + ["test"] * 10
#: error_mrad of the selected coarse preset per split (hand-chosen; statistics below follow)
TEST_ERRORS = np.linspace(0.5, 1.4, 10)  # mean 0.95, median 0.95, p95 1.355 (numpy linear)
VAL_ERRORS = np.full(10, 0.8)
TRAIN_ERRORS = np.full(20, 0.6)
SELECTED = {"AA01": "static-6", "AB02": "static-20"}
#: mean validation / test error_mrad of the selected preset (coarse_params.parquet): the means of
#: VAL_ERRORS / TEST_ERRORS, + 0.05 for static-20 (see the coarse predictions below)
COARSE_VAL = {"AA01": 0.8, "AB02": 0.85}
COARSE_TEST = {"AA01": 0.95, "AB02": 1.0}

_DEFAULTS = {"string": "x", "float64": 0.0, "int64": 0, "bool": False,
             "timestamp": pd.Timestamp("2023-01-01", tz="UTC")}


# ------------------------------------------------------------------------------------------------
# fake work directories
# ------------------------------------------------------------------------------------------------
def _write(df: pd.DataFrame, workdir: Path, schema) -> None:
    """Write through the declared schema, filling columns the test does not care about."""
    df = df.copy()
    for c in schema.columns:
        if c.name not in df.columns:
            # fit_degenerate: empty means the data are fine (a text would flag the heliostat)
            df[c.name] = "" if c.name == "fit_degenerate" else _DEFAULTS[c.dtype]
    write_artifact(df, workdir, schema, stage=schema.producer, inputs={})


def _write_optional(df: pd.DataFrame, workdir: Path, filename: str) -> None:
    """hybrid/sweep/selection: through their schema once one is declared, else plain Parquet."""
    schema = next((s for s in all_schemas() if s.filename == filename), None)
    if schema is None:
        df.to_parquet(workdir / filename)
        return
    keep = [c for c in df.columns if c in schema.column_names()
            or c.startswith(schema.extra_prefixes or ("\0",))]
    _write(df[keep], workdir, schema)


def _measurements() -> pd.DataFrame:
    rows = []
    for h, hid in enumerate(HIDS):
        for i in range(N):
            rows.append({
                "heliostat_id": hid, "measurement_id": f"{1000 + i}",
                "timestamp": pd.Timestamp("2023-01-05", tz="UTC") + pd.Timedelta(days=9 * i + h),
                "sun_azimuth_deg": -80.0 + 4.0 * i, "sun_elevation_deg": 10.0 + (i * 7) % 50,
            })
    return pd.DataFrame(rows)


#: The time split (split.parquet time_split): AA01's rows in time order (its timestamps grow with
#: the row), AB02 without one (n/a)
TIME_SPLITS = {"AA01": SPLITS, "AB02": [None] * N}
#: time_error_mrad of AA01's models evaluated forward in time (the selected coarse preset and the
#: hybrid): their error + 1.0 and + 0.5 (hand-chosen; metrics.json's forward_in_time follows)
TIME_OFFSET = {"static-6": 1.0, "hybrid": 0.5}


def _predictions(model_errors: dict[str, np.ndarray], selected: dict[str, str]) -> pd.DataFrame:
    rows = []
    for hid in HIDS:
        for model, err in model_errors.items():
            for i in range(N):
                off = TIME_OFFSET.get(model) if hid == "AA01" else None
                rows.append({"heliostat_id": hid, "measurement_id": f"{1000 + i}",
                             "split": SPLITS[i], "model": model,
                             "selected": selected.get(hid) == model,
                             "error_mrad": float(err[i]), "beam_error_mrad": 2 * float(err[i]),
                             "spot_offset_horizontal_m": 0.01, "spot_offset_vertical_m": 0.0,
                             "spot_offset_m": 0.01,
                             "time_error_mrad": np.nan if off is None else float(err[i]) + off})
    return pd.DataFrame(rows)


def make_workdir(root: Path, stage: str = "sweep") -> Path:
    """A fake work directory with the artifacts of every stage up to ``stage``.

    stage: ``ingest``, ``split``, ``coarse`` or ``sweep`` (hybrid predictions, sweep, selection).
    """
    wd = root / stage
    wd.mkdir(parents=True)
    m = _measurements()
    _write(m, wd, MEASUREMENTS)
    _write(pd.DataFrame({"heliostat_id": list(HIDS), "n_measurements": [N, N]}), wd, HELIOSTATS)
    _write(pd.DataFrame({"source_file": ["a.csv", "a.csv", "b.csv"], "source_row": [3, 7, 2],
                         "heliostat_id": ["AA01", "AA01", None],
                         "reason": ["missing_value", "sun_below_horizon", "missing_value"],
                         "detail": ["d"] * 3, "raw": ["{}"] * 3}), wd, REJECTED)
    if stage == "ingest":
        return wd
    split = m[["heliostat_id", "measurement_id", "sun_azimuth_deg", "sun_elevation_deg"]].copy()
    split["split"] = SPLITS * len(HIDS)
    split["time_split"] = [v for hid in HIDS for v in TIME_SPLITS[hid]]
    split["knn_distance_deg"] = 3.0
    split["knn_rank"] = list(range(N)) * len(HIDS)
    split["nearest_train_distance_deg"] = np.where(split["split"] == "test", 12.5, 4.0)
    split["method"], split["metric"] = "knn", "euclidean"
    _write(split, wd, SPLIT)
    if stage == "split":
        return wd
    coarse_err = np.concatenate([TRAIN_ERRORS, VAL_ERRORS, TEST_ERRORS])
    _write(_predictions({"nominal": coarse_err * 20, "static-6": coarse_err,
                         "static-20": coarse_err + 0.05}, SELECTED), wd, COARSE_PREDICTIONS)
    params = [{"heliostat_id": hid, "preset": SELECTED[hid], "selected": True,
               "parameter_index": k, "parameter": name, "unit": "rad", "nominal": 0.0,
               "fitted": 0.001 * (k + 1), "std_error": 0.0002, "free": True, "determined": k < 2,
               "n_train": 20, "fit_iterations": 7, "fit_condition_number": 12.0,
               "fit_implausible": "", "val_error_mrad": COARSE_VAL[hid],
               "test_error_mrad": COARSE_TEST[hid]}
              for hid in HIDS for k, name in enumerate(("joint_1_tilt_e_rad", "joint_1_tilt_n_rad",
                                                        "joint_2_tilt_u_rad"))]
    _write(pd.DataFrame(params), wd, COARSE_PARAMS)
    # regimes: AA01 changes at its 20th row (detected), AB02 stays in one regime with an outlier
    t = m.groupby("heliostat_id")["timestamp"]
    first, last = t.min(), t.max()
    at = m.loc[(m["heliostat_id"] == "AA01") & (m["measurement_id"] == "1020"), "timestamp"].iloc[0]
    _write(pd.DataFrame([
        {"heliostat_id": "AA01", "kind": "regime", "regime": 0, "start": first["AA01"],
         "end": at - pd.Timedelta(days=9), "cause": "start", "n_rows": 20, "step_mrad": np.nan,
         "evidence": np.nan, "error_mrad": 0.6},
        {"heliostat_id": "AA01", "kind": "regime", "regime": 1, "start": at, "end": last["AA01"],
         "cause": "detected", "n_rows": 20, "step_mrad": 2.5, "evidence": 40.0, "error_mrad": 0.9},
        {"heliostat_id": "AB02", "kind": "regime", "regime": 0, "start": first["AB02"],
         "end": last["AB02"], "cause": "start", "n_rows": 40, "step_mrad": np.nan,
         "evidence": np.nan, "error_mrad": 0.7},
        {"heliostat_id": "AB02", "kind": "outlier", "regime": 0, "start": first["AB02"],
         "end": first["AB02"], "cause": "outlier", "n_rows": 1, "measurement_id": "1000",
         "step_mrad": 3.0, "evidence": 9.0, "error_mrad": 3.1}]), wd, REGIMES)
    if stage == "coarse":
        return wd
    _write_optional(_predictions({"hybrid": coarse_err * 0.7, "nn-only": coarse_err * 1.5},
                                 {h: "hybrid" for h in HIDS}), wd, "hybrid_predictions.parquet")
    sweep = []
    for hid in HIDS:
        for model, base in (("hybrid", 0.6), ("nn-only", 1.2)):
            for n_train in (5, 10, 20):
                for wd_ in (0.0, 1e-3, 1e-2, 1e-1):
                    for seed in (0, 1):
                        test = base + 2.0 / n_train + 3 * abs(wd_ - 1e-2) + 0.02 * seed
                        sweep.append({
                            "heliostat_id": hid, "model": model, "n_train": n_train,
                            "weight_decay": wd_, "seed": seed,
                            "train_error_mrad_mean": test / 2, "train_error_mrad_median": test / 2,
                            "val_error_mrad_mean": test - 0.1, "val_error_mrad_median": test - 0.1,
                            "test_error_mrad_mean": test, "test_error_mrad_median": test,
                            "test_train_distance_deg": 20.0 - 0.5 * n_train, "wall_time_s": 1.0})
    _write_optional(pd.DataFrame(sweep), wd, "sweep.parquet")
    _write_optional(pd.DataFrame({"heliostat_id": list(HIDS), "model": ["hybrid", "hybrid"],
                                  "weight_decay": [1e-2, 1e-2], "val_error_mrad": [0.56, 0.6],
                                  "test_error_mrad": [0.665, 0.7],
                                  "coarse_val_error_mrad": [0.8, 0.85],
                                  "coarse_test_error_mrad": [0.95, 1.0]}),
                    wd, "selection.parquet")
    return wd


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    """(workdir, summary) of a report over every stage's artifacts (built once per module)."""
    wd = make_workdir(tmp_path_factory.mktemp("report"), "sweep")
    return wd, run_report(wd)


# ------------------------------------------------------------------------------------------------
# JSON Schema: jsonschema when installed, else a small validator of the keywords we use
# ------------------------------------------------------------------------------------------------
_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None)}


def _is_type(value, name: str) -> bool:
    if name == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if name == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, _TYPES[name])


def _small_validate(value, schema: dict, root: dict, path: str = "$") -> list[str]:
    if "$ref" in schema:
        target = root
        for part in schema["$ref"].lstrip("#/").split("/"):
            target = target[part]
        return _small_validate(value, target, root, path)
    errs = []
    types = schema.get("type")
    if types is not None:
        types = [types] if isinstance(types, str) else types
        if not any(_is_type(value, t) for t in types):
            return [f"{path}: {value!r} is not of type {types}"]
    if "const" in schema and value != schema["const"]:
        errs.append(f"{path}: {value!r} != {schema['const']!r}")
    if "enum" in schema and value not in schema["enum"]:
        errs.append(f"{path}: {value!r} not in {schema['enum']}")
    if "minimum" in schema and _is_type(value, "number") and value < schema["minimum"]:
        errs.append(f"{path}: {value} < {schema['minimum']}")
    if "pattern" in schema and isinstance(value, str) and not re.search(schema["pattern"], value):
        errs.append(f"{path}: {value!r} does not match {schema['pattern']}")
    if isinstance(value, dict):
        props = schema.get("properties", {})
        errs += [f"{path}: missing {k!r}" for k in schema.get("required", []) if k not in value]
        for k, v in value.items():
            if k in props:
                errs += _small_validate(v, props[k], root, f"{path}.{k}")
            elif schema.get("additionalProperties") is False:
                errs.append(f"{path}: unexpected key {k!r}")
            elif isinstance(schema.get("additionalProperties"), dict):
                errs += _small_validate(v, schema["additionalProperties"], root, f"{path}.{k}")
    if isinstance(value, list) and "items" in schema:
        for i, v in enumerate(value):
            errs += _small_validate(v, schema["items"], root, f"{path}[{i}]")
    return errs


def validation_errors(instance) -> list[str]:
    """Schema violations of a metrics.json instance (empty when valid)."""
    try:
        import jsonschema
    except ImportError:
        return _small_validate(instance, SCHEMA, SCHEMA)
    validator = jsonschema.Draft202012Validator(SCHEMA)
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}"
            for e in validator.iter_errors(instance)]


def test_schema_itself_is_valid_json_schema():
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.Draft202012Validator.check_schema(SCHEMA)


def test_small_validator_catches_what_jsonschema_would():
    good = {"n": 3, "n_finite": 3, "mean_error_mrad": 1.0, "median_error_mrad": None,
            "p95_error_mrad": 2.0, "mean_beam_error_mrad": 1.0, "mean_spot_offset_m": 0.1}
    stats = SCHEMA["$defs"]["stats"]
    assert _small_validate(good, stats, SCHEMA) == []
    assert _small_validate({**good, "n": -1}, stats, SCHEMA) == ["$.n: -1 < 0"]
    assert _small_validate({**good, "extra": 1}, stats, SCHEMA) == ["$: unexpected key 'extra'"]
    assert _small_validate({k: v for k, v in good.items() if k != "n"}, stats, SCHEMA) == [
        "$: missing 'n'"]


# ------------------------------------------------------------------------------------------------
# the full report
# ------------------------------------------------------------------------------------------------
def _figure_names() -> list[str]:
    per = ("training_size", "sky_map", "weight_decay", "regimes", "error_over_time")
    return [f"{p}_{h}.png" for p in per for h in HIDS] + ["hybrid_vs_coarse.png"]


#: the field's figures: the error distribution (index.html) and the paper's aggregates (field.html)
FIELD_FIGURES = ["field_error_cdf.png", "field_weight_decay.png", "field_training_size.png",
                 "field_hybrid_vs_coarse.png"]


@pytest.mark.slow
def test_report_writes_every_figure_and_references_it(full_report):
    wd, summary = full_report
    out = wd / "report"
    details = (out / "details.html").read_text()
    field = (out / "field.html").read_text()
    index = (out / "index.html").read_text()
    md = (out / "report.md").read_text()
    assert sorted(Path(f).name for f in summary["figures"]) == sorted(_figure_names()
                                                                      + FIELD_FIGURES)
    for name in _figure_names():
        png = (out / "figures" / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n", name
        # the lab notebook links every figure (lazily loaded), and so does the Markdown
        assert f'loading="lazy" src="figures/{name}"' in details, name
        assert f"](figures/{name})" in md, name
    for name in FIELD_FIGURES[1:]:
        assert f'src="figures/{name}"' in field, name
    assert 'src="figures/field_error_cdf.png"' in index
    # no page embeds images: every page stays small whatever the field's size
    assert "data:image" not in details + field + index
    assert sorted(p.name for p in (out / "figures").iterdir()) == sorted(_figure_names()
                                                                        + FIELD_FIGURES)
    assert not any("Omitted" in n for n in summary["notes"])


@pytest.mark.slow
def test_figures_are_readable_images(full_report):
    import matplotlib.image

    wd, _ = full_report
    for name in _figure_names() + FIELD_FIGURES:
        img = matplotlib.image.imread(wd / "report" / "figures" / name)
        assert img.shape[0] >= 300 and img.shape[1] >= 600, (name, img.shape)


@pytest.mark.slow
def test_tables_in_markdown(full_report):
    wd, _ = full_report
    md = (wd / "report" / "report.md").read_text()
    # accuracy row of the selected coarse preset on the test split (numbers from TEST_ERRORS)
    assert "| AA01 | static-6 ★ | test | 10 | 0.950 | 0.950 | 1.355 | 1.900 | 0.010 |" in md
    assert "| AA01 | hybrid ★ | test | 10 | 0.665 |" in md
    # data summary: counts, dates (2023-01-05 + 39 * 9 days = 2023-12-22), test-to-train
    # distance; rejected rows by reason
    assert "| AA01 | 40 | 20 | 10 | 10 | 2023-01-05 | 2023-12-22 | 12.50 |" in md
    assert "| missing_value | 2 | a required field is empty |" in md
    assert "| sun_below_horizon | 1 |" in md
    # coarse parameters with standard errors
    assert "| joint_1_tilt_n_rad | rad | 0 | 0.002 | 0.0002 | yes |" in md
    # test forward in time: 0.95 * 0.7 + 0.5 (hybrid) and 0.95 + 1.0 (coarse); AB02 has none
    assert ("| AA01 | static-6 | hybrid | 0.01 | 0.560 | 0.665 | 0.800 | 0.950 | 1.165 | 1.950 |"
            in md)
    assert "| AB02 | static-20 | hybrid | 0.01 | 0.600 | 0.700 | 0.850 | 1.000 | n/a | n/a |" in md


@pytest.mark.slow
def test_metrics_values_and_schema(full_report):
    wd, _ = full_report
    metrics = json.loads((wd / "report" / "metrics.json").read_text())
    assert validation_errors(metrics) == []
    a = metrics["heliostats"]["AA01"]
    # hand computation: TEST_ERRORS = 0.5, 0.6, ..., 1.4
    assert a["models"]["static-6"]["splits"]["test"] == {
        "n": 10, "n_finite": 10, "mean_error_mrad": 0.95, "median_error_mrad": 0.95,
        "p95_error_mrad": 1.355, "mean_beam_error_mrad": 1.9, "mean_spot_offset_m": 0.01}
    assert a["models"]["static-6"]["selected"] and not a["models"]["static-20"]["selected"]
    assert a["models"]["hybrid"]["source"] == "hybrid_predictions"
    assert a["split_counts"] == {"train": 20, "validation": 10, "test": 10}
    assert a["test_train_distance_deg"] == 12.5
    assert a["selection"] == {"coarse_preset": "static-6", "model": "hybrid", "weight_decay": 0.01,
                              "val_error_mrad": 0.56, "test_error_mrad": 0.665,
                              "coarse_val_error_mrad": 0.8, "coarse_test_error_mrad": 0.95}
    # forward in time (hand computation from TIME_OFFSET): the kNN test error of the selected
    # preset and of the final model beside their time-split test error; AB02 n/a
    f = a["forward_in_time"]
    assert f["time_split_counts"] == {"train": 20, "validation": 10, "test": 10}
    assert f["coarse"]["model"] == "static-6" and f["final"]["model"] == "hybrid"
    assert f["coarse"]["knn_test"] == a["models"]["static-6"]["splits"]["test"] | {
        "mean_beam_error_mrad": None, "mean_spot_offset_m": None}
    assert f["coarse"]["time_test"]["mean_error_mrad"] == 1.95
    assert f["coarse"]["time_test"]["p95_error_mrad"] == 2.355
    assert (f["final"]["knn_test"]["mean_error_mrad"], f["final"]["time_test"]["mean_error_mrad"],
            f["final"]["time_test"]["median_error_mrad"]) == (0.665, 1.165, 1.165)
    b = metrics["heliostats"]["AB02"]["forward_in_time"]
    assert b["time_split_counts"] == {} and b["final"]["time_test"]["n"] == 0
    assert b["final"]["time_test"]["mean_error_mrad"] is None
    assert b["final"]["knn_test"]["mean_error_mrad"] == 0.665  # its hybrid rows: 0.95 * 0.7
    field = metrics["field"]["forward_in_time"]
    assert field["n_heliostats_time_split"] == 1
    assert (field["final"]["knn_test"]["n"], field["final"]["time_test"]["n"]) == (20, 10)
    assert field["final"]["knn_test"]["mean_error_mrad"] == 0.665
    assert field["final"]["time_test"]["mean_error_mrad"] == 1.165
    assert metrics["data"]["n_measurements"] == 80
    assert metrics["data"]["rejected_by_reason"] == {"missing_value": 2, "sun_below_horizon": 1}
    assert metrics["data"]["first_timestamp"] == "2023-01-05T00:00:00Z"
    assert set(metrics["inputs"]) == {"measurements.parquet", "heliostats.parquet",
                                      "rejected.parquet", "split.parquet", "coarse_params.parquet",
                                      "coarse_predictions.parquet", "regimes.parquet",
                                      "hybrid_predictions.parquet",
                                      "sweep.parquet", "selection.parquet"}
    assert all(re.fullmatch("[0-9a-f]{64}", h) for h in metrics["inputs"].values())


@pytest.mark.slow
def test_metrics_json_is_deterministic(full_report):
    wd, _ = full_report
    text = (wd / "report" / "metrics.json").read_text()
    assert metrics_json(compute_metrics(load_inputs(wd))) == text
    assert text == json.dumps(json.loads(text), sort_keys=True, indent=2) + "\n"
    floats = re.findall(r":\s(-?\d+\.\d+)", text)
    assert floats and all(len(f.split(".")[1]) <= 4 for f in floats)


def test_committed_baseline_matches_schema():
    baseline = json.loads(BASELINE.read_text())
    assert validation_errors(baseline) == []
    assert set(baseline["heliostats"]) == {"BE36", "BF41", "BH35"}


# ------------------------------------------------------------------------------------------------
# partial work directories
# ------------------------------------------------------------------------------------------------
def test_report_after_fit_coarse_names_the_missing_stages(tmp_path):
    wd = make_workdir(tmp_path, "coarse")
    summary = run_report(wd)
    names = sorted(Path(f).name for f in summary["figures"])
    assert names == sorted([f"{p}_{h}.png" for p in ("sky_map", "regimes", "error_over_time")
                            for h in HIDS] + ["field_error_cdf.png"])
    md = (wd / "report" / "report.md").read_text()
    assert f"Omitted: needs sweep.parquet; run `heliocal sweep --workdir {wd}`." in md
    assert ("Omitted: needs selection.parquet or hybrid_predictions.parquet; run "
            f"`heliocal fit-hybrid --workdir {wd}`") in md
    metrics = json.loads((wd / "report" / "metrics.json").read_text())
    assert validation_errors(metrics) == []
    assert metrics["heliostats"]["AB02"]["selection"]["model"] == "static-20"
    assert set(metrics["heliostats"]["AB02"]["models"]) == {"nominal", "static-6", "static-20"}


def test_report_after_ingest_only(tmp_path):
    wd = make_workdir(tmp_path, "ingest")
    summary = run_report(wd)
    assert sorted(Path(f).name for f in summary["figures"]) == [f"sky_map_{h}.png" for h in HIDS]
    index = (wd / "report" / "index.html").read_text()
    assert "No model yet: run <code>heliocal fit-coarse --workdir" in index
    assert "no heliostat has a test error yet" in index
    md = (wd / "report" / "report.md").read_text()
    assert f"No split.parquet: run `heliocal split-knn --workdir {wd}`" in md
    assert f"No predictions: run `heliocal fit-coarse --workdir {wd}`" in md
    metrics = json.loads((wd / "report" / "metrics.json").read_text())
    assert validation_errors(metrics) == []
    assert metrics["heliostats"]["AA01"]["models"] == {}


def test_stale_predictions_are_noted(tmp_path):
    wd = make_workdir(tmp_path, "coarse")
    # rewrite coarse_predictions recording a split hash that is not the current one
    p = pd.read_parquet(wd / "coarse_predictions.parquet")
    write_artifact(p, wd, COARSE_PREDICTIONS, stage="fit-coarse",
                   inputs={"split": wd / "measurements.parquet"})
    summary = run_report(wd)
    assert ("coarse_predictions.parquet is stale: split.parquet changed after it was written "
            "(rerun `heliocal fit-coarse`).") in summary["notes"]


@pytest.mark.slow
def test_figures_of_removed_stages_are_removed(tmp_path):
    wd = make_workdir(tmp_path, "sweep")
    run_report(wd)
    # the sweep's outputs are removed whole (its manifest with them: a listed file that is
    # missing is refused, see test_reliability.py)
    for name in ("sweep.parquet", "selection.parquet", "selected_predictions.parquet",
                 "sweep.manifest.json"):
        (wd / name).unlink(missing_ok=True)
    run_report(wd)
    assert not list((wd / "report" / "figures").glob("training_size_*.png"))


def test_missing_measurements_is_a_stage_input_error(tmp_path):
    with pytest.raises(StageInputError, match=r"measurements.parquet is missing: run `heliocal "
                                              r"ingest SOURCE\.\.\. --workdir"):
        run_report(tmp_path)


def test_sweep_columns_are_found_by_name():
    df = pd.DataFrame(columns=["val_error_mrad", "test_error_mrad", "test_error_median_mrad",
                               "coarse_test_error_mrad", "train_error_mrad_mean",
                               "mean_validation_error_mrad_x"])
    assert _col(df, "test") == "test_error_mrad"
    assert _col(df, "test", "median") == "test_error_median_mrad"
    assert _col(df, "validation") == "val_error_mrad"
    assert _col(df, "train") == "train_error_mrad_mean"
    assert _col(pd.DataFrame(columns=["n_train"]), "test") is None


# ------------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_report_and_compare(runner, tmp_path):
    wd = make_workdir(tmp_path, "coarse")
    res = runner.invoke(app, ["report", "--workdir", str(wd), "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["report"] == str(wd / "report" / "index.html")
    baseline = json.loads((wd / "report" / "metrics.json").read_text())
    (tmp_path / "same.json").write_text(json.dumps(baseline))
    res = runner.invoke(app, ["report", "-w", str(wd), "--compare", str(tmp_path / "same.json")])
    assert res.exit_code == 0, res.stderr
    better = json.loads(json.dumps(baseline))
    better["heliostats"]["AA01"]["models"]["static-6"]["splits"]["test"]["mean_error_mrad"] = 0.5
    (tmp_path / "better.json").write_text(json.dumps(better))
    res = runner.invoke(app, ["report", "-w", str(wd), "--compare", str(tmp_path / "better.json")])
    assert res.exit_code == 1
    assert ("AA01 / static-6 / test: mean_error_mrad 0.5000 -> 0.9500 (+0.4500 mrad, +90.0 %; "
            "allowed +0.0500)") in res.stderr
    res = runner.invoke(app, ["report", "-w", str(wd), "--compare", str(tmp_path / "nope.json")])
    assert res.exit_code == 1
    assert res.stderr.startswith("Error: ") and "nope.json does not exist" in res.stderr


def test_cli_report_without_measurements(runner, tmp_path):
    res = runner.invoke(app, ["report", "-w", str(tmp_path)])
    assert res.exit_code == 1
    assert res.stderr.strip().count("\n") == 0
    assert res.stderr.startswith("Error: ") and "run `heliocal ingest" in res.stderr


def test_cli_report_help(runner):
    res = runner.invoke(app, ["report", "--help"])
    assert res.exit_code == 0
    assert "index.html" in res.stdout and "--compare" in res.stdout


@pytest.mark.slow
def test_alert_list_of_regimes(full_report):
    # the fake regimes above: one detected change (AA01, 2.5 mrad), no renovation
    wd, _ = full_report
    md = (wd / "report" / "report.md").read_text()
    assert "Alert list" in md
    alerts = [line for line in md.splitlines() if "regime 1 starts" in line]
    assert len(alerts) == 1 and "AA01" in alerts[0] and "2.50" in alerts[0]


def test_error_statistics_are_numpy_s_median_percentile_and_mean_to_the_bit():
    """metrics.json's statistics read the median and 95th percentile off one sort; the reference
    is numpy's own ``np.median`` and ``np.percentile(.., 95)`` (method linear), which they must
    equal exactly: lengths 1 to 400 (odd and even, ties, a tiny and a huge scale) and NaNs,
    which count in ``n`` only."""
    from heliocal.pipeline.report.metrics import error_statistics

    rng = np.random.default_rng(7)
    for trial in range(3000):
        n = 1 + trial % 400
        err = rng.gamma(1.5, 0.3, n) * 10.0 ** rng.uniform(-4, 4)
        if trial % 3 == 0:
            err = np.round(err, 1)                       # ties
        if trial % 5 == 0 and n > 2:
            err[rng.choice(n, 2, replace=False)] = np.nan
        got = error_statistics(pd.DataFrame({"error_mrad": err}))
        finite = err[np.isfinite(err)]
        assert (got["n"], got["n_finite"]) == (n, len(finite))
        want = {"mean_error_mrad": finite.mean(), "median_error_mrad": np.median(finite),
                "p95_error_mrad": np.percentile(finite, 95)}
        for key, value in want.items():
            assert got[key] == round(float(value), 4) or (got[key] == 0.0 and round(
                float(value), 4) == 0), (trial, key)
    # and without rounding: the helpers themselves against numpy, bit for bit
    from heliocal.pipeline.report.metrics import _sorted_median, _sorted_quantile

    for n in range(1, 300):
        values = rng.lognormal(0.0, 1.0, n)
        ordered = np.sort(values)
        assert _sorted_median(ordered) == np.median(values), n
        assert _sorted_quantile(ordered, 0.95) == np.percentile(values, 95), n
