"""The report's pages: the Markdown text (tables and figure references, every value escaped) and
the self-contained HTML rendering of it.
"""

from __future__ import annotations

import base64
import html
import math
import re
import urllib.parse
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..artifacts.schemas import REJECTION_REASONS
from .figures import (SKY_POINTS_PER_MRAD, hybrid_vs_coarse_table, plot_error_over_time,
                      plot_hybrid_vs_coarse, plot_sky_map, plot_training_size, plot_weight_decay,
                      png_bytes)
from .inputs import ReportInputs
from .metrics import final_models, split_sort_key
from .regimes import regime_blocks

__all__ = [
    "build_report",
    "render_html",
    "render_markdown",
]


# ------------------------------------------------------------------------------------------------
# document: a list of blocks rendered to Markdown and self-contained HTML
# ------------------------------------------------------------------------------------------------
@dataclass
class _Figure:
    filename: str
    caption: str
    png: bytes


def _fmt(x, digits: int = 3) -> str:
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


def _fmt_g(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{float(x):.6g}"


def _degenerate(inp: ReportInputs) -> dict:
    """heliostat -> why its training data cannot determine the coarse model (coarse_params'
    ``fit_degenerate``), for the heliostats where they cannot."""
    cp = inp.coarse_params
    if cp is None or "fit_degenerate" not in cp.columns:
        return {}
    first = cp.groupby("heliostat_id", sort=True)["fit_degenerate"].first()
    return {str(h): str(w) for h, w in first.items() if isinstance(w, str) and w}


def build_report(inp: ReportInputs, metrics: dict) -> list[tuple]:
    """The report as blocks: ``("h1"|"h2"|"h3"|"p"|"note", text)``, ``("table", headers, rows)``
    and ``("figure", _Figure)``."""
    blocks: list[tuple] = []
    wd = inp.workdir
    data = metrics["data"]
    helios = metrics["heliostats"]
    finals = final_models(inp)
    blocks.append(("h1", f"heliocal report: {wd}"))
    blocks.append(("p", f"heliocal {metrics['heliocal_version']}, git {metrics['git_revision']}. "
                        f"Artifacts: {', '.join(data['artifacts'])}. Errors are angles between "
                        "predicted and measured mirror normal in mrad (error_mrad); the "
                        "numbers are also in metrics.json."))
    for note in inp.notes:
        blocks.append(("note", note))

    # --- data summary
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
             _fmt(h["test_train_distance_deg"], 2)] for hid, h in helios.items()]
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

    # --- accuracy tables
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
                    rows.append([label, name, sp, st["n"], _fmt(st["mean_error_mrad"]),
                                 _fmt(st["median_error_mrad"]), _fmt(st["p95_error_mrad"]),
                                 _fmt(st["mean_beam_error_mrad"]), _fmt(st["mean_spot_offset_m"])])
        blocks.append(("table", headers, rows))

    # --- selection
    if any(h["selection"]["model"] for h in helios.values()):
        blocks.append(("h3", "Selection"))
        headers = ["heliostat", "coarse preset", "final model", "weight decay",
                   "validation [mrad]", "test [mrad]", "coarse validation [mrad]",
                   "coarse test [mrad]"]
        rows = []
        # the sweep's choice (hybrid, hybrid-octaves or coarse) behind the "selected" rows
        choice = {}
        if inp.selection is not None and {"heliostat_id", "model"} <= set(inp.selection.columns):
            choice = dict(zip(inp.selection["heliostat_id"].astype(str),
                              inp.selection["model"].astype(str)))
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
                         _fmt_g(s["weight_decay"]),
                         _fmt(pick("val_error_mrad", model, "validation")),
                         _fmt(pick("test_error_mrad", model, "test")),
                         _fmt(pick("coarse_val_error_mrad", coarse, "validation")),
                         _fmt(pick("coarse_test_error_mrad", coarse, "test"))])
        blocks.append(("table", headers, rows))

    # --- coarse parameters
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
        for hid, g in sel.groupby("heliostat_id", sort=True):
            g = g.sort_values("parameter_index") if "parameter_index" in g.columns else g
            first = g.iloc[0]
            diag = []
            for key, label in (("n_train", "training rows"), ("fit_iterations", "iterations"),
                               ("fit_condition_number", "condition number")):
                if key in g.columns:
                    diag.append(f"{label} {_fmt_g(first[key])}")
            blocks.append(("h3", f"{hid}: {first.get('preset', '?')}"
                                 + (f" ({', '.join(diag)})" if diag else "")))
            if "fit_implausible" in g.columns and str(first["fit_implausible"] or ""):
                blocks.append(("note", f"Large corrections of the nominal geometry: "
                                       f"{first['fit_implausible']}."))
            free = g[g["free"].astype(bool)] if "free" in g.columns else g
            rows = [[r["parameter"], r.get("unit", ""), _fmt_g(r["nominal"]), _fmt_g(r["fitted"]),
                     _fmt_g(r["std_error"]), _fmt(bool(r["determined"]))
                     if "determined" in free.columns else "–"] for _, r in free.iterrows()]
            blocks.append(("table", ["parameter", "unit", "nominal", "fitted", "std error",
                                     "determined"], rows))

    # --- figures
    blocks.append(("h2", "Figures"))
    figs = _figures(inp, metrics, finals)
    for item in figs:
        blocks.append(item)
    return blocks


