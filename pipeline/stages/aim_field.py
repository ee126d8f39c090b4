"""Many aims in one process: ``heliocal aim --schedule FILE`` and ``aim --date D --every 10min``.

A schedule is a table of aims, one row each: ``heliostat_id``, ``time_utc`` and the aim point,
either a calibration target's name (``target``) or ``aim_e_m, aim_n_m, aim_u_m`` [m ENU];
``env_<name>`` columns give the env inputs of fine models that use them. :func:`aim_schedule`
reads the work directory once, takes every heliostat's model and error budget once (the
covariances from one batched chain evaluation, :func:`.aim_budget.error_budgets`), and aims all
rows as arrays: the sun from NREL SPA for every row in one call (each at its heliostat's site),
and for the coarse model (and the nominal geometry) the inverse kinematics and the expected
error's Jacobian as tensor operations over the rows of one kinematic type, each row a batch of
one with its own parameters and spec, so that each row's numbers are those of one ``aim``.
A fine model's steps are a fixed point per row (:mod:`.aim`), solved row by row; a GP's
predictive variance at each row enters its expected error (:func:`.aim_budget.fine_level_mrad`).

Every row of the schedule gets one output row: ``status`` ``ok``, or ``rejected`` with the
reason (an unknown heliostat or target, a heliostat without a coarse fit or location, the sun
below the horizon, an aim point out of the actuators' reach, an expected error above the
limit); a bad row never stops the others. The output's columns are :data:`AIM_COLUMNS`.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from ..artifacts.manifests import CommittedWorkdir
from ..artifacts.modelfiles import check_fine_model_inputs
from ..artifacts.paths import atomic_path
from ..artifacts.schemas import HELIOSTATS, MEASUREMENTS
from ..artifacts.store import read_artifact
from ..errors import HeliocalError, InputError, ParameterError, StageInputError, check_choice
from ..models.network import MODES
from ..physics.jacobian import residual_and_jacobian
from ..physics.kinematics import inverse_kinematics
from ..physics.parameters import HeliostatSpec, nominal_parameters
from ..physics.sun import spa_sun_position, sun_vector_enu
from ..runtime.process_state import one_thread, restores_process_state
from ..models.uncertainty import aim_variance_mrad2
from .aim_budget import ErrorBudget, error_budgets, fine_level_mrad, sun_distance_deg
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
    if df.empty:
        raise InputError(f"{path}: the schedule has no rows; give one row per aim "
                         "(heliostat_id, time_utc, target)")
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
# the schedule's rows as arrays
# ------------------------------------------------------------------------------------------------
@dataclass
class _Rows:
    """The schedule's rows as arrays, in schedule order, and what is known of each so far."""

    frame: pd.DataFrame                 # the normalised schedule
    hid: np.ndarray                     # (R,) heliostat ids (str; None where missing)
    ok: np.ndarray                      # (R,) bool: not rejected (yet)
    reason: np.ndarray                  # (R,) object: why a row is rejected (None while ok)
    point: np.ndarray                   # (R, 3) aim points [m ENU]

    @classmethod
    def of(cls, frame: pd.DataFrame) -> "_Rows":
        hid = np.array([None if pd.isna(h) else str(h) for h in frame["heliostat_id"]], object)
        return cls(frame, hid, np.ones(len(frame), bool), np.full(len(frame), None, object),
                   frame[_POINT].to_numpy(float).copy())

    def reject(self, mask, reason: str) -> None:
        """Reject the rows ``mask`` that are still ok for ``reason``."""
        mask = np.asarray(mask, bool) & self.ok
        self.ok[mask] = False
        self.reason[mask] = reason


def _among(hid: np.ndarray, ids) -> np.ndarray:
    """(R,) bool: which heliostat ids ``hid`` (str or None) are in ``ids`` (a hash lookup per
    row; numpy's isin sorts object arrays, seconds for a field's day)."""
    return pd.Series(hid, dtype=object).isin(set(ids)).to_numpy(bool)


def _per_row(values: dict, hid: np.ndarray, default=None) -> np.ndarray:
    """(R,) object array: each row's heliostat's entry of ``values``."""
    return np.array([values.get(h, default) for h in hid], object)


def _aim_points(field: _Field, rows: _Rows, fitted: np.ndarray) -> None:
    """Fill the aim points of the ``fitted`` rows from their target names; unknown names and
    rows without a finite point are rejected."""
    target = rows.frame["target"]
    named = fitted & target.notna().to_numpy()
    names = target.to_numpy(object, na_value=None)
    for name in pd.unique(names[named]):
        these = named & (names == name)
        point = field.target_points.get(str(name))
        if point is None:
            rows.reject(these, f"unknown target {name!r}: give one of the measurements' targets "
                               "or aim_e_m, aim_n_m, aim_u_m")
        else:
            rows.point[these] = point
    rows.reject(fitted & ~np.isfinite(rows.point).all(axis=1),
                "no aim point: give a target or finite aim_e_m, aim_n_m, aim_u_m")


