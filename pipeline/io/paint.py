"""PAINT folders: heliostat properties (kinematics columns, defaults of the Juelich type) and the
calibration JSON files staged into rows, one file one row.
"""

from __future__ import annotations

import json
import logging
import math
import re
import stat
from pathlib import Path

import numpy as np
import pandas as pd
import tomllib

from ..artifacts.paths import kind_of
from ..artifacts.schemas import HELIOSTATS
from ..errors import InputError
from ..physics.geodesy import wgs84_to_enu
from .sources import TIMESTAMPS_FILENAME, TOWER_FILENAME, find_tower_file, read_tower
from .staged import IngestOptions, Staged, Target
from .text import load_json, shorten

__all__ = [
    "read_paint_properties",
    "renovation_window",
    "DEFAULT_JUELICH_PROPERTIES",
    "default_properties_row",
    "stage_paint",
    "paint_kinematics_columns",
    "read_properties_table",
]

log = logging.getLogger("heliocal.ingest")


_CALIB_RE = re.compile(r"^(?P<id>[^-_]+)[-_]calibration[-_]properties\.json$")


#: Nominal geometry of a Jülich heliostat (ARTIST's test fixture), used for log heliostats without
#: a properties file. The axis-1 initial angle is already in ARTIST's internal convention.
DEFAULT_JUELICH_PROPERTIES = {
    "kinematic_type": "juelich",
    "actuator_type": "linear",
    "initial_orientation": (0.0, -1.0, 0.0),
    "joint_1_translation": (0.0, 0.0, 0.0),
    "joint_2_translation": (0.0, 0.0, 0.0),
    "concentrator_translation": (0.0, 0.175, 0.0),
    "axes": (
        {"increment": 154166.666, "initial_stroke_length_m": 0.075, "offset_m": 0.34061,
         "pivot_radius_m": 0.3204, "initial_angle_rad": -1.570796, "clockwise": False,
         "min_steps": 0.0, "max_steps": 80000.0},
        {"increment": 154166.666, "initial_stroke_length_m": 0.075, "offset_m": 0.3479,
         "pivot_radius_m": 0.309, "initial_angle_rad": 0.959931, "clockwise": True,
         "min_steps": 0.0, "max_steps": 80000.0},
    ),
}


#: ARTIST adds this to actuator 1's ``initial_angle`` when it loads a PAINT properties file.
PAINT_AXIS_1_INITIAL_ANGLE_SHIFT_RAD = -math.pi / 2


def paint_kinematics_columns(kin: dict) -> dict:
    """heliostats.parquet columns of a PAINT ``kinematics_properties`` dict: translations and
    both linear actuators, with ARTIST's -pi/2 shift on actuator 1's ``initial_angle``.

    Raises KeyError / TypeError / ValueError on a malformed dict (the caller names the file).
    """
    row = {}
    for j, key in (("joint_1", "joint_translation_{a}_1"), ("joint_2", "joint_translation_{a}_2"),
                   ("concentrator", "concentrator_translation_{a}")):
        for a in "enu":
            row[f"{j}_translation_{a}_m"] = float(kin.get(key.format(a=a), 0.0))
    for i, act in enumerate(kin["actuators"], start=1):
        angle = float(act["initial_angle"])
        if i == 1:
            angle += PAINT_AXIS_1_INITIAL_ANGLE_SHIFT_RAD
        row.update({
            f"axis_{i}_increment": float(act["increment"]),
            f"axis_{i}_initial_stroke_length_m": float(act["initial_stroke_length"]),
            f"axis_{i}_offset_m": float(act["offset"]),
            f"axis_{i}_pivot_radius_m": float(act["pivot_radius"]),
            f"axis_{i}_initial_angle_rad": angle,
            f"axis_{i}_clockwise": bool(int(act.get("clockwise_axis_movement", 0))),
            f"axis_{i}_min_steps": float(act.get("min_increment", 0)),
            f"axis_{i}_max_steps": float(act["max_increment"]),
            f"axis_{i}_gear_ratio_steps_per_rad": np.nan,
            f"axis_{i}_angle_offset_rad": np.nan,
        })
    return row