def _figure_block(fig, filename: str, caption: str) -> tuple:
    """A figure as a report block (its PNG); the figure is cleared."""
    try:
        return ("figure", _Figure(filename, caption, png_bytes(fig)))
    finally:
        fig.clear()


def _figures(inp: ReportInputs, metrics: dict, finals: dict) -> list[tuple]:
    out: list[tuple] = []
    hids = list(metrics["heliostats"])

    def add(fig, filename, caption):
        out.append(_figure_block(fig, filename, caption))

    sweep_hint = inp.run_hint("sweep.parquet")

    # fig. 6
    out.append(("h3", "Error against training size (paper 000, fig. 6)"))
    if inp.sweep is None:
        out.append(("note", f"Omitted: needs sweep.parquet; run {sweep_hint}."))
    else:
        for hid in hids:
            sel = metrics["heliostats"][hid]["selection"]
            coarse = metrics["heliostats"][hid]["models"].get(sel["coarse_preset"] or "")
            level = coarse["splits"].get("test", {}).get("mean_error_mrad") if coarse else None
            fig, why = plot_training_size(inp.sweep, hid, level,
                                          f"coarse {sel['coarse_preset']}")
            if fig is None:
                out.append(("note", f"{hid}: omitted ({why})."))
                continue
            add(fig, f"training_size_{hid}.png",
                f"{hid}: mean test error against the number of training measurements per model "
                "(weight decay chosen on validation; band: spread over seeds). Below: mean distance "
                "in sun position from the test set to the training set.")

    # fig. 7
    out.append(("h3", "Sky map (paper 000, fig. 7)"))
    for hid in hids:
        model = finals.get(hid, {}).get("model")
        fig = plot_sky_map(inp.measurements, inp.split, inp.predictions, hid, model)
        cap = (f"{hid}: measurements over sun azimuth and elevation; dots are training points. "
               f"Validation and test points are circles whose radius grows linearly with the "
               f"error of {model} ({SKY_POINTS_PER_MRAD:g} pt per mrad); the grey ring is 1 mrad.")
        if model is None:
            cap = f"{hid}: measurements over sun azimuth and elevation (no predictions yet)."
        add(fig, f"sky_map_{hid}.png", cap)

    # fig. 9a
    out.append(("h3", "Error against weight decay (paper 000, fig. 9a)"))
    if inp.sweep is None:
        out.append(("note", f"Omitted: needs sweep.parquet; run {sweep_hint}."))
    else:
        for hid in hids:
            h = metrics["heliostats"][hid]
            sel = h["selection"]
            coarse = h["models"].get(sel["coarse_preset"] or "", {}).get("splits", {})
            cval = sel["coarse_val_error_mrad"]
            ctest = sel["coarse_test_error_mrad"]
            cval = cval if cval is not None else coarse.get("validation", {}).get("mean_error_mrad")
            ctest = ctest if ctest is not None else coarse.get("test", {}).get("mean_error_mrad")
            fig, why = plot_weight_decay(inp.sweep, hid, sel["model"], cval, ctest,
                                         sel["weight_decay"])
            if fig is None:
                out.append(("note", f"{hid}: omitted ({why})."))
                continue
            add(fig, f"weight_decay_{hid}.png",
                f"{hid}: mean validation and test error against weight decay at the largest "
                "training size (band: spread over seeds); dashed lines: the selected coarse "
                "model's validation and test error; dotted: the selected weight decay.")

    # fig. 8
    out.append(("h3", "Hybrid against coarse (paper 000, fig. 8)"))
    table = hybrid_vs_coarse_table(inp)
    if table is None:
        out.append(("note", "Omitted: needs selection.parquet or hybrid_predictions.parquet; run "
                            f"{inp.run_hint('hybrid_predictions.parquet')} and {sweep_hint}."))
    else:
        add(plot_hybrid_vs_coarse(table), "hybrid_vs_coarse.png",
            "Mean validation and test error of the selected hybrid model and the selected coarse "
            "preset per heliostat.")

    # regimes (issue 17): alert list and per-heliostat regime figures
    out += regime_blocks(inp, hids, _figure_block)

    # error over time
    out.append(("h3", "Error over time"))
    if inp.predictions is None:
        out.append(("note", "Omitted: needs predictions; run "
                            f"{inp.run_hint('coarse_predictions.parquet')}."))
    else:
        for hid in hids:
            f = finals.get(hid, {})
            if f.get("model") is None:
                continue
            fig, why = plot_error_over_time(inp.measurements, inp.predictions, hid, f["model"],
                                            f.get("coarse_preset"))
            if fig is None:
                out.append(("note", f"{hid}: omitted ({why})."))
                continue
            add(fig, f"error_over_time_{hid}.png",
                f"{hid}: error of {f['model']} per measurement over the date, coloured by split, "
                "with a centred 30-day rolling median (drift and seasonal patterns).")
    return out


