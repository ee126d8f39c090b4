"""Forward in time against the nominal geometry: per heliostat of a fitted work directory (after
``ingest``, ``split-knn``, ``fit-coarse`` and optionally ``sweep``), the model ``aim --model
auto`` uses and the evidence for and against it.

Columns (mean ``error_mrad`` [mrad]; "n/a": no such rows):

* ``aim uses``: :func:`heliocal.pipeline.stages.aim_choice.aim_models`' model (``nominal`` where
  it falls back) and the fitted model it judged (the sweep's variant or fit-coarse's preset);
* ``kNN test``: the fitted model on the kNN split's test rows;
* ``fwd test`` / ``nom fwd test``: the fitted model trained on the time split's training rows
  (selection.parquet ``time_test_error_mrad``, else coarse_params.parquet's) and the nominal
  geometry, on the time split's test rows (the rows no aim-time evidence has seen);
* ``aim fwd``: the forward test error of what aim uses (the nominal's where it falls back);
* ``kNN val`` / ``nom kNN val``, ``time val`` / ``nom time val``: the held-out evidence at aim
  time (the coarse model's time-split fit on the time split's validation rows);
* ``next-day`` / ``nom next-day``: fit-coarse's rolling-origin rows (rolling_origin.parquet) and
  the nominal geometry on the same rows; ``n`` the rolling rows (what ``aim`` weighs: every row);
* ``nd < test`` / ``nom nd < test``: the same on the rolling rows before the time split's first
  test row (the next-day evidence a plant had when the time split's test period began);
* ``rows``: kNN train/val/test and time train/val/test rows.

Printed as a Markdown table, with the heliostats whose ``aim fwd`` is above ``nom fwd test``
listed after it. Usage::

    python benchmarks/forward_nominal.py WORKDIR [--heliostats AH48,AJ51] [--csv OUT.csv]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pandas as pd


def _cell(v) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.3f}"


def rows_frame(workdir: Path, heliostats=None) -> pd.DataFrame:
    """One row per heliostat with the columns of the module docstring."""
    from heliocal.pipeline.artifacts.schemas import (COARSE_PARAMS, MEASUREMENTS, ROLLING_ORIGIN,
                                                     SELECTION)
    from heliocal.pipeline.artifacts.store import artifact_present, read_artifact
    from heliocal.pipeline.stages.aim_choice import aim_models, time_labelled_predictions

    models = aim_models(workdir, heliostats)
    params = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats)
    coarse = params[params["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")
    sel = (read_artifact(workdir, SELECTION, heliostats=heliostats).set_index("heliostat_id")
           if artifact_present(workdir, SELECTION) else None)
    pred = time_labelled_predictions(workdir, heliostats, ["split", "model", "error_mrad"])
    nom = pred[pred["model"] == "nominal"]
    knn_n = nom.groupby(["heliostat_id", "split"]).size()
    time_n = nom.groupby(["heliostat_id", "time_split"]).size()
    knn_nom = nom.groupby(["heliostat_id", "split"])["error_mrad"].mean()
    time_nom = nom.groupby(["heliostat_id", "time_split"])["error_mrad"].mean()
    keys = ["heliostat_id", "measurement_id"]
    rolling = pd.DataFrame(columns=keys + ["error_mrad"])
    if artifact_present(workdir, ROLLING_ORIGIN):
        rolling = read_artifact(workdir, ROLLING_ORIGIN, heliostats=heliostats,
                                columns=keys + ["error_mrad"])
    rolling = rolling.merge(nom[keys + ["error_mrad"]], on=keys, suffixes=("", "_nominal"))
    times = read_artifact(workdir, MEASUREMENTS, heliostats=heliostats,
                          columns=keys + ["timestamp"])
    rolling = rolling.merge(times, on=keys)
    first_test = (times.merge(pred.loc[pred["time_split"] == "test", keys].drop_duplicates(),
                              on=keys).groupby("heliostat_id")["timestamp"].min())
    early = rolling[rolling["timestamp"] < rolling["heliostat_id"].map(first_test)]
    nd = rolling.groupby("heliostat_id").agg(next_day=("error_mrad", "mean"),
                                             nom_next_day=("error_mrad_nominal", "mean"),
                                             n_next_day=("error_mrad", "size"))
    nd_early = early.groupby("heliostat_id").agg(early=("error_mrad", "mean"),
                                                 nom_early=("error_mrad_nominal", "mean"))
    nan = float("nan")
    out = []
    for hid, m in models.items():
        c = coarse.loc[hid]
        s = sel.loc[hid] if sel is not None and hid in sel.index else None
        fitted = str(s["model"]) if s is not None else str(c["preset"])
        fitted = str(c["preset"]) if fitted == "coarse" else fitted
        fwd = float(s["time_test_error_mrad"]) if s is not None else float(c["time_test_error_mrad"])
        knn_test = float(s["test_error_mrad"]) if s is not None else float(c["test_error_mrad"])
        nom_fwd = float(time_nom.get((hid, "test"), nan))
        counts = "/".join(str(int(knn_n.get((hid, k), 0))) for k in ("train", "validation", "test"))
        tcounts = "/".join(str(int(time_n.get((hid, k), 0))) for k in ("train", "validation", "test"))
        r = nd.loc[hid] if hid in nd.index else None
        e = nd_early.loc[hid] if hid in nd_early.index else None
        out.append({
            "heliostat": hid, "aim_uses": m["model"], "fitted": fitted,
            "knn_test": knn_test, "fwd_test": fwd, "nom_fwd_test": nom_fwd,
            "aim_fwd": nom_fwd if m["model"] == "nominal" else fwd,
            "knn_val": float(s["val_error_mrad"]) if s is not None else float(c["val_error_mrad"]),
            "nom_knn_val": float(knn_nom.get((hid, "validation"), nan)),
            "time_val": float(c["time_val_error_mrad"]),
            "nom_time_val": float(time_nom.get((hid, "validation"), nan)),
            "next_day": float(r["next_day"]) if r is not None else nan,
            "nom_next_day": float(r["nom_next_day"]) if r is not None else nan,
            "n_next_day": int(r["n_next_day"]) if r is not None else 0,
            "next_day_before_test": float(e["early"]) if e is not None else nan,
            "nom_next_day_before_test": float(e["nom_early"]) if e is not None else nan,
            "knn_rows": counts, "time_rows": tcounts, "fallback": m.get("fallback")})
    return pd.DataFrame(out)


def markdown(df: pd.DataFrame) -> list[str]:
    cols = ["knn_test", "fwd_test", "nom_fwd_test", "aim_fwd", "knn_val", "nom_knn_val",
            "time_val", "nom_time_val", "next_day", "nom_next_day"]
    early = ["next_day_before_test", "nom_next_day_before_test"]
    lines = ["| heliostat | aim uses | fitted | kNN test | fwd test | nom fwd test | aim fwd | "
             "kNN val | nom kNN val | time val | nom time val | next-day | nom next-day | n | "
             "nd < test | nom nd < test | kNN rows | time rows |",
             "|---|---|---|" + "---:|" * 13 + "---|---|"]
    for _, r in df.iterrows():
        lines.append(f"| {r['heliostat']} | {r['aim_uses']} | {r['fitted']} | "
                     + " | ".join(_cell(r[c]) for c in cols)
                     + f" | {r['n_next_day']} | " + " | ".join(_cell(r[c]) for c in early)
                     + f" | {r['knn_rows']} | {r['time_rows']} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--heliostats", default="", help="comma-separated (default: every heliostat)")
    ap.add_argument("--all", action="store_true",
                    help="also heliostats without time-split test rows")
    ap.add_argument("--csv", type=Path, default=None)
    a = ap.parse_args(argv)
    wanted = [h.strip() for h in a.heliostats.split(",") if h.strip()] or None
    df = rows_frame(a.workdir, wanted)
    if not a.all:
        df = df[df["nom_fwd_test"].notna()]
    if a.csv:
        df.to_csv(a.csv, index=False)
    print("\n".join(markdown(df)))
    worse = df[df["aim_fwd"] > df["nom_fwd_test"]]
    print(f"\n{len(df)} heliostats; aim's model forward worse than the nominal geometry on "
          f"{len(worse)}: {', '.join(worse['heliostat'])}")
    print(f"means: kNN test {df['knn_test'].mean():.3f}, fwd test {df['fwd_test'].mean():.3f}, "
          f"aim fwd {df['aim_fwd'].mean():.3f}, nom fwd test {df['nom_fwd_test'].mean():.3f}; "
          f"aim uses nominal on {int((df['aim_uses'] == 'nominal').sum())}")
    for _, r in df[df["fallback"].notna()].iterrows():
        print(f"  {r['heliostat']}: {r['fallback']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
