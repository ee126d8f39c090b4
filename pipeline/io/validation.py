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
from ..errors import InputError
from ..physics.sun import spa_sun_position, sun_vector_enu, wrap_deg
from .paint import default_properties_row
from ..vocabulary import AzimuthConvention
from .staged import ENV_ABS_MAX, IngestOptions, Staged, Target, time_bounds

__all__ = [
    "to_float_frame",
    "validate_rows",
    "MedianVsThreshold",
    "SourceChecks",
    "invalid_id_message",
]

log = logging.getLogger("heliocal.ingest")


def to_float_frame(df: pd.DataFrame, names: Sequence[str]) -> pd.DataFrame:
    """Columns ``names`` of ``df`` as floats (:func:`_to_float`; a missing column all NaN)."""
    return pd.DataFrame({n: _to_float(df[n]) if n in df else np.nan for n in names},
                        index=df.index)


def _to_float(series: pd.Series) -> pd.Series:
    """A column of cells as floats: text stripped and read as a number, blank, unreadable and
    non-finite cells NaN.

    One pass of plain Python over the cells and one of :func:`pandas.to_numeric` over the array:
    a frame of a few rows (a day's log, a streamed chunk) spends its time in per-call overhead,
    a large one in the per-cell loop, which a ``Series.map`` would run as well."""
    cells = series.to_numpy(dtype=object)
    cells = np.array([np.nan if v == "" else v for v in
                      (v.strip() if isinstance(v, str) else v for v in cells)], dtype=object)
    values = pd.to_numeric(cells, errors="coerce").astype(float)
    return pd.Series(np.where(np.isfinite(values), values, np.nan), index=series.index)


# ------------------------------------------------------------------------------------------------
# validation: one reason per rejected row, in a fixed order
# ------------------------------------------------------------------------------------------------
class _Rejections:
    """The first rejection reason and detail of each row: a check rejects only rows no earlier
    check rejected (the readers' own rejections, ``_reject``, come first)."""

    def __init__(self, df: pd.DataFrame):
        self.reason = pd.Series([r[0] if r else None for r in df["_reject"]], index=df.index,
                                dtype=object)
        self.detail = pd.Series([r[1] if r else None for r in df["_reject"]], index=df.index,
                                dtype=object)

    def __call__(self, mask, code: str, text) -> None:
        """Reject the rows ``mask`` not yet rejected with reason ``code`` and ``text`` (one text,
        or a Series of texts per row)."""
        mask = mask & self.reason.isna()
        if mask.any():
            self.reason[mask] = code
            self.detail[mask] = text[mask] if isinstance(text, pd.Series) else text

    @property
    def open(self) -> pd.Series:
        """Rows no check has rejected so far."""
        return self.reason.isna()


def _blank(df: pd.DataFrame, col: str) -> pd.Series:
    """Rows whose ``col`` is empty (None, NaN, blank text; every row if there is no column)."""
    if col not in df:
        return pd.Series(True, index=df.index)
    return df[col].map(lambda v: v is None or (isinstance(v, float) and math.isnan(v))
                       or (isinstance(v, str) and v.strip() == ""))


def validate_rows(st: Staged, opts: IngestOptions, checks: "SourceChecks"):
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
    known_h = df["heliostat_id"].isin(list(heliostats))
    reject(~known_h, "unknown_heliostat",
           df["heliostat_id"].map(lambda h: f"no properties or position for heliostat {h!r}"))
    tgt = _resolve_targets(df, st.targets)
    reject(~tgt, "unknown_target",
           df["target_name"].map(lambda t: f"target {t!r} is not in the tower/targets file"))
    _check_sun(st, df, opts, checks, reject, heliostats)
    _check_steps(df, heliostats, known_h, reject)
    _check_spot(df, opts, tgt, reject)
    _check_duplicates(df, reject)

    kept = df.loc[reject.open].copy()
    rejected = pd.DataFrame({
        "source_file": df["source_file"], "source_row": df["source_row"],
        "heliostat_id": df["heliostat_id"].map(lambda v: v if isinstance(v, str) and v else None),
        "measurement_id": df["measurement_id"].map(
            lambda v: v if isinstance(v, str) and v else None),
        "reason": reject.reason, "detail": reject.detail, "raw": df["raw"]}).loc[~reject.open]
    cols = MEASUREMENTS.column_names()
    kept = kept[cols + env_cols + (["qa_env_blanked"] if env_cols else [])]
    return kept, rejected, heliostats


