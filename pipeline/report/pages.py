"""The report's pages: the Markdown text (tables and figure references, every value escaped) and
the self-contained HTML rendering of it.
"""

from __future__ import annotations

import base64
import html
import math
import re
import urllib.parse
from typing import Sequence

import numpy as np

from ..artifacts.schemas import REJECTION_REASONS
from ..vocabulary import STD_ERROR_PSEUDO_INVERSE
from .inputs import ReportInputs
from .metrics import final_models, split_sort_key
from .scope import FigureScope
from .render import (FigureTask, ReportFigure, heliostat_figure_plan, sweep_choices,
                     sweep_weight_decays)

__all__ = [
    "build_report",
    "figure_tasks",
    "fmt",
    "fmt_g",
    "inline_html",
    "md_inline",
    "md_text",
    "page_head",
    "parameter_tables",
    "PAGE_CSS",
    "render_html",
    "render_markdown",
    "resolve_figures",
]


# ------------------------------------------------------------------------------------------------
# document: a list of blocks rendered to Markdown and self-contained HTML
# ------------------------------------------------------------------------------------------------
def fmt(x, digits: int = 3) -> str:
    """A value as table text: 3 decimals, "–" for missing, yes/no for booleans."""
    if x is None:
        return "–"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        if not math.isfinite(float(x)):
            return "–"
        return f"{float(x):.{digits}f}"
    return str(x)


