"""Benchmark: how far a field prior can take a few-row fit on a simulated field (issue 34).

On a work directory of ``benchmarks/field_prior.py`` (a simulated field ingested and split, e.g.
``OUT/n10-none``) and the field's ``ground_truth.json``, per heliostat and split (kNN, time) the
mean test error [mrad] of

* ``true static``: the heliostat's true static geometry (nominal plus its true deviations, no
  dynamic disturbance): what a perfect static fit predicts;
* ``oracle prior``: the preset fitted on the split's training rows, as fit-coarse fits it
  (``fit_presets``: batched LM, soft-l1, each prior weighed against the noise), under the true
  population prior of *every* free parameter (mean and standard deviation of the field's true
  deviations over its heliostats), weighed against the true noise;
  (``--covered-by``: only on the parameters a fit-coarse run's field prior covers, the default
  prior on the others, as fit-coarse fits them);
* ``oracle spatial``: the same, with the mounting parameters' prior the true Gaussian random
  field's conditional (kriging) mean and variance given the other heliostats' true deviations
  (pipeline/models/mounting.py: its correlation length and standard deviations).

No estimated prior does better than the oracle prior on average, so it bounds what an
improvement of the field prior's estimate can give at that training size; ``x ref`` divides by
the mean test error of the selected models in ``--reference`` (``OUT/nall-none``: the issue's
"full-data error without a prior").

Usage::

    .venv/bin/python benchmarks/field_prior_oracle.py WORKDIR --truth FIELD/ground_truth.json
        [--reference OUT/nall-none] [--compare OUT/n10-field ...] [--compare-preset]
        [--covered-by OUT/n10-field] [--preset static-20]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from heliocal.pipeline.models.coarse import (MeasurementBatch, normal_errors_mrad, predict,
                                            prior_sigma)
from heliocal.pipeline.models.coarse_presets import fit_presets
from heliocal.pipeline.models.disturbances import deviation_kind
from heliocal.pipeline.models.mounting import (CORRELATION_LENGTH_M, INDIVIDUAL_SD, SPATIAL_SD,
                                               mounting_parameters)
from heliocal.pipeline.physics.parameters import (PARAMETER_INDEX, PARAMETER_NAMES,
                                                  HeliostatSpec, nominal_parameters)

SPLITS = {"kNN": "split", "time": "time_split"}


def _rows(workdir: Path) -> pd.DataFrame:
    meas = pd.read_parquet(workdir / "measurements.parquet")
    split = pd.read_parquet(workdir / "split.parquet",
                            columns=["heliostat_id", "measurement_id", "split", "time_split"])
    return meas.merge(split, on=["heliostat_id", "measurement_id"])


def _true_deviations(truth: dict, ids) -> pd.DataFrame:
    """(heliostat x 28) true minus nominal [parameter units] (0 where not deviated)."""
    return pd.DataFrame({h: {n: truth[h]["deviation"].get(n, 0.0) for n in PARAMETER_NAMES}
                         for h in ids}).T[list(PARAMETER_NAMES)]


def _true_parameters(hrow, dev: pd.DataFrame) -> torch.Tensor:
    """(28,) a heliostat's true static geometry: nominal plus its true deviations."""
    return nominal_parameters(hrow) + torch.as_tensor(
        dev.loc[hrow["heliostat_id"]].to_numpy(np.float64, copy=True))


def _noise_mrad(helio, rows, dev, truth) -> float:
    """RMS residual per component [mrad] of the static heliostats' true geometries on their rows:
    the measurements' noise a prior is weighed against."""
    sq, n = 0.0, 0
    for hid, hrow in helio.iterrows():
        if truth[hid]["dynamic"]:
            continue
        params = _true_parameters(hrow, dev)
        err = normal_errors_mrad(params, HeliostatSpec.from_row(hrow),
                                 MeasurementBatch.from_frame(rows[rows["heliostat_id"] == hid]))
        sq, n = sq + float((err ** 2).sum()), n + 3 * len(err)
    return float(np.sqrt(sq / max(n, 1)))


