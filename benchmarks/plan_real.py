"""Does ``heliocal plan --from-existing`` choose better rows than random ones? Real Jülich logs.

For each dataset of ``../shared/data/juelich`` (the PAINT heliostats; the CSV log with the PAINT
properties) it runs ``ingest``, ``split-knn --n-test 20 --n-val 10`` (each heliostat's 20 rows
most isolated in sun position are its test rows; its training and validation rows are the pool),
and ``fit-coarse --preset PRESET`` (default ``auto``: each heliostat's preset chosen on its
validation rows; the point the plan's covariance is linearized at, and its noise scale). It keeps the heliostats whose pool has at least ``--min-pool`` rows (enough to choose
from), then ``plan --from-existing --budget 10*H --max-per-heliostat 10`` over the logs' whole
span chooses 10 pool rows per heliostat. Each choice of 10 rows is fitted with fit-coarse's fit
(``models.coarse_presets.fit_presets``: the heliostat's selected preset, the one the plan's covariance
rests on, fit-coarse's loss and robust start) and scored on the heliostat's test rows (mean
error_mrad):

* ``plan``: the 10 rows ``plan --from-existing`` chose (it sees the rows' sun positions, steps and
  targets, never their test rows);
* ``random``: 10 pool rows drawn at random, seeds 0..S-1 (default 20);
* ``first-10``: the heliostat's first 10 pool rows in time (what the plant's own schedule gave);
* ``pool``: every pool row (the reference with all the data).

Printed per dataset: the mean over heliostats of each choice's test error, the ratio plan /
random (random: the mean over seeds), the median per-heliostat ratio and the share of heliostats
where the plan beats the random mean. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/plan_real.py \\
        [--preset auto] [--seeds 20] [--min-pool 20] [--out runs/plan-real]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "juelich"

DATASETS = {
    "juelich-paint": ([SHARED / "paint"], None),
    "juelich-csv": ([SHARED / "csv" / "juelich_calibration_log.csv"], SHARED / "paint"),
}


def _prepare(work: Path, sources, properties, preset: str) -> None:
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.split import run_split

    if not (work / "coarse_params.parquet").exists():
        run_ingest(sources, work, IngestOptions(properties=properties) if properties else None)
        run_split(work, n_test=20, n_val=10)
        # the rolling-origin evaluation scores the selected fits and leaves them as they are
        run_fit_coarse(work, preset=preset, workers=1, rolling_origins=0)


def _test_errors(work: Path, choices: dict, presets: dict) -> pd.Series:
    """Per heliostat: the mean test error of its preset ``presets[hid]`` fitted on its rows
    ``choices[hid]`` (measurement ids) the way fit-coarse fits (batched, its loss and start)."""
    from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS, SPLIT
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.coarse import MeasurementBatch, predict
    from heliocal.pipeline.models.coarse_presets import fit_presets
    from heliocal.pipeline.physics.parameters import HeliostatSpec, nominal_parameters
    from heliocal.pipeline.stages.fit_coarse import coarse_fit_options

    meas = read_artifact(work, MEASUREMENTS)
    split = read_artifact(work, SPLIT)
    meas = meas.merge(split[["heliostat_id", "measurement_id", "split"]], how="inner")
    helio = read_artifact(work, HELIOSTATS).set_index("heliostat_id")
    opts = {k: v for k, v in coarse_fit_options(work).items() if k != "solver"}
    out = {}
    for preset in sorted(set(presets.values())):
        keys = [h for h in choices if presets[h] == preset]
        specs, nominals, trains, tests = [], [], [], []
        for hid in keys:
            rows = meas[meas["heliostat_id"] == hid]
            hrow = helio.loc[hid].copy()
            hrow["heliostat_id"] = hid
            specs.append(HeliostatSpec.from_row(hrow))
            nominals.append(nominal_parameters(hrow))
            trains.append(MeasurementBatch.from_frame(rows[rows["measurement_id"].isin(
                set(choices[hid]))]))
            tests.append(MeasurementBatch.from_frame(rows[rows["split"] == "test"]))
        fits = fit_presets(specs, nominals, trains, [preset], solver="batched", **opts)
        out.update({k: float(predict(f[0].params, s, t)["error_mrad"].mean())
                    for k, f, s, t in zip(keys, fits, specs, tests)})
    return pd.Series(out).sort_index()


def run_dataset(name: str, work: Path, sources, properties, preset: str, seeds: int,
                min_pool: int) -> None:
    from heliocal.pipeline.artifacts.schemas import MEASUREMENTS, SPLIT
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.regime_fit import base_preset
    from heliocal.pipeline.stages.plan import run_plan

    _prepare(work, sources, properties, preset)
    meas = read_artifact(work, MEASUREMENTS).merge(read_artifact(work, SPLIT), how="inner")
    pool = meas[meas["split"] != "test"].sort_values(["heliostat_id", "timestamp"])
    sizes = pool.groupby("heliostat_id").size()
    ids = sorted(sizes[sizes >= min_pool].index)
    start = str(pool["timestamp"].min().date())
    days = (pool["timestamp"].max() - pool["timestamp"].min()).days + 2
    summary = run_plan(work, start=start, days=days, from_existing=True, budget=10 * len(ids),
                       max_per_heliostat=10, heliostats=ids, workers=1)
    presets = {h["heliostat_id"]: base_preset(h["coarse_model"].split(":")[-1])
               for h in summary["heliostats"]}
    plan = pd.read_parquet(work / "plan.parquet")
    by_h = {h: list(g["measurement_id"]) for h, g in plan.groupby("heliostat_id")}
    rows_of = {h: list(g["measurement_id"]) for h, g in pool[pool["heliostat_id"].isin(ids)]
               .groupby("heliostat_id")}
    errors = {"plan": _test_errors(work, by_h, presets),
              "first-10": _test_errors(work, {h: r[:10] for h, r in rows_of.items()}, presets),
              "pool": _test_errors(work, rows_of, presets)}
    random = []
    for s in range(seeds):
        rng = np.random.default_rng(s)
        pick = {h: list(rng.choice(r, size=10, replace=False)) for h, r in rows_of.items()}
        random.append(_test_errors(work, pick, presets))
    errors["random"] = pd.concat(random, axis=1).mean(axis=1)
    r = errors["plan"] / errors["random"]
    print(f"\n== {name}: {len(ids)} heliostats with >= {min_pool} pool rows (20 kNN test rows "
          f"each), fit-coarse --preset {preset} (presets: "
          f"{pd.Series(presets).value_counts().to_dict()}); plan over {start} + {days} days "
          f"chose {summary['planned_rows']} rows")
    for arm in ("plan", "random", "first-10", "pool"):
        e = errors[arm]
        extra = (f"  (seeds: {min(x.mean() for x in random):.3f}-"
                 f"{max(x.mean() for x in random):.3f})" if arm == "random" else "")
        print(f"  {arm:9s} mean test error {e.mean():8.3f} mrad, median {e.median():7.3f}{extra}")
    print(f"  plan / random: mean {errors['plan'].mean() / errors['random'].mean():.3f}, median "
          f"per heliostat {r.median():.3f}; plan better than the random mean on "
          f"{int((r < 1).sum())} of {len(r)}; random seeds the plan beats on average "
          f"{np.mean([(errors['plan'] < x).mean() for x in random]):.2f}")
    print(f"  expected (covariance) after plan {summary['expected_error_after_plan_mrad']:.3f}, "
          f"after random {summary['expected_error_after_random_mrad']:.3f} mrad")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="auto")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--min-pool", type=int, default=20)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "plan-real")
    a = ap.parse_args(argv)
    logging.getLogger("heliocal").setLevel(logging.ERROR)
    for name, (sources, properties) in DATASETS.items():
        run_dataset(name, a.out / f"{name}-{a.preset}", sources, properties, a.preset, a.seeds,
                    a.min_pool)
    return 0


if __name__ == "__main__":
    sys.exit(main())
