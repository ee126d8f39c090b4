"""``heliocal sweep``: the production model selection of every heliostat, and the training-size
study of a sample of them."""

from __future__ import annotations

from typing import Annotated, Optional

import typer
from rich.table import Table

from heliocal.cli.app import (DEFAULT_WORKDIR, DaskAddress, JsonFlag, QuietFlag, Scheduler,
                              SchedulerChoice, Workdir, Workers, command, emit, fmt_number,
                              incremental_line, progress_bar, stdout)
from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.config import FineConfig, PathConfig, ScreenConfig
from heliocal.pipeline.runtime.parallel import warm_up_stage
from heliocal.pipeline.vocabulary import (DEFAULT_STUDY, HYBRID_BATCH_SIZE, MIN_IMPROVEMENT,
                                         OCTAVE_BANDS, NeuralBaseline, PretrainVariant,
                                         SweepScreen, TrainingDtype)


def _ints(text: Optional[str], name: str):
    if text is None:
        return None
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise ParameterError(f"The '{name}' parameter of sweep must be comma-separated integers. "
                             f"Got {text!r} instead.") from exc


def _human(summary: dict) -> None:
    incremental_line(summary)   # a kept sweep still shows its selection below
    table = Table(title=f"sweep -> {summary['workdir']} (selection at the full training size)",
                  show_edge=False)
    for col in ("heliostat", "model", "preset", "weight decay", "val", "test", "coarse val",
                "coarse test"):
        table.add_column(col, justify="left" if col in ("heliostat", "model", "preset") else "right")
    for s in summary["selection"]:
        table.add_row(s["heliostat_id"], s["model"], s["preset"],
                      "-" if s["weight_decay"] != s["weight_decay"] else f"{s['weight_decay']:g}",
                      fmt_number(s["val_error_mrad"]), fmt_number(s["test_error_mrad"]),
                      fmt_number(s["coarse_val_error_mrad"]), fmt_number(s["coarse_test_error_mrad"]))
    stdout.print(table)
    stdout.print("mean error_mrad; coarse = fit-coarse's selected fit (the same numbers), always a "
                 "candidate, so the selection is never worse than it on validation.")
    if summary.get("study_heliostats"):
        stdout.print(f"training-size study: {', '.join(summary['study_heliostats'])}")


