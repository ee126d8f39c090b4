"""Whose own figures ``heliocal report`` draws (``--figures``, ``--figures-for``;
pipeline/report/scope.py).

The field tables below are written out here (ids, errors and alerts set by hand), so each expected
set follows from them; the report runs use the hand-made two-heliostat work directory of
tests/test_report.py (AA01 test error 0.95 mrad and on alert for its regime change, AB02 1.0 mrad).
"""

from __future__ import annotations

import re

import pandas as pd
import pytest

from heliocal.pipeline.errors import InputError, ParameterError
from heliocal.pipeline.report.scope import EVERY_HELIOSTAT_UP_TO, figure_scope, study_heliostats
from heliocal.pipeline.stages import report as report_stage
from heliocal.pipeline.stages.report import run_report
from test_report import make_workdir


def _table(n: int, alerted: dict[int, str] | None = None) -> pd.DataFrame:
    """A field table of ``n`` heliostats H0000...: test error 0.1 mrad + 0.001 mrad per index
    (so the last ids are the worst), ``alerted``: index -> alert text."""
    alerted = alerted or {}
    return pd.DataFrame({"heliostat_id": [f"H{i:04d}" for i in range(n)],
                         "test_error_mrad": [0.1 + 0.001 * i for i in range(n)],
                         "alerts": [[alerted[i]] if i in alerted else [] for i in range(n)]})


def test_auto_draws_every_heliostat_up_to_the_limit_and_attention_beyond():
    small = figure_scope(_table(EVERY_HELIOSTAT_UP_TO), "auto")
    assert small.every and len(small.heliostats) == 100 and small.field_note() is None
    big = _table(2000, {3: "no test measurements: its accuracy is unknown", 7: "regime change"})
    first = ["H1999", "H1998", "H1997"]             # what the overview lists first
    scope = figure_scope(big, "auto", figures_for=["H0010"], first=first,
                         study=["H0500", "H0501", "NOT-IN-FIELD"])
    # 2 on alert + 3 listed first + 2 of the study (the third is not in the field) + 1 named
    assert scope.heliostats == {"H0003", "H0007", "H1999", "H1998", "H1997", "H0500", "H0501",
                                "H0010"}
    assert scope.mode == "auto" and not scope.every and scope.n_field == 2000
    assert "Figures of 8 of the 2000 heliostats" in scope.field_note()
    note = scope.page_note("H0042")
    assert "No figures drawn for H0042" in note
    assert "`heliocal report --workdir DIR --incremental --figures-for H0042`" in note
    # the same choice asked for at any size; every heliostat's when asked for
    assert figure_scope(_table(5, {1: "x"}), "attention").heliostats == {"H0001"}
    assert figure_scope(big, "all").every


def test_unknown_heliostats_and_modes_are_refused_with_what_to_do():
    with pytest.raises(InputError, match=r"--figures-for names 'NOPE', 'ZZ', not a heliostat "
                                         r"of W \(the heliostats are listed on the report's "
                                         r"heliostats.html\)"):
        figure_scope(_table(3), "auto", figures_for=["H0001", "ZZ", "NOPE"], workdir="W")
    with pytest.raises(ParameterError, match="The 'figures' parameter of report must be one of "
                                             "{'auto', 'all', 'attention'}. Got 'some' instead."):
        figure_scope(_table(3), "some")


def test_study_heliostats_are_those_with_two_or_more_training_sizes():
    sweep = pd.DataFrame({"heliostat_id": ["A", "A", "B", "B", "C"],
                          "n_train": [10, 20, 30, 30, 5]})
    assert study_heliostats(sweep) == {"A"}
    assert study_heliostats(None) == set()


