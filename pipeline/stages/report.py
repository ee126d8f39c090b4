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

import base64
import html
import io
import json
import logging
import math
import re
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import pandas as pd

from .. import __version__
from ..artifacts.store import (artifact_present, committed_fingerprint, read_artifact,
                               recorded_inputs)
from ..artifacts.provenance import git_revision
from ..artifacts.paths import safe_name
from ..errors import SchemaError, StageInputError
from ..artifacts.schemas import MEASUREMENTS, REJECTION_REASONS, all_schemas
from ..artifacts.manifests import committed_entry, current_transaction
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir

__all__ = [
    "METRICS_SCHEMA_VERSION",
    "SPLIT_ORDER",
    "ReportInputs",
    "load_inputs",
    "error_statistics",
    "compute_metrics",
    "metrics_json",
    "build_report",
    "run_report",
    "plot_training_size",
    "plot_sky_map",
    "plot_weight_decay",
    "plot_hybrid_vs_coarse",
    "plot_error_over_time",
]

log = logging.getLogger("heliocal.report")

#: Version of metrics.json's layout (``docs/metrics_schema.json``); bump when a key changes meaning.
METRICS_SCHEMA_VERSION = 1
#: Order of the splits in tables and metrics.json.
SPLIT_ORDER = ("train", "validation", "test", "unused")
#: Decimals of every float in metrics.json (1e-4 mrad = 0.1 microradian).
DECIMALS = 4
#: Radius of an error circle on the sky map per mrad of error [pt]; larger errors are clipped.
SKY_POINTS_PER_MRAD = 4.0
SKY_CLIP_MRAD = 6.0

_OPTIONAL = ("split.parquet", "coarse_params.parquet", "coarse_predictions.parquet",
             "hybrid_predictions.parquet", "sweep.parquet", "selection.parquet",
             "selected_predictions.parquet")
#: Stage that writes each optional artifact (used when its schema is not importable yet).
_PRODUCERS = {"split.parquet": "split-knn", "coarse_params.parquet": "fit-coarse",
              "coarse_predictions.parquet": "fit-coarse", "hybrid_predictions.parquet": "fit-hybrid",
              "sweep.parquet": "sweep", "selection.parquet": "sweep",
              "selected_predictions.parquet": "sweep"}
_HYBRID_ORDER = ("hybrid", "nn-only", "pretrained-nn")
_COARSE_ORDER = ("nominal", "static-6", "stone-8", "static-14", "static-20", "static-28")
_SPLIT_COLORS = {"train": "0.55", "validation": "tab:blue", "test": "tab:orange", "unused": "0.8"}


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
@dataclass
class ReportInputs:
    """The artifacts of one work directory (``None`` where absent)."""

    workdir: Path
    measurements: pd.DataFrame
    heliostats: pd.DataFrame | None = None
    rejected: pd.DataFrame | None = None
    split: pd.DataFrame | None = None
    coarse_params: pd.DataFrame | None = None
    predictions: pd.DataFrame | None = None  # coarse and hybrid predictions, column `source`
    sweep: pd.DataFrame | None = None
    selection: pd.DataFrame | None = None
    paths: dict[str, Path] = field(default_factory=dict)  # filename -> path of every input read
    notes: list[str] = field(default_factory=list)  # staleness and similar warnings

    def producer(self, filename: str) -> str:
        schema = _schema_for(filename)
        return schema.producer if schema is not None else _PRODUCERS.get(filename, "?")

    def run_hint(self, filename: str) -> str:
        return f"`heliocal {self.producer(filename)} --workdir {self.workdir}`"


def _schema_for(filename: str):
    for schema in all_schemas():
        if schema.filename == filename:
            return schema
    return None


def _read(workdir: Path, filename: str) -> pd.DataFrame | None:
    """An artifact through its declared schema (``None`` when its stage has not written it). A file
    that exists but that no complete run of its stage committed is refused, as every reader does."""
    path = workdir / filename
    schema = _schema_for(filename)
    if schema is None:  # pragma: no cover - every artifact the report reads has a schema
        raise SchemaError(f"{path}: no declared schema (this is a bug in heliocal; please report it)")
    if not artifact_present(workdir, schema):
        return None
    return read_artifact(workdir, schema)


