"""The report's field-prior page (``field_prior.html``, issue 34).

Work directories are the hand-made ones of tests/test_report.py (two heliostats, AA01 selects
static-6 and AB02 static-20) with a hand-written field_prior.parquet and the prior's columns of
coarse_params.parquet, so every number on the page follows from the constants below:

* PRIOR: static-6's prior of the group juelich / linear / default (two parameters with a field
  prior, one that keeps the default prior: no scale); the page shows mean and scale in mrad
  (x 1e3) and keeps the artifact's value in ``data-v``;
* SHRINKAGE: AA01's shrinkage per parameter; its median over the two parameters with a prior is
  (0.2 + 0.9) / 2 = 0.55, the largest 0.9 (joint_1_tilt_n_rad).
"""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, FIELD_PRIOR, HELIOSTATS
from heliocal.pipeline.artifacts.store import read_artifact
from heliocal.pipeline.stages.report import run_report
from test_report import HIDS, N, _write, make_workdir

GROUP = ("juelich", "linear", "default")
#: parameter -> (mean [rad], scale [rad] or NaN, heliostats)
PRIOR = {"joint_1_tilt_e_rad": (0.00123, 0.00045, 14), "joint_1_tilt_n_rad": (-0.0021, 0.0008, 9),
         "joint_2_tilt_u_rad": (0.0, np.nan, 5)}
SHRINKAGE = {"joint_1_tilt_e_rad": 0.2, "joint_1_tilt_n_rad": 0.9, "joint_2_tilt_u_rad": np.nan}


def _with_prior(root, stage: str = "coarse"):
    wd = make_workdir(root, stage)
    _write(pd.DataFrame({"heliostat_id": list(HIDS), "n_measurements": [N, N],
                         "kinematic_type": GROUP[0], "actuator_type": GROUP[1],
                         "properties_source": "default geometry"}), wd, HELIOSTATS)
    p = read_artifact(wd, COARSE_PARAMS)
    aa01 = (p["heliostat_id"] == "AA01").to_numpy()
    p["prior_mean"] = np.where(aa01, p["parameter"].map(lambda n: PRIOR[n][0]), np.nan)
    p["prior_sigma"] = np.where(aa01, p["parameter"].map(lambda n: PRIOR[n][1]), np.nan)
    p["prior_shrinkage"] = np.where(aa01, p["parameter"].map(SHRINKAGE), np.nan)
    p["own_noise_mrad"] = np.where(aa01, 0.12, np.nan)
    p["prior_noise_mrad"] = np.where(aa01, 0.12, np.nan)
    _write(p, wd, COARSE_PARAMS)
    rows = [{"kinematic_type": GROUP[0], "actuator_type": GROUP[1], "geometry_source": GROUP[2],
             "preset": "static-6", "parameter_index": k, "parameter": name, "unit": "rad",
             "mean": mean, "scale": scale, "n_heliostats": n, "noise_mrad": 0.16,
             "spatial": False, "expected_error_mrad": 1.5, "nominal_error_mrad": 9.0,
             "n_evaluated": 12}
            for k, (name, (mean, scale, n)) in enumerate(PRIOR.items())]
    _write(pd.DataFrame(rows), wd, FIELD_PRIOR)
    return wd


@pytest.fixture(scope="module")
def prior_report(tmp_path_factory):
    wd = _with_prior(tmp_path_factory.mktemp("prior"))
    return wd, run_report(wd, workers=1)


def test_the_page_shows_field_prior_parquets_numbers(prior_report):
    wd, summary = prior_report
    page = (wd / "report" / "field_prior.html").read_text()
    assert summary["field_prior"] == str(wd / "report" / "field_prior.html")
    table = read_artifact(wd, FIELD_PRIOR)
    shown = table[table["scale"].notna()]
    assert len(shown) == 2
    for _, r in shown.iterrows():
        row = re.search(rf'<tr data-parameter="{r["parameter"]}" data-preset="static-6">(.*?)'
                        r"</tr>", page).group(1)
        cells = re.findall(r'<td(?: data-v="([^"]*)")?>([^<]*)</td>', row)
        # preset, parameter, unit, mean, scale, heliostats, spatial
        assert [c[1] for c in cells[:3]] == ["static-6", r["parameter"], "mrad"]
        assert float(cells[3][0]) == r["mean"] and float(cells[4][0]) == r["scale"]
        assert cells[3][1] == f"{r['mean'] * 1e3:.3f}" and cells[4][1] == f"{r['scale'] * 1e3:.3f}"
        assert int(cells[5][1]) == r["n_heliostats"]
    # the parameter without enough heliostats keeps the default prior, and the page says so
    assert "Default prior (fewer than 8 determining heliostats): joint_2_tilt_u_rad." in page
    assert "leave-one-out" in page and "at least 8 heliostats" in page
    assert "docs/field_prior.md" in page


