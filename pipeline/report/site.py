"""The report's HTML pages for a plant: the field overview (``index.html``), one page per
heliostat (``heliostats/<id>.html``), the list of all heliostats (``heliostats.html``) and the
paper's figures as field aggregates (``field.html``).

Static HTML with relative links (works from ``file://``, nothing loaded from the network); the
only script is :data:`SORT_JS`, a few lines that sort a table by a clicked column. Every text that
came from the input (heliostat ids, presets, notes) is escaped with :func:`html.escape`, and every
link to a file named after a heliostat is percent-encoded.
"""

from __future__ import annotations

import html
import math
import urllib.parse
from typing import Sequence

import pandas as pd

from .pages import fmt, fmt_g, inline_html as inline, page_head
from .render import ReportFigure

__all__ = [
    "SORT_JS",
    "field_page_blocks",
    "heliostat_html",
    "heliostats_list_html",
    "index_html",
    "model_label",
    "nav_html",
    "why_text",
]

e = html.escape


#: Sorts a ``table.sortable`` by the clicked header (numbers as numbers; "–" last).
SORT_JS = """<script>
document.querySelectorAll("table.sortable th").forEach(function (th, col) {
  th.setAttribute("data-sort", "");
  th.addEventListener("click", function () {
    var body = th.closest("table").tBodies[0], rows = Array.from(body.rows);
    var asc = th.getAttribute("data-dir") !== "asc";
    th.setAttribute("data-dir", asc ? "asc" : "desc");
    function key(r) { var t = r.cells[col].getAttribute("data-v") || r.cells[col].textContent;
      var x = parseFloat(t); return isNaN(x) ? t : x; }
    rows.sort(function (a, b) { var x = key(a), y = key(b);
      if (typeof x !== typeof y) { return typeof x === "number" ? -1 : 1; }
      return (x < y ? -1 : x > y ? 1 : 0) * (asc ? 1 : -1); });
    rows.forEach(function (r) { body.appendChild(r); });
  });
});
</script>"""


def nav_html(prefix: str = "", pages: Sequence[tuple[str, str]] = ()) -> str:
    """Links to the report's pages (``prefix``: ``../`` from ``heliostats/``); ``pages``: (file,
    title) of the pages only some reports have (the field prior's), after the field figures."""
    links = (("index.html", "Field overview"), ("heliostats.html", "All heliostats"),
             ("field.html", "Field figures (paper)"), *pages, ("details.html", "All tables"),
             ("report.md", "report.md"), ("metrics.json", "metrics.json"))
    return "<nav>" + "".join(f'<a href="{prefix}{h}">{e(t)}</a>' for h, t in links) + "</nav>"


def model_label(row) -> str:
    """``hybrid-octaves on static-20``, ``pretrained-nn on static-20``, ``coarse static-6``,
    ``nominal geometry (...)`` (the fallback) or ``no model``."""
    if row["model"] in ("hybrid", "pretrained-nn"):
        return f"{row['variant'] or row['model']} on {row['preset']}"
    if row["model"] == "coarse":
        return f"coarse {row['preset']}"
    if row["model"] == "nominal":
        return f"nominal geometry (the fitted {row['preset']} is worse)"
    return "no model"


def _num(x, digits: int = 3) -> str:
    return fmt(None if x is None or (isinstance(x, float) and not math.isfinite(x)) else x, digits)


def _time_num(row) -> str:
    """The forward-in-time test error of a field-table row, "n/a" without a time split."""
    v = row.get("time_test_error_mrad") if hasattr(row, "get") else None
    return "n/a" if v is None or not math.isfinite(float(v)) else _num(float(v))


def _link(row, prefix: str = "heliostats/") -> str:
    return (f'<a href="{e(prefix + urllib.parse.quote(row["page"]))}">'
            f'{e(str(row["heliostat_id"]))}</a>')


def _alerts_cell(alerts: Sequence[str]) -> str:
    """Each alert's headline (the text before its details in parentheses); the whole text on
    hover and on the heliostat's page."""
    return "; ".join(f'<span class="alert" title="{e(a)}">{e(a.split(" (", 1)[0])}</span>'
                     for a in alerts)