def renovation_window(text) -> dict:
    """``renovation_start`` and ``renovation_end`` [UTC] of PAINT's ``renovation`` property: a day
    (``2022-06-09``) or a range of days (``2020-10-26/2020-11-08``); the window runs from the
    first day's midnight to the midnight after the last day. Missing values give NaT; a value
    that is not such a date raises ValueError."""
    if text is None or (isinstance(text, str) and not text.strip()):
        return {"renovation_start": pd.NaT, "renovation_end": pd.NaT}
    parts = str(text).strip().split("/")
    if len(parts) > 2:
        raise ValueError(f"renovation {text!r} is neither a date nor FIRST/LAST")
    days = [pd.Timestamp(p.strip(), tz="UTC") for p in parts]
    if any(d != d.normalize() for d in days) or days[-1] < days[0]:
        raise ValueError(f"renovation {text!r} is neither a date nor FIRST/LAST")
    return {"renovation_start": days[0], "renovation_end": days[-1] + pd.Timedelta(days=1)}


def read_paint_properties(path: Path, reference) -> dict:
    """One heliostats.parquet row from a PAINT ``<HID>-heliostat-properties.json``.

    The axis-1 ``initial_angle`` gets ARTIST's -pi/2 shift (PAINT measures it against another
    reference than ARTIST's kinematic model; AA39's 0.039009536 becomes -1.531787).
    """
    data = load_json(path, "the heliostat properties file")
    hid = path.name.split("-heliostat-properties.json")[0]
    try:
        lat, lon, alt = (float(x) for x in data["heliostat_position"])
        kin = data["kinematics_properties"]
        actuators = kin["actuators"]
        if len(actuators) != 2:
            raise ValueError(f"{len(actuators)} actuators, expected 2")
        orientation = [float(x) for x in data.get("initial_orientation", (0.0, -1.0, 0.0))]
        if len(orientation) != 3:
            raise ValueError(f"initial_orientation has {len(orientation)} components, expected 3")
        e, n, u = wgs84_to_enu(lat, lon, alt, reference)
        row = {
            "heliostat_id": hid, "kinematic_type": "juelich",
            "properties_source": str(path),
            "heliostat_e_m": float(e), "heliostat_n_m": float(n), "heliostat_u_m": float(u),
            "latitude_deg": lat, "longitude_deg": lon, "altitude_m": alt,
            "initial_orientation_e": orientation[0], "initial_orientation_n": orientation[1],
            "initial_orientation_u": orientation[2],
        }
        row.update(paint_kinematics_columns(kin))
        row.update(renovation_window(data.get("renovation")))
        types = {str(act.get("type_axis", "linear")).lower() for act in actuators}
        if types != {"linear"}:
            raise ValueError(f"actuator types {sorted(types)}; PAINT heliostats have linear actuators")
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise InputError(f"{path}: malformed heliostat properties ({shorten(exc)}); restore the "
                         "original PAINT file or remove the heliostat's folder") from exc
    row.update(actuator_type="linear", primary_axis_e=np.nan, primary_axis_n=np.nan,
               primary_axis_u=np.nan)
    return row


