"""Benchmark: what the sweep's aligned layout (``training.MEMBER_ALIGN``: rows and parameters
padded to multiples of 32, so a heliostat's networks do not depend on its chunk) costs.

Trains one weight decay of the first ``--chunks`` training chunks of a work directory (after
``fit-coarse``) as the sweep stacks them, with the layout unaligned (1) and aligned (32),
interleaved ``--repeats`` times, in this process (torch on one thread, as the sweep's tasks run),
and prints each chunk's times and the ratio of the totals. Usage::

    .venv/bin/python benchmarks/sweep_alignment.py WORKDIR [--chunks 3] [--repeats 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd
import torch

from heliocal.pipeline.models.config import FineConfig, PathConfig
from heliocal.pipeline.models.selection import SelectionRule
from heliocal.pipeline.stages import sweep, sweep_path
from heliocal.pipeline.stages.selection import CandidatePool
from heliocal.pipeline.stages.sweep_increment import sweep_chunks
from heliocal.pipeline.stages.sweep_inputs import SweepHeliostat, read_sweep_inputs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir")
    ap.add_argument("--chunks", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    torch.use_deterministic_algorithms(True, warn_only=True)   # as the sweep's tasks run
    items = read_sweep_inputs(args.workdir, None)
    selected = {h: i.selected for h, i in items.items()}
    helio = pd.DataFrame([i.hrow for i in items.values()], index=list(items))
    chunks = sweep_chunks(items, selected, helio, 32)
    kind, cfg = sweep.hybrid_variants(FineConfig())[0]
    totals = {1: 0.0, 32: 0.0}
    for chunk in chunks[:args.chunks]:
        helios = [SweepHeliostat.of(items[h]) for h in chunk]
        longest = max(int(np.isin(h.labels, ("train", "validation")).sum()) for h in helios)
        times: dict[int, list[float]] = {1: [], 32: []}
        for _ in range(args.repeats):
            for align in (1, 32):
                sweep_path.MEMBER_ALIGN = align     # the layout _train_stages stacks with
                pools = [CandidatePool(h, SelectionRule()) for h in helios]
                t0 = time.perf_counter()
                problems, taken = sweep_path._band_set_problems(helios, cfg)
                sweep_path._train_stages(helios, problems, taken, pools, [[] for _ in helios],
                                         kind, cfg, [1e-2], [0], PathConfig())
                times[align].append(time.perf_counter() - t0)
                totals[align] += times[align][-1]
        print(f"{len(chunk)} heliostats, longest {longest} rows: align 1 "
              f"{[round(t, 1) for t in times[1]]} s, align 32 {[round(t, 1) for t in times[32]]} s",
              flush=True)
    print(f"total: align 1 {totals[1]:.1f} s, align 32 {totals[32]:.1f} s, "
          f"ratio {totals[32] / totals[1]:.3f}")


if __name__ == "__main__":
    main()
