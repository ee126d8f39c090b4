"""Benchmark: the daily update's stages alone, timed again and again on one finished full run.

``benchmarks/field.py --stages all`` runs the full method, the update and a rerun in one go, so
every timing of the update costs a full run first. This script keeps the full run: ``--build``
runs :func:`field.phase_commands`' ``full`` phase (ingest of the log without the update's rows,
split-knn, fit-coarse, sweep, report; the commands of ``field.py --stages all``) into
``OUT/full-<heliostats>-w<workers>`` once; every later call copies that work directory to
``OUT/update-copy`` and runs the ``update`` phase there (``ingest --append`` of the update's rows,
then split-knn, fit-coarse, sweep and report with ``--incremental``), ``--runs`` times, each on a
fresh copy, and prints each stage's wall time per run and the median per stage and of the totals.

The incremental stages compare their field key, which holds the SHA-256 of ``pipeline/**/*.py``,
with the full run's: the full run must have been built by the code that runs the update, or the
update computes every heliostat again (the script refuses, from the sweep's manifest). Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/update_phase.py --build
    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/update_phase.py --runs 3
    .venv/bin/python benchmarks/update_phase.py --until sweep   # a copy ready for the sweep

``--full DIR`` times the update on another kept full run (one built by other code, with that
code checked out). ``--until STAGE`` stops before STAGE, leaves the copy and prints STAGE's command (for a profiler).
Options as ``field.py``: ``--heliostats`` (200), ``--update-heliostats`` (20), ``--workers`` (2),
``--out`` (runs/field-bench).
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import field  # noqa: E402 - benchmarks/field.py, beside this script


def _phases(args, wd: Path) -> dict[str, list[list[str]]]:
    field_dir = args.out / f"field-{args.heliostats}"
    base, update, _ = field.split_update(field_dir, args.update_heliostats)
    opts = argparse.Namespace(solver="batched", sweep_args="", later="sweep,report")
    return field.phase_commands(opts, field_dir, wd, base, update, args.workers)


def _check_same_code(full: Path) -> None:
    """Refuse a full run whose sweep recorded other code than this checkout's."""
    from heliocal.pipeline.artifacts.revision import code_identity

    recorded = json.loads((full / "sweep.manifest.json").read_text())["incremental"]["code"]
    if recorded != code_identity():
        raise SystemExit(f"{full} was built by other code (pipeline/ differs): its update would "
                         "compute every heliostat again; run --build with this code")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=200)
    ap.add_argument("--update-heliostats", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=field.ROOT / "runs" / "field-bench")
    ap.add_argument("--build", action="store_true", help="run the full method into the kept "
                                                         "work directory first")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--until", default=None, help="stop before this update stage")
    ap.add_argument("--full", type=Path, default=None,
                    help="the kept full run (default OUT/full-<heliostats>-w<workers>)")
    args = ap.parse_args()
    info = field.write_field(args.out / f"field-{args.heliostats}", args.heliostats)
    full = args.full or args.out / f"full-{args.heliostats}-w{args.workers}"
    if args.build:
        shutil.rmtree(full, ignore_errors=True)
        for cmd in _phases(args, full)["full"]:
            wall, _ = field.run_stage(cmd)
            print(f"  full   {cmd[0]:11s} {wall:8.1f} s", flush=True)
    _check_same_code(full)
    copy = args.out / "update-copy"
    walls: dict[str, list[float]] = {}
    totals = []
    for run in range(1 if args.until else args.runs):
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(full, copy)
        total = 0.0
        for cmd in _phases(args, copy)["update"]:
            if cmd[0] == args.until:
                print("heliocal " + shlex.join(cmd))
                return
            wall, _ = field.run_stage(cmd)
            total += wall
            walls.setdefault(cmd[0], []).append(wall)
            print(f"  run {run + 1} {cmd[0]:11s} {wall:8.1f} s", flush=True)
        totals.append(total)
        print(f"  run {run + 1} total       {total:8.1f} s", flush=True)
    print(f"\n{info['heliostats']} heliostats, update of {args.update_heliostats}, "
          f"{args.workers} workers: median of {len(totals)} runs")
    for stage, w in walls.items():
        print(f"{stage:11s} {statistics.median(w):6.1f} s   ({', '.join(f'{x:.1f}' for x in w)})")
    print(f"{'total':11s} {statistics.median(totals):6.1f} s   "
          f"({', '.join(f'{x:.1f}' for x in totals)})")


if __name__ == "__main__":
    main()
