"""Does the fine model earn its place? The sweep's candidates and choices on real and simulated
heliostats, before and after issue 35's selection (the GP correction, the fade, the
distance-weighted validation with its max-T margin, the forward-in-time check).

Datasets (each through ``ingest``, ``split-knn`` and ``fit-coarse`` once, cached in ``--out``):

- ``juelich-csv``: ../shared/data/juelich's CSV log with its PAINT properties (the heliostats
  with enough rows for the split: 30 test + 20 validation + 2 training);
- ``juelich-paint``: its PAINT folder (BE36, BF41, BH35);
- ``synthetic``: the synthetic sample (sample_data/synthetic: 2 static, 2 dynamic heliostats,
  its ground_truth.json);
- ``sim``: the simulated development fields of docs/experiments/hybrid-development.md
  (``heliocal simulate --heliostats 4 --measurements 140,160 --seed S --dynamic-fraction 0.5``,
  S = 11..16: 12 static and 12 dynamic heliostats; ground_truth.json says which and gives each
  one's noise floor, the mean error of the true model).

Then ``sweep --study 0 --time-split`` (one worker: every heliostat's candidates are recorded as
the selection sees them). Per heliostat it prints the mean test error_mrad of fit-coarse's model
(``coarse``), of the hybrid main's rule would have looked at (the best hybrid ensemble on
validation, unfaded: ``hybrid``), of the GP candidate (``gp``), of the model selected now and
of the model main's rule selects on the same trainings (``before``: the best hybrid on the
plain validation mean if 20 % better than coarse); then the false selections (a fine model
selected whose test error is above the coarse model's) before and after, and the targets of
issue 35. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/fine_selection.py \\
        [--datasets juelich-paint,juelich-csv,synthetic,sim] [--env temperature]
        [--out runs/fine-selection]

``--env temperature`` gives the networks and the GP the logged temperature (the simulated
heliostats' thermal tilt is a function of it; docs/experiments/hybrid-development.md runs its
fields so). (``sim-S`` names one simulated field; a suffix ``-nN``, e.g. ``juelich-paint-n40``, restricts
every heliostat's training rows to N with ``split-knn --n-train N``.) ``--records FILE ...`` re-analyses the records of
previous runs (no sweep).
"""

from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "juelich"
SIM_SEEDS = (11, 12, 13, 14, 15, 16)

#: main's rule (cc54442): the best hybrid on the plain validation mean, if 20 % better
BEFORE_MARGIN = 0.20


def _heliocal(*args: str) -> None:
    subprocess.run([str(Path(sys.executable).parent / "heliocal"), *args, "--quiet"], check=True)


def simulated_field(out: Path, seed: int) -> Path:
    """The simulated field of ``seed`` (4 heliostats, half dynamic) under ``out``, simulated
    once, and the ingest arguments that read it."""
    field = out / f"sim-{seed}"
    if not (field / "ground_truth.json").exists():
        _heliocal("simulate", "--out", str(field), "--heliostats", "4", "--measurements",
                  "140,160", "--seed", str(seed), "--dynamic-fraction", "0.5")
    return field


def simulated_ingest(field: Path) -> list[str]:
    """``heliocal ingest`` arguments of a :func:`simulated_field`."""
    return ["ingest", str(field / "calibration_log.csv"), "--properties", str(field / "paint")]


def prepare(name: str, out: Path) -> list[tuple[str, Path, dict]]:
    """(label, workdir, noise floors by heliostat (simulated only)) of a dataset, ingested,
    split and fitted (cached). A suffix ``-nN`` restricts the training rows to N
    (``split-knn --n-train N``: farther from the test rows, the regime of low-data heliostats)."""
    base, _, n_train = name.partition("-n")
    split_args = ["--n-train", n_train] if n_train else []
    if n_train:
        name = base
    if name == "juelich-csv":
        jobs = [("juelich-csv", ["ingest", str(SHARED / "csv" / "juelich_calibration_log.csv"),
                                 "--properties", str(SHARED / "paint")], None)]
    elif name == "juelich-paint":
        jobs = [("juelich-paint", ["ingest", str(SHARED / "paint")], None)]
    elif name == "synthetic":
        field = ROOT / "sample_data" / "synthetic"
        jobs = [("synthetic", ["ingest", str(field / "calibration_log.csv"), "--properties",
                               str(field / "paint")], field)]
    else:
        jobs = []
        seeds = SIM_SEEDS if name == "sim" else (int(name.split("-")[1]),)
        for seed in seeds:
            field = simulated_field(out, seed)
            jobs.append((f"sim-{seed}", simulated_ingest(field), field))
    done = []
    for label, ingest, field in jobs:
        label = f"{label}-n{n_train}" if n_train else label
        wd = out / f"wd-{label}"
        if not (wd / "coarse_params.parquet").exists():
            _heliocal(*ingest, "--workdir", str(wd))
            _heliocal("split-knn", "--workdir", str(wd), *split_args)
            _heliocal("fit-coarse", "--workdir", str(wd), "--workers", "2")
        truth = {}
        if field is not None:
            gt = json.loads((field / "ground_truth.json").read_text())["heliostats"]
            truth = {h: {"dynamic": bool(v["dynamic"]), "floor": float(v["noise_floor_mrad"])}
                     for h, v in gt.items()}
        done.append((label, wd, truth))
    return done


