"""The field at a glance: one row per heliostat (position, the model ``aim`` uses and its test
error, alerts), the field's summary numbers and the field map as inline SVG.

The error shown per heliostat is the one ``aim`` uses: the caller passes
``heliocal.pipeline.stages.aim.aim_models(workdir)``'s answer (the sweep's selection, else the
fit-hybrid hybrid, else fit-coarse's preset, with their mean validation and test error_mrad), so
the report never recomputes a different answer.
"""

from __future__ import annotations

import html
import math
import urllib.parse

import numpy as np
import pandas as pd

from .forward import next_day_mean
from ..vocabulary import DEFAULT_ALERT_MRAD
from .inputs import ReportInputs
from .site import model_label

__all__ = [
    "ALERT_MRAD",
    "ERROR_LINES_MRAD",
    "field_table",
    "field_summary",
    "heliostat_page_name",
    "tower_en_m",
    "svg_field_map",
    "worst",
]


#: Default alert threshold: a heliostat whose model (the one aim uses) has a mean test error
#: above it is on alert [mrad].
ALERT_MRAD = DEFAULT_ALERT_MRAD


#: Reference lines of the error distribution [mrad].
ERROR_LINES_MRAD = (0.5, 1.0, 2.0)


def heliostat_page_name(heliostat_id: str) -> str:
    """File name of a heliostat's page under ``report/heliostats/`` (checked by the stage with
    ``artifacts.paths.safe_child``)."""
    return f"{heliostat_id}.html"


def _first_per_heliostat(df: pd.DataFrame | None, column: str, selected: bool = True) -> dict:
    if df is None or column not in df.columns:
        return {}
    d = df[df["selected"].astype(bool)] if selected and "selected" in df.columns else df
    first = d.groupby(d["heliostat_id"].astype(str), sort=False)[column].first()
    return {h: v for h, v in first.items()}


def field_table(inp: ReportInputs, metrics: dict, choices: dict, *,
                alert_mrad: float = ALERT_MRAD,
                extra_alerts: dict[str, list[str]] | None = None) -> pd.DataFrame:
    """One row per heliostat of measurements.parquet.

    Columns: ``heliostat_id``, ``e_m``, ``n_m`` (position, ENU metres; heliostats.parquet, else
    the mean of the measurement rows; NaN if neither), ``model`` (``coarse`` / ``hybrid`` /
    None), ``variant``, ``preset``, ``source`` (the stage that chose the model), ``val_error_mrad``
    and ``test_error_mrad`` (mean, of the model aim uses, from ``choices``),
    ``time_test_error_mrad`` (forward in time: the final model trained on the time split's
    training rows, mean on its test rows; NaN: n/a), ``n_measurements``,
    ``n_test``, ``alerts`` (list of texts, empty when none), ``degenerate`` (its training data
    cannot determine its model: :func:`field_summary` leaves it out of the field's figures),
    ``page`` (file name of its page).

    Alerts: no model (fit-coarse has not run for it), no test rows, test error above
    ``alert_mrad``, degenerate training data, implausible corrections of the geometry, and
    ``extra_alerts`` (heliostat -> texts; e.g. a detector of regime changes).
    """
    helios = metrics["heliostats"]
    pos = pd.DataFrame(columns=["heliostat_e_m", "heliostat_n_m"], dtype=float)
    if inp.heliostats is not None and {"heliostat_e_m", "heliostat_n_m"} <= set(inp.heliostats):
        h = inp.heliostats.assign(heliostat_id=inp.heliostats["heliostat_id"].astype(str))
        pos = h.drop_duplicates("heliostat_id").set_index("heliostat_id")[
            ["heliostat_e_m", "heliostat_n_m"]]
    elif {"heliostat_e_m", "heliostat_n_m"} <= set(inp.measurements.columns):
        pos = inp.measurements.groupby("heliostat_id")[["heliostat_e_m", "heliostat_n_m"]].mean()
    degenerate = _first_per_heliostat(inp.coarse_params, "fit_degenerate")
    implausible = _first_per_heliostat(inp.coarse_params, "fit_implausible")
    rows = []
    for hid, h in helios.items():
        c = choices.get(hid)
        test = c["test_error_mrad"] if c else float("nan")
        val = c["val_error_mrad"] if c else float("nan")
        test = float(test) if test is not None else float("nan")
        val = float(val) if val is not None else float("nan")
        alerts = []
        if c is None:
            alerts.append("no model: fit-coarse has not fitted it")
        elif not math.isfinite(test):
            alerts.append("no test measurements: its accuracy is unknown")
        elif test > alert_mrad:
            alerts.append(f"test error {test:.2f} mrad above {alert_mrad:g} mrad")
        why = degenerate.get(hid)
        if isinstance(why, str) and why:
            alerts.append(f"degenerate training data ({why})")
        big = implausible.get(hid)
        if isinstance(big, str) and big:
            alerts.append(f"large corrections of the nominal geometry ({big})")
        alerts += list((extra_alerts or {}).get(hid, []))
        e, n = (float(pos.loc[hid, "heliostat_e_m"]), float(pos.loc[hid, "heliostat_n_m"])) \
            if hid in pos.index else (float("nan"), float("nan"))
        rows.append({"heliostat_id": hid, "e_m": e, "n_m": n,
                     "model": c["model"] if c else None, "variant": c["variant"] if c else None,
                     "preset": c["preset"] if c else None, "source": c["source"] if c else None,
                     "weight_decay": c["weight_decay"] if c else None,
                     "val_error_mrad": val, "test_error_mrad": test,
                     "time_test_error_mrad": _forward_test(h),
                     "next_day_error_mrad": next_day_mean(h),
                     "n_measurements": int(h["n_measurements"]),
                     "n_test": int(h["split_counts"].get("test", 0)), "alerts": alerts,
                     "degenerate": isinstance(why, str) and bool(why),
                     "page": heliostat_page_name(hid)})
    return pd.DataFrame(rows, columns=["heliostat_id", "e_m", "n_m", "model", "variant", "preset",
                                       "source", "weight_decay", "val_error_mrad",
                                       "test_error_mrad", "time_test_error_mrad",
                                       "next_day_error_mrad",
                                       "n_measurements", "n_test", "alerts", "degenerate", "page"])