def _stale_notes(workdir: Path, filenames: Iterable[str]) -> list[str]:
    """One note per artifact whose recorded input fingerprints differ from the inputs' committed
    ones (nothing is hashed: the manifests hold the fingerprints)."""
    notes = []
    by_name = {s.name: s for s in all_schemas()}
    for name in filenames:
        schema = _schema_for(name)
        if schema is None:
            continue
        for label, fp in sorted(recorded_inputs(workdir, schema).items()):
            up = by_name.get(label)
            if up is None or fp is None:
                continue
            current = committed_fingerprint(workdir, up)
            if current is not None and current != fp:
                notes.append(f"{name} is stale: {up.filename} changed after it was written (rerun "
                             f"`heliocal {_PRODUCERS.get(name, '?')}`).")
    return notes


def load_inputs(workdir: str | Path) -> ReportInputs:
    """Read every artifact the report can use from ``workdir``.

    Raises
    ------
    StageInputError : ``measurements.parquet`` is missing (run ``ingest`` first).
    SchemaError : an artifact that exists cannot be read.
    """
    workdir = Path(workdir)
    if not artifact_present(workdir, MEASUREMENTS):
        raise StageInputError(f"{workdir / MEASUREMENTS.filename} is missing: run `heliocal ingest "
                              f"SOURCE... --workdir {workdir}` first")
    inp = ReportInputs(workdir=workdir, measurements=_read(workdir, MEASUREMENTS.filename))
    inp.paths[MEASUREMENTS.filename] = workdir / MEASUREMENTS.filename
    for name in ("heliostats.parquet", "rejected.parquet") + _OPTIONAL:
        df = _read(workdir, name)
        if df is None:
            continue
        inp.paths[name] = workdir / name
        if name == "heliostats.parquet":
            inp.heliostats = df
        elif name == "rejected.parquet":
            inp.rejected = df
        elif name == "split.parquet":
            inp.split = df
        elif name == "coarse_params.parquet":
            inp.coarse_params = df
        elif name == "sweep.parquet":
            inp.sweep = df
        elif name == "selection.parquet":
            inp.selection = df
    preds = []
    for name in ("coarse_predictions.parquet", "hybrid_predictions.parquet",
                 "selected_predictions.parquet"):
        df = _read(workdir, name)
        if df is not None:
            missing = [c for c in ("heliostat_id", "measurement_id", "model", "split", "error_mrad")
                       if c not in df.columns]
            if missing:
                raise SchemaError(f"{workdir / name} lacks columns {missing}: rerun "
                                  f"{inp.run_hint(name)}")
            inp.paths[name] = workdir / name
            preds.append(df.assign(source=name.removesuffix(".parquet")))
    if preds:
        p = pd.concat(preds, ignore_index=True)
        for col in ("heliostat_id", "measurement_id", "model", "split"):
            p[col] = p[col].astype(str)
        if "selected" not in p.columns:
            p["selected"] = False
        p["selected"] = p["selected"].fillna(False).astype(bool)
        inp.predictions = p
    for col in ("heliostat_id", "measurement_id"):
        inp.measurements[col] = inp.measurements[col].astype(str)
    if inp.split is not None:
        for col in ("heliostat_id", "measurement_id", "split"):
            inp.split[col] = inp.split[col].astype(str)
    inp.notes += _stale_notes(workdir, [n for n in inp.paths if n != MEASUREMENTS.filename])
    return inp


# ------------------------------------------------------------------------------------------------
# numbers
# ------------------------------------------------------------------------------------------------
def _r(x) -> float | None:
    """Round for metrics.json; NaN and infinities become null."""
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x):
        return None
    v = round(x, DECIMALS)
    return 0.0 if v == 0 else v


def _iso(ts) -> str | None:
    if ts is None or pd.isna(ts):
        return None
    return pd.Timestamp(ts).tz_convert("UTC").strftime("%Y-%m-%dT%H:%M:%SZ")


def error_statistics(rows: pd.DataFrame) -> dict:
    """n, mean, median and 95th percentile of ``error_mrad``, mean beam error and spot offset.

    NaN errors count in ``n`` but not in the statistics (``n_finite`` says how many did); the
    percentile is numpy's default (linear interpolation).
    """
    err = rows["error_mrad"].to_numpy(float)
    ok = np.isfinite(err)
    out = {"n": int(len(rows)), "n_finite": int(ok.sum()),
           "mean_error_mrad": None, "median_error_mrad": None, "p95_error_mrad": None,
           "mean_beam_error_mrad": None, "mean_spot_offset_m": None}
    if ok.any():
        e = err[ok]
        out.update(mean_error_mrad=_r(e.mean()), median_error_mrad=_r(np.median(e)),
                   p95_error_mrad=_r(np.percentile(e, 95)))
    for col, key in (("beam_error_mrad", "mean_beam_error_mrad"),
                     ("spot_offset_m", "mean_spot_offset_m")):
        if col in rows.columns:
            v = rows[col].to_numpy(float)
            v = v[np.isfinite(v)]
            if len(v):
                out[key] = _r(v.mean())
    return out


