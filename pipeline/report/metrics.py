"""``metrics.json``: the accuracy numbers of a run (per split and model: mean, median, percentiles of
error_mrad), rounded to fixed decimals so that two runs of the same pipeline give the same text.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .. import __version__
from ..artifacts.manifests import all_manifests, checked_relative_path
from ..artifacts.provenance import git_revision
from .inputs import ReportInputs

__all__ = [
    "WITHOUT_FIELD_PRIOR",
    "column_of",
    "final_models",
    "first_column",
    "model_sort_key",
    "split_sort_key",
    "METRICS_SCHEMA_VERSION",
    "SPLIT_ORDER",
    "error_statistics",
    "compute_metrics",
    "degenerate_heliostats",
    "metrics_json",
]


#: Version of metrics.json's layout (``docs/metrics_schema.json``); bump when a key changes meaning.
METRICS_SCHEMA_VERSION = 1


#: Order of the splits in tables and metrics.json.
SPLIT_ORDER = ("train", "validation", "test", "unused")


#: Decimals of every float in metrics.json (1e-4 mrad = 0.1 microradian).
DECIMALS = 4


_HYBRID_ORDER = ("hybrid", "nn-only", "pretrained-nn")


_COARSE_ORDER = ("nominal", "static-6", "stone-8", "static-14", "static-20", "static-28")


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
    return _statistics(rows["error_mrad"].to_numpy(float),
                       *(rows[c].to_numpy(float) if c in rows.columns else None
                         for c in ("beam_error_mrad", "spot_offset_m")))


def _statistics(err: np.ndarray, beam: np.ndarray | None, spot: np.ndarray | None) -> dict:
    """:func:`error_statistics` of the arrays of one group of rows.

    metrics.json holds these for every heliostat, model and split (some 40,000 groups at 2,000
    heliostats), so the median and percentile are read off one sort with numpy's own arithmetic
    (:func:`_sorted_quantile`) instead of a call of ``np.median`` and ``np.percentile`` each:
    the same numbers to the bit, at about a third of the cost."""
    ok = np.isfinite(err)
    out = {"n": int(len(err)), "n_finite": int(ok.sum()),
           "mean_error_mrad": None, "median_error_mrad": None, "p95_error_mrad": None,
           "mean_beam_error_mrad": None, "mean_spot_offset_m": None}
    if ok.any():
        e = err[ok]
        ordered = np.sort(e)
        out.update(mean_error_mrad=_r(e.mean()), median_error_mrad=_r(_sorted_median(ordered)),
                   p95_error_mrad=_r(_sorted_quantile(ordered, 0.95)))
    for v, key in ((beam, "mean_beam_error_mrad"), (spot, "mean_spot_offset_m")):
        if v is not None:
            v = v[np.isfinite(v)]
            if len(v):
                out[key] = _r(v.mean())
    return out


def _sorted_median(ordered: np.ndarray) -> float:
    """``np.median`` of the ascending finite values ``ordered`` (not empty): the middle value, or
    the two middle ones' sum over 2 (``np.mean`` of the pair)."""
    n, mid = len(ordered), len(ordered) // 2
    if n % 2:
        return float(ordered[mid])
    return (float(ordered[mid - 1]) + float(ordered[mid])) / 2


def _sorted_quantile(ordered: np.ndarray, q: float) -> float:
    """``np.quantile(ordered, q)`` (method ``linear``) of the ascending finite values
    ``ordered`` (not empty), in numpy's arithmetic: the virtual index ``(n - 1) q``, its floor,
    and numpy's two-sided interpolation between the neighbours (exact at both ends)."""
    n = len(ordered)
    index = (n - 1) * q
    if index >= n - 1:
        return float(ordered[-1])
    below = math.floor(index)
    t = index - below
    a, b = float(ordered[below]), float(ordered[below + 1])
    diff = b - a
    return b - diff * (1 - t) if t >= 0.5 else a + diff * t


#: Suffix of sweep.parquet's models of the training-size study fitted without fit-coarse's
#: field prior (``<preset>+no-field-prior``, heliocal.pipeline.stages.study_prior; the report
#: reads artifacts and imports no stage): drawn on the field-prior page only.
WITHOUT_FIELD_PRIOR = "+no-field-prior"