def test_the_page_shows_each_heliostats_shrinkage(prior_report):
    wd, summary = prior_report
    page = (wd / "report" / "field_prior.html").read_text()
    row = re.search(r'<a href="heliostats/AA01.html">AA01</a></td>(.*?)</tr>', page).group(1)
    cells = re.findall(r'<td(?: data-v="([^"]*)")?>([^<]*)</td>', row)
    # model, training rows, own noise, prior noise, median, largest, largest for
    assert cells[0][1] == "static-6" and cells[1][1] == "20"
    assert float(cells[4][0]) == pytest.approx(0.55, abs=1e-12)
    assert float(cells[5][0]) == pytest.approx(0.9, abs=1e-12)
    assert cells[6][1] == "joint_1_tilt_n_rad"
    assert "AB02" not in page.split("<h3>Shrinkage per heliostat</h3>")[1].split("<h2>")[0]
    figures = {f.rsplit("/", 1)[1] for f in summary["figures"]}
    assert {"field_prior_juelich_linear_default.png",
            "field_prior_shrinkage_juelich_linear_default.png"} <= figures
    for name in ("field_prior_juelich_linear_default.png",
                 "field_prior_shrinkage_juelich_linear_default.png"):
        assert (wd / "report" / "figures" / name).read_bytes()[:4] == b"\x89PNG"
        assert f'src="figures/{name}"' in page
    # every page links to it
    for name in ("index.html", "heliostats.html", "field.html", "details.html",
                 "heliostats/AA01.html"):
        nav = (wd / "report" / name).read_text().split("</nav>")[0]
        prefix = "../" if "/" in name else ""
        assert f'<a href="{prefix}field_prior.html">Field prior</a>' in nav


def test_no_page_without_a_field_prior(tmp_path):
    wd = make_workdir(tmp_path, "coarse")
    summary = run_report(wd, workers=1)
    assert summary["field_prior"] is None
    assert not (wd / "report" / "field_prior.html").exists()
    assert "Field prior" not in (wd / "report" / "index.html").read_text()
    # an empty field_prior.parquet (fit-coarse --prior field that found no prior) gives none
    _write(pd.DataFrame(columns=FIELD_PRIOR.column_names()), wd, FIELD_PRIOR)
    assert run_report(wd, workers=1)["field_prior"] is None


def test_an_incremental_report_keeps_the_prior_figures_until_a_shrinkage_moves(tmp_path):
    wd = _with_prior(tmp_path)
    first = run_report(wd, workers=1)
    again = run_report(wd, workers=1, incremental=True)
    assert again["figures_drawn"] == 0 and again["figures_kept"] == len(first["figures"])
    p = read_artifact(wd, COARSE_PARAMS)
    p.loc[p["parameter"] == "joint_1_tilt_e_rad", "prior_shrinkage"] = np.where(
        p.loc[p["parameter"] == "joint_1_tilt_e_rad", "heliostat_id"] == "AA01", 0.3, np.nan)
    _write(p, wd, COARSE_PARAMS)
    moved = run_report(wd, workers=1, incremental=True)
    # both prior figures draw the shrinkage; nothing else reads it
    assert moved["figures_drawn"] == 2


def test_a_large_group_is_drawn_in_bins_of_training_rows():
    from heliocal.pipeline.report.prior_figures import MAX_HEATMAP_ROWS, shrinkage_rows

    # 130 heliostats with 1..130 training rows, their ids in another order than their rows
    # (H(37 n mod 131)), shrinkage 1 / rows on one parameter: np.array_split makes 10 bins of 3
    # then 50 of 2, fewest rows first
    n = np.arange(130, 0, -1)
    points = pd.DataFrame({"heliostat_id": [f"H{37 * k % 131:03d}" for k in n],
                           "parameter_index": 4, "n_train": n, "prior_shrinkage": 1.0 / n})
    labels, matrix, cols = shrinkage_rows(points)
    assert MAX_HEATMAP_ROWS == 60 and len(labels) == 60 and cols == [4]
    assert labels[0] == "1-3 rows (3)" and labels[-1] == "129-130 rows (2)"
    assert matrix[0, 0] == pytest.approx(1 / 2) and matrix[-1, 0] == pytest.approx(
        (1 / 129 + 1 / 130) / 2)
    # a small group: one row per heliostat, fewest rows first
    labels, matrix, _ = shrinkage_rows(points.iloc[-5:])
    assert labels == ["H037 (1)", "H074 (2)", "H111 (3)", "H017 (4)", "H054 (5)"]
    np.testing.assert_allclose(matrix[:, 0], 1.0 / np.arange(1, 6))


# ------------------------------------------------------------------------------------------------
# the training-size study with and without the prior
# ------------------------------------------------------------------------------------------------
#: AA01's study rows of static-6 (its shown preset; 20 training rows in coarse_params):
#: n_train -> (test error with the prior, without) [mrad]. AB02 (static-20, not the shown
#: preset's curve: it has no static-6+no-field-prior rows) is left out of the figure.
STUDY = {5: (1.4, 2.3), 10: (1.2, 1.5), 20: (1.0, 1.05)}


