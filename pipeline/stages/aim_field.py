"""Many aims in one process: ``heliocal aim --schedule FILE`` and ``aim --date D --every 10min``.

A schedule is a table of aims, one row each: ``heliostat_id``, ``time_utc`` and the aim point,
either a calibration target's name (``target``) or ``aim_e_m, aim_n_m, aim_u_m`` [m ENU];
``env_<name>`` columns give the env inputs of fine models that use them. :func:`aim_schedule`
reads the work directory once, takes every heliostat's model and error budget once, and aims
each heliostat's rows together: the sun from NREL SPA at the heliostat for all its times in
one call, and for the coarse model (and the nominal geometry) the inverse kinematics and the
expected error as one tensor operation over the rows. A fine model's steps are a fixed point
per row (:mod:`.aim`), solved row by row.

Every row of the schedule gets one output row: ``status`` ``ok``, or ``rejected`` with the
reason (an unknown heliostat or target, a heliostat without a coarse fit or location, the sun
below the horizon, an aim point out of the actuators' reach, an expected error above the
limit); a bad row never stops the others. The output's columns are :data:`AIM_COLUMNS`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..artifacts.manifests import CommittedWorkdir
from ..artifacts.paths import atomic_path
from ..artifacts.schemas import HELIOSTATS, MEASUREMENTS
from ..artifacts.store import read_artifact
from ..errors import InputError, ParameterError, StageInputError, check_choice
from ..models.network import MODES
from ..physics.kinematics import inverse_kinematics
from ..physics.parameters import HeliostatSpec, nominal_parameters
from ..physics.sun import spa_sun_position, sun_vector_enu
from ..runtime.process_state import one_thread, restores_process_state
from .aim_budget import ErrorBudget, error_budgets, expected_error_mrad, sun_distance_deg
from .fit_coarse import coarse_row_parameters

__all__ = [
    "AIM_COLUMNS",
    "read_schedule",
    "day_schedule",
    "aim_schedule",
    "aims_csv",
    "write_aims",
]

log = logging.getLogger("heliocal.aim")

#: The columns of an aim table, in order.
AIM_COLUMNS = ["heliostat_id", "time_utc", "target", "aim_e_m", "aim_n_m", "aim_u_m",
               "sun_azimuth_deg", "sun_elevation_deg", "axis_1_steps", "axis_2_steps", "model",
               "regime", "expected_error_mrad", "level_source", "sun_distance_deg",
               "days_since_last_row", "status", "reason"]

_POINT = ["aim_e_m", "aim_n_m", "aim_u_m"]


# ------------------------------------------------------------------------------------------------
# schedules
# ------------------------------------------------------------------------------------------------
def read_schedule(path: str | Path) -> pd.DataFrame:
    """The schedule in ``path`` (.csv or .parquet) with its columns checked: ``heliostat_id``,
    ``time_utc`` and ``target`` or ``aim_e_m, aim_n_m, aim_u_m``. Times are parsed per row
    (an unreadable one is a rejected row, not an error)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet", ".pq"):
        raise InputError(f"{path}: a schedule is a .csv or .parquet file; got {suffix or 'no suffix'!r}")
    if not path.is_file():
        raise InputError(f"{path}: no such schedule file")
    try:
        df = (pd.read_csv(path, dtype={"heliostat_id": str, "target": str}) if suffix == ".csv"
              else pd.read_parquet(path))
    except (ValueError, OSError, pd.errors.ParserError) as exc:
        raise InputError(f"{path}: not a readable schedule ({type(exc).__name__}: {exc}); "
                         "give a CSV or Parquet table with heliostat_id, time_utc, target") from None
    missing = [c for c in ("heliostat_id", "time_utc") if c not in df.columns]
    has_point = all(c in df.columns for c in _POINT)
    if missing or not ("target" in df.columns or has_point):
        raise InputError(f"{path}: a schedule needs the columns heliostat_id, time_utc and target "
                         f"(or aim_e_m, aim_n_m, aim_u_m); it has {list(df.columns)}")
    return _normalised(df)