def _heliostat_table(rows: pd.DataFrame, prefix: str, rank: bool = False) -> str:
    head = (["#"] if rank else []) + ["heliostat", "test [mrad]", "forward in time [mrad]",
                                      "validation [mrad]", "model",
                                      "measurements", "test rows", "east [m]", "north [m]",
                                      "alerts"]
    out = ['<table class="sortable"><thead><tr>' + "".join(f"<th>{e(h)}</th>" for h in head)
           + "</tr></thead><tbody>"]
    for k, (_, r) in enumerate(rows.iterrows(), 1):
        cells = ([f"<td>{k}</td>"] if rank else []) + [
            f'<td class="t">{_link(r, prefix)}</td>', f"<td>{_num(r['test_error_mrad'])}</td>",
            f"<td>{_time_num(r)}</td>",
            f"<td>{_num(r['val_error_mrad'])}</td>", f'<td class="t">{e(model_label(r))}</td>',
            f"<td>{int(r['n_measurements'])}</td>", f"<td>{int(r['n_test'])}</td>",
            f"<td>{_num(r['e_m'], 1)}</td>", f"<td>{_num(r['n_m'], 1)}</td>",
            f'<td class="t">{_alerts_cell(r["alerts"])}</td>']
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return "\n".join(out)


def index_html(title: str, subtitle: str, summary: dict, table: pd.DataFrame, worst: pd.DataFrame,
               svg_map: str, cdf: ReportFigure | None, cdf_note: str | None, floor_text: str,
               notes: Sequence[str], nav_pages: Sequence[tuple[str, str]] = ()) -> str:
    """``index.html``: summary numbers, the field map, the error distribution, the worst
    heliostats (each a link to its page) and the notes of the run. Small at any field size: the
    map is one SVG circle per heliostat, the distribution one PNG file, the table 20 rows.
    ``nav_pages``: :func:`nav_html`'s ``pages``."""
    s = summary
    presets = ", ".join(f"{k} {v}" for k, v in s["presets"].items()) or "–"
    kpis = [("heliostats", s["n_heliostats"]),
            ("calibrated", s["n_calibrated"]),
            ("hybrid / coarse", f"{s['n_hybrid']} / {s['n_coarse']}"
             + (f" (+ {s['n_pretrained']} pretrained-nn)" if s.get("n_pretrained") else "")
             + (f" (+ {s['n_gp']} GP)" if s.get("n_gp") else "")
             + (f" (+ {s['n_nominal']} on the nominal geometry)" if s.get("n_nominal") else "")),
            ("median test error", f"{_num(s['median_test_error_mrad'])} mrad"
             + (f" ({s['n_degenerate']} degenerate left out)" if s.get("n_degenerate") else "")),
            ("p95 test error", f"{_num(s['p95_test_error_mrad'])} mrad"),
            ("median next-day error", f"{_num(s.get('median_next_day_error_mrad'))} mrad"),
            (f"above {s['alert_mrad']:g} mrad", s["n_above_alert"]),
            ("on alert", s["n_on_alert"])]
    out = page_head(title)
    out.append(nav_html(pages=nav_pages))
    out.append(f"<h1>{e(title)}</h1><p>{e(subtitle)}</p>")
    out.append('<ul class="kpi">' + "".join(
        f"<li><b>{e(str(v))}</b>{e(k)}</li>" for k, v in kpis) + "</ul>")
    out.append(f"<p>Coarse presets chosen: {e(presets)}. Errors are the mean test error_mrad "
               "(angle between predicted and measured mirror normal, on the heliostat's test "
               "measurements) of the model <code>heliocal aim</code> uses. "
               f"{inline(floor_text)}</p>")
    for n in notes:
        out.append(f'<p class="note"><b>Note:</b> {inline(n)}</p>')
    out.append("<h2>Field map</h2>")
    out.append('<div class="map">' + svg_map + "</div>")
    out.append("<p>Each dot is a heliostat at its position (east/north metres of the plant's "
               "ENU frame), coloured by its test error; a red ring marks a heliostat on alert. "
               "Hover for its numbers, click for its page.</p>")
    out.append("<h2>Error distribution</h2>")
    if cdf is not None:
        out.append(f'<figure><img alt="{e(cdf.caption)}" src="figures/'
                   f'{e(urllib.parse.quote(cdf.filename))}"><figcaption>{e(cdf.caption)}'
                   "</figcaption></figure>")
    elif cdf_note:
        out.append(f'<p class="note"><b>Note:</b> {inline(cdf_note)}</p>')
    out.append(f"<h2>The {len(worst)} heliostats that need attention first</h2>")
    out.append("<p>Largest test error first (heliostats without a test error before all); click a "
               'column to sort. Every heliostat: <a href="heliostats.html">all heliostats</a>.</p>')
    out.append(_heliostat_table(worst, "heliostats/", rank=True))
    out.append(SORT_JS)
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def heliostats_list_html(title: str, table: pd.DataFrame,
                         nav_pages: Sequence[tuple[str, str]] = ()) -> str:
    """``heliostats.html``: every heliostat in one sortable table, each a link to its page
    (``nav_pages``: :func:`nav_html`'s ``pages``)."""
    out = page_head(f"All heliostats: {title}")
    out.append(nav_html(pages=nav_pages))
    out.append(f"<h1>All {len(table)} heliostats</h1>")
    out.append("<p>Click a column to sort; click a heliostat for its page.</p>")
    out.append(_heliostat_table(table.sort_values("heliostat_id"), "heliostats/"))
    out.append(SORT_JS)
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def why_text(row, h: dict, best_hybrid_val: float | None) -> str:
    """Which model aim uses for a heliostat and why, from the numbers that decided it."""
    sel = h["selection"]
    cval = sel.get("coarse_val_error_mrad")
    if row["model"] is None:
        return ("No model yet: fit-coarse has not fitted this heliostat, so aim cannot point it "
                "(run `heliocal fit-coarse`).")
    if row["model"] == "nominal":
        alert = [a for a in row.get("alerts", []) if "nominal geometry" in a]
        return (alert[0][0].upper() + alert[0][1:] + "." if alert else
                "aim uses the nominal geometry: the fitted model is worse on held-out rows.")
    if row["source"] == "sweep" and row["model"] in ("hybrid", "pretrained-nn"):
        change = (f" ({100 * (row['val_error_mrad'] / cval - 1):+.0f} %)"
                  if cval and math.isfinite(row["val_error_mrad"]) else "")
        what = (f"selected {row['variant']} model (weight decay {fmt_g(row['weight_decay'])})"
                if row["model"] == "hybrid" else
                "selected pre-trained network (pretrained-nn, sweep --select-pretrained)")
        return (f"aim uses the sweep's {what} on the coarse preset {row['preset']}: its "
                f"validation error {_num(row['val_error_mrad'])} mrad against the coarse "
                f"model's {_num(cval)} mrad{change}.")
    if row["source"] == "sweep":
        best = (f" (the best hybrid candidate reached {_num(best_hybrid_val)} mrad)"
                if best_hybrid_val is not None else "")
        return (f"aim uses the coarse model {row['preset']}: the sweep kept it because no hybrid "
                f"candidate beat its validation error {_num(row['val_error_mrad'])} mrad by the "
                f"sweep's margin{best}.")
    if row["model"] == "coarse" and str(row["preset"]).endswith("+field-prior"):
        return (f"aim uses the field-prior geometry of its group ({row['preset']}): the nominal "
                "geometry moved by the field's typical deviations (fit-coarse --prior field), "
                "either because it has no training rows, so no fit of its own, or because it "
                "beat every fitted preset on validation; field_prior.parquet gives the error "
                "measured on heliostats like it.")
    if row["source"] == "fit-hybrid":
        return (f"aim uses fit-hybrid's hybrid model (weight decay {fmt_g(row['weight_decay'])}) "
                f"on {row['preset']}; no sweep has run to compare it with the coarse model "
                "(run `heliocal sweep`).")
    return (f"aim uses fit-coarse's selected preset {row['preset']} (the preset with the lowest "
            "validation error unless it is worse forward in time, on the time split, than another "
            "by more than 20 %; or the one given with --preset); no hybrid model has been fitted "
            "(run `heliocal sweep`).")