def _forward_test(h: dict) -> float:
    """The final model's forward-in-time test error (metrics.json's ``forward_in_time``; NaN:
    n/a, the heliostat has no time split)."""
    v = (((h.get("forward_in_time") or {}).get("final") or {}).get("time_test") or {}).get(
        "mean_error_mrad")
    return float("nan") if v is None else float(v)


def _median_or_none(values: np.ndarray) -> float | None:
    v = values[np.isfinite(values)]
    return float(np.median(v)) if len(v) else None


def field_summary(table: pd.DataFrame, *, alert_mrad: float = ALERT_MRAD) -> dict:
    """The field's numbers: heliostats, calibrated (with a model), coarse and hybrid counts,
    presets chosen, median and 95th percentile (numpy's linear) of the per-heliostat test error,
    heliostats above ``alert_mrad`` and on alert.

    A heliostat flagged degenerate (``degenerate``: its training rows cannot determine its model,
    e.g. one measurement repeated, so its test error of ~0 says nothing) is counted in
    ``n_degenerate`` and left out of the error figures (``n_with_test_error``, the median, the
    95th percentile and ``n_above_alert``); it stays on alert."""
    err = table["test_error_mrad"].to_numpy(float)
    degenerate = (table["degenerate"].to_numpy(bool) if "degenerate" in table.columns
                  else np.zeros(len(table), bool))
    ok = np.isfinite(err) & ~degenerate
    return {
        "n_heliostats": int(len(table)),
        "n_calibrated": int(table["model"].notna().sum()),
        "n_coarse": int((table["model"] == "coarse").sum()),
        "n_hybrid": int((table["model"] == "hybrid").sum()),
        "n_pretrained": int((table["model"] == "pretrained-nn").sum()),
        "presets": {str(k): int(v) for k, v in table["preset"].dropna().value_counts()
                    .sort_index().items()},
        "n_with_test_error": int(ok.sum()),
        "n_degenerate": int(degenerate.sum()),
        "median_test_error_mrad": float(np.median(err[ok])) if ok.any() else None,
        "p95_test_error_mrad": float(np.percentile(err[ok], 95)) if ok.any() else None,
        "median_next_day_error_mrad": _median_or_none(
            table["next_day_error_mrad"].to_numpy(float)[~degenerate]
            if "next_day_error_mrad" in table.columns else np.array([])),
        "alert_mrad": float(alert_mrad),
        "n_above_alert": int((err[ok] > alert_mrad).sum()),
        "n_on_alert": int(table["alerts"].map(bool).sum()),
    }