def _split_sort_key(s: str) -> tuple:
    return (SPLIT_ORDER.index(s) if s in SPLIT_ORDER else len(SPLIT_ORDER), s)


def _model_sort_key(m: str) -> tuple:
    if m in _COARSE_ORDER:
        return (0, _COARSE_ORDER.index(m), m)
    if m in _HYBRID_ORDER:
        return (2, _HYBRID_ORDER.index(m), m)
    return (1, 0, m)


def _col(df: pd.DataFrame | None, split: str, stat: str = "mean") -> str | None:
    """Find a sweep/selection column of ``split``'s error by name, whatever its exact spelling.

    ``split`` is train, validation (also matches ``val``) or test; ``stat`` mean or median. For
    example ``test_error_mrad``, ``test_error_mrad_mean``, ``mean_test_error_mrad`` and
    ``val_error_median_mrad`` are all found.
    """
    if df is None:
        return None
    token = r"(val|validation)" if split == "validation" else split
    pattern = re.compile(rf"(^|_)({token})(_|$)")
    found = []
    for c in df.columns:
        name = str(c).lower()
        if "coarse" in name or "error" not in name or not pattern.search(name):
            continue
        is_median = "median" in name
        if (stat == "median") == is_median:
            found.append(str(c))
    return min(found, key=len) if found else None


def _first_col(df: pd.DataFrame | None, *names: str) -> str | None:
    if df is None:
        return None
    for n in names:
        if n in df.columns:
            return n
    return None


def _final_models(inp: ReportInputs) -> dict[str, dict]:
    """Per heliostat: the selected coarse preset and the final model (hybrid where selected)."""
    out: dict[str, dict] = {}
    p = inp.predictions
    if p is not None:
        for hid, g in p[p["selected"]].groupby("heliostat_id", sort=True):
            coarse = g[g["source"] == "coarse_predictions"]["model"].unique()
            hybrid = g[g["source"] == "hybrid_predictions"]["model"].unique()
            chosen = g[g["source"] == "selected_predictions"]["model"].unique()
            out[hid] = {"coarse_preset": str(coarse[0]) if len(coarse) else None,
                        "model": str(chosen[0]) if len(chosen) else
                        str(hybrid[0]) if len(hybrid) else
                        (str(coarse[0]) if len(coarse) else None)}
    sel = inp.selection
    if sel is not None and "heliostat_id" in sel.columns:
        for _, row in sel.iterrows():
            hid = str(row["heliostat_id"])
            entry = out.setdefault(hid, {"coarse_preset": None, "model": None})
            if "model" in sel.columns and pd.notna(row["model"]) and entry["model"] != "selected":
                # without the sweep's per-measurement predictions: the coarse choice is the
                # selected preset's rows
                entry["model"] = (entry["coarse_preset"] or "coarse") if row["model"] == "coarse" \
                    else str(row["model"])
            for key in ("weight_decay", "val_error_mrad", "test_error_mrad",
                        "coarse_val_error_mrad", "coarse_test_error_mrad"):
                if key in sel.columns:
                    entry[key] = row[key]
    return out


