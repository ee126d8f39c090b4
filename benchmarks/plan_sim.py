"""Does ``heliocal plan`` choose better rows than random times? A simulated field with ground truth.

A field of static heliostats (``heliocal simulate``'s model) with 10 calibration rows each, spread
over the year before the plan the way the simulator schedules them, is ingested and fitted
(``fit-coarse --preset PRESET`` on all rows: ``split-knn --n-test 0 --n-val 0``). Then 10 more
rows per heliostat are measured (simulated, same noise) in the plan's days, chosen four ways:

* ``plan``: ``heliocal plan --budget 10*H --max-per-heliostat 10`` (10 rows for every heliostat);
* ``plan-free``: ``heliocal plan --budget 10*H`` (the same budget spent where it helps most);
* ``plan-fieldprior``: as ``plan``, with the covariance's prior scale per parameter the RMS of the
  simulated field's true deviations (what a field prior learned from this field, issue 34,
  would approach; fit-coarse's prior is 2 to 50 times wider than the simulator's deviations);
* ``random``: per planned row, the same day at a random daylight time (sun above the plan's
  minimum elevation) on a target drawn from the heliostat's logged rows (as the plant uses its
  targets), seeds 0..S-1;
* ``random-same-target``: the same on the planned row's target (the plan's choice of target
  kept: only the time is random), seeds 0..S-1;
* ``historical``: times of day and targets drawn from the field's logged rows (the hours the
  plant has measured at), on random days of the plan, seeds 0..S-1.

Each arm's 20 rows per heliostat are fitted again the same way, and each heliostat's year-round
test error is the mean aim error of its fitted model against the noiseless true geometry over a
dense grid of a year's sun positions (every 3rd day, every 10 minutes, sun above 10 deg; aims at
the lower tower target; ``models.plan_check.year_error_mrad``). Printed: per arm the field's mean
and median year-round error and the ratio to ``random`` (mean over its seeds), and the covariance's
expected year-round errors from the plan's summary. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/plan_sim.py \\
        [--heliostats 40] [--fields 1] [--seeds 5] [--noise 0.4] [--preset static-6] \\
        [--deviations static-6] [--start 2024-03-01] [--days 7] [--seed 0] [--noise-seed 12345]
        [--out runs/plan-sim]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def _fit(field_, folder: Path, preset: str) -> dict:
    """Write, ingest, split (all rows train) and fit ``field_``; the selected parameters."""
    from heliocal.pipeline.stages.fit_coarse import load_selected_parameters, run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.simulate import write_field
    from heliocal.pipeline.stages.split import run_split

    shutil.rmtree(folder, ignore_errors=True)
    write_field(field_, folder / "field")
    wd = folder / "work"
    run_ingest([folder / "field"], wd)
    run_split(wd, n_test=0, n_val=0)
    # the rolling-origin evaluation scores the selected fit and leaves it as it is: not needed
    run_fit_coarse(wd, preset=preset, workers=1, rolling_origins=0)
    return load_selected_parameters(wd)


def _with_rows(field_, rows: pd.DataFrame, noise_seed: int = 12345):
    """The field with ``rows`` (heliostat_id, time_utc, target) measured as well, their noise
    drawn from ``noise_seed``."""
    from heliocal.pipeline.models.plan_check import simulated_rows
    from heliocal.pipeline.models.simulator import SimulatedField

    rng = np.random.default_rng(noise_seed)     # the same noise draws for every arm's k-th row
    frames = [field_.measurements]
    for hid, g in rows.groupby("heliostat_id", sort=True):
        frames.append(simulated_rows(field_, field_.heliostats[hid], g["time_utc"],
                                     list(g["target"]), rng))
    meas = pd.concat(frames, ignore_index=True)
    meas["measurement_id"] = [str(100001 + i) for i in range(len(meas))]
    meas = meas.sort_values(["timestamp", "heliostat_id"], kind="mergesort").reset_index(drop=True)
    return SimulatedField(field_.reference, field_.targets, field_.heliostats, meas,
                          field_.settings)


def _daylight_minutes(reference, start: str, days: int, min_elevation: float) -> dict:
    """Per solar day of the plan: its UTC minutes with the sun above ``min_elevation``."""
    from heliocal.pipeline.models.schedule import solar_day_start
    from heliocal.pipeline.physics.sun import spa_sun_position

    first = solar_day_start(start, reference[1])
    t = pd.date_range(first, first + pd.Timedelta(days=days), freq="1min", inclusive="left")
    _, el = spa_sun_position(t, *reference)
    day = ((t - first) // pd.Timedelta(days=1)).to_numpy()
    return {d: t[(day == d) & (el > min_elevation)] for d in range(days)}


def random_rows(field_, plan: pd.DataFrame, daylight: dict, seed: int,
                same_target: bool) -> pd.DataFrame:
    """Each planned row on its day at a random daylight minute, on the planned target or on one
    of the heliostat's logged rows' targets (drawn with their frequencies)."""
    rng = np.random.default_rng(seed)
    times = [daylight[int(d)][rng.integers(len(daylight[int(d)]))] for d in plan["day"]]
    if same_target:
        targets = list(plan["target"])
    else:
        logged = field_.measurements.groupby("heliostat_id")["target_name"]
        pools = {h: g.to_numpy() for h, g in logged}
        targets = [pools[h][rng.integers(len(pools[h]))] for h in plan["heliostat_id"]]
    return pd.DataFrame({"heliostat_id": plan["heliostat_id"].to_numpy(), "time_utc": times,
                         "target": targets})


def historical_rows(field_, plan: pd.DataFrame, daylight: dict, seed: int) -> pd.DataFrame:
    """As many rows per heliostat as the plan gives it, at the times of day (UTC) and on the
    targets of random logged rows of the field, on random days of the plan (times with the sun
    too low that day are drawn again)."""
    rng = np.random.default_rng(seed)
    logged = field_.measurements
    out = []
    for hid, n in plan["heliostat_id"].value_counts().sort_index().items():
        while sum(1 for r in out if r[0] == hid) < n:
            r = logged.iloc[rng.integers(len(logged))]
            day = int(rng.integers(len(daylight)))
            t = daylight[day][0].normalize() + (r["timestamp"] - r["timestamp"].normalize())
            if len(daylight[day]) and daylight[day][0] <= t <= daylight[day][-1]:
                out.append((hid, t, r["target_name"]))
    return pd.DataFrame(out, columns=["heliostat_id", "time_utc", "target"])


def field_prior_scale(field_):
    """The prior scale (28,) per parameter as the RMS over the field of true minus nominal,
    floored at 1 % of fit-coarse's prior (a run_plan ``prior``)."""
    import torch

    from heliocal.pipeline.models.coarse import prior_sigma

    dev = torch.stack([h.true - h.nominal for h in field_.heliostats.values()]).numpy()
    rms = np.sqrt((dev ** 2).mean(axis=0))
    return lambda row, nominal: np.maximum(rms, 0.01 * prior_sigma(nominal))


