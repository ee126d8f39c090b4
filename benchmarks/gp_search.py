"""Benchmark: the sweep's GP fits with heliocal's likelihood (models/gp_likelihood.py) against
scikit-learn's own, on the same heliostats in one run.

For the ``--heliostats`` K heliostats of WORKDIR with the most rows (the costliest fits), each
fit is what the sweep runs (:func:`heliocal.pipeline.models.gp_heliostat.fit_heliostat_gps`:
both kernel structures, their restarts, the fade choice), once with ``Regressor`` and once with
scikit-learn's ``GaussianProcessRegressor`` in its place, alternating which goes first, in one
process with one thread. Prints per heliostat the rows, both times, their ratio and the largest
relative differences of the structures' log marginal likelihoods and mean errors; then the
total times and their ratio. Usage (after a sweep's inputs exist, e.g. benchmarks/field.py's
work directory)::

    .venv/bin/python benchmarks/gp_search.py runs/field-bench/full-200-w2 --heliostats 12
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time
from pathlib import Path

from sklearn.gaussian_process import GaussianProcessRegressor

import heliocal.pipeline.models.gp as gp
from heliocal.pipeline.models.fade import TIME_FADE_DAYS
from heliocal.pipeline.models.gp_heliostat import fit_heliostat_gps
from heliocal.pipeline.models.selection import SelectionRule
from heliocal.pipeline.runtime.process_state import one_thread
from heliocal.pipeline.stages.fit_coarse import coarse_row_parameters
from heliocal.pipeline.stages.selection import CandidatePool
from heliocal.pipeline.stages.sweep_inputs import SweepHeliostat, read_sweep_inputs


@contextlib.contextmanager
def _scikit_learn_likelihood():
    """The GP module's regressor replaced by scikit-learn's for the block."""
    ours = gp.Regressor
    gp.Regressor = GaussianProcessRegressor
    try:
        yield
    finally:
        gp.Regressor = ours


def _fit(h: SweepHeliostat, weights, config) -> tuple[float, dict]:
    """Seconds of one heliostat's GP fits and per structure (log marginal likelihood, mean
    error [mrad])."""
    t0 = time.perf_counter()
    fits = fit_heliostat_gps(h.rows, h.labels, h.spec, h.data,
                             coarse_row_parameters(h.selected, h.rows["timestamp"]), config,
                             weights, time_length_days=TIME_FADE_DAYS)
    seconds = time.perf_counter() - t0
    return seconds, {s: (f.model.log_marginal_likelihood, float(f.errors.mean()))
                     for s, f in fits.items()}


def _relative(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), abs(b), 1e-300)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--heliostats", type=int, default=12)
    args = ap.parse_args()
    items = read_sweep_inputs(args.workdir, None)
    chosen = sorted(items, key=lambda h: (-len(items[h].rows), h))[:args.heliostats]
    config = gp.GPConfig().validated()
    totals = {"scikit-learn": 0.0, "heliocal": 0.0}
    ratios = []
    print(f"{'heliostat':12s} {'rows':>5s} {'scikit-learn':>13s} {'heliocal':>9s} {'ratio':>6s} "
          f"{'d lml':>9s} {'d error':>9s}")
    with one_thread(blas=True):
        for k, hid in enumerate(chosen):
            h = SweepHeliostat.of(items[hid])
            weights = CandidatePool(h, SelectionRule()).weights
            runs = {}
            for name in (("scikit-learn", "heliocal") if k % 2 == 0
                         else ("heliocal", "scikit-learn")):
                with (_scikit_learn_likelihood() if name == "scikit-learn"
                      else contextlib.nullcontext()):
                    runs[name] = _fit(h, weights, config)
            (t_ref, ref), (t_ours, ours) = runs["scikit-learn"], runs["heliocal"]
            totals["scikit-learn"] += t_ref
            totals["heliocal"] += t_ours
            ratios.append(t_ours / t_ref)
            d_lml = max(_relative(ref[s][0], ours[s][0]) for s in ref)
            d_err = max(_relative(ref[s][1], ours[s][1]) for s in ref)
            print(f"{hid:12s} {len(h.rows):5d} {t_ref:12.2f}s {t_ours:8.2f}s {t_ours / t_ref:6.3f} "
                  f"{d_lml:9.1e} {d_err:9.1e}")
    print(f"total: scikit-learn {totals['scikit-learn']:.2f} s, heliocal {totals['heliocal']:.2f} s, "
          f"ratio {totals['heliocal'] / totals['scikit-learn']:.3f} (median of the heliostats' "
          f"ratios {statistics.median(ratios):.3f})")


if __name__ == "__main__":
    main()
