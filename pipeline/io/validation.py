"""Row validation of ``ingest``: every staged row either becomes a canonical measurement or a
rejected row with a reason (REJECTION_REASONS); plausibility checks per source.
"""

from __future__ import annotations

import datetime
import logging
import math
import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd

from ..artifacts.schemas import (HELIOSTAT_ID_RULE, MEASUREMENTS, heliostat_id_problem,
                                 suggest_heliostat_id)
from ..physics.sun import spa_sun_position, sun_vector_enu, wrap_deg
from .paint import default_properties_row
from ..vocabulary import AzimuthConvention
from .source_checks import SourceChecks
from .staged import ENV_ABS_MAX, IngestOptions, Staged, Target, time_bounds

__all__ = [
    "float_columns",
    "validate_rows",
    "invalid_id_message",
]

log = logging.getLogger("heliocal.ingest")


def float_columns(df: pd.DataFrame, names: Sequence[str]) -> list[np.ndarray]:
    """Columns ``names`` of ``df`` as float arrays (:func:`_to_float_array`; a missing column all
    NaN)."""
    return [_to_float_array(df[n].to_numpy(dtype=object)) if n in df else np.full(len(df), np.nan)
            for n in names]


def _to_float_array(cells: np.ndarray) -> np.ndarray:
    """An object array of cells as floats: text stripped and read as a number, blank, unreadable
    and non-finite cells NaN.

    One pass of plain Python over the cells and one of :func:`pandas.to_numeric` over the array:
    a frame of a few rows (a day's log, a streamed chunk) spends its time in per-call overhead,
    a large one in the per-cell loop, which a ``Series.map`` would run as well."""
    cells = np.array([np.nan if v == "" else v for v in
                      (v.strip() if isinstance(v, str) else v for v in cells)], dtype=object)
    values = pd.to_numeric(cells, errors="coerce").astype(float)
    return np.where(np.isfinite(values), values, np.nan)


# ------------------------------------------------------------------------------------------------
# validation: one reason per rejected row, in a fixed order
# ------------------------------------------------------------------------------------------------
class _Rejections:
    """The first rejection reason and detail of each row (by position in the staged frame): a
    check rejects only rows no earlier check rejected (the readers' own rejections, ``_reject``,
    come first). Kept in numpy arrays: a check on a few rows costs no pandas call."""

    def __init__(self, df: pd.DataFrame):
        first = df["_reject"].tolist()
        self.index = df.index
        self.reason = np.array([r[0] if r else None for r in first] or [], dtype=object)
        self.detail = np.array([r[1] if r else None for r in first] or [], dtype=object)
        self.open = np.array([not r for r in first], dtype=bool)  # rows no check has rejected

    def __call__(self, mask, code: str, text) -> None:
        """Reject the rows ``mask`` (booleans per row) not yet rejected with reason ``code`` and
        ``text``: one text, a sequence of texts per row, or a function of the positions of the
        rows it rejects that returns their texts (only those rows' texts are made)."""
        rows = np.flatnonzero(np.asarray(mask, dtype=bool) & self.open)
        if not len(rows):
            return
        self.reason[rows] = code
        if isinstance(text, str):
            self.detail[rows] = text
        elif callable(text):
            texts = np.empty(len(rows), dtype=object)
            texts[:] = list(text(rows))
            self.detail[rows] = texts
        else:
            self.detail[rows] = np.asarray(text, dtype=object)[rows]
        self.open[rows] = False

    def reasons(self) -> pd.Series:
        return pd.Series(self.reason, index=self.index, dtype=object)

    def details(self) -> pd.Series:
        return pd.Series(self.detail, index=self.index, dtype=object)


def _is_blank(v) -> bool:
    return v is None or (isinstance(v, float) and math.isnan(v)) or (
        isinstance(v, str) and v.strip() == "")


def _blank(df: pd.DataFrame, col: str) -> np.ndarray:
    """Rows whose ``col`` is empty (None, NaN, blank text; every row if there is no column)."""
    if col not in df:
        return np.ones(len(df), dtype=bool)
    return np.array([_is_blank(v) for v in df[col].tolist()], dtype=bool)


