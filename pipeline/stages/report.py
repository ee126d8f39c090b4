"""``report``: figures, tables and ``metrics.json`` of a work directory.

The report works with whatever artifacts exist. ``measurements.parquet`` (from ``ingest``) is the
only required input; each later artifact adds what it can:

========================== ==================================================================
artifact                   adds
========================== ==================================================================
split.parquet              split counts, training points on the sky map, test-to-train distance
coarse_params.parquet      the fitted coarse parameters with standard errors
coarse_predictions.parquet error tables, error circles on the sky map, error over time
hybrid_predictions.parquet the hybrid models in every table and figure
sweep.parquet              error against training size (paper 000, fig. 6) and against weight
                           decay (fig. 9a)
selection.parquet          hybrid against coarse per heliostat (fig. 8), the selection
========================== ==================================================================

A figure whose inputs are absent is omitted, and the report says which stage to run for it.

Outputs in ``DIR/report/`` (one stage transaction, see :mod:`heliocal.pipeline.artifacts.transaction`): ``index.html`` (self-contained, the
figures embedded as base64 PNG), ``report.md`` (the same content, figures linked), ``figures/*.png``
and ``metrics.json`` (schema: ``docs/metrics_schema.json``; sorted keys and rounded floats, so two
runs of the same pipeline give the same numbers and :mod:`heliocal.pipeline.report.regression` can diff
them).

Figures are drawn on :class:`matplotlib.figure.Figure` objects directly (the non-interactive Agg
renderer, no pyplot state), so the report runs headless and in threads.
"""

from __future__ import annotations

from pathlib import Path

from ..artifacts.manifests import current_transaction
from ..artifacts.paths import safe_name
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir
from ..report.inputs import load_inputs
from ..report.metrics import compute_metrics, metrics_json
from ..report.pages import build_report, render_html, render_markdown
from ..runtime.process_state import restores_process_state

__all__ = [
    "run_report",
]


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
@locks_workdir("report")
@restores_process_state
def run_report(workdir: str | Path, out_dir: str | Path | None = None) -> dict:
    """The ``report`` stage: write index.html, report.md, figures/*.png and metrics.json.

    Parameters
    ----------
    workdir : the work directory (needs at least measurements.parquet).
    out_dir : where to write (default ``workdir/report``). The files are one transaction on
        ``out_dir`` (manifest ``out_dir/report.manifest.json``): a report is replaced whole or not
        at all. PNGs of figures no longer produced are removed from ``out_dir/figures`` so the
        folder matches the report.

    Returns
    -------
    A summary: paths written, figures, notes, and per heliostat the final model's mean test error.
    """
    workdir = Path(workdir)
    out = Path(out_dir) if out_dir is not None else workdir / "report"
    summary = _write_report(workdir, out)
    # figures of a report written before reports were transactions (not in any manifest)
    keep = {Path(f).name for f in summary["figures"]}
    if (out / "figures").is_dir():
        for old in (out / "figures").glob("*.png"):
            if old.name not in keep:
                old.unlink()
    return summary


@stage_transaction("report", root=lambda a: a["out"], consistent_inputs=False)
def _write_report(workdir: Path, out: Path) -> dict:
    txn = current_transaction(out, "report")
    inp = load_inputs(workdir)
    metrics = compute_metrics(inp)
    blocks = build_report(inp, metrics)
    figs = [b[1] for b in blocks if b[0] == "figure"]
    fig_dir = out / "figures"
    for f in figs:
        txn.write_bytes(f"figures/{safe_name(f.filename)}", f.png)
    txn.write_bytes("metrics.json", metrics_json(metrics).encode("utf-8"))
    txn.write_bytes("report.md", render_markdown(blocks).encode("utf-8"))
    txn.write_bytes("index.html", render_html(blocks).encode("utf-8"))
    notes = [b[1] for b in blocks if b[0] == "note"]
    heliostats = []
    for hid, h in metrics["heliostats"].items():
        model = h["selection"]["model"]
        test = h["models"].get(model or "", {}).get("splits", {}).get("test", {})
        heliostats.append({"heliostat_id": hid, "model": model,
                           "test_mean_error_mrad": test.get("mean_error_mrad"),
                           "test_p95_error_mrad": test.get("p95_error_mrad")})
    return {"workdir": str(workdir), "report": str(out / "index.html"),
            "markdown": str(out / "report.md"), "metrics": str(out / "metrics.json"),
            "figures": [str(fig_dir / f.filename) for f in figs], "notes": notes,
            "heliostats": heliostats}
