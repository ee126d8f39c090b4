"""What the GP correction costs the sweep (issue 35): benchmarks/field.py's simulated field,
``sweep --study 0`` without the GP (``--no-gp``) and with it (the default), in one run.

The field is field.py's (``--heliostats`` of them, 100 to 400 measurements each, seed 0, cached
in ``OUT/field-N``); ``ingest``, ``split-knn`` and ``fit-coarse --preset static-20`` run once,
then the two sweeps alternate ``--repeats`` times, each a fresh ``heliocal`` process with
``--workers``. Printed: each sweep's wall time and peak memory, the ratio with/without, the GP's
own time per heliostat (sweep.parquet ``wall_time_s`` of the ``gp`` rows: its fits of every
structure and its predictions, in the workers), how many heliostats chose a GP, and with
``--time-split`` the same for ``sweep --time-split`` (the forward pass that checks a selected
hybrid). Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/gp_cost.py \\
        [--heliostats 200] [--workers 2] [--repeats 1] [--out runs/field-bench]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from field import ROOT, run_stage, write_field  # noqa: E402  (the same field, measured alike)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--time-split", action="store_true",
                    help="also measure sweep --time-split (with the GP)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "field-bench")
    a = ap.parse_args(argv)
    info = write_field(a.out / f"field-{a.heliostats}", a.heliostats)
    field = a.out / f"field-{a.heliostats}"
    wd = a.out / f"gp-cost-{a.heliostats}"
    print(f"field: {info['heliostats']} heliostats, {info['measurements']} measurements", flush=True)
    if not (wd / "coarse_params.parquet").exists():
        run_stage(["ingest", str(field / "calibration_log.csv"), "--properties",
                   str(field / "paint"), "--workdir", str(wd)])
        run_stage(["split-knn", "--workdir", str(wd)])
        run_stage(["fit-coarse", "--workdir", str(wd), "--preset", "static-20", "--workers",
                   str(a.workers)])
    arms = {"without gp": ["--no-gp"], "with gp": []}
    if a.time_split:
        arms["with gp, --time-split"] = ["--time-split"]
    walls: dict[str, list[float]] = {k: [] for k in arms}
    for r in range(a.repeats):
        for name, extra in arms.items():
            wall, peak = run_stage(["sweep", "--workdir", str(wd), "--study", "0", "--workers",
                                    str(a.workers), *extra])
            walls[name].append(wall)
            sel = pd.read_parquet(wd / "selection.parquet")
            sweep = pd.read_parquet(wd / "sweep.parquet")
            gp = sweep[sweep["model"].astype(str).str.startswith("gp")]
            per = gp.groupby("heliostat_id")["wall_time_s"].sum()
            chosen = sel["model"].value_counts().to_dict()
            checks = sel["forward_check"].value_counts().to_dict() if "forward_check" in sel else {}
            print(f"  repeat {r + 1} {name:22s} {wall:7.1f} s  peak {peak.gib()}  "
                  f"selected {chosen}" + (f"  GP {per.mean():.3f} s per heliostat (median "
                                          f"{per.median():.3f})" if len(per) else "")
                  + (f"  forward checks {checks}" if checks else ""), flush=True)
    base = sorted(walls["without gp"])[len(walls["without gp"]) // 2]
    for name, values in walls.items():
        med = sorted(values)[len(values) // 2]
        print(f"{name:22s} median {med:7.1f} s  ({med / base:.3f}x without gp; "
              f"{med / info['heliostats']:.3f} s per heliostat)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
