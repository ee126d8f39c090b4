"""Is ``aim``'s ``expected_error_mrad`` right? Its calibration on held-out rows.

For every heliostat of fitted work directories (``fit-coarse`` has run), the expected error of
each held-out row (the budget of :mod:`heliocal.pipeline.stages.aim_budget` evaluated at the
row's steps, sun and focal spot, as for an aim at that spot) beside its actual error
(``error_mrad`` of the model on that row), in two settings:

* ``forward``: the model fitted on the time split's training rows (``time_fitted``), its
  budget from those rows and the time split's validation rows, scored on the time split's test
  rows (the latest): how a plant meets its aims after calibrating;
* ``knn``: the selected model, its budget from its training and kNN validation rows, scored on
  the kNN test rows.

Printed per work directory and setting: rows, the share of rows with actual <= 2 x expected
(the target is >= 90 %), the median actual / expected (1 would be an exact root-mean-square
match; about 0.83 for a Gaussian normal error of two components), and per heliostat the same
with its level source. Usage::

    python benchmarks/expected_error.py WORKDIR [WORKDIR ...] [--per-heliostat]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdirs", nargs="+", type=Path)
    ap.add_argument("--per-heliostat", action="store_true")
    args = ap.parse_args()
    print("| work directory | setting | rows | actual <= 2x expected | median actual/expected "
          "| mean actual | mean expected |")
    print("|---|---|---:|---:|---:|---:|---:|")
    per = []
    from heliocal.pipeline.stages.aim_calibration import calibration_rows, calibration_summary

    for wd in args.workdirs:
        for setting in ("forward", "knn"):
            rows = calibration_rows(wd, setting)
            if rows.empty:
                continue
            s = calibration_summary(rows)
            print(f"| {wd.name} | {setting} | {s['rows']} | {100 * s['within_2x']:.1f} % | "
                  f"{s['median_ratio']:.2f} | {s['mean_actual']:.3f} | {s['mean_expected']:.3f} |")
            for hid, g in rows.groupby("heliostat_id"):
                per.append({"workdir": wd.name, "setting": setting, "heliostat": hid,
                            "source": g["level_source"].iloc[0], **calibration_summary(g)})
    if args.per_heliostat and per:
        print()
        print(pd.DataFrame(per).to_string(index=False, float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