def _with_study(root, with_curves: bool = True):
    from heliocal.pipeline.artifacts.schemas import SWEEP
    from test_report import _write as write_schema

    wd = _with_prior(root, "sweep")
    sweep = read_artifact(wd, SWEEP)
    rows = []
    for n, (with_prior, without) in STUDY.items():
        rows.append({"heliostat_id": "AA01", "model": "static-6", "n_train": n,
                     "test_error_mrad": with_prior, "val_error_mrad": with_prior})
        if with_curves:
            rows.append({"heliostat_id": "AA01", "model": "static-6+no-field-prior",
                         "n_train": n, "test_error_mrad": without, "val_error_mrad": without})
        rows.append({"heliostat_id": "AB02", "model": "static-6", "n_train": n,
                     "test_error_mrad": 9.0, "val_error_mrad": 9.0})
    rows = pd.DataFrame(rows)
    rows = rows.assign(weight_decay=np.nan, seed=0, base_preset="static-6", wall_time_s=0.0,
                       train_error_mrad=rows["test_error_mrad"] / 2,
                       train_median_error_mrad=rows["test_error_mrad"] / 2)
    write_schema(pd.concat([sweep, rows], ignore_index=True), wd, SWEEP)
    return wd


@pytest.mark.slow   # the report stage end to end, two and three times
def test_the_page_draws_the_studys_curves_with_and_without_the_prior(tmp_path):
    from heliocal.pipeline.artifacts.schemas import SWEEP
    from heliocal.pipeline.report.prior_figures import size_medians
    from heliocal.pipeline.report.prior_page import prior_groups, study_curves
    from heliocal.pipeline.stages.coarse_prior import heliostat_groups, with_deviations
    from heliocal.pipeline.report.field_figures import training_size_frame
    from heliocal.pipeline.report.metrics import WITHOUT_FIELD_PRIOR
    from heliocal.pipeline.stages.study_prior import NO_FIELD_PRIOR

    wd = _with_study(tmp_path)
    summary = run_report(wd, workers=1)
    page = (wd / "report" / "field_prior.html").read_text()
    name = "field_prior_sizes_juelich_linear_default.png"
    assert (wd / "report" / "figures" / name).read_bytes()[:4] == b"\x89PNG"
    assert f'src="figures/{name}"' in page and "with and without the prior" in page
    assert "each group above draws the two curves" in page
    assert name in {f.rsplit("/", 1)[1] for f in summary["figures"]}
    # what the figure draws: AA01's two curves (the report's name of the model is the stage's)
    assert "+" + NO_FIELD_PRIOR == WITHOUT_FIELD_PRIOR
    # field.html's training-size figure leaves them to this page (static-6 with the prior stays)
    models = set(training_size_frame(read_artifact(wd, SWEEP))["model"])
    assert "static-6" in models and not any(m.endswith(WITHOUT_FIELD_PRIOR) for m in models)
    group = prior_groups(read_artifact(wd, FIELD_PRIOR),
                         with_deviations(read_artifact(wd, COARSE_PARAMS)),
                         heliostat_groups(read_artifact(wd, HELIOSTATS)))[0]
    curves = study_curves(group, read_artifact(wd, SWEEP))
    assert set(curves["heliostat_id"]) == {"AA01"} and (curves["full"] == 20).all()
    medians = size_medians(curves).set_index(["prior", "n_train"])["median"]
    # below the full size (20 rows, a diamond of its own): the sizes 5 and 10 of STUDY
    assert medians.to_dict() == {("field", 5): 1.4, ("field", 10): 1.2,
                                 ("none", 5): 2.3, ("none", 10): 1.5}
    # drawn once, then kept by the incremental report until a study number moves
    drawn = (wd / "report" / "figures" / name).read_bytes()
    again = run_report(wd, workers=1, incremental=True)
    assert again["figures_drawn"] == 0 and again["figures_kept"] == len(summary["figures"])
    assert (wd / "report" / "figures" / name).read_bytes() == drawn
    sweep = read_artifact(wd, SWEEP)
    moved = (sweep["model"] == "static-6+no-field-prior") & (sweep["n_train"] == 5)
    sweep.loc[moved, "test_error_mrad"] = 2.2
    from test_report import _write as write_schema
    write_schema(sweep, wd, SWEEP)
    assert run_report(wd, workers=1, incremental=True)["figures_drawn"] >= 1
    assert (wd / "report" / "figures" / name).read_bytes() != drawn   # drawn again


@pytest.mark.slow   # the report stage end to end, two and three times
def test_no_curves_without_the_studys_fits_without_the_prior_or_without_a_prior(tmp_path):
    wd = _with_study(tmp_path / "a", with_curves=False)
    summary = run_report(wd, workers=1)
    page = (wd / "report" / "field_prior.html").read_text()
    assert "field_prior_sizes_" not in page and "<h3>Training size" not in page
    assert not any("field_prior_sizes_" in f for f in summary["figures"])
    assert "no curves with and without the prior here" in page
    # no field prior: no page, no figure, even with the study's rows in sweep.parquet
    plain = make_workdir(tmp_path / "b", "sweep")
    summary = run_report(plain, workers=1)
    assert summary["field_prior"] is None
    assert not any("field_prior_sizes_" in f for f in summary["figures"])
