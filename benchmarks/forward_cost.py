"""Benchmark: what forward-in-time evaluation (the time split's second training of the selected
model) adds to ``fit-coarse`` and to the production ``sweep``.

Simulates a field as benchmarks/field.py does (default 100 juelich heliostats with 100 to 400
measurements each, half of them dynamic, seed 0; ``heliocal simulate``'s model), runs ``ingest``
and ``split-knn``, then ``fit-coarse`` (default preset ``auto``) and ``sweep --study 0`` (the
production selection of benchmarks/field.py: default weight decays, band sets and ensembles)
with ``--workers`` workers, in this process. The forward-in-time pass of each stage
(``stages.forward.fit_coarse_time_split`` and ``stages.forward.add_sweep_time_split``) is timed
from inside the same run, so its share of the stage is measured in one run, without the noise of
comparing two runs. With ``--compare`` the sweep also runs with ``time_split=False`` afterwards,
and both wall times are printed. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/forward_cost.py \
        [--heliostats 100] [--workers 2] [--compare] [--out runs/forward-cost]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _field_module():
    spec = importlib.util.spec_from_file_location("bench_field", ROOT / "benchmarks" / "field.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _timed(module, name: str, spent: list):
    """Replace ``module.name`` by a wrapper that adds its wall seconds to ``spent``."""
    inner = getattr(module, name)

    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            spent.append(time.perf_counter() - t0)

    setattr(module, name, wrapper)
    return inner


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "forward-cost")
    a = ap.parse_args(argv)

    from heliocal.pipeline.artifacts.schemas import SELECTION, SPLIT
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages import fit_coarse, sweep
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.split import run_split

    info = _field_module().write_field(a.out / "field", a.heliostats)
    work = a.out / "work"
    if not (work / "split.parquet").exists():
        run_ingest([a.out / "field" / "calibration_log.csv"], work,
                   IngestOptions(properties=a.out / "field" / "paint"))
        run_split(work)
    split = read_artifact(work, SPLIT, columns=["heliostat_id", "time_split"])
    print(f"field: {info['heliostats']} heliostats, {info['measurements']} measurements; "
          f"{split.loc[split['time_split'].notna(), 'heliostat_id'].nunique()} with a time split; "
          f"workers {a.workers}")

    coarse_spent: list[float] = []
    _timed(fit_coarse, "fit_coarse_time_split", coarse_spent)
    t0 = time.perf_counter()
    fit_coarse.run_fit_coarse(work, workers=a.workers)
    coarse_total = time.perf_counter() - t0
    print(f"fit-coarse: {coarse_total:.1f} s, of which the time-split fit {coarse_spent[0]:.1f} s "
          f"({100 * coarse_spent[0] / coarse_total:.1f} %; "
          f"+{100 * coarse_spent[0] / (coarse_total - coarse_spent[0]):.1f} % over the stage "
          "without it)")

    sweep_spent: list[float] = []
    _timed(sweep, "add_sweep_time_split", sweep_spent)
    t0 = time.perf_counter()
    sweep.run_sweep(work, study=0, workers=a.workers)
    sweep_total = time.perf_counter() - t0
    sel = read_artifact(work, SELECTION)
    n_hybrid = int(sel["model"].str.startswith("hybrid").sum())
    print(f"sweep --study 0: {sweep_total:.1f} s, of which the forward-in-time pass "
          f"{sweep_spent[0]:.1f} s ({100 * sweep_spent[0] / sweep_total:.1f} %; "
          f"+{100 * sweep_spent[0] / (sweep_total - sweep_spent[0]):.1f} % over the sweep without "
          f"it); selected: {n_hybrid} hybrid of {len(sel)}")
    if a.compare:
        t0 = time.perf_counter()
        sweep.run_sweep(work, study=0, workers=a.workers, time_split=False)
        off = time.perf_counter() - t0
        print(f"sweep --study 0 --no-time-split: {off:.1f} s (ratio with / without "
              f"{sweep_total / off:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
