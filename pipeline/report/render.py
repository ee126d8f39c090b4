"""The report's figures as tasks: what to draw, with the rows it needs, so that any process can
draw it.

The report plans its figures in the main process (:func:`heliostat_figure_plan`: captions, file
names, the order in the pages) and draws them with :func:`render_task`, one matplotlib figure per
task, in worker processes (``runtime.parallel.map_tasks``; the Agg renderer, no pyplot state).
Each task carries only its own heliostat's rows (the inputs are grouped by heliostat once), so a
task is small to send and costs the same whatever the field's size.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from .figures import (SKY_POINTS_PER_MRAD, plot_error_over_time, plot_gp_correction,
                      plot_hybrid_vs_coarse, plot_sky_map, plot_training_size, plot_weight_decay,
                      png_bytes)
from .inputs import ReportInputs
from .scope import FigureScope

__all__ = [
    "FigureTask",
    "ReportFigure",
    "by_heliostat",
    "heliostat_figure_plan",
    "render_task",
    "sweep_choices",
    "sweep_weight_decays",
]


@dataclass
class ReportFigure:
    """A drawn figure: its file name under ``figures/``, caption, PNG bytes and heliostat (None
    for a figure of several)."""

    filename: str
    caption: str
    png: bytes
    heliostat: str | None = None


@dataclass
class FigureTask:
    """One figure to draw: ``kind`` names the drawing function, ``args`` its arguments (small
    per-heliostat frames and numbers), ``heliostat`` its heliostat (None for field figures)."""

    kind: str
    filename: str
    caption: str
    heliostat: str | None = None
    args: dict[str, Any] = field(default_factory=dict)


def _draw(task: FigureTask):
    """(figure, None) or (None, why) for a task (a figure function's own contract)."""
    a = task.args
    if task.kind == "training_size":
        return plot_training_size(a["sweep"], task.heliostat, a["level"], a["label"])
    if task.kind == "sky_map":
        return plot_sky_map(a["measurements"], a["split"], a["predictions"], task.heliostat,
                            a["model"], a.get("label")), None
    if task.kind == "weight_decay":
        return plot_weight_decay(a["sweep"], task.heliostat, a["model"], a["cval"], a["ctest"],
                                 a["weight_decay"])
    if task.kind == "error_over_time":
        return plot_error_over_time(a["measurements"], a["predictions"], task.heliostat,
                                    a["model"], a["coarse"], label=a.get("label"))
    if task.kind == "gp_correction":
        return plot_gp_correction(a["grid"], task.heliostat), None
    if task.kind == "hybrid_vs_coarse":
        return plot_hybrid_vs_coarse(a["table"]), None
    if task.kind == "regimes":
        from .regimes import plot_regimes

        return plot_regimes(a["measurements"], a["predictions"], a["regimes"], task.heliostat)
    if task.kind.startswith("prior_"):
        from .prior_figures import draw_prior_figure

        return draw_prior_figure(task.kind, a)
    if task.kind.startswith("field_"):
        from .field_figures import draw_field_figure

        return draw_field_figure(task.kind, a)
    raise ValueError(f"unknown figure kind {task.kind!r}")  # pragma: no cover - a bug


def render_task(task: FigureTask) -> tuple[bytes | None, str | None]:
    """Draw one task: ``(png, None)``, or ``(None, why)`` when its data cannot make the figure.
    Module level and picklable: the report runs it in worker processes."""
    fig, why = _draw(task)
    if fig is None:
        return None, why
    return png_bytes(fig), None  # (no fig.clear(): it costs ~5 %; the figure is dropped here)


# ------------------------------------------------------------------------------------------------
# planning (main process)
# ------------------------------------------------------------------------------------------------
def by_heliostat(df: pd.DataFrame | None) -> dict[str, pd.DataFrame]:
    """``df``'s rows per heliostat_id (one groupby over the frame; empty without ``df``)."""
    if df is None:
        return {}
    return {str(h): g for h, g in df.groupby(df["heliostat_id"].astype(str), sort=False)}


def sweep_choices(inp: ReportInputs) -> dict[str, str]:
    """The sweep's choice per heliostat behind the predictions of model "selected" (hybrid,
    hybrid-octaves, coarse, ...; selection.parquet ``model``)."""
    sel = inp.selection
    if sel is None or not {"heliostat_id", "model"} <= set(sel.columns):
        return {}
    return dict(zip(sel["heliostat_id"].astype(str), sel["model"].astype(str)))


def sweep_weight_decays(inp: ReportInputs) -> dict[str, float]:
    """The selected weight decay per heliostat as the sweep wrote it (metrics.json rounds to 4
    decimals: 1e-5 would show 0)."""
    sel = inp.selection
    if sel is None or not {"heliostat_id", "weight_decay"} <= set(sel.columns):
        return {}
    return dict(zip(sel["heliostat_id"].astype(str), sel["weight_decay"].astype(float)))


@dataclass
class _Plan:
    """What the per-heliostat figure plans share: the inputs grouped by heliostat."""

    inp: ReportInputs
    helios: dict                # metrics.json's heliostats
    meas: dict                  # heliostat -> its measurements
    split: dict                 # heliostat -> its split.parquet rows
    preds: dict                 # heliostat -> its predictions
    sweep: dict                 # heliostat -> its sweep.parquet rows
    choice: dict                # heliostat -> the sweep's choice (sweep_choices)

    @property
    def hids(self) -> list[str]:
        return list(self.helios)

    @property
    def empty_sweep(self):
        return self.inp.sweep.iloc[:0] if self.inp.sweep is not None else None

    @property
    def sweep_hint(self) -> str:
        return self.inp.run_hint("sweep.parquet")

    def label(self, hid: str, model: str | None) -> str | None:
        """How a caption names ``model`` of ``hid`` (the selected model with the sweep's choice)."""
        if model == "selected" and hid in self.choice:
            return f"the selected model ({self.choice[hid]})"
        return model


def heliostat_figure_plan(inp: ReportInputs, metrics: dict, finals: dict,
                          scope: FigureScope | None = None) -> list[tuple]:
    """The per-heliostat figures (paper 000 figs. 6, 7, 9a, error over time) and fig. 8, in the
    order of the report, as blocks: ``("h3", text)``, ``("note", text)``, ``("hnote", text,
    heliostat)`` (a note for that heliostat's page only) and ``("task", FigureTask)`` (a task
    whose figure cannot be drawn becomes a note naming why). ``scope``: whose figures are
    drawn (default every heliostat's); the others get a note on their page instead, and only
    the drawn heliostats' rows are grouped."""
    helios = metrics["heliostats"]
    notes: list[tuple] = []
    if scope is not None and not scope.every:
        helios = {hid: h for hid, h in helios.items() if scope.covers(hid)}
        notes = [("note", scope.field_note())] + [
            ("hnote", scope.page_note(hid), hid) for hid in metrics["heliostats"]
            if not scope.covers(hid)]
    plan = _Plan(inp, helios, *(by_heliostat(_rows_of(df, helios)) for df in (
        inp.measurements, inp.split, inp.predictions, inp.sweep)), sweep_choices(inp))
    return (notes + _training_size_plan(plan) + _sky_map_plan(plan, finals)
            + _weight_decay_plan(plan) + _gp_map_plan(plan) + _hybrid_vs_coarse_plan(plan)
            + _regime_plan(inp, plan.hids, plan.meas, plan.preds)
            + _error_over_time_plan(plan, finals))


def _rows_of(df: pd.DataFrame | None, heliostats: dict) -> pd.DataFrame | None:
    """``df``'s rows of ``heliostats`` (all of them when it has no other)."""
    if df is None:
        return None
    ids = df["heliostat_id"].astype(str)
    keep = ids.isin(set(heliostats))
    return df if keep.all() else df[keep.to_numpy()]


def _training_size_plan(plan: _Plan) -> list[tuple]:
    """Paper 000 fig. 6 per heliostat of the sweep's training-size study."""
    out: list[tuple] = [("h3", "Error against training size (paper 000, fig. 6)")]
    if plan.inp.sweep is None:
        return out + [("note", f"Omitted: needs sweep.parquet; run {plan.sweep_hint}.")]
    outside = []
    for hid in plan.hids:
        sel = plan.helios[hid]["selection"]
        coarse = plan.helios[hid]["models"].get(sel["coarse_preset"] or "")
        level = coarse["splits"].get("test", {}).get("mean_error_mrad") if coarse else None
        g = plan.sweep.get(hid)
        if g is not None and "n_train" in g.columns and g["n_train"].nunique() < 2:
            # not in the training-size study: said once below, and on its own page
            outside.append(hid)
            out.append(("hnote", f"{hid} is not in the sweep's training-size study "
                                 "(`heliocal sweep --study N` samples N heliostats): no "
                                 "training-size figure.", hid))
            continue
        out.append(("task", FigureTask(
            "training_size", f"training_size_{hid}.png",
            f"{hid}: mean test error against the number of training measurements per model "
            "(weight decay chosen on validation; band: spread over seeds). Below: mean "
            "distance in sun position from the test set to the training set.", hid,
            {"sweep": plan.sweep.get(hid, plan.empty_sweep), "level": level,
             "label": f"coarse {sel['coarse_preset']}"})))
    if outside:
        out.append(("note", f"{len(outside)} of {len(plan.hids)} heliostats are not in the "
                            "sweep's training-size study (`heliocal sweep --study N` samples "
                            "N heliostats): no training-size figure for them."))
    return out


def _sky_map_plan(plan: _Plan, finals: dict) -> list[tuple]:
    """Paper 000 fig. 7 per heliostat: its measurements on the sky, errors as circles."""
    out: list[tuple] = [("h3", "Sky map (paper 000, fig. 7)")]
    for hid in plan.hids:
        model = finals.get(hid, {}).get("model")
        cap = (f"{hid}: measurements over sun azimuth and elevation; dots are training points. "
               f"Validation and test points are circles whose radius grows linearly with the "
               f"error of {plan.label(hid, model)} ({SKY_POINTS_PER_MRAD:g} pt per mrad); the "
               "grey ring is 1 mrad.")
        if model is None:
            cap = f"{hid}: measurements over sun azimuth and elevation (no predictions yet)."
        out.append(("task", FigureTask(
            "sky_map", f"sky_map_{hid}.png", cap, hid,
            {"measurements": plan.meas[hid], "split": plan.split.get(hid),
             "predictions": plan.preds.get(hid), "model": model,
             "label": plan.label(hid, model)})))
    return out


def _weight_decay_plan(plan: _Plan) -> list[tuple]:
    """Paper 000 fig. 9a per heliostat: errors against weight decay at the full size."""
    out: list[tuple] = [("h3", "Error against weight decay (paper 000, fig. 9a)")]
    if plan.inp.sweep is None:
        return out + [("note", f"Omitted: needs sweep.parquet; run {plan.sweep_hint}.")]
    chosen_wd = sweep_weight_decays(plan.inp)
    for hid in plan.hids:
        h = plan.helios[hid]
        sel = h["selection"]
        coarse = h["models"].get(sel["coarse_preset"] or "", {}).get("splits", {})
        cval, ctest = sel["coarse_val_error_mrad"], sel["coarse_test_error_mrad"]
        cval = cval if cval is not None else coarse.get("validation", {}).get("mean_error_mrad")
        ctest = ctest if ctest is not None else coarse.get("test", {}).get("mean_error_mrad")
        out.append(("task", FigureTask(
            "weight_decay", f"weight_decay_{hid}.png",
            f"{hid}: mean validation and test error against weight decay at the largest "
            "training size (band: spread over seeds); dashed lines: the selected coarse "
            "model's validation and test error; dotted: the selected weight decay.", hid,
            {"sweep": plan.sweep.get(hid, plan.empty_sweep),
             "model": _swept_model(plan.choice.get(hid, sel["model"]) if sel["model"] == "selected"
                                   else sel["model"]), "cval": cval,
             "ctest": ctest, "weight_decay": chosen_wd.get(hid, sel["weight_decay"])})))
    return out


def _swept_model(model: str | None) -> str | None:
    """The model whose weight decays the figure shows: the chosen one where it has them (a
    hybrid), else the figure's default (None: the hybrids'), e.g. for a GP or coarse choice."""
    return model if model is not None and model.startswith("hybrid") else None


def _gp_map_plan(plan: _Plan) -> list[tuple]:
    """The GP correction over the sky of every heliostat whose model is a GP (issue 35)."""
    maps = {hid: plan.inp.gp_maps[hid] for hid in plan.hids if hid in plan.inp.gp_maps}
    if not maps:
        return []
    out: list[tuple] = [("h3", "GP correction of the coarse model")]
    for hid, grid in maps.items():
        out.append(("task", FigureTask(
            "gp_correction", f"gp_correction_{hid}.png",
            f"{hid}: the Gaussian-process correction of the coarse model's pointing [mrad] over "
            f"sun azimuth and elevation at {grid['when']}, as aim applies it (faded with the "
            "distance to the training rows, black dots; dashed: fade 1/2); arrows: its "
            "direction on the mirror (horizontal, vertical).", hid, {"grid": grid})))
    return out


def _hybrid_vs_coarse_plan(plan: _Plan) -> list[tuple]:
    """Paper 000 fig. 8: the selected hybrid against the selected coarse preset, per heliostat
    (a field page scatter plot instead beyond a few dozen heliostats)."""
    from .figures import hybrid_vs_coarse_table

    out: list[tuple] = [("h3", "Hybrid against coarse (paper 000, fig. 8)")]
    table = hybrid_vs_coarse_table(plan.inp)
    if table is None:
        out.append(("note", "Omitted: needs selection.parquet or hybrid_predictions.parquet; run "
                            f"{plan.inp.run_hint('hybrid_predictions.parquet')} and "
                            f"{plan.sweep_hint}."))
    elif len(table) > 40:
        out.append(("note", f"Per-heliostat bars omitted for {len(table)} heliostats (unreadable "
                            "beyond a few dozen): the field page shows hybrid against coarse "
                            "for every heliostat as one scatter plot."))
    else:
        out.append(("task", FigureTask(
            "hybrid_vs_coarse", "hybrid_vs_coarse.png",
            "Mean validation and test error of the selected hybrid model and the selected coarse "
            "preset per heliostat.", None, {"table": table})))
    return out


def _error_over_time_plan(plan: _Plan, finals: dict) -> list[tuple]:
    """Each heliostat's final model's error per measurement over the date."""
    out: list[tuple] = [("h3", "Error over time")]
    if plan.inp.predictions is None:
        return out + [("note", "Omitted: needs predictions; run "
                               f"{plan.inp.run_hint('coarse_predictions.parquet')}.")]
    for hid in plan.hids:
        f = finals.get(hid, {})
        if f.get("model") is None or hid not in plan.preds:
            continue
        out.append(("task", FigureTask(
            "error_over_time", f"error_over_time_{hid}.png",
            f"{hid}: error of {plan.label(hid, f['model'])} per measurement over the date, "
            "coloured by split, with a centred 30-day rolling median (drift and seasonal "
            "patterns).", hid,
            {"measurements": plan.meas[hid], "predictions": plan.preds[hid], "model": f["model"],
             "coarse": f.get("coarse_preset"), "label": plan.label(hid, f["model"])})))
    return out


def _regime_plan(inp: ReportInputs, hids, meas: dict, preds: dict) -> list[tuple]:
    """The field's list of detected changes (regimes.parquet, fit-coarse) and one regime figure
    per heliostat (:func:`heliocal.pipeline.report.regimes.plot_regimes`)."""
    from .regimes import alert_table

    out: list[tuple] = [("h3", "Regimes, episodes and outliers")]
    if inp.regimes is None or inp.predictions is None:
        out.append(("note", "Omitted: needs regimes.parquet; run "
                            f"{inp.run_hint('regimes.parquet')}."))
        return out
    headers, rows = alert_table(inp.regimes)
    if rows:
        out.append(("p", "Alert list: every detected change and renovation, newest first (step: "
                         "distance of the median residuals before and after; evidence > 1: the "
                         "change-point "
                         "test's penalty is exceeded; error: the selected coarse model's mean "
                         "error on the segment)."))
        out.append(("table", headers, rows))
    else:
        out.append(("p", "No change detected: every heliostat is in one regime."))
    regimes = by_heliostat(inp.regimes)
    for hid in hids:
        if hid not in preds or hid not in regimes:
            continue
        out.append(("task", FigureTask(
            "regimes", f"regimes_{hid}.png",
            f"{hid}: error of the selected coarse model over time; shaded: regimes "
            "(alternating), red: episodes; vertical lines: breaks (dashed: renovation); red "
            "circles: outliers (flagged, kept).", hid,
            {"measurements": meas[hid], "predictions": preds[hid], "regimes": regimes[hid]})))
    return out