def record_sweep(wd: Path, env: tuple[str, ...] = ()) -> tuple[list[dict], pd.DataFrame, float]:
    """Run the sweep (``env``: env_* columns as inputs of the networks and the GP), recording
    every heliostat's candidates as the selection sees them."""
    from heliocal.pipeline.artifacts.schemas import SELECTION
    from heliocal.pipeline.models.config import FineConfig
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.fade import sun_distance_deg
    from heliocal.pipeline.stages import selection as sel_module
    from heliocal.pipeline.stages.sweep import run_sweep

    records: list[dict] = []
    choose = sel_module.CandidatePool.choose

    def recording(pool):
        h = pool.h
        labels = np.asarray(h.labels, dtype=object)
        sun = h.rows[["sun_azimuth_deg", "sun_elevation_deg"]].to_numpy(float)
        dist = sun_distance_deg(sun[:, 0], sun[:, 1], sun[labels == "train"])
        records.append({
            "heliostat_id": h.hid, "labels": labels, "distance_deg": dist,
            "coarse": pool.coarse_errors.copy(), "weights": pool.weights.copy(),
            "candidates": [{"model": c.model, "complexity": c.complexity,
                            "weight_decay": c.info["weight_decay"],
                            "date_inputs": c.info["date_inputs"],
                            "errors": np.asarray(c.info["errors"]),
                            "by_length": np.asarray(c.info.get("errors_by_length",
                                                               c.info["errors"][None])),
                            "unfaded": np.asarray(c.info.get("errors_by_length",
                                                             c.info["errors"][None])[0])}
                           for c in pool.candidates]})
        return choose(pool)

    t0 = time.perf_counter()
    with mock.patch.object(sel_module.CandidatePool, "choose", recording):
        run_sweep(wd, study=0, workers=1, time_split=True, config=FineConfig(env=env))
    return records, read_artifact(wd, SELECTION).set_index("heliostat_id"), time.perf_counter() - t0


def _mean(v: np.ndarray, m: np.ndarray) -> float:
    return float(np.mean(v[m])) if m.any() else float("nan")


def before_choice(rec: dict) -> tuple[str, float]:
    """(model, test mean) main's rule picks from the same hybrid trainings (unfaded)."""
    val, test = rec["labels"] == "validation", rec["labels"] == "test"
    coarse_val = _mean(rec["coarse"], val)
    best = None
    for c in rec["candidates"]:
        if not c["model"].startswith("hybrid"):
            continue
        v = _mean(c["unfaded"], val)
        if v < (1 - BEFORE_MARGIN) * coarse_val and (best is None or v < best[0]):
            best = (v, c)
    if best is None:
        return "coarse", _mean(rec["coarse"], test)
    return best[1]["model"], _mean(best[1]["unfaded"], test)


