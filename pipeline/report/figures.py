"""The report's figures (matplotlib, Agg backend): training size, sky map of errors, weight decay,
hybrid versus coarse, error over time. Each function returns a figure; nothing is shown.
"""

from __future__ import annotations

import io
import logging
import math

import numpy as np
import pandas as pd

from .inputs import ReportInputs
from .metrics import (WITHOUT_FIELD_PRIOR, column_of, final_models, first_column,
                      model_sort_key, split_sort_key)

__all__ = [
    "hybrid_vs_coarse_table",
    "new_figure",
    "png_bytes",
    "plot_training_size",
    "plot_sky_map",
    "plot_weight_decay",
    "plot_hybrid_vs_coarse",
    "plot_error_over_time",
    "plot_gp_correction",
    "SKY_POINTS_PER_MRAD",
]

log = logging.getLogger("heliocal.report")


#: Radius of an error circle on the sky map per mrad of error [pt]; larger errors are clipped.
SKY_POINTS_PER_MRAD = 4.0


SKY_CLIP_MRAD = 6.0


#: Title height in axes coordinates. Given, not found: matplotlib's automatic placement (which
#: measures every tick label to dodge them) costs ~15 % of a per-heliostat figure.
TITLE_Y = 1.01


_SPLIT_COLORS = {"train": "0.55", "validation": "tab:blue", "test": "tab:orange", "unused": "0.8"}


# ------------------------------------------------------------------------------------------------
# figures (matplotlib Figure objects: Agg renderer, no pyplot)
# ------------------------------------------------------------------------------------------------
def new_figure(width: float, height: float, nrows: int = 1, ncols: int = 1,
               margins_in: tuple[float, float, float, float] | None = None, **kw):
    """A matplotlib Figure (Agg, no pyplot) and its axes (2-D array).

    ``margins_in``: fixed (left, right, bottom, top) margins in inches around the axes (room for
    labels and a legend outside the axes); without them matplotlib's constrained layout places
    everything, which costs about as much again as drawing the figure: the figures drawn once
    per heliostat use fixed margins, so that a field of thousands is drawn in minutes.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout=None if margins_in else "constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    if margins_in:
        left, right, bottom, top = margins_in
        fig.subplots_adjust(left=left / width, right=1 - right / width, bottom=bottom / height,
                            top=1 - top / height)
    return fig, axes


def png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    # zlib level 1: a third faster to encode than the default 6, files ~6 % larger
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None},
                pil_kwargs={"compress_level": 1})
    return buf.getvalue()


def _best_weight_decay_rows(g: pd.DataFrame, val: str | None, test: str) -> pd.DataFrame:
    """Per n_train: seeds' test errors at the weight decay with the lowest mean validation error."""
    wd = first_column(g, "weight_decay")
    out = []
    for n, gn in g.groupby("n_train", sort=True):
        if wd is not None and val is not None and gn[wd].nunique() > 1:
            by = gn.groupby(wd)[val].mean()
            gn = gn[gn[wd] == by.idxmin()]
        out.append({"n_train": n, "mean": gn[test].mean(), "min": gn[test].min(),
                    "max": gn[test].max()})
    return pd.DataFrame(out)


