"""Which model ``aim --model auto`` uses per heliostat (:func:`aim_models`): read from the
artifacts and the model files' manifests only, without torch, so that ``report`` and ``info``
ask the same question as ``aim`` cheaply. :mod:`.aim` re-exports it.
"""

from __future__ import annotations

import json
from typing import Sequence

import pandas as pd

from ..artifacts.manifests import CommittedWorkdir
from ..artifacts.modelfiles import model_files
from ..artifacts.schemas import COARSE_PARAMS, HELIOSTATS, HYBRID_PREDICTIONS, MEASUREMENTS
from ..artifacts.store import artifact_present, check_fresh, read_artifact
from ..errors import StageInputError
from ..runtime.process_state import restores_process_state

__all__ = [
    "aim_models",
    "nominal_fallback",
    "group_prior_errors",
    "zero_row_fallback",
    "time_labelled_predictions",
]


def _model_committed(wd: CommittedWorkdir, mode: str, heliostat_id: str) -> bool:
    """Whether the stage that writes ``mode``'s models committed one for the heliostat (both its
    files listed in the stage's manifest; :func:`load_model` checks their content)."""
    stage = "sweep" if mode == "selected" else "fit-hybrid"
    return all(wd.listed(stage, rel) for rel in model_files(mode, heliostat_id))