def _texts(text, values: list):
    """Detail texts of rejected rows: ``text(value)`` of each row's value in ``values``."""
    return lambda rows: [text(values[k]) for k in rows]


def validate_rows(st: Staged, opts: IngestOptions, checks: SourceChecks):
    """Kept rows, rejected rows and heliostat rows of staged rows (a whole source or a chunk
    holding every row of its heliostats: nothing here looks beyond one heliostat's rows, except
    what goes to ``checks``, which judges the whole source once all its chunks were seen).

    One check per step, in a fixed order; a row carries the first reason that rejects it."""
    df = st.frame.copy()
    reject = _Rejections(df)
    for col in ("heliostat_id", "measurement_id", "target_name"):
        df[col] = df[col].map(lambda v: v.strip() if isinstance(v, str) else v)
    df["heliostat_id"] = df["heliostat_id"].map(_id_text)
    heliostats = _inherit_positions(st, df)
    spot_raw = _check_required(st, df, reject)
    _check_numbers(st, df, reject, spot_raw)
    env_cols = _blank_faulty_env(df)
    _check_timestamps(df, opts, checks, reject)
    ids = df["heliostat_id"].tolist()
    known_h = np.array([isinstance(h, str) and h in heliostats for h in ids], dtype=bool)
    reject(~known_h, "unknown_heliostat",
           _texts(lambda h: f"no properties or position for heliostat {h!r}", ids))
    tgt = _resolve_targets(df, st.targets)
    reject(~tgt, "unknown_target",
           _texts(lambda t: f"target {t!r} is not in the tower/targets file",
                  df["target_name"].tolist()))
    _check_sun(st, df, opts, checks, reject, heliostats)
    _check_steps(df, heliostats, known_h, reject)
    _check_spot(df, opts, tgt, reject)
    _check_duplicates(df, reject)

    rejected = pd.DataFrame({
        "source_file": df["source_file"], "source_row": df["source_row"],
        "heliostat_id": df["heliostat_id"].map(lambda v: v if isinstance(v, str) and v else None),
        "measurement_id": df["measurement_id"].map(
            lambda v: v if isinstance(v, str) and v else None),
        "reason": reject.reasons(), "detail": reject.details(), "raw": df["raw"]}).loc[~reject.open]
    cols = MEASUREMENTS.column_names() + env_cols + (["qa_env_blanked"] if env_cols else [])
    return df.loc[reject.open, cols], rejected, heliostats


def _inherit_positions(st: Staged, df: pd.DataFrame) -> dict:
    """The heliostats' property rows: the source's, plus for a WGS84 log a default row at the
    median logged position of each heliostat without properties; a log row without a position
    inherits its heliostat's (in ``df``)."""
    heliostats = dict(st.heliostats)
    if st.kind not in ("wgs84-log", "enu-log"):
        return heliostats
    ids = df["heliostat_id"].tolist()
    if st.kind == "wgs84-log":  # an ENU log's heliostats all come from its properties
        _add_default_rows(df, ids, heliostats)
    for a in "enu":
        df[f"heliostat_{a}_m"] = _per_row(ids, {h: r[f"heliostat_{a}_m"]
                                                      for h, r in heliostats.items()})
    return heliostats


def _add_default_rows(df: pd.DataFrame, ids: list, heliostats: dict) -> None:
    """Default property rows of a WGS84 log's heliostats without one, at the median logged ENU
    position [m] of the rows whose position is complete (and their median WGS84 position [deg,
    deg, m], missing values skipped); heliostats without such a row get none."""
    pos = np.stack(float_columns(df, ["heliostat_e_m", "heliostat_n_m", "heliostat_u_m"]), axis=1)
    groups: dict[str, list[int]] = {}  # rows of each heliostat, in order of first appearance
    for k, hid in enumerate(ids):
        if isinstance(hid, str) and hid and hid not in heliostats:
            groups.setdefault(hid, []).append(k)
    wgs_cells = df["_hpos_wgs84"].tolist() if "_hpos_wgs84" in df else None
    for hid, rows in groups.items():
        good = [k for k in rows if not np.isnan(pos[k]).any()]
        if not good:
            continue
        med = np.array([np.median(pos[good, j]) for j in range(3)])
        wgs = (np.nan, np.nan, np.nan)
        if wgs_cells is not None:
            w = np.array([wgs_cells[k] for k in good], dtype=float).reshape(len(good), 3)
            wgs = tuple(float(np.median(c[~np.isnan(c)])) if (~np.isnan(c)).any() else math.nan
                        for c in w.T)
        heliostats[hid] = default_properties_row(hid, med, wgs)