def compute_metrics(inp: ReportInputs) -> dict:
    """The content of metrics.json (see ``docs/metrics_schema.json``)."""
    m = inp.measurements
    ts = pd.to_datetime(m["timestamp"], utc=True) if "timestamp" in m.columns else pd.Series(
        pd.NaT, index=m.index, dtype="datetime64[ns, UTC]")
    rej = inp.rejected if inp.rejected is not None else pd.DataFrame(columns=["reason"])
    hids = sorted(set(m["heliostat_id"]))
    finals = _final_models(inp)
    data = {
        "n_heliostats": len(hids),
        "n_measurements": int(len(m)),
        "n_rejected": int(len(rej)),
        "rejected_by_reason": {str(k): int(v) for k, v in
                               rej["reason"].value_counts().sort_index().items()},
        "first_timestamp": _iso(ts.min()) if ts.notna().any() else None,
        "last_timestamp": _iso(ts.max()) if ts.notna().any() else None,
        "n_missing_timestamp": int(ts.isna().sum()),
        "artifacts": sorted(inp.paths),
    }
    helios = {}
    for hid in hids:
        rows = m["heliostat_id"] == hid
        t = ts[rows]
        h: dict[str, Any] = {
            "n_measurements": int(rows.sum()),
            "first_timestamp": _iso(t.min()) if t.notna().any() else None,
            "last_timestamp": _iso(t.max()) if t.notna().any() else None,
            "split_counts": {},
            "test_train_distance_deg": None,
            "selection": {"coarse_preset": None, "model": None, "weight_decay": None,
                          "val_error_mrad": None, "test_error_mrad": None,
                          "coarse_val_error_mrad": None, "coarse_test_error_mrad": None},
            "models": {},
        }
        if inp.split is not None:
            s = inp.split[inp.split["heliostat_id"] == hid]
            counts = s["split"].value_counts()
            h["split_counts"] = {k: int(counts[k]) for k in sorted(counts.index, key=_split_sort_key)}
            test = s[s["split"] == "test"]
            if len(test) and "nearest_train_distance_deg" in s.columns:
                h["test_train_distance_deg"] = _r(test["nearest_train_distance_deg"].mean())
        f = finals.get(hid, {})
        for key in h["selection"]:
            v = f.get(key)
            if key in ("coarse_preset", "model"):
                h["selection"][key] = v
            elif v is not None:
                h["selection"][key] = _r(v)
        if inp.predictions is not None:
            p = inp.predictions[inp.predictions["heliostat_id"] == hid]
            for model in sorted(p["model"].unique(), key=_model_sort_key):
                g = p[p["model"] == model]
                h["models"][model] = {
                    "source": str(g["source"].iloc[0]),
                    "selected": bool(g["selected"].any()),
                    "splits": {sp: error_statistics(g[g["split"] == sp])
                               for sp in sorted(g["split"].unique(), key=_split_sort_key)},
                }
        helios[hid] = h
    return {
        "metrics_schema_version": METRICS_SCHEMA_VERSION,
        "heliocal_version": __version__,
        "git_revision": git_revision(),
        "inputs": {name: _committed_sha256(inp.workdir, name) for name in sorted(inp.paths)},
        "data": data,
        "heliostats": helios,
    }


def _committed_sha256(workdir: Path, filename: str) -> str | None:
    """SHA-256 of an input artifact as its run committed it (verified when it was read)."""
    found = committed_entry(workdir, filename)
    return None if found is None else found[1]["sha256"]


def metrics_json(metrics: dict) -> str:
    """metrics.json text: sorted keys, two-space indent, trailing newline (stable diffs)."""
    return json.dumps(metrics, sort_keys=True, indent=2, allow_nan=False) + "\n"


# ------------------------------------------------------------------------------------------------
# figures (matplotlib Figure objects: Agg renderer, no pyplot)
# ------------------------------------------------------------------------------------------------
def _figure(width: float, height: float, nrows: int = 1, ncols: int = 1, **kw):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    return buf.getvalue()


def _best_weight_decay_rows(g: pd.DataFrame, val: str | None, test: str) -> pd.DataFrame:
    """Per n_train: seeds' test errors at the weight decay with the lowest mean validation error."""
    wd = _first_col(g, "weight_decay")
    out = []
    for n, gn in g.groupby("n_train", sort=True):
        if wd is not None and val is not None and gn[wd].nunique() > 1:
            by = gn.groupby(wd)[val].mean()
            gn = gn[gn[wd] == by.idxmin()]
        out.append({"n_train": n, "mean": gn[test].mean(), "min": gn[test].min(),
                    "max": gn[test].max()})
    return pd.DataFrame(out)