@restores_process_state
def aim_models(workdir, heliostats: Sequence[str] | None = None, *,
               strict: bool = False) -> dict:
    """Per heliostat the model ``aim --model auto`` uses, and its mean validation and test error.

    The one decision both :func:`aim_steps` and ``heliocal info WORKDIR`` use: the sweep's
    selection (selection.parquet) where the sweep ran: its coarse model, or its selected hybrid
    ensemble (``hybrid/selected/``) if that was written; without a selection row for the
    heliostat, the ``fit-hybrid`` hybrid (``hybrid/hybrid/``) where fitted; otherwise (and when a
    selected hybrid's files are missing) the coarse model, ``fit-coarse``'s selected preset.
    Every artifact and model is read through its stage's manifest (``workdir``: the work
    directory or its :class:`CommittedWorkdir`, whose reads ``aim`` shares). With ``strict`` (``aim``),
    selection.parquet must also be fresh and a selected hybrid's model committed, else a
    one-line :class:`StageInputError` says what to rerun (``info`` shows what is there).

    Returns
    -------
    dict heliostat_id -> {``model`` (``coarse``, ``hybrid``, ``pretrained-nn``, ``gp``, or
    ``nominal`` where the fitted model is not better than the nominal geometry on held-out
    rows (kNN validation, the time split's validation, the rolling-origin next-day rows):
    :func:`nominal_fallback`, whose sentence is in ``fallback``, else None), ``variant``
    (``hybrid``, ``hybrid-octaves``, ``pretrained-nn``, ``gp``, ``gp-sun``; None for coarse),
    ``source`` (the stage that chose it: ``sweep``,
    ``fit-hybrid`` or ``fit-coarse``), ``preset`` (the coarse preset, also under a hybrid),
    ``weight_decay`` (None for coarse), ``val_error_mrad``, ``test_error_mrad`` (NaN without
    such rows), ``forward_error_mrad`` (the same model fitted on the time split's training rows,
    on its test rows; NaN: n/a), ``next_day_error_mrad`` (the mean next-day error of fit-coarse's
    rolling-origin evaluation; NaN without one), ``model_dir`` (the folder under ``hybrid/``
    with its weights; None for coarse)}; empty without coarse_params.parquet.
    """
    from ..artifacts.schemas import SELECTION, SPLIT

    workdir = CommittedWorkdir.of(workdir)
    if not artifact_present(workdir, COARSE_PARAMS):
        return {}
    params = read_artifact(workdir, COARSE_PARAMS, heliostats=heliostats,
                           columns=["heliostat_id", "preset", "selected", "n_train",
                                    "val_error_mrad", "test_error_mrad", "time_val_error_mrad",
                                    "time_test_error_mrad"])
    coarse = params[params["selected"]].drop_duplicates("heliostat_id").set_index("heliostat_id")
    selection = None
    if artifact_present(workdir, SELECTION):
        selection = read_artifact(workdir, SELECTION, heliostats=heliostats)  # a committed sweep's
        if strict:
            check_fresh(workdir, SELECTION, {"measurements": MEASUREMENTS, "heliostats": HELIOSTATS,
                                             "split": SPLIT, "coarse_params": COARSE_PARAMS})
        selection = selection.drop_duplicates("heliostat_id").set_index("heliostat_id")
    fit_hybrid_errors = groups = None
    next_day = _next_day_errors(workdir, heliostats)
    nominal = _nominal_errors(workdir, heliostats)
    out = {}
    for hid in sorted(coarse.index):
        c = coarse.loc[hid]
        entry = {"heliostat_id": hid, "model": "coarse", "variant": None, "source": "fit-coarse",
                 "preset": str(c["preset"]), "weight_decay": None,
                 "val_error_mrad": float(c["val_error_mrad"]),
                 "test_error_mrad": float(c["test_error_mrad"]),
                 "forward_error_mrad": float(c["time_test_error_mrad"]),
                 "next_day_error_mrad": next_day.get(hid, float("nan")), "model_dir": None,
                 "fallback": None}
        choice = (str(selection.loc[hid, "model"])
                  if selection is not None and hid in selection.index else None)
        if choice == "coarse":
            row = selection.loc[hid]
            entry.update(source="sweep", val_error_mrad=float(row["coarse_val_error_mrad"]),
                         test_error_mrad=float(row["coarse_test_error_mrad"]))
        elif choice is not None and (choice.startswith(("hybrid", "gp"))
                                     or choice == "pretrained-nn"):
            if _model_committed(workdir, "selected", hid):
                row = selection.loc[hid]
                mode = choice if choice == "pretrained-nn" else choice.split("-")[0]
                entry.update(model=mode, variant=choice, source="sweep",
                             weight_decay=(float(row["weight_decay"]) if mode == "hybrid"
                                           else None),
                             val_error_mrad=float(row["val_error_mrad"]),
                             test_error_mrad=float(row["test_error_mrad"]),
                             forward_error_mrad=_number(row.get("time_test_error_mrad")),
                             model_dir="selected")
            elif strict:
                raise StageInputError(f"{workdir}/selection.parquet selects {choice} for {hid}, "
                                      f"but the sweep committed no model for it; rerun `heliocal "
                                      f"sweep --workdir {workdir}`")
        elif _model_committed(workdir, "hybrid", hid):
            cfg_rel = model_files("hybrid", hid)[0]
            cfg = _config(workdir.read(
                "fit-hybrid", cfg_rel,
                hint=f"`heliocal fit-hybrid --workdir {workdir} --mode hybrid`").data)
            if fit_hybrid_errors is None:
                fit_hybrid_errors = _fit_hybrid_errors(workdir)
            val, test = fit_hybrid_errors.get(hid, (float("nan"), float("nan")))
            entry.update(model="hybrid", variant="hybrid", source="fit-hybrid",
                         weight_decay=_number(cfg.get("weight_decay")),
                         val_error_mrad=val, test_error_mrad=test,
                         forward_error_mrad=float("nan"), model_dir="hybrid")
        entry = nominal_fallback(entry, float(c["time_val_error_mrad"]), nominal.get(hid))
        if int(c["n_train"]) == 0:   # no rows of its own: judged on heliostats like it
            if groups is None:
                groups = group_prior_errors(workdir)
            entry = zero_row_fallback(entry, groups.get(hid))
        out[hid] = entry
    return out


def zero_row_fallback(entry: dict, group: dict | None) -> dict:
    """``entry``, or the nominal geometry in its place for a heliostat without training rows of
    its own whose field-prior geometry (its coarse model) is not better than the nominal geometry on
    the test rows of the heliostats like it (``group``: field_prior.parquet's
    ``expected_error_mrad`` and ``nominal_error_mrad`` of its group, medians over its
    heliostats with test rows; None or NaN: nothing to judge by, ``entry`` as it is)."""
    from .coarse_prior import is_field_prior

    if not group or entry["model"] != "coarse" or not is_field_prior(entry["preset"]):
        return entry
    prior, nominal = group["expected_error_mrad"], group["nominal_error_mrad"]
    if not prior > nominal:      # better, equal-or-NaN-free comparisons keep the geometry
        return entry
    return {**entry, "model": "nominal", "variant": None, "weight_decay": None, "model_dir": None,
            "fallback": (f"{entry['heliostat_id']} has no rows of its own, and its group's "
                         f"field-prior geometry ({entry['preset']}) is worse than the nominal "
                         f"geometry on the test rows of {group['n_evaluated']} heliostats like it "
                         f"({prior:.3g} vs {nominal:.3g} mrad, medians): aim uses the nominal "
                         "geometry; calibrate it to get its own fit")}


