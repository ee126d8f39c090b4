"""Benchmark: split-knn's incremental merge (``split._split_increment``) on a work directory, 20
heliostats computed and the others reused; its check for reused heliostats the previous run
skipped as it was before 6893291 (a set of the previous split's heliostats built once per reused
heliostat, inlined here as ``before``) and as it is (``after``), alternating twice in one process,
then the whole merge. Usage (benchmarks/field.py's 2,000-heliostat work directory)::

    .venv/bin/python benchmarks/split_increment.py runs/field-bench/run-2000-all-w2
"""
import sys, time
from pathlib import Path
import pandas as pd
from heliocal.pipeline.artifacts.incremental import Increment
from heliocal.pipeline.artifacts.schemas import MEASUREMENTS, SPLIT
from heliocal.pipeline.artifacts.store import read_artifact
from heliocal.pipeline.stages import split as sp
from heliocal.pipeline.stages.rerun import split_options

wd = Path(sys.argv[1])
meas = read_artifact(wd, MEASUREMENTS, columns=sp._INPUT_COLUMNS)
ids = sorted(meas["heliostat_id"].astype(str).unique())
plan = Increment(compute=ids[:20], reuse=ids[20:])
opts = split_options()
prev = read_artifact(wd, SPLIT)
def before():
    kept = sp.reused_rows(prev, plan.reuse)
    return [h for h in plan.reuse if h not in set(kept["heliostat_id"])]
def after():
    kept = sp.reused_rows(prev, plan.reuse)
    s = set(kept["heliostat_id"])
    return [h for h in plan.reuse if h not in s]
for f in (before, after, before, after):
    t = time.perf_counter(); out = f(); print(f.__name__, f"{time.perf_counter() - t:.2f} s", len(out))
t = time.perf_counter(); table, skipped = sp._split_increment(wd, meas, plan, opts)
print("whole merge (after)", f"{time.perf_counter() - t:.2f} s", len(table))