def _check_required(st: Staged, df: pd.DataFrame, reject: _Rejections) -> list[str]:
    """Empty required values, invalid heliostat ids, rows with neither sun angles nor a time;
    returns the focal-spot columns the source is judged on (a WGS84 log's logged lat/lon/alt,
    from which the ENU columns derive)."""
    spot_raw = (["focal_spot_lat", "focal_spot_lon", "focal_spot_alt"] if st.kind == "wgs84-log"
                else ["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"])
    required = ["heliostat_id", "measurement_id", "axis_1_steps", "axis_2_steps", "target_name",
                *spot_raw]
    for col in required:
        reject(_blank(df, col), "missing_value", f"{col} is empty")
    _reject_invalid_ids(df["heliostat_id"], reject)
    sun_given = ~_blank(df, "sun_azimuth_deg") & ~_blank(df, "sun_elevation_deg")
    reject(~sun_given & ~_timestamp_given(df), "missing_value",
           "sun angles and timestamp are empty")
    return spot_raw


def _timestamp_given(df: pd.DataFrame) -> np.ndarray:
    """Rows with a timestamp cell that is not empty."""
    return ~_blank(df, "timestamp") if "timestamp" in df else np.zeros(len(df), dtype=bool)


def _check_numbers(st: Staged, df: pd.DataFrame, reject: _Rejections,
                   spot_raw: Sequence[str]) -> None:
    """Steps, sun angles and focal spot as finite numbers (converted in ``df``); a WGS84 spot
    within [-90, 90] / [-180, 180] deg and convertible to ENU."""
    numeric = {}
    for col in ("axis_1_steps", "axis_2_steps", "sun_azimuth_deg", "sun_elevation_deg", *spot_raw):
        if col not in df:
            continue
        raw = df[col].to_numpy(dtype=object)
        cells = raw.tolist()
        val = _to_float_array(raw)
        numeric[col] = val
        bad = np.isnan(val) & ~np.array([_is_blank(v) for v in cells], dtype=bool)
        reject(bad, "unparsable_number", _texts(lambda v, c=col: f"{c}={v!r} is not a finite number", cells))
    if st.kind == "wgs84-log":
        for col, limit in (("focal_spot_lat", 90.0), ("focal_spot_lon", 180.0)):
            val = numeric[col]
            reject(np.abs(val) > limit, "unparsable_number",
                   _texts(lambda v, c=col, lim=limit: f"{c}={v!r} is outside [-{lim:g}, {lim:g}] deg",
                          val.tolist()))
        enu = float_columns(df, ["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"])
        reject(np.isnan(np.stack(enu)).any(axis=0), "unparsable_number",
               "focal spot lat/lon/alt cannot be converted to ENU (not a point near the plant)")
    for col, val in numeric.items():
        df[col] = val


def _blank_faulty_env(df: pd.DataFrame) -> list[str]:
    """Env values: non-finite or overflowing cells are blanked (the row is kept) and listed in
    ``qa_env_blanked``; returns the env columns."""
    env_cols = [c for c in df.columns if c.startswith("env_")]
    if env_cols:
        blanked = pd.Series("", index=df.index, dtype=object)
        for col in env_cols:
            v = pd.to_numeric(df[col], errors="coerce").astype(float)
            faulty = np.isinf(v) | (v.abs() > ENV_ABS_MAX)
            if faulty.any():
                blanked[faulty] = blanked[faulty] + [f"{col}={x:g}; " for x in v[faulty]]
                df[col] = v.where(~faulty)
        df["qa_env_blanked"] = blanked.str.rstrip("; ")
    return env_cols


