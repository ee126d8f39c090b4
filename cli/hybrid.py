"""``heliocal fit-hybrid`` (fine model / baselines) and ``heliocal aim`` (steps for an aim point).

See docs/hybrid.md. Library: :mod:`heliocal.pipeline.stages.fit_hybrid`, :mod:`heliocal.pipeline.stages.aim`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich import box
from rich.table import Table

from heliocal.cli.app import (DEFAULT_WORKDIR, DaskAddress, JsonFlag, QuietFlag, Scheduler,
                              SchedulerChoice, Seed, Workdir, Workers, command, emit, fmt_number,
                              incremental_line, progress_bar, stdout)
from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.config import FineConfig
from heliocal.pipeline.runtime.parallel import warm_up_stage
from heliocal.pipeline.vocabulary import (HYBRID_BATCH_SIZE, AimModel, FineMode, PretrainVariant,
                                         TrainingDtype)

__all__ = ["fit_hybrid_cmd", "aim_cmd"]

# str Enums (heliocal.pipeline.vocabulary): typer lists the choices in --help and rejects others
# as a usage error (exit 2). The library (torch) is imported when a command runs.
Mode = FineMode


def _human(summary: dict) -> None:
    if incremental_line(summary):
        return
    mode = summary["mode"]
    table = Table(title=f"fit-hybrid --mode {mode} (weight decay {summary['weight_decay']:g}, seed "
                        f"{summary['seed']}) -> {summary['workdir']}", box=box.SIMPLE_HEAD,
                  pad_edge=False)
    table.add_column("heliostat", no_wrap=True)
    table.add_column("coarse", no_wrap=True)
    for col in ("train", "val", "test", "train", "val", "test"):
        table.add_column(col, justify="right", no_wrap=True)
    for h in summary["heliostats"]:
        c, f = h["coarse"], h[mode]
        table.add_row(h["heliostat_id"], h["coarse_preset"], fmt_number(c["train"]),
                      fmt_number(c["validation"]), fmt_number(c["test"]), fmt_number(f["train"]),
                      fmt_number(f["validation"]), fmt_number(f["test"]))
    stdout.print(table)
    stdout.print("mean error_mrad per split: the selected coarse preset (first three columns) vs "
                 f"{mode} (last three); wrote hybrid/{mode}/ and hybrid_predictions.parquet", markup=False)


def _floats(text: str, name: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ParameterError(f"The '{name}' option must be comma-separated numbers. Got "
                             f"{text!r} instead.") from None
    return values


@command("fit-hybrid", writes=True)
def fit_hybrid_cmd(
    workdir: Workdir = DEFAULT_WORKDIR,
    mode: Annotated[Mode, typer.Option(
        "--mode", help="hybrid: coarse fit + network deviations (paper 000); nn-only: the same "
                       "network from the nominal geometry; pretrained-nn: paper 002's network "
                       "on the coarse model (variant: --pretrain-variant); gp: a Gaussian-"
                       "process correction of the coarse model's pointing over sun position, "
                       "time and --env columns.")] = Mode.hybrid,
    pretrain_variant: Annotated[PretrainVariant, typer.Option(
        "--pretrain-variant", help="pretrained-nn only. residual: the network learns the "
                                   "correction to the coarse model's inverse kinematics in "
                                   "motor steps (starts as the coarse model); paper: paper "
                                   "002's network pre-trained on simulated calibrations, then "
                                   "fine-tuned.")] = PretrainVariant.residual,
    weight_decay: Annotated[float, typer.Option(
        "--weight-decay", min=0.0, help="L2 penalty on the network's weights (pulls the hybrid "
                                        "toward the coarse model).")] = 0.0,
    env: Annotated[str, typer.Option(
        "--env", help="Comma-separated env_* columns (without the prefix) to use as inputs, "
                      "e.g. temperature,wind_speed.")] = "",
    depth: Annotated[int, typer.Option("--depth", min=0, help="Hidden layers.")] = FineConfig.depth,
    width: Annotated[int, typer.Option(
        "--width", min=1, help="Neurons per hidden layer.")] = FineConfig.width,
    fourier_bands: Annotated[str, typer.Option(
        "--fourier-bands", help="Frequency bands of the Fourier features of the steps "
                                "[1 / max steps], comma-separated (default: every integer 1..32)."
    )] = ",".join(f"{b:g}" for b in FineConfig.fourier_bands),
    ensemble: Annotated[int, typer.Option(
        "--ensemble", min=1, help="Networks per heliostat (seeds seed*K .. seed*K+K-1); the model "
                                  "is their mean deviation.")] = FineConfig.ensemble,
    max_epochs: Annotated[int, typer.Option("--max-epochs", min=0, help="Epoch budget.")] = FineConfig.max_epochs,
    patience: Annotated[int, typer.Option(
        "--patience", min=1, help="Epochs without validation improvement before stopping.")] = FineConfig.patience,
    learning_rate: Annotated[float, typer.Option(
        "--learning-rate", min=0.0, help="Adam step size.")] = FineConfig.learning_rate,
    training_dtype: Annotated[TrainingDtype, typer.Option(
        "--training-dtype", help="Precision of the networks' training arithmetic (float32: "
                                 "~1.7x faster; float64: exact comparisons of trainings). "
                                 "Errors are float64 either way.")
    ] = TrainingDtype(FineConfig.training_dtype),
    heliostat: Annotated[Optional[list[str]], typer.Option(
        help="Fit only these heliostats (repeat the option).")] = None,
    seed: Seed = 0,
    batch_size: Annotated[int, typer.Option(
        "--batch-size", min=1, help="Heliostats that train together as one batched program "
                                    "(same type and coarse preset); each batch is one task for "
                                    "the workers.")] = HYBRID_BATCH_SIZE,
    workers: Workers = None,
    scheduler: Scheduler = SchedulerChoice.local,
    dask_address: DaskAddress = None,
    incremental: Annotated[bool, typer.Option(
        "--incremental", help="Keep the previous run as it is when it was this mode with these "
                              "options and seed on unchanged inputs and code; otherwise train "
                              "every heliostat (a heliostat's networks depend on the others in "
                              "its batch).")] = False,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Train the fine model (or a baseline) on each heliostat's training rows."""
    warm_up_stage("fit-hybrid", workers=workers, scheduler=scheduler.value,
                  dask_address=dask_address)   # before the stage's import: side by side
    from heliocal.pipeline.models.pretrained import PretrainConfig
    from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid

    config = FineConfig(depth=depth, width=width, fourier_bands=_floats(fourier_bands, "--fourier-bands"),
                        env=tuple(e.strip() for e in env.split(",") if e.strip()),
                        learning_rate=learning_rate, max_epochs=max_epochs, patience=patience,
                        ensemble=ensemble, training_dtype=training_dtype.value)
    with progress_bar(f"fit-hybrid {mode.value}", quiet) as advance:
        summary = run_fit_hybrid(workdir, mode=mode.value, weight_decay=weight_decay, seed=seed,
                                 config=config,
                                 pretrain_config=PretrainConfig(variant=pretrain_variant.value),
                                 heliostats=heliostat, progress=advance,
                                 workers=workers, scheduler=scheduler.value, dask_address=dask_address,
                                 batch_size=batch_size, incremental=incremental)
    emit(summary, json_, _human)


