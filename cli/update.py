"""``heliocal update``: a day's new rows through every stage the work directory has run (see
:mod:`heliocal.pipeline.stages.update`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from heliocal.cli.app import (DEFAULT_WORKDIR, JsonFlag, QuietFlag, Workdir, Workers, command,
                              emit, stdout)

__all__ = ["update"]


def _what(entry: dict) -> str:
    """What one stage of the update recomputed, in words."""
    if entry.get("unchanged"):
        return "unchanged, kept"
    if "figures_drawn" in entry:
        return f"{entry['figures_drawn']} figures drawn, {entry['figures_kept']} kept"
    if "computed" in entry:
        return f"{entry['computed']} heliostats computed, {entry['reused']} kept"
    return "computed"


def _human(summary: dict) -> None:
    ingest = summary["ingest"]
    if ingest is not None:
        reasons = ", ".join(f"{n} {why}" for why, n in ingest["rejected_by_reason"].items())
        stdout.print(f"ingest --append: {ingest['kept']} rows kept, {ingest['rejected']} rejected"
                     + (f" ({reasons})" if reasons else "") + f" ({ingest['seconds']:.1f} s)",
                     markup=False)
    for entry in summary["stages"]:
        stdout.print(f"{entry['stage']}: {_what(entry)} ({entry['seconds']:.1f} s)", markup=False)
    stdout.print(f"updated {summary['workdir']} in {summary['seconds']:.1f} s", markup=False)


@command("update", writes=True)
def update(
    sources: Annotated[Optional[list[Path]], typer.Argument(
        help="The new calibration logs (files or folders, as for ingest). None: only bring the "
             "stages up to date with the rows already ingested.")] = None,
    workdir: Workdir = DEFAULT_WORKDIR,
    workers: Workers = None,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Add a day's rows (ingest --append) and rerun every stage the work directory has run,
    --incremental and with the options it recorded: only the heliostats whose inputs changed
    are computed again."""
    from heliocal.pipeline.stages.update import run_update

    summary = run_update(sources or [], workdir, workers=workers)
    emit(summary, json_, _human)