def plot_training_size(sweep: pd.DataFrame, heliostat: str,
                       coarse_test_mrad: float | None = None, coarse_label: str = "coarse"):
    """Paper 000, fig. 6: test error against training size per model; test-to-train distance below.

    For each model and training size the weight decay with the lowest validation error (mean over
    seeds) is used; the band spans the seeds. Returns ``(figure, None)`` or ``(None, reason)``.
    """
    test, val = _col(sweep, "test"), _col(sweep, "validation")
    dist = _first_col(sweep, "test_train_distance_deg")
    if test is None or "n_train" not in sweep.columns or "model" not in sweep.columns:
        return None, "sweep.parquet has no n_train, model or test error column"
    g = sweep[sweep["heliostat_id"].astype(str) == heliostat]
    if g["n_train"].nunique() < 2:
        return None, (f"the sweep of {heliostat} has a single training size: it is not in the "
                      "training-size study (`heliocal sweep --study N` samples N heliostats)")
    fig, axes = _figure(7.5, 6.0, 2, 1, sharex=True, height_ratios=(2.2, 1))
    ax, ax2 = axes[0, 0], axes[1, 0]
    for model in sorted(g["model"].astype(str).unique(), key=_model_sort_key):
        b = _best_weight_decay_rows(g[g["model"].astype(str) == model], val, test)
        line, = ax.plot(b["n_train"], b["mean"], marker="o", ms=4, label=model)
        if (b["max"] > b["min"]).any():
            ax.fill_between(b["n_train"], b["min"], b["max"], color=line.get_color(), alpha=0.15,
                            lw=0)
    if coarse_test_mrad is not None and math.isfinite(coarse_test_mrad):
        ax.axhline(coarse_test_mrad, color="0.3", ls="--", lw=1,
                   label=f"{coarse_label} (all training data)")
    ax.set_ylabel("mean test error [mrad]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", ncols=2)
    ax.set_title(f"{heliostat}: test error against training size")
    if dist is not None:
        d = g.groupby("n_train", sort=True)[dist].mean()
        ax2.plot(d.index, d.to_numpy(), marker="o", ms=4, color="0.2")
        ax2.set_ylabel("test-to-train\ndistance [deg]")
    else:
        ax2.text(0.5, 0.5, "sweep.parquet has no test_train_distance_deg", ha="center",
                 va="center", transform=ax2.transAxes)
    ax2.set_xlabel("training measurements")
    ax2.grid(alpha=0.3)
    return fig, None


def plot_sky_map(measurements: pd.DataFrame, split: pd.DataFrame | None,
                 predictions: pd.DataFrame | None, heliostat: str, model: str | None):
    """Paper 000, fig. 7: measurements over sun azimuth and elevation.

    Training points are dots; each validation and test point is a filled circle whose radius grows
    linearly with its error (:data:`SKY_POINTS_PER_MRAD` pt per mrad, clipped at
    :data:`SKY_CLIP_MRAD`), inside a grey ring of 1 mrad for reference.
    """
    m = measurements[measurements["heliostat_id"] == heliostat][
        ["measurement_id", "sun_azimuth_deg", "sun_elevation_deg"]]
    if split is not None:
        s = split[split["heliostat_id"] == heliostat][["measurement_id", "split"]]
        m = m.merge(s, on="measurement_id", how="left")
        m["split"] = m["split"].fillna("unsplit")
    else:
        m = m.assign(split="unsplit")
    if predictions is not None and model is not None:
        p = predictions[(predictions["heliostat_id"] == heliostat) & (predictions["model"] == model)]
        m = m.merge(p[["measurement_id", "error_mrad"]], on="measurement_id", how="left")
    else:
        m["error_mrad"] = np.nan
    fig, axes = _figure(8.0, 4.8)
    ax = axes[0, 0]
    k = SKY_POINTS_PER_MRAD
    handles = []
    from matplotlib.lines import Line2D

    for label, color, marker, size in (("train", "0.25", "o", 9), ("unused", "0.7", "x", 12),
                                       ("unsplit", "0.25", "o", 9)):
        g = m[m["split"] == label]
        if len(g):
            ax.scatter(g["sun_azimuth_deg"], g["sun_elevation_deg"], s=size, c=color,
                       marker=marker, lw=0.8 if marker == "x" else 0, zorder=2)
            handles.append(Line2D([], [], ls="", marker=marker, color=color, ms=4,
                                  label={"unsplit": "measurement", "unused": "unused (not trained on)"}
                                  .get(label, "training")))
    ring_drawn = False
    for label in ("validation", "test"):
        g = m[m["split"] == label]
        if not len(g):
            continue
        color = _SPLIT_COLORS[label]
        err = g["error_mrad"].to_numpy(float)
        has_err = np.isfinite(err)
        if not has_err.any():
            ax.scatter(g["sun_azimuth_deg"], g["sun_elevation_deg"], s=16, c=color, zorder=3)
            handles.append(Line2D([], [], ls="", marker="o", color=color, ms=4, label=label))
            continue
        shown = np.clip(err, 0, SKY_CLIP_MRAD)
        ax.scatter(g["sun_azimuth_deg"][has_err], g["sun_elevation_deg"][has_err],
                   s=(2 * k) ** 2, facecolors="none", edgecolors="0.6", lw=0.8, zorder=3)
        ring_drawn = True
        ax.scatter(g["sun_azimuth_deg"][has_err], g["sun_elevation_deg"][has_err],
                   s=(2 * k * shown[has_err]) ** 2, c=color, alpha=0.55, lw=0.6,
                   edgecolors=color, zorder=4)
        clipped = has_err & (err > SKY_CLIP_MRAD)
        if clipped.any():
            ax.scatter(g["sun_azimuth_deg"][clipped], g["sun_elevation_deg"][clipped],
                       s=(2 * k * SKY_CLIP_MRAD) ** 2, facecolors="none", edgecolors="k",
                       linestyle="--", lw=0.8, zorder=5)
        handles.append(Line2D([], [], ls="", marker="o", color=color, alpha=0.55, ms=2 * k,
                              label=f"{label} (mean {np.nanmean(err):.2f} mrad)"))
    if ring_drawn:
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec="0.6", ms=2 * k,
                              label="1 mrad reference"))
        if (m["error_mrad"] > SKY_CLIP_MRAD).any():
            handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec="k", ms=8,
                                  label=f"dashed: clipped at {SKY_CLIP_MRAD:g} mrad"))
    ax.set_xlabel("sun azimuth [deg] (0 = south, positive toward east)")
    ax.set_ylabel("sun elevation [deg]")
    ax.grid(alpha=0.3)
    ax.margins(0.06)
    title = f"{heliostat}: measurements in sun position"
    if model is not None and ring_drawn:
        title += f"; circle radius = error of {model}"
    ax.set_title(title, fontsize="medium")
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small",
              borderaxespad=0, labelspacing=1.0)
    return fig