def _inherit_positions(st: Staged, df: pd.DataFrame) -> dict:
    """The heliostats' property rows: the source's, plus for a WGS84 log a default row at the
    median logged position of each heliostat without properties; a log row without a position
    inherits its heliostat's (in ``df``)."""
    heliostats = dict(st.heliostats)
    if st.kind not in ("wgs84-log", "enu-log"):
        return heliostats
    pos = to_float_frame(df, ["heliostat_e_m", "heliostat_n_m", "heliostat_u_m"])
    for hid, grp in pos.groupby(df["heliostat_id"], sort=False):
        if hid in heliostats or not isinstance(hid, str) or not hid:
            continue
        good = grp.dropna()
        if st.kind == "enu-log" or good.empty:
            continue
        med = good.median().to_numpy()
        wgs = (np.nan, np.nan, np.nan)
        if "_hpos_wgs84" in df:
            w = pd.DataFrame(df.loc[good.index, "_hpos_wgs84"].tolist(), columns=list("abc"))
            wgs = tuple(float(x) for x in w.median())
        heliostats[hid] = default_properties_row(hid, med, wgs)
    for a in "enu":
        df[f"heliostat_{a}_m"] = df["heliostat_id"].map(
            {h: r[f"heliostat_{a}_m"] for h, r in heliostats.items()})
    return heliostats


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


def _timestamp_given(df: pd.DataFrame) -> pd.Series:
    return ~_blank(df, "timestamp") if "timestamp" in df else pd.Series(False, index=df.index)


def _check_numbers(st: Staged, df: pd.DataFrame, reject: _Rejections,
                   spot_raw: Sequence[str]) -> None:
    """Steps, sun angles and focal spot as finite numbers (converted in ``df``); a WGS84 spot
    within [-90, 90] / [-180, 180] deg and convertible to ENU."""
    numeric = {}
    for col in ("axis_1_steps", "axis_2_steps", "sun_azimuth_deg", "sun_elevation_deg", *spot_raw):
        if col not in df:
            continue
        raw_col = df[col]
        val = _to_float(raw_col.astype(object))
        numeric[col] = val
        bad = val.isna() & ~_blank(df, col)
        reject(bad, "unparsable_number", raw_col.map(lambda v, c=col: f"{c}={v!r} is not a finite number"))
    if st.kind == "wgs84-log":
        for col, limit in (("focal_spot_lat", 90.0), ("focal_spot_lon", 180.0)):
            val = numeric[col]
            reject(val.abs() > limit, "unparsable_number",
                   val.map(lambda v, c=col, lim=limit: f"{c}={v!r} is outside [-{lim:g}, {lim:g}] deg"))
        enu = to_float_frame(df, ["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"])
        reject(enu.isna().any(axis=1), "unparsable_number",
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


def _check_timestamps(df: pd.DataFrame, opts: IngestOptions, checks: "SourceChecks",
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
        reject(parsed.unparsable & ts_given, "unparsable_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} does not match --date-format "
                                             f"{opts.date_format!r}" if opts.date_format else
                                   f"timestamp {v!r} is not a UTC time"))
        reject(parsed.local_problem.notna() & ts_given, "unparsable_timestamp",
               parsed.local_problem)
        reject(parsed.ambiguous & ts_given, "ambiguous_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} has day and month as numbers, "
                                             "which heliocal cannot tell apart: give "
                                             "--date-format (e.g. '%d.%m.%Y %H:%M:%S%z')"))
        reject(parsed.naive & ts_given, "unparsable_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} has no time zone"))
        reject(parsed.implausible.notna() & ts_given, "implausible_timestamp", parsed.implausible)
    df["timestamp"] = ts


