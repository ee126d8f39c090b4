"""Forward in time on real heliostats: the kNN and the time-split test errors of the coarse model
and of the selected model, side by side.

For each dataset (``../shared/data/juelich``: the CSV log with the PAINT properties, and its PAINT
folder; ``sample_data/juelich``) it runs ``ingest``, ``split-knn`` (the kNN split selects; the
time split is written beside it), ``fit-coarse`` and ``sweep --study 0`` (the production
selection), and prints, per heliostat asked for (default AK32, BF41 and every heliostat of the
PAINT folders) and as medians over the dataset, selection.parquet's mean test errors: on the kNN
split's test rows (``knn``) and on the time split's test rows of the same model trained again on
the time split's training rows (``time``), for fit-coarse's selected preset and for the selected
model. "n/a": no time split (too few timestamps). Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/forward_real.py \
        [--heliostats AK32,BF41] [--workers 2] [--out runs/forward-real]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from regimes_real import DATASETS, ROOT  # noqa: E402  (the same real datasets, named once)


def run_dataset(work: Path, sources, properties, workers: int) -> tuple[pd.DataFrame, float]:
    from heliocal.pipeline.artifacts.schemas import SELECTION
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.split import run_split
    from heliocal.pipeline.stages.sweep import run_sweep

    t0 = time.perf_counter()
    run_ingest(sources, work, IngestOptions(properties=properties) if properties else IngestOptions())
    run_split(work)
    run_fit_coarse(work, workers=workers)
    run_sweep(work, study=0, workers=workers, time_split=True)
    return read_artifact(work, SELECTION).set_index("heliostat_id"), time.perf_counter() - t0


def _cell(v) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.3f}"


def table(sel: pd.DataFrame, ids) -> list[str]:
    out = ["| heliostat | coarse preset | coarse kNN test | coarse time test | selected model | "
           "selected kNN test | selected time test |", "|---|---|---|---|---|---|---|"]
    for hid in ids:
        r = sel.loc[hid]
        out.append(f"| {hid} | {r['preset']} | {_cell(r['coarse_test_error_mrad'])} | "
                   f"{_cell(r['coarse_time_test_error_mrad'])} | {r['model']} | "
                   f"{_cell(r['test_error_mrad'])} | {_cell(r['time_test_error_mrad'])} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", default="AK32,BF41")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "forward-real")
    a = ap.parse_args(argv)
    wanted = [h.strip() for h in a.heliostats.split(",") if h.strip()]
    for name, (sources, properties) in DATASETS.items():
        sel, seconds = run_dataset(a.out / name, sources, properties, a.workers)
        paint = name != "juelich-csv"
        ids = sorted(sel.index) if paint else [h for h in wanted if h in sel.index]
        cols = ["coarse_test_error_mrad", "coarse_time_test_error_mrad", "test_error_mrad",
                "time_test_error_mrad"]
        med = sel[cols].median()
        timed = sel["time_test_error_mrad"].notna()
        print(f"\n== {name}: {len(sel)} heliostats ({int(timed.sum())} with a time split), "
              f"{int(sel['model'].str.startswith('hybrid').sum())} hybrid selected; "
              f"ingest to sweep {seconds:.0f} s")
        print("\n".join(table(sel, ids)))
        print(f"medians [mrad]: coarse kNN {med.iloc[0]:.3f}, coarse time {med.iloc[1]:.3f}, "
              f"selected kNN {med.iloc[2]:.3f}, selected time {med.iloc[3]:.3f}")
        both = sel[timed]
        if len(both):
            better = int((both["time_test_error_mrad"] < both["coarse_time_test_error_mrad"]).sum())
            knn_better = int((both["test_error_mrad"] < both["coarse_test_error_mrad"]).sum())
            print(f"selected model better than coarse on test: kNN {knn_better} of {len(both)}, "
                  f"time {better} of {len(both)} (heliostats with a time split)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