def plot_weight_decay(sweep: pd.DataFrame, heliostat: str, model: str | None,
                      coarse_val_mrad: float | None, coarse_test_mrad: float | None,
                      selected_weight_decay: float | None = None):
    """Paper 000, fig. 9a: validation and test error against weight decay; coarse levels as lines.

    Uses ``model`` (default: the model with the most weight decays, preferring ``hybrid``) at its
    largest training size; the band spans the seeds. Returns ``(figure, None)`` or ``(None, why)``.
    """
    wd, test, val = (_first_col(sweep, "weight_decay"), _col(sweep, "test"),
                     _col(sweep, "validation"))
    if wd is None or test is None or "model" not in sweep.columns:
        return None, "sweep.parquet has no weight_decay, model or test error column"
    g = sweep[sweep["heliostat_id"].astype(str) == heliostat].copy()
    g["model"] = g["model"].astype(str)
    if model not in set(g["model"]):
        counts = g.groupby("model")[wd].nunique()
        if not len(counts):
            return None, f"sweep.parquet has no rows of {heliostat}"
        model = "hybrid" if "hybrid" in counts.index else str(counts.idxmax())
    g = g[g["model"] == model]
    if "n_train" in g.columns:
        g = g[g["n_train"] == g["n_train"].max()]
    if g[wd].nunique() < 2:
        return None, f"the sweep of {heliostat} ({model}) has a single weight decay"
    fig, axes = _figure(7.5, 4.4)
    ax = axes[0, 0]
    positive = g.loc[g[wd] > 0, wd]
    if (g[wd] <= 0).any():
        ax.set_xscale("symlog", linthresh=float(positive.min()) if len(positive) else 1e-6)
    else:
        ax.set_xscale("log")
    for split, col, color in (("validation", val, "tab:blue"), ("test", test, "tab:orange")):
        if col is None:
            continue
        a = g.groupby(wd, sort=True)[col].agg(["mean", "min", "max"])
        ax.plot(a.index, a["mean"], marker="o", ms=4, color=color, label=f"{model}, {split}")
        if (a["max"] > a["min"]).any():
            ax.fill_between(a.index, a["min"], a["max"], color=color, alpha=0.15, lw=0)
    for level, color, split in ((coarse_val_mrad, "#08306b", "validation"),
                                (coarse_test_mrad, "#6baed6", "test")):
        if level is not None and math.isfinite(level):
            ax.axhline(level, color=color, ls="--", lw=1.2, label=f"coarse, {split}")
    if selected_weight_decay is not None and math.isfinite(selected_weight_decay):
        ax.axvline(selected_weight_decay, color="0.4", ls=":", lw=1,
                   label=f"selected ({selected_weight_decay:g})")
    ax.set_xlabel("weight decay [1]")
    ax.set_ylabel("mean error [mrad]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.set_title(f"{heliostat}: error against weight decay ({model})", fontsize="medium")
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None


def _hybrid_vs_coarse_table(inp: ReportInputs) -> pd.DataFrame | None:
    """Per heliostat: validation and test mean error of the selected coarse and hybrid model."""
    sel = inp.selection
    if sel is not None and all(c in sel.columns for c in ("heliostat_id", "val_error_mrad",
                                                           "test_error_mrad",
                                                           "coarse_val_error_mrad",
                                                           "coarse_test_error_mrad")):
        return pd.DataFrame({
            "heliostat_id": sel["heliostat_id"].astype(str),
            "model": sel["model"].astype(str) if "model" in sel.columns else "hybrid",
            "coarse_validation": sel["coarse_val_error_mrad"].astype(float),
            "coarse_test": sel["coarse_test_error_mrad"].astype(float),
            "hybrid_validation": sel["val_error_mrad"].astype(float),
            "hybrid_test": sel["test_error_mrad"].astype(float),
        }).sort_values("heliostat_id").reset_index(drop=True)
    p = inp.predictions
    if p is None or not (p["source"] == "hybrid_predictions").any():
        return None
    rows = []
    for hid, f in sorted(_final_models(inp).items()):
        hp = p[(p["heliostat_id"] == hid) & (p["source"] == "hybrid_predictions")]
        if not len(hp) or f.get("coarse_preset") is None:
            continue
        hmodel = f["model"] if f["model"] in set(hp["model"]) else (
            "hybrid" if "hybrid" in set(hp["model"]) else str(hp["model"].iloc[0]))
        cp = p[(p["heliostat_id"] == hid) & (p["model"] == f["coarse_preset"])]
        hp = hp[hp["model"] == hmodel]
        rows.append({"heliostat_id": hid, "model": hmodel,
                     **{f"coarse_{s}": cp.loc[cp["split"] == s, "error_mrad"].mean()
                        for s in ("validation", "test")},
                     **{f"hybrid_{s}": hp.loc[hp["split"] == s, "error_mrad"].mean()
                        for s in ("validation", "test")}})
    return pd.DataFrame(rows) if rows else None


def plot_hybrid_vs_coarse(table: pd.DataFrame):
    """Paper 000, fig. 8: mean validation and test error of hybrid and coarse per heliostat."""
    n = len(table)
    fig, axes = _figure(max(6.0, 1.6 * n + 3.0), 4.2, 1, 2, sharey=True)
    x = np.arange(n)
    w = 0.38
    top = np.nanmax(table[["coarse_validation", "coarse_test", "hybrid_validation",
                           "hybrid_test"]].to_numpy(float))
    for ax, split in zip(axes[0], ("validation", "test")):
        for off, kind, color in ((-w / 2, "coarse", "#6baed6"), (w / 2, "hybrid", "tab:red")):
            vals = table[f"{kind}_{split}"].to_numpy(float)
            label = "coarse (selected preset)" if kind == "coarse" else "hybrid (selected)"
            bars = ax.bar(x + off, vals, w, color=color, label=label)
            ax.bar_label(bars, labels=[f"{v:.2f}" if math.isfinite(v) else "n/a" for v in vals],
                         fontsize="x-small", padding=2)
        ax.set_xticks(x, table["heliostat_id"])
        ax.set_title(f"{split} set", fontsize="medium")
        ax.set_xlabel("heliostat")
        ax.grid(alpha=0.3, axis="y")
        ax.set_ylim(0, top * 1.18 if math.isfinite(top) and top > 0 else 1)
    axes[0, 0].set_ylabel("mean error [mrad]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=2, fontsize="small")
    fig.suptitle("Hybrid against coarse model per heliostat")
    return fig


def plot_error_over_time(measurements: pd.DataFrame, predictions: pd.DataFrame, heliostat: str,
                         model: str, coarse_model: str | None = None, window_days: int = 30):
    """Error of ``model`` over the measurement date, coloured by split, with a rolling median.

    The rolling median (``window_days``, centred) shows drift and seasonal patterns; with a
    different ``coarse_model`` its rolling median is drawn dashed for comparison. Returns
    ``(figure, None)`` or ``(None, reason)``.
    """
    import matplotlib.dates as mdates

    m = measurements[measurements["heliostat_id"] == heliostat][["measurement_id", "timestamp"]]
    p = predictions[predictions["heliostat_id"] == heliostat]
    d = p[p["model"] == model][["measurement_id", "split", "error_mrad"]].merge(
        m, on="measurement_id", how="inner")
    d["timestamp"] = pd.to_datetime(d["timestamp"], utc=True)
    n_missing = int(d["timestamp"].isna().sum())
    d = d.dropna(subset=["timestamp"]).sort_values("timestamp")
    if len(d) < 2:
        return None, f"{heliostat} has fewer than two timestamped predictions of {model}"
    fig, axes = _figure(8.0, 3.8)
    ax = axes[0, 0]
    for split in sorted(d["split"].unique(), key=_split_sort_key):
        g = d[d["split"] == split]
        ax.scatter(g["timestamp"].dt.tz_localize(None), g["error_mrad"], s=12 if split != "train"
                   else 7, color=_SPLIT_COLORS.get(split, "0.5"), label=f"{split} ({len(g)})",
                   alpha=0.85, lw=0, zorder=3 if split != "train" else 2)

    def rolling(frame):
        s = frame.set_index(frame["timestamp"].dt.tz_localize(None))["error_mrad"]
        r = s.rolling(f"{window_days}D", center=True, min_periods=3).median()
        # break the line across gaps longer than the window instead of bridging them
        gap = s.index.to_series().diff() > pd.Timedelta(days=window_days)
        if gap.any():
            breaks = pd.Series(np.nan, index=s.index[gap.to_numpy()] - pd.Timedelta(seconds=1))
            r = pd.concat([r, breaks]).sort_index()
        return r

    r = rolling(d)
    ax.plot(r.index, r.to_numpy(), color="k", lw=1.4, label=f"{model}: {window_days}-day median")
    if coarse_model and coarse_model != model:
        c = p[p["model"] == coarse_model][["measurement_id", "error_mrad"]].merge(
            m, on="measurement_id")
        c["timestamp"] = pd.to_datetime(c["timestamp"], utc=True)
        c = c.dropna(subset=["timestamp"]).sort_values("timestamp")
        if len(c) >= 2:
            rc = rolling(c)
            ax.plot(rc.index, rc.to_numpy(), color="#6baed6", ls="--", lw=1.4,
                    label=f"{coarse_model}: {window_days}-day median")
    locator = mdates.AutoDateLocator()
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    ax.set_xlabel("measurement date (UTC)")
    ax.set_ylabel("error [mrad]")
    ax.set_ylim(bottom=0)
    top = float(np.nanpercentile(d["error_mrad"], 99)) if d["error_mrad"].notna().any() else 1.0
    if d["error_mrad"].max() > 1.5 * top:  # keep a few wild points from flattening the rest
        ax.set_ylim(0, 1.3 * top)
        n_above = int((d["error_mrad"] > 1.3 * top).sum())
        ax.text(0.99, 0.97, f"{n_above} point{'s' if n_above != 1 else ''} above the axis",
                transform=ax.transAxes, ha="right", va="top", fontsize="x-small")
    ax.grid(alpha=0.3)
    title = f"{heliostat}: error of {model} over time"
    if n_missing:
        title += f" ({n_missing} without timestamp not shown)"
    ax.set_title(title, fontsize="medium")
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig, None


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
    finals = _final_models(inp)
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
    splits = sorted({s for h in helios.values() for s in h["split_counts"]}, key=_split_sort_key)
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


def _figures(inp: ReportInputs, metrics: dict, finals: dict) -> list[tuple]:
    out: list[tuple] = []
    hids = list(metrics["heliostats"])

    def add(fig, filename, caption):
        try:
            out.append(("figure", _Figure(filename, caption, _png(fig))))
        finally:
            fig.clear()

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
    table = _hybrid_vs_coarse_table(inp)
    if table is None:
        out.append(("note", "Omitted: needs selection.parquet or hybrid_predictions.parquet; run "
                            f"{inp.run_hint('hybrid_predictions.parquet')} and {sweep_hint}."))
    else:
        add(plot_hybrid_vs_coarse(table), "hybrid_vs_coarse.png",
            "Mean validation and test error of the selected hybrid model and the selected coarse "
            "preset per heliostat.")

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


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
@locks_workdir("report")
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
