"""The sweep's screen (issue 36, part 1): per heliostat the selected model and its test error,
and the sweep's wall time, for two arms of the sweep (e.g. ``--screen off`` and ``--screen on``)
on the same prepared work directories.

Datasets (each through ``ingest``, ``split-knn`` and ``fit-coarse`` once, cached in ``--out``):

- ``sample``: sample_data/juelich/paint with ``make sample``'s options (split seed 0, preset auto);
- ``paint``: ../shared/data/juelich/paint (the shared PAINT heliostats with calibration rows:
  BE36, BF41, BH35, the sample's);
- ``csv``: ../shared/data/juelich's CSV log with its PAINT properties (120 heliostats, most with
  30-70 rows: the split leaves them few training rows);
- ``synthetic``: the synthetic sample (sample_data/synthetic's log with its PAINT properties,
  ``--env temperature``; ground_truth.json says which heliostats are static);
- ``sim``: the simulated development fields of docs/hybrid.md (``heliocal simulate --heliostats 4
  --measurements 140,160 --seed S --dynamic-fraction 0.5``, S = 11..16, ``--env temperature``).

Each arm copies the prepared work directory and runs ``heliocal sweep --study 0 --workers 2``
plus ``--sweep-args`` in it, timed (wall clock of the process); its selection.parquet is kept in
``OUT/<arm>.json``. ``--compare A B`` prints the table of two arms. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/sweep_screen.py \\
        --datasets sample,paint --arm off --sweep-args "--screen off" [--out runs/screen]
    .venv/bin/python benchmarks/sweep_screen.py --out runs/screen --compare off on
    .venv/bin/python benchmarks/sweep_screen.py --compare-selections OFF.parquet ON.parquet
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
from fine_selection import SIM_SEEDS, simulated_field, simulated_ingest  # the same datasets

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "juelich"
HELIOCAL = str(Path(sys.executable).parent / "heliocal")


def _heliocal(*args: str) -> None:
    subprocess.run([HELIOCAL, *args, "--quiet"], check=True)


def prepare(name: str, out: Path) -> list[tuple[str, Path, dict, list[str]]]:
    """(label, prepared work directory, ground truth by heliostat (simulated only), extra sweep
    options) of a dataset; cached in ``out``."""
    synthetic = ROOT / "sample_data" / "synthetic"
    env = ["--env", "temperature"]
    if name == "sample":
        jobs = [("sample", ["ingest", str(ROOT / "sample_data" / "juelich" / "paint")], None, [])]
    elif name == "paint":
        jobs = [("paint", ["ingest", str(SHARED / "paint")], None, [])]
    elif name == "csv":
        jobs = [("csv", ["ingest", str(SHARED / "csv" / "juelich_calibration_log.csv"),
                         "--properties", str(SHARED / "paint")], None, [])]
    elif name == "synthetic":
        jobs = [("synthetic", ["ingest", str(synthetic / "calibration_log.csv"), "--properties",
                               str(synthetic / "paint")], synthetic, env)]
    elif name == "sim":
        jobs = [(f"sim-{seed}", simulated_ingest(field), field, env)
                for seed in SIM_SEEDS for field in [simulated_field(out, seed)]]
    else:
        raise SystemExit(f"Error: unknown dataset {name!r}; use sample, paint, csv, synthetic "
                         "or sim.")
    done = []
    for label, ingest, field, extra in jobs:
        wd = out / "prepared" / label
        if not (wd / "coarse_params.parquet").exists():
            _heliocal(*ingest, "--workdir", str(wd))
            _heliocal("split-knn", "--workdir", str(wd), "--seed", "0")
            _heliocal("fit-coarse", "--workdir", str(wd), "--preset", "auto", "--workers", "2")
        truth = {}
        if field is not None:
            gt = json.loads((field / "ground_truth.json").read_text())["heliostats"]
            truth = {h: "dynamic" if v["dynamic"] else "static" for h, v in gt.items()}
        done.append((label, wd, truth, extra))
    return done


def run_arm(datasets: list[str], arm: str, sweep_args: list[str], out: Path) -> None:
    """Sweep every prepared work directory of ``datasets`` with ``sweep_args``; record the
    selection and the wall time in ``OUT/<arm>.json``."""
    path = out / f"{arm}.json"
    record = json.loads(path.read_text()) if path.exists() else {"rows": [], "wall_s": {}}
    for name in datasets:
        record["rows"] = [r for r in record["rows"] if r["dataset"] != name]
        wall = 0.0
        for label, prepared, truth, extra in prepare(name, out):
            wd = out / arm / label
            shutil.rmtree(wd, ignore_errors=True)
            shutil.copytree(prepared, wd)
            t0 = time.perf_counter()
            _heliocal("sweep", "--workdir", str(wd), "--study", "0", "--seeds", "0",
                      "--workers", "2", *extra, *sweep_args)
            wall += time.perf_counter() - t0
            sel = pd.read_parquet(wd / "selection.parquet")
            for _, r in sel.iterrows():
                record["rows"].append({
                    "dataset": name, "field": label, "heliostat_id": r["heliostat_id"],
                    "kind": truth.get(r["heliostat_id"], "real"), "model": r["model"],
                    "test_error_mrad": float(r["test_error_mrad"]),
                    "coarse_test_error_mrad": float(r["coarse_test_error_mrad"]),
                    "screen": str(r.get("screen", ""))})
        record["wall_s"][name] = wall
        print(f"{arm} {name}: sweep {wall:.1f} s", flush=True)
    path.write_text(json.dumps(record, indent=1))


def compare(out: Path, before: str, after: str) -> None:
    """Print the per-heliostat table and the wall times of two arms (Markdown)."""
    a = json.loads((out / f"{before}.json").read_text())
    b = json.loads((out / f"{after}.json").read_text())
    key = ["dataset", "field", "heliostat_id"]
    t = pd.DataFrame(a["rows"]).merge(pd.DataFrame(b["rows"]), on=key + ["kind"],
                                      suffixes=("_a", "_b"))
    t["ratio"] = t["test_error_mrad_b"] / t["test_error_mrad_a"]
    print(f"| dataset | heliostat | kind | coarse test | {before}: model | test | "
          f"{after}: model | test | screen | after / before |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for _, r in t.iterrows():
        print(f"| {r['field']} | {r['heliostat_id']} | {r['kind']} | "
              f"{r['coarse_test_error_mrad_a']:.3f} | {r['model_a']} | {r['test_error_mrad_a']:.3f} | "
              f"{r['model_b']} | {r['test_error_mrad_b']:.3f} | {r['screen_b']} | "
              f"{r['ratio']:.3f} |")
    worse = t[t["ratio"] > 1.02]
    print(f"\n{len(t)} heliostats; same model {int((t['model_a'] == t['model_b']).sum())}; "
          f"worse on test by more than 2 %: {len(worse)}; largest ratio {t['ratio'].max():.3f}")
    print(f"\n| dataset | sweep {before} [s] | sweep {after} [s] | ratio |\n|---|---|---|---|")
    for name, wall in a["wall_s"].items():
        if name in b["wall_s"]:
            print(f"| {name} | {wall:.1f} | {b['wall_s'][name]:.1f} | "
                  f"{b['wall_s'][name] / wall:.2f} |")


def compare_selections(before: Path, after: Path) -> None:
    """Summarise two selection.parquet files of one field (e.g. benchmarks/field.py's with
    ``--sweep-args "--screen off"`` and without): models chosen, the screen's verdicts, and
    every heliostat whose selected model or test error changed."""
    a = pd.read_parquet(before).set_index("heliostat_id")
    b = pd.read_parquet(after).set_index("heliostat_id")
    t = a.join(b, how="inner", suffixes=("_a", "_b"))
    t["ratio"] = t["test_error_mrad_b"] / t["test_error_mrad_a"]
    print(f"{len(t)} heliostats; before: {a['model'].value_counts().to_dict()}; "
          f"after: {b['model'].value_counts().to_dict()}; screen: "
          f"{b['screen'].value_counts().to_dict() if 'screen' in b else 'n/a'}")
    changed = t[(t["model_a"] != t["model_b"]) | (t["ratio"] - 1).abs().gt(1e-9)]
    print(f"changed: {len(changed)}; worse on test by more than 2 %: "
          f"{int((t['ratio'] > 1.02).sum())}; largest ratio {t['ratio'].max():.3f}; mean test "
          f"{t['test_error_mrad_a'].mean():.4f} -> {t['test_error_mrad_b'].mean():.4f} mrad")
    if len(changed):
        print("| heliostat | before: model | test | after: model | test | screen | gain | ratio |")
        print("|---|---|---|---|---|---|---|---|")
        for hid, r in changed.iterrows():
            print(f"| {hid} | {r['model_a']} | {r['test_error_mrad_a']:.3f} | {r['model_b']} | "
                  f"{r['test_error_mrad_b']:.3f} | {r.get('screen_b', '')} | "
                  f"{r.get('screen_gain_b', float('nan')):.3f} | {r['ratio']:.3f} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="sample,paint,csv,synthetic,sim")
    ap.add_argument("--arm", help="name of this arm (OUT/<arm>.json)")
    ap.add_argument("--sweep-args", default="", help="options of this arm's sweep")
    ap.add_argument("--out", default="runs/screen")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"))
    ap.add_argument("--compare-selections", nargs=2, type=Path, metavar=("BEFORE", "AFTER"),
                    help="two selection.parquet files of one field")
    args = ap.parse_args(argv)
    if args.compare_selections:
        compare_selections(*args.compare_selections)
        return
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.compare:
        compare(out, *args.compare)
        return
    if not args.arm:
        raise SystemExit("Error: --arm NAME is needed to run an arm (or --compare A B).")
    run_arm(args.datasets.split(","), args.arm, args.sweep_args.split(), out)


if __name__ == "__main__":
    main()