def default_properties_row(hid: str, position_enu, wgs84=(np.nan, np.nan, np.nan)) -> dict:
    d = DEFAULT_JUELICH_PROPERTIES
    row = {"heliostat_id": hid, "kinematic_type": d["kinematic_type"],
           "actuator_type": d["actuator_type"], "properties_source": "default-juelich",
           "heliostat_e_m": position_enu[0], "heliostat_n_m": position_enu[1],
           "heliostat_u_m": position_enu[2], "latitude_deg": wgs84[0], "longitude_deg": wgs84[1],
           "altitude_m": wgs84[2], "initial_orientation_e": d["initial_orientation"][0],
           "initial_orientation_n": d["initial_orientation"][1],
           "initial_orientation_u": d["initial_orientation"][2],
           "primary_axis_e": np.nan, "primary_axis_n": np.nan, "primary_axis_u": np.nan}
    for j in ("joint_1", "joint_2", "concentrator"):
        for a, v in zip("enu", d[f"{j}_translation"]):
            row[f"{j}_translation_{a}_m"] = v
    for i, ax in enumerate(d["axes"], start=1):
        for k, v in ax.items():
            row[f"axis_{i}_{k}"] = v
        row[f"axis_{i}_gear_ratio_steps_per_rad"] = np.nan
        row[f"axis_{i}_angle_offset_rad"] = np.nan
    return row


# properties CSV/TOML (ENU logs, ideal actuators) -------------------------------------------------
_PROPERTY_DEFAULTS = {
    "kinematic_type": "az-el", "actuator_type": "ideal",
    "initial_orientation_e": 0.0, "initial_orientation_n": -1.0, "initial_orientation_u": 0.0,
    **{f"{j}_translation_{a}_m": 0.0 for j in ("joint_1", "joint_2", "concentrator") for a in "enu"},
    **{f"axis_{i}_{k}": np.nan for i in (1, 2) for k in (
        "increment", "initial_stroke_length_m", "offset_m", "pivot_radius_m", "initial_angle_rad",
        "gear_ratio_steps_per_rad", "angle_offset_rad")},
    "axis_1_clockwise": False, "axis_2_clockwise": False,
    "primary_axis_e": np.nan, "primary_axis_n": np.nan, "primary_axis_u": np.nan,
    "latitude_deg": np.nan, "longitude_deg": np.nan, "altitude_m": np.nan,
}


_PROPERTY_REQUIRED = ("heliostat_id", "heliostat_e_m", "heliostat_n_m", "heliostat_u_m",
                      "axis_1_min_steps", "axis_1_max_steps", "axis_2_min_steps", "axis_2_max_steps")


def read_properties_table(path: Path) -> tuple[list[dict], dict[str, Target]]:
    """Heliostat properties (and optional targets) from a CSV or TOML file.

    CSV: one row per heliostat with heliostats.parquet column names. TOML: ``[heliostats.<ID>]``
    tables with the same keys, and optional ``[targets.<name>]`` tables with ``center_enu_m`` and
    ``normal_enu``. Missing optional keys take az-el/ideal defaults (see README).
    """
    targets: dict[str, Target] = {}
    if path.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: malformed TOML ({shorten(exc)}); fix the properties file") from exc
        records = [{"heliostat_id": hid, **vals} for hid, vals in data.get("heliostats", {}).items()]
        for name, spec in data.get("targets", {}).items():
            try:
                c = np.asarray(spec["center_enu_m"], float)
                nrm = np.asarray(spec.get("normal_enu", (0.0, 1.0, 0.0)), float)
            except (KeyError, TypeError, ValueError) as exc:
                raise InputError(f"{path}: target {name!r} needs center_enu_m = [e, n, u] "
                                 f"({shorten(exc)}); fix the properties file") from exc
            targets[name] = Target(name, c, nrm / np.linalg.norm(nrm))
    else:
        try:
            records = pd.read_csv(path).to_dict("records")
        except Exception as exc:  # noqa: BLE001 - pandas raises many types
            raise InputError(f"{path}: unreadable properties CSV ({shorten(exc)}); fix the file") from exc
    if not records:
        raise InputError(f"{path}: no heliostats in the properties file; add one row (CSV) or "
                         "[heliostats.<ID>] table (TOML) per heliostat")
    rows = []
    for rec in records:
        missing = [k for k in _PROPERTY_REQUIRED if k not in rec or pd.isna(rec[k])]
        if missing:
            raise InputError(f"{path}: heliostat {rec.get('heliostat_id')!r} lacks {missing}; add "
                             "them to the properties file")
        row = {**_PROPERTY_DEFAULTS, **rec, "properties_source": str(path)}
        row["heliostat_id"] = str(row["heliostat_id"])
        if row["actuator_type"] == "ideal":
            for i in (1, 2):
                for k in ("gear_ratio_steps_per_rad", "angle_offset_rad"):
                    if pd.isna(row[f"axis_{i}_{k}"]):
                        raise InputError(f"{path}: heliostat {row['heliostat_id']!r} has ideal "
                                         f"actuators but no axis_{i}_{k}; add it")
        unknown = set(row) - set(HELIOSTATS.column_names())
        if unknown:
            raise InputError(f"{path}: unknown property keys {sorted(unknown)}; see "
                             "docs/nomenclature.md (heliostats.parquet) for the names")
        rows.append(row)
    return rows, targets