def _check_timestamps(df: pd.DataFrame, opts: IngestOptions, checks: SourceChecks,
                      reject: _Rejections) -> None:
    """Timestamps parsed to UTC in ``df`` (NaT where missing or refused): unreadable, a local
    time the zone skips or repeats, ambiguous day and month, no zone, implausible."""
    ts = pd.Series(pd.NaT, index=df.index, dtype="datetime64[us, UTC]")
    if "timestamp" in df:
        ts_given = _timestamp_given(df)
        parsed = _parse_timestamps(df["timestamp"], opts.timezone, opts.date_format,
                                   time_bounds(opts))
        ts = parsed.utc
        # a source whose timestamps are all naive or all ambiguous is refused (checks.finish)
        checks.add_timestamps(df, ts_given, parsed.naive, parsed.ambiguous)
        texts = df["timestamp"].tolist()
        reject(parsed.unparsable.to_numpy() & ts_given, "unparsable_timestamp", _texts(
            lambda v: f"timestamp {v!r} does not match --date-format {opts.date_format!r}"
            if opts.date_format else f"timestamp {v!r} is not a UTC time", texts))
        reject(parsed.local_problem.notna().to_numpy() & ts_given, "unparsable_timestamp",
               parsed.local_problem)
        reject(parsed.ambiguous.to_numpy() & ts_given, "ambiguous_timestamp", _texts(
            lambda v: f"timestamp {v!r} has day and month as numbers, which heliocal cannot tell "
                      "apart: give --date-format (e.g. '%d.%m.%Y %H:%M:%S%z')", texts))
        reject(parsed.naive.to_numpy() & ts_given, "unparsable_timestamp",
               _texts(lambda v: f"timestamp {v!r} has no time zone", texts))
        reject(parsed.implausible.notna().to_numpy() & ts_given, "implausible_timestamp",
               parsed.implausible)
    df["timestamp"] = ts


def _check_sun(st: Staged, df: pd.DataFrame, opts: IngestOptions, checks: SourceChecks,
               reject: _Rejections, heliostats: dict) -> None:
    """Sun angles: NREL SPA where the log has none, compared with SPA where it has them
    (``qa_sun_spa_diff_deg``, ``qa_sun_mismatch``); out of range or below the horizon rejected;
    the sun vector columns written."""
    ts = df["timestamp"]
    missing = np.full(len(df), np.nan)
    az = df["sun_azimuth_deg"].to_numpy(dtype=float) if "sun_azimuth_deg" in df else missing
    el = df["sun_elevation_deg"].to_numpy(dtype=float) if "sun_elevation_deg" in df else missing
    if opts.azimuth_convention == AzimuthConvention.north_clockwise:
        az = wrap_deg(180.0 - az)
    df["sun_source"] = np.where(~np.isnan(az) & ~np.isnan(el), "log", "spa")
    spa_diff = np.full(len(df), np.nan)  # qa_sun_spa_diff_deg
    location = _location(st, heliostats)
    can_spa = ts.notna().to_numpy() & reject.open
    if location is not None and can_spa.any():
        spa_az, spa_el = np.full(len(df), np.nan), np.full(len(df), np.nan)
        spa_az[can_spa], spa_el[can_spa] = spa_sun_position(ts[can_spa], *location)
        need = can_spa & (np.isnan(az) | np.isnan(el))
        az, el = np.where(need, spa_az, az), np.where(need, spa_el, el)
        logged = can_spa & ~need
        if logged.any():
            v_log = sun_vector_enu(az[logged], el[logged])
            v_spa = sun_vector_enu(spa_az[logged], spa_el[logged])
            diff = np.degrees(np.arccos(np.clip((v_log * v_spa).sum(axis=1), -1, 1)))
            spa_diff[logged] = diff
            checks.add_sun(az[logged], el[logged], spa_az[logged], spa_el[logged], diff)
    elif (np.isnan(az) | np.isnan(el)).any() and location is None:
        reject(np.isnan(az) | np.isnan(el), "missing_value", "sun angles are empty and there is "
               "no plant location to compute them (pass --location LAT,LON,ALT)")
    reject(np.isnan(az) | np.isnan(el), "missing_value", "sun angles are empty and no timestamp")
    reject((el > 90) | (el < -90) | (az < -360) | (az > 360), "sun_angle_out_of_range",
           lambda rows: [f"sun azimuth {az[i]:g} deg / elevation {el[i]:g} deg outside "
                         "[-360, 360] / [-90, 90]" for i in rows])
    reject(el <= 0, "sun_below_horizon",
           lambda rows: [f"sun elevation {el[i]:.3f} deg is not above the horizon" for i in rows])
    az = wrap_deg(az)
    df["sun_azimuth_deg"], df["sun_elevation_deg"] = az, el
    vec = sun_vector_enu(np.where(np.isnan(az), 0.0, az), np.where(np.isnan(el), 0.0, el))
    df["sun_e"], df["sun_n"], df["sun_u"] = vec[:, 0], vec[:, 1], vec[:, 2]
    df["qa_sun_spa_diff_deg"] = spa_diff
    df["qa_sun_mismatch"] = np.where(np.isnan(spa_diff), 0.0, spa_diff) > opts.sun_tolerance_deg