def _target(text: str) -> tuple[list[float] | None, str | None]:
    """(E, N, U) [m] when ``text`` is three comma-separated numbers (each finite), else the
    target name."""
    import math

    parts = text.split(",")
    if len(parts) == 3:
        try:
            point = [float(p) for p in parts]
        except ValueError:
            return None, text
        if not all(math.isfinite(v) for v in point):
            raise typer.BadParameter(f"{text!r}: the aim point must be three finite numbers "
                                     "E,N,U [m] (not finite), or a target name",
                                     param_hint="'--target'")
        return point, None
    return None, text


def _env(items: list[str]) -> dict[str, float]:
    values = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = None
        if not sep or not name.strip() or number is None:
            raise typer.BadParameter(f"{item!r}: give NAME=VALUE with a number",
                                     param_hint="'--env'")
        values[name.strip()] = number
    return values


def _sun(azimuth: float | None, elevation: float | None):
    import math

    if (azimuth is None) != (elevation is None):
        raise ParameterError("give both --sun-azimuth and --sun-elevation, or neither")
    if azimuth is None:
        return None
    for value, name in ((azimuth, "--sun-azimuth"), (elevation, "--sun-elevation")):
        if not math.isfinite(value):
            raise typer.BadParameter(f"{value!r} is not finite", param_hint=f"'{name}'")
    if not -90.0 <= elevation <= 90.0:
        raise typer.BadParameter(f"{elevation!r}: the elevation must be in [-90, 90] deg",
                                 param_hint="'--sun-elevation'")
    from heliocal.pipeline.physics.sun import sun_vector_enu

    return sun_vector_enu(azimuth, elevation)


