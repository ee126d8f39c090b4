"""``heliocal split-knn``: training/validation/test split per heliostat (see docs/split.md)."""

from __future__ import annotations

import logging
from typing import Annotated, Optional

import typer
from rich import box
from rich.table import Table

from heliocal.cli.app import (DEFAULT_WORKDIR, IncrementalFlag, JsonFlag, QuietFlag, Seed, Workdir,
                              command, emit, fmt_number, incremental_line, stdout)
from heliocal.pipeline.vocabulary import SplitMethod, SplitMetric

__all__ = ["split_knn"]

log = logging.getLogger("heliocal.split")

# str Enums (heliocal.pipeline.vocabulary): typer lists the choices in --help and rejects others
# as a usage error (exit 2).
Method = SplitMethod
Metric = SplitMetric


def _print_summary(summary: dict) -> None:
    if incremental_line(summary):
        return
    table = Table(title=f"split-knn: method {summary['method']}, k={summary['k']}, metric "
                        f"{summary['metric']}", box=box.SIMPLE_HEAD, pad_edge=False)
    table.add_column("heliostat", no_wrap=True)
    for name in ("n", "train", "val", "test", "unused", "kNN\ntrain", "kNN\nval", "kNN\ntest",
                 "test->\ntrain"):
        table.add_column(name, justify="right", no_wrap=True)
    for h in summary["heliostats"]:
        c, d = h["counts"], h["mean_knn_distance_deg"]
        table.add_row(h["heliostat_id"], str(h["n_measurements"]), str(c["train"]),
                      str(c["validation"]), str(c["test"]), str(c["unused"]),
                      fmt_number(d["train"], 2), fmt_number(d["validation"], 2),
                      fmt_number(d["test"], 2),
                      fmt_number(h["mean_test_to_train_distance_deg"], 2))
    stdout.print(table)
    stdout.print("kNN <set>: mean kNN distance of the set (deg); test->train: mean distance from "
                 "a test measurement to the nearest training measurement (deg).", markup=False)
    timed = [h for h in summary["heliostats"] if h.get("time_split_counts")]
    stdout.print(f"time split beside it (the latest rows test, forward-in-time evaluation): "
                 f"{len(timed)} of {len(summary['heliostats'])} heliostats; the others have too "
                 "few timestamps (n/a).", markup=False)
    stdout.print(f"wrote {summary['artifact']}", markup=False)


@command("split-knn", writes=True)
def split_knn(
    workdir: Workdir = DEFAULT_WORKDIR,
    method: Annotated[Method, typer.Option(
        "--method",
        help="knn: the paper's kNN split (default); random, time, and PAINT's benchmark splits "
             "azimuth, solstice, balanced, high-variance for comparison.")] = Method.knn,
    k: Annotated[int, typer.Option(
        "--k", min=1, max=3, help="Neighbours of the kNN distance (1, 2 or 3).")] = 3,
    n_test: Annotated[int, typer.Option(
        "--n-test", min=0, help="Test measurements per heliostat.")] = 30,
    n_val: Annotated[int, typer.Option(
        "--n-val", min=0, help="Validation measurements per heliostat.")] = 20,
    n_train: Annotated[Optional[int], typer.Option(
        "--n-train", min=2, help="Keep only N training measurements, those with the largest kNN "
                                 "distance; the rest are marked unused. Default: all.")] = None,
    metric: Annotated[Metric, typer.Option(
        "--metric",
        help="Distance in sun position: euclidean in (azimuth, elevation) degrees (paper) or "
             "great-circle angle between sun vectors.")] = Metric.euclidean,
    seed: Seed = 0,
    incremental: IncrementalFlag = False,
    json_: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Split each heliostat's measurements into train/validation/test sets (writes split.parquet)."""
    from heliocal.pipeline.stages.split import run_split

    summary = run_split(workdir, method=method.value, k=k, n_test=n_test, n_val=n_val,
                        n_train=n_train, metric=metric.value, seed=seed,
                        incremental=incremental)
    for s in summary["skipped"]:
        log.warning("skipped heliostat %s: it has %d measurements, the split needs at least %s",
                    s["heliostat_id"], s["n_measurements"], summary["requirement"])
    emit(summary, json_, _print_summary)