def _normalised(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with string ids and targets, UTC times (NaT where unreadable) and the point
    columns present (NaN where a target names the point)."""
    out = df.copy()
    out["heliostat_id"] = out["heliostat_id"].astype("string")
    out["time_utc"] = pd.to_datetime(out["time_utc"], utc=True, errors="coerce")
    if "target" not in out:
        out["target"] = pd.NA
    out["target"] = out["target"].astype("string")
    for c in _POINT:
        out[c] = pd.to_numeric(out[c], errors="coerce") if c in out else np.nan
    return out.reset_index(drop=True)


def _every_minutes(every: str) -> float:
    """``10min``, ``1h``, ``90s`` (or a number of minutes) as minutes."""
    try:
        delta = pd.Timedelta(every if not str(every).strip().isdigit() else f"{every}min")
    except ValueError:
        raise ParameterError(f"--every must be a time step such as 10min or 1h. Got {every!r} "
                             "instead.") from None
    if not pd.Timedelta(seconds=1) <= delta <= pd.Timedelta(hours=24):
        raise ParameterError(f"--every must be between 1s and 24h. Got {every!r} instead.")
    return delta / pd.Timedelta(minutes=1)


def day_schedule(workdir, date: str, every: str = "10min", heliostats=None,
                 target: str | None = None) -> pd.DataFrame:
    """Every heliostat's aims of one UTC day, one every ``every`` from 00:00 UTC (the rows with
    the sun below the horizon are dropped by :func:`aim_schedule` with ``daylight_only``).

    ``target``: a calibration target name for every aim; by default each heliostat aims at the
    target of most of its calibration rows (the receiver is not in the logs)."""
    try:
        day = pd.Timestamp(date)
    except ValueError:
        day = pd.NaT
    if pd.isna(day):
        raise ParameterError(f"--date must be a day such as 2024-06-21. Got {date!r} instead.")
    if day.tzinfo is None:
        day = day.tz_localize("UTC")
    day = day.tz_convert("UTC").normalize()
    step = _every_minutes(every)
    times = pd.date_range(day, day + pd.Timedelta(days=1), freq=pd.Timedelta(minutes=step),
                          inclusive="left")
    wd = CommittedWorkdir.of(workdir)
    ids = list(heliostats) if heliostats else sorted(read_artifact(wd, HELIOSTATS,
                                                                  columns=["heliostat_id"])["heliostat_id"])
    targets = {h: target for h in ids} if target else _usual_targets(wd, ids)
    rows = pd.DataFrame({"heliostat_id": np.repeat(ids, len(times)),
                         "time_utc": np.tile(times, len(ids))})
    rows["target"] = rows["heliostat_id"].map(targets)
    return _normalised(rows)


def _usual_targets(wd: CommittedWorkdir, ids) -> dict:
    """heliostat -> the target name of most of its calibration rows."""
    m = read_artifact(wd, MEASUREMENTS, heliostats=ids, columns=["heliostat_id", "target_name"])
    counts = m.dropna().groupby(["heliostat_id", "target_name"]).size()
    if counts.empty:
        return {}
    return {str(h): str(t) for h, t in counts.groupby(level=0).idxmax().map(lambda k: k[1]).items()}


# ------------------------------------------------------------------------------------------------
# what every heliostat's aims share
# ------------------------------------------------------------------------------------------------
@dataclass
class _Field:
    """The work directory's facts an aim table needs, read once."""

    wd: CommittedWorkdir
    helio: pd.DataFrame                 # heliostats.parquet, indexed by heliostat_id
    specs: dict
    selected: dict                      # load_selected_parameters
    models: dict                        # aim_models (strict)
    budgets: dict[str, ErrorBudget]
    target_points: dict                 # target name -> (3,) median centre [m ENU]
    regimes: dict                       # heliostat -> latest regime number (or None)
    auto: bool                          # the model is aim's choice per heliostat


