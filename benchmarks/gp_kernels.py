"""Which kernel for the GP correction (issue 35, item 1)? Every structure on every heliostat of
the prepared work directories, judged by marginal likelihood, validation and test error, and
forward in time (which time fade length).

Reads the work directories ``benchmarks/fine_selection.py`` prepared (ingest, split-knn,
fit-coarse; ``--out`` as there). Per heliostat with test rows, on the residuals of fit-coarse's
selected model (each row at its regime's parameters), it fits each kernel variant on the
training rows (models/gp.py, no fade) and records its log marginal likelihood, its mean
error_mrad on the validation and test rows, and its fit time (one thread). Variants: the
structures ``sun``, ``sun+time``, ``sun*time`` with the Ornstein-Uhlenbeck time kernel
(nu 1/2), ``sun+time`` with nu 3/2, and the choice by marginal likelihood between ``sun`` and
``sun+time`` (the default). Forward in time: the default GP fitted on the time split's training
rows on top of fit-coarse's time-split fit, its mean error on the time split's test rows with
time fade lengths of inf, 90, 30, 10 and 3 days (the sun fade off), against the coarse model's.
Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/gp_kernels.py \\
        [--out runs/fine-selection]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {"sun": (("sun",), 0.5), "sun+time": (("sun+time",), 0.5),
            "sun*time": (("sun*time",), 0.5), "sun+time nu 3/2": (("sun+time",), 1.5),
            "by likelihood": (("sun", "sun+time"), 0.5)}
TIME_FADES_DAYS = (math.inf, 90.0, 30.0, 10.0, 3.0)


def heliostats(wd: Path):
    """Per heliostat with test rows: (id, rows, labels, time labels, spec, data, coarse
    per-row parameters, time-split parameters or None)."""
    from heliocal.pipeline.artifacts.schemas import HELIOSTATS, MEASUREMENTS, SPLIT
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.coarse import MeasurementBatch
    from heliocal.pipeline.physics.parameters import HeliostatSpec
    from heliocal.pipeline.stages.fit_coarse import coarse_row_parameters, load_selected_parameters
    from heliocal.pipeline.stages.forward import load_time_parameters

    m = read_artifact(wd, MEASUREMENTS)
    split = read_artifact(wd, SPLIT, columns=["heliostat_id", "measurement_id", "split",
                                              "time_split"])
    helio = read_artifact(wd, HELIOSTATS).set_index("heliostat_id", drop=False)
    selected = load_selected_parameters(wd)
    time_params = load_time_parameters(wd)
    m = m.merge(split, on=["heliostat_id", "measurement_id"])
    for hid, rows in m.groupby("heliostat_id", sort=True):
        rows = rows.reset_index(drop=True)
        labels = rows["split"].to_numpy(dtype=object)
        if hid not in selected or not (labels == "test").any():
            continue
        yield (hid, rows, labels, rows["time_split"].to_numpy(dtype=object),
               HeliostatSpec.from_row(helio.loc[hid]), MeasurementBatch.from_frame(rows),
               coarse_row_parameters(selected[hid], rows["timestamp"]), time_params.get(hid))


def measure(wd: Path) -> pd.DataFrame:
    from heliocal.pipeline.models.gp import GPConfig
    from heliocal.pipeline.models.gp_heliostat import coarse_normals, fit_heliostat_gp
    from heliocal.pipeline.physics.metrics import error_mrad
    from heliocal.pipeline.runtime.process_state import one_thread

    out = []
    for hid, rows, labels, tlabels, spec, data, params, tparams in heliostats(wd):
        val, test = labels == "validation", labels == "test"
        n, _, meas = coarse_normals(params, spec, data)
        coarse = error_mrad(n, meas).numpy()
        row = {"heliostat": hid, "n_train": int((labels == "train").sum()),
               "coarse_val": coarse[val].mean(), "coarse_test": coarse[test].mean()}
        weights = np.ones(int(val.sum()))
        for name, (structures, nu) in VARIANTS.items():
            config = GPConfig(structures=structures, time_nu=nu)
            t0 = time.perf_counter()
            with one_thread(blas=True):
                fit = fit_heliostat_gp(rows, labels, spec, data, params, config, weights,
                                       lengths=(math.inf,))
            row[f"{name}|seconds"] = time.perf_counter() - t0
            row[f"{name}|lml"] = fit.model.log_marginal_likelihood
            row[f"{name}|structure"] = fit.model.structure
            row[f"{name}|val"], row[f"{name}|test"] = fit.errors[val].mean(), fit.errors[test].mean()
        tt = tlabels == "test"
        if tparams is not None and (tlabels == "train").sum() >= 2 and tt.any():
            n, _, meas = coarse_normals(tparams, spec, data)
            row["time|coarse"] = error_mrad(n, meas).numpy()[tt].mean()
            with one_thread(blas=True):
                fit = fit_heliostat_gp(rows, tlabels, spec, data, tparams, GPConfig(),
                                       np.ones(int((tlabels == "validation").sum())),
                                       lengths=(math.inf,))
            mean = fit.model.predict(fit.model.inputs.encode_rows(rows)).mean_mrad
            from heliocal.pipeline.models.gp import correct_normals
            for days in TIME_FADES_DAYS:
                fade = dataclasses.replace(fit.model.fade, length_days=days)
                w = fade.weights_of_rows(rows)[:, None] if fit.model.uses_time else 1.0
                err = error_mrad(correct_normals(n, w * mean), meas).numpy()
                row[f"time|{days:g}"] = err[tt].mean()
        out.append(row)
    return pd.DataFrame(out)


def summary(df: pd.DataFrame, label: str) -> list[str]:
    lines = [f"\n== {label}: {len(df)} heliostats (median {df['n_train'].median():.0f} training "
             f"rows); coarse test median {df['coarse_test'].median():.3f} mrad",
             "| kernel | median val / coarse | median test / coarse | test worse > 5 % | "
             "best likelihood | fit [s] median |", "|---|---|---|---|---|---|"]
    lml = df[[f"{k}|lml" for k in ("sun", "sun+time", "sun*time", "sun+time nu 3/2")]]
    wins = lml.idxmax(axis=1).str.split("|").str[0].value_counts()
    for name in VARIANTS:
        v, t = df[f"{name}|val"] / df["coarse_val"], df[f"{name}|test"] / df["coarse_test"]
        lines.append(f"| {name} | {v.median():.3f} | {t.median():.3f} | "
                     f"{int((t > 1.05).sum())} | {int(wins.get(name, 0))} | "
                     f"{df[f'{name}|seconds'].median():.3f} |")
    chosen = df["by likelihood|structure"].value_counts().to_dict()
    lines.append(f"by likelihood chose: {chosen}")
    if "time|coarse" in df:
        f = df[df["time|coarse"].notna()]
        cells = ", ".join(f"{d:g} days {(f[f'time|{d:g}'] / f['time|coarse']).median():.3f} "
                          f"(worse > 5 %: {int((f[f'time|{d:g}'] > 1.05 * f['time|coarse']).sum())})"
                          for d in TIME_FADES_DAYS)
        lines.append(f"forward in time ({len(f)} heliostats), median GP / coarse on the time "
                     f"split's test rows by time fade length: {cells}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "fine-selection")
    a = ap.parse_args(argv)
    frames = []
    for wd in sorted(a.out.glob("wd-*")):
        df = measure(wd).assign(data=wd.name[3:])
        frames.append(df)
        if not wd.name.startswith("wd-sim"):
            print("\n".join(summary(df, wd.name[3:])), flush=True)
    sims = [f for f in frames if f["data"].iloc[0].startswith("sim")]
    if sims:
        print("\n".join(summary(pd.concat(sims, ignore_index=True), "simulated (all)")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
