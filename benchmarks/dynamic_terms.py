"""Experiment (issue 35): how near their noise floor could the simulated dynamic heliostats get
with a kinematic model that has terms for their disturbances? Not a heliocal model: a ceiling
for one.

Per heliostat of a simulated work directory (``ingest``, ``split-knn``, ``fit-coarse`` done; its
simulation folder's ground_truth.json gives the floor), from fit-coarse's selected preset's
static fit (the regime-aware models' base), three Gauss-Newton steps on the kNN training rows
over the preset's free parameters plus per-row terms ``d p_j(row) = c f(row)``, each through the
exact Jacobian column of its parameter (``heliocal.pipeline.physics.jacobian``), with a tiny
ridge:

* ``gear``: axis 2's zero point by ``sin``/``cos`` of ``2 pi k s / P`` (k = 1, 2), ``P`` the
  period :func:`heliocal.pipeline.models.periodic.find_periodic_error` finds in the residuals;
* ``drift``: both zero points by the years since the first training row;
* ``temperature``: every free tilt parameter by the temperature's deviation from its mean;
* ``season``: every free tilt parameter by ``cos``/``sin`` of the day of the year.

Then the kNN test rows' mean error over the floor; printed per heliostat and as medians, and
with a GP (sun + time + temperature, as the sweep's) on the refit's residuals. Usage::

    .venv/bin/python benchmarks/dynamic_terms.py WORKDIR SIMULATION_FOLDER \\
        [--terms gear,drift,temperature,season]
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from heliocal.pipeline.models.coarse import MeasurementBatch
from heliocal.pipeline.models.gp import GPConfig, correct_normals, fit_gp_correction
from heliocal.pipeline.models.gp import pointing_residuals_mrad
from heliocal.pipeline.models.periodic import find_periodic_error
from heliocal.pipeline.physics.jacobian import residual_and_jacobian
from heliocal.pipeline.physics.kinematics import forward_kinematics
from heliocal.pipeline.physics.metrics import error_mrad, measured_normal
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX, PARAMETER_NAMES, HeliostatSpec

TERMS = ("gear", "drift", "temperature", "season")


def _normals(params_rows, spec, data):
    with torch.no_grad():
        n, pos = forward_kinematics(params_rows, spec, data.steps.unsqueeze(1))
    return n[:, 0], measured_normal(data.sun, pos[:, 0], data.focal_spot)


def _features(rows, train, free, residuals, terms) -> dict:
    """name -> (parameter, per-row feature (N,)) of the terms asked for."""
    out = {}
    if "gear" in terms:
        found = find_periodic_error(rows[["axis_1_steps", "axis_2_steps"]].to_numpy()[train],
                                    residuals[train])
        if found is not None:
            s = rows[f"axis_{found.axis}_steps"].to_numpy(float)
            zero = f"axis_{found.axis}_initial_angle_rad"
            for k in (1, 2):
                out[f"gear sin {k}"] = (zero, np.sin(2 * np.pi * k * s / found.period_steps))
                out[f"gear cos {k}"] = (zero, np.cos(2 * np.pi * k * s / found.period_steps))
    t = rows["timestamp"]
    years = (t - t[train].min()).dt.total_seconds().to_numpy() / (365.25 * 86400)
    if "drift" in terms:
        for axis in (1, 2):
            out[f"drift {axis}"] = (f"axis_{axis}_initial_angle_rad", years)
    tilts = [n for n in PARAMETER_NAMES if "_tilt_" in n and free[PARAMETER_INDEX[n]]]
    if "temperature" in terms and "env_temperature" in rows:
        temp = rows["env_temperature"].to_numpy(float)
        temp = np.nan_to_num(temp - np.nanmean(temp[train]))
        for n in tilts:
            out[f"temperature {n}"] = (n, temp)
    if "season" in terms:
        doy = 2 * np.pi * t.dt.dayofyear.to_numpy(float) / 365.25
        for n in tilts:
            out[f"season cos {n}"] = (n, np.cos(doy))
            out[f"season sin {n}"] = (n, np.sin(doy))
    return out


def refit(rows, spec, data, base, free, train, terms, steps: int = 3) -> torch.Tensor:
    """Per-row parameters (N, 28) after ``steps`` Gauss-Newton steps (module docstring)."""
    params = base.expand(len(rows), 28).clone()
    n, meas = _normals(params, spec, data)
    feats = _features(rows, train, free, pointing_residuals_mrad(n, meas), terms)
    free_idx = np.flatnonzero(free)
    for _ in range(steps):
        r, jac = residual_and_jacobian(params, spec, data.steps.unsqueeze(1),
                                       data.sun.unsqueeze(1), data.focal_spot.unsqueeze(1))
        r, jac = r[:, 0].numpy(), jac[:, 0].numpy()
        cols = [jac[:, :, free_idx]] + [(jac[:, :, PARAMETER_INDEX[p]] * f[:, None])[:, :, None]
                                        for p, f in feats.values()]
        a = np.concatenate(cols, axis=2)[train].reshape(-1, sum(c.shape[2] for c in cols))
        scale = np.linalg.norm(a, axis=0) + 1e-12
        an = a / scale
        step = np.linalg.solve(an.T @ an + 1e-6 * np.eye(an.shape[1]),
                               -an.T @ r[train].reshape(-1)) / scale
        params[:, torch.as_tensor(free_idx)] += torch.as_tensor(step[:len(free_idx)])
        for c, (p, f) in zip(step[len(free_idx):], feats.values()):
            params[:, PARAMETER_INDEX[p]] += torch.as_tensor(c * f)
    return params


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("simulation", type=Path)
    ap.add_argument("--terms", default=",".join(TERMS))
    a = ap.parse_args(argv)
    terms = tuple(t for t in a.terms.split(",") if t)
    warnings.filterwarnings("ignore")
    truth = json.loads((a.simulation / "ground_truth.json").read_text())["heliostats"]
    m = pd.read_parquet(a.workdir / "measurements.parquet").merge(
        pd.read_parquet(a.workdir / "split.parquet")[["heliostat_id", "measurement_id", "split"]])
    helio = pd.read_parquet(a.workdir / "heliostats.parquet").set_index("heliostat_id", drop=False)
    cp = pd.read_parquet(a.workdir / "coarse_params.parquet")
    out = []
    for hid, rows in m.groupby("heliostat_id"):
        if not truth.get(hid, {}).get("dynamic"):
            continue
        rows = rows.reset_index(drop=True)
        spec, data = HeliostatSpec.from_row(helio.loc[hid]), MeasurementBatch.from_frame(rows)
        chosen = cp[(cp["heliostat_id"] == hid) & cp["selected"]]["preset"].iloc[0]
        p = cp[(cp["heliostat_id"] == hid) & (cp["preset"] == chosen.split("+")[0])]
        p = p.sort_values("parameter_index")
        base = torch.tensor(p["fitted"].to_numpy(), dtype=torch.float64)
        free = p["free"].to_numpy(bool)
        train, test = (rows["split"] == "train").to_numpy(), (rows["split"] == "test").to_numpy()
        params = refit(rows, spec, data, base, free, train, terms)
        n, meas = _normals(params, spec, data)
        gp = fit_gp_correction(rows[train].reset_index(drop=True),
                               pointing_residuals_mrad(n, meas)[train],
                               GPConfig(env=("temperature",), periodic=False))
        corrected = correct_normals(n, gp.predict_rows(rows).mean_mrad)
        floor = truth[hid]["noise_floor_mrad"]
        n0, meas0 = _normals(base.expand(len(rows), 28), spec, data)
        out.append({"heliostat": hid, "train rows": int(train.sum()),
                    "static / floor": error_mrad(n0, meas0).numpy()[test].mean() / floor,
                    "refit / floor": error_mrad(n, meas).numpy()[test].mean() / floor,
                    "refit + GP / floor": error_mrad(corrected, meas).numpy()[test].mean() / floor})
        print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in out[-1].items()},
              flush=True)
    d = pd.DataFrame(out)
    print(f"terms {','.join(terms)}: medians",
          d[["static / floor", "refit / floor", "refit + GP / floor"]].median().round(2).to_dict())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
