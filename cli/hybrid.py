"""``heliocal fit-hybrid`` (fine model / baselines) and ``heliocal aim`` (steps for an aim point).

See docs/hybrid.md. Library: :mod:`heliocal.pipeline.stages.fit_hybrid`, :mod:`heliocal.pipeline.stages.aim`.
"""

from __future__ import annotations

import json
import sys
from typing import Annotated, Optional

import typer
from rich import box
from rich.table import Table

from heliocal.cli.app import (DEFAULT_WORKDIR, DaskAddress, JsonFlag, QuietFlag, Scheduler,
                              SchedulerChoice, Seed, Workdir, Workers, command, emit, progress_bar,
                              stdout)
from heliocal.pipeline.errors import InputError, ParameterError
from heliocal.pipeline.models.config import FineConfig
from heliocal.pipeline.vocabulary import (HYBRID_BATCH_SIZE, AimModel, FineMode, PretrainVariant,
                                         TrainingDtype)

__all__ = ["fit_hybrid_cmd", "aim_cmd"]

# str Enums (heliocal.pipeline.vocabulary): typer lists the choices in --help and rejects others
# as a usage error (exit 2). The library (torch) is imported when a command runs.
Mode = FineMode


def _fmt(x) -> str:
    return "-" if x is None or x != x else f"{x:.3f}"


def _human(summary: dict) -> None:
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
        table.add_row(h["heliostat_id"], h["coarse_preset"], _fmt(c["train"]),
                      _fmt(c["validation"]), _fmt(c["test"]), _fmt(f["train"]),
                      _fmt(f["validation"]), _fmt(f["test"]))
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


@command("fit-hybrid")
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
    depth: Annotated[int, typer.Option("--depth", min=0, help="Hidden layers.")] = 14,
    width: Annotated[int, typer.Option("--width", min=1, help="Neurons per hidden layer.")] = 2,
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
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Train the fine model (or a baseline) on each heliostat's training rows."""
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
                                 batch_size=batch_size)
    emit(summary, json_, _human)


def _target(text: str, workdir) -> tuple[list[float], str | None]:
    parts = text.split(",")
    if len(parts) == 3:
        try:
            return [float(p) for p in parts], None
        except ValueError:
            pass
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.artifacts.schemas import MEASUREMENTS

    m = read_artifact(workdir, MEASUREMENTS, columns=["target_name", "target_e_m", "target_n_m",
                                                       "target_u_m"])
    rows = m[m["target_name"] == text]
    if rows.empty:
        names = sorted(m["target_name"].dropna().unique())
        raise InputError(f"unknown target {text!r}: give E,N,U in metres or one of {names}")
    return rows[["target_e_m", "target_n_m", "target_u_m"]].median().tolist(), text


@command("aim")
def aim_cmd(
    heliostat: Annotated[str, typer.Option("--heliostat", help="Heliostat id.")],
    target: Annotated[str, typer.Option(
        "--target", help="Aim point: a target name of the measurements or E,N,U [m].")],
    workdir: Workdir = DEFAULT_WORKDIR,
    time: Annotated[Optional[str], typer.Option(
        "--time", help="UTC time, e.g. 2024-06-01T12:00Z (sun from NREL SPA; the date is an "
                       "input of the fine model).")] = None,
    sun_azimuth: Annotated[Optional[float], typer.Option(
        "--sun-azimuth", help="Sun azimuth [deg], 0 = south, positive toward east.")] = None,
    sun_elevation: Annotated[Optional[float], typer.Option(
        "--sun-elevation", help="Sun elevation [deg].")] = None,
    env: Annotated[Optional[list[str]], typer.Option(
        "--env", help="NAME=VALUE of an env input of the model (repeat).")] = None,
    model: Annotated[AimModel, typer.Option(
        "--model", help="auto: the sweep's selection, else the hybrid where fitted, else "
                        "coarse.")] = AimModel.auto,
    quiet: QuietFlag = False,
) -> None:
    """Motor steps that put the reflected beam on an aim point (printed as JSON)."""
    import numpy as np

    from heliocal.pipeline.physics.sun import sun_vector_enu
    from heliocal.pipeline.stages.aim import aim_steps

    if (sun_azimuth is None) != (sun_elevation is None):
        raise ParameterError("give both --sun-azimuth and --sun-elevation, or neither")
    if time is None and sun_azimuth is None:
        raise ParameterError("give --time or --sun-azimuth/--sun-elevation")
    sun = None if sun_azimuth is None else sun_vector_enu(sun_azimuth, sun_elevation)
    values = {}
    for item in env or []:
        name, _, value = item.partition("=")
        try:
            values[name.strip()] = float(value)
        except ValueError:
            raise ParameterError(f"--env must be NAME=VALUE with a number. Got {item!r} instead.") from None
    point, name = _target(target, workdir)
    result = aim_steps(workdir, heliostat, aim_point_enu=np.asarray(point), sun_vector_enu=sun,
                       time_utc=time, env=values, model=model.value)
    result["target"] = name or target
    sys.stdout.write(json.dumps(result, indent=2) + "\n")