def _check_steps(df: pd.DataFrame, heliostats: dict, known_h: np.ndarray,
                 reject: _Rejections) -> None:
    """Motor steps within each axis' range of the heliostat's properties."""
    ids = df["heliostat_id"].tolist()
    for i in (1, 2):
        lo = _per_row(ids, {h: r[f"axis_{i}_min_steps"] for h, r in heliostats.items()})
        hi = _per_row(ids, {h: r[f"axis_{i}_max_steps"] for h, r in heliostats.items()})
        steps = df[f"axis_{i}_steps"].to_numpy(dtype=float)
        out = known_h & ((steps < lo) | (steps > hi))
        reject(out, "steps_out_of_range", lambda rows, i=i, s=steps, a=lo, b=hi: [
            f"axis_{i}_steps={s[k]:g} outside [{a[k]:g}, {b[k]:g}]" for k in rows])


def _per_row(ids: list, values: dict) -> np.ndarray:
    """``values`` of each row's heliostat id (NaN for an id without one), as ``Series.map`` gives
    them (an integer column stays one, a text stays text); as a float array without pandas when
    every value is a float (the properties' positions and step ranges)."""
    if all(isinstance(v, float) for v in values.values()):
        return np.array([values.get(h, np.nan) for h in ids], dtype=float)
    return pd.Series(ids, dtype=object).map(values).to_numpy()


def _check_spot(df: pd.DataFrame, opts: IngestOptions, tgt: np.ndarray,
                reject: _Rejections) -> None:
    """Focal spot within ``max_spot_distance_m`` of the (known) target's centre."""
    def column_stack(names):
        return np.stack([df[c].to_numpy(dtype=float) for c in names], axis=1)

    spot = column_stack(["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"])
    center = column_stack(["target_e_m", "target_n_m", "target_u_m"])
    dist = np.linalg.norm(spot - center, axis=1)
    reject((dist > opts.max_spot_distance_m) & tgt, "focal_spot_far_from_target", lambda rows: [
        f"focal spot {dist[k]:.1f} m from the target centre (limit "
        f"{opts.max_spot_distance_m:g} m)" for k in rows])


def _check_duplicates(df: pd.DataFrame, reject: _Rejections) -> None:
    """A measurement id seen before for the same heliostat (the first occurrence is kept).

    Ids are compared as text (a measurement id 7 and "7" are the same). The detail names the
    source row (1-based) of the first occurrence."""
    open_rows = np.flatnonzero(reject.open)
    if not len(open_rows):
        return
    hids, mids = df["heliostat_id"].tolist(), df["measurement_id"].tolist()
    source_rows = df["source_row"].tolist()
    first: dict[tuple, object] = {}
    dup = np.zeros(len(df), dtype=bool)
    seen_in = [None] * len(df)
    for k in open_rows:
        key = (str(hids[k]), str(mids[k]))
        if key in first:
            dup[k], seen_in[k] = True, first[key]
        else:
            first[key] = int(source_rows[k])
    reject(dup, "duplicate_measurement_id", lambda rows: [
        f"measurement id {mids[k]!r} already seen in source row {seen_in[k]}" for k in rows])