def _read_field(wd: CommittedWorkdir, ids, model: str) -> _Field:
    from .aim_choice import aim_models
    from .fit_coarse import load_selected_parameters

    helio = read_artifact(wd, HELIOSTATS, heliostats=ids).set_index("heliostat_id")
    known = [h for h in ids if h in helio.index]
    selected = load_selected_parameters(wd, known) if known else {}
    specs = {h: HeliostatSpec.from_row(helio.loc[h]) for h in selected}
    models = (aim_models(wd, list(selected), strict=True) if model == "auto" and selected
              else {h: {"model": model} for h in selected})
    budgets = error_budgets(wd, specs, selected, models)
    m = read_artifact(wd, MEASUREMENTS, columns=["target_name", "target_e_m", "target_n_m",
                                                 "target_u_m"])
    points = {str(k): g[["target_e_m", "target_n_m", "target_u_m"]].median().to_numpy(float)
              for k, g in m.dropna(subset=["target_name"]).groupby("target_name")}
    return _Field(wd, helio, specs, selected, models, budgets, points, _latest_regimes(wd, known),
                  model == "auto")


def _latest_regimes(wd: CommittedWorkdir, ids) -> dict:
    from ..artifacts.schemas import REGIMES
    from ..artifacts.store import artifact_present

    if not ids or not artifact_present(wd, REGIMES):
        return {}
    r = read_artifact(wd, REGIMES, heliostats=ids, columns=["heliostat_id", "kind", "regime"])
    r = r[r["kind"] == "regime"]
    return {str(h): int(v) for h, v in r.groupby("heliostat_id")["regime"].max().items()}


# ------------------------------------------------------------------------------------------------
# one heliostat's aims
# ------------------------------------------------------------------------------------------------
def _reject(out: pd.DataFrame, mask, reason: str) -> None:
    """Mark the rows ``mask`` of ``out`` that are still ``ok`` as rejected for ``reason``."""
    mask = np.asarray(mask, bool) & (out["status"] == "ok").to_numpy()
    out.loc[mask, "status"] = "rejected"
    out.loc[mask, "reason"] = reason


def _aim_points(field: _Field, out: pd.DataFrame) -> None:
    """Fill the aim point columns from the target names; unknown names are rejected."""
    named = out["target"].notna().to_numpy()
    for name in out.loc[named, "target"].unique():
        rows = named & (out["target"] == name).to_numpy()
        point = field.target_points.get(str(name))
        if point is None:
            _reject(out, rows, f"unknown target {name!r}: give one of the measurements' targets "
                               "or aim_e_m, aim_n_m, aim_u_m")
        else:
            out.loc[rows, _POINT] = point
    _reject(out, ~np.isfinite(out[_POINT].to_numpy(float)).all(axis=1),
            "no aim point: give a target or finite aim_e_m, aim_n_m, aim_u_m")


def _sun(field: _Field, hid: str, out: pd.DataFrame) -> np.ndarray:
    """(M, 3) unit sun vectors of the rows (NaN where rejected); fills the sun angles."""
    row = field.helio.loc[hid]
    lat, lon, alt = row["latitude_deg"], row["longitude_deg"], row["altitude_m"]
    if lat is None or not np.isfinite(lat):
        _reject(out, np.ones(len(out), bool), "the heliostat has no WGS84 location for the sun")
        return np.full((len(out), 3), np.nan)
    _reject(out, out["time_utc"].isna().to_numpy(), "time_utc is not a time")
    ok = (out["status"] == "ok").to_numpy()
    az, el = np.full(len(out), np.nan), np.full(len(out), np.nan)
    if ok.any():
        alt = float(alt) if alt is not None and np.isfinite(alt) else 0.0
        az[ok], el[ok] = spa_sun_position(out.loc[ok, "time_utc"], float(lat), float(lon), alt)
    out["sun_azimuth_deg"], out["sun_elevation_deg"] = az, el
    _reject(out, ~(el > 0), "the sun is below the horizon")
    return sun_vector_enu(az, el)