def _kriging(positions: np.ndarray, values: np.ndarray, k: int, spatial_sd: float,
             individual_sd: float) -> tuple[float, float]:
    """Conditional mean and sd of heliostat ``k``'s deviation (zero-mean part) given the others'
    ``values`` (n,): squared-exponential field plus an independent individual part."""
    o = np.arange(len(values)) != k
    d2 = ((positions[o][:, None] - positions[o][None]) ** 2).sum(-1)
    cov = spatial_sd ** 2 * np.exp(-d2 / (2 * CORRELATION_LENGTH_M ** 2))
    cov += individual_sd ** 2 * np.eye(int(o.sum()))
    kv = spatial_sd ** 2 * np.exp(-((positions[o] - positions[k]) ** 2).sum(-1)
                                  / (2 * CORRELATION_LENGTH_M ** 2))
    a = np.linalg.solve(cov, kv)
    var = spatial_sd ** 2 + individual_sd ** 2 - a @ kv
    return float(a @ values[o]), float(np.sqrt(max(var, 1e-14)))


def _covered(workdir: Path | None, preset: str) -> np.ndarray:
    """(28,) bool: the parameters ``workdir``'s field_prior.parquet gives ``preset`` a field prior
    on (all of them without ``workdir``)."""
    if workdir is None:
        return np.ones(len(PARAMETER_NAMES), bool)
    table = pd.read_parquet(workdir / "field_prior.parquet")
    names = set(table.loc[(table["preset"] == preset) & table["scale"].notna(), "parameter"])
    return np.array([n in names for n in PARAMETER_NAMES])


def _priors(helio, dev: pd.DataFrame, preset: str, noise: float, spatial: bool,
            covered: np.ndarray) -> dict:
    """heliostat -> {preset: (mean (28,), sigma (28,), noise (28,))}: the true population prior
    on the ``covered`` parameters, the default prior (nominal, default sigma, 1 mrad) elsewhere,
    as fit-coarse gives a parameter without a field prior."""
    mean_dev, sd_dev = dev.mean().to_numpy(), dev.std().to_numpy()
    ids = list(helio.index)
    positions = helio[["heliostat_e_m", "heliostat_n_m"]].to_numpy(float)
    out = {}
    for k, hid in enumerate(ids):
        nominal = nominal_parameters(helio.loc[hid]).numpy()
        mean, sigma = nominal + mean_dev, np.maximum(sd_dev, 1e-9)
        if spatial:
            for name in mounting_parameters(str(helio.loc[hid, "kinematic_type"])):
                i, kind = PARAMETER_INDEX[name], deviation_kind(name)
                centred = dev[name].to_numpy() - mean_dev[i]
                m, s = _kriging(positions, centred, k, SPATIAL_SD[kind], INDIVIDUAL_SD[kind])
                mean[i], sigma[i] = nominal[i] + mean_dev[i] + m, s
        out[hid] = {preset: (np.where(covered, mean, nominal),
                             np.where(covered, sigma, prior_sigma(torch.as_tensor(nominal))),
                             np.where(covered, noise, 1.0))}
    return out


def _fit_errors(helio, rows, priors, preset: str, column: str) -> pd.Series:
    ids = list(helio.index)
    specs = [HeliostatSpec.from_row(helio.loc[h]) for h in ids]
    trains = [MeasurementBatch.from_frame(rows[(rows["heliostat_id"] == h)
                                               & (rows[column] == "train")]) for h in ids]
    fits = fit_presets(specs, [nominal_parameters(helio.loc[h]) for h in ids], trains, [preset],
                       priors=priors)
    out = {}
    for hid, spec, fit in zip(ids, specs, fits):
        test = rows[(rows["heliostat_id"] == hid) & (rows[column] == "test")]
        out[hid] = float(predict(fit[0].params, spec, MeasurementBatch.from_frame(test))[
            "error_mrad"].mean()) if len(test) else np.nan
    return pd.Series(out)