#: Characters that start Markdown (CommonMark, GitHub's extensions) or HTML markup anywhere in a
#: line; :func:`md_text` puts a backslash before each (CommonMark's escape of ASCII punctuation).
_MD_ALWAYS = frozenset("\\`*[]<>&|~$")


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
    text = re.sub(r"\s+", " ", str(text))
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
            lines += ["| " + " | ".join(md_text(_fmt(c), False) for c in r) + " |" for r in rows]
            lines.append("")
        elif kind == "figure":
            f: _Figure = b[1]
            link = "figures/" + urllib.parse.quote(f.filename)
            lines += [f"![{md_text(f.caption, False)}]({link})", "",
                      f"*{md_inline(f.caption)}*", ""]
    return "\n".join(lines).rstrip() + "\n"


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;
padding:0 1em;color:#222;line-height:1.45}
table{border-collapse:collapse;margin:0.5em 0 1.2em;font-size:0.88em}
th,td{border:1px solid #ccc;padding:2px 8px;text-align:right}
th{background:#f0f0f0}td:first-child,td:nth-child(2),th:first-child{text-align:left}
figure{margin:1em 0 2em}figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:0.9em;color:#444}
.note{background:#fff8e1;border-left:4px solid #f0b400;padding:0.4em 0.8em}
"""


def render_html(blocks: Sequence[tuple]) -> str:
    """index.html: self-contained, every figure embedded as a base64 PNG ``data:`` URI."""
    e = html.escape
    title = next((b[1] for b in blocks if b[0] == "h1"), "heliocal report")
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           f"<title>{e(title)}</title><style>{_CSS}</style></head><body>"]
    for b in blocks:
        kind = b[0]
        if kind in ("h1", "h2", "h3"):
            out.append(f"<{kind}>{e(b[1])}</{kind}>")
        elif kind == "p":
            out.append(f"<p>{e(b[1])}</p>")
        elif kind == "note":
            out.append(f'<p class="note"><b>Note:</b> {e(b[1])}</p>')
        elif kind == "table":
            headers, rows = b[1], b[2]
            out.append("<table><thead><tr>" + "".join(f"<th>{e(str(h))}</th>" for h in headers)
                       + "</tr></thead><tbody>")
            out += ["<tr>" + "".join(f"<td>{e(_fmt(c))}</td>" for c in r) + "</tr>" for r in rows]
            out.append("</tbody></table>")
        elif kind == "figure":
            f: _Figure = b[1]
            data = base64.b64encode(f.png).decode("ascii")
            out.append(f'<figure id="{e(f.filename)}"><img alt="{e(f.caption)}" '
                       f'data-file="figures/{e(f.filename)}" src="data:image/png;base64,{data}">'
                       f"<figcaption>{e(f.caption)}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"
