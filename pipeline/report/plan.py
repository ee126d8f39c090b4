"""The report's page of the measurement plan (``plan.html``, written when ``plan.parquet``
exists): what the plan buys per heliostat, where on the sky it measures, and the schedule by day.
Every text from the data is escaped; the sky plot is one inline SVG.
"""

from __future__ import annotations

import html

import numpy as np
import pandas as pd

from .pages import fmt, inline_html as inline, page_head

__all__ = ["plan_html", "plan_heliostats", "svg_sky", "MAX_SCHEDULE_ROWS"]

e = html.escape

#: Rows of the schedule shown on the page (plan.csv has all).
MAX_SCHEDULE_ROWS = 500


def plan_heliostats(plan: pd.DataFrame) -> pd.DataFrame:
    """Per planned heliostat: rows, expected year-round RMS aim error before its first planned
    row and after its last, the summed gain, the model and the first time."""
    g = plan.sort_values("rank").groupby("heliostat_id", sort=False)
    out = pd.DataFrame({
        "rows": g.size(),
        "before_mrad": g["expected_error_before_mrad"].first(),
        "after_mrad": g["expected_error_after_mrad"].last(),
        "gain_mrad2": g["expected_gain_mrad2"].sum(),
        "coarse_model": g["coarse_model"].first(),
        "first": g["time_utc"].min(),
    })
    return out.sort_values(["gain_mrad2"], ascending=False)


def svg_sky(plan: pd.DataFrame, width: int = 560, height: int = 260) -> str:
    """The planned rows on the sky: azimuth [deg] (east left, as seen facing south) against
    elevation [deg]; larger dots for larger gains."""
    pad = 36
    az = plan["sun_azimuth_deg"].to_numpy(float)
    el = plan["sun_elevation_deg"].to_numpy(float)
    gain = plan["expected_gain_mrad2"].to_numpy(float)
    x = lambda a: pad + (180.0 - a) / 360.0 * (width - 2 * pad)  # noqa: E731 (east on the left)
    y = lambda v: height - pad - v / 90.0 * (height - 2 * pad)  # noqa: E731
    top = max(float(np.nanmax(gain)) if len(gain) else 1.0, 1e-300)
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'role="img" aria-label="planned sun positions">',
           f'<rect x="{pad}" y="{pad}" width="{width - 2 * pad}" height="{height - 2 * pad}" '
           'fill="none" stroke="#999"/>']
    for a in (-120, -60, 0, 60, 120):
        out.append(f'<text x="{x(a):.1f}" y="{height - pad + 14}" font-size="10" '
                   f'text-anchor="middle">{a}</text>')
    for v in (0, 30, 60, 90):
        out.append(f'<text x="{pad - 4}" y="{y(v) + 3:.1f}" font-size="10" '
                   f'text-anchor="end">{v}</text>')
    out.append(f'<text x="{width / 2:.0f}" y="{height - 4}" font-size="11" text-anchor="middle">'
               'sun azimuth [deg] (0 south, + east)</text>')
    for a, v, g, hid in zip(az, el, gain, plan["heliostat_id"]):
        r = 2.0 + 4.0 * np.sqrt(max(g, 0.0) / top)
        out.append(f'<circle cx="{x(a):.1f}" cy="{y(v):.1f}" r="{r:.1f}" fill="#1f77b4" '
                   f'fill-opacity="0.5"><title>{e(str(hid))}: gain {g:.3g} mrad^2</title></circle>')
    out.append("</svg>")
    return "".join(out)


def _table(headers, rows) -> str:
    head = "".join(f"<th>{e(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="sortable"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def plan_html(title: str, plan: pd.DataFrame, options: dict, nav: str, sort_js: str) -> str:
    """``plan.html``: the plan's numbers, the sky plot, per heliostat what it buys, and the
    schedule by time (the first :data:`MAX_SCHEDULE_ROWS` rows; plan.csv beside plan.parquet
    in the work directory has them all)."""
    per = plan_heliostats(plan)
    mode = ("chosen among rows already measured (--from-existing)" if options.get("from_existing")
            else "in free slots of the coming days")
    out = page_head(f"Measurement plan: {title}")
    out.append(nav)
    out.append("<h1>Measurement plan</h1>")
    out.append(f"<p>{len(plan)} measurements of {len(per)} heliostats over "
               f"{e(str(options.get('days', '?')))} days from {e(str(options.get('start', '?')))}, "
               f"{e(mode)}, each chosen for the largest drop of its heliostat's expected "
               "year-round aim error (the coarse model's parameter uncertainty propagated to a "
               "year of aims at the site; docs/plan.md). "
               + inline("The schedule for a plant is `plan.csv` in the work directory.") + "</p>")
    if options.get("spacing_s"):
        out.append(f"<p>One heliostat on a target at a time: measurements on one target at "
                   f"least {int(options['spacing_s'])} s apart.</p>")
    out.append("<h2>Where on the sky</h2>")
    out.append('<div class="map">' + svg_sky(plan) + "</div>")
    out.append("<p>Each dot a planned measurement at its sun position, its area the expected "
               "gain. Rows at the edges of the year's sun positions (low sun in the morning "
               "and evening) teach a heliostat most where its rows so far leave it "
               "uncertain.</p>")
    out.append(f"<h2>Per heliostat ({len(per)})</h2>")
    out.append("<p>Expected year-round RMS aim error from the parameters' uncertainty before "
               "its first planned row and after its last [mrad]; the summed gain [mrad^2].</p>")
    out.append(_table(["heliostat", "rows", "before [mrad]", "after [mrad]", "gain [mrad^2]",
                       "coarse model", "first measurement (UTC)"],
                      [[hid, int(r["rows"]), fmt(r["before_mrad"]), fmt(r["after_mrad"]),
                        fmt(r["gain_mrad2"], 4), r["coarse_model"],
                        pd.Timestamp(r["first"]).strftime("%Y-%m-%d %H:%M")]
                       for hid, r in per.iterrows()]))
    shown = plan.sort_values(["time_utc", "rank"]).head(MAX_SCHEDULE_ROWS)
    out.append(f"<h2>Schedule ({len(shown)} of {len(plan)} rows, in time order)</h2>")
    out.append(_table(["time (UTC)", "day", "heliostat", "target", "sun azimuth [deg]",
                       "sun elevation [deg]", "gain [mrad^2]", "rank"],
                      [[pd.Timestamp(r["time_utc"]).strftime("%Y-%m-%d %H:%M:%S"), int(r["day"]),
                        r["heliostat_id"], r["target"], fmt(r["sun_azimuth_deg"], 1),
                        fmt(r["sun_elevation_deg"], 1), fmt(r["expected_gain_mrad2"], 4),
                        int(r["rank"])] for _, r in shown.iterrows()]))
    out.append(sort_js)
    out.append("</body></html>")
    return "\n".join(out) + "\n"