def worst(table: pd.DataFrame, n: int = 20) -> pd.DataFrame:
    """The ``n`` heliostats that need attention first: largest test error first; heliostats
    without a test error (no model, no test rows) come before all of them."""
    key = table["test_error_mrad"].fillna(np.inf)
    return table.assign(_key=key).sort_values(["_key", "heliostat_id"],
                                              ascending=[False, True]).head(n).drop(columns="_key")


def tower_en_m(inp: ReportInputs) -> tuple[float, float] | None:
    """East and north [m] of the tower: the mean of the targets' centres the measurements aimed
    at (``target_e_m``, ``target_n_m``); None without them."""
    m = inp.measurements
    if not {"target_e_m", "target_n_m"} <= set(m.columns):
        return None
    e, n = m["target_e_m"].to_numpy(float), m["target_n_m"].to_numpy(float)
    ok = np.isfinite(e) & np.isfinite(n)
    if not ok.any():
        return None
    return float(e[ok].mean()), float(n[ok].mean())


# ------------------------------------------------------------------------------------------------
# the field map (inline SVG: every heliostat a link to its page, its numbers on hover)
# ------------------------------------------------------------------------------------------------
def _nice_step(span: float) -> float:
    raw = span / 6 if span > 0 else 1.0
    mag = 10 ** math.floor(math.log10(raw))
    return next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)


def _hex(rgba) -> str:
    return "#" + "".join(f"{int(round(255 * c)):02x}" for c in rgba[:3])