def split_sort_key(s: str) -> tuple:
    return (SPLIT_ORDER.index(s) if s in SPLIT_ORDER else len(SPLIT_ORDER), s)


def model_sort_key(m: str) -> tuple:
    if m in _COARSE_ORDER:
        return (0, _COARSE_ORDER.index(m), m)
    if m in _HYBRID_ORDER:
        return (2, _HYBRID_ORDER.index(m), m)
    return (1, 0, m)


def column_of(df: pd.DataFrame | None, split: str, stat: str = "mean") -> str | None:
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


def first_column(df: pd.DataFrame | None, *names: str) -> str | None:
    if df is None:
        return None
    for n in names:
        if n in df.columns:
            return n
    return None


def final_models(inp: ReportInputs) -> dict[str, dict]:
    """Per heliostat: the selected coarse preset and the final model (hybrid where selected)."""
    out: dict[str, dict] = {}
    p = inp.predictions
    if p is not None:
        # per heliostat and source the first selected model (one pass, not a mask per heliostat)
        s = p.loc[p["selected"], ["heliostat_id", "source", "model"]].drop_duplicates(
            ["heliostat_id", "source"])
        first = {src: dict(zip(d["heliostat_id"], d["model"].astype(str)))
                 for src, d in s.groupby("source", sort=False)}
        coarse, hybrid, chosen = (first.get(f"{k}_predictions", {})
                                  for k in ("coarse", "hybrid", "selected"))
        for hid in sorted(set(s["heliostat_id"])):
            c, h, x = coarse.get(hid), hybrid.get(hid), chosen.get(hid)
            out[hid] = {"coarse_preset": c,
                        "model": x if x is not None else h if h is not None else c}
    sel = inp.selection
    if sel is not None and "heliostat_id" in sel.columns:
        for row in sel.to_dict("records"):
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
    hids = sorted(m["heliostat_id"].unique())  # distinct first: a row-by-row walk is slow
    finals = final_models(inp)
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
    # each frame grouped by heliostat once (a mask per heliostat would cost rows x heliostats)
    ts_by = {h: g for h, g in ts.groupby(m["heliostat_id"].to_numpy(), sort=False)}
    split_counts = _counts_by_heliostat(inp.split, "split") if inp.split is not None else {}
    test_distance = _test_distances(inp.split)
    models_of = _model_statistics(inp.predictions) if inp.predictions is not None else {}
    degenerate = degenerate_heliostats(inp)
    forward = _forward_in_time(inp, finals, degenerate)
    for hid in hids:
        t = ts_by[hid]
        h: dict[str, Any] = {
            "n_measurements": int(len(t)),
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
            counts = split_counts.get(hid, {})
            h["split_counts"] = {k: counts[k] for k in sorted(counts, key=split_sort_key)}
            if hid in test_distance:
                h["test_train_distance_deg"] = _r(test_distance[hid].mean())
        f = finals.get(hid, {})
        for key in h["selection"]:
            v = f.get(key)
            if key in ("coarse_preset", "model"):
                h["selection"][key] = v
            elif v is not None:
                h["selection"][key] = _r(v)
        for model, mm in sorted(models_of.get(hid, {}).items(),
                                key=lambda kv: model_sort_key(kv[0])):
            h["models"][model] = {**mm, "splits": {sp: mm["splits"][sp] for sp in
                                                   sorted(mm["splits"], key=split_sort_key)}}
        h["forward_in_time"] = forward[0].get(hid) or _empty_forward(finals.get(hid, {}))
        helios[hid] = h
    return {
        "metrics_schema_version": METRICS_SCHEMA_VERSION,
        "heliocal_version": __version__,
        "git_revision": git_revision(),
        "inputs": _committed_sha256s(inp.workdir, sorted(inp.paths)),
        "data": data,
        "heliostats": helios,
        "field": {"forward_in_time": forward[1], "degenerate_heliostats": sorted(degenerate)},
    }


#: The two models of the forward-in-time comparison: fit-coarse's selected preset and the final
#: model (the one metrics.json's selection names).
FORWARD_ROLES = ("coarse", "final")


def _counts_by_heliostat(frame: pd.DataFrame, column: str) -> dict[str, dict[str, int]]:
    """heliostat -> value of ``column`` -> rows (missing values not counted; a heliostat whose
    values are all missing is left out), from one groupby of the whole frame."""
    counts = frame.groupby([frame["heliostat_id"], frame[column]], sort=False).size()
    out: dict[str, dict[str, int]] = {}
    for (hid, value), n in counts.items():
        out.setdefault(hid, {})[value] = int(n)
    return out


def _test_distances(split: pd.DataFrame | None) -> dict[str, pd.Series]:
    """heliostat -> its kNN test rows' ``nearest_train_distance_deg`` (heliostats with test
    rows)."""
    if split is None or "nearest_train_distance_deg" not in split.columns:
        return {}
    test = split.loc[split["split"] == "test", ["heliostat_id", "nearest_train_distance_deg"]]
    return dict(tuple(test.groupby("heliostat_id", sort=False)["nearest_train_distance_deg"]))


def _empty_forward(final: dict) -> dict:
    none = _statistics(np.array([]), None, None)
    return {"time_split_counts": {},
            **{role: {"model": final.get("coarse_preset" if role == "coarse" else "model"),
                      "knn_test": none, "time_test": none} for role in FORWARD_ROLES}}


def degenerate_heliostats(inp: ReportInputs) -> set[str]:
    """The heliostats whose training rows cannot determine their model (coarse_params.parquet's
    ``fit_degenerate`` is set, e.g. one measurement repeated): their errors say nothing about
    accuracy, so the field's pooled figures leave them out."""
    cp = inp.coarse_params
    if cp is None or "fit_degenerate" not in cp.columns:
        return set()
    why = cp.groupby(cp["heliostat_id"].astype(str), sort=False)["fit_degenerate"].first()
    return {h for h, w in why.items() if isinstance(w, str) and w}


def _forward_in_time(inp: ReportInputs, finals: dict,
                     degenerate: set[str] = frozenset()) -> tuple[dict, dict]:
    """Per heliostat and pooled over the field: the kNN test error (``error_mrad`` on the split's
    test rows) and the forward-in-time test error (``time_error_mrad``: the same model trained
    on the time split's training rows, on the time split's test rows) of the selected coarse
    preset and of the final model. A heliostat without time split has empty ``time_test``
    statistics (n = 0): "n/a". The pooled figures leave out the ``degenerate`` heliostats (they
    keep their own)."""
    p, split = inp.predictions, inp.split
    per: dict[str, dict] = {}
    pooled = {role: {"knn_test": [], "time_test": []} for role in FORWARD_ROLES}
    if p is not None and split is not None:
        want = pd.DataFrame(
            [(hid, role, f.get("coarse_preset" if role == "coarse" else "model"))
             for hid, f in finals.items() for role in FORWARD_ROLES],
            columns=["heliostat_id", "role", "model"]).dropna()
        cols = ["heliostat_id", "measurement_id", "model", "source", "split", "error_mrad"]
        rows = p[cols + (["time_error_mrad"] if "time_error_mrad" in p.columns else [])]
        if "time_error_mrad" not in rows.columns:
            rows = rows.assign(time_error_mrad=np.nan)
        # only the final models' rows take part in the (inner) merge: filter them first
        rows = rows[rows["model"].isin(want["model"].unique())]
        rows = rows.merge(want, on=["heliostat_id", "model"])
        # the coarse role's rows are fit-coarse's; a model name in several sources: its first
        rows = rows[(rows["role"] != "coarse") | (rows["source"] == "coarse_predictions")]
        rows = rows.drop_duplicates(["role", "heliostat_id", "measurement_id"])
        tcol = split["time_split"] if "time_split" in split.columns else pd.Series(
            None, index=split.index, dtype=object)
        rows = rows.merge(split[["heliostat_id", "measurement_id"]].assign(time_split=tcol),
                          on=["heliostat_id", "measurement_id"], how="left")
        err = rows["error_mrad"].to_numpy(float)
        terr = rows["time_error_mrad"].to_numpy(float)
        knn = (rows["split"] == "test").to_numpy()
        tt = (rows["time_split"] == "test").to_numpy()
        tcounts = _counts_by_heliostat(split.assign(time_split=tcol), "time_split")
        for (role, hid), idx in rows.groupby(["role", "heliostat_id"]).indices.items():
            entry = per.setdefault(hid, _empty_forward(finals.get(hid, {})))
            entry["time_split_counts"] = {k: tcounts.get(hid, {})[k] for k in sorted(
                tcounts.get(hid, {}), key=split_sort_key)}
            k_idx, t_idx = idx[knn[idx]], idx[tt[idx]]
            entry[role]["knn_test"] = _statistics(err[k_idx], None, None)
            entry[role]["time_test"] = _statistics(terr[t_idx], None, None)
            if hid in degenerate:
                continue
            pooled[role]["knn_test"].append(err[k_idx])
            pooled[role]["time_test"].append(terr[t_idx])
    field = {"n_heliostats_time_split": sum(1 for h, e in per.items() if h not in degenerate
                                            and (e["final"]["time_test"]["n_finite"]
                                                 or e["coarse"]["time_test"]["n_finite"]))}
    for role in FORWARD_ROLES:
        field[role] = {k: _statistics(np.concatenate(v) if v else np.array([]), None, None)
                       for k, v in pooled[role].items()}
    _next_day(inp, finals, per, field, degenerate)
    return per, field


def _next_day(inp: ReportInputs, finals: dict, per: dict, field: dict,
              degenerate: set[str]) -> None:
    """Each heliostat's ``next_day`` (the rolling-origin evaluation's errors of fit-coarse's
    selected preset: statistics, origins, median days since the fit's last row) and the field's
    pooled over the heliostats that are not ``degenerate`` (in place)."""
    r = inp.rolling
    empty = {**_statistics(np.array([]), None, None), "origins": 0,
             "median_days_since_last_row": None}
    pooled = []
    groups = dict(tuple(r.groupby(r["heliostat_id"].astype(str), sort=True))) if (
        r is not None and len(r)) else {}
    for hid in set(per) | set(finals):
        entry = per.setdefault(hid, _empty_forward(finals.get(hid, {})))
        g = groups.get(hid)
        if g is None:
            entry["next_day"] = dict(empty)
            continue
        err = g["error_mrad"].to_numpy(float)
        entry["next_day"] = {**_statistics(err, None, None),
                             "origins": int(g["origin_date"].nunique()),
                             "median_days_since_last_row": _r(
                                 np.median(g["days_since_last_row"].to_numpy(float)))}
        if hid not in degenerate:
            pooled.append(err)
    field["next_day"] = {**_statistics(np.concatenate(pooled) if pooled else np.array([]),
                                       None, None),
                         "n_heliostats": len(pooled)}


def _model_statistics(p: pd.DataFrame) -> dict:
    """heliostat -> model -> {source (of its first row), selected (any row), splits: split ->
    :func:`error_statistics`}, from one groupby's row indices (no frame per group)."""
    err = p["error_mrad"].to_numpy(float)
    beam, spot = (p[c].to_numpy(float) if c in p.columns else None
                  for c in ("beam_error_mrad", "spot_offset_m"))
    source = p["source"].to_numpy()
    selected = p["selected"].to_numpy(bool)
    out: dict[str, dict] = {}
    for (hid, model, split), idx in p.groupby(["heliostat_id", "model", "split"],
                                              sort=False).indices.items():
        mm = out.setdefault(hid, {}).setdefault(model, {"first": idx[0], "selected": False,
                                                        "splits": {}})
        mm["first"] = min(mm["first"], idx[0])
        mm["selected"] = mm["selected"] or bool(selected[idx].any())
        mm["splits"][split] = _statistics(err[idx], None if beam is None else beam[idx],
                                          None if spot is None else spot[idx])
    return {hid: {m: {"source": str(source[mm["first"]]), "selected": mm["selected"],
                      "splits": mm["splits"]} for m, mm in models.items()}
            for hid, models in out.items()}


def _committed_sha256s(workdir: Path, filenames) -> dict[str, str | None]:
    """filename -> SHA-256 of the input artifact as its run committed it (verified when it was
    read; None if no manifest lists it), the work directory's manifests loaded once: the first
    manifest by stage that lists it, as
    :func:`heliocal.pipeline.artifacts.manifests.committed_entry` finds it."""
    manifests = all_manifests(workdir)
    out = {}
    for name in filenames:
        rel = checked_relative_path(name)
        out[name] = next((m.files[rel]["sha256"] for m in manifests if rel in m.files), None)
    return out


def metrics_json(metrics: dict) -> str:
    """metrics.json text: sorted keys, two-space indent, trailing newline (stable diffs)."""
    return json.dumps(metrics, sort_keys=True, indent=2, allow_nan=False) + "\n"
