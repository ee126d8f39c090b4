"""The report's view of regimes.parquet: per heliostat the coarse residual against time with its
regimes shaded, episodes and outliers marked; for the field an alert list of the detected
changes, and the regime alerts of the field overview. Kept apart from the page layout:
``report.render`` places the figure and the list on the pages.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .figures import TITLE_Y, new_figure


__all__ = [
    "alert_table",
    "regime_alerts",
    "plot_regimes",
]

_REGIME_SHADES = ("#deebf7", "#fee6ce")  # alternate regimes
_EPISODE_SHADE = "#de2d26"  # drawn at least two days wide


def alert_table(regimes: pd.DataFrame) -> tuple[list[str], list[list]]:
    """The field's alert list: every detected change (break, episode) and renovation, newest
    first: (headers, rows) of a report table."""
    r = regimes[regimes["cause"].isin(["detected", "renovation"])].copy()
    r = r.sort_values(["start", "heliostat_id"], ascending=[False, True], kind="mergesort")
    headers = ["date (UTC)", "heliostat", "what", "cause", "rows", "step [mrad]", "evidence",
               "error [mrad]"]
    rows = []
    for x in r.itertuples(index=False):
        what = (f"episode until {pd.Timestamp(x.end):%Y-%m-%d}" if x.kind == "episode"
                else f"regime {x.regime} starts")
        err = getattr(x, "error_mrad", np.nan)
        rows.append([f"{pd.Timestamp(x.start):%Y-%m-%d %H:%M}", x.heliostat_id, what, x.cause,
                     int(x.n_rows), f"{x.step_mrad:.2f}", f"{x.evidence:.1f}",
                     "–" if pd.isna(err) else f"{err:.2f}"])
    return headers, rows


#: A break into the latest regime at least this large [mrad] puts the heliostat on alert.
REGIME_ALERT_MRAD = 1.0


def regime_alerts(regimes: pd.DataFrame | None) -> dict[str, list[str]]:
    """Heliostat -> alert texts for the field report: the heliostat's latest regime began with a
    detected change of at least :data:`REGIME_ALERT_MRAD` (its geometry may have moved: the
    fit averages over the change; docs/regimes.md)."""
    if regimes is None or regimes.empty:
        return {}
    out: dict[str, list[str]] = {}
    seg = regimes[regimes["kind"] == "regime"]
    for hid, g in seg.groupby(seg["heliostat_id"].astype(str), sort=True):
        last = g.sort_values("start", kind="mergesort").iloc[-1]
        if (int(last["regime"]) > 0 and last["cause"] == "detected"
                and abs(float(last["step_mrad"])) >= REGIME_ALERT_MRAD):
            out[hid] = [f"regime change detected on {pd.Timestamp(last['start']):%Y-%m-%d} "
                        f"({float(last['step_mrad']):.1f} mrad); the latest regime has "
                        f"{int(last['n_rows'])} rows"]
    return out


def plot_regimes(measurements: pd.DataFrame, predictions: pd.DataFrame, regimes: pd.DataFrame,
                 heliostat: str):
    """The selected coarse model's error of ``heliostat`` against time, its regimes shaded
    (alternating colours; episodes red), breaks as vertical lines (dashed: renovation) and
    outliers circled. Returns ``(figure, None)`` or ``(None, reason)``."""
    import matplotlib.dates as mdates

    p = predictions[(predictions["heliostat_id"] == heliostat) & predictions["selected"]]
    if "source" in p.columns:
        p = p[p["source"] == "coarse_predictions"]
    m = measurements[measurements["heliostat_id"] == heliostat][["measurement_id", "timestamp"]]
    d = p[["measurement_id", "split", "error_mrad"]].merge(m, on="measurement_id")
    d["timestamp"] = pd.to_datetime(d["timestamp"], utc=True).dt.tz_localize(None)
    d = d.dropna(subset=["timestamp"]).sort_values("timestamp")
    r = regimes[regimes["heliostat_id"] == heliostat]
    if len(d) < 2 or r.empty:
        return None, f"{heliostat} has no regimes (fewer than three timestamped rows)"
    # fixed margins (room for the legend on the right): constrained layout would cost about as
    # much again as drawing the figure, which the report draws for many heliostats
    fig, axes = new_figure(8.0, 3.4, margins_in=(0.65, 1.55, 0.55, 0.35))
    ax = axes[0, 0]
    naive = lambda t: pd.Timestamp(t).tz_convert("UTC").tz_localize(None)  # noqa: E731
    seg = r[r["kind"] != "outlier"].sort_values("start", kind="mergesort")
    starts = [naive(t) for t in seg["start"]]
    bounds = starts[1:] + [max(naive(seg["end"].iloc[-1]), d["timestamp"].iloc[-1])]
    for x, a, b in zip(seg.itertuples(index=False), starts, bounds):
        if x.kind == "episode":  # at least two days wide, so that it shows
            b = max(naive(x.end), a + pd.Timedelta(days=2))
            ax.axvspan(a, b, color=_EPISODE_SHADE, alpha=0.35, lw=0, zorder=0.5)
        else:  # a regime lasts until the next segment starts
            ax.axvspan(a, b, color=_REGIME_SHADES[x.regime % 2], lw=0, zorder=0)
        if x.cause in ("detected", "renovation"):
            ax.axvline(a, color="0.3", lw=0.8, ls="--" if x.cause == "renovation" else "-",
                       zorder=1)
    for split, marker in (("train", "."), ("validation", "^"), ("test", "s")):
        g = d[d["split"] == split]
        if len(g):
            ax.scatter(g["timestamp"], g["error_mrad"], s=10, marker=marker, color="0.2",
                       lw=0, label=f"{split} ({len(g)})", zorder=3)
    out = d[d["measurement_id"].isin(set(r.loc[r["kind"] == "outlier", "measurement_id"]))]
    if len(out):
        ax.scatter(out["timestamp"], out["error_mrad"], s=60, facecolors="none",
                   edgecolors="tab:red", label=f"outlier ({len(out)})", zorder=4)
    n_ep = int((seg["kind"] == "episode").sum())
    n_reg = int(seg.loc[seg["kind"] == "regime", "regime"].nunique())
    locator = mdates.AutoDateLocator()
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    ax.set_xlabel("measurement date (UTC)")
    ax.set_ylabel("error [mrad]")
    ax.set_ylim(0, max(1.05 * float(d["error_mrad"].max()), 1e-3))
    ax.grid(alpha=0.3)
    ax.set_title(f"{heliostat}: {n_reg} regime{'s' if n_reg != 1 else ''}, {n_ep} "
                 f"episode{'s' if n_ep != 1 else ''}", fontsize="medium", y=TITLE_Y)
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None