def _check_sun(st: Staged, df: pd.DataFrame, opts: IngestOptions, checks: "SourceChecks",
               reject: _Rejections, heliostats: dict) -> None:
    """Sun angles: NREL SPA where the log has none, compared with SPA where it has them
    (``qa_sun_spa_diff_deg``, ``qa_sun_mismatch``); out of range or below the horizon rejected;
    the sun vector columns written."""
    ts = df["timestamp"]
    missing = pd.Series(np.nan, index=df.index)
    az = df["sun_azimuth_deg"].astype(float) if "sun_azimuth_deg" in df else missing
    el = df["sun_elevation_deg"].astype(float) if "sun_elevation_deg" in df else missing
    if opts.azimuth_convention == AzimuthConvention.north_clockwise:
        az = pd.Series(wrap_deg(180.0 - az.to_numpy()), index=df.index)
    df["sun_source"] = np.where(az.notna() & el.notna(), "log", "spa")
    df["qa_sun_spa_diff_deg"] = np.nan
    location = _location(st, heliostats)
    can_spa = ts.notna() & reject.open
    if location is not None and can_spa.any():
        spa_az, spa_el = spa_sun_position(ts[can_spa], *location)
        spa_az = pd.Series(spa_az, index=ts[can_spa].index)
        spa_el = pd.Series(spa_el, index=ts[can_spa].index)
        need = can_spa & (az.isna() | el.isna())
        az = az.where(~need, spa_az.reindex(df.index))
        el = el.where(~need, spa_el.reindex(df.index))
        logged = can_spa & ~need
        if logged.any():
            v_log = sun_vector_enu(az[logged], el[logged])
            v_spa = sun_vector_enu(spa_az[logged], spa_el[logged])
            diff = np.degrees(np.arccos(np.clip((v_log * v_spa).sum(axis=1), -1, 1)))
            df.loc[logged, "qa_sun_spa_diff_deg"] = diff
            checks.add_sun(az[logged], el[logged], spa_az[logged], spa_el[logged], diff)
    elif (az.isna() | el.isna()).any() and location is None:
        reject(az.isna() | el.isna(), "missing_value", "sun angles are empty and there is no plant "
               "location to compute them (pass --location LAT,LON,ALT)")
    reject(az.isna() | el.isna(), "missing_value", "sun angles are empty and no timestamp")
    reject((el > 90) | (el < -90) | (az < -360) | (az > 360), "sun_angle_out_of_range",
           pd.Series([f"sun azimuth {a:g} deg / elevation {e:g} deg outside [-360, 360] / [-90, 90]"
                      for a, e in zip(az, el)], index=df.index))
    reject(el <= 0, "sun_below_horizon",
           el.map(lambda e: f"sun elevation {e:.3f} deg is not above the horizon"))
    az = pd.Series(wrap_deg(az.to_numpy()), index=df.index)
    df["sun_azimuth_deg"], df["sun_elevation_deg"] = az, el
    vec = sun_vector_enu(az.fillna(0), el.fillna(0))
    df["sun_e"], df["sun_n"], df["sun_u"] = vec[:, 0], vec[:, 1], vec[:, 2]
    df["qa_sun_mismatch"] = df["qa_sun_spa_diff_deg"].fillna(0.0) > opts.sun_tolerance_deg


def _check_steps(df: pd.DataFrame, heliostats: dict, known_h: pd.Series,
                 reject: _Rejections) -> None:
    """Motor steps within each axis' range of the heliostat's properties."""
    for i in (1, 2):
        lo = df["heliostat_id"].map({h: r[f"axis_{i}_min_steps"] for h, r in heliostats.items()})
        hi = df["heliostat_id"].map({h: r[f"axis_{i}_max_steps"] for h, r in heliostats.items()})
        steps = df[f"axis_{i}_steps"].astype(float)
        out = known_h & ((steps < lo) | (steps > hi))
        reject(out, "steps_out_of_range", pd.Series(
            [f"axis_{i}_steps={s:g} outside [{a:g}, {b:g}]" for s, a, b in zip(steps, lo, hi)],
            index=df.index))


def _check_spot(df: pd.DataFrame, opts: IngestOptions, tgt: pd.Series,
                reject: _Rejections) -> None:
    """The focal spot within --max-spot-distance of its (known) target's centre."""
    spot = df[["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"]].astype(float).to_numpy()
    center = df[["target_e_m", "target_n_m", "target_u_m"]].astype(float).to_numpy()
    dist = np.linalg.norm(spot - center, axis=1)
    far = pd.Series(dist > opts.max_spot_distance_m, index=df.index) & tgt
    reject(far, "focal_spot_far_from_target", pd.Series(
        [f"focal spot {d:.1f} m from the target centre (limit {opts.max_spot_distance_m:g} m)"
         for d in dist], index=df.index))


