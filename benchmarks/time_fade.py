"""How long may a fine model's correction hold forward in time? The hybrid networks' time fade
length (models/fade.py ``NETWORK_TIME_FADE_DAYS``) measured on the time split.

For each work directory ``benchmarks/fine_selection.py`` prepared (``--out``), the production
sweep runs once per time fade length of ``--lengths`` (``sweep --study 0 --time-split``, no GP:
the time fade of the networks alone; the forward check off, so every length judges the hybrids
the kNN split chose, which do not depend on it: the time split's rows lie after the training
period, where the fade acts). Printed per length, over
the heliostats whose selected model is a hybrid: the median and mean ratio of its mean error on
the time split's validation rows (the forward check's figure) and test rows to the coarse
model's, and how many of them are worse than the coarse model forward in time by more than 5 %.
Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/time_fade.py \\
        [--out runs/fine-selection] [--lengths inf,180,60,30]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from unittest import mock

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def run(wd: Path, days: float) -> pd.DataFrame:
    from heliocal.pipeline.artifacts.schemas import SELECTION
    from heliocal.pipeline.artifacts.store import read_artifact
    from heliocal.pipeline.stages import fit_hybrid, forward, selection
    from heliocal.pipeline.stages.sweep import run_sweep

    # every kNN choice kept (no forward check), so each length judges the same hybrids
    with mock.patch.object(selection, "NETWORK_TIME_FADE_DAYS", days), \
            mock.patch.object(forward, "NETWORK_TIME_FADE_DAYS", days), \
            mock.patch.object(fit_hybrid, "NETWORK_TIME_FADE_DAYS", days), \
            mock.patch.object(selection, "FORWARD_TOLERANCE", math.inf):
        run_sweep(wd, study=0, workers=1, time_split=True, gp=False)
    return read_artifact(wd, SELECTION)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "fine-selection")
    ap.add_argument("--lengths", default="inf,180,60,30")
    ap.add_argument("--datasets", default="", help="work directory names (default: all)")
    a = ap.parse_args(argv)
    wds = sorted(w for w in a.out.glob("wd-*") if "-n" not in w.name[3:].replace("-paint", "")
                 and (not a.datasets or w.name[3:] in a.datasets.split(",")))
    print("| time fade [days] | hybrids | time validation / coarse (median, mean) | time test / "
          "coarse (median, mean) | time test > 5 % worse |\n|---|---|---|---|---|")
    for days in [float(x) for x in a.lengths.split(",")]:
        frames = [run(wd, days).assign(data=wd.name[3:]) for wd in wds]
        sel = pd.concat(frames, ignore_index=True)
        h = sel[sel["model"].astype(str).str.startswith("hybrid")
                & sel["time_test_error_mrad"].notna()]
        v = h["time_val_error_mrad"] / h["coarse_time_val_error_mrad"]
        t = h["time_test_error_mrad"] / h["coarse_time_test_error_mrad"]
        label = "inf" if math.isinf(days) else f"{days:g}"
        print(f"| {label} | {len(h)} | {v.median():.3f}, {v.mean():.3f} | {t.median():.3f}, "
              f"{t.mean():.3f} | {int((t > 1.05).sum())} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