def plot_training_size(sweep: pd.DataFrame, heliostat: str,
                       coarse_test_mrad: float | None = None, coarse_label: str = "coarse"):
    """Paper 000, fig. 6: test error against training size per model; test-to-train distance below.

    For each model and training size the weight decay with the lowest validation error (mean over
    seeds) is used; the band spans the seeds; the presets fitted without the field prior are
    the field-prior page's. Returns ``(figure, None)`` or ``(None, reason)``.
    """
    test, val = column_of(sweep, "test"), column_of(sweep, "validation")
    dist = first_column(sweep, "test_train_distance_deg")
    if test is None or "n_train" not in sweep.columns or "model" not in sweep.columns:
        return None, "sweep.parquet has no n_train, model or test error column"
    g = sweep[(sweep["heliostat_id"].astype(str) == heliostat)   # without: the prior page's
              & ~sweep["model"].astype(str).str.endswith(WITHOUT_FIELD_PRIOR)]
    if g["n_train"].nunique() < 2:
        return None, (f"the sweep of {heliostat} has a single training size: it is not in the "
                      "training-size study (`heliocal sweep --study N` samples N heliostats)")
    fig, axes = new_figure(7.5, 6.0, 2, 1, margins_in=(0.8, 0.2, 0.55, 0.35), sharex=True,
                           height_ratios=(2.2, 1), gridspec_kw={"hspace": 0.08})
    ax, ax2 = axes[0, 0], axes[1, 0]
    for model in sorted(g["model"].astype(str).unique(), key=model_sort_key):
        b = _best_weight_decay_rows(g[g["model"].astype(str) == model], val, test)
        line, = ax.plot(b["n_train"], b["mean"], marker="o", ms=4, label=model)
        if (b["max"] > b["min"]).any():
            ax.fill_between(b["n_train"], b["min"], b["max"], color=line.get_color(), alpha=0.15,
                            lw=0)
    if coarse_test_mrad is not None and math.isfinite(coarse_test_mrad):
        ax.axhline(coarse_test_mrad, color="0.3", ls="--", lw=1,
                   label=f"{coarse_label} (all training data)")
    ax.set_ylabel("mean test error [mrad]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", ncols=2)
    ax.set_title(f"{heliostat}: test error against training size", y=TITLE_Y)
    if dist is not None:
        d = g.groupby("n_train", sort=True)[dist].mean()
        ax2.plot(d.index, d.to_numpy(), marker="o", ms=4, color="0.2")
        ax2.set_ylabel("test-to-train\ndistance [deg]")
    else:
        ax2.text(0.5, 0.5, "sweep.parquet has no test_train_distance_deg", ha="center",
                 va="center", transform=ax2.transAxes)
    ax2.set_xlabel("training measurements")
    ax2.grid(alpha=0.3)
    return fig, None