def _id_text(value):
    """A heliostat id as text: a Parquet log's integer ids become their digits; missing stays."""
    if isinstance(value, (bool, np.bool_)) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)) and math.isnan(value):
        return value
    return str(value)


def _reject_invalid_ids(ids: pd.Series, reject) -> None:
    """Reject rows whose heliostat id is not a safe file name (invalid_heliostat_id): the detail
    names the problem and a valid id to rename it to."""
    values = ids.tolist()
    present = {h for h in values if not (h is None or (isinstance(h, float) and math.isnan(h)))}
    problems = {h: heliostat_id_problem(h) for h in present if h != ""}
    bad = {h: p for h, p in problems.items() if p is not None}
    if not bad:
        return
    detail = {h: (f"heliostat id {h!r} cannot be used as a file name ({p}); rename it in the "
                  f"source to {HELIOSTAT_ID_RULE}, e.g. {suggest_heliostat_id(h)!r}")
              for h, p in bad.items()}
    mask = np.array([isinstance(h, str) and h in bad for h in values], dtype=bool)
    reject(mask, "invalid_heliostat_id", lambda rows: [detail[values[k]] for k in rows])


#: Day and month as numbers first (02.03.2023, 3/2/2023, 02-03-2023 ...): day.month or month/day
#: cannot be told from the text. Year-first forms (ISO 8601, 2023/03/02) are unambiguous.
_DAY_MONTH_FIRST = re.compile(r"^\s*\d{1,2}[./-]\d{1,2}[./-]\d{2,4}(?!\d)")


def _parse_one(t: str, date_format: str | None):
    """One timestamp text as a pandas Timestamp (``None``: unreadable; ``"ambiguous"``)."""
    if date_format is not None:
        try:
            return pd.Timestamp(datetime.datetime.strptime(t, date_format))
        except (ValueError, TypeError, OverflowError):
            return None
    if _DAY_MONTH_FIRST.match(t):
        return "ambiguous"
    try:
        stamp = pd.Timestamp(t)
    except (ValueError, TypeError, OverflowError):
        return None
    return None if stamp is pd.NaT else stamp


@dataclass
class _ParsedTimes:
    """Timestamps parsed to UTC, and per row why one could not be (masks, or reasons: ``None``
    for a good or missing time)."""

    utc: pd.Series              # datetime64[us, UTC]; NaT where missing or refused
    unparsable: pd.Series       # text that is no time (or does not match --date-format)
    naive: pd.Series            # a time without zone and no --timezone
    ambiguous: pd.Series        # day and month as numbers in an order that cannot be told
    local_problem: pd.Series    # a local time --timezone skips or repeats: the reason
    implausible: pd.Series      # outside --time-min / --time-max: the reason


def _local_time_problem(text: str, stamp: pd.Timestamp, timezone: str) -> str:
    """Why the naive ``stamp`` is no single instant in ``timezone`` (a clock change skips or
    repeats it; tz_localize refused it)."""
    skipped = stamp.tz_localize(timezone, nonexistent="NaT", ambiguous=True) is pd.NaT
    what = ("does not exist in time zone {} (a clock change skips it)" if skipped
            else "occurs twice in time zone {} (a clock change repeats it)").format(timezone)
    return (f"timestamp {text!r} {what}; write it with its UTC offset, e.g. "
            "2024-06-01T12:00:00+02:00")


