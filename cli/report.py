"""``heliocal report``: HTML/Markdown report, figures and metrics.json (see docs/report.md)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from heliocal.cli.app import DEFAULT_WORKDIR, JsonFlag, QuietFlag, Workdir, command, emit, fail, stdout

__all__ = ["report_cmd"]


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def _human(summary: dict) -> None:
    for h in summary["heliostats"]:
        stdout.print(f"{h['heliostat_id']}: {h['model'] or 'no model'}, test mean "
                     f"{_fmt(h['test_mean_error_mrad'])} mrad, p95 "
                     f"{_fmt(h['test_p95_error_mrad'])} mrad", markup=False)
    for note in summary["notes"]:
        stdout.print(f"note: {note}", markup=False)
    stdout.print(f"wrote {summary['report']} ({len(summary['figures'])} figures), "
                 f"{summary['markdown']}, {summary['metrics']}", markup=False)


@command("report")
def report_cmd(
    workdir: Workdir = DEFAULT_WORKDIR,
    compare: Annotated[Optional[Path], typer.Option(
        "--compare", help="Baseline metrics.json: exit 1 with the differences when accuracy "
                          "regressed beyond tolerance (docs/report.md).",
        dir_okay=False)] = None,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Write DIR/report/ (index.html, report.md, figures/*.png, metrics.json) from the artifacts."""
    from heliocal.pipeline.report.regression import compare_metrics, format_report, load_metrics
    from heliocal.pipeline.stages.report import run_report

    summary = run_report(workdir)
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