def plot_sky_map(measurements: pd.DataFrame, split: pd.DataFrame | None,
                 predictions: pd.DataFrame | None, heliostat: str, model: str | None,
                 label: str | None = None):
    """Paper 000, fig. 7: measurements over sun azimuth and elevation.

    Training points are dots; each validation and test point is a filled circle whose radius grows
    linearly with its error (:data:`SKY_POINTS_PER_MRAD` pt per mrad, clipped at
    :data:`SKY_CLIP_MRAD`), inside a grey ring of 1 mrad for reference. ``label``: the model's
    name in the title (default ``model``).
    """
    model_name = label or model  # (the loops below use `label` for the splits)
    m = measurements[measurements["heliostat_id"] == heliostat][
        ["measurement_id", "sun_azimuth_deg", "sun_elevation_deg"]]
    if split is not None:
        s = split[split["heliostat_id"] == heliostat][["measurement_id", "split"]]
        m = m.merge(s, on="measurement_id", how="left")
        m["split"] = m["split"].fillna("unsplit")
    else:
        m = m.assign(split="unsplit")
    if predictions is not None and model is not None:
        p = predictions[(predictions["heliostat_id"] == heliostat) & (predictions["model"] == model)]
        m = m.merge(p[["measurement_id", "error_mrad"]], on="measurement_id", how="left")
    else:
        m["error_mrad"] = np.nan
    fig, axes = new_figure(8.5, 4.8, margins_in=(0.65, 2.45, 0.55, 0.35))
    ax = axes[0, 0]
    k = SKY_POINTS_PER_MRAD
    handles = []
    from matplotlib.lines import Line2D

    for label, color, marker, size in (("train", "0.25", "o", 9), ("unused", "0.7", "x", 12),
                                       ("unsplit", "0.25", "o", 9)):
        g = m[m["split"] == label]
        if len(g):
            ax.scatter(g["sun_azimuth_deg"], g["sun_elevation_deg"], s=size, c=color,
                       marker=marker, lw=0.8 if marker == "x" else 0, zorder=2)
            handles.append(Line2D([], [], ls="", marker=marker, color=color, ms=4,
                                  label={"unsplit": "measurement", "unused": "unused (not trained on)"}
                                  .get(label, "training")))
    ring_drawn = False
    for label in ("validation", "test"):
        g = m[m["split"] == label]
        if not len(g):
            continue
        color = _SPLIT_COLORS[label]
        err = g["error_mrad"].to_numpy(float)
        has_err = np.isfinite(err)
        if not has_err.any():
            ax.scatter(g["sun_azimuth_deg"], g["sun_elevation_deg"], s=16, c=color, zorder=3)
            handles.append(Line2D([], [], ls="", marker="o", color=color, ms=4, label=label))
            continue
        shown = np.clip(err, 0, SKY_CLIP_MRAD)
        ax.scatter(g["sun_azimuth_deg"][has_err], g["sun_elevation_deg"][has_err],
                   s=(2 * k) ** 2, facecolors="none", edgecolors="0.6", lw=0.8, zorder=3)
        ring_drawn = True
        ax.scatter(g["sun_azimuth_deg"][has_err], g["sun_elevation_deg"][has_err],
                   s=(2 * k * shown[has_err]) ** 2, c=color, alpha=0.55, lw=0.6,
                   edgecolors=color, zorder=4)
        clipped = has_err & (err > SKY_CLIP_MRAD)
        if clipped.any():
            ax.scatter(g["sun_azimuth_deg"][clipped], g["sun_elevation_deg"][clipped],
                       s=(2 * k * SKY_CLIP_MRAD) ** 2, facecolors="none", edgecolors="k",
                       linestyle="--", lw=0.8, zorder=5)
        handles.append(Line2D([], [], ls="", marker="o", color=color, alpha=0.55, ms=2 * k,
                              label=f"{label} (mean {np.nanmean(err):.2f} mrad)"))
    if ring_drawn:
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec="0.6", ms=2 * k,
                              label="1 mrad reference"))
        if (m["error_mrad"] > SKY_CLIP_MRAD).any():
            handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec="k", ms=8,
                                  label=f"dashed: clipped at {SKY_CLIP_MRAD:g} mrad"))
    ax.set_xlabel("sun azimuth [deg] (0 = south, positive toward east)")
    ax.set_ylabel("sun elevation [deg]")
    ax.grid(alpha=0.3)
    ax.margins(0.06)
    title = f"{heliostat}: measurements in sun position"
    if model is not None and ring_drawn:
        title += f"; circle radius = error of {model_name}"
    ax.set_title(title, fontsize="medium", y=TITLE_Y)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small",
              borderaxespad=0, labelspacing=1.0)
    return fig