def _parse_timestamps(values: pd.Series, timezone: str | None, date_format: str | None = None,
                      bounds: tuple[pd.Timestamp, pd.Timestamp] | None = None) -> _ParsedTimes:
    """Parse to UTC (:class:`_ParsedTimes`).

    A time outside ``bounds`` is reported as implausible and left missing; each time is converted
    to microseconds on its own, so a year outside pandas' nanosecond range never fails the whole
    column."""
    text = values.map(lambda v: v.strip() if isinstance(v, str) else ("" if v is None else str(v)))
    stamps = [None] * len(text)  # filled in a list: a Series item assignment per row is slow
    bad = np.zeros(len(text), bool)
    naive = np.zeros(len(text), bool)
    ambiguous = np.zeros(len(text), bool)
    implausible = [None] * len(text)
    local_problem = [None] * len(text)
    for i, t in enumerate(text):
        if not t or t.lower() in ("nan", "nat", "none"):
            continue
        stamp = _parse_one(t, date_format)
        if stamp is None:
            bad[i] = True
            continue
        if isinstance(stamp, str):
            ambiguous[i] = True
            continue
        if stamp.tzinfo is None:
            if timezone is None:
                naive[i] = True
                continue
            try:
                stamp = stamp.tz_localize(timezone)
            except ValueError:  # pandas: a nonexistent or ambiguous local time
                local_problem[i] = _local_time_problem(t, stamp, timezone)
                continue
        stamp = stamp.tz_convert("UTC")
        if bounds is not None and not bounds[0] <= stamp <= bounds[1]:
            which, bound = (("before --time-min", bounds[0]) if stamp < bounds[0]
                            else ("after --time-max", bounds[1]))
            implausible[i] = (f"timestamp {t!r} is {which} {bound.isoformat(timespec='seconds')}"
                              " (the plausible range of a calibration)")
            continue
        stamps[i] = stamp.to_datetime64().astype("datetime64[us]")
    micro = np.array([np.datetime64("NaT", "us") if s is None else s for s in stamps],
                     dtype="datetime64[us]")
    index = values.index
    return _ParsedTimes(pd.Series(pd.DatetimeIndex(micro).tz_localize("UTC"), index=index),
                        pd.Series(bad, index=index), pd.Series(naive, index=index),
                        pd.Series(ambiguous, index=index),
                        pd.Series(local_problem, index=index, dtype=object),
                        pd.Series(implausible, index=index, dtype=object))


def _resolve_targets(df: pd.DataFrame, targets: dict[str, Target]) -> pd.Series:
    """Fill target centre/normal from the tower file; log-given centres are used for unknown names.

    A target known only from the log's centre columns gets a normal pointing horizontally from
    the target toward the heliostat (documented assumption). Returns the mask of resolved rows.
    """
    center = np.stack(float_columns(df, ["target_e_m", "target_n_m", "target_u_m"]), axis=1)
    normal = np.stack(float_columns(df, ["target_normal_e", "target_normal_n", "target_normal_u"]),
                      axis=1)
    names = df["target_name"].tolist()
    known = np.array([isinstance(t, str) and t in targets for t in names], dtype=bool)
    if known.any():
        named = [targets[t] for t, k in zip(names, known) if k]
        center[known] = np.array([t.center_enu for t in named], dtype=float)
        normal[known] = np.array([t.normal_enu for t in named], dtype=float)
    has_center = ~np.isnan(center).any(axis=1)
    fill = has_center & np.isnan(normal).any(axis=1)
    if fill.any():
        d = (np.stack([df[c].to_numpy(dtype=float)[fill] for c in ("heliostat_e_m",
                                                                   "heliostat_n_m")], axis=1)
             - center[fill, :2])
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        d = np.where(norm > 0, d / np.where(norm > 0, norm, 1), [[0.0, 1.0]])
        normal[fill] = np.column_stack([d, np.zeros(len(d))])
    for k, a in enumerate("enu"):
        df[f"target_{a}_m"], df[f"target_normal_{a}"] = center[:, k], normal[:, k]
    resolved = has_center & ~np.isnan(normal).any(axis=1)
    return resolved & np.array([isinstance(t, str) and t != "" for t in names], dtype=bool)


def _location(st: Staged, heliostats: dict[str, dict]):
    if st.reference is not None:
        return st.reference
    return None


def invalid_id_message(n: int) -> str:
    """One line for the summary: rows rejected for their heliostat id and how to fix them."""
    return (f"{n} rows rejected as invalid_heliostat_id: heliostat ids must be {HELIOSTAT_ID_RULE} "
            "(they become file names); rename them in the source (rejected.parquet's detail "
            "suggests a name) and rerun ingest")