def _sun(field: _Field, rows: _Rows, fitted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((R, 2) sun azimuth and elevation [deg], (R, 3) unit sun vectors), NaN where not
    computed: NREL SPA at each row's heliostat, all rows in one call."""
    site = field.helio.reindex(pd.Index(rows.hid[fitted], dtype=object))
    lat = np.full(len(rows.hid), np.nan)
    lat[fitted] = pd.to_numeric(site["latitude_deg"], errors="coerce").to_numpy(float)
    lon, alt = np.full(len(lat), np.nan), np.full(len(lat), np.nan)
    lon[fitted] = pd.to_numeric(site["longitude_deg"], errors="coerce").to_numpy(float)
    alt[fitted] = pd.to_numeric(site["altitude_m"], errors="coerce").to_numpy(float)
    located = fitted & np.isfinite(lat)
    rows.reject(fitted & ~located, "the heliostat has no WGS84 location for the sun")
    rows.reject(located & rows.frame["time_utc"].isna().to_numpy(), "time_utc is not a time")
    angles = np.full((len(lat), 2), np.nan)
    ok = rows.ok.copy()
    if ok.any():
        az, el = spa_sun_position(rows.frame["time_utc"][ok], lat[ok], lon[ok],
                                  np.where(np.isfinite(alt[ok]), alt[ok], 0.0))
        angles[ok, 0], angles[ok, 1] = az, el
    rows.reject(located & ~(angles[:, 1] > 0), "the sun is below the horizon")
    return angles, sun_vector_enu(angles[:, 0], angles[:, 1])


def _row_parameters(field: _Field, hid: str, chosen: str, times: pd.Series) -> torch.Tensor:
    """(M, 28) coarse parameters of a heliostat's rows at ``times``: its one geometry, or for a
    regime-aware model each row's regime and drift, as one aim takes them."""
    if chosen == "nominal":
        return nominal_parameters(field.helio.loc[hid]).expand(len(times), 28)
    sel = field.selected[hid]
    if sel.get("regime_table") is None:
        return sel["params"].to(torch.float64).expand(len(times), 28)
    return coarse_row_parameters(sel, times.to_numpy())


#: Aims per batched inverse kinematics and Jacobian (rows x 3 x 28 float64: about 40 MB).
AIM_CHUNK_ROWS = 20_000


def _coarse_aims(field: _Field, rows: _Rows, chosen: np.ndarray, sun: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """((R, 2) steps, (R,) the parameters' part of the expected error's variance [mrad^2]) of
    the ok rows under the coarse model (or the nominal geometry) of their heliostat, NaN
    elsewhere: each row a batch of one with its own
    parameters and spec, the rows of one kinematic type in batches of :data:`AIM_CHUNK_ROWS`,
    so the numbers are those of one aim at a time."""
    from ..physics.lm import SPEC_TENSORS, stack_specs

    steps, variance = np.full((len(rows.hid), 2), np.nan), np.full(len(rows.hid), np.nan)
    rows_of = dict(_heliostat_rows(rows.hid, rows.ok))
    params = {h: _row_parameters(field, h, chosen[idx[0]], rows.frame["time_utc"].iloc[idx])
              for h, idx in rows_of.items()}
    groups: dict[tuple, list[str]] = {}
    for h in rows_of:
        groups.setdefault((field.specs[h].kinematic_type, field.specs[h].actuator_type), []).append(h)
    for members in groups.values():
        spec_all = stack_specs([field.specs[h] for h in members])
        code = {h: k for k, h in enumerate(members)}
        idx = np.concatenate([rows_of[h] for h in members])
        p_all = torch.cat([params[h] for h in members])
        for start in range(0, len(idx), AIM_CHUNK_ROWS):
            part = idx[start:start + AIM_CHUNK_ROWS]
            which = torch.as_tensor([code[h] for h in rows.hid[part]])
            spec = copy.copy(spec_all)
            for name in SPEC_TENSORS:
                object.__setattr__(spec, name, getattr(spec_all, name)[which])
            s, e = _aim_batch(field, rows.hid[part], spec,
                              p_all[start:start + AIM_CHUNK_ROWS],
                              torch.as_tensor(sun[part], dtype=torch.float64)[:, None],
                              torch.as_tensor(rows.point[part], dtype=torch.float64)[:, None])
            steps[part], variance[part] = s, e
    return steps, variance


def _heliostat_rows(hid: np.ndarray, mask: np.ndarray):
    """(heliostat, its rows' indices in schedule order) of the rows ``mask``, heliostat by
    heliostat in the order of their ids."""
    todo = np.flatnonzero(mask)
    todo = todo[np.argsort(hid[todo].astype(str), kind="stable")]
    bounds = np.flatnonzero(np.r_[True, hid[todo][1:] != hid[todo][:-1], True])
    for a, b in zip(bounds[:-1], bounds[1:]):
        yield hid[todo[a]], todo[a:b]


def _aim_batch(field: _Field, hid: np.ndarray, spec: HeliostatSpec, params: torch.Tensor,
               sun: torch.Tensor, aim: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(steps (K, 2), the parameters' part of the expected error's variance (K,) [mrad^2]) of K
    rows of one type, each a batch of one (``params`` (K, 28), ``sun`` and ``aim`` (K, 1, 3));
    rows of one heliostat are contiguous."""
    steps = inverse_kinematics(params, spec, sun, aim)
    with torch.no_grad():
        _, jac = residual_and_jacobian(params, spec, torch.nan_to_num(steps), sun, aim)
    jac = jac.numpy()
    variance = np.zeros(len(hid))
    bounds = np.flatnonzero(np.r_[True, hid[1:] != hid[:-1], True])
    for a, b in zip(bounds[:-1], bounds[1:]):
        budget = field.budgets[hid[a]]
        if budget.covariance is not None:
            j = jac[a:b, 0][..., budget.covariance.free_idx]
            variance[a:b] = aim_variance_mrad2(j, budget.covariance)
    return steps[:, 0].numpy(), variance


def _fine_steps(field: _Field, rows: _Rows, chosen: np.ndarray, sun: np.ndarray,
                steps: np.ndarray, gp_terms: np.ndarray) -> None:
    """The steps of the ok rows whose heliostat aims with a fine model, in place in ``steps``,
    and a GP's part of their expected error in ``gp_terms`` (R, 2) (``explained_mrad2``,
    ``noise_mrad2`` of :class:`.aim_fine.FineAim`): :func:`.aim_fine.fine_aims` (each
    heliostat's model read once, the aims' fixed points solved together); a failure is the
    row's reason."""
    fine = rows.ok & ~np.isin(chosen.astype(str), ["coarse", "nominal", "None"])
    if not fine.any():
        return
    from .aim import heliostat_of
    from .aim_fine import AimRequest, fine_aims

    stale = _stale_fine_inputs(field.wd)
    if stale is not None:                   # fit-coarse's parameters missing or stale
        steps[fine] = np.nan
        rows.reject(fine, str(stale))
        return
    env_cols = [c for c in rows.frame.columns if str(c).startswith("env_")]
    times = rows.frame["time_utc"]
    requests, rows_of = [], []
    for hid, idx in _heliostat_rows(rows.hid, fine):
        envs = [{c[4:]: float(rows.frame[c].iat[i]) for c in env_cols
                 if pd.notna(rows.frame[c].iat[i])} for i in idx]
        model = "auto" if field.auto else str(chosen[idx[0]])
        try:
            row = field.helio.loc[hid].copy()
            row["heliostat_id"] = hid
            h = heliostat_of(field.wd, row, field.selected.get(hid))
        except HeliocalError as exc:
            _reject_each(rows, steps, idx, [exc] * len(idx))
            continue
        requests.append(AimRequest(hid, model, sun[idx], rows.point[idx],
                                   [times.iat[i] for i in idx], envs,
                                   field.models.get(hid) if field.auto else None, h))
        rows_of.append(idx)
    for idx, results in zip(rows_of, fine_aims(field.wd, requests)):
        _reject_each(rows, steps, idx, results)
        for i, result in zip(idx, results):
            if not isinstance(result, Exception):
                steps[i] = result.steps
                gp_terms[i] = result.explained_mrad2, result.noise_mrad2


def _reject_each(rows: _Rows, steps: np.ndarray, idx: np.ndarray, results: list) -> None:
    """The rows ``idx`` whose result is an error rejected with it as their reason (their
    steps NaN)."""
    for i, result in zip(idx, results):
        if isinstance(result, Exception):
            steps[i] = np.nan
            rows.reject(np.arange(len(steps)) == i, str(result))


def _stale_fine_inputs(wd: CommittedWorkdir) -> HeliocalError | None:
    """Why no fine model can aim (fit-coarse's parameters missing or stale: every fine row's
    reason), or None."""
    try:
        check_fine_model_inputs(wd)
    except HeliocalError as exc:
        return exc
    return None


def _flags(field: _Field, rows: _Rows, fitted: np.ndarray, sun: np.ndarray) -> dict:
    """The fitted rows' ``level_source``, ``sun_distance_deg`` and ``days_since_last_row``."""
    distance = np.full(len(rows.hid), np.nan)
    for h, idx in _heliostat_rows(rows.hid, fitted):
        distance[idx] = sun_distance_deg(field.budgets[h], sun[idx])
    last = _per_row({h: b.last_row_utc for h, b in field.budgets.items()}, rows.hid)
    last = pd.to_datetime(pd.Series(np.where(fitted, last, None)), utc=True)
    days = ((rows.frame["time_utc"].reset_index(drop=True) - last) / pd.Timedelta(days=1)
            ).to_numpy(float)
    source = _per_row({h: b.level_source for h, b in field.budgets.items()}, rows.hid, np.nan)
    return {"level_source": np.where(fitted, source, np.nan), "sun_distance_deg": distance,
            "days_since_last_row": days}


def _expected(field: _Field, rows: _Rows, variance: np.ndarray, days: np.ndarray,
              gp_terms: np.ndarray) -> np.ndarray:
    """(R,) expected error [mrad]: the parameters' variance plus each row's level at its days
    since its heliostat's last row (:meth:`.aim_budget.ErrorBudget.level_at`), through a GP's
    predictive variance where ``gp_terms`` (R, 2) has one (:func:`.aim_budget.fine_level_mrad`; 0:
    the level as it is); NaN where the variance is."""
    level = np.full(len(rows.hid), np.nan)
    floor = np.zeros(len(rows.hid))
    for h, idx in _heliostat_rows(rows.hid, np.isfinite(variance)):
        level[idx] = field.budgets[h].level_at(days[idx])
        floor[idx] = field.budgets[h].fine_floor_ratio
    return np.sqrt(variance + fine_level_mrad(level, gp_terms[:, 0], gp_terms[:, 1], floor) ** 2)


def _aim_rows(field: _Field, schedule: pd.DataFrame,
              max_expected_error_mrad: float | None) -> pd.DataFrame:
    """Every row of the (normalised) schedule aimed, in schedule order (module docstring)."""
    rows = _Rows.of(schedule)
    known = _among(rows.hid, field.helio.index)
    rows.reject(~known, "unknown heliostat: not in heliostats.parquet")
    fitted = known & _among(rows.hid, field.selected)
    rows.reject(~fitted, "the heliostat has no coarse fit (run fit-coarse)")
    _aim_points(field, rows, fitted)
    angles, sun = _sun(field, rows, fitted)
    chosen = _per_row({h: field.models.get(h, {}).get("model", "coarse") for h in field.selected},
                      rows.hid)
    steps, variance = _coarse_aims(field, rows, chosen, np.where(rows.ok[:, None], sun, 0.0))
    gp_terms = np.zeros((len(rows.hid), 2))
    _fine_steps(field, rows, chosen, sun, steps, gp_terms)
    steps[~rows.ok] = np.nan
    rows.reject(~np.isfinite(steps).all(axis=1), "the aim point is out of the actuators' reach")
    flags = _flags(field, rows, fitted, sun)
    expected = _expected(field, rows, variance, flags["days_since_last_row"], gp_terms)
    expected = np.where(np.isfinite(steps).all(axis=1), expected, np.nan)
    if max_expected_error_mrad is not None:
        rows.reject(~(expected <= max_expected_error_mrad),
                    f"expected error above --max-expected-error {max_expected_error_mrad:g} mrad")
    steps[~rows.ok], expected[~rows.ok] = np.nan, np.nan
    out = schedule.copy()
    out[_POINT] = rows.point
    out["sun_azimuth_deg"], out["sun_elevation_deg"] = angles[:, 0], angles[:, 1]
    out["axis_1_steps"], out["axis_2_steps"] = steps[:, 0], steps[:, 1]
    out["model"] = pd.Series(np.where(fitted, chosen, np.nan), dtype="str")
    out["regime"] = pd.to_numeric(pd.Series(np.where(fitted, _per_row(field.regimes, rows.hid),
                                                     np.nan)), errors="coerce")
    out["expected_error_mrad"] = expected
    for name, values in flags.items():
        out[name] = values
    out["level_source"] = out["level_source"].astype("str")
    out["status"] = pd.Series(np.where(rows.ok, "ok", "rejected"), dtype="str")
    out["reason"] = rows.reason
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
    schedule = _normalised(schedule)
    ids = sorted(schedule["heliostat_id"].dropna().unique())
    field = _read_field(wd, ids, model)
    if not field.selected and ids and any(h in field.helio.index for h in ids):
        raise StageInputError(f"no coarse fit in {wd}: run `heliocal fit-coarse --workdir {wd}` "
                              "first")
    with one_thread():
        out = _aim_rows(field, schedule, max_expected_error_mrad)
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