def plot_weight_decay(sweep: pd.DataFrame, heliostat: str, model: str | None,
                      coarse_val_mrad: float | None, coarse_test_mrad: float | None,
                      selected_weight_decay: float | None = None):
    """Paper 000, fig. 9a: validation and test error against weight decay; coarse levels as lines.

    Uses ``model`` (default: the model with the most weight decays, preferring ``hybrid``) at its
    largest training size; the band spans the seeds. Returns ``(figure, None)`` or ``(None, why)``.
    """
    wd, test, val = (first_column(sweep, "weight_decay"), column_of(sweep, "test"),
                     column_of(sweep, "validation"))
    if wd is None or test is None or "model" not in sweep.columns:
        return None, "sweep.parquet has no weight_decay, model or test error column"
    g = sweep[sweep["heliostat_id"].astype(str) == heliostat].copy()
    g["model"] = g["model"].astype(str)
    if model not in set(g["model"]):
        counts = g.groupby("model")[wd].nunique()
        if not len(counts):
            return None, f"sweep.parquet has no rows of {heliostat}"
        model = "hybrid" if "hybrid" in counts.index else str(counts.idxmax())
    g = g[g["model"] == model]
    if "n_train" in g.columns:
        g = g[g["n_train"] == g["n_train"].max()]
    if g[wd].nunique() < 2:
        return None, f"the sweep of {heliostat} ({model}) has a single weight decay"
    fig, axes = new_figure(7.8, 4.4, margins_in=(0.65, 2.1, 0.55, 0.35))
    ax = axes[0, 0]
    positive = g.loc[g[wd] > 0, wd]
    if (g[wd] <= 0).any():
        ax.set_xscale("symlog", linthresh=float(positive.min()) if len(positive) else 1e-6)
    else:
        ax.set_xscale("log")
    for split, col, color in (("validation", val, "tab:blue"), ("test", test, "tab:orange")):
        if col is None:
            continue
        a = g.groupby(wd, sort=True)[col].agg(["mean", "min", "max"])
        ax.plot(a.index, a["mean"], marker="o", ms=4, color=color, label=f"{model}, {split}")
        if (a["max"] > a["min"]).any():
            ax.fill_between(a.index, a["min"], a["max"], color=color, alpha=0.15, lw=0)
    for level, color, split in ((coarse_val_mrad, "#08306b", "validation"),
                                (coarse_test_mrad, "#6baed6", "test")):
        if level is not None and math.isfinite(level):
            ax.axhline(level, color=color, ls="--", lw=1.2, label=f"coarse, {split}")
    if selected_weight_decay is not None and math.isfinite(selected_weight_decay):
        ax.axvline(selected_weight_decay, color="0.4", ls=":", lw=1,
                   label=f"selected ({selected_weight_decay:g})")
    ax.set_xlabel("weight decay [1]")
    ax.set_ylabel("mean error [mrad]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.set_title(f"{heliostat}: error against weight decay ({model})", fontsize="medium",
                 y=TITLE_Y)
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None


def hybrid_vs_coarse_table(inp: ReportInputs) -> pd.DataFrame | None:
    """Per heliostat: validation and test mean error of the selected coarse and hybrid model."""
    sel = inp.selection
    if sel is not None and all(c in sel.columns for c in ("heliostat_id", "val_error_mrad",
                                                           "test_error_mrad",
                                                           "coarse_val_error_mrad",
                                                           "coarse_test_error_mrad")):
        return pd.DataFrame({
            "heliostat_id": sel["heliostat_id"].astype(str),
            "model": sel["model"].astype(str) if "model" in sel.columns else "hybrid",
            "coarse_validation": sel["coarse_val_error_mrad"].astype(float),
            "coarse_test": sel["coarse_test_error_mrad"].astype(float),
            "hybrid_validation": sel["val_error_mrad"].astype(float),
            "hybrid_test": sel["test_error_mrad"].astype(float),
        }).sort_values("heliostat_id").reset_index(drop=True)
    p = inp.predictions
    if p is None or not (p["source"] == "hybrid_predictions").any():
        return None
    rows = []
    for hid, f in sorted(final_models(inp).items()):
        hp = p[(p["heliostat_id"] == hid) & (p["source"] == "hybrid_predictions")]
        if not len(hp) or f.get("coarse_preset") is None:
            continue
        hmodel = f["model"] if f["model"] in set(hp["model"]) else (
            "hybrid" if "hybrid" in set(hp["model"]) else str(hp["model"].iloc[0]))
        cp = p[(p["heliostat_id"] == hid) & (p["model"] == f["coarse_preset"])]
        hp = hp[hp["model"] == hmodel]
        rows.append({"heliostat_id": hid, "model": hmodel,
                     **{f"coarse_{s}": cp.loc[cp["split"] == s, "error_mrad"].mean()
                        for s in ("validation", "test")},
                     **{f"hybrid_{s}": hp.loc[hp["split"] == s, "error_mrad"].mean()
                        for s in ("validation", "test")}})
    return pd.DataFrame(rows) if rows else None