def year_errors(field_, fitted: dict, sun: np.ndarray) -> pd.Series:
    from heliocal.pipeline.models.plan_check import year_error_mrad

    aim = field_.targets["tower_target_lower"]["center_enu"]
    return pd.Series({hid: year_error_mrad(fitted[hid]["params"], h, sun, aim)[0]
                      for hid, h in field_.heliostats.items()})


def run_field(a, seed: int) -> tuple[dict, dict, pd.Series]:
    """One simulated field (seed ``seed``): per arm the heliostats' year-round errors (a list of
    Series, one per run), the plans' summaries and the errors with the 10 rows alone."""
    from heliocal.pipeline.models.schedule import year_sun_grid
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.stages.plan import run_plan

    h = a.heliostats
    out = a.out / f"field-{seed}"
    field_ = simulate_field(h, seed=seed, measurements=(10, 10), dynamic_fraction=0.0,
                            noise_mrad=a.noise, deviations=a.deviations, start="2023-01-01",
                            end="2024-01-01")
    base = _fit(field_, out / "base", a.preset)
    wd = out / "base" / "work"
    dense = year_sun_grid(field_.reference, a.start, 3, 10, 10.0)
    daylight = _daylight_minutes(field_.reference, a.start, a.days, 10.0)
    arms: dict[str, list[pd.Series]] = {}
    summaries = {}
    for arm, cap, prior in (("plan", 10, {}), ("plan-free", None, {}),
                            ("plan-fieldprior", 10, {"prior": field_prior_scale(field_)})):
        summaries[arm] = run_plan(wd, start=a.start, days=a.days, budget=10 * h,
                                  max_per_heliostat=cap, workers=1, **prior)
        plan = pd.read_parquet(wd / "plan.parquet")
        if arm == "plan":
            capped = plan
        fitted = _fit(_with_rows(field_, plan, a.noise_seed), out / arm, a.preset)
        arms[arm] = [year_errors(field_, fitted, dense)]
    for s in range(a.seeds):
        for arm, rows in (("random", random_rows(field_, capped, daylight, s, False)),
                          ("random-same-target", random_rows(field_, capped, daylight, s, True)),
                          ("historical", historical_rows(field_, capped, daylight, s))):
            fitted = _fit(_with_rows(field_, rows, a.noise_seed), out / f"{arm}-{s}", a.preset)
            arms.setdefault(arm, []).append(year_errors(field_, fitted, dense))
    return arms, summaries, year_errors(field_, base, dense)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=40, help="per field")
    ap.add_argument("--fields", type=int, default=1, help="fields, seeds SEED..SEED+FIELDS-1")
    ap.add_argument("--seeds", type=int, default=5, help="runs of the random arms per field")
    ap.add_argument("--noise", type=float, default=0.4, help="beam noise per axis [mrad]")
    ap.add_argument("--preset", default="static-6")
    ap.add_argument("--deviations", default="static-6", help="simulate_field's deviations")
    ap.add_argument("--start", default="2024-03-01")
    ap.add_argument("--days", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0, help="the first field's seed")
    ap.add_argument("--noise-seed", type=int, default=12345,
                    help="seed of the new rows' noise (shared by every arm and random seed)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "plan-sim")
    a = ap.parse_args(argv)
    print(f"{a.fields} field(s) of {a.heliostats} static heliostats, 10 rows each over 2023 "
          f"(noise {a.noise} mrad, deviations {a.deviations}); fit-coarse --preset {a.preset}; "
          f"plan {a.start} + {a.days} days; year-round test: every 3rd day, every 10 minutes")
    pooled: dict[str, list[float]] = {}
    for k in range(a.fields):
        arms, summaries, before = run_field(a, a.seed + k)
        arms = {"10 rows": [before], **arms}
        random_mean = float(np.mean([e.mean() for e in arms["random"]]))
        print(f"\nfield seed {a.seed + k}:")
        print(f"{'arm':19s} {'runs':>4s} {'mean mrad':>10s} {'median':>8s} {'x random':>9s}")
        for arm, runs in arms.items():
            m = float(np.mean([e.mean() for e in runs]))
            med = float(np.mean([e.median() for e in runs]))
            spread = (f"  (runs {min(e.mean() for e in runs):.4f}-"
                      f"{max(e.mean() for e in runs):.4f})" if len(runs) > 1 else "")
            print(f"{arm:19s} {len(runs):4d} {m:10.4f} {med:8.4f} {m / random_mean:9.3f}{spread}")
            pooled.setdefault(arm, []).append(m)
        for arm, s in summaries.items():
            rows = pd.Series([x["planned_rows"] for x in s["heliostats"]])
            print(f"  {arm}: expected (covariance) now {s['expected_error_now_mrad']:.4f}, after "
                  f"plan {s['expected_error_after_plan_mrad']:.4f}, after random "
                  f"{s['expected_error_after_random_mrad']:.4f} mrad; spacing {s['spacing_s']} s; "
                  f"rows per heliostat {rows.min()}-{rows.max()} (median {rows.median():g})")
    if a.fields > 1:
        r = np.mean(pooled["random"])
        print(f"\nall {a.fields} fields (mean of the fields' means; x random):")
        for arm, ms in pooled.items():
            print(f"{arm:19s} {np.mean(ms):10.4f} {np.mean(ms) / r:9.3f}  (per field: "
                  + ", ".join(f"{m / x:.3f}" for m, x in zip(ms, pooled["random"])) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
