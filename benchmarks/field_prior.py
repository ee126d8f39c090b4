"""Benchmark: the field prior (issue 34) against none, by training size, on one data source.

Ingests SOURCE once (into ``OUT/ingested``, kept between invocations), then for each training
size N (``split-knn --n-train N``; ``all``: no limit) and each prior runs ``fit-coarse --prior
PRIOR`` on the same split, in ``OUT/n<N>-<prior>``. Each invocation runs only the sizes and
priors it is given, so a long study is split into several short jobs; ``--table`` runs nothing
and prints the tables of every run found under OUT:

1. per training size and prior: the mean (and median) test error [mrad] of the selected models,
   on the kNN split's test rows and on the time split's test rows (fit-coarse's refit on the time
   split's training rows), over the heliostats that have those rows in *every* run found (so
   every cell averages the same heliostats; a heliostat the split skips at a larger N is left
   out of all cells), and the ratio to ``all`` rows without a prior (the issue's targets: at
   10 rows <= 1.2, at 5 rows <= 1.5);
2. the field-prior geometry (what a heliostat without training rows gets; each heliostat's from
   the prior of the other heliostats' folds) against the nominal geometry, on the same test rows;
3. the heliostats with at least 100 training rows (at ``all``): their test error with the prior
   over the one without (the issue's target: none above 1.02), and for each above 1.02 the
   paired t statistic of its per-row test errors with and without the prior (the same rows).

Usage::

    .venv/bin/python benchmarks/field_prior.py SOURCE [--properties DIR] [--out DIR]
        [--n-train 3,5,10,20,all] [--split-args "--n-test 10 --n-val 5"]
        [--priors none,field,field+spatial] [--workers 2] [--table [--exclude ID,...]]

SOURCE is what ``heliocal ingest`` reads (a calibration log, a PAINT folder, or a simulated
field's folder). The rolling-origin evaluation is skipped (``--rolling-origins 0``): it does not
change the test errors.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
HELIOCAL = str(Path(sys.executable).parent / "heliocal")
#: Rows at ``all`` from which a heliostat counts as "well measured" (the issue's 100).
BIG = 100


def _run(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([HELIOCAL, *args, "--quiet"], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _per_heliostat(workdir: Path) -> pd.DataFrame:
    """Per heliostat with training rows: n_train, the selected model's kNN and time test errors,
    the field-prior geometry's and the nominal geometry's kNN and time test errors [mrad]."""
    p = pd.read_parquet(workdir / "coarse_params.parquet")
    p = p[p["parameter_index"] == 0]
    sel = p[p["selected"]].set_index("heliostat_id")
    out = pd.DataFrame({"n_train": sel["n_train"], "preset": sel["preset"],
                        "knn": sel["test_error_mrad"], "time": sel["time_test_error_mrad"]})
    geo = p[p["preset"].str.endswith("+field-prior")].set_index("heliostat_id")
    out["geometry_knn"] = geo["test_error_mrad"]
    out["geometry_time"] = geo["time_test_error_mrad"]
    pred = pd.read_parquet(workdir / "coarse_predictions.parquet",
                           columns=["heliostat_id", "measurement_id", "model", "error_mrad"])
    split = pd.read_parquet(workdir / "split.parquet",
                            columns=["heliostat_id", "measurement_id", "split", "time_split"])
    nom = pred[pred["model"] == "nominal"].merge(split, on=["heliostat_id", "measurement_id"])
    out["nominal_knn"] = nom[nom["split"] == "test"].groupby("heliostat_id")["error_mrad"].mean()
    out["nominal_time"] = nom[nom["time_split"] == "test"].groupby("heliostat_id")[
        "error_mrad"].mean()
    return out[out["n_train"] > 0]


def _test_rows(workdir: Path, heliostats) -> dict[str, pd.DataFrame]:
    """split -> (heliostat_id, measurement_id) -> the selected model's error on that split's
    test rows [mrad] (coarse_predictions: ``error_mrad`` for kNN, ``time_error_mrad`` for the
    time split's refit)."""
    pred = pd.read_parquet(workdir / "coarse_predictions.parquet",
                           columns=["heliostat_id", "measurement_id", "split", "selected",
                                    "error_mrad", "time_error_mrad"])
    pred = pred[pred["selected"] & pred["heliostat_id"].isin(list(heliostats))]
    split = pd.read_parquet(workdir / "split.parquet",
                            columns=["heliostat_id", "measurement_id", "time_split"])
    pred = pred.merge(split, on=["heliostat_id", "measurement_id"])
    key = ["heliostat_id", "measurement_id"]
    return {"knn": pred[pred["split"] == "test"].set_index(key)["error_mrad"],
            "time": pred[pred["time_split"] == "test"].set_index(key)["time_error_mrad"]}


def _paired_t(with_prior: pd.Series, without: pd.Series, heliostat: str) -> float:
    """Paired t statistic of one heliostat's per-row test errors with the prior minus without
    (the same test rows): how many standard errors of the row sample the difference is."""
    d = (with_prior.xs(heliostat) - without.xs(heliostat)).dropna()
    if len(d) < 2 or d.std() == 0:
        return float("nan")
    return float(d.mean() / (d.std() / np.sqrt(len(d))))


def _runs(out: Path) -> dict[tuple[str, str], pd.DataFrame]:
    """(n_train, prior) -> per-heliostat table of every finished run under ``out``."""
    found = {}
    for meta in sorted(out.glob("n*/bench.json")):
        m = json.loads(meta.read_text())
        found[(m["n_train"], m["prior"])] = (_per_heliostat(meta.parent), m["wall_s"])
    return found


def _order(keys):
    size = {"all": 10 ** 9}
    return sorted(keys, key=lambda k: (size.get(k[0], None) or int(k[0]),
                                       ["none", "field", "field+spatial"].index(k[1])))


def tables(out: Path, exclude: frozenset = frozenset()) -> str:
    """The three tables (module docstring) in Markdown; the heliostats ``exclude`` are left out
    of the first table's averages."""
    runs = _runs(out)
    if not runs:
        return "no finished run under " + str(out)
    keys = _order(runs)
    common = {c: set.intersection(*(set(t[t[c].notna()].index) for t, _ in runs.values()))
              - exclude for c in ("knn", "time")}
    base = runs.get(("all", "none"))
    lines = [f"heliostats in every run: kNN test {len(common['knn'])}, time test "
             f"{len(common['time'])}" + (f" (left out: {', '.join(sorted(exclude))})"
                                         if exclude else ""), "",
             "| n-train | prior | kNN test mean | median | x none@all | time test mean | median "
             "| x none@all | field-prior selected | fit [s] |", "|---|---|---|---|---|---|---|---|---|---|"]
    ref = {c: base[0].loc[sorted(common[c]), c].mean() if base else np.nan
           for c in ("knn", "time")}
    for k in keys:
        t, wall = runs[k]
        cells = []
        for c in ("knn", "time"):
            v = t.loc[sorted(common[c]), c]
            cells += [f"{v.mean():.3f}", f"{v.median():.3f}", f"{v.mean() / ref[c]:.2f}"]
        chosen = int(t.loc[sorted(common["knn"]), "preset"].str.endswith("+field-prior").sum())
        lines.append(f"| {k[0]} | {k[1]} | " + " | ".join(cells) + f" | {chosen} | {wall:.1f} |")
    lines += ["", "field-prior geometry (each heliostat's from the other folds) against the "
              "nominal geometry, on the same heliostats' test rows [mrad]:", "",
              "| n-train | prior | heliostats | kNN: geometry median | nominal median | "
              "time: geometry median | nominal median |", "|---|---|---|---|---|---|---|"]
    for k in keys:
        t, _ = runs[k]
        g = t[t["geometry_knn"].notna()]
        if k[1] == "none" or g.empty:
            continue
        gt = t[t["geometry_time"].notna()]
        lines.append(f"| {k[0]} | {k[1]} | {len(g)} | {g['geometry_knn'].median():.3f} | "
                     f"{g['nominal_knn'].median():.3f} | {gt['geometry_time'].median():.3f} | "
                     f"{gt['nominal_time'].median():.3f} |")
    if base is not None:
        big = base[0][base[0]["n_train"] >= BIG]
        lines += ["", f"heliostats with >= {BIG} training rows (at all rows): test error with "
                  "the prior / without", "",
                  "| prior | heliostats | kNN worst ratio | kNN median | kNN > 1.02 | "
                  "time worst ratio | time median | time > 1.02 |", "|---|---|---|---|---|---|---|---|"]
        worse = []
        for prior in ("field", "field+spatial"):
            if ("all", prior) not in runs or big.empty:
                continue
            other = runs[("all", prior)][0].loc[big.index]
            cells = []
            for c in ("knn", "time"):
                r = (other[c] / big[c]).dropna()
                cells += [f"{r.max():.4f} ({r.idxmax()})" if len(r) else "n/a",
                          f"{r.median():.4f}" if len(r) else "n/a", str(int((r > 1.02).sum()))]
                worse += [(prior, c, h, v) for h, v in r[r > 1.02].items()]
            lines.append(f"| {prior} | {len(big)} | " + " | ".join(cells) + " |")
        lines += _worse_lines(out, worse)
    return "\n".join(lines)


def _worse_lines(out: Path, worse: list) -> list[str]:
    """The heliostats above 1.02 with the paired t statistic of their test rows' differences."""
    if not worse:
        return []
    lines = ["", "above 1.02, with the paired t of their per-row test errors (with the prior "
             "minus without, the same rows; |t| < 2: within the test rows' sampling noise):", ""]
    base = _test_rows(out / "nall-none", {h for *_, h, _ in worse})
    for prior, c, h, ratio in sorted(worse):
        mine = _test_rows(out / f"nall-{prior.replace('+', '-')}", [h])
        split = "kNN" if c == "knn" else "time"
        t = _paired_t(mine[c], base[c], h)
        lines.append(f"- {prior}, {split}: {h} {ratio:.4f} (t {t:.2f})")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source", type=Path, nargs="?")
    ap.add_argument("--properties", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "field-prior")
    ap.add_argument("--n-train", default="3,5,10,20,all")
    ap.add_argument("--split-args", default="")
    ap.add_argument("--priors", default="none,field", help="fit-coarse --prior values to compare")
    ap.add_argument("--workers", default="2")
    ap.add_argument("--table", action="store_true", help="only print the tables of OUT's runs")
    ap.add_argument("--exclude", default="", help="heliostat ids (comma-separated) to leave out "
                    "of the first table's averages")
    args = ap.parse_args()
    if not args.table:
        base = args.out / "ingested"
        if not (base / "ingest.manifest.json").exists():
            shutil.rmtree(base, ignore_errors=True)
            ingest = ["ingest", str(args.source), "--workdir", str(base)]
            if args.properties:
                ingest += ["--properties", str(args.properties)]
            _run(*ingest)
        for n in args.n_train.split(","):
            split = ["--n-train", n] if n != "all" else []
            for prior in args.priors.split(","):
                wd = args.out / f"n{n}-{prior.replace('+', '-')}"
                shutil.rmtree(wd, ignore_errors=True)
                shutil.copytree(base, wd)
                _run("split-knn", "--workdir", str(wd), *split, *args.split_args.split())
                wall = _run("fit-coarse", "--workdir", str(wd), "--prior", prior,
                            "--rolling-origins", "0", "--workers", args.workers)
                (wd / "bench.json").write_text(json.dumps(
                    {"n_train": n, "prior": prior, "wall_s": wall}))
                print(f"n_train={n} prior={prior}: fit-coarse {wall:.1f} s", flush=True)
    print(tables(args.out, frozenset(h for h in args.exclude.split(",") if h)))


if __name__ == "__main__":
    main()
