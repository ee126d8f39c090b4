"""Benchmark: the field prior (issue 34) against none, by training size, on one data source.

Ingests SOURCE once, then for each training size N (``split-knn --n-train N``; ``all``: no
limit) runs ``fit-coarse --prior none`` and ``fit-coarse --prior field`` on the same split and
prints, per prior, the mean test error of the selected models over the heliostats with test
rows (kNN split) and over those with a time split (the time split's test rows, fit-coarse's
refit on its training rows), the heliostats whose selected model is the field-prior geometry,
and the wall time of each fit. The last table compares the heliostats with at least 100
training rows (at ``all``): the largest relative test-error increase under the prior. Usage::

    .venv/bin/python benchmarks/field_prior.py SOURCE [--properties DIR] [--out DIR]
        [--n-train 3,5,10,20,all] [--split-args "--n-test 10 --n-val 5"]
        [--priors none,field,field+spatial]

SOURCE is what ``heliocal ingest`` reads (a calibration log, a PAINT folder, or a simulated
field's folder). The rolling-origin evaluation is skipped (``--rolling-origins 0``): it does not
change the test errors.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
HELIOCAL = str(Path(sys.executable).parent / "heliocal")


def _run(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([HELIOCAL, *args, "--quiet"], check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _scores(workdir: Path) -> dict:
    p = pd.read_parquet(workdir / "coarse_params.parquet")
    sel = p[p["selected"] & (p["parameter_index"] == 0)]
    test = sel["test_error_mrad"].dropna()
    big = sel[sel["n_train"] >= 100].set_index("heliostat_id")["test_error_mrad"]
    return {"knn_test": test.mean(), "n_knn": len(test),
            "time_test": sel["time_test_error_mrad"].dropna().mean(),
            "n_time": int(sel["time_test_error_mrad"].notna().sum()),
            "field_prior_selected": int(sel["preset"].str.endswith("+field-prior").sum()),
            "zero_rows": int((sel["n_train"] == 0).sum()), "big": big}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source", type=Path)
    ap.add_argument("--properties", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "field-prior")
    ap.add_argument("--n-train", default="3,5,10,20,all")
    ap.add_argument("--split-args", default="")
    ap.add_argument("--priors", default="none,field", help="fit-coarse --prior values to compare")
    args = ap.parse_args()
    base = args.out / "ingested"
    shutil.rmtree(args.out, ignore_errors=True)
    ingest = ["ingest", str(args.source), "--workdir", str(base)]
    if args.properties:
        ingest += ["--properties", str(args.properties)]
    _run(*ingest)
    rows = []
    for n in args.n_train.split(","):
        split = ["--n-train", n] if n != "all" else []
        for prior in args.priors.split(","):
            wd = args.out / f"n{n}-{prior.replace('+', '-')}"
            shutil.copytree(base, wd)
            _run("split-knn", "--workdir", str(wd), *split, *args.split_args.split())
            wall = _run("fit-coarse", "--workdir", str(wd), "--prior", prior,
                        "--rolling-origins", "0")
            s = _scores(wd)
            rows.append({"n_train": n, "prior": prior, **s, "wall_s": wall})
            print(f"n_train={n:>3} prior={prior:13s} kNN test {s['knn_test']:.3f} mrad "
                  f"({s['n_knn']} heliostats)  time test {s['time_test']:.3f} ({s['n_time']})  "
                  f"field-prior selected {s['field_prior_selected']}  zero-row {s['zero_rows']}  "
                  f"fit {wall:.1f} s", flush=True)
    full = [r for r in rows if r["n_train"] == "all" and r["prior"] in ("none", "field")]
    if len(full) == 2 and len(full[0]["big"]):
        ratio = (full[1]["big"] / full[0]["big"]).dropna()
        print(f"heliostats with >= 100 training rows: {len(ratio)}; worst test ratio field/none "
              f"{ratio.max():.4f} ({ratio.idxmax()}), median {ratio.median():.4f}")


if __name__ == "__main__":
    main()