def svg_field_map(table: pd.DataFrame, tower: tuple[float, float] | None, *,
                  alert_mrad: float = ALERT_MRAD, link_prefix: str = "heliostats/",
                  width: int = 760, height: int = 600) -> str:
    """The field as an SVG: heliostats at their east/north position [m], coloured by the test
    error of the model aim uses (colour scale 0 .. the field's 95th percentile),
    heliostats on alert ringed in red, the tower a black triangle; each heliostat links to its
    page and shows its id, model and errors on hover (``<title>``). Every text is escaped."""
    import matplotlib

    e = html.escape
    cmap = matplotlib.colormaps["viridis"]
    t = table[np.isfinite(table["e_m"].to_numpy(float)) & np.isfinite(table["n_m"].to_numpy(float))]
    if not len(t):
        return ('<p class="note"><b>Note:</b> no heliostat positions (heliostats.parquet has no '
                "heliostat_e_m / heliostat_n_m): no field map.</p>")
    xs, ys = list(t["e_m"].astype(float)), list(t["n_m"].astype(float))
    if tower is not None:
        xs.append(tower[0])
        ys.append(tower[1])
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    span = max(x1 - x0, y1 - y0, 10.0)
    pad = 0.06 * span
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    half = span / 2 + pad
    left, top, plot = 62, 28, min(width - 62 - 110, height - 28 - 50)
    scale = plot / (2 * half)

    def px(x):  # east -> right
        return left + (x - (cx - half)) * scale

    def py(y):  # north -> up
        return top + ((cy + half) - y) * scale

    err = t["test_error_mrad"].to_numpy(float)
    finite = err[np.isfinite(err)]
    # the colours spread over the field's own range (a well calibrated field is not one colour);
    # the alert threshold, absolute, is the red ring
    vmax = max(float(np.percentile(finite, 95)), 1e-3) if len(finite) else alert_mrad
    r = max(2.0, min(7.0, 0.45 * plot / math.sqrt(max(len(t), 1))))
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'viewBox="0 0 {width} {height}" role="img" aria-label="field map">',
           f'<rect x="{left}" y="{top}" width="{plot:.1f}" height="{plot:.1f}" fill="#fcfcfc" '
           'stroke="#999"/>']
    step = _nice_step(2 * half)
    for k in range(math.ceil((cx - half) / step), math.floor((cx + half) / step) + 1):
        v = k * step
        out.append(f'<line x1="{px(v):.1f}" y1="{top}" x2="{px(v):.1f}" y2="{top + plot:.1f}" '
                   f'stroke="#eee"/><text x="{px(v):.1f}" y="{top + plot + 15:.1f}" '
                   f'font-size="11" text-anchor="middle">{v:g}</text>')
    for k in range(math.ceil((cy - half) / step), math.floor((cy + half) / step) + 1):
        v = k * step
        out.append(f'<line x1="{left}" y1="{py(v):.1f}" x2="{left + plot:.1f}" y2="{py(v):.1f}" '
                   f'stroke="#eee"/><text x="{left - 5}" y="{py(v) + 4:.1f}" font-size="11" '
                   f'text-anchor="end">{v:g}</text>')
    out.append(f'<text x="{left + plot / 2:.1f}" y="{top + plot + 34:.1f}" font-size="12" '
               'text-anchor="middle">east [m]</text>')
    out.append(f'<text x="16" y="{top + plot / 2:.1f}" font-size="12" text-anchor="middle" '
               f'transform="rotate(-90 16 {top + plot / 2:.1f})">north [m]</text>')
    # worst last, so they are drawn on top
    order = np.argsort(np.where(np.isfinite(err), err, np.inf), kind="stable")
    for i in order:
        row = t.iloc[i]
        v = err[i]
        fill = _hex(cmap(min(v / vmax, 1.0))) if math.isfinite(v) else "#bbbbbb"
        alert = bool(row["alerts"])
        stroke = ('stroke="#d00000" stroke-width="2.2"' if alert else
                  'stroke="#333" stroke-width="0.4"')
        model = model_label(row)
        tip = (f"{row['heliostat_id']}: test {v:.3f} mrad, validation "
               f"{row['val_error_mrad']:.3f} mrad ({model})" if math.isfinite(v) else
               f"{row['heliostat_id']}: no test error ({model})")
        if alert:
            tip += "; ALERT: " + "; ".join(row["alerts"])
        href = link_prefix + urllib.parse.quote(row["page"])
        out.append(f'<a href="{e(href)}"><circle cx="{px(row["e_m"]):.1f}" '
                   f'cy="{py(row["n_m"]):.1f}" r="{r:.1f}" fill="{fill}" {stroke}>'
                   f"<title>{e(tip)}</title></circle></a>")
    if tower is not None:
        tx, ty = px(tower[0]), py(tower[1])
        out.append(f'<polygon points="{tx:.1f},{ty - 9:.1f} {tx - 7:.1f},{ty + 5:.1f} '
                   f'{tx + 7:.1f},{ty + 5:.1f}" fill="#000"><title>tower (mean of the target '
                   f'centres: E {tower[0]:.1f} m, N {tower[1]:.1f} m)</title></polygon>')
    # colour bar and legend
    bx, by, bh = left + plot + 26, top + 40, plot * 0.5
    out.append('<defs><linearGradient id="errscale" x1="0" y1="1" x2="0" y2="0">'
               + "".join(f'<stop offset="{k / 10:.1f}" stop-color="{_hex(cmap(k / 10))}"/>'
                         for k in range(11)) + "</linearGradient></defs>")
    out.append(f'<rect x="{bx}" y="{by}" width="14" height="{bh:.1f}" fill="url(#errscale)" '
               'stroke="#999"/>')
    tick = _nice_step(vmax * 6 / 5)  # about five ticks
    for k in range(int(vmax / tick + 1e-9) + 1):
        yy = by + bh * (1 - k * tick / vmax)
        out.append(f'<line x1="{bx + 14}" y1="{yy:.1f}" x2="{bx + 18}" y2="{yy:.1f}" '
                   f'stroke="#333"/><text x="{bx + 21}" y="{yy + 4:.1f}" font-size="11">'
                   f"{k * tick:g}</text>")
    out.append(f'<text x="{bx + 21}" y="{by - 12}" font-size="11">≥ {vmax:.3g}</text>')
    if alert_mrad < vmax:
        ya = by + bh * (1 - alert_mrad / vmax)
        out.append(f'<line x1="{bx - 4}" y1="{ya:.1f}" x2="{bx + 18}" y2="{ya:.1f}" '
                   f'stroke="#d00000" stroke-width="2"><title>alert threshold {alert_mrad:g} '
                   "mrad</title></line>")
    out.append(f'<text x="{bx - 4}" y="{by - 28}" font-size="11">test error [mrad]</text>')
    ly = by + bh + 26
    out.append(f'<circle cx="{bx + 6}" cy="{ly}" r="5" fill="#fff" stroke="#d00000" '
               f'stroke-width="2.2"/><text x="{bx + 16}" y="{ly + 4}" font-size="11">on alert'
               "</text>")
    out.append(f'<circle cx="{bx + 6}" cy="{ly + 18}" r="5" fill="#bbbbbb" stroke="#333" '
               f'stroke-width="0.4"/><text x="{bx + 16}" y="{ly + 22}" font-size="11">no test '
               "error</text>")
    if tower is not None:
        out.append(f'<polygon points="{bx + 6},{ly + 30} {bx},{ly + 42} {bx + 12},{ly + 42}" '
                   f'fill="#000"/><text x="{bx + 16}" y="{ly + 41}" font-size="11">tower</text>')
    out.append("</svg>")
    return "\n".join(out)
