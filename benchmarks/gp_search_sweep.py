"""Check: the GP's search (models/gp_likelihood.py) against scikit-learn's through a whole sweep
with the time split and the training-size study at 5, 10 and 20 rows, on two copies of
WORKDIR (after fit-coarse); compares every GP row's errors and the selections' models and
errors, kNN and forward in time. Usage (the sample's CI work directory, for instance)::

    .venv/bin/python benchmarks/gp_search_sweep.py runs/ci
"""
import shutil, sys
from pathlib import Path
import numpy as np, pandas as pd
from sklearn.gaussian_process import GaussianProcessRegressor
import heliocal.pipeline.models.gp as gp
from heliocal.pipeline.stages.sweep import run_sweep
src = Path(sys.argv[1]); root = src.parent / f"{src.name}-gp-search"; shutil.rmtree(root, ignore_errors=True)
out = {}
for arm in ("scikit-learn", "heliocal"):
    wd = shutil.copytree(src, root / arm)
    ours = gp.Regressor
    if arm == "scikit-learn":
        gp.Regressor = GaussianProcessRegressor
    try:
        run_sweep(wd, n_train=[5, 10, 20], study=None, time_split=True, workers=1)
    finally:
        gp.Regressor = ours
    out[arm] = (pd.read_parquet(wd / "sweep.parquet"), pd.read_parquet(wd / "selection.parquet"))
(a, sa), (b, sb) = out["scikit-learn"], out["heliocal"]
k = ["heliostat_id", "model", "n_train", "weight_decay", "seed"]
m = a.merge(b, on=k, suffixes=("_a", "_b"))
g = m[m.model.str.startswith("gp")]
print("rows", len(a), len(b), "gp rows", len(g), "n_train", sorted(g.n_train.unique()))
for c in ("train_error_mrad", "val_error_mrad", "test_error_mrad"):
    d = (g[c + "_a"] - g[c + "_b"]).abs() / g[c + "_a"].abs().clip(lower=1e-300)
    print(c, f"largest relative difference {d.max():.2e}")
print("selection models equal:", sa["model"].tolist() == sb["model"].tolist(), sa["model"].tolist())
for c in ("test_error_mrad", "val_error_mrad", "time_test_error_mrad", "time_val_error_mrad"):
    x, y = sa[c].to_numpy(float), sb[c].to_numpy(float)
    ok = ~np.isnan(x)
    d = np.abs(x[ok] - y[ok]) / np.abs(x[ok]) if ok.any() else np.array([0.0])
    print(c, "missing alike:", bool((np.isnan(x) == np.isnan(y)).all()), f"largest relative difference {d.max():.2e}")