@command("sweep", writes=True)
def sweep_cmd(
    workdir: Workdir = DEFAULT_WORKDIR,
    n_train: Annotated[Optional[str], typer.Option(
        help="Training sizes of the study, e.g. 5,10,20,40,60,100 (default: that ladder up to "
             "all train rows).")] = None,
    study: Annotated[int, typer.Option(
        min=0, help="Heliostats in the training-size study (a seeded random choice; all if the "
                    "field has no more; 0: production selection only).")] = DEFAULT_STUDY,
    study_seed: Annotated[int, typer.Option(
        min=0, help="Seed of the study's choice of heliostats.")] = 0,
    wd_max: Annotated[float, typer.Option(help="Strongest weight decay.")] = 1.0,
    wd_min: Annotated[float, typer.Option(help="Weakest non-zero weight decay (0 is always added).")] = 1e-6,
    wd_per_decade: Annotated[int, typer.Option(help="Weight decays per decade.")] = 1,
    warm_start: Annotated[bool, typer.Option(
        "--warm-start/--no-warm-start",
        help="Train the weight decays as a path, strong to weak, each starting from the "
             "previous one's best-validation weights (default); or each from scratch with "
             "--max-epochs and --patience.")] = PathConfig.warm_start,
    stage_epochs: Annotated[int, typer.Option(
        help="Epoch budget of each weight decay with --warm-start.")] = PathConfig.stage_epochs,
    stage_patience: Annotated[int, typer.Option(
        help="Early stopping of each weight decay with --warm-start: epochs without a "
             "validation improvement.")] = PathConfig.stage_patience,
    seeds: Annotated[str, typer.Option(help="Seeds, comma-separated (repeats of every member).")] = "0",
    ensemble: Annotated[int, typer.Option(
        min=1, help="Networks averaged per member (weight decay, seed).")] = FineConfig.ensemble,
    baselines: Annotated[str, typer.Option(
        help="Neural baselines of the study: "
             f"{', '.join(NeuralBaseline.values())} (comma-separated, or none).")
    ] = NeuralBaseline.nn_only.value,
    select_pretrained: Annotated[bool, typer.Option(
        "--select-pretrained/--no-select-pretrained",
        help="Also fit the pre-trained network (pretrained-nn, --pretrain-variant) on every "
             "heliostat as a candidate of the selection, under the hybrids' "
             f"{100 * MIN_IMPROVEMENT:g} % margin rule.")] = False,
    time_split: Annotated[bool, typer.Option(
        "--time-split/--no-time-split",
        help="Also evaluate the selected networks (hybrids, pretrained-nn) forward in time: "
             "train each again on the time split's training rows (split.parquet time_split); "
             "a selected network worse there than the coarse model falls back to the static "
             "choice (without this option its check is left out: selection.parquet "
             "forward_check). Coarse and GP selections always get it (cheap).")] = False,
    gp: Annotated[bool, typer.Option(
        "--gp/--no-gp",
        help="The Gaussian-process correction of the coarse model is a candidate (and a line "
             "of the training-size study).")] = True,
    screen: Annotated[SweepScreen, typer.Option(
        "--screen", help="on: the integer bands' path up to its third weight decay first, "
                         "the rest of the path and the octave bands only where that gains at "
                         "least half the networks' margin on the weighted validation rows "
                         "(selection.parquet screen). off: the full path for every "
                         "heliostat.")] = SweepScreen.on,
    stage_gain: Annotated[float, typer.Option(
        min=0.0, max=1.0,
        help="With --screen on: past the screen's weight decays, each band set's path trains "
             "the next weight decay only where the last one raised its best gain over the "
             "coarse model (weighted validation rows) by at least this share; 0 trains every "
             "passing heliostat's whole path.")] = ScreenConfig.stage_gain,
    pretrain_variant: Annotated[PretrainVariant, typer.Option(
        "--pretrain-variant", help="Variant of the pre-trained network (candidate and "
                                   "baseline): residual (correction to the coarse inverse "
                                   "kinematics in steps) or paper (paper 002's).")
    ] = PretrainVariant.residual,
    octaves: Annotated[bool, typer.Option(
        "--octaves/--no-octaves", help="Also sweep the hybrid with octave Fourier bands "
                                       "1,2,4,...,32 (model hybrid-octaves) as a candidate.")] = True,
    max_epochs: Annotated[int, typer.Option(
        help="Epoch budget of a network trained from scratch (--no-warm-start, and the "
             "nn-only baseline).")] = FineConfig.max_epochs,
    patience: Annotated[int, typer.Option(
        help="Early stopping of a network trained from scratch: epochs without a validation "
             "improvement.")] = FineConfig.patience,
    training_dtype: Annotated[TrainingDtype, typer.Option(
        help="Precision of the networks' training arithmetic (float32: ~1.7x faster, selects "
             "as well; float64: exact comparisons of trainings). Errors are float64 either "
             "way.")] = TrainingDtype(FineConfig.training_dtype),
    env: Annotated[Optional[str], typer.Option(help="env_* columns as extra network inputs.")] = None,
    heliostat: Annotated[Optional[list[str]], typer.Option(help="Only these heliostats.")] = None,
    batch_size: Annotated[int, typer.Option(
        min=1, help="Heliostats per batched training program of the selection.")] = HYBRID_BATCH_SIZE,
    workers: Workers = None,
    scheduler: Scheduler = SchedulerChoice.local,
    dask_address: DaskAddress = None,
    incremental: Annotated[bool, typer.Option(
        "--incremental", help="Train again only the batches holding a heliostat whose inputs "
                              "(rows, split, coarse fit) changed since the last sweep and keep "
                              "the others' results; every batch when an option, a seed or the "
                              "code changed, or with --time-split.")] = False,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Select every heliostat's model (coarse, hybrid or GP) at its full training size; study the
    training size on a sample of heliostats."""
    warm_up_stage("sweep", workers=workers, scheduler=scheduler.value,
                  dask_address=dask_address)   # before the stage's import: side by side
    from heliocal.pipeline.models.pretrained import PretrainConfig
    from heliocal.pipeline.stages.sweep import run_sweep, weight_decay_grid

    config = FineConfig(max_epochs=max_epochs, patience=patience, ensemble=ensemble,
                        training_dtype=training_dtype.value,
                        env=tuple(e.strip() for e in env.split(",") if e.strip()) if env else ())
    base = [] if baselines.strip() in ("", "none") else [b.strip() for b in baselines.split(",")]
    path = PathConfig(warm_start=warm_start, stage_epochs=stage_epochs,
                      stage_patience=stage_patience)
    with progress_bar("sweep", quiet) as advance:
        summary = run_sweep(workdir, n_train=_ints(n_train, "n_train"),
                            weight_decays=weight_decay_grid(wd_max, wd_min, wd_per_decade),
                            seeds=_ints(seeds, "seeds"), baselines=tuple(base), config=config,
                            heliostats=heliostat, workers=workers, scheduler=scheduler.value,
                            dask_address=dask_address, progress=advance,
                            extra_bands=(OCTAVE_BANDS,) if octaves else (), study=study,
                            study_seed=study_seed, path=path, batch_size=batch_size,
                            pretrain_config=PretrainConfig(variant=pretrain_variant.value),
                            select_pretrained=select_pretrained, time_split=time_split, gp=gp,
                            incremental=incremental,
                            screen=ScreenConfig(enabled=screen == SweepScreen.on,
                                                stage_gain=stage_gain))
    emit(summary, json_, _human)
