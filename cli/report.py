"""``heliocal report``: HTML/Markdown report, figures and metrics.json (see docs/report.md)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from heliocal.pipeline.vocabulary import DEFAULT_ALERT_MRAD, ReportFigures
from heliocal.cli.app import (DEFAULT_WORKDIR, JsonFlag, QuietFlag, Workdir, Workers, command,
                              emit, fail, fmt_number, incremental_line, stdout)

__all__ = ["report_cmd"]


def _human(summary: dict) -> None:
    if incremental_line(summary):
        return
    for h in summary["heliostats"]:
        stdout.print(f"{h['heliostat_id']}: {h['model'] or 'no model'}, test mean "
                     f"{fmt_number(h['test_mean_error_mrad'])} mrad, p95 "
                     f"{fmt_number(h['test_p95_error_mrad'])} mrad", markup=False)
    for note in summary["notes"]:
        stdout.print(f"note: {note}", markup=False)
    f = summary.get("field_summary") or {}
    if f:
        stdout.print(f"field: {f['n_calibrated']} of {f['n_heliostats']} heliostats calibrated "
                     f"({f['n_hybrid']} hybrid, " + (f"{f['n_gp']} GP, " if f.get("n_gp") else "")
                     + f"{f['n_coarse']} coarse); median test error "
                     f"{fmt_number(f['median_test_error_mrad'])} mrad, p95 "
                     f"{fmt_number(f['p95_test_error_mrad'])} mrad; {f['n_on_alert']} on alert",
                     markup=False)
    kept = f", {summary['figures_kept']} kept from the last report" if summary.get(
        "figures_kept") else ""
    pages = len(summary.get("heliostat_pages", []))
    scope = summary.get("figure_heliostats")
    scope = f" ({scope} with their own figures)" if scope is not None and scope < pages else ""
    stdout.print(f"wrote {summary['report']} ({len(summary['figures'])} figures{kept}, "
                 f"{pages} heliostat pages{scope}), "
                 f"{summary['markdown']}, {summary['metrics']}", markup=False)


@command("report", writes=True)
def report_cmd(
    workdir: Workdir = DEFAULT_WORKDIR,
    compare: Annotated[Optional[Path], typer.Option(
        "--compare", help="Baseline metrics.json: exit 1 with the differences when accuracy "
                          "regressed beyond tolerance (docs/report.md).",
        dir_okay=False)] = None,
    workers: Workers = None,
    alert_mrad: Annotated[float, typer.Option(
        "--alert-mrad", min=0.0, help="A heliostat whose model (the one aim uses) has a mean test "
                                      "error above this is on alert [mrad].")] = DEFAULT_ALERT_MRAD,
    floor_mrad: Annotated[Optional[float], typer.Option(
        "--floor-mrad", min=0.0, help="Measurement floor drawn on the error distribution [mrad] "
                                      "(default: the simulator's noise floor for a simulated "
                                      "field, else none).")] = None,
    incremental: Annotated[bool, typer.Option(
        "--incremental", help="Keep the last report as it is when nothing it is made from "
                              "changed; else draw only the figures whose data changed since "
                              "the last report and keep the others' images (pages, tables "
                              "and metrics are computed again).")] = False,
    figures: Annotated[ReportFigures, typer.Option(
        "--figures", help="Whose own figures to draw: all, attention (on alert, listed first "
                          "on the overview, in the sweep's training-size study) or auto (all "
                          "up to 100 heliostats, else attention); every heliostat keeps its "
                          "page.")] = ReportFigures.auto,
    figures_for: Annotated[Optional[list[str]], typer.Option(
        "--figures-for", help="Also draw this heliostat's figures (repeat, or comma-separated "
                              "ids); with --incremental the others' are kept.")] = None,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Write DIR/report/: index.html (the field overview), heliostats/<id>.html, field.html,
    details.html, report.md, figures/*.png and metrics.json, from the artifacts."""
    from heliocal.pipeline.report.regression import compare_metrics, format_report, load_metrics
    from heliocal.pipeline.stages.report import run_report

    named = [h.strip() for item in figures_for or () for h in item.split(",") if h.strip()]
    summary = run_report(workdir, workers=workers, alert_mrad=alert_mrad, floor_mrad=floor_mrad,
                         incremental=incremental, figures=figures.value, figures_for=named)
    if compare is not None:
        try:
            diffs = compare_metrics(load_metrics(summary["metrics"]), load_metrics(compare))
        except ValueError as exc:
            fail(str(exc))
        summary["regressions"] = diffs
    emit(summary, json_, _human)
    if compare is not None and summary["regressions"]:
        print(format_report(summary["regressions"], summary["metrics"], str(compare)),
              file=sys.stderr)
        raise typer.Exit(1)
