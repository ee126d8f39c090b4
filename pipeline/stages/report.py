"""``report``: a plant's report of a work directory, its figures and ``metrics.json``.

The report works with whatever artifacts exist. ``measurements.parquet`` (from ``ingest``) is the
only required input; each later artifact adds what it can:

========================== ==================================================================
artifact                   adds
========================== ==================================================================
split.parquet              split counts, training points on the sky map, test-to-train distance
coarse_params.parquet      the model aim uses (field map, error distribution, worst heliostats),
                           the fitted coarse parameters with standard errors
coarse_predictions.parquet error tables, error circles on the sky map, error over time
hybrid_predictions.parquet the hybrid models in every table and figure
sweep.parquet              error against training size (paper 000, fig. 6) and against weight
                           decay (fig. 9a), per heliostat and across the field
selection.parquet          the sweep's choice per heliostat, hybrid against coarse (fig. 8)
========================== ==================================================================

A figure whose inputs are absent is omitted, and the report says which stage to run for it.

Outputs in ``DIR/report/`` (one stage transaction, see
:mod:`heliocal.pipeline.artifacts.transaction`):

* ``index.html``: the field overview (summary numbers, field map, error distribution, the 20
  heliostats that need attention first); small at any field size;
* ``heliostats/<id>.html``: one page per heliostat; ``heliostats.html``: all of them, sortable;
* ``field.html``: paper 000's figures as field aggregates;
* ``field_prior.html``: the field prior and how much each heliostat's fit leans on it, when
  fit-coarse fitted under one (:mod:`heliocal.pipeline.report.prior_page`);
* ``details.html``: every table of every model and split (the lab notebook), figures linked;
* ``report.md`` (the same content as details.html), ``figures/*.png`` and ``metrics.json``
  (schema: ``docs/metrics_schema.json``; sorted keys and rounded floats, so two runs of the
  same pipeline give the same numbers and :mod:`heliocal.pipeline.report.regression` can diff
  them).

The error per heliostat on the overview is the one ``aim`` uses (:func:`.aim_choice.aim_models`, which ``aim`` uses).
Figures are drawn one per task (matplotlib's Agg renderer, no pyplot state) in ``workers``
processes (``runtime.parallel.map_tasks``), in this process when there are few.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

from ..artifacts.manifests import current_transaction
from ..artifacts.modelfiles import model_stage, read_model_config
from ..artifacts.unchanged import INCREMENTAL_KEY, carry_over_unchanged
from ..artifacts.paths import artifact_path, safe_child, safe_name
from ..artifacts.schemas import COARSE_PARAMS
from ..artifacts.store import read_provenance
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..errors import SchemaError, check_choice, check_int
from ..models.gp_map import stored_correction_map
from ..report.field import (ALERT_MRAD, ERROR_LINES_MRAD, field_summary, field_table, tower_en_m,
                            svg_field_map, worst)
from ..report.floor import MeasurementFloor, find_measurement_floor
from ..report.field_figures import comparison_table, training_size_frame, weight_decay_frame
from ..report.inputs import load_inputs
from ..report.metrics import compute_metrics, metrics_json
from ..report.prior_page import (PRIOR_PAGE, prior_groups, prior_page_html, prior_page_tasks,
                                 training_size_note)
from ..report.pages import (build_report, figure_tasks, parameter_tables, render_html,
                            render_markdown, resolve_figures)
from ..report.forward import svg_next_day
from ..report.render import FigureTask, ReportFigure, by_heliostat
from ..report.regimes import regime_alerts
from ..report.scope import figure_scope, study_heliostats
from ..report.site import (SORT_JS, field_page_blocks, heliostat_html, heliostats_list_html,
                           index_html, nav_html, why_text)
from ..runtime.parallel import default_workers
from ..runtime.process_state import restores_process_state
from ..vocabulary import ReportFigures
from .report_figures import drawn_or_kept
from .rerun import report_kept_summary, report_options, report_state

__all__ = [
    "measurement_floor",
    "run_report",
]

log = logging.getLogger("heliocal.report")


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
@locks_workdir("report")
@restores_process_state
def run_report(workdir: str | Path, out_dir: str | Path | None = None, *,
               workers: int | None = None, alert_mrad: float = ALERT_MRAD,
               floor_mrad: float | None = None, incremental: bool = False,
               figures: str = "auto", figures_for: Sequence[str] = ()) -> dict:
    """The ``report`` stage: write the pages, report.md, figures/*.png and metrics.json.

    Parameters
    ----------
    workdir : the work directory (needs at least measurements.parquet).
    out_dir : where to write (default ``workdir/report``). The files are one transaction on
        ``out_dir`` (manifest ``out_dir/report.manifest.json``): a report is replaced whole or not
        at all. Files of an earlier report that this one does not write (figures, heliostat
        pages) are removed so the folder matches the report.
    workers : processes drawing the figures (default: the machine's cores; 1 draws here).
    alert_mrad : a heliostat whose model has a mean test error above it is on alert [mrad].
    floor_mrad : the measurement floor drawn on the error distribution [mrad]; default: the
        simulator's noise floor when the sources are a simulated field (ground_truth.json next
        to them), else none.
    incremental : keep the previous report whole when nothing it depends on changed (the
        options, the code, the committed artifacts of the work directory, the measurement floor,
        the git revision and matplotlib version: :func:`.rerun.report_state`); else take each
        figure whose task (its data, caption and the code) is the one the previous report
        recorded from that report instead of drawing it again (:mod:`.report_figures`), and
        compute pages, tables and metrics again.
    figures : whose own figures are drawn: ``all``, ``attention`` (the heliostats on alert,
        listed first on the overview or in the sweep's training-size study) or ``auto``
        (default: ``all`` up to 100 heliostats, else ``attention``); see
        :mod:`heliocal.pipeline.report.scope`.
    figures_for : heliostats (ids, or one id) whose figures are drawn as well, whatever
        ``figures`` says.

    Returns
    -------
    A summary: paths written, figures, notes, the field's numbers, per heliostat the final
    model's mean test error, and how many heliostats have their own figures.
    """
    workers = default_workers() if workers is None else check_int(workers, "workers", "report", 1)
    workdir = Path(workdir)
    out = Path(out_dir) if out_dir is not None else workdir / "report"
    figures = check_choice(str(figures), "figures", "run_report", ReportFigures.values())
    figures_for = [figures_for] if isinstance(figures_for, str) else list(figures_for)
    summary = _write_report(workdir, out, workers, float(alert_mrad), floor_mrad,
                            bool(incremental), (str(figures), tuple(map(str, figures_for))))
    if summary.get("incremental", {}).get("unchanged"):
        return summary  # the previous report is kept whole: nothing to tidy
    keep = {Path(f).name for f in summary["figures"]}
    pages = {Path(p).name for p in summary["heliostat_pages"]}
    for folder, kept, pattern in ((out / "figures", keep, "*.png"),
                                  (out / "heliostats", pages, "*.html")):
        if folder.is_dir():
            for old in folder.glob(pattern):
                if old.name not in kept:
                    old.unlink()
    return summary


def measurement_floor(workdir: Path, floor_mrad: float | None) -> tuple[float | None, str]:
    """(floor [mrad] or None, where it comes from or why there is none): ``floor_mrad`` when
    given, else the median ``noise_floor_mrad`` of the heliostats in the ``ground_truth.json`` of
    a simulated field the sources came from (``heliocal simulate`` writes it beside them); a
    malformed one is logged once as a warning and named instead of a source."""
    floor = _measurement_floor(workdir, floor_mrad)
    return floor.value_mrad, floor.source or "; ".join(floor.problems)


def _measurement_floor(workdir: Path, floor_mrad: float | None) -> MeasurementFloor:
    floor = find_measurement_floor(workdir, floor_mrad)
    for problem in floor.problems:
        log.warning("%s", problem)
    return floor


@stage_transaction("report", root=lambda a: a["out"], consistent_inputs=False)
def _write_report(workdir: Path, out: Path, workers: int, alert_mrad: float,
                  floor_mrad: float | None, incremental: bool,
                  figures: tuple[str, tuple[str, ...]]) -> dict:
    from .aim_choice import aim_models  # the one answer to "which model does aim use"

    txn = current_transaction(out, "report")
    txn.options = report_options(workdir, out, alert_mrad, floor_mrad, *figures)
    measured_floor = _measurement_floor(workdir, floor_mrad)
    state = report_state(workdir, measured_floor)
    if incremental and carry_over_unchanged(txn, txn.options, workdir=workdir, state=state):
        return report_kept_summary(workdir, out, txn.previous_files())
    inp = load_inputs(workdir)
    choices = aim_models(workdir)
    metrics = compute_metrics(inp)
    helios = metrics["heliostats"]
    table = field_table(inp, metrics, choices, alert_mrad=alert_mrad,
                        extra_alerts=regime_alerts(inp.regimes))
    first = worst(table)    # the overview's table; their figures are drawn at any field size
    scope = figure_scope(table, figures[0], figures[1], first["heliostat_id"],
                         study_heliostats(inp.sweep), str(workdir))
    inp.gp_maps = _gp_maps(workdir, {h: c for h, c in choices.items() if scope.covers(h)})
    blocks = build_report(inp, metrics, scope)
    summary = field_summary(table, alert_mrad=alert_mrad)
    floor, floor_source = measured_floor.value_mrad, measured_floor.source

    # field figures
    wd_frame = weight_decay_frame(inp.sweep)
    cdf_task = _cdf_task(table, floor, floor_source)
    ts_frame = training_size_frame(inp.sweep)
    field_plan = _field_plan(inp, wd_frame, ts_frame, comparison_table(wd_frame, inp.selection))
    groups = _prior_groups(inp)
    prior_tasks = prior_page_tasks(groups, inp.sweep)
    nav_pages = ((PRIOR_PAGE, "Field prior"),) if groups else ()
    tasks = [cdf_task] + figure_tasks(blocks) + figure_tasks(field_plan) + prior_tasks
    drawn, counts = drawn_or_kept(txn, out, tasks, workers, incremental)
    txn.extra[INCREMENTAL_KEY]["state"] = state  # what a next --incremental run compares
    blocks = resolve_figures(blocks, drawn)
    field_blocks = resolve_figures(field_plan, drawn)
    figs = [b[1] for b in blocks + field_blocks if b[0] == "figure"]
    figs += [ReportFigure(t.filename, t.caption, drawn[t.filename][0]) for t in prior_tasks
             if drawn[t.filename][0] is not None]
    cdf_png, cdf_why = drawn[cdf_task.filename]
    cdf = ReportFigure(cdf_task.filename, cdf_task.caption, cdf_png) if cdf_png else None
    if cdf is not None:
        figs.append(cdf)
    for f in figs:
        txn.write_bytes(f"figures/{safe_name(f.filename)}", f.png)

    title = f"heliocal report: {workdir}"
    notes = [b[1] for b in blocks if b[0] == "note"]
    floor_text = (f"Measurement floor: {floor:.3f} mrad ({floor_source})." if floor is not None
                  else "Measurement floor: unknown (give `heliocal report --floor-mrad F`).")
    subtitle = (f"heliocal {metrics['heliocal_version']}, git {metrics['git_revision']}; "
                f"{metrics['data']['n_measurements']} measurements from "
                f"{metrics['data']['first_timestamp'] or '?'} to "
                f"{metrics['data']['last_timestamp'] or '?'}.")
    run_notes = (list(inp.notes) + measured_floor.problems
                 + _plan_page(workdir, txn, title, nav_pages))
    if not choices:
        run_notes.append(f"No model yet: run {inp.run_hint('coarse_params.parquet')} for the "
                         "field map's errors and the worst heliostats.")
    if groups:
        options = read_provenance(artifact_path(workdir, COARSE_PARAMS)).get("options") or {}
        txn.write_bytes(PRIOR_PAGE, prior_page_html(
            title, nav_html(pages=nav_pages), SORT_JS, groups, prior_tasks, drawn, options,
            training_size_note(ts_frame is not None, any(
                t.kind == "prior_training_size" for t in prior_tasks))).encode("utf-8"))
        run_notes.append(f"fit-coarse fitted under a field prior: its prior and how much each "
                         f"heliostat leans on it are on {PRIOR_PAGE}.")
    svg = svg_field_map(table, tower_en_m(inp), alert_mrad=alert_mrad)
    txn.write_bytes("index.html", index_html(
        title, subtitle, summary, table, first, svg, cdf, cdf_why, floor_text,
        run_notes, nav_pages).encode("utf-8"))
    txn.write_bytes("heliostats.html", heliostats_list_html(title, table,
                                                            nav_pages).encode("utf-8"))
    txn.write_bytes("field.html", render_html(field_page_blocks(field_blocks), embed=False,
                                              nav=nav_html(pages=nav_pages)).encode("utf-8"))
    txn.write_bytes("details.html", render_html(blocks, embed=False,
                                                nav=nav_html(pages=nav_pages)).encode("utf-8"))
    txn.write_bytes("metrics.json", metrics_json(metrics).encode("utf-8"))
    txn.write_bytes("report.md", render_markdown(blocks).encode("utf-8"))
    pages = _heliostat_pages(txn, out, inp, helios, table, blocks, wd_frame, title, nav_pages)

    heliostats = []
    for hid, h in helios.items():
        model = h["selection"]["model"]
        test = h["models"].get(model or "", {}).get("splits", {}).get("test", {})
        heliostats.append({"heliostat_id": hid, "model": model,
                           "test_mean_error_mrad": test.get("mean_error_mrad"),
                           "test_p95_error_mrad": test.get("p95_error_mrad")})
    fig_dir = out / "figures"
    return {"workdir": str(workdir), "report": str(out / "index.html"),
            "markdown": str(out / "report.md"), "metrics": str(out / "metrics.json"),
            "details": str(out / "details.html"), "field": str(out / "field.html"),
            "field_prior": str(out / PRIOR_PAGE) if groups else None,
            "figures": [str(fig_dir / f.filename) for f in figs], "notes": notes,
            "measurement_floor": {"value_mrad": floor, "source": floor_source,
                                  "problems": measured_floor.problems},
            "heliostat_pages": pages, "field_summary": summary, "heliostats": heliostats,
            "figures_drawn": counts["drawn"], "figures_kept": counts["kept"],
            "figure_heliostats": len(scope.heliostats)}


def _cdf_task(table, floor: float | None, floor_source: str) -> FigureTask:
    """The overview's error distribution (``field_error_cdf.png``) as a figure task."""
    return FigureTask("field_cdf", "field_error_cdf.png",
                      "Share of heliostats whose model (the one aim uses) has a mean test error "
                      "below x (dotted: the mean next-day error of the rolling-origin "
                      "evaluation, the coarse preset recalibrated every calibration day); "
                      "dashed: " + ", ".join(f"{x:g}" for x in ERROR_LINES_MRAD)
                      + " mrad" + (f"; grey: the measurement floor ({floor_source})"
                                   if floor is not None else ""), None,
                      {"errors": table["test_error_mrad"].to_numpy(float),
                       "next_day": table.loc[~table["degenerate"].to_numpy(bool),
                                             "next_day_error_mrad"].to_numpy(float),
                       "lines": ERROR_LINES_MRAD, "floor": floor,
                       "floor_source": floor_source})


def _prior_groups(inp) -> list:
    """The field-prior page's groups (none without a field prior), with the model's
    conventions the report package does not import: each fit's deviation from nominal and
    each heliostat's group. The model's code (with it torch, about 1.3 s of a daily update's
    report) is imported only when there is a field prior to show."""
    if inp.field_prior is None or inp.field_prior.empty or inp.coarse_params is None \
            or inp.heliostats is None:
        return []
    from .coarse_prior import heliostat_groups, with_deviations

    return prior_groups(inp.field_prior, with_deviations(inp.coarse_params),
                        heliostat_groups(inp.heliostats))


def _gp_maps(workdir: Path, choices: dict) -> dict[str, dict]:
    """heliostat -> its GP correction on a sky grid, for every heliostat whose model (the one aim
    uses, ``choices`` of :func:`aim_models`) is a GP correction: the map its stage stored in the
    model's configuration (:mod:`heliocal.pipeline.models.gp_map`, read with numpy and json), or
    for a model written before maps were stored, computed from the model as its stage would."""
    gps = {hid: choice["model_dir"] for hid, choice in choices.items()
           if choice.get("model") == "gp" and choice.get("model_dir") is not None}
    out, unstored = {}, {}
    for hid, mode in gps.items():
        grid = _stored_gp_map(workdir, mode, hid)
        if grid is None:
            unstored[hid] = mode
        else:
            out[hid] = grid
    if unstored:
        log.info("computing the GP correction maps of %d heliostats whose models were written "
                 "before maps were stored (rerun their stage to store them): %s", len(unstored),
                 ", ".join(sorted(unstored)))
        out.update(_computed_gp_maps(workdir, unstored))
    return {hid: out[hid] for hid in gps if hid in out}


def _stored_gp_map(workdir: Path, mode: str, heliostat_id: str) -> dict | None:
    """The map stored in a GP model's configuration (``None``: no committed model, or one
    written without a map). The files are checked as ``load_model`` checks them but for the
    weights' tensors, which need torch and which the map does not read."""
    stage, hint = model_stage(workdir, mode)
    found = read_model_config(workdir, stage, mode, heliostat_id, hint=hint)
    if found is None:
        return None
    try:
        return stored_correction_map(found.config)
    except (ValueError, KeyError, TypeError) as exc:
        why = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
        raise SchemaError(f"{found.config_path} holds no readable correction map ({why}); "
                          f"rerun {hint}") from None


def _computed_gp_maps(workdir: Path, modes: dict[str, str]) -> dict[str, dict]:
    """heliostat -> its GP correction map computed from its model (imports the GP's modules:
    torch and scikit-learn, about 1.5 s)."""
    from ..models.gp import GPCorrection
    from ..models.gp_heliostat import correction_grid
    from .aim import load_model

    out = {}
    for hid, mode in modes.items():
        fitted = load_model(workdir, mode, hid)
        if fitted is not None:
            out[hid] = correction_grid(GPCorrection.from_model(*fitted))
    return out


def _field_plan(inp, wd_frame, ts_frame, comp) -> list[tuple]:
    """field.html's blocks: paper 000's figures as field aggregates (weight decay, training size,
    hybrid against coarse), each a figure task or a note naming the stage to run for it."""
    field_plan: list[tuple] = [("h2", "Error against weight decay (paper 000, fig. 9a)")]
    sweep_hint = f"run {inp.run_hint('sweep.parquet')}"
    if wd_frame is None:
        field_plan.append(("note", f"Omitted: needs sweep.parquet with two or more weight decays; "
                                   f"{sweep_hint}."))
    else:
        sel = inp.selection
        levels = {} if sel is None else {
            "coarse_val": float(sel["coarse_val_error_mrad"].median()),
            "coarse_test": float(sel["coarse_test_error_mrad"].median())}
        field_plan.append(("task", FigureTask(
            "field_weight_decay", "field_weight_decay.png",
            "Mean validation and test error (over seeds) against weight decay at each "
            "heliostat's full training size, across the field: line the median over heliostats, "
            "band the 25-75 % range; dashed: the field median of the coarse "
            "model.",
            None, {"frame": wd_frame, **levels})))
    field_plan.append(("h2", "Error against training size (paper 000, fig. 6)"))
    if ts_frame is None:
        field_plan.append(("note", "Omitted: needs the sweep's training-size study (`heliocal "
                                   f"sweep --study N`); {sweep_hint}."))
    else:
        field_plan.append(("task", FigureTask(
            "field_training_size", "field_training_size.png",
            "Mean test error against training size per model (weight decay chosen on validation "
            "per heliostat and size), across the heliostats of the training-size study: line the "
            "median, band the 25-75 % range, at the sizes at least two thirds of "
            "them share (log scale when every error is positive).", None,
            {"frame": ts_frame})))
    field_plan.append(("h2", "Hybrid against coarse (paper 000, fig. 8)"))
    if comp is None:
        field_plan.append(("note", f"Omitted: needs selection.parquet and sweep.parquet; "
                                   f"{sweep_hint}."))
    else:
        field_plan.append(("task", FigureTask(
            "field_comparison", "field_hybrid_vs_coarse.png",
            "Per heliostat: the best hybrid candidate (lowest validation error) against the "
            "coarse model (fit-coarse's selected preset), on validation and test; red: the "
            "sweep selected the hybrid. Below the diagonal the hybrid is better.", None,
            {"table": comp})))
    return field_plan


def _plan_page(workdir: Path, txn, title: str, nav_pages=()) -> list[str]:
    """Write ``plan.html`` when the work directory has a plan (``heliocal plan``); the note
    for the overview that points to it."""
    from ..artifacts.paths import artifact_path
    from ..artifacts.schemas import PLAN
    from ..artifacts.store import artifact_present, read_artifact, read_provenance
    from ..report.plan import plan_html

    if not artifact_present(workdir, PLAN):
        return []
    plan = read_artifact(workdir, PLAN)
    options = read_provenance(artifact_path(workdir, PLAN)).get("options") or {}
    page = plan_html(title, plan, options, nav_html(pages=nav_pages), SORT_JS)
    txn.write_bytes("plan.html", page.encode("utf-8"))
    return ["The measurement plan (`heliocal plan`) is on plan.html."]


def _heliostat_pages(txn, out: Path, inp, helios: dict, table, blocks, wd_frame,
                     title: str, nav_pages=()) -> list[str]:
    """Write ``heliostats/<id>.html`` for every heliostat (``nav_pages``: the optional pages of
    the navigation); return their paths."""
    per: dict[str, list] = {hid: [] for hid in helios}
    for b in blocks:
        if b[0] == "figure" and b[1].heliostat in per:
            per[b[1].heliostat].append(b)
        elif b[0] in ("note", "hnote") and len(b) > 2 and b[2] in per:
            per[b[2]].append(("note", b[1]))
    order = {"sky_map": 0, "error_over_time": 1, "regimes": 2, "weight_decay": 3,
             "training_size": 4}
    best_val = {}
    if wd_frame is not None:
        best_val = wd_frame.groupby("heliostat_id")["val_error_mrad"].min().to_dict()
    params, presets = {}, {}
    cp = inp.coarse_params
    if cp is not None:
        sel = cp[cp["selected"].astype(bool)] if "selected" in cp.columns else cp
        params = parameter_tables(sel)
        if "preset" in sel.columns:
            first = sel.drop_duplicates("heliostat_id")
            presets = dict(zip(first["heliostat_id"].astype(str), first["preset"].astype(str)))
    rows = {r["heliostat_id"]: r for _, r in table.iterrows()}
    rolling = by_heliostat(inp.rolling)
    ids = list(helios)
    written = []
    folder = out / "heliostats"
    for k, hid in enumerate(ids):
        row = rows[hid]
        figs = sorted(per[hid], key=lambda b: order.get(b[2], 9) if b[0] == "figure" else 10)
        prow = params.get(hid)
        if prow is None:
            head = "No coarse fit yet (run `heliocal fit-coarse`)."
        else:
            head = (f"Free parameters of the selected preset {presets.get(hid, '?')}: nominal "
                    "and fitted value with the standard error from the Jacobian at the solution "
                    "('determined: no': the data cannot pin it; the weak prior holds it near "
                    "nominal).")
        mrows = [[model + (" ★" if mm["selected"] else ""), sp, st["n"], st["mean_error_mrad"],
                  st["median_error_mrad"], st["p95_error_mrad"], st["mean_beam_error_mrad"],
                  st["mean_spot_offset_m"]]
                 for model, mm in helios[hid]["models"].items()
                 for sp, st in mm["splits"].items()]
        prev_next = (rows[ids[k - 1]]["page"] if k > 0 else None,
                     rows[ids[k + 1]]["page"] if k + 1 < len(ids) else None)
        bv = best_val.get(hid)
        page = heliostat_html(title, row, helios[hid],
                              why_text(row, helios[hid], None if bv is None else float(bv)),
                              figs, prow, head, mrows, prev_next,
                              svg_next_day(rolling.get(hid)), nav_pages)
        path = safe_child(folder, row["page"])
        # a daily update changes a few heliostats: the other pages stay the files they were
        txn.write_bytes(f"heliostats/{path.name}", page.encode("utf-8"), keep_same=True)
        written.append(str(path))
    return written
