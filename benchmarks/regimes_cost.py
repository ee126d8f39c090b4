"""Benchmark: what regime detection (with the refit of heliostats with episodes and the
regime-aware candidates of heliostats with breaks) adds to ``fit-coarse``.

Simulates a field (default 200 juelich heliostats, 100 to 400 measurements each over one year,
half of them dynamic as in benchmarks/field.py, and 20 % with steps, 20 % with episodes, 10 % with
a drift), runs ``ingest`` and ``split-knn`` once, then ``fit-coarse`` alternately *without*
detection (``fit_coarse._SKIP_REGIMES``, a hook for this benchmark only: the stage with
nothing detected, refitted or offered as a candidate), with detection and the episode refit but without the
candidates (``"detect"``), and *with* both (``"candidates"``, the default), ``--repeats`` times
each, every run in a fresh Python process as ``heliocal fit-coarse`` runs, and prints the median
times and their ratios from this one run: the stage's own time (``run_fit_coarse``, measured in
that process) and the whole process's wall time (what ``benchmarks/field.py`` times for the CLI).
Fresh processes, because runs in one process share the workers' fork server and the heap of the
runs before them, which is not what a user runs (docs/experiments/regimes-cost.md). ``--workdir`` takes an ingested and split work directory instead (the
issue's benchmark: ``benchmarks/field.py``'s field, whose fit-coarse runs ``--preset static-20``
with 2 workers; its dynamic heliostats drift, so about half of them get candidates). Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/regimes_cost.py \
        [--heliostats 200] [--repeats 3] [--out runs/regimes-cost] \
        [--workdir runs/field-bench/run-2000-w2 --preset static-20] [--workers 2]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "regimes-cost")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="an ingested and split work directory to use instead of simulating")
    ap.add_argument("--preset", default="auto")
    ap.add_argument("--workers", type=int, default=1)
    a = ap.parse_args(argv)

    from heliocal.pipeline.artifacts.schemas import HELIOSTATS as HELIOSTATS_SCHEMA
    from heliocal.pipeline.artifacts.schemas import REGIME_PARAMS, REGIMES
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.changes import Changes
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.simulate import write_field
    from heliocal.pipeline.stages.split import run_split

    work = a.workdir or a.out / "work"
    if a.workdir is None and not (work / "split.parquet").exists():
        field = simulate_field(a.heliostats, seed=a.seed, measurements=(100, 400),
                               dynamic_fraction=0.5,
                               changes=Changes(step_fraction=0.2, episode_fraction=0.2,
                                               drift_fraction=0.1))
        write_field(field, a.out / "field", overwrite=True)
        run_ingest([a.out / "field" / "paint"], work, IngestOptions())
        run_split(work, seed=a.seed)

    steps = {"without": "off", "detection": "detect", "with": "candidates"}
    times = {mode: [] for mode in steps}
    walls = {mode: [] for mode in steps}
    for _ in range(a.repeats):
        for mode, regime_steps in steps.items():
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", _CHILD, str(work), regime_steps,
                                  a.preset, str(a.workers)], check=True, capture_output=True,
                                 text=True).stdout
            walls[mode].append(time.perf_counter() - t0)
            times[mode].append(float(out.split()[-1]))
    regimes = read_artifact(work, REGIMES)
    candidates = read_artifact(work, REGIME_PARAMS)
    refit = regimes.loc[regimes["kind"] == "episode", "heliostat_id"].nunique()
    before, after = statistics.median(times["without"]), statistics.median(times["with"])
    detect = statistics.median(times["detection"])
    wall = {mode: statistics.median(w) for mode, w in walls.items()}
    n = read_artifact(work, HELIOSTATS_SCHEMA)["heliostat_id"].nunique()
    print(f"fit-coarse --preset {a.preset} --workers {a.workers} on {n} heliostats ({work}), "
          f"{a.repeats} runs each (alternating, each in a fresh process); the stage's time:")
    print(f"  without detection: median {before:.2f} s  ({', '.join(f'{t:.2f}' for t in times['without'])})")
    print(f"  detection, no candidates: median {detect:.2f} s  "
          f"({', '.join(f'{t:.2f}' for t in times['detection'])}); ratio {detect / before:.3f}")
    print(f"  with detection:    median {after:.2f} s  ({', '.join(f'{t:.2f}' for t in times['with'])})")
    print(f"  ratio with/without: {after / before:.3f}  (+{100 * (after / before - 1):.1f} %); "
          f"{refit} heliostats refitted without their episodes; "
          f"{int((regimes['cause'] == 'detected').sum())} detected breaks, "
          f"{int((regimes['kind'] == 'outlier').sum())} outliers; "
          f"{candidates['heliostat_id'].nunique()} heliostats with regime-aware candidates, "
          f"{candidates.loc[candidates['selected'], 'heliostat_id'].nunique()} selected")
    print(f"  whole processes (median wall): without {wall['without']:.2f} s, detection "
          f"{wall['detection']:.2f} s ({wall['detection'] / wall['without']:.3f}), with "
          f"{wall['with']:.2f} s ({wall['with'] / wall['without']:.3f})")
    return 0


#: One run in a fresh process: argv workdir, regime steps (``off``: none, through the stage's
#: benchmark hook), preset, workers; prints the stage's own time [s] last.
_CHILD = """
import sys, time
from heliocal.pipeline.stages import fit_coarse
if __name__ == "__main__":
    work, steps, preset, workers = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    if steps == "off":
        fit_coarse._SKIP_REGIMES = True
        steps = "candidates"
    t0 = time.perf_counter()
    fit_coarse.run_fit_coarse(work, regime_steps=steps, preset=preset, workers=workers)
    print(f"{time.perf_counter() - t0:.3f}")
"""


if __name__ == "__main__":
    sys.exit(main())