def rescore(rec: dict, rule) -> tuple[str, float]:
    """(model, test mean) ``rule`` selects from a heliostat's recorded candidates, as the sweep's
    CandidatePool does: validation weights from the rows' distances, each candidate's fade
    chosen on them, every variant in the margin."""
    from heliocal.pipeline.models.selection import (Candidate, choose_fade, select,
                                                    validation_weights)

    labels, dist = rec["labels"], rec["distance_deg"]
    val, test = labels == "validation", labels == "test"
    w = validation_weights(dist[val], dist[test], rule.match_k, rule.match_share)
    candidates, variants = [], []
    for c in rec["candidates"]:
        by = c["by_length"]
        k = choose_fade([e[val] for e in by], w)
        complexity = (*c["complexity"][:-1], k if by.shape[0] > 1 else 0)
        candidates.append(Candidate(c["model"], by[k][val], complexity, {"errors": by[k]}))
        variants += [e[val] for e in by]
    if not candidates or not val.any():
        return "coarse", _mean(rec["coarse"], test)
    k, _ = select(rec["coarse"][val], candidates, w, rule, len(variants), variants)
    if k is None:
        return "coarse", _mean(rec["coarse"], test)
    return candidates[k].model, _mean(candidates[k].info["errors"], test)


#: Rules compared in the "rules" table (the default first).
RULES = {
    "default": {},
    "alpha 1 (no max-T)": {"alpha": 1.0},
    "alpha 0.3": {"alpha": 0.3},
    "alpha 0.05": {"alpha": 0.05},
    "unweighted validation": {"match_k": 0},
    "fully matched weights": {"match_share": 1.0},
    "GP margin 5 %": {"min_improvement_gp": 0.05},
    "GP margin 20 %": {"min_improvement_gp": 0.20},
    "network margin 10 %": {"min_improvement": 0.10},
    "Bonferroni, alpha 0.05": {"multiplicity": "bonferroni", "alpha": 0.05},
    "no one-se preference": {"one_se": False},
    "one-se band: the best's error SE": {"one_se_of": "error"},
    "one-se band: paired difference SE": {"one_se_of": "difference"},
}


def rules_table(saved) -> list[str]:
    """False selections and targets of each rule of :data:`RULES`, re-scored on the records."""
    from heliocal.pipeline.models.selection import SelectionRule

    lines = ["| rule | fine selected | false | > 5 % worse | real: fine, median test | static "
             "within 2 % | dynamic: fine, median / coarse |", "|---|---|---|---|---|---|---|"]
    for name, change in RULES.items():
        rule = SelectionRule(**change)
        rows = []
        for label, records, _, truth in saved:
            for rec in records:
                if (rec["labels"] == "test").any():
                    model, t = rescore(rec, rule)
                    rows.append({"data": label, "coarse": _mean(rec["coarse"], rec["labels"] == "test"),
                                 "sel": t, "model": model,
                                 "dynamic": truth.get(rec["heliostat_id"], {}).get("dynamic")})
        d = pd.DataFrame(rows)
        fine = d["model"] != "coarse"
        real, st, dy = (d[d["data"].str.startswith("juelich")], d[d["dynamic"] == False],  # noqa: E712
                        d[d["dynamic"] == True])  # noqa: E712
        lines.append(f"| {name} | {int(fine.sum())} | {int((fine & (d['sel'] > d['coarse'])).sum())} "
                     f"| {int((d['sel'] > 1.05 * d['coarse']).sum())} | "
                     f"{int((real['model'] != 'coarse').sum())}, {real['sel'].median():.3f} | "
                     f"{int((st['sel'] <= 1.02 * st['coarse']).sum())}/{len(st)} | "
                     f"{int((dy['model'] != 'coarse').sum())}, "
                     f"{(dy['sel'] / dy['coarse']).median():.3f} |")
    return lines


def heliostat_table(rec: dict, selected: pd.Series, truth: dict) -> dict:
    """One heliostat's row of the must-show table."""
    val, test = rec["labels"] == "validation", rec["labels"] == "test"
    hybrids = [c for c in rec["candidates"] if c["model"].startswith("hybrid")]
    hyb = min(hybrids, key=lambda c: _mean(c["unfaded"], val)) if hybrids else None
    gp = next((c for c in rec["candidates"] if c["model"] == "gp"), None)
    before_model, before_test = before_choice(rec)
    out = {"heliostat": rec["heliostat_id"], "coarse": _mean(rec["coarse"], test),
           "hybrid": _mean(hyb["unfaded"], test) if hyb else float("nan"),
           "gp": _mean(gp["errors"], test) if gp else float("nan"),
           "selected": float(selected["test_error_mrad"]), "model": str(selected["model"]),
           "before": before_test, "before_model": before_model,
           "forward_check": str(selected.get("forward_check", ""))}
    if rec["heliostat_id"] in truth:
        out.update(truth[rec["heliostat_id"]])
    return out


