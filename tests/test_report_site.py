"""The plant's report pages of ``heliocal report``: field overview, heliostat pages, escaping of
input text, figures drawn in worker processes, the measurement floor.

Work directories are the hand-made ones of tests/test_report.py (two heliostats, errors chosen by
hand), so every number below follows from the constants there.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.artifacts.schemas import all_schemas
from heliocal.pipeline.artifacts.store import write_artifact
from heliocal.pipeline.report.field import svg_field_map, worst
from heliocal.pipeline.stages import report as report_stage
from heliocal.pipeline.stages import report_figures
from heliocal.pipeline.stages.aim import aim_models
from heliocal.pipeline.stages.report import run_report
from test_report import COARSE_TEST, COARSE_VAL, HIDS, make_workdir

PAGES = ("index.html", "heliostats.html", "field.html", "details.html")


@pytest.fixture(scope="module")
def coarse_report(tmp_path_factory):
    """A report after fit-coarse, with the alert threshold between the two heliostats' test errors
    (AA01 0.95 mrad, AB02 1.0 mrad)."""
    wd = make_workdir(tmp_path_factory.mktemp("site"), "coarse")
    return wd, run_report(wd, alert_mrad=0.97, workers=1)


@pytest.mark.slow
def test_overview_numbers_are_the_errors_aim_uses(coarse_report):
    wd, summary = coarse_report
    choices = aim_models(wd)
    # the report's per-heliostat error is aim's, which is coarse_params' (the hand-set constants)
    assert {h: c["test_error_mrad"] for h, c in choices.items()} == COARSE_TEST
    s = summary["field_summary"]
    assert s["n_heliostats"] == 2 and s["n_calibrated"] == 2
    assert (s["n_coarse"], s["n_hybrid"]) == (2, 0)
    assert s["presets"] == {"static-20": 1, "static-6": 1}
    # median of (0.95, 1.0); numpy's linear 95th percentile: 0.95 + 0.95 * 0.05
    assert s["median_test_error_mrad"] == pytest.approx(0.975, abs=1e-12)
    assert s["p95_test_error_mrad"] == pytest.approx(0.9975, abs=1e-12)
    # AB02 is above the threshold; AA01 is on alert for the regime change the fixture's
    # regimes.parquet holds (detected, 2.5 mrad, into its latest regime: report.regimes)
    assert (s["n_above_alert"], s["n_on_alert"]) == (1, 2)
    index = (wd / "report" / "index.html").read_text()
    assert "<b>0.975 mrad</b>median test error" in index
    # worst first: AB02 (1.0) is rank 1, AA01 (0.95) rank 2; beside the test error the one
    # forward in time (AA01: its coarse preset's time_error_mrad, 0.95 + 1.0; AB02: n/a)
    rows = re.findall(r"<tr><td>(\d)</td><td class=\"t\"><a href=\"heliostats/(\w+)\.html\">"
                      r"\w+</a></td><td>([\d.]+)</td><td>([\d.]+|n/a)</td><td>([\d.]+)</td>",
                      index)
    assert rows == [("1", "AB02", "1.000", "n/a", "0.850"),
                    ("2", "AA01", "0.950", "1.950", "0.800")]
    assert 'title="test error 1.00 mrad above 0.97 mrad"' in index
    assert "regime change detected on" in index and "(2.5 mrad)" in index
    # the map: one link per heliostat, those on alert ringed in red
    assert re.search(r'<a href="heliostats/AB02.html"><circle [^>]*stroke="#d00000"', index)
    assert re.search(r'<a href="heliostats/AA01.html"><circle [^>]*stroke="#d00000"', index)
    assert 'src="figures/field_error_cdf.png"' in index


@pytest.mark.slow
def test_index_stays_small_and_embeds_no_image(coarse_report):
    wd, _ = coarse_report
    index = (wd / "report" / "index.html").read_bytes()
    assert b"data:image" not in index and len(index) < 60_000


@pytest.mark.slow
def test_every_heliostat_has_its_page(coarse_report):
    wd, summary = coarse_report
    out = wd / "report"
    assert sorted(Path(p).name for p in summary["heliostat_pages"]) == [f"{h}.html" for h in HIDS]
    page = (out / "heliostats" / "AA01.html").read_text()
    assert '<a href="../index.html">Field overview</a>' in page
    assert '<a href="AB02.html">next →</a>' in page
    # its figures (one folder up), its parameters with standard errors, its accuracy table
    for name in ("sky_map_AA01.png", "error_over_time_AA01.png"):
        assert f'src="../figures/{name}"' in page and (out / "figures" / name).is_file()
    assert ("<tr><td>joint_1_tilt_n_rad</td><td>rad</td><td>0</td><td>0.002</td>"
            "<td>0.0002</td><td>yes</td></tr>") in page
    assert "<tr><td>static-6 ★</td><td>test</td><td>10</td><td>0.950</td>" in page
    assert "aim uses fit-coarse&#x27;s selected preset static-6" in page
    assert "AB02" in (out / "heliostats" / "AB02.html").read_text()
    # the list of all heliostats links every page
    listing = (out / "heliostats.html").read_text()
    assert all(f'href="heliostats/{h}.html"' in listing for h in HIDS)


@pytest.mark.slow
def test_pages_of_heliostats_no_longer_present_are_removed(tmp_path):
    wd = make_workdir(tmp_path, "coarse")
    run_report(wd, workers=1)
    stale = wd / "report" / "heliostats" / "GONE.html"
    stale.write_text("old")
    run_report(wd, workers=1)
    assert not stale.exists()


@pytest.mark.slow
def test_input_text_is_escaped(tmp_path):
    """A heliostat id with markup (ingest refuses it; the report must not trust that) shows as
    text on every page, its file name is the id itself and links to it are percent-encoded."""
    evil = '<script>alert("x")'
    wd = make_workdir(tmp_path, "coarse")
    for schema in all_schemas():
        if (wd / schema.filename).is_file():
            df = pd.read_parquet(wd / schema.filename)
            df["heliostat_id"] = df["heliostat_id"].replace({"AA01": evil})
            write_artifact(df, wd, schema, stage=schema.producer, inputs={})
    run_report(wd, workers=1)
    out = wd / "report"
    assert (out / "heliostats" / f"{evil}.html").is_file()
    texts = {p: (out / p).read_text() for p in PAGES}
    texts["page"] = (out / "heliostats" / f"{evil}.html").read_text()
    texts["md"] = (out / "report.md").read_text()
    for where, text in texts.items():
        assert "<script>alert" not in text, where
    assert "&lt;script&gt;alert(&quot;x&quot;)" in texts["index.html"]
    assert 'href="heliostats/%3Cscript%3Ealert%28%22x%22%29.html"' in texts["index.html"]
    assert "<h1>Heliostat &lt;script&gt;alert(&quot;x&quot;)</h1>" in texts["page"]


def test_field_map_escapes_and_orders():
    table = pd.DataFrame({"heliostat_id": ["A&B", "C"], "e_m": [0.0, 10.0], "n_m": [50.0, 60.0],
                          "model": ["coarse", None], "variant": [None, None],
                          "preset": ["static-6", None], "val_error_mrad": [0.5, np.nan],
                          "test_error_mrad": [0.6, np.nan], "alerts": [[], ["no <model>"]],
                          "page": ["A&B.html", "C.html"]})
    svg = svg_field_map(table, (0.0, 0.0))
    assert "<title>A&amp;B: test 0.600 mrad, validation 0.500 mrad (coarse static-6)</title>" in svg
    assert "ALERT: no &lt;model&gt;" in svg and 'href="heliostats/A%26B.html"' in svg
    # a heliostat without a test error counts as worst (it cannot be judged)
    assert list(worst(table, 1)["heliostat_id"]) == ["C"]


@pytest.mark.slow
def test_figures_drawn_in_worker_processes_equal_those_drawn_here(tmp_path, monkeypatch):
    wd = make_workdir(tmp_path, "sweep")
    here = run_report(wd, tmp_path / "here", workers=1)
    monkeypatch.setattr(report_figures, "MIN_PARALLEL_FIGURES", 0)
    pool = run_report(wd, tmp_path / "pool", workers=2)
    # 13 figures of the sweep workdir plus one regime figure per heliostat (its regimes.parquet)
    names = sorted(Path(f).name for f in here["figures"])
    assert names == sorted(Path(f).name for f in pool["figures"]) and len(names) == 15
    for n in names:  # the same matplotlib draws the same pixels, wherever it runs
        assert (tmp_path / "here" / "figures" / n).read_bytes() == \
            (tmp_path / "pool" / "figures" / n).read_bytes(), n
    assert (tmp_path / "here" / "index.html").read_text() == \
        (tmp_path / "pool" / "index.html").read_text()


@pytest.mark.slow
def test_measurement_floor(tmp_path):
    wd = make_workdir(tmp_path, "coarse")
    assert report_stage.measurement_floor(wd, None) == (None, "")
    run_report(wd, workers=1)
    assert "Measurement floor: unknown" in (wd / "report" / "index.html").read_text()
    run_report(wd, workers=1, floor_mrad=0.3)
    assert ("Measurement floor: 0.300 mrad (given with --floor-mrad)"
            in (wd / "report" / "index.html").read_text())
    # sources from `heliocal simulate`: the median of its heliostats' noise floors
    field = tmp_path / "field"
    field.mkdir()
    (field / "ground_truth.json").write_text(json.dumps({"heliostats": {
        "X1": {"noise_floor_mrad": 0.1}, "X2": {"noise_floor_mrad": 0.4},
        "X3": {"noise_floor_mrad": 0.2}}}))
    manifest = wd / "ingest.manifest.json"
    m = json.loads(manifest.read_text())
    m.setdefault("options", {})["sources"] = [str(field / "calibration_log.csv")]
    manifest.write_text(json.dumps(m))
    floor, source = report_stage.measurement_floor(wd, None)
    assert floor == pytest.approx(0.2) and "noise floor" in source


def test_index_of_2000_heliostats_stays_under_2_mb():
    """The overview's size grows with the map (one SVG circle per heliostat), not with figures:
    2,000 heliostats on alert with long alert texts (the worst case for the map's tooltips)."""
    from heliocal.pipeline.report.field import field_summary
    from heliocal.pipeline.report.site import index_html

    rng = np.random.default_rng(0)
    n = 2000
    ids = [f"C{k // 100:03d}SA{k % 100:02d}" for k in range(n)]
    table = pd.DataFrame({
        "heliostat_id": ids, "e_m": rng.uniform(-800, 800, n), "n_m": rng.uniform(50, 1200, n),
        "model": "hybrid", "variant": "hybrid-octaves", "preset": "static-20", "source": "sweep",
        "weight_decay": 1e-3, "val_error_mrad": rng.uniform(0.3, 3, n),
        "test_error_mrad": rng.uniform(0.3, 3, n), "n_measurements": 400, "n_test": 40,
        "alerts": [["test error 2.50 mrad above 2 mrad", "large corrections of the nominal "
                    "geometry (axis_1_initial_angle_rad +0.2366 rad; axis_2_offset_m -0.1 m)"]] * n,
        "page": [f"{h}.html" for h in ids]})
    page = index_html("t", "s", field_summary(table), table, worst(table),
                      svg_field_map(table, (0.0, 0.0)), None, "no figure", "floor", [])
    assert page.count("<circle") >= n and len(page.encode()) < 2 * 2**20


@pytest.mark.slow
def test_extra_alerts_join_the_field_table(coarse_report):
    """Alerts of other detectors (regime changes, say) are marked like the report's own."""
    from heliocal.pipeline.report.field import field_summary, field_table
    from heliocal.pipeline.report.inputs import load_inputs
    from heliocal.pipeline.report.metrics import compute_metrics

    wd, _ = coarse_report
    inp = load_inputs(wd)
    table = field_table(inp, compute_metrics(inp), aim_models(wd), alert_mrad=0.97,
                        extra_alerts={"AA01": ["regime change on 2023-06-01"]})
    alerts = dict(zip(table["heliostat_id"], table["alerts"]))
    assert alerts == {"AA01": ["regime change on 2023-06-01"],
                      "AB02": ["test error 1.00 mrad above 0.97 mrad"]}
    assert field_summary(table, alert_mrad=0.97)["n_on_alert"] == 2


def test_selected_weight_decay_is_not_rounded_away(tmp_path):
    """metrics.json keeps 4 decimals (1e-5 -> 0); the figure's 'selected' line and the selection
    table take the sweep's own value."""
    from heliocal.pipeline.report.inputs import load_inputs
    from heliocal.pipeline.report.metrics import compute_metrics, final_models
    from heliocal.pipeline.report.pages import build_report, figure_tasks
    from heliocal.pipeline.report.render import heliostat_figure_plan

    wd = make_workdir(tmp_path, "sweep")
    schema = next(s for s in all_schemas() if s.name == "selection")
    sel = pd.read_parquet(wd / schema.filename).assign(weight_decay=1e-5)
    write_artifact(sel, wd, schema, stage=schema.producer, inputs={})
    inp = load_inputs(wd)
    metrics = compute_metrics(inp)
    assert metrics["heliostats"]["AA01"]["selection"]["weight_decay"] == 0.0  # rounded
    plan = heliostat_figure_plan(inp, metrics, final_models(inp))
    wd_args = {b[1].heliostat: b[1].args["weight_decay"] for b in plan
               if b[0] == "task" and b[1].kind == "weight_decay"}
    assert wd_args == {"AA01": 1e-5, "AB02": 1e-5}
    blocks = build_report(inp, metrics)
    table = next(b for b in blocks if b[0] == "table" and "weight decay" in b[1])
    assert [r[3] for r in table[2]] == ["1e-05", "1e-05"]
    assert figure_tasks(blocks)