def _row_parameters(field: _Field, hid: str, chosen: str, times: pd.Series) -> torch.Tensor:
    """The coarse parameters of each row: (28,) for one geometry, (M, 28) for a regime-aware
    model (its regime and drift at each row's time, as one aim takes them)."""
    if chosen == "nominal":
        return nominal_parameters(field.helio.loc[hid])
    sel = field.selected[hid]
    if sel.get("regime_table") is None:
        return sel["params"]
    t = times.where(times.notna(), pd.Timestamp("1970-01-01", tz="UTC"))
    return coarse_row_parameters(sel, t.to_numpy())


def _coarse_aims(params: torch.Tensor, spec: HeliostatSpec, sun, aim, budget: ErrorBudget
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(steps (M, 2), expected error (M,)) of the coarse model: one geometry for all rows
    (``params`` (28,)), or each row its own (``params`` (M, 28), rows as a batch of one)."""
    if params.dim() == 1:
        steps = inverse_kinematics(params, spec, sun, aim)
        safe = torch.nan_to_num(steps)
        return steps.numpy(), expected_error_mrad(budget, spec, params, safe, sun, aim)
    steps = inverse_kinematics(params, spec, sun[:, None], aim[:, None])
    safe = torch.nan_to_num(steps)
    expected = expected_error_mrad(budget, spec, params, safe, sun[:, None], aim[:, None])
    return steps[:, 0].numpy(), expected.reshape(-1)


def _fine_steps(field: _Field, hid: str, model: str, out: pd.DataFrame, sun, aim) -> np.ndarray:
    """(M, 2) steps of a fine model: :func:`.aim.aim_steps` row by row (its fixed point is
    per aim; NaN where it fails, and the failure is the row's reason)."""
    from ..errors import HeliocalError
    from .aim import aim_steps

    env_cols = [c for c in out.columns if str(c).startswith("env_")]
    steps = np.full((len(out), 2), np.nan)
    for i in np.flatnonzero((out["status"] == "ok").to_numpy()):
        env = {c[4:]: float(out.at[i, c]) for c in env_cols if pd.notna(out.at[i, c])}
        try:
            one = aim_steps(field.wd, hid, aim_point_enu=aim[i].numpy(),
                            sun_vector_enu=sun[i].numpy(), time_utc=out.at[i, "time_utc"],
                            env=env, model=model)
            steps[i] = one["axis_1_steps"], one["axis_2_steps"]
        except HeliocalError as exc:
            out.at[i, "status"], out.at[i, "reason"] = "rejected", str(exc)
    return steps


def _aim_heliostat(field: _Field, hid: str, rows: pd.DataFrame,
                   max_expected_error_mrad: float | None) -> pd.DataFrame:
    out = rows.copy().reset_index(drop=True)
    out["status"], out["reason"] = "ok", None
    if hid not in field.helio.index:
        _reject(out, np.ones(len(out), bool), "unknown heliostat: not in heliostats.parquet")
        return out
    if hid not in field.selected:
        _reject(out, np.ones(len(out), bool), "the heliostat has no coarse fit (run fit-coarse)")
        return out
    _aim_points(field, out)
    sun_np = _sun(field, hid, out)
    ok = (out["status"] == "ok").to_numpy()
    chosen = field.models.get(hid, {}).get("model", "coarse")
    requested = "auto" if field.auto else chosen
    params = _row_parameters(field, hid, chosen, out["time_utc"])
    sun = torch.tensor(np.where(ok[:, None], sun_np, [0.0, 0.0, 1.0]), dtype=torch.float64)
    aim = torch.tensor(np.nan_to_num(out[_POINT].to_numpy(float)), dtype=torch.float64)
    budget = field.budgets[hid]
    steps, expected = _coarse_aims(params, field.specs[hid], sun, aim, budget)
    if chosen not in ("coarse", "nominal"):   # the expected error stays the coarse model's
        steps = _fine_steps(field, hid, requested, out, sun, aim)
    steps[~ok] = np.nan
    _reject(out, ~np.isfinite(steps).all(axis=1), "the aim point is out of the actuators' reach")
    out["axis_1_steps"], out["axis_2_steps"] = steps[:, 0], steps[:, 1]
    out["model"] = chosen
    out["regime"] = field.regimes.get(hid)
    out["expected_error_mrad"] = np.where(np.isfinite(steps).all(axis=1), expected, np.nan)
    out["level_source"] = budget.level_source
    out["sun_distance_deg"] = sun_distance_deg(budget, sun_np)
    out["days_since_last_row"] = ((out["time_utc"] - budget.last_row_utc) / pd.Timedelta(days=1)
                                  if budget.last_row_utc is not None else np.nan)
    if max_expected_error_mrad is not None:
        _reject(out, ~(out["expected_error_mrad"] <= max_expected_error_mrad),
                f"expected error above --max-expected-error {max_expected_error_mrad:g} mrad")
    bad = (out["status"] != "ok").to_numpy()
    out.loc[bad, ["axis_1_steps", "axis_2_steps", "expected_error_mrad"]] = np.nan
    return out


# ------------------------------------------------------------------------------------------------
# the whole schedule
# ------------------------------------------------------------------------------------------------
@restores_process_state
def aim_schedule(workdir, schedule: pd.DataFrame, *, model: str = "auto",
                 max_expected_error_mrad: float | None = None,
                 daylight_only: bool = False) -> pd.DataFrame:
    """Aim every row of ``schedule`` (:func:`read_schedule` or :func:`day_schedule`).

    Parameters
    ----------
    workdir : the work directory (or its :class:`CommittedWorkdir`).
    schedule : the aims; see the module docstring.
    model : ``auto`` (what ``aim`` uses per heliostat: :func:`.aim_choice.aim_models`, the
        nominal geometry where a fit is worse than it), ``coarse`` or a fine mode.
    max_expected_error_mrad : reject aims expected to be off by more [mrad].
    daylight_only : drop the rows with the sun below the horizon instead of reporting them
        (a day's schedule).

    Returns
    -------
    DataFrame with :data:`AIM_COLUMNS` (and the schedule's env columns), in schedule order.
    """
    check_choice(model, "model", "aim", ("auto", "coarse") + MODES)
    if max_expected_error_mrad is not None and not max_expected_error_mrad > 0:
        raise ParameterError(f"--max-expected-error must be a positive number of mrad. Got "
                             f"{max_expected_error_mrad!r} instead.")
    wd = CommittedWorkdir.of(workdir)
    schedule = _normalised(schedule).assign(_order=np.arange(len(schedule)))
    ids = sorted(schedule["heliostat_id"].dropna().unique())
    field = _read_field(wd, ids, model)
    if not field.selected and ids and any(h in field.helio.index for h in ids):
        raise StageInputError(f"no coarse fit in {wd}: run `heliocal fit-coarse --workdir {wd}` "
                              "first")
    parts = []
    with one_thread():
        for hid, rows in schedule.groupby("heliostat_id", sort=True, dropna=False):
            parts.append(_aim_heliostat(field, str(hid), rows, max_expected_error_mrad))
    out = pd.concat(parts, ignore_index=True).sort_values("_order").drop(columns="_order")
    if daylight_only:
        out = out[out["reason"] != "the sun is below the horizon"]
    extra = [c for c in out.columns if c not in AIM_COLUMNS]
    return out[AIM_COLUMNS + extra].reset_index(drop=True)


def aims_csv(aims: pd.DataFrame, buffer) -> None:
    """The aim table as CSV on ``buffer`` (a path or a text stream): times ISO 8601 in UTC
    (``2024-06-21T12:00:00Z``), ten significant digits."""
    table = aims.assign(time_utc=aims["time_utc"].map(
        lambda t: t.strftime("%Y-%m-%dT%H:%M:%SZ") if pd.notna(t) else None))
    table.to_csv(buffer, index=False, float_format="%.10g")


def write_aims(aims: pd.DataFrame, path: str | Path) -> Path:
    """Write the aim table atomically as Parquet (.parquet) or CSV (.csv, :func:`aims_csv`)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise ParameterError(f"--out must end in .parquet or .csv. Got {str(path)!r} instead.")
    with atomic_path(path) as tmp:
        if suffix == ".csv":
            aims_csv(aims, tmp)
        else:
            aims.to_parquet(tmp, index=False)
    return path
