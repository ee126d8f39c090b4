"""The field-prior page's figures (matplotlib, Agg; :mod:`.prior_page` plans them): each
parameter's prior against the group's fitted values, the heatmap of how much each
heliostat's fit leans on the prior, and the training-size study's error of the shown preset
with and without the prior. Drawn by :func:`draw_prior_figure` in a worker
(``render.render_task``) from the small frames of the task."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .figures import new_figure

__all__ = ["DISPLAY_UNITS", "MAX_HEATMAP_ROWS", "MAX_DRAWN_HELIOSTATS", "draw_prior_figure",
           "shrinkage_rows", "size_medians"]

#: field_prior.parquet's unit -> (factor, display unit): the page and its figures show mean,
#: scale and deviations times factor.
DISPLAY_UNITS = {"rad": (1e3, "mrad"), "m": (1e3, "mm"), "1": (1e3, "‰ of nominal")}

#: Heliostats drawn one row each in the heatmap; a larger group is drawn in this many bins of
#: training rows (median shrinkage per bin).
MAX_HEATMAP_ROWS = 60

#: Study heliostats drawn one line each in the training-size figure (besides the median).
MAX_DRAWN_HELIOSTATS = 8

#: Panels per row of the prior-against-fit figure.
_COLUMNS = 4


def _display(unit: str) -> tuple[float, str]:
    return DISPLAY_UNITS.get(str(unit), (1.0, str(unit)))


def _short(name: str) -> str:
    """A parameter name without its unit suffix (the axis label carries the unit)."""
    for suffix in ("_rad", "_m"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def _rows_axis(ax, rows: np.ndarray) -> None:
    """A log axis of training rows labelled with plain numbers (1, 2, 5 per decade)."""
    from matplotlib.ticker import NullFormatter

    ax.set_yscale("log")
    finite = rows[np.isfinite(rows) & (rows > 0)]
    low, high = (finite.min(), finite.max()) if len(finite) else (1.0, 10.0)
    ticks = [m * 10 ** k for k in range(0, 7) for m in (1, 2, 5)
             if low / 1.5 <= m * 10 ** k <= high * 1.5]
    ax.set_ylim(low / 1.3, high * 1.3)
    ax.set_yticks(ticks or [low], [f"{t:g}" for t in ticks] or [f"{low:g}"])
    ax.yaxis.set_minor_formatter(NullFormatter())


def _prior_vs_fitted(args: dict):
    params: pd.DataFrame = args["params"]
    points: pd.DataFrame = args["points"]
    if params.empty or points.empty:
        return None, "no parameter with a field prior, or no heliostat fitted under it"
    from matplotlib import cm, colormaps
    from matplotlib.colors import Normalize

    n = len(params)
    ncols = min(n, _COLUMNS)
    nrows = math.ceil(n / ncols)
    fig, axes = new_figure(1.2 + 2.7 * ncols, 2.35 * nrows + 0.9, nrows, ncols)
    norm, cmap = Normalize(0.0, 1.0), colormaps["viridis"]
    for k, ax in enumerate(axes.flat):
        if k >= n:
            ax.set_visible(False)
            continue
        p = params.iloc[k]
        factor, unit = _display(p["unit"])
        mine = points[points["parameter_index"] == p["parameter_index"]]
        mean, scale = float(p["mean"]) * factor, float(p["scale"]) * factor
        ax.axvspan(mean - 2 * scale, mean + 2 * scale, color="#dde6f3", lw=0)
        ax.axvspan(mean - scale, mean + scale, color="#b3c7e6", lw=0)
        ax.axvline(mean, color="#1f4e9c", lw=1.2)
        share = mine["prior_shrinkage"].to_numpy(float)
        ax.scatter(mine["deviation"].to_numpy(float) * factor,
                   mine["n_train"].to_numpy(float), s=16,
                   c=cmap(norm(np.nan_to_num(share, nan=0.0))), edgecolors="#333",
                   linewidths=0.3, zorder=3)
        _rows_axis(ax, mine["n_train"].to_numpy(float))
        ax.set_title(f"{_short(str(p['parameter']))} (n={int(p['n_heliostats'])})",
                     fontsize="small")
        ax.set_xlabel(f"fitted − nominal [{unit}]", fontsize="x-small")
        ax.tick_params(labelsize="x-small")
        if k % ncols == 0:
            ax.set_ylabel("training rows", fontsize="x-small")
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, shrink=0.6,
                       pad=0.01)
    bar.set_label("shrinkage (0 data, 1 prior)", fontsize="small")
    return fig, None


def shrinkage_rows(points: pd.DataFrame, max_rows: int = MAX_HEATMAP_ROWS):
    """The heatmap's rows: (labels, matrix (rows, parameters), parameter indexes), heliostats
    by training rows, fewest first; with more than ``max_rows`` heliostats, that many bins of
    consecutive heliostats, each the median per parameter."""
    wide = points.pivot_table(index="heliostat_id", columns="parameter_index",
                              values="prior_shrinkage", aggfunc="first", dropna=False)
    n_train = points.groupby("heliostat_id")["n_train"].first()
    order = n_train.loc[wide.index].sort_values(kind="stable").index
    wide = wide.loc[order]
    if len(wide) <= max_rows:
        labels = [f"{h} ({int(n_train[h])})" for h in wide.index]
        return labels, wide.to_numpy(float), list(wide.columns)
    bins = np.array_split(np.arange(len(wide)), max_rows)
    labels, rows = [], []
    for b in bins:
        ids = wide.index[b]
        labels.append(f"{int(n_train[ids[0]])}-{int(n_train[ids[-1]])} rows ({len(ids)})")
        with np.errstate(all="ignore"):
            rows.append(np.nanmedian(wide.to_numpy(float)[b], axis=0))
    return labels, np.vstack(rows), list(wide.columns)


def _heatmap(args: dict):
    points: pd.DataFrame = args["points"]
    names = dict(zip(args["params"]["parameter_index"], args["params"]["parameter"]))
    if points.empty or points["prior_shrinkage"].notna().sum() == 0:
        return None, "no heliostat fitted under the field prior"
    labels, matrix, cols = shrinkage_rows(points)
    height = max(2.8, 1.6 + 0.22 * len(labels))
    fig, axes = new_figure(max(6.5, 3.0 + 0.55 * len(cols)), height)
    ax = axes[0, 0]
    image = ax.imshow(np.ma.masked_invalid(matrix), cmap="viridis", vmin=0.0, vmax=1.0,
                      aspect="auto", interpolation="nearest")
    ax.set_xticks(range(len(cols)))
    ax.set_xticklabels([_short(str(names.get(c, c))) for c in cols], rotation=45, ha="right",
                       fontsize="x-small")
    ax.set_yticks(range(len(labels)))
    ax.set_yticklabels(labels, fontsize="x-small")
    ax.set_ylabel("heliostat (training rows)", fontsize="x-small")
    if matrix.size <= 400:
        for (i, j), v in np.ndenumerate(matrix):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=6,
                        color="white" if v < 0.6 else "black")
    bar = fig.colorbar(image, ax=ax, shrink=0.8, pad=0.01)
    bar.set_label("shrinkage", fontsize="small")
    return fig, None


def size_medians(frame: pd.DataFrame) -> pd.DataFrame:
    """Per curve (``prior``) and training size below each heliostat's full one: the median
    test error over the study heliostats with that size and their number (columns ``prior``,
    ``n_train``, ``median``, ``n``). ``frame``: the study rows (``heliostat_id``, ``prior``,
    ``n_train``, ``test_error_mrad``, ``full``: the heliostat's full training size)."""
    below = frame[frame["n_train"] < frame["full"]]
    g = below.groupby(["prior", "n_train"], sort=True)["test_error_mrad"]
    return pd.DataFrame({"median": g.median(), "n": g.size()}).reset_index()


#: The two curves: (``prior`` value, label, colour, marker face).
_CURVES = (("field", "with the field prior", "#1f4e9c", "#1f4e9c"),
           ("none", "without (default prior)", "#c0392b", "white"))


def _training_size(args: dict):
    frame: pd.DataFrame = args["frame"]
    if frame.empty:
        return None, "no study heliostat of the group was fitted with and without the prior"
    fig, axes = new_figure(7.5, 4.6)
    ax = axes[0, 0]
    ids = sorted(frame["heliostat_id"].unique())
    medians = size_medians(frame)
    for prior, label, color, face in _CURVES:
        mine = frame[frame["prior"] == prior]
        if len(ids) <= MAX_DRAWN_HELIOSTATS:
            for hid in ids:
                h = mine[mine["heliostat_id"] == hid].sort_values("n_train")
                ax.plot(h["n_train"], h["test_error_mrad"], color=color, lw=0.7, alpha=0.35)
        m = medians[medians["prior"] == prior]
        ax.plot(m["n_train"], m["median"], color=color, lw=2.0, marker="o", ms=5,
                markerfacecolor=face, label=f"{label}: median")
        full = mine[mine["n_train"] == mine["full"]]
        ax.scatter(full["n_train"], full["test_error_mrad"], s=36, marker="D",
                   edgecolors=color, facecolors=face, zorder=3,
                   label=f"{label}: all training rows (each heliostat)")
    ax.set_xscale("log")
    # each size's tick says over how many heliostats its median is (those with more rows)
    counts = medians.groupby("n_train")["n"].max()
    ax.set_xticks(counts.index.to_numpy(int), [f"{n}\n({k})" for n, k in counts.items()])
    ax.minorticks_off()
    ax.set_xlabel(f"training rows (heliostats with that many, of {len(ids)})")
    ax.set_ylabel("mean test error [mrad]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title(f"{args['preset']}: test error against training rows", fontsize="medium")
    return fig, None


def draw_prior_figure(kind: str, args: dict):
    """(figure, None) or (None, why) of a field-prior figure ``kind`` (``prior_vs_fitted``,
    ``prior_shrinkage``, ``prior_training_size``)."""
    return {"prior_vs_fitted": _prior_vs_fitted, "prior_shrinkage": _heatmap,
            "prior_training_size": _training_size}[kind](args)