def plot_hybrid_vs_coarse(table: pd.DataFrame):
    """Paper 000, fig. 8: mean validation and test error of hybrid and coarse per heliostat."""
    n = len(table)
    fig, axes = new_figure(max(6.0, 1.6 * n + 3.0), 4.2, 1, 2, sharey=True)
    x = np.arange(n)
    w = 0.38
    top = np.nanmax(table[["coarse_validation", "coarse_test", "hybrid_validation",
                           "hybrid_test"]].to_numpy(float))
    for ax, split in zip(axes[0], ("validation", "test")):
        for off, kind, color in ((-w / 2, "coarse", "#6baed6"), (w / 2, "hybrid", "tab:red")):
            vals = table[f"{kind}_{split}"].to_numpy(float)
            label = "coarse (selected preset)" if kind == "coarse" else "hybrid (selected)"
            bars = ax.bar(x + off, vals, w, color=color, label=label)
            ax.bar_label(bars, labels=[f"{v:.2f}" if math.isfinite(v) else "n/a" for v in vals],
                         fontsize="x-small", padding=2)
        ax.set_xticks(x, table["heliostat_id"])
        ax.set_title(f"{split} set", fontsize="medium")
        ax.set_xlabel("heliostat")
        ax.grid(alpha=0.3, axis="y")
        ax.set_ylim(0, top * 1.18 if math.isfinite(top) and top > 0 else 1)
    axes[0, 0].set_ylabel("mean error [mrad]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=2, fontsize="small")
    fig.suptitle("Hybrid against coarse model per heliostat")
    return fig


def plot_error_over_time(measurements: pd.DataFrame, predictions: pd.DataFrame, heliostat: str,
                         model: str, coarse_model: str | None = None, window_days: int = 30,
                         label: str | None = None):
    """Error of ``model`` over the measurement date, coloured by split, with a rolling median.

    The rolling median (``window_days``, centred) shows drift and seasonal patterns; with a
    different ``coarse_model`` its rolling median is drawn dashed for comparison; ``label``
    names ``model`` in the title and legend (default ``model``). Returns
    ``(figure, None)`` or ``(None, reason)``.
    """
    import matplotlib.dates as mdates

    m = measurements[measurements["heliostat_id"] == heliostat][["measurement_id", "timestamp"]]
    p = predictions[predictions["heliostat_id"] == heliostat]
    d = p[p["model"] == model][["measurement_id", "split", "error_mrad"]].merge(
        m, on="measurement_id", how="inner")
    d["timestamp"] = pd.to_datetime(d["timestamp"], utc=True)
    n_missing = int(d["timestamp"].isna().sum())
    d = d.dropna(subset=["timestamp"]).sort_values("timestamp")
    if len(d) < 2:
        return None, f"{heliostat} has fewer than two timestamped predictions of {model}"
    fig, axes = new_figure(8.5, 3.8, margins_in=(0.65, 2.25, 0.55, 0.35))
    ax = axes[0, 0]
    for split in sorted(d["split"].unique(), key=split_sort_key):
        g = d[d["split"] == split]
        ax.scatter(g["timestamp"].dt.tz_localize(None), g["error_mrad"], s=12 if split != "train"
                   else 7, color=_SPLIT_COLORS.get(split, "0.5"), label=f"{split} ({len(g)})",
                   alpha=0.85, lw=0, zorder=3 if split != "train" else 2)

    def rolling(frame):
        s = frame.set_index(frame["timestamp"].dt.tz_localize(None))["error_mrad"]
        r = s.rolling(f"{window_days}D", center=True, min_periods=3).median()
        # break the line across gaps longer than the window instead of bridging them
        gap = s.index.to_series().diff() > pd.Timedelta(days=window_days)
        if gap.any():
            breaks = pd.Series(np.nan, index=s.index[gap.to_numpy()] - pd.Timedelta(seconds=1))
            r = pd.concat([r, breaks]).sort_index()
        return r

    r = rolling(d)
    ax.plot(r.index, r.to_numpy(), color="k", lw=1.4, label=f"{window_days}-day median")
    if coarse_model and coarse_model != model:
        c = p[p["model"] == coarse_model][["measurement_id", "error_mrad"]].merge(
            m, on="measurement_id")
        c["timestamp"] = pd.to_datetime(c["timestamp"], utc=True)
        c = c.dropna(subset=["timestamp"]).sort_values("timestamp")
        if len(c) >= 2:
            rc = rolling(c)
            ax.plot(rc.index, rc.to_numpy(), color="#6baed6", ls="--", lw=1.4,
                    label=f"{coarse_model}: {window_days}-day median")
    locator = mdates.AutoDateLocator()
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    ax.set_xlabel("measurement date (UTC)")
    ax.set_ylabel("error [mrad]")
    ax.set_ylim(bottom=0)
    top = float(np.nanpercentile(d["error_mrad"], 99)) if d["error_mrad"].notna().any() else 1.0
    if d["error_mrad"].max() > 1.5 * top:  # keep a few wild points from flattening the rest
        ax.set_ylim(0, 1.3 * top)
        n_above = int((d["error_mrad"] > 1.3 * top).sum())
        ax.text(0.99, 0.97, f"{n_above} point{'s' if n_above != 1 else ''} above the axis",
                transform=ax.transAxes, ha="right", va="top", fontsize="x-small")
    ax.grid(alpha=0.3)
    title = f"{heliostat}: error of {label or model} over time"
    if n_missing:
        title += f" ({n_missing} without timestamp not shown)"
    ax.set_title(title, fontsize="medium", y=TITLE_Y)
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None


def plot_gp_correction(grid: dict, heliostat: str):
    """The GP correction of one heliostat over the sky (issue 35): colour the size of the faded
    correction [mrad], arrows its direction (horizontal, vertical on the mirror), dots the
    training rows, the dashed line where the fade is 1/2. ``grid`` (computed where the model is,
    :func:`heliocal.pipeline.models.gp_heliostat.correction_grid`): ``azimuth_deg`` (A,),
    ``elevation_deg`` (E,), ``mean_h``, ``mean_v``, ``fade`` (E, A), ``train_sun_deg`` (M, 2),
    ``structure``, ``fade_length_deg``, ``when`` (the date it shows)."""
    az, el = np.asarray(grid["azimuth_deg"]), np.asarray(grid["elevation_deg"])
    h, v = np.asarray(grid["mean_h"]), np.asarray(grid["mean_v"])
    size = np.hypot(h, v)
    fig, axes = new_figure(8.5, 4.8, margins_in=(0.65, 0.2, 0.55, 0.35))
    ax = axes[0, 0]
    mesh = ax.pcolormesh(az, el, size, cmap="viridis", shading="auto",
                         vmin=0.0, vmax=max(float(np.nanmax(size)), 1e-3))
    fig.colorbar(mesh, ax=ax, label="correction [mrad]", pad=0.02)
    step = (slice(None, None, max(1, len(el) // 12)), slice(None, None, max(1, len(az) // 16)))
    aa, ee = np.meshgrid(az, el)
    ax.quiver(aa[step], ee[step], h[step], v[step], color="w", alpha=0.8, width=0.003)
    if np.nanmin(grid["fade"]) < 0.5:
        ax.contour(az, el, grid["fade"], levels=[0.5], colors="w", linestyles="--",
                   linewidths=1.0)
    train = np.asarray(grid["train_sun_deg"]).reshape(-1, 2)
    ax.scatter(train[:, 0], train[:, 1], s=6, c="k", lw=0, zorder=3)
    ax.set_xlabel("sun azimuth [deg] (0 = south, positive toward east)")
    ax.set_ylabel("sun elevation [deg]")
    length = grid.get("fade_length_deg")
    fade = ("no sun fade" if length is None or not math.isfinite(length)
            else f"fade length {length:g} deg")
    ax.set_title(f"{heliostat}: GP correction ({grid['structure']}; {fade}) at {grid['when']}",
                 fontsize="medium", y=TITLE_Y)
    return fig
