"""``heliocal fit-coarse``: the rigid-body coarse model per heliostat (Levenberg-Marquardt)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from heliocal.cli.app import (DEFAULT_WORKDIR, DaskAddress, IncrementalFlag, JsonFlag, QuietFlag,
                              Scheduler, SchedulerChoice, Workdir, Workers, command, emit,
                              fmt_number, incremental_line, progress_bar, stdout)
from heliocal.pipeline.runtime.parallel import warm_up_stage
from heliocal.pipeline.vocabulary import (DEFAULT_ROLLING_ORIGINS, CoarseLoss, CoarsePreset,
                                         CoarsePrior, CoarseSolver, RobustStart)


def _human(summary: dict) -> None:
    if incremental_line(summary):
        return
    table = Table(title=f"fit-coarse ({summary['preset']}, loss {summary['loss']}) -> "
                        f"{summary['workdir']}", show_edge=False)
    for col in ("heliostat", "n_train", "nominal test", "selected", "train", "validation", "test",
                "forward", "next day"):
        table.add_column(col, justify="left" if col in ("heliostat", "selected") else "right")
    for h in summary["heliostats"]:
        s = h["presets"][h["selected"]]
        forward = (h.get("time_split") or {}).get("test")
        next_day = (h.get("next_day") or {}).get("mean_error_mrad")
        table.add_row(h["heliostat_id"], str(h["n_train"]), fmt_number(h["nominal"]["test"]),
                      h["selected"], fmt_number(s["train"]), fmt_number(s["validation"]),
                      fmt_number(s["test"]), fmt_number(forward), fmt_number(next_day))
    stdout.print(table)
    stdout.print("mean error_mrad per split; forward: the model fitted on the time split's "
                 "training rows, on its test rows; next day: the rolling-origin evaluation "
                 "(rolling_origin.parquet). The preset is chosen by the kNN validation error, "
                 "guarded by the time split's.")
    r = summary.get("regimes")
    if r:
        refit = r["refitted_without_episodes"]
        stdout.print(f"regimes: {r['detected_breaks']} detected and {r['renovation_breaks']} "
                     f"renovation breaks in {r['heliostats_with_breaks']} heliostats, "
                     f"{r['episodes']} episodes, {r['outliers']} outliers (regimes.parquet); "
                     f"fitted again without their episodes: {', '.join(refit) if refit else 'none'}.",
                     markup=False)
        chosen = r.get("regime_models_selected") or []
        stdout.print(f"regime-aware candidates (regime_params.parquet) fitted for "
                     f"{r.get('regime_models_fitted', 0)} heliostats, selected for "
                     f"{', '.join(chosen) if chosen else 'none'}.", markup=False)


@command("fit-coarse", writes=True)
def fit_coarse_cmd(
    workdir: Workdir = DEFAULT_WORKDIR,
    preset: Annotated[CoarsePreset, typer.Option(
        help="static-6, static-14, static-20, static-28, stone-8, or auto (all; the best on "
             "validation is selected per heliostat).")] = CoarsePreset.auto,
    loss: Annotated[CoarseLoss, typer.Option(
        help="linear (Levenberg-Marquardt), or a robust soft_l1 / huber (trust region).")] = CoarseLoss.soft_l1,
    f_scale: Annotated[float, typer.Option(help="Residual scale of a robust loss [mrad].")] = 1.0,
    robust_start: Annotated[RobustStart, typer.Option(
        help="Grid-search the actuator zero points before LM: auto (when the nominal geometry's "
             "median error exceeds 50 mrad), always or never.")] = RobustStart.auto,
    heliostat: Annotated[Optional[list[str]], typer.Option(
        help="Fit only these heliostats (repeat the option).")] = None,
    solver: Annotated[CoarseSolver, typer.Option(
        help="batched (many heliostats per vectorized Levenberg-Marquardt program) or scipy "
             "(one least_squares per heliostat, the reference).")] = CoarseSolver.batched,
    prior: Annotated[Optional[CoarsePrior], typer.Option(
        help="Prior of the fits: none (a weak prior around the nominal geometry; the default: "
             "the field prior costs well-measured heliostats a few per cent), field (the "
             "field's typical geometry, learned from the well-determined heliostats of each "
             "type and geometry "
             "source; only where at least 8 of them determine a parameter; the default with "
             "--prior-from) or field+spatial (its mean from the nearest heliostats).")] = None,
    prior_from: Annotated[Optional[Path], typer.Option(
        "--prior-from", file_okay=False,
        help="Use the field prior of another work directory's fit-coarse run (e.g. a plant's "
             "longer history for new heliostats; this work directory itself reuses its "
             "committed prior) instead of learning it here.")] = None,
    rolling_origins: Annotated[int, typer.Option(
        min=0, help="Origins per heliostat of the rolling-origin evaluation (each a refit on "
                    "the rows before a calibration day, scored on that day's rows); 0 skips "
                    "it.")] = DEFAULT_ROLLING_ORIGINS,
    workers: Workers = None,
    scheduler: Scheduler = SchedulerChoice.local,
    dask_address: DaskAddress = None,
    incremental: IncrementalFlag = False,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Fit the coarse (rigid-body) model on each heliostat's training rows."""
    warm_up_stage("fit-coarse", workers=workers, scheduler=scheduler.value,
                  dask_address=dask_address)   # before the stage's import: side by side
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse

    with progress_bar("fit-coarse", quiet) as advance:
        summary = run_fit_coarse(workdir, preset=preset.value, loss=loss.value, f_scale_mrad=f_scale,
                                 robust_start=robust_start.value, heliostats=heliostat, progress=advance,
                                 solver=solver.value, workers=workers, scheduler=scheduler.value,
                                 dask_address=dask_address, rolling_origins=rolling_origins,
                                 prior=(prior.value if prior is not None
                                        else "field" if prior_from is not None else "none"),
                                 prior_from=prior_from, incremental=incremental)
    emit(summary, json_, _human)