@command("aim")
def aim_cmd(
    heliostat: Annotated[Optional[list[str]], typer.Option(
        "--heliostat", help="Heliostat id (with --date: repeat, or leave out for all).")] = None,
    target: Annotated[Optional[str], typer.Option(
        "--target", help="Aim point: a target name of the measurements or E,N,U [m] (with "
                         "--date: a target name; default each heliostat's usual one).")] = None,
    workdir: Workdir = DEFAULT_WORKDIR,
    time: Annotated[Optional[str], typer.Option(
        "--time", help="UTC time, e.g. 2024-06-01T12:00Z (sun from NREL SPA; the date is an "
                       "input of the fine model). Without a zone it is UTC.")] = None,
    sun_azimuth: Annotated[Optional[float], typer.Option(
        "--sun-azimuth", help="Sun azimuth [deg], 0 = south, positive toward east.")] = None,
    sun_elevation: Annotated[Optional[float], typer.Option(
        "--sun-elevation", help="Sun elevation [deg].")] = None,
    env: Annotated[Optional[list[str]], typer.Option(
        "--env", help="NAME=VALUE of an env input of the model (repeat).")] = None,
    model: Annotated[AimModel, typer.Option(
        "--model", help="auto: the sweep's selection, else the hybrid where fitted, else "
                        "coarse.")] = AimModel.auto,
    max_expected_error: Annotated[Optional[float], typer.Option(
        "--max-expected-error", metavar="MRAD",
        help="Refuse an aim expected to be off by more [mrad] (batch: that row is rejected).")] = None,
    schedule: Annotated[Optional[Path], typer.Option(
        "--schedule", help="Many aims: a CSV or Parquet table with heliostat_id, time_utc, target "
                           "(or aim_e_m, aim_n_m, aim_u_m) and optional env_<name> columns.")] = None,
    date: Annotated[Optional[str], typer.Option(
        "--date", help="Many aims: a whole UTC day of the field, one aim every --every while "
                       "the sun is up.")] = None,
    every: Annotated[str, typer.Option("--every", help="Time step of --date, e.g. 10min.")] = "10min",
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="Many aims: write the table here (.parquet or .csv); default CSV on "
                      "stdout.")] = None,
    as_json: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Motor steps that put the reflected beam on an aim point, with the error the aim is
    expected to show (one aim: JSON; warnings, such as an aim far from the heliostat's data,
    also on stderr). --schedule or --date aim many at once into a table."""
    import numpy as np

    from heliocal.pipeline.stages.aim import aim_steps, utc_time

    if schedule is not None or date is not None:
        from heliocal.cli.aim_field import aim_many

        return aim_many(workdir, schedule=schedule, date=date, every=every, heliostats=heliostat,
                        target=target, out=out, model=model.value,
                        max_expected_error=max_expected_error, as_json=as_json)
    if not heliostat or len(heliostat) != 1 or target is None:
        raise ParameterError("one aim needs one --heliostat and a --target (or --schedule FILE "
                             "/ --date DAY for many)")

    sun = _sun(sun_azimuth, sun_elevation)
    if time is None and sun is None:
        raise ParameterError("give --time or --sun-azimuth/--sun-elevation")
    try:
        when = utc_time(time, "--time")
    except ParameterError:
        raise typer.BadParameter(f"{time!r} is not a UTC time such as 2023-06-21T12:00:00Z",
                                 param_hint="'--time'") from None
    values = _env(env or [])
    point, name = _target(target)
    result = aim_steps(workdir, heliostat[0],
                       aim_point_enu=None if point is None else np.asarray(point),
                       target=name, sun_vector_enu=sun, time_utc=when, env=values,
                       model=model.value, max_expected_error_mrad=max_expected_error)
    result["target"] = name or target
    sys.stdout.write(json.dumps(result, indent=2) + "\n")