@pytest.mark.slow
def test_attention_report_draws_only_their_figures_and_adds_one_named_incrementally(
        tmp_path, monkeypatch):
    """At alert 5 mrad only AA01 is on alert (its regime change); with an overview that lists
    no heliostat first, ``--figures attention`` draws AA01's figures only. AB02 keeps its page
    with a note; ``--incremental --figures-for AB02`` then draws AB02's figures and keeps the
    rest."""
    wd = make_workdir(tmp_path, "coarse")    # after fit-coarse: no training-size study
    real_worst = report_stage.worst
    monkeypatch.setattr(report_stage, "worst", lambda table, n=20: real_worst(table, 0))
    first = run_report(wd, workers=1, alert_mrad=5.0, figures="attention")
    names = {p.name for p in (wd / "report" / "figures").glob("*.png")}
    own = lambda hid: {n for n in names if hid in n}  # noqa: E731
    assert first["figure_heliostats"] == 1 and own("AA01") and not own("AB02")
    assert len(first["heliostat_pages"]) == 2
    page = (wd / "report" / "heliostats" / "AB02.html").read_text()
    assert "No figures drawn for AB02" in page and "<img" not in page
    # its numbers stay: the model and why, the parameters, the accuracy table (AB02's test
    # error 1.000 mrad, tests/test_report.py's constants)
    assert "Selected model and why" in page and "<h2>Parameters</h2>" in page
    assert "<b>1.000 mrad</b>test error" in page
    assert re.search(r"--incremental --figures-for AB02</code>", page)
    assert "<img" in (wd / "report" / "heliostats" / "AA01.html").read_text()
    assert "Figures of 1 of the 2 heliostats" in (wd / "report" / "report.md").read_text()

    added = run_report(wd, workers=1, alert_mrad=5.0, figures="attention",
                       figures_for="AB02", incremental=True)   # one id: not its characters
    names2 = {p.name for p in (wd / "report" / "figures").glob("*.png")}
    assert names2 - names == {n.replace("AA01", "AB02") for n in own("AA01")}
    # drawn: AB02's own figures only; kept: everything of the first report
    assert (added["figures_drawn"], added["figures_kept"]) == (len(names2 - names), len(names))
    page = (wd / "report" / "heliostats" / "AB02.html").read_text()
    assert "No figures drawn" not in page and "<img" in page


def test_cli_names_an_unknown_heliostat_in_one_error_line(tmp_path, runner):
    from heliocal.cli.main import app

    wd = make_workdir(tmp_path, "coarse")
    result = runner.invoke(app, ["report", "--workdir", str(wd), "--figures-for", "AA01,NOPE",
                                 "--quiet"])
    assert result.exit_code == 1
    assert result.stderr.strip() == (f"Error: --figures-for names 'NOPE', not a heliostat of {wd} "
                                     "(the heliostats are listed on the report's "
                                     "heliostats.html)")
    result = runner.invoke(app, ["report", "--workdir", str(wd), "--figures", "some"])
    assert result.exit_code == 2 and "'some' is not one of" in result.stderr


def test_workers_get_the_figures_in_chunks_of_at_most_fifty(monkeypatch):
    """8,000 figures on 2 workers went as 8 chunks of 1,000 tasks, each task with its
    heliostat's rows (a gigabyte per worker); now at most FIGURES_PER_CHUNK (50) per chunk:
    8,000 / (2 x 80) = 50. Few figures keep the 4 chunks per worker."""
    from types import SimpleNamespace

    from heliocal.pipeline.report.render import FigureTask
    from heliocal.pipeline.stages import report_figures

    calls = []

    def fake_map(func, tasks, workers, chunks_per_worker, torch_threads=True):
        assert not torch_threads    # figures run no torch: torch is not imported for them
        calls.append((len(tasks), workers, chunks_per_worker))
        return [(b"png", None)] * len(tasks)

    monkeypatch.setattr(report_figures, "map_tasks", fake_map)
    for n in (8000, 120):
        tasks = [FigureTask("sky_map", f"sky_map_H{i:04d}.png", "c", f"H{i:04d}", {"i": i})
                 for i in range(n)]
        drawn, counts = report_figures.drawn_or_kept(SimpleNamespace(extra={}), None, tasks, 2,
                                                     incremental=False)
        assert counts == {"drawn": n, "kept": 0} and len(drawn) == n
    assert calls == [(8000, 2, 80), (120, 2, 4)]
