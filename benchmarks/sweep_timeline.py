"""Benchmark: where a ``sweep`` run's wall time goes, as a timeline of the main process's phases
and of each worker's tasks (docs/experiments/sweep-update-cost.md).

Copies WORKDIR (a work directory after ``fit-coarse``, e.g. one that ``benchmarks/field.py
--stages all`` left before its update's sweep) to ``--copy`` and runs the sweep stage there in
this process, with each of these functions timed where it runs (the workers are forked from a
fork server that imports this module, so the timers are in them too): reading the inputs, the
plan (the per-heliostat digests of ``--incremental``), the pool's map, each training chunk
(``_select_chunk``) with its band sets' training (``train_candidates``) and its GP fits, the
forward-in-time pass and writing the outputs. Prints one line per call: process, start and end
[s since this process started], duration, name. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/sweep_timeline.py WORKDIR
        [--copy /tmp/sweep-timeline] [--workers 2] [--full] [--same-code]

``--full``: without ``--incremental``. ``--same-code``: take the code that the previous sweep
recorded as this run's (profiling only: the update of a work directory swept by other code
would otherwise train every heliostat again; never use its results).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time

T0 = float(os.environ.setdefault("SWEEP_TIMELINE_T0", repr(time.time())))

import heliocal.pipeline.stages.sweep as sweep  # noqa: E402 - after the clock starts


def _stamp(name: str, t0: float, t1: float) -> None:
    print(f"[{os.getpid()}] {t0 - T0:8.2f} -> {t1 - T0:8.2f} ({t1 - t0:7.2f} s) {name}",
          flush=True)


def _timed(name: str, label: str | None = None) -> None:
    """Replace ``sweep.<name>`` by a timed wrapper (looked up as a module global by its callers,
    in this process and in the workers forked after this module was imported)."""
    func = getattr(sweep, name)

    def wrapper(*args, **kwargs):
        t0 = time.time()
        try:
            return func(*args, **kwargs)
        finally:
            _stamp(label or name, t0, time.time())

    setattr(sweep, name, wrapper)


_stamp("imports (heliocal's sweep stage)", T0, time.time())
for _name in ("read_sweep_inputs", "_plan", "map_tasks", "_select_chunk", "train_candidates",
              "add_sweep_time_split", "apply_forward_checks", "write_sweep_outputs"):
    _timed(_name)
_timed("fit_heliostat_gps", "gp (one heliostat)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir")
    ap.add_argument("--copy", default="/tmp/sweep-timeline")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--full", action="store_true", help="without --incremental")
    ap.add_argument("--same-code", action="store_true",
                    help="take the previous sweep's recorded code as this run's (profiling only)")
    args = ap.parse_args()
    shutil.rmtree(args.copy, ignore_errors=True)
    shutil.copytree(args.workdir, args.copy)
    if args.same_code:
        from heliocal.pipeline.artifacts import incremental

        manifest = json.loads(open(os.path.join(args.copy, "sweep.manifest.json")).read())
        incremental._CODE = manifest["incremental"]["code"]
    t0 = time.time()
    summary = sweep.run_sweep(args.copy, study=0, workers=args.workers,
                              incremental=not args.full)
    _stamp(f"run_sweep {summary['incremental']}", t0, time.time())


if __name__ == "__main__":
    main()
