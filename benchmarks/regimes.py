"""Benchmark: how well fit-coarse's regime detection finds simulated steps and episodes, and how
often it raises a false alarm on heliostats that do not change.

Simulates a field (``heliocal simulate``'s model, juelich heliostats, no dynamic disturbances)
where a share of the heliostats gets regime steps (1-4 mrad on actuator zero points or tilts) and
a share gets episodes (2-15 mrad for 1-4 days), a share has the simulator's dynamic
disturbances (seasonal tilt, actuator drift, gear error, thermal tilt), the rest stays static; runs ``ingest``,
``split-knn`` and ``fit-coarse`` (which writes regimes.parquet) and scores the detected breaks
against ground_truth.json with :func:`heliocal.pipeline.models.changes.score_detection`:

* recall: steps and episodes whose effect on the mirror normal is >= 1 mrad and that have
  measurements (>= 2 rows on the changed side) found by a break within +-3 days of the event's
  date (``recall``) and of the first measurement at or after it (``recall_first_row``: where
  the calibration schedule has no measurement for days, no detector can do better);
* false alarms per 10 heliostat-years on the static heliostats (breaks detected there);
* the regime-aware coarse models (models/regime_fit.py): per kind of heliostat (static, steps,
  episodes only, drift, dynamic without events) the plain fit's and the final selected model's
  mean test error (their median over heliostats), how often each candidate is selected, and the
  heliostats whose test error got worse by more than 2 %; with ``--drift-fraction`` a share of
  the heliostats also drifts (1-3 mrad/year on a zero point).

Usage (measured figures are quoted under the shared lock)::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/regimes.py \
        [--heliostats 60] [--measurements 600] [--years 2] [--noise-mrad 0.6] [--seed 0]
        [--dynamic-fraction 0.2] [--drift-fraction 0] [--penalty-factors 1,2,3,4]
        [--out runs/regimes-bench] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def run(n: int, measurements: int, years: int, noise_mrad: float, seed: int, out: Path,
        step_fraction: float = 0.3, episode_fraction: float = 0.3, dynamic_fraction: float = 0.2,
        penalty_factors: tuple[float, ...] = (), drift_fraction: float = 0.0) -> dict:
    from heliocal.pipeline.artifacts.schemas import (COARSE_PARAMS, COARSE_PREDICTIONS, HELIOSTATS,
                                                     MEASUREMENTS, REGIMES, SPLIT)
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.models.changes import Changes, score_detection
    from heliocal.pipeline.models.simulator import simulate_field
    from heliocal.pipeline.models.regime_fit import base_preset
    from heliocal.pipeline.stages.fit_coarse import detect_coarse_regimes, run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.simulate import write_field
    from heliocal.pipeline.stages.split import run_split

    t0 = time.perf_counter()
    end = f"{2023 + years}-01-01"
    field = simulate_field(n, seed=seed, measurements=(measurements, measurements),
                           dynamic_fraction=dynamic_fraction, noise_mrad=noise_mrad, end=end,
                           changes=Changes(step_fraction=step_fraction,
                                           episode_fraction=episode_fraction,
                                           drift_fraction=drift_fraction))
    write_field(field, out / "field", overwrite=True)
    t_sim = time.perf_counter() - t0
    work = out / "work"
    run_ingest([out / "field" / "paint"], work, IngestOptions())
    run_split(work, seed=seed)
    t1 = time.perf_counter()
    run_fit_coarse(work)
    t_fit = time.perf_counter() - t1
    regimes = read_artifact(work, REGIMES)
    meas = read_artifact(work, MEASUREMENTS, columns=["heliostat_id", "measurement_id", "timestamp"])
    split = read_artifact(work, SPLIT, columns=["heliostat_id", "measurement_id", "split"])
    seen = meas.merge(split, on=["heliostat_id", "measurement_id"])
    seen = seen[seen["split"].isin(["train", "validation"])]  # the rows the detection read
    times = {h: g["timestamp"] for h, g in seen.groupby("heliostat_id")}
    truth = {h: [{**e, "start": str(e["start"].date()), "end": str(e["end"].date())}
                 for e in v.changes] for h, v in field.heliostats.items()}
    dynamic = frozenset(h for h, v in field.heliostats.items() if v.dynamic)
    score = score_detection(truth, regimes, times, dynamic=dynamic)
    if penalty_factors:  # the same residuals, detected again with other penalties
        meas_all = read_artifact(work, MEASUREMENTS)
        preds = read_artifact(work, COARSE_PREDICTIONS)
        helio = read_artifact(work, HELIOSTATS)
        # the residuals the detection read: the plain preset's (a selected regime-aware model
        # follows the steps, its residuals show none), i.e. the base preset of the selection
        chosen = preds.loc[preds["selected"]].groupby("heliostat_id")["model"].first()
        plain = preds["heliostat_id"].map(chosen.map(base_preset))
        preds = preds.assign(selected=(preds["model"] == plain).to_numpy())
        score["penalty_factors"] = {}
        for f in penalty_factors:
            t2 = time.perf_counter()
            other = detect_coarse_regimes(meas_all, preds, helio, penalty_factor=f)
            s2 = score_detection(truth, other, times, dynamic=dynamic)
            s2["detect_s"] = time.perf_counter() - t2
            score["penalty_factors"][f] = {k: v for k, v in s2.items() if k != "missed"}
    score["regime_models"] = regime_model_table(read_artifact(work, COARSE_PARAMS), field)
    score.update({"heliostats": n, "dynamic_fraction": dynamic_fraction, "measurements_per_heliostat": measurements, "years": years,
                  "noise_mrad": noise_mrad, "seed": seed, "simulate_s": t_sim, "fit_coarse_s": t_fit,
                  "heliostats_with_changes": sum(1 for v in truth.values() if v),
                  "outliers_flagged": int((regimes["kind"] == "outlier").sum())})
    return score


def _kind(h) -> str:
    kinds = {e["kind"] for e in h.changes}
    if "step" in kinds:
        return "steps"
    if "drift" in kinds:
        return "drift"
    if kinds:
        return "episodes only"
    return "dynamic" if h.dynamic else "static"


def regime_model_table(params: pd.DataFrame, field) -> pd.DataFrame:
    """Per heliostat: its kind, the plain fit's and the selected model's test error [mrad] and
    the regime-aware candidate selected (``-`` for none)."""
    from heliocal.pipeline.models.regime_fit import base_preset

    p = params[params["parameter_index"] == 0].set_index(["heliostat_id", "preset"])
    rows = []
    for hid, g in params[params["selected"] & (params["parameter_index"] == 0)].groupby("heliostat_id"):
        model = str(g["preset"].iloc[0])
        plain = p.loc[(hid, base_preset(model)), "test_error_mrad"]
        rows.append({"heliostat_id": hid, "kind": _kind(field.heliostats[hid]),
                     "candidate": model.split("+")[1] if "+" in model else "-",
                     "plain_test": float(plain), "final_test": float(g["test_error_mrad"].iloc[0]),
                     "noise_floor": field.heliostats[hid].noise_floor_mrad})
    return pd.DataFrame(rows)


def print_regime_models(t: pd.DataFrame) -> None:
    t = t.assign(ratio=t["final_test"] / t["plain_test"])
    print("regime-aware coarse models (test error = mean error_mrad of the selected model on a "
          "heliostat's test rows; medians over heliostats):")
    print(f"  {'kind':<14}{'n':>4}{'plain':>9}{'final':>9}{'floor':>9}{'offsets':>9}{'drift':>7}"
          f"{'worse>2%':>10}{'ratio min':>11}")
    for kind, g in list(t.groupby("kind")) + [("all", t)]:
        print(f"  {kind:<14}{len(g):>4}{g['plain_test'].median():>9.3f}"
              f"{g['final_test'].median():>9.3f}{g['noise_floor'].median():>9.3f}"
              f"{int((g['candidate'] == 'offsets').sum()):>9}{int((g['candidate'] == 'drift').sum()):>7}"
              f"{int((g['ratio'] > 1.02).sum()):>10}{g['ratio'].min():>11.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=60)
    ap.add_argument("--measurements", type=int, default=600, help="per heliostat, whole period")
    ap.add_argument("--years", type=int, default=2)
    ap.add_argument("--noise-mrad", type=float, default=0.6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dynamic-fraction", type=float, default=0.2,
                    help="share of heliostats with the simulator's dynamic disturbances")
    ap.add_argument("--drift-fraction", type=float, default=0.0,
                    help="share of heliostats whose zero point drifts (1-3 mrad/year)")
    ap.add_argument("--penalty-factors", default="",
                    help="also detect with these penalty factors (comma-separated) on the same fit")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "regimes-bench")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    factors = tuple(float(f) for f in a.penalty_factors.split(",") if f.strip())
    s = run(a.heliostats, a.measurements, a.years, a.noise_mrad, a.seed, a.out,
            dynamic_fraction=a.dynamic_fraction, penalty_factors=factors,
            drift_fraction=a.drift_fraction)
    table = s.pop("regime_models")
    if a.json:
        s["regime_models"] = table.to_dict(orient="records")
        print(json.dumps(s, indent=2, default=str))
        return 0
    print(f"field: {s['heliostats']} heliostats ({s['heliostats_with_changes']} with steps or "
          f"episodes), {s['measurements_per_heliostat']} measurements each over {s['years']} "
          f"years, noise {s['noise_mrad']} mrad, seed {s['seed']}")
    print(f"steps and episodes >= 1 mrad with rows: {s['events']} ({s['unobservable']} more "
          "without rows on the changed side)")
    print(f"recall within +-3 days of the date:            {s['found']}/{s['events']} = "
          f"{s['recall']:.3f}")
    print(f"recall within +-3 days of the first row after: {s['found_first_row']}/{s['events']} = "
          f"{s['recall_first_row']:.3f}")
    print(f"false alarms on {s['static_heliostats']} static heliostats: "
          f"{s['static_false_alarms']} in {s['static_years']:.1f} heliostat-years = "
          f"{s['false_alarms_per_10_years']:.2f} per 10 heliostat-years")
    print(f"breaks on {s['dynamic_heliostats']} dynamic heliostats without events (seasonal "
          f"tilt, drift, gear error, thermal tilt; not static): {s['dynamic_alarms']} in "
          f"{s['dynamic_years']:.1f} heliostat-years = {s['dynamic_alarms_per_10_years']:.2f} "
          "per 10 heliostat-years")
    print(f"outliers flagged: {s['outliers_flagged']}; fit-coarse {s['fit_coarse_s']:.1f} s, "
          f"simulate+write {s['simulate_s']:.1f} s")
    for f, r in s.get("penalty_factors", {}).items():
        print(f"penalty factor {f:g}: recall {r['recall']:.3f} (first row {r['recall_first_row']:.3f}), "
              f"false alarms {r['false_alarms_per_10_years']:.2f} per 10 static heliostat-years, "
              f"dynamic {r['dynamic_alarms_per_10_years']:.2f}, detection {r['detect_s']:.2f} s")
    for m in s["missed"]:
        print("missed:", json.dumps(m, default=str))
    print_regime_models(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
