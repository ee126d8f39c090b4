"""Benchmark: many heliostats' coarse fits, batched Levenberg-Marquardt vs scipy per heliostat.

Builds ``--heliostats`` synthetic Jülich-type heliostats (benchmarks/coarse_fit.py's generator,
one seed each: own true deviations, ``--min-rows`` to ``--max-rows`` measurements, 0.2 mrad spot
noise), fits preset ``--preset`` with the stage's default loss (soft_l1, 1 mrad) from the nominal
geometry, once with :func:`heliocal.pipeline.models.coarse.fit_heliostat` per heliostat (scipy) and once
with :func:`heliocal.pipeline.models.coarse.fit_heliostats_batched` in chunks of ``--batch-size``, in one
process on one thread, alternating, ``--repeats`` times. Prints the median wall time per
heliostat of each, their ratio, and the largest per-heliostat difference of the mean training
error and of the relative cost between the two. Usage::

    .venv/bin/python benchmarks/coarse_batched.py [--heliostats 256] [--batch-size 64]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from coarse_fit import make_data  # noqa: E402

from heliocal.pipeline.models.coarse import (fit_heliostat, fit_heliostats_batched,
                                             normal_errors_mrad)  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=256)
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--preset", default="static-20")
    ap.add_argument("--loss", default="soft_l1")
    ap.add_argument("--min-rows", type=int, default=70)
    ap.add_argument("--max-rows", type=int, default=280)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    cases = [make_data(int(rng.integers(args.min_rows, args.max_rows + 1)), seed=s)
             for s in range(args.heliostats)]
    cases.sort(key=lambda c: len(c[2]))  # as run_fit_coarse chunks them: similar row counts
    kw = dict(loss=args.loss, robust_start="never")

    def scipy_all():
        return [fit_heliostat(spec, nom, data, args.preset, **kw) for spec, nom, data in cases]

    def batched_all():
        out = []
        for i in range(0, len(cases), args.batch_size):
            chunk = cases[i:i + args.batch_size]
            out += fit_heliostats_batched([c[0] for c in chunk], [c[1] for c in chunk],
                                          [c[2] for c in chunk], args.preset, **kw)
        return out

    times = {"scipy": [], "batched": []}
    fits = {}
    for _ in range(args.repeats):
        for name, fn in (("scipy", scipy_all), ("batched", batched_all)):
            t0 = time.perf_counter()
            fits[name] = fn()
            times[name].append(time.perf_counter() - t0)
    n = len(cases)
    rows = sum(len(c[2]) for c in cases)
    print(f"{n} heliostats ({rows} measurements), {args.preset}, loss {args.loss}, batch size "
          f"{args.batch_size}, {args.repeats} repeats (median, one thread):")
    for name, ts in times.items():
        jev = np.mean([f.iterations for f in fits[name]])
        print(f"  {name:8s} {statistics.median(ts) / n * 1000:8.2f} ms per heliostat  "
              f"(total {statistics.median(ts):6.2f} s, {jev:.1f} Jacobians per fit)")
    print(f"  speed-up batched / scipy: {statistics.median(times['scipy']) / statistics.median(times['batched']):.1f}x")
    d_err, d_cost = [], []
    for (spec, _, data), a, b in zip(cases, fits["scipy"], fits["batched"]):
        ea = float(normal_errors_mrad(a.params, spec, data).mean())
        eb = float(normal_errors_mrad(b.params, spec, data).mean())
        d_err.append(abs(ea - eb))
        d_cost.append((b.cost - a.cost) / a.cost)
    print(f"  agreement: max |mean error difference| {max(d_err):.2e} mrad, relative cost "
          f"difference batched - scipy in [{min(d_cost):.2e}, {max(d_cost):.2e}]")


if __name__ == "__main__":
    main()
