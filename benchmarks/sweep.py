"""Benchmark: a 16-member sweep of one heliostat, batched vs a sequential loop, in one run.

The 16 members (8 weight decays x 2 seeds, or as given) train as ONE batched torch program
(:func:`heliocal.pipeline.models.training.train_members` with M = 16) and, for comparison, one by one
(16 calls with M = 1, the same seeds). Both paths are first warmed up once (a process's first
training pays a one-time start-up cost of about a second: torch's lazy initialisation and the
allocator growing), then timed ``--repeats`` times, alternating. Prints the median wall times,
the throughput ratio of the medians, and the largest difference of the members' final mean
errors. Usage::

    .venv/bin/python benchmarks/sweep.py [--epochs 300] [--members 16] [--repeats 3]

Data: the synthetic static heliostat SP13 of sample_data/synthetic (ingested, kNN split, coarse
fit static-6 on its training rows) so the benchmark needs no workdir.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from heliocal.pipeline.stages.fit_coarse import load_selected_parameters, run_fit_coarse
from heliocal.pipeline.models.config import FineConfig
from heliocal.pipeline.models.training import build_problem, member_errors_mrad, train_members
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS
from heliocal.pipeline.artifacts.store import read_artifact
from heliocal.pipeline.artifacts.schemas import SPLIT
from heliocal.pipeline.stages.split import run_split

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--members", type=int, default=16)
    ap.add_argument("--heliostat", default="SP13")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        w = Path(tmp)
        run_ingest([ROOT / "sample_data" / "synthetic" / "paint"], w)
        run_split(w)
        run_fit_coarse(w, preset="static-6", heliostats=[args.heliostat])
        sel = load_selected_parameters(w)[args.heliostat]
        m = read_artifact(w, MEASUREMENTS, heliostats=[args.heliostat])
        split = read_artifact(w, SPLIT, heliostats=[args.heliostat])
        rows = m.merge(split[["measurement_id", "split"]], on="measurement_id").reset_index(drop=True)
        hrow = read_artifact(w, HELIOSTATS, heliostats=[args.heliostat]).iloc[0]
    config = FineConfig(max_epochs=args.epochs, patience=args.epochs)
    problem = build_problem(rows, hrow, sel["params"], sel["free"], config)
    labels = rows["split"].to_numpy()
    train, val = labels == "train", labels == "validation"
    wds = [float(x) for x in np.logspace(0, -6, (args.members + 1) // 2)][: args.members]
    wds = (wds * 2)[: args.members]
    seeds = [k // max(len(wds) // 2, 1) for k in range(args.members)]

    def batched_run():
        return train_members(problem, train, val, wds, seeds, config)

    def loop_run():
        return [train_members(problem, train, val, [wd], [s], config) for wd, s in zip(wds, seeds)]

    warm = FineConfig(max_epochs=5, patience=5)
    train_members(problem, train, val, wds, seeds, warm)
    train_members(problem, train, val, wds[:1], seeds[:1], warm)
    t_b, t_l = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        batched = batched_run()
        t_b.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        singles = loop_run()
        t_l.append(time.perf_counter() - t0)
    t_batched, t_loop = float(np.median(t_b)), float(np.median(t_l))
    with torch.no_grad():
        err_b = member_errors_mrad(problem, batched.layers).mean(-1)
        err_l = [member_errors_mrad(problem, single.layers).mean(-1)[0] for single in singles]
    diff = (err_b - torch.stack(err_l)).abs().max().item()
    print(f"{args.members}-member sweep of {args.heliostat}, {args.epochs} epochs "
          f"({int(train.sum())} training rows, single thread):")
    print(f"  batched (one program): {t_batched:8.2f} s  (median of {args.repeats}: "
          f"{', '.join(f'{t:.2f}' for t in t_b)})")
    print(f"  sequential loop:       {t_loop:8.2f} s  (median of {args.repeats}: "
          f"{', '.join(f'{t:.2f}' for t in t_l)})")
    print(f"  throughput ratio loop / batched: {t_loop / t_batched:.1f}x")
    print(f"  largest difference of members' mean error_mrad: {diff:.2e} mrad")


if __name__ == "__main__":
    main()
