"""How a drift model should behave past its last row: hold, extrapolate, or extrapolate a while.

A ``<preset>+drift`` coarse model moves each regime's actuator zero points linearly in time
(models/regime_fit.py). Past the last training row of a regime the line can be held at its end
value (heliocal's rule), continued without bound, or continued for a bounded time and held
after. This script measures the three forward in time: for every heliostat of a work directory
whose fit-coarse ran (any selection), the ``drift`` candidate is fitted on the time split's
training rows (outside episodes, the heliostat's detected regimes), as fit-coarse fits it, and
its mean error on the time split's test rows (the latest measurements) is computed under each
rule. Heliostats whose time-split fit has no second regime with enough rows are skipped.

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/drift_extrapolation.py WORKDIR...

Prints per work directory the mean and median over heliostats of the test error for each rule
and how often each rule is best.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np
import pandas as pd

RULES = {"hold": 0.0, "bounded-30d": 30.0, "bounded-90d": 90.0, "linear": np.inf}
_DAY_S = 86400.0


def _heliostat_errors(work, hid, rows, hrow, regimes, preset) -> dict | None:
    from heliocal.pipeline.models.coarse import MeasurementBatch
    from heliocal.pipeline.models.coarse_presets import fit_presets
    from heliocal.pipeline.models.regime_fit import fit_regime_model, predict_rows
    from heliocal.pipeline.models.regimes import regime_arrays
    from heliocal.pipeline.physics.parameters import HeliostatSpec, nominal_parameters

    labels = rows["time_split"].to_numpy(object)
    if not (labels == "test").any():
        return None
    regime, episode = regime_arrays(regimes, hid, rows["timestamp"])
    train = (labels == "train") & ~episode
    spec, data = HeliostatSpec.from_row(hrow), MeasurementBatch.from_frame(rows)
    plain = fit_presets([spec], [nominal_parameters(hrow)], [data.subset(train)], (preset,))[0][0]
    fit = fit_regime_model(spec, preset, plain.params, plain.free, data, regime, rows["timestamp"],
                           train, "drift")
    if fit is None:
        return None
    test = labels == "test"
    out = {}
    for name, days in RULES.items():
        span = fit.span_s.copy()
        span[:, 1] = span[:, 1] + days * _DAY_S
        span[:, 0] = span[:, 0] - days * _DAY_S
        err = predict_rows(dataclasses.replace(fit, span_s=span), spec, data, regime,
                           rows["timestamp"])["error_mrad"].to_numpy()
        out[name] = float(np.nanmean(err[test]))
    return out


def measure(work) -> pd.DataFrame:
    from heliocal.pipeline.artifacts.schemas import (COARSE_PARAMS, HELIOSTATS, MEASUREMENTS,
                                                     REGIMES, SPLIT)
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.models.regime_fit import base_preset

    meas = read_artifact(work, MEASUREMENTS)
    split = read_artifact(work, SPLIT, columns=["heliostat_id", "measurement_id", "time_split"])
    meas = meas.merge(split, on=["heliostat_id", "measurement_id"])
    helio = read_artifact(work, HELIOSTATS).set_index("heliostat_id", drop=False)
    regimes = read_artifact(work, REGIMES)
    params = read_artifact(work, COARSE_PARAMS, columns=["heliostat_id", "preset", "selected"])
    chosen = params[params["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")
    broken = set(regimes.loc[regimes["cause"].isin(["detected", "renovation"]), "heliostat_id"])
    records = []
    for hid, rows in meas.groupby("heliostat_id", sort=True):
        if hid not in broken or hid not in chosen.index:
            continue
        errs = _heliostat_errors(work, hid, rows.reset_index(drop=True), helio.loc[hid], regimes,
                                 base_preset(str(chosen.loc[hid, "preset"])))
        if errs:
            records.append({"heliostat_id": hid, **errs})
    return pd.DataFrame(records)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdirs", nargs="+")
    a = ap.parse_args(argv)
    for work in a.workdirs:
        df = measure(work)
        print(f"{work}: {len(df)} heliostats with a drift candidate on the time split")
        if not len(df):
            continue
        best = df[list(RULES)].idxmin(axis=1).value_counts()
        print("| rule | mean test error [mrad] | median | best on |")
        print("|---|---|---|---|")
        for name in RULES:
            print(f"| {name} | {df[name].mean():.3f} | {df[name].median():.3f} | "
                  f"{int(best.get(name, 0))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