def stage_paint(folder: Path, opts: IngestOptions) -> Staged:
    tower = read_tower(find_tower_file(folder, opts.tower))
    if tower.reference is None:
        raise InputError(f"{folder}: no {TOWER_FILENAME} beside or above the PAINT folder; pass "
                         "--tower PATH to the plant's tower-measurements.json")
    stamps: dict[str, str] = {}
    for cand in [folder, *folder.resolve().parents][:3]:
        if (cand / TIMESTAMPS_FILENAME).is_file():
            stamps = load_json(cand / TIMESTAMPS_FILENAME, "the timestamps map")
            if not isinstance(stamps, dict):
                raise InputError(f"{cand / TIMESTAMPS_FILENAME}: the timestamps map is not a JSON "
                                 'object {"<HID>_<id>": "<UTC time>", ...}; restore the original '
                                 "file")
            break
    helio_dirs = [folder] if (folder / "calibration").is_dir() or any(
        folder.glob("*-heliostat-properties.json")) else sorted(p for p in folder.iterdir() if p.is_dir())
    inside = folder.resolve()
    records, heliostats = [], {}
    for hdir in helio_dirs:
        hid = hdir.name
        prop = hdir / f"{hid}-heliostat-properties.json"
        props_ok = prop.is_file()
        if props_ok:
            outside = _outside_reason(prop, inside)
            if outside is not None:
                raise InputError(f"{prop}: {outside}; copy the file into {folder} or give the "
                                 "folder it is in as its own source")
            heliostats[hid] = read_paint_properties(prop, tower.reference)
        calib = hdir / "calibration"
        files = sorted(calib.glob("*.json")) if calib.is_dir() else []
        for f in files:
            m = _CALIB_RE.match(f.name)
            rec = {"source_file": str(f), "source_row": 1, "heliostat_id": hid,
                   "measurement_id": m.group("id") if m else f.stem, "_reject": None, "raw": ""}
            if not m:
                rec["_reject"] = ("malformed_file", f"file name {f.name!r} is not "
                                  "<id>-calibration-properties.json")
                rec["raw"] = f.name
                records.append(rec)
                continue
            why = _not_readable_reason(f, inside)
            if why is not None:  # never opened: a FIFO would block, a link leads outside
                rec["_reject"] = ("malformed_file", why)
                records.append(rec)
                continue
            try:
                text = f.read_text(encoding="utf-8")
                rec["raw"] = text
                data = json.loads(text)
                if not isinstance(data, dict):
                    raise ValueError("top level is not an object")
            except (UnicodeDecodeError, ValueError) as exc:
                rec["_reject"] = ("malformed_file", f"not valid JSON: {shorten(exc)}")
                if not rec["raw"]:
                    rec["raw"] = f.read_bytes()[:2000].decode("latin-1")
                records.append(rec)
                continue
            if not props_ok:
                rec["_reject"] = ("unknown_heliostat", f"no properties file {prop}")
            for key in ("motor_position", "focal_spot"):
                if not isinstance(data.get(key) or {}, dict):
                    rec["_reject"] = rec["_reject"] or (
                        "malformed_file", f"{key} is a {type(data[key]).__name__}, not an object")
                    data[key] = {}
            motor = data.get("motor_position") or {}
            rec["axis_1_steps"] = motor.get("axis_1_motor_position")
            rec["axis_2_steps"] = motor.get("axis_2_motor_position")
            rec["sun_azimuth_deg"] = data.get("sun_azimuth")
            rec["sun_elevation_deg"] = data.get("sun_elevation")
            rec["target_name"] = data.get("target_name")
            rec["timestamp"] = stamps.get(f"{hid}_{rec['measurement_id']}")
            spots = data.get("focal_spot") or {}
            preferred, other = ("UTIS", "HeliOS") if opts.focal_spot == "utis" else ("HeliOS", "UTIS")
            spot, source = spots.get(preferred), preferred
            if not _valid_triplet(spot):
                spot, source = spots.get(other), other
            if _valid_triplet(spot):
                rec["_spot_wgs84"] = tuple(float(x) for x in spot)
                rec["focal_spot_source"] = source.lower()
            else:
                rec["_spot_wgs84"] = None
                rec["focal_spot_source"] = None
            records.append(rec)
    frame = pd.DataFrame.from_records(records)
    if frame.empty:
        raise InputError(f"{folder}: no calibration files (<HID>/calibration/<id>-calibration-"
                         "properties.json) found; check the PAINT folder")
    _add_positions(frame, heliostats, tower.reference)
    return Staged(frame, heliostats, tower.targets, tower.reference, "paint")


