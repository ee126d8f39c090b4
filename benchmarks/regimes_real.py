"""Regimes found on real heliostats, and what leaving detected episodes out of the geometry fit
does to their test errors, on the kNN split and on the time split.

For each dataset (``../shared/data/juelich``: the CSV log of 120 heliostats with the PAINT
properties, and its PAINT folder; ``sample_data/juelich``) and each split method (``knn``, the
default, and ``time``: train on the past, validate and test on the latest rows, same sizes), it
runs ``ingest``, ``split-knn`` and ``fit-coarse`` twice: *before* (episodes not used and no
regime-aware candidates: the plain fit every heliostat got before issue 17; regime detection then
only reports) and *after* (this version: heliostats with detected episodes are fitted again
without the episodes' rows, heliostats with breaks get the regime-aware candidates of
models/regime_fit.py, each kept only when 20 % better on validation). It prints the regimes of
the heliostats asked for (default AK32, BF41), their test errors before and after, the selected
models, and for every heliostat whether its test error got worse by more than 2 %. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/regimes_real.py \
        [--heliostats AK32,BF41] [--out runs/regimes-real]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from unittest import mock

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "juelich"
if not SHARED.is_dir():
    SHARED = Path("/work/shared/data/juelich")

DATASETS = {
    "juelich-csv": ([SHARED / "csv" / "juelich_calibration_log.csv"], SHARED / "paint"),
    "juelich-paint": ([SHARED / "paint"], None),
    "sample_data": ([ROOT / "sample_data" / "juelich" / "paint"], None),
}


def _no_episodes(regimes, heliostat_id, timestamps):
    """regime_of_rows as if nothing had been detected: the fit of earlier versions."""
    return pd.DataFrame({"regime": 0, "episode": False}, index=timestamps.index)


def _plain_only(hid, spec, rows, regimes, outputs, **options):
    """fit_coarse's regime_candidates as if there were none: the plain fit is kept."""
    return outputs, []


def run_one(work: Path, sources, properties, method: str, before: bool) -> tuple[pd.DataFrame, pd.DataFrame]:
    from heliocal.pipeline.artifacts.schemas import COARSE_PARAMS, REGIMES
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.io.staged import IngestOptions
    from heliocal.pipeline.stages import coarse_regimes, fit_coarse
    from heliocal.pipeline.stages.ingest import run_ingest
    from heliocal.pipeline.stages.split import run_split

    if not (work / "split.parquet").exists():
        run_ingest(sources, work, IngestOptions(properties=properties) if properties else IngestOptions())
        run_split(work, method=method)
    if before:
        with mock.patch.object(coarse_regimes, "regime_of_rows", _no_episodes), \
                mock.patch.object(coarse_regimes, "regime_candidates", _plain_only):
            fit_coarse.run_fit_coarse(work)
    else:
        fit_coarse.run_fit_coarse(work)
    params = read_artifact(work, COARSE_PARAMS)
    params = params[params["selected"] & (params["parameter_index"] == 0)]
    return params.set_index("heliostat_id"), read_artifact(work, REGIMES)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", default="AK32,BF41")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "regimes-real")
    a = ap.parse_args(argv)
    show = [h.strip() for h in a.heliostats.split(",") if h.strip()]
    pd.set_option("display.width", 200)
    pd.set_option("display.max_rows", 500)
    for name, (sources, properties) in DATASETS.items():
        for method in ("knn", "time"):
            work = a.out / f"{name}-{method}"
            b, _ = run_one(work, sources, properties, method, before=True)
            after, regimes = run_one(work, sources, properties, method, before=False)
            cmp = pd.DataFrame({"preset_before": b["preset"], "test_before": b["test_error_mrad"],
                                "preset_after": after["preset"],
                                "test_after": after["test_error_mrad"]})
            cmp["ratio"] = cmp["test_after"] / cmp["test_before"]
            changed = cmp[(cmp["ratio"] - 1.0).abs() > 1e-9]
            worse = cmp[cmp["ratio"] > 1.02]
            print(f"\n== {name}, split {method}: {len(cmp)} heliostats, "
                  f"{int((regimes['kind'] == 'episode').sum())} episodes, "
                  f"{int((regimes['cause'] == 'detected').sum())} detected breaks, "
                  f"{int((regimes['cause'] == 'renovation').sum())} renovation breaks, "
                  f"{int((regimes['kind'] == 'outlier').sum())} outliers; refitted heliostats "
                  f"whose test error changed: {len(changed)}; worse by more than 2 %: {len(worse)}")
            models = cmp["preset_after"].str.partition("+")[2].replace("", "plain")
            print("selected after: " + ", ".join(f"{k} {v}" for k, v in
                                                  models.value_counts().sort_index().items()))
            print(f"mean test error before {cmp['test_before'].mean():.3f} mrad, after "
                  f"{cmp['test_after'].mean():.3f} mrad; median ratio after/before of the changed "
                  f"{changed['ratio'].median() if len(changed) else float('nan'):.3f}")
            if len(changed):
                print(changed.round(3).to_string())
            for hid in show:
                if hid not in cmp.index:
                    continue
                r = regimes[regimes["heliostat_id"] == hid]
                print(f"-- {hid}: test error before {cmp.loc[hid, 'test_before']:.3f} mrad "
                      f"({cmp.loc[hid, 'preset_before']}), after "
                      f"{cmp.loc[hid, 'test_after']:.3f} mrad ({cmp.loc[hid, 'preset_after']})")
                cols = ["kind", "regime", "start", "end", "cause", "n_rows", "step_mrad", "evidence",
                        "noise_mrad", "error_mrad"]
                print(r[cols].round(3).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