def _next_day_text(row) -> str:
    v = row.get("next_day_error_mrad") if hasattr(row, "get") else None
    return "n/a" if v is None or not math.isfinite(float(v)) else f"{_num(v)} mrad"


def heliostat_html(title: str, row, h: dict, why: str, figures: Sequence[tuple],
                   param_rows: list[list] | None, param_head: str, model_rows: list[list],
                   prev_next: tuple[str | None, str | None],
                   next_day_svg: str | None = None,
                   nav_pages: Sequence[tuple[str, str]] = ()) -> str:
    """``heliostats/<id>.html``: the heliostat's alerts, model and why, its figures (``figures``:
    ``("figure", ReportFigure)`` or ``("note", text)`` blocks), parameters with standard errors
    and accuracy per model and split (``nav_pages``: :func:`nav_html`'s ``pages``)."""
    hid = str(row["heliostat_id"])
    out = page_head(f"{hid}: {title}")
    out.append(nav_html("../", nav_pages))
    links = []
    for label, page in zip(("← previous", "next →"), prev_next):
        if page is not None:
            links.append(f'<a href="{e(urllib.parse.quote(page))}">{label}</a>')
    out.append(f"<h1>Heliostat {e(hid)}</h1>" + (f"<p>{' '.join(links)}</p>" if links else ""))
    for a in row["alerts"]:
        out.append(f'<p class="note alert">Alert: {e(a)}</p>')
    t = _time_num(row)
    kpis = [("test error", f"{_num(row['test_error_mrad'])} mrad"),
            ("test error forward in time", t if t == "n/a" else f"{t} mrad"),
            ("next-day error", _next_day_text(row)),
            ("validation error", f"{_num(row['val_error_mrad'])} mrad"),
            ("model aim uses", model_label(row)),
            ("measurements", row["n_measurements"]), ("test rows", row["n_test"]),
            ("position E / N", f"{_num(row['e_m'], 1)} / {_num(row['n_m'], 1)} m"),
            ("dates", f"{(h['first_timestamp'] or '–')[:10]} … {(h['last_timestamp'] or '–')[:10]}")]
    out.append('<ul class="kpi">' + "".join(
        f"<li><b>{e(str(v))}</b>{e(k)}</li>" for k, v in kpis) + "</ul>")
    out.append(f"<h2>Selected model and why</h2><p>{inline(why)}</p>")
    if next_day_svg:
        out.append("<h2>Recalibrated every calibration day</h2>")
        out.append(f'<figure>{next_day_svg}<figcaption>Rolling-origin evaluation '
                   "(rolling_origin.parquet): on each calibration day the coarse preset fitted "
                   "on every earlier row, its error on that day's rows, against the days since "
                   "the fit's last row.</figcaption></figure>")
    out.append("<h2>Figures</h2>")
    for b in figures:
        if b[0] == "note":
            out.append(f'<p class="note"><b>Note:</b> {inline(b[1])}</p>')
        else:
            f: ReportFigure = b[1]
            out.append(f'<figure><img alt="{e(f.caption)}" loading="lazy" src="../figures/'
                       f'{e(urllib.parse.quote(f.filename))}"><figcaption>{e(f.caption)}'
                       "</figcaption></figure>")
    out.append(f"<h2>Parameters</h2><p>{inline(param_head)}</p>")
    if param_rows:
        out.append(_table(["parameter", "unit", "nominal", "fitted", "std error", "determined"],
                          param_rows))
    out.append("<h2>Accuracy per model and split</h2><p>error_mrad statistics of every model "
               "fitted for this heliostat (★: selected); p95 = 95th percentile.</p>")
    out.append(_table(["model", "split", "n", "mean [mrad]", "median [mrad]", "p95 [mrad]",
                       "beam [mrad]", "spot offset [m]"], model_rows))
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def _table(headers: Sequence[str], rows: Sequence[Sequence]) -> str:
    return ("<table><thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in headers)
            + "</tr></thead><tbody>"
            + "".join("<tr>" + "".join(f"<td>{e(fmt(c))}</td>" for c in r) + "</tr>"
                      for r in rows) + "</tbody></table>")


def field_page_blocks(figures: Sequence[tuple]) -> list[tuple]:
    """Blocks of ``field.html`` (rendered by ``pages.render_html`` with linked figures)."""
    return [("h1", "Paper 000's figures across the field"),
            ("p", "Each figure aggregates every heliostat that has the data: the line is the "
                  "median over heliostats, the band the 25-75 % range. Per "
                  "heliostat the same figures are on its page."), *figures]

