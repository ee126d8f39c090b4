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

``--arms stages,command`` times, in each run, the update both ways on fresh copies, alternating
which goes first: ``stages`` (the commands above, one process each) and ``command`` (``heliocal
update UPDATE_LOG --workdir COPY --workers W``: the same stages in one process, with the options
each stage recorded); it prints the medians of both and their ratio.

``--full DIR`` times the update on another kept full run (one built by other code, with that
code checked out). ``--until STAGE`` stops before STAGE, leaves the copy and prints STAGE's
command (for a profiler).
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


def _update_command(args, wd: Path) -> list[str]:
    """``heliocal update`` of the update's rows (the ``update`` phase's first command's log)."""
    log = _phases(args, wd)["update"][0][1]
    return ["update", log, "--workdir", str(wd), "--workers", str(args.workers)]


def _time_arm(args, arm: str, full: Path, copy: Path, run: int, walls: dict) -> float:
    """One update on a fresh copy of ``full``, the stages one by one or as one command; the
    wall times go into ``walls`` (stage or ``update`` -> list); return the total."""
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(full, copy)
    commands = _phases(args, copy)["update"] if arm == "stages" else [_update_command(args, copy)]
    total = 0.0
    for cmd in commands:
        wall, _ = field.run_stage(cmd)
        total += wall
        walls.setdefault(cmd[0], []).append(wall)
        print(f"  run {run + 1} {arm:8s} {cmd[0]:11s} {wall:8.1f} s", flush=True)
    print(f"  run {run + 1} {arm:8s} total       {total:8.1f} s", flush=True)
    return total


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
    ap.add_argument("--arms", default="stages",
                    help="stages (one process per stage), command (heliocal update), or both")
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
    if args.until:
        cmd = next(c for c in _phases(args, copy)["update"] if c[0] == args.until)
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(full, copy)
        for c in _phases(args, copy)["update"]:
            if c[0] == args.until:
                break
            field.run_stage(c)
        print("heliocal " + shlex.join(cmd))
        return
    arms = args.arms.split(",")
    walls: dict[str, list[float]] = {}
    totals: dict[str, list[float]] = {arm: [] for arm in arms}
    for run in range(args.runs):
        for arm in (arms if run % 2 == 0 else arms[::-1]):   # alternate which goes first
            totals[arm].append(_time_arm(args, arm, full, copy, run, walls))
    print(f"\n{info['heliostats']} heliostats, update of {args.update_heliostats}, "
          f"{args.workers} workers: median of {args.runs} runs")
    for stage, w in walls.items():
        print(f"{stage:11s} {statistics.median(w):6.1f} s   ({', '.join(f'{x:.1f}' for x in w)})")
    for arm, t in totals.items():
        print(f"{'total ' + arm:15s} {statistics.median(t):6.1f} s   "
              f"({', '.join(f'{x:.1f}' for x in t)})")
    if len(arms) == 2:
        ratios = [b / a for a, b in zip(*totals.values())]
        print(f"{arms[1]} / {arms[0]}: median of the runs' ratios "
              f"{statistics.median(ratios):.3f} ({', '.join(f'{r:.3f}' for r in ratios)})")


if __name__ == "__main__":
    main()