def fmt(v) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.3f}"


def report(rows: pd.DataFrame) -> list[str]:
    """The per-heliostat table, the false selections and the targets."""
    lines = ["| data | heliostat | coarse | hybrid | gp | selected | model | before | before model "
             "| floor |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows.itertuples():
        kind = "" if not isinstance(getattr(r, "dynamic", None), (bool, np.bool_)) else (
            " (dynamic)" if r.dynamic else " (static)")
        lines.append(f"| {r.data} | {r.heliostat}{kind} | {fmt(r.coarse)} | {fmt(r.hybrid)} | "
                     f"{fmt(r.gp)} | {fmt(r.selected)} | {r.model} | {fmt(r.before)} | "
                     f"{r.before_model} | {fmt(getattr(r, 'floor', np.nan))} |")
    false_before = (rows["before_model"] != "coarse") & (rows["before"] > rows["coarse"])
    false_after = (rows["model"] != "coarse") & (rows["selected"] > rows["coarse"])
    lines += ["", f"false selections (a fine model selected, test mean above coarse): before "
                  f"{int(false_before.sum())} -> after {int(false_after.sum())} of {len(rows)} "
                  f"heliostats ({int((rows['before_model'] != 'coarse').sum())} -> "
                  f"{int((rows['model'] != 'coarse').sum())} fine models selected)"]
    worse = rows["selected"] > 1.05 * rows["coarse"]
    lines.append(f"selected worse than coarse by more than 5 %: {int(worse.sum())} "
                 f"({', '.join(rows.loc[worse, 'heliostat']) or 'none'})")
    if "dynamic" in rows:
        sim = rows[rows["dynamic"].notna()]
        st, dy = sim[sim["dynamic"] == False], sim[sim["dynamic"] == True]  # noqa: E712
        keep = (st["selected"] <= 1.02 * st["coarse"])
        lines.append(f"simulated static within 2 % of coarse: {int(keep.sum())} of {len(st)}")
        ratio = dy["selected"] / dy["floor"]
        lines.append(f"simulated dynamic selected / floor: median {ratio.median():.2f}, "
                     f"<= 1.2: {int((ratio <= 1.2).sum())} of {len(dy)} (coarse / floor median "
                     f"{(dy['coarse'] / dy['floor']).median():.2f})")
    real = rows[rows["data"].str.startswith("juelich")]
    if len(real):
        lines.append(f"real heliostats: median test coarse {real['coarse'].median():.3f}, "
                     f"selected {real['selected'].median():.3f}, before "
                     f"{real['before'].median():.3f}; mean coarse {real['coarse'].mean():.3f}, "
                     f"selected {real['selected'].mean():.3f}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="juelich-paint,juelich-csv,sim")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "fine-selection")
    ap.add_argument("--env", default="",
                    help="env_* columns (comma-separated, without the prefix) as inputs of the "
                         "networks and the GP, e.g. temperature (the simulated fields' thermal "
                         "tilt is a function of it)")
    ap.add_argument("--records", type=Path, nargs="*", default=None,
                    help="analyse these records instead of running the sweeps")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    env = tuple(e.strip() for e in a.env.split(",") if e.strip())
    if a.records is None:
        saved = []
        for name in a.datasets.split(","):
            for label, wd, truth in prepare(name, a.out):
                records, selection, seconds = record_sweep(wd, env)
                print(f"{label}: sweep of {len(selection)} heliostats in {seconds:.0f} s",
                      flush=True)
                saved.append((label, records, selection, truth))
        tag = a.datasets.replace(",", "+") + (f"-env-{'+'.join(env)}" if env else "")
        path = a.out / f"records-{tag}.pkl"
        with open(path, "wb") as f:
            pickle.dump(saved, f)
        a.records = [path]
    saved = []
    for path in a.records:
        with open(path, "rb") as f:
            saved += pickle.load(f)
    rows = []
    for label, records, selection, truth in saved:
        for rec in records:
            if (rec["labels"] == "test").any():
                rows.append({"data": label, **heliostat_table(
                    rec, selection.loc[rec["heliostat_id"]], truth)})
    print("\n".join(report(pd.DataFrame(rows))))
    print("\nThe rule's settings re-scored on the same candidates (kNN split only; the sweep's "
          "forward check not applied):")
    print("\n".join(rules_table(saved)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