def _check_duplicates(df: pd.DataFrame, reject: _Rejections) -> None:
    """A measurement id seen before for the same heliostat (the first occurrence is kept)."""
    key = df["heliostat_id"].astype(str) + "\0" + df["measurement_id"].astype(str)
    ok_so_far = reject.open
    first_row = df.loc[ok_so_far].groupby(key[ok_so_far])["source_row"].transform("first")
    dup = key[ok_so_far].duplicated(keep="first")
    dup = dup.reindex(df.index, fill_value=False)
    reject(dup, "duplicate_measurement_id", pd.Series(
        [f"measurement id {m!r} already seen in source row {r}" for m, r in
         zip(df["measurement_id"], first_row.reindex(df.index))], index=df.index))


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
    problems = {h: heliostat_id_problem(h) for h in ids.dropna().unique() if h != ""}
    bad = {h: p for h, p in problems.items() if p is not None}
    if not bad:
        return
    detail = {h: (f"heliostat id {h!r} cannot be used as a file name ({p}); rename it in the "
                  f"source to {HELIOSTAT_ID_RULE}, e.g. {suggest_heliostat_id(h)!r}")
              for h, p in bad.items()}
    mask = ids.map(lambda h: h in bad if isinstance(h, str) else False).astype(bool)
    reject(mask, "invalid_heliostat_id",
           ids.map(lambda h: detail.get(h) if isinstance(h, str) else None))


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
    for col in ("target_e_m", "target_n_m", "target_u_m", "target_normal_e", "target_normal_n",
                "target_normal_u"):
        if col not in df:
            df[col] = np.nan
        df[col] = _to_float(df[col].astype(object))
    names = df["target_name"]
    known = names.isin(list(targets))
    if known.any():
        named = [targets[n] for n in names[known]]
        df.loc[known, ["target_e_m", "target_n_m", "target_u_m"]] = np.array(
            [t.center_enu for t in named], dtype=float)
        df.loc[known, ["target_normal_e", "target_normal_n", "target_normal_u"]] = np.array(
            [t.normal_enu for t in named], dtype=float)
    has_center = df[["target_e_m", "target_n_m", "target_u_m"]].notna().all(axis=1)
    no_normal = df[["target_normal_e", "target_normal_n", "target_normal_u"]].isna().any(axis=1)
    fill = has_center & no_normal
    if fill.any():
        d = (df.loc[fill, ["heliostat_e_m", "heliostat_n_m"]].to_numpy(float)
             - df.loc[fill, ["target_e_m", "target_n_m"]].to_numpy(float))
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        d = np.where(norm > 0, d / np.where(norm > 0, norm, 1), [[0.0, 1.0]])
        df.loc[fill, "target_normal_e"] = d[:, 0]
        df.loc[fill, "target_normal_n"] = d[:, 1]
        df.loc[fill, "target_normal_u"] = 0.0
    resolved = has_center & df[["target_normal_e", "target_normal_n", "target_normal_u"]].notna().all(axis=1)
    return resolved & names.map(lambda v: isinstance(v, str) and v != "")


def _location(st: Staged, heliostats: dict[str, dict]):
    if st.reference is not None:
        return st.reference
    return None