def _true_static_errors(helio, rows, dev, column: str) -> pd.Series:
    out = {}
    for hid, hrow in helio.iterrows():
        test = rows[(rows["heliostat_id"] == hid) & (rows[column] == "test")]
        params = _true_parameters(hrow, dev)
        out[hid] = float(normal_errors_mrad(params, HeliostatSpec.from_row(hrow),
                                            MeasurementBatch.from_frame(test)).mean())
    return pd.Series(out)


def _selected(workdir: Path, preset: str | None = None) -> dict[str, pd.Series]:
    """split -> per heliostat the test error [mrad] of the model fit-coarse selected there (of
    its fit of ``preset``, selected or not, when given)."""
    p = pd.read_parquet(workdir / "coarse_params.parquet")
    which = p["selected"] if preset is None else p["preset"] == preset
    sel = p[(p["parameter_index"] == 0) & which].set_index("heliostat_id")
    return {"kNN": sel["test_error_mrad"], "time": sel["time_test_error_mrad"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--truth", type=Path, required=True, help="the field's ground_truth.json")
    ap.add_argument("--reference", type=Path, default=None,
                    help="a fit-coarse work directory whose selected models' mean is the ratio's "
                         "denominator (the field at all rows without a prior)")
    ap.add_argument("--compare", type=Path, action="append", default=[],
                    help="a fit-coarse work directory on the same split whose selected models "
                         "to list beside the oracle (repeatable)")
    ap.add_argument("--compare-preset", action="store_true",
                    help="list the --compare runs' fits of --preset too (selected or not)")
    ap.add_argument("--covered-by", type=Path, default=None,
                    help="a fit-coarse work directory with a field prior: give the true prior only "
                         "to the parameters its field_prior.parquet covers (default: every one)")
    ap.add_argument("--preset", default="static-20")
    args = ap.parse_args()
    truth = json.loads(args.truth.read_text())["heliostats"]
    helio = pd.read_parquet(args.workdir / "heliostats.parquet").set_index("heliostat_id",
                                                                          drop=False)
    rows = _rows(args.workdir)
    dev = _true_deviations(truth, helio.index)
    noise = _noise_mrad(helio, rows, dev, truth)
    dynamic = pd.Series({h: bool(truth[h]["dynamic"]) for h in helio.index})
    covered = _covered(args.covered_by, args.preset)
    ref = ({k: float(v.mean()) for k, v in _selected(args.reference).items()}
           if args.reference else {})
    print(f"{args.workdir}: {len(helio)} heliostats ({int(dynamic.sum())} dynamic), "
          f"true noise {noise:.3f} mrad per residual component, preset {args.preset}; the "
          f"oracle's prior on {int(covered.sum())} parameters\n")
    print("| model | split | static | dynamic | all | x ref |\n|---|---|---|---|---|---|")

    def line(label: str, name: str, err: pd.Series) -> None:
        err = err.reindex(helio.index)
        ratio = f"{err.mean() / ref[name]:.2f}" if name in ref else ""
        print(f"| {label} | {name} | {err[~dynamic].mean():.3f} | {err[dynamic].mean():.3f} | "
              f"{err.mean():.3f} | {ratio} |")

    for other in args.compare:
        for name, err in _selected(other).items():
            line(other.name, name, err)
        if args.compare_preset:
            for name, err in _selected(other, args.preset).items():
                line(f"{other.name}, its {args.preset}", name, err)
    for label, spatial in (("true static", None), ("oracle prior", False),
                           ("oracle spatial", True)):
        priors = None if spatial is None else _priors(helio, dev, args.preset, noise, spatial,
                                                      covered)
        for name, column in SPLITS.items():
            line(label, name, _true_static_errors(helio, rows, dev, column) if priors is None
                 else _fit_errors(helio, rows, priors, args.preset, column))


if __name__ == "__main__":
    main()
