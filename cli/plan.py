"""``heliocal plan``: which heliostats to measure next, and when (docs/plan.md).

Library: :mod:`heliocal.pipeline.stages.plan`.
"""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from heliocal.cli.app import (DEFAULT_WORKDIR, JsonFlag, QuietFlag, Seed, Workdir, Workers,
                              command, emit, stdout)
from heliocal.pipeline.runtime.parallel import warm_up_stage
from heliocal.pipeline.vocabulary import PLAN_DEFAULT_DAYS, PLAN_MIN_ELEVATION_DEG

__all__ = ["plan_cmd"]

#: Heliostats listed in the human summary (the JSON has all).
SHOWN = 20


def _human(summary: dict) -> None:
    mode = "rows already measured" if summary["from_existing"] else "slots"
    stdout.print(f"plan {summary['start']} + {summary['days']} days ({mode}): "
                 f"{summary['planned_rows']} measurements of {summary['planned_heliostats']} "
                 f"heliostats (budget {summary['budget_total']}) -> {summary['plan']}, "
                 f"{summary['csv']}", markup=False)
    if not summary["from_existing"]:
        stdout.print(f"one heliostat on a target at a time: slots {summary['spacing_s']} s apart "
                     f"({summary['spacing_source']})", markup=False)
    stdout.print(f"expected year-round aim error from the parameters' uncertainty, mean over "
                 f"{summary['heliostats_considered']} heliostats: now "
                 f"{summary['expected_error_now_mrad']:.3f} mrad, after the plan "
                 f"{summary['expected_error_after_plan_mrad']:.3f} mrad, after as many rows at "
                 f"random times {summary['expected_error_after_random_mrad']:.3f} mrad",
                 markup=False)
    shown = sorted(summary["heliostats"], key=lambda h: -h["planned_rows"])[:SHOWN]
    for h in (h for h in shown if h["planned_rows"]):
        stdout.print(f"  {h['heliostat_id']}: {h['planned_rows']} rows, "
                     f"{h['expected_error_now_mrad']:.3f} -> {h['expected_error_after_mrad']:.3f} "
                     f"mrad ({h['coarse_model']}, {h['known_rows']} rows known)", markup=False)
    missing = summary["without_coarse_fit"]
    if missing:
        stdout.print(f"{len(missing)} heliostats have no coarse fit and are planned on their "
                     f"nominal geometry: {', '.join(missing[:10])}"
                     + (" ..." if len(missing) > 10 else ""), markup=False)


@command("plan", writes=True)
def plan_cmd(
    start: Annotated[str, typer.Option(
        "--start", help="First day of the plan, e.g. 2024-06-01 (the site's solar day).")],
    workdir: Workdir = DEFAULT_WORKDIR,
    days: Annotated[int, typer.Option("--days", min=1, help="Days in the plan.")] = PLAN_DEFAULT_DAYS,
    per_day: Annotated[Optional[int], typer.Option(
        "--per-day", min=1, help="Measurements per day (default: the logs' median per "
                                 "measurement day, unless --budget is given).")] = None,
    budget: Annotated[Optional[int], typer.Option(
        "--budget", min=1, help="Measurements in all (with --per-day both apply).")] = None,
    max_per_heliostat: Annotated[Optional[int], typer.Option(
        "--max-per-heliostat", min=1, help="At most this many measurements per heliostat.")] = None,
    from_existing: Annotated[bool, typer.Option(
        "--from-existing", help="Choose among rows already measured in those days (not test "
                                "rows), to check the plan on real logs.")] = False,
    spacing: Annotated[Optional[float], typer.Option(
        "--spacing", help="Least time between two measurements on one target [min] (default: "
                          "the logs' median gap between two heliostats on a target).")] = None,
    min_elevation: Annotated[float, typer.Option(
        "--min-elevation", help="Lowest sun elevation of a planned measurement and of the "
                                "year's aims [deg].")] = PLAN_MIN_ELEVATION_DEG,
    heliostat: Annotated[Optional[list[str]], typer.Option(
        "--heliostat", help="Plan only these heliostats (repeat the option).")] = None,
    seed: Seed = 0,
    workers: Workers = None,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Which heliostats to measure next, and when: plan.parquet, plan.csv (time order, for a
    plant scheduler), each row chosen for the largest drop of its heliostat's expected
    year-round aim error."""
    warm_up_stage("plan", workers=workers)   # before the stage's import: side by side
    from heliocal.pipeline.stages.plan import run_plan

    summary = run_plan(workdir, start=start, days=days, per_day=per_day, budget=budget,
                       max_per_heliostat=max_per_heliostat, from_existing=from_existing,
                       spacing_minutes=spacing, min_elevation_deg=min_elevation,
                       heliostats=heliostat, seed=seed, workers=workers)
    emit(summary, json_, _human)
