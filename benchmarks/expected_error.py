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
with its level source.

Then the heliostats ``aim`` aims with the GP correction (the sweep selected ``gp``), on their
own: the GP-corrected model's actual error on the same held-out rows (forward: the GP fitted
again on the time split's training rows) against the coarse budget alone (``before``, what aim
expected of them until the GP's variance entered) and through the GP's predictive variance at
each row (``after``; :func:`heliocal.pipeline.stages.aim_budget.fine_level_mrad`). Usage::

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
    gp_table(args.workdirs, args.per_heliostat)


def gp_table(workdirs, per_heliostat: bool) -> None:
    """The GP-selected heliostats' calibration, before -> after (module docstring)."""
    from heliocal.pipeline.stages.aim_calibration import calibration_summary, gp_calibration_rows

    lines, per = [], []
    for wd in workdirs:
        for setting in ("forward", "knn"):
            rows = gp_calibration_rows(wd, setting)
            if rows.empty:
                continue
            b = calibration_summary(rows.assign(expected_mrad=rows["expected_before_mrad"]))
            a = calibration_summary(rows)
            lines.append(f"| {wd.name} | {setting} | {rows['heliostat_id'].nunique()} | {a['rows']} "
                         f"| {100 * b['within_2x']:.1f} % -> {100 * a['within_2x']:.1f} % "
                         f"| {b['median_ratio']:.2f} -> {a['median_ratio']:.2f} "
                         f"| {a['mean_actual']:.3f} | {b['mean_expected']:.3f} -> "
                         f"{a['mean_expected']:.3f} |")
            for hid, g in rows.groupby("heliostat_id"):
                gb = calibration_summary(g.assign(expected_mrad=g["expected_before_mrad"]))
                ga = calibration_summary(g)
                per.append({"workdir": wd.name, "setting": setting, "heliostat": hid,
                            "rows": ga["rows"], "within_2x_before": gb["within_2x"],
                            "within_2x_after": ga["within_2x"],
                            "median_before": gb["median_ratio"], "median_after": ga["median_ratio"],
                            "mean_actual": ga["mean_actual"],
                            "mean_expected_before": gb["mean_expected"],
                            "mean_expected_after": ga["mean_expected"]})
    if not lines:
        return
    print()
    print("GP-selected heliostats, before (coarse budget) -> after (through the GP's variance):")
    print("| work directory | setting | heliostats | rows | actual <= 2x expected "
          "| median actual/expected | mean actual | mean expected |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    print("\n".join(lines))
    if per_heliostat:
        print()
        print(pd.DataFrame(per).to_string(index=False, float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
