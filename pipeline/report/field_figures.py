"""Figures of the whole field (matplotlib, Agg): the distribution of the heliostats' test errors,
and paper 000's figures as field aggregates with their spread across heliostats (weight decay,
training size, hybrid against coarse).

The numbers they draw are aggregated in the main process (:func:`weight_decay_frame`,
:func:`training_size_frame`: groupbys over sweep.parquet) and drawn by :func:`draw_field_figure`
in a worker (``render.render_task``).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .figures import new_figure
from .metrics import WITHOUT_FIELD_PRIOR, model_sort_key

__all__ = [
    "comparison_table",
    "draw_field_figure",
    "training_size_frame",
    "weight_decay_frame",
]


def _cdf(args: dict):
    """Empirical CDF of the per-heliostat test error (and of the next-day error of the
    rolling-origin evaluation, dotted) with reference lines and the floor."""
    err = np.sort(np.asarray(args["errors"], float))
    err = err[np.isfinite(err)]
    if not len(err):
        return None, "no heliostat has a test error yet (run fit-coarse with a split)"
    fig, axes = new_figure(7.0, 3.9)
    ax = axes[0, 0]
    frac = np.arange(1, len(err) + 1) / len(err)
    ax.step(np.concatenate([[0.0], err]), np.concatenate([[0.0], frac]), where="post",
            color="k", lw=1.6, label=f"test error, {len(err)} heliostats")
    nxt = np.sort(np.asarray(args.get("next_day", []), float))
    nxt = nxt[np.isfinite(nxt)]
    if len(nxt):   # the rolling-origin evaluation: recalibrated every calibration day
        ax.step(np.concatenate([[0.0], nxt]), np.concatenate([[0.0], np.arange(1, len(nxt) + 1)
                                                              / len(nxt)]), where="post",
                color="tab:blue", lw=1.3, ls=":", label=f"next-day error, {len(nxt)} heliostats")
    colors = {0.5: "tab:green", 1.0: "tab:olive", 2.0: "tab:red"}
    for x in args["lines"]:
        share = float((err <= x).mean())
        ax.axvline(x, color=colors.get(x, "0.5"), ls="--", lw=1,
                   label=f"{x:g} mrad: {100 * share:.0f} % of heliostats below")
    floor = args.get("floor")
    if floor is not None and math.isfinite(floor):
        ax.axvspan(0, floor, color="0.85", zorder=0,
                   label=f"measurement floor {floor:.2f} mrad ({args.get('floor_source', '')})")
    top = max(float(np.percentile(err, 99)) * 1.15, max(args["lines"]) * 1.1,
              float(np.percentile(nxt, 95)) * 1.1 if len(nxt) else 0.0)
    ax.set_xlim(0, top)
    ax.set_ylim(0, 1.0)
    ax.set_xlabel("mean error per heliostat [mrad]")
    ax.set_ylabel("share of heliostats")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="lower right")
    return fig, None


def weight_decay_frame(sweep: pd.DataFrame | None) -> pd.DataFrame | None:
    """Per heliostat, hybrid model and weight decay at the heliostat's largest training size:
    mean (over seeds) validation and test error, and the heliostat's coarse levels (the selected
    preset's rows have no weight decay)."""
    if sweep is None or not {"weight_decay", "val_error_mrad", "test_error_mrad", "n_train",
                             "model"} <= set(sweep.columns):
        return None
    s = sweep[sweep["weight_decay"].notna()]
    if not len(s):
        return None
    s = s[s["n_train"] == s.groupby(["heliostat_id", "model"])["n_train"].transform("max")]
    g = s.groupby(["model", "heliostat_id", "weight_decay"], sort=True)[
        ["val_error_mrad", "test_error_mrad"]].mean().reset_index()
    return g if g["weight_decay"].nunique() >= 2 else None


def training_size_frame(sweep: pd.DataFrame | None) -> pd.DataFrame | None:
    """Per model, heliostat of the training-size study and training size: the mean (over seeds)
    test error at the weight decay with the lowest mean validation error (models without weight
    decay: their only rows). The presets fitted without the field prior
    (:data:`~.metrics.WITHOUT_FIELD_PRIOR`) are left to the field-prior page."""
    if sweep is None or not {"n_train", "model", "val_error_mrad", "test_error_mrad"} <= set(
            sweep.columns):
        return None
    sweep = sweep[~sweep["model"].astype(str).str.endswith(WITHOUT_FIELD_PRIOR)]
    sizes = sweep.groupby("heliostat_id")["n_train"].nunique()
    s = sweep[sweep["heliostat_id"].isin(sizes[sizes >= 2].index)]
    if not len(s):
        return None
    keys = ["model", "heliostat_id", "n_train"]
    g = s.assign(weight_decay=s["weight_decay"].fillna(-1.0)).groupby(
        keys + ["weight_decay"], sort=True)[["val_error_mrad", "test_error_mrad"]].mean()
    g = g.reset_index()
    best = g.loc[g.groupby(keys)["val_error_mrad"].idxmin().dropna().astype(int)]
    return best[keys + ["test_error_mrad"]].reset_index(drop=True)


def _band(ax, x, groups, color, label):
    """The median over heliostats as a line, the 25-75 % range as a band."""
    q = groups.quantile([0.25, 0.5, 0.75]).unstack()
    line, = ax.plot(x, q[0.5], marker="o", ms=4, color=color, label=label)
    ax.fill_between(x, q[0.25], q[0.75], color=line.get_color(), alpha=0.15, lw=0)


