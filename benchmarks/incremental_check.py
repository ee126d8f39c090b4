"""Check an incremental work directory against a full rerun: copy WORKDIR, run ``split-knn`` and
``fit-coarse`` on the copy without ``--incremental`` (the options of WORKDIR's last runs), and
compare their six artifacts with WORKDIR's: structure exactly, floats with the tolerance of
tests/test_incremental.py. Prints per artifact the rows, the largest relative difference of its
floats and whether it holds. With ``--sweep`` it also runs ``heliocal sweep --study 0`` (the
sweep ``benchmarks/field.py`` runs) on another copy of WORKDIR, whose fit-coarse artifacts are
WORKDIR's (the sweep's inputs; fit-coarse's incremental results equal a full rerun's to 1e-7,
not bit for bit), and compares sweep.parquet, selection.parquet and
selected_predictions.parquet exactly, but ``wall_time_s`` (the run's own timing). Usage (after
``benchmarks/field.py --stages all``)::

    .venv/bin/python benchmarks/incremental_check.py runs/field-bench/run-200-all-w2 [--workers 2]
        [--sweep]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_incremental import REL, ABS, assert_same_artifact  # noqa: E402

SWEEP_ARTIFACTS = ("sweep", "selection", "selected_predictions")
ARTIFACTS = ("split", "coarse_params", "coarse_predictions", "regimes", "regime_params",
             "rolling_origin")


def largest_relative_difference(a: pd.DataFrame, b: pd.DataFrame) -> float:
    worst = 0.0
    for c in a.columns:
        if a[c].dtype.kind == "f" and len(a) == len(b):
            x, y = a[c].to_numpy(float), b[c].to_numpy(float)
            ok = ~(np.isnan(x) | np.isnan(y))
            d = np.abs(x[ok] - y[ok]) / np.maximum(np.maximum(np.abs(x[ok]), np.abs(y[ok])), 1e-300)
            worst = max(worst, float(d.max()) if d.size else 0.0)
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sweep", action="store_true", help="compare the sweep's artifacts too")
    args = ap.parse_args()
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.split import run_split

    with tempfile.TemporaryDirectory(dir=args.workdir.parent) as tmp:
        full = Path(shutil.copytree(args.workdir, Path(tmp) / "full"))
        split_opts = json.loads((full / "split-knn.manifest.json").read_text())["options"]
        coarse_opts = json.loads((full / "fit-coarse.manifest.json").read_text())["options"]
        run_split(full, **split_opts)
        run_fit_coarse(full, workers=args.workers, **{k: coarse_opts[k] for k in (
            "preset", "loss", "f_scale_mrad", "robust_start", "solver", "rolling_origins")})
        print(f"tolerance: relative {REL}, absolute {ABS}")
        for name in ARTIFACTS:
            a = pd.read_parquet(args.workdir / f"{name}.parquet")
            b = pd.read_parquet(full / f"{name}.parquet")
            try:
                assert_same_artifact(a, b, name)
                verdict = "equal"
            except AssertionError as exc:
                verdict = "DIFFERS: " + " ".join(str(exc).split())[:200]
            print(f"{name:20s} {len(a):8d} rows  largest relative difference "
                  f"{largest_relative_difference(a, b):.2e}  {verdict}")
        if args.sweep:
            _check_sweep(args.workdir, Path(tmp) / "sweep", args.workers)


def _check_sweep(workdir: Path, copy: Path, workers: int) -> None:
    """A full ``sweep --study 0`` of a copy of ``workdir`` (at ``copy``) against ``workdir``'s
    sweep, exactly."""
    full = Path(shutil.copytree(workdir, copy, ignore=shutil.ignore_patterns("report")))
    heliocal = str(Path(sys.executable).parent / "heliocal")
    subprocess.run([heliocal, "sweep", "--workdir", str(full), "--study", "0", "--workers",
                    str(workers), "--quiet"], check=True, stdout=subprocess.DEVNULL)
    for name in SWEEP_ARTIFACTS:
        a, b = (pd.read_parquet(d / f"{name}.parquet").drop(columns=["wall_time_s"],
                                                            errors="ignore")
                for d in (workdir, full))
        try:
            pd.testing.assert_frame_equal(a, b, check_exact=True, obj=name)
            verdict = "equal, every value (tolerance 0)"
        except AssertionError as exc:
            verdict = "DIFFERS: " + " ".join(str(exc).split())[:200]
        print(f"{name:20s} {len(a):8d} rows  {verdict}")


if __name__ == "__main__":
    main()
