"""Benchmark: the per-epoch cost of the sweep's batched training against the heliostats in a
chunk (the constant behind ``sweep_increment.CHUNK_OVERHEAD_ROWS``).

Stacks K heliostats of a work directory (after ``fit-coarse``; heliostats of 250 to 300 rows,
repeated to reach K) as the sweep stacks a chunk (4-network ensembles, the aligned layout),
trains one weight decay for 40 epochs after a warm-up run, in this process on one thread, and
prints the milliseconds per epoch for each K. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/chunk_cost.py WORKDIR \\
        [--heliostats 1,2,5,10,20,32,64]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from heliocal.pipeline.models.config import FineConfig, ensemble_seeds
from heliocal.pipeline.models.training import (MEMBER_ALIGN, build_problem, stack_problems,
                                               take_rows, train_members)
from heliocal.pipeline.stages.fit_coarse import coarse_row_parameters
from heliocal.pipeline.stages.sweep_inputs import SweepHeliostat, read_sweep_inputs

EPOCHS = 40


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--heliostats", default="1,2,5,10,20,32,64")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True, warn_only=True)   # as the sweep's tasks run
    items = read_sweep_inputs(args.workdir, None)
    mid = [h for h in sorted(items) if 250 <= len(items[h].rows) <= 300]
    cfg = FineConfig(max_epochs=EPOCHS, patience=10 * EPOCHS)
    for k in (int(x) for x in args.heliostats.split(",")):
        helios = [SweepHeliostat.of(items[h]) for h in (mid * (k // len(mid) + 1))[:k]]
        fit = [np.isin(h.labels, ("train", "validation")) for h in helios]
        taken = [take_rows(build_problem(h.rows, h.hrow, coarse_row_parameters(
            h.selected, h.rows["timestamp"]), h.selected["free"], cfg), torch.as_tensor(f))
            for h, f in zip(helios, fit)]
        stacked, valid = stack_problems([t for t in taken for _ in range(4)], MEMBER_ALIGN)
        n = stacked.data.steps.shape[1]
        labels = np.array([np.resize(h.labels[f], n) for h, f in zip(helios, fit)
                           for _ in range(4)])
        seeds = [x for _ in helios for x in ensemble_seeds(0, 4)]
        masks = (torch.as_tensor(labels == "train") & valid,
                 torch.as_tensor(labels == "validation") & valid)
        train_members(stacked, *masks, [0.1] * len(seeds), seeds, cfg, align=MEMBER_ALIGN)
        t0 = time.perf_counter()
        train_members(stacked, *masks, [0.1] * len(seeds), seeds, cfg, align=MEMBER_ALIGN)
        ms = 1e3 * (time.perf_counter() - t0) / (EPOCHS + 1)
        print(f"heliostats {k:3d} ({len(seeds)} networks, {n} rows): {ms:6.2f} ms per epoch, "
              f"{ms / k:5.2f} ms per heliostat", flush=True)


if __name__ == "__main__":
    main()