def group_prior_errors(workdir: CommittedWorkdir) -> dict:
    """heliostat -> its field-prior group's ``expected_error_mrad``, ``nominal_error_mrad`` and
    ``n_evaluated`` (field_prior.parquet; empty without one)."""
    from ..artifacts.schemas import FIELD_PRIOR
    from ..models.field_prior import group_key

    if not artifact_present(workdir, FIELD_PRIOR) or not artifact_present(workdir, HELIOSTATS):
        return {}
    table = read_artifact(workdir, FIELD_PRIOR)
    keys = ["kinematic_type", "actuator_type", "geometry_source"]
    first = table.drop_duplicates(keys).set_index(keys)
    out = {}
    for _, hrow in read_artifact(workdir, HELIOSTATS).iterrows():
        key = group_key(hrow)
        if key in first.index:
            r = first.loc[key]
            out[str(hrow["heliostat_id"])] = {
                "expected_error_mrad": float(r["expected_error_mrad"]),
                "nominal_error_mrad": float(r["nominal_error_mrad"]),
                "n_evaluated": int(r["n_evaluated"]) if pd.notna(r["n_evaluated"]) else 0}
    return out


def nominal_fallback(entry: dict, time_val_error_mrad: float, nominal: dict | None) -> dict:
    """``entry`` (an :func:`aim_models` value), or the nominal geometry in its place when the
    fitted model is not better than the nominal geometry on rows it had not seen, any of:

    - its mean on the kNN validation rows above the nominal geometry's on the same rows;
    - the coarse model fitted on the time split's training rows (``time_val_error_mrad``) above
      the nominal geometry on the time split's validation rows;
    - its mean next-day error (``entry["next_day_error_mrad"]``: fit-coarse's rolling-origin
      evaluation, each day's rows scored by a fit on the rows before that day) above the
      nominal geometry's on the same rows: the forward evidence of a plant that keeps
      calibrating, which the time split's one validation period can miss.

    Held-out rows decide (the test rows stay a measurement); a NaN figure (no such rows)
    decides nothing. ``fallback`` says why in one sentence."""
    if not nominal:
        return entry
    worse = []
    if entry["val_error_mrad"] > nominal["val_error_mrad"]:
        worse.append(f"validation {entry['val_error_mrad']:.3g} vs {nominal['val_error_mrad']:.3g} mrad")
    if time_val_error_mrad > nominal["time_val_error_mrad"]:
        worse.append(f"forward in time {time_val_error_mrad:.3g} vs "
                     f"{nominal['time_val_error_mrad']:.3g} mrad")
    next_day = entry.get("next_day_error_mrad", float("nan"))
    if next_day > nominal.get("next_day_error_mrad", float("nan")):
        worse.append(f"next day {next_day:.3g} vs {nominal['next_day_error_mrad']:.3g} mrad on "
                     "the rolling-origin rows")
    if not worse:
        return entry
    model = entry["variant"] or entry["preset"]
    return {**entry, "model": "nominal", "variant": None, "weight_decay": None, "model_dir": None,
            "val_error_mrad": nominal["val_error_mrad"],
            "test_error_mrad": nominal["test_error_mrad"],
            "forward_error_mrad": nominal["time_test_error_mrad"],
            "next_day_error_mrad": nominal.get("next_day_error_mrad", float("nan")),
            "fallback": (f"the fitted {model} is worse than the nominal geometry on held-out "
                         f"rows ({'; '.join(worse)}): aim uses the nominal geometry; add "
                         "calibration rows and refit")}