# ------------------------------------------------------------------------------------------------
# whole-source checks, accumulated over the chunks of a source
# ------------------------------------------------------------------------------------------------
class MedianVsThreshold:
    """Compares the median of values seen in chunks with a fixed threshold, in constant memory.

    :meth:`median` returns ``np.median`` of all values when the two middle values lie on both
    sides of the threshold (they are then the largest value below and the smallest above it,
    which are kept), and otherwise a value on the same side of the threshold as the median.
    """

    def __init__(self, threshold: float):
        self.threshold = float(threshold)
        self.n_lt = self.n_eq = self.n_gt = self.n_nan = 0
        self.max_lt, self.min_gt = -math.inf, math.inf

    @property
    def n(self) -> int:
        return self.n_lt + self.n_eq + self.n_gt + self.n_nan

    def add(self, values) -> None:
        v = np.asarray(values, float)
        lt, gt, nan = v < self.threshold, v > self.threshold, np.isnan(v)
        self.n_lt += int(lt.sum())
        self.n_gt += int(gt.sum())
        self.n_nan += int(nan.sum())
        self.n_eq += int(len(v) - lt.sum() - gt.sum() - nan.sum())
        if lt.any():
            self.max_lt = max(self.max_lt, float(v[lt].max()))
        if gt.any():
            self.min_gt = min(self.min_gt, float(v[gt].min()))

    def median(self) -> float:
        if self.n_nan:
            return math.nan

        def at(i: int) -> float:
            if i < self.n_lt:
                return self.max_lt
            return self.threshold if i < self.n_lt + self.n_eq else self.min_gt

        n = self.n
        if n % 2:
            return at(n // 2)
        return (at(n // 2 - 1) + at(n // 2)) / 2


class SourceChecks:
    """Checks of :func:`validate_rows` that judge a whole source (time zones, azimuth convention):
    the chunks of one source add their rows here, :meth:`finish` raises once all were seen."""

    def __init__(self, opts: IngestOptions):
        self.opts = opts
        self.first: tuple | None = None  # (row label, source file) of the source's first row
        self.ts_given = 0
        self.naive = 0
        self.naive_example: tuple | None = None  # (row label, timestamp)
        self.ambiguous = 0
        self.ambiguous_example: tuple | None = None
        self.sun_diff = MedianVsThreshold(5 * opts.sun_tolerance_deg + 1.0)
        self.sun_alt_diff = MedianVsThreshold(1.0)

    def add_rows(self, df: pd.DataFrame) -> None:
        if len(df):
            label = df.index.min()
            if self.first is None or label < self.first[0]:
                self.first = (label, df.loc[label, "source_file"])

    def add_timestamps(self, df: pd.DataFrame, ts_given: pd.Series, naive: pd.Series,
                       ambiguous: pd.Series | None = None) -> None:
        self.ts_given += int(ts_given.sum())
        self.naive += int((naive & ts_given).sum())
        if ambiguous is not None and ambiguous.any():
            self.ambiguous += int((ambiguous & ts_given).sum())
            label = ambiguous[ambiguous].index.min()
            if self.ambiguous_example is None or label < self.ambiguous_example[0]:
                self.ambiguous_example = (label, df.loc[label, "timestamp"])
        if naive.any():
            label = naive[naive].index.min()
            if self.naive_example is None or label < self.naive_example[0]:
                self.naive_example = (label, df.loc[label, "timestamp"])

    def add_sun(self, az, el, spa_az, spa_el, diff) -> None:
        """Logged sun angles against SPA, and the same with azimuths read north-clockwise."""
        alt = sun_vector_enu(wrap_deg(180.0 - np.asarray(az, float)), el)
        alt_diff = np.degrees(np.arccos(np.clip((alt * sun_vector_enu(spa_az, spa_el)).sum(axis=1),
                                                -1, 1)))
        self.sun_diff.add(diff)
        self.sun_alt_diff.add(alt_diff)

    def finish(self) -> None:
        source = self.first[1] if self.first else "?"
        if self.naive and self.naive == self.ts_given and self.opts.timezone is None:
            raise InputError(f"{source}: timestamps have no time zone (e.g. "
                             f"{self.naive_example[1]!r}); add a UTC offset such as 'Z' or pass "
                             "--timezone Europe/Berlin")
        if self.ambiguous and self.ambiguous == self.ts_given:
            raise InputError(f"{source}: timestamps such as {self.ambiguous_example[1]!r} write "
                             "day and month as numbers, and heliocal cannot tell which is which; "
                             "pass --date-format, e.g. '%d.%m.%Y %H:%M:%S%z' (day first) or "
                             "'%m/%d/%Y %H:%M:%S%z' (month first)")
        # a log whose azimuths are clearly north-clockwise (0 = north) is refused
        if (self.opts.azimuth_convention == "south" and self.sun_diff.n >= 3
                and not self.sun_diff.median() <= self.sun_diff.threshold
                and self.sun_alt_diff.median() < 1.0):
            raise InputError(f"{source}: sun azimuths look north-clockwise (0 = north); heliocal's "
                             "convention is 0 = south, positive toward east: pass "
                             "--azimuth-convention north-clockwise")


def invalid_id_message(n: int) -> str:
    """One line for the summary: rows rejected for their heliostat id and how to fix them."""
    return (f"{n} rows rejected as invalid_heliostat_id: heliostat ids must be {HELIOSTAT_ID_RULE} "
            "(they become file names); rename them in the source (rejected.parquet's detail "
            "suggests a name) and rerun ingest")