def _weight_decay(args: dict):
    g: pd.DataFrame = args["frame"]
    fig, axes = new_figure(8.0, 4.4)
    ax = axes[0, 0]
    colors = iter(["tab:blue", "tab:orange", "tab:green", "tab:purple"])
    for model in sorted(g["model"].astype(str).unique(), key=model_sort_key):
        gm = g[g["model"] == model]
        for col, split in (("val_error_mrad", "validation"), ("test_error_mrad", "test")):
            by = gm.groupby("weight_decay")[col]
            n = gm["heliostat_id"].nunique()
            _band(ax, np.array(sorted(gm["weight_decay"].unique())), by, next(colors, "0.4"),
                  f"{model}, {split} ({n} heliostats)")
    for level, color, split in ((args.get("coarse_val"), "#08306b", "validation"),
                                (args.get("coarse_test"), "#6baed6", "test")):
        if level is not None and math.isfinite(level):
            ax.axhline(level, color=color, ls="--", lw=1.2,
                       label=f"coarse (selected preset), {split}: field median")
    wd = g["weight_decay"]
    if (wd <= 0).any():
        ax.set_xscale("symlog", linthresh=float(wd[wd > 0].min()) if (wd > 0).any() else 1e-6)
        ax.set_xlim(left=0)  # weight decays are never negative
    else:
        ax.set_xscale("log")
    ax.set_xlabel("weight decay [1]")
    ax.set_ylabel("mean error [mrad]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.set_title("Error against weight decay across the field", fontsize="medium")
    ax.legend(fontsize="x-small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None


def _training_size(args: dict):
    g: pd.DataFrame = args["frame"]
    fig, axes = new_figure(8.0, 4.4)
    ax = axes[0, 0]
    for model in sorted(g["model"].astype(str).unique(), key=model_sort_key):
        gm = g[g["model"] == model]
        n = gm["heliostat_id"].nunique()
        # sizes most of the heliostats share (each heliostat's full size is its own)
        counts = gm.groupby("n_train")["heliostat_id"].nunique()
        sizes = counts[counts >= max(1, math.ceil(2 * n / 3))].index
        gm = gm[gm["n_train"].isin(sizes)]
        if not len(gm):
            continue
        _band(ax, np.array(sorted(gm["n_train"].unique())), gm.groupby("n_train")[
            "test_error_mrad"], None, f"{model} ({n} heliostats)")
    ax.set_xlabel("training measurements")
    ax.set_ylabel("mean test error [mrad]")
    if (g["test_error_mrad"] > 0).all():
        ax.set_yscale("log")  # rigid-body presets fitted on a few rows miss by 100x
    else:
        ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.set_title("Test error against training size across the study's heliostats",
                 fontsize="medium")
    ax.legend(fontsize="x-small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None


def _comparison(args: dict):
    t: pd.DataFrame = args["table"]
    fig, axes = new_figure(8.0, 4.2, 1, 2)
    for ax, split in zip(axes[0], ("validation", "test")):
        c, h = t[f"coarse_{split}"].to_numpy(float), t[f"hybrid_{split}"].to_numpy(float)
        ok = np.isfinite(c) & np.isfinite(h)
        chose = t["model"].astype(str).str.startswith("hybrid").to_numpy()
        for mask, color, label in ((ok & chose, "tab:red", "hybrid selected"),
                                   (ok & ~chose, "#6baed6", "coarse kept")):
            ax.scatter(c[mask], h[mask], s=12, color=color, alpha=0.7, lw=0,
                       label=f"{label} ({int(mask.sum())})")
        top = float(np.nanmax(np.concatenate([c[ok], h[ok]]))) * 1.05 if ok.any() else 1.0
        ax.plot([0, top], [0, top], color="0.3", lw=1, ls="--", label="equal")
        ax.set_xlim(0, top)
        ax.set_ylim(0, top)
        ax.set_aspect("equal")
        better = float(np.median(h[ok] / c[ok])) if ok.any() else float("nan")
        ax.set_title(f"{split}: median hybrid / coarse = {better:.2f}", fontsize="medium")
        ax.set_xlabel("coarse (selected preset) [mrad]")
        ax.set_ylabel("best hybrid candidate [mrad]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="x-small", loc="upper left")
    return fig, None


def comparison_table(frame: pd.DataFrame | None, selection: pd.DataFrame | None) -> pd.DataFrame | None:
    """Per heliostat: validation and test error of fit-coarse's selected preset (selection.parquet)
    and of the hybrid candidate with the lowest validation error (``frame`` of
    :func:`weight_decay_frame`), and the sweep's choice (``model``)."""
    need = {"heliostat_id", "model", "coarse_val_error_mrad", "coarse_test_error_mrad"}
    if frame is None or selection is None or not need <= set(selection.columns):
        return None
    best = frame.loc[frame.groupby("heliostat_id")["val_error_mrad"].idxmin().dropna().astype(int)]
    sel = selection.assign(heliostat_id=selection["heliostat_id"].astype(str))
    t = sel.merge(best.assign(heliostat_id=best["heliostat_id"].astype(str)),
                  on="heliostat_id", suffixes=("", "_best"))
    if not len(t):
        return None
    return pd.DataFrame({"heliostat_id": t["heliostat_id"], "model": t["model"].astype(str),
                         "coarse_validation": t["coarse_val_error_mrad"].astype(float),
                         "coarse_test": t["coarse_test_error_mrad"].astype(float),
                         "hybrid_validation": t["val_error_mrad_best"].astype(float),
                         "hybrid_test": t["test_error_mrad_best"].astype(float)})


def draw_field_figure(kind: str, args: dict):
    """(figure, None) or (None, why) of a field figure ``kind`` (``field_cdf``,
    ``field_weight_decay``, ``field_training_size``, ``field_comparison``)."""
    return {"field_cdf": _cdf, "field_weight_decay": _weight_decay,
            "field_training_size": _training_size, "field_comparison": _comparison}[kind](args)