def _add_positions(frame: pd.DataFrame, heliostats: dict, reference) -> None:
    """The staged rows' focal spot in ENU [m] (from its WGS84 triplet, NaN without one) and their
    heliostat's position [m] (NaN unless the heliostat has a properties file), as columns."""
    n = len(frame)
    spots = frame["_spot_wgs84"].tolist() if "_spot_wgs84" in frame else [None] * n
    has = np.array([isinstance(s, tuple) for s in spots], dtype=bool)
    enu = np.full((3, n), np.nan)
    if has.any():  # vectorised over the rows that have one
        arr = np.array([s for s, h in zip(spots, has) if h], float)
        enu[:, has] = wgs84_to_enu(arr[:, 0], arr[:, 1], arr[:, 2], reference)
    for k, a in enumerate("enu"):
        frame[f"focal_spot_{a}_m"] = enu[k]
    if "_spot_wgs84" in frame:
        del frame["_spot_wgs84"]
    ids = frame["heliostat_id"].tolist()
    for a in "enu":
        frame[f"heliostat_{a}_m"] = np.array(
            [heliostats[h][f"heliostat_{a}_m"] if h in heliostats else np.nan for h in ids], float)


def _outside_reason(path: Path, inside: Path) -> str | None:
    """Why ``path`` (found in the PAINT folder ``inside``, resolved) lies outside it: a symbolic
    link (of the file or a folder on the way) to elsewhere; ``None`` if it is inside."""
    target = path.resolve()
    if target == inside or inside in target.parents:
        return None
    return (f"a symbolic link to {target}, outside the PAINT folder {inside}; heliocal reads only "
            "files inside the source folder")


def _not_readable_reason(path: Path, inside: Path) -> str | None:
    """Why a calibration file is not read (``None``: it is a regular file inside the folder)."""
    why = _outside_reason(path, inside)
    if why is not None:
        return why
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if not stat.S_ISREG(mode):
        return f"{kind_of(mode)}, not a file; heliocal reads only regular files"
    return None


def _valid_triplet(v) -> bool:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        return False
    try:
        return all(math.isfinite(float(x)) for x in v)
    except (TypeError, ValueError):
        return False