def fmt_g(x) -> str:
    """A number in 6 significant digits ("–" when missing)."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{float(x):.6g}"


def _forward_cell(h: dict, role: str) -> str:
    """A heliostat's forward-in-time test error of ``role`` (final or coarse) from metrics.json;
    "n/a" when it has no time split."""
    v = (((h.get("forward_in_time") or {}).get(role) or {}).get("time_test") or {}).get(
        "mean_error_mrad")
    return "n/a" if v is None else fmt(v)


def _degenerate(inp: ReportInputs) -> dict:
    """heliostat -> why its training data cannot determine the coarse model (coarse_params'
    ``fit_degenerate``), for the heliostats where they cannot."""
    cp = inp.coarse_params
    if cp is None or "fit_degenerate" not in cp.columns:
        return {}
    first = cp.groupby("heliostat_id", sort=True)["fit_degenerate"].first()
    return {str(h): str(w) for h, w in first.items() if isinstance(w, str) and w}


def parameter_tables(coarse_params) -> dict[str, list[list]]:
    """heliostat -> table rows (parameter, unit, nominal, fitted, std error, determined) of the
    free parameters of its fit in ``coarse_params`` rows (pass the selected preset's rows), in
    parameter order. Columns are read once for the whole field."""
    g = coarse_params
    if "parameter_index" in g.columns:
        g = g.sort_values(["heliostat_id", "parameter_index"], kind="stable")
    free = g[g["free"].astype(bool)] if "free" in g.columns else g
    col = {c: free[c].tolist() if c in free.columns else None
           for c in ("parameter", "unit", "nominal", "fitted", "std_error", "determined")}
    out: dict[str, list[list]] = {}
    for i, hid in enumerate(free["heliostat_id"].astype(str).tolist()):
        out.setdefault(hid, []).append([
            col["parameter"][i], col["unit"][i] if col["unit"] is not None else "",
            fmt_g(col["nominal"][i]), fmt_g(col["fitted"][i]), fmt_g(col["std_error"][i]),
            fmt(bool(col["determined"][i])) if col["determined"] is not None else "–"])
    return out


def build_report(inp: ReportInputs, metrics: dict,
                 scope: FigureScope | None = None) -> list[tuple]:
    """The report as blocks: ``("h1"|"h2"|"h3"|"p"|"note", text)``, ``("table", headers, rows)``
    and ``("task", FigureTask)`` (figures still to draw: :func:`figure_tasks` lists them,
    :func:`resolve_figures` puts the drawn figures in their place). A note about one heliostat
    carries its id third (its page shows it too). ``scope``: whose figures are drawn (default
    every heliostat's, :mod:`.scope`)."""
    data = metrics["data"]
    helios = metrics["heliostats"]
    blocks: list[tuple] = [("h1", f"heliocal report: {inp.workdir}")]
    blocks.append(("p", f"heliocal {metrics['heliocal_version']}, git {metrics['git_revision']}. "
                        f"Artifacts: {', '.join(data['artifacts'])}. Errors are angles between "
                        "predicted and measured mirror normal in mrad (error_mrad); the "
                        "numbers are also in metrics.json."))
    for note in inp.notes:
        blocks.append(("note", note))
    blocks += _data_blocks(inp, data, helios)
    blocks += _accuracy_blocks(inp, helios)
    if any(h["selection"]["model"] for h in helios.values()):
        blocks += _selection_blocks(inp, helios)
    blocks += _parameter_blocks(inp)
    blocks.append(("h2", "Figures"))
    blocks += heliostat_figure_plan(inp, metrics, final_models(inp), scope)
    return blocks


def _data_blocks(inp: ReportInputs, data: dict, helios: dict) -> list[tuple]:
    """The data summary: measurements, split counts per heliostat, rejected rows."""
    blocks: list[tuple] = []
    blocks.append(("h2", "Data"))
    blocks.append(("p", f"{data['n_measurements']} measurements of {data['n_heliostats']} "
                        f"heliostats from {data['first_timestamp'] or '?'} to "
                        f"{data['last_timestamp'] or '?'}"
                        + (f" ({data['n_missing_timestamp']} without timestamp)"
                           if data["n_missing_timestamp"] else "")
                        + f"; {data['n_rejected']} rows rejected by ingest."))
    splits = sorted({s for h in helios.values() for s in h["split_counts"]}, key=split_sort_key)
    headers = ["heliostat", "measurements", *splits, "first", "last", "test→train [deg]"]
    rows = [[hid, h["n_measurements"], *[h["split_counts"].get(s, 0) for s in splits],
             (h["first_timestamp"] or "–")[:10], (h["last_timestamp"] or "–")[:10],
             fmt(h["test_train_distance_deg"], 2)] for hid, h in helios.items()]
    blocks.append(("table", headers, rows))
    if inp.split is None:
        blocks.append(("note", f"No split.parquet: run {inp.run_hint('split.parquet')} for the "
                               "training/validation/test split."))
    else:
        blocks.append(("p", "test→train: mean distance in sun position from a test measurement "
                            "to the nearest training measurement (split.parquet)."))
    if data["rejected_by_reason"]:
        blocks.append(("table", ["reason", "rows", "meaning"],
                       [[k, v, REJECTION_REASONS.get(k, "")]
                        for k, v in data["rejected_by_reason"].items()]))
    else:
        blocks.append(("p", "No input rows were rejected."))
    return blocks


def _accuracy_blocks(inp: ReportInputs, helios: dict) -> list[tuple]:
    """Per heliostat, model and split: the error statistics; degenerate training data noted."""
    blocks: list[tuple] = []
    blocks.append(("h2", "Accuracy"))
    degenerate = _degenerate(inp)
    for hid, why in degenerate.items():
        blocks.append(("note", f"{hid}: degenerate training data ({why}). Its errors below say "
                               "nothing about its accuracy, however small they are: calibrate "
                               "it at more sun positions."))
    if inp.predictions is None:
        blocks.append(("note", "No predictions: run "
                               f"{inp.run_hint('coarse_predictions.parquet')} for the error "
                               "tables and figures."))
    else:
        blocks.append(("p", "Per heliostat, model and split: error_mrad statistics (p95 = 95th "
                            "percentile), mean beam error and mean spot offset on the target. "
                            "★ marks the selected coarse preset and the selected hybrid model."))
        headers = ["heliostat", "model", "split", "n", "mean [mrad]", "median [mrad]",
                   "p95 [mrad]", "beam [mrad]", "spot offset [m]"]
        rows = []
        for hid, h in helios.items():
            label = hid + (" (degenerate data)" if hid in degenerate else "")
            for model, mm in h["models"].items():
                name = model + (" ★" if mm["selected"] else "")
                for sp, st in mm["splits"].items():
                    rows.append([label, name, sp, st["n"], fmt(st["mean_error_mrad"]),
                                 fmt(st["median_error_mrad"]), fmt(st["p95_error_mrad"]),
                                 fmt(st["mean_beam_error_mrad"]), fmt(st["mean_spot_offset_m"])])
        blocks.append(("table", headers, rows))
    return blocks


def _selection_blocks(inp: ReportInputs, helios: dict) -> list[tuple]:
    """The sweep's (or fit-coarse's) final model per heliostat and its errors."""
    blocks: list[tuple] = [("h3", "Selection")]
    headers = ["heliostat", "coarse preset", "final model", "weight decay",
               "validation [mrad]", "test [mrad]", "coarse validation [mrad]",
               "coarse test [mrad]", "test forward in time [mrad]",
               "coarse test forward in time [mrad]"]
    rows = []
    choice, wd_of = sweep_choices(inp), sweep_weight_decays(inp)
    for hid, h in helios.items():
        s = dict(h["selection"])
        model = h["models"].get(s["model"] or "", {}).get("splits", {})
        coarse = h["models"].get(s["coarse_preset"] or "", {}).get("splits", {})
        pick = lambda key, splits, sp: s[key] if s[key] is not None else (
            splits.get(sp, {}).get("mean_error_mrad"))
        shown = s["model"] or "–"
        if shown == "selected" and hid in choice:
            shown = f"selected ({choice[hid]})"
        rows.append([hid, s["coarse_preset"] or "–", shown,
                     fmt_g(wd_of.get(hid, s["weight_decay"])),
                     fmt(pick("val_error_mrad", model, "validation")),
                     fmt(pick("test_error_mrad", model, "test")),
                     fmt(pick("coarse_val_error_mrad", coarse, "validation")),
                     fmt(pick("coarse_test_error_mrad", coarse, "test")),
                     *(_forward_cell(h, role) for role in ("final", "coarse"))])
    blocks.append(("table", headers, rows))
    blocks.append(("p", "Test: the split that selects (split.parquet `split`, kNN by "
                        "default). Forward in time: the same model trained again on the "
                        "time split's training rows only, its mean error on the time "
                        "split's test rows (the latest measurements); n/a: the heliostat "
                        "has no time split (too few timestamps), or its selected hybrid "
                        "was not trained again (`heliocal sweep --time-split`)."))
    return blocks


def _parameter_blocks(inp: ReportInputs) -> list[tuple]:
    """The selected coarse fit's parameters per heliostat, with its diagnostics and warnings."""
    blocks: list[tuple] = []
    blocks.append(("h2", "Coarse parameters"))
    cp = inp.coarse_params
    if cp is None:
        blocks.append(("note", f"No coarse_params.parquet: run "
                               f"{inp.run_hint('coarse_params.parquet')}."))
    else:
        sel = cp[cp["selected"].astype(bool)] if "selected" in cp.columns else cp
        blocks.append(("p", "Free parameters of the selected preset: nominal and fitted value with "
                            "the standard error from the Jacobian at the solution. 'determined: "
                            "no' means the data cannot pin the parameter (the weak prior holds "
                            "it near nominal)."))
        tables = parameter_tables(sel)
        for first in sel.drop_duplicates("heliostat_id").sort_values("heliostat_id").to_dict(
                "records"):  # the fit's diagnostics are repeated on each of its rows
            hid = str(first["heliostat_id"])
            diag = [f"{label} {fmt_g(first[key])}" for key, label in (
                ("n_train", "training rows"), ("fit_iterations", "iterations"),
                ("fit_condition_number", "condition number")) if key in first]
            blocks.append(("h3", f"{hid}: {first.get('preset', '?')}"
                                 + (f" ({', '.join(diag)})" if diag else "")))
            if str(first.get("fit_implausible") or ""):
                blocks.append(("note", f"Large corrections of the nominal geometry: "
                                       f"{first['fit_implausible']}."))
            if STD_ERROR_PSEUDO_INVERSE in str(first.get("fit_status") or ""):
                blocks.append(("note", f"{hid}: {STD_ERROR_PSEUDO_INVERSE} (the data and the "
                                       "prior leave a direction of the parameters free).", hid))
            blocks.append(("table", ["parameter", "unit", "nominal", "fitted", "std error",
                                     "determined"], tables.get(hid, [])))
    return blocks


def figure_tasks(blocks: Sequence[tuple]) -> list[FigureTask]:
    """The figures the blocks need drawn, in order."""
    return [b[1] for b in blocks if b[0] == "task"]


def resolve_figures(blocks: Sequence[tuple], drawn: dict[str, tuple]) -> list[tuple]:
    """Blocks with each ``task`` replaced by ``("figure", ReportFigure, kind)``, or by ``("note",
    why, heliostat)`` saying why it was omitted. ``drawn``: file name -> ``(png or None, why)`` of :func:`render.render_task`."""
    out = []
    for b in blocks:
        if b[0] != "task":
            out.append(b)
            continue
        task: FigureTask = b[1]
        png, why = drawn[task.filename]
        if png is None:
            who = f"{task.heliostat}: omitted" if task.heliostat is not None else "Omitted"
            out.append(("note", f"{who} ({why}).", task.heliostat))
        else:
            out.append(("figure", ReportFigure(task.filename, task.caption, png, task.heliostat),
                        task.kind))
    return out


#: Characters that start Markdown (CommonMark, GitHub's extensions) or HTML markup anywhere in a
#: line; :func:`md_text` puts a backslash before each (CommonMark's escape of ASCII punctuation).
_MD_ALWAYS = frozenset("\\`*[]<>&|~$")


#: Text without white space, :data:`_MD_ALWAYS` characters or ``_``: :func:`md_text` keeps it.
_MD_PLAIN = re.compile(r"[^\s\\`*\[\]<>&|~$_]*\Z")

#: Line starts that open a block (heading, quote, list, setext underline, thematic break).
_MD_LINE_START = re.compile(r"^(?:([#>+=-])|(\d{1,9})([.)])(?=\s|$))")


def md_text(text, line_start: bool = True) -> str:
    """``text`` as Markdown that renders as exactly that text, on one line.

    Every character that could open markup is backslash-escaped (``<img src=x onerror=...>``
    renders as those characters, never as HTML); ``_`` only where it could open or close
    emphasis (not between two letters or digits, so ``joint_1_tilt_n_rad`` stays readable); a
    leading ``#``, ``>``, ``+``, ``-``, ``=`` or ``1.`` cannot start a block (``line_start``:
    the text begins a line; not in table cells); runs of white space (newlines too) become one
    space.
    """
    text = str(text)
    if _MD_PLAIN.match(text) and not (line_start and _MD_LINE_START.match(text)):
        return text                      # nothing to escape (most table cells: numbers, ids)
    text = re.sub(r"\s+", " ", text)
    if line_start:
        text = text.lstrip()
    out = []
    for i, c in enumerate(text):
        if c in _MD_ALWAYS:
            out.append("\\" + c)
        elif c == "_" and not (0 < i < len(text) - 1 and text[i - 1].isalnum()
                               and text[i + 1].isalnum()):
            out.append("\\_")
        else:
            out.append(c)
    escaped = "".join(out)
    m = _MD_LINE_START.match(escaped) if line_start else None
    if m and m.group(1):
        escaped = "\\" + escaped
    elif m:
        escaped = m.group(2) + "\\" + escaped[len(m.group(2)):]
    return escaped


def md_inline(text) -> str:
    """Like :func:`md_text`, but a span in backticks (a command such as
    `` `heliocal sweep --workdir DIR` `` in the report's own sentences) stays a code span, whose
    content Markdown shows literally. With an odd number of backticks everything is plain text."""
    text = " ".join(str(text).split())
    parts = text.split("`")
    if len(parts) % 2 == 0:
        return md_text(text)
    out = []
    for i, part in enumerate(parts):
        if i % 2 == 0:
            out.append(md_text(part, line_start=i == 0) if part else "")
        elif part.strip():
            out.append(f"`{part}`")
    return "".join(out)


def render_markdown(blocks: Sequence[tuple]) -> str:
    """report.md: figures linked as ``figures/<name>.png``; every text from the data escaped
    (:func:`md_text`), so the file renders as the same text as index.html."""
    lines: list[str] = []
    for b in blocks:
        kind = b[0]
        if kind in ("h1", "h2", "h3"):
            lines += ["#" * int(kind[1]) + " " + md_inline(b[1]), ""]
        elif kind == "p":
            lines += [md_inline(b[1]), ""]
        elif kind == "note":
            lines += [f"> **Note:** {md_inline(b[1])}", ""]
        elif kind == "table":
            headers, rows = b[1], b[2]
            lines.append("| " + " | ".join(md_text(h, False) for h in headers) + " |")
            lines.append("|" + "|".join("---" for _ in headers) + "|")
            lines += ["| " + " | ".join(md_text(fmt(c), False) for c in r) + " |" for r in rows]
            lines.append("")
        elif kind == "figure":
            f: ReportFigure = b[1]
            link = "figures/" + urllib.parse.quote(f.filename)
            lines += [f"![{md_text(f.caption, False)}]({link})", "",
                      f"*{md_inline(f.caption)}*", ""]
    return "\n".join(lines).rstrip() + "\n"


#: The style sheet of every page of the report (no external resource: pages work from file://).
PAGE_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1150px;margin:1.5em auto;
padding:0 1em;color:#222;line-height:1.45}
table{border-collapse:collapse;margin:0.5em 0 1.2em;font-size:0.88em}
th,td{border:1px solid #ccc;padding:2px 8px;text-align:right}
th{background:#f0f0f0}td:first-child,td:nth-child(2),th:first-child{text-align:left}
figure{margin:1em 0 2em}figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:0.9em;color:#444}
.note{background:#fff8e1;border-left:4px solid #f0b400;padding:0.4em 0.8em}
nav{font-size:0.92em;margin-bottom:0.6em}nav a{margin-right:1.2em}
.alert{color:#b00020;font-weight:600}td.t{text-align:left}code{font-size:0.92em}
.kpi{display:flex;flex-wrap:wrap;gap:0.6em;margin:0.6em 0 1em;padding:0}
.kpi li{list-style:none;border:1px solid #ddd;border-radius:4px;padding:0.35em 0.8em;background:#fafafa}
.kpi b{display:block;font-size:1.25em}
.map{display:flex;flex-wrap:wrap;gap:1em;align-items:flex-start}
svg text{font-family:system-ui,sans-serif}
th[data-sort]{cursor:pointer}th[data-sort]:after{content:" \\2195";color:#999}
"""


def page_head(title: str, extra: str = "") -> list[str]:
    """The opening lines of a report page (title escaped, the shared style sheet)."""
    return ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
            '<meta name="viewport" content="width=device-width, initial-scale=1">',
            f"<title>{html.escape(title)}</title><style>{PAGE_CSS}</style>{extra}</head><body>"]


def inline_html(text) -> str:
    """``text`` HTML-escaped, with each `backtick span` (a command) shown as code."""
    parts = html.escape(str(text)).split("`")
    if len(parts) % 2 == 0:
        return html.escape(str(text))
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))


def render_html(blocks: Sequence[tuple], *, embed: bool = True, nav: str = "",
                figure_prefix: str = "figures/") -> str:
    """The blocks as an HTML page. ``embed``: every figure a base64 PNG ``data:`` URI (a
    self-contained page); else an ``<img loading="lazy">`` of ``figure_prefix + filename``.
    ``nav``: HTML put first in the body (links to the other pages)."""
    e = html.escape
    title = next((b[1] for b in blocks if b[0] == "h1"), "heliocal report")
    out = page_head(title)
    if nav:
        out.append(nav)
    for b in blocks:
        kind = b[0]
        if kind in ("h1", "h2", "h3"):
            out.append(f"<{kind}>{e(b[1])}</{kind}>")
        elif kind == "p":
            out.append(f"<p>{inline_html(b[1])}</p>")
        elif kind == "note":
            out.append(f'<p class="note"><b>Note:</b> {inline_html(b[1])}</p>')
        elif kind == "table":
            headers, rows = b[1], b[2]
            out.append("<table><thead><tr>" + "".join(f"<th>{e(str(h))}</th>" for h in headers)
                       + "</tr></thead><tbody>")
            out += ["<tr>" + "".join(f"<td>{e(fmt(c))}</td>" for c in r) + "</tr>" for r in rows]
            out.append("</tbody></table>")
        elif kind == "figure":
            f: ReportFigure = b[1]
            if embed:
                data = base64.b64encode(f.png).decode("ascii")
                src = f"data:image/png;base64,{data}"
                extra = f' data-file="{e(figure_prefix + f.filename)}"'
            else:
                src = e(figure_prefix + urllib.parse.quote(f.filename))
                extra = ' loading="lazy"'
            out.append(f'<figure id="{e(f.filename)}"><img alt="{e(f.caption)}"{extra} '
                       f'src="{src}"><figcaption>{e(f.caption)}</figcaption></figure>')
    out.append("</body></html>")
    return "\n".join(out) + "\n"