def time_labelled_predictions(workdir: CommittedWorkdir, heliostats, columns,
                              model: str | None = None) -> pd.DataFrame:
    """coarse_predictions.parquet's ``columns`` (with heliostat_id and measurement_id) of the
    heliostats (the rows of ``model`` only, if given), each row with its time split label
    (``time_split``; None without split.parquet)."""
    from ..artifacts.schemas import COARSE_PREDICTIONS, SPLIT

    keys = ["heliostat_id", "measurement_id"]
    p = read_artifact(workdir, COARSE_PREDICTIONS, heliostats=heliostats,
                      columns=keys + [c for c in columns if c not in keys])
    if model is not None:
        p = p[p["model"] == model]
    if not artifact_present(workdir, SPLIT):
        return p.assign(time_split=None)
    t = read_artifact(workdir, SPLIT, heliostats=heliostats, columns=keys + ["time_split"])
    return p.merge(t, on=keys, how="left")


def _nominal_errors(workdir: CommittedWorkdir, heliostats) -> dict:
    """heliostat -> the nominal geometry's mean error on its validation and test rows of the
    kNN split and of the time split, and on its rolling-origin rows (``next_day_error_mrad``:
    the rows rolling_origin.parquet scores; NaN without such rows)."""
    from ..artifacts.schemas import COARSE_PREDICTIONS, ROLLING_ORIGIN

    if not artifact_present(workdir, COARSE_PREDICTIONS):
        return {}
    p = time_labelled_predictions(workdir, heliostats, ["split", "model", "error_mrad"],
                                  model="nominal")
    nan = float("nan")
    knn = p.groupby(["heliostat_id", "split"])["error_mrad"].mean()
    fwd = p.groupby(["heliostat_id", "time_split"])["error_mrad"].mean()
    rolling = pd.Series(dtype=float)
    if artifact_present(workdir, ROLLING_ORIGIN):
        keys = ["heliostat_id", "measurement_id"]
        scored = read_artifact(workdir, ROLLING_ORIGIN, heliostats=heliostats, columns=keys)
        rolling = scored.merge(p[keys + ["error_mrad"]], on=keys).groupby(
            "heliostat_id")["error_mrad"].mean()
    return {str(h): {"val_error_mrad": float(knn.get((h, "validation"), nan)),
                     "test_error_mrad": float(knn.get((h, "test"), nan)),
                     "time_val_error_mrad": float(fwd.get((h, "validation"), nan)),
                     "time_test_error_mrad": float(fwd.get((h, "test"), nan)),
                     "next_day_error_mrad": float(rolling.get(h, nan))}
            for h in p["heliostat_id"].unique()}


def _next_day_errors(workdir: CommittedWorkdir, heliostats) -> dict:
    """heliostat -> its mean next-day error (rolling_origin.parquet; empty without it)."""
    from ..artifacts.schemas import ROLLING_ORIGIN

    if not artifact_present(workdir, ROLLING_ORIGIN):
        return {}
    r = read_artifact(workdir, ROLLING_ORIGIN, heliostats=heliostats,
                      columns=["heliostat_id", "error_mrad"])
    return {str(h): float(v) for h, v in r.groupby("heliostat_id")["error_mrad"].mean().items()}


def _config(data: bytes) -> dict:
    """A model configuration's JSON object, or ``{}`` if it is not one (loading the model says
    why: :func:`heliocal.pipeline.artifacts.modelfiles.read_model`)."""
    try:
        cfg = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return {}
    return cfg if isinstance(cfg, dict) else {}


def _number(value) -> float:
    """``value`` as a float, NaN if it is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def _fit_hybrid_errors(workdir: CommittedWorkdir) -> dict:
    """Mean validation and test error_mrad of fit-hybrid's ``hybrid`` mode per heliostat."""
    if not artifact_present(workdir, HYBRID_PREDICTIONS):
        return {}
    p = read_artifact(workdir, HYBRID_PREDICTIONS,
                      columns=["heliostat_id", "split", "model", "error_mrad"])
    p = p[p["model"] == "hybrid"]
    means = p.groupby(["heliostat_id", "split"])["error_mrad"].mean()
    return {str(h): (float(means.get((h, "validation"), float("nan"))),
                     float(means.get((h, "test"), float("nan"))))
            for h in p["heliostat_id"].unique()}
