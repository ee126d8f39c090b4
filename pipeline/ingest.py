"""``ingest``: PAINT folders and flat CSV/Parquet logs into the canonical measurement table.

Three source kinds are detected automatically (:func:`detect_source`):

``paint``
    A PAINT download: ``<HID>/<HID>-heliostat-properties.json`` and
    ``<HID>/calibration/<id>-calibration-properties.json`` (or ``<id>_calibration_properties.json``),
    UTC times from a ``timestamps.json`` map (``"<HID>_<id>"``) found in or above the folder, and the
    plant's ``tower-measurements.json`` found beside or above it (or given). One JSON file is one
    input row.
``wgs84-log``
    A flat CSV or Parquet calibration log with WGS84 coordinates (``focal_spot_lat/lon/alt``,
    ``heliostat_lat/lon/alt``), like the Jülich calibration log.
``enu-log``
    A flat CSV or Parquet log already in local ENU metres (``focal_spot_e_m`` ...), with the
    heliostat properties (and targets) from a small CSV or TOML file (``--properties``).

Nothing is lost: every input row ends in ``measurements.parquet`` or, with a reason, in
``rejected.parquet``. A source that cannot be read at all raises :class:`InputError` (one line
naming the file, the problem and the fix) before any artifact is written.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from .artifacts import artifact_path, write_artifact
from .errors import InputError, check_choice, check_float
from .geodesy import wgs84_to_enu
from .schemas import HELIOSTATS, MEASUREMENTS, REJECTED, REJECTION_REASONS
from .sun import spa_sun_position, sun_vector_enu, wrap_deg

__all__ = [
    "SOURCE_KINDS",
    "IngestOptions",
    "Tower",
    "detect_source",
    "find_tower_file",
    "read_tower",
    "read_paint_properties",
    "ingest",
    "run_ingest",
    "DEFAULT_JUELICH_PROPERTIES",
]

log = logging.getLogger("heliocal.ingest")

SOURCE_KINDS = ("paint", "wgs84-log", "enu-log")
TOWER_FILENAME = "tower-measurements.json"
TIMESTAMPS_FILENAME = "timestamps.json"
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


# ------------------------------------------------------------------------------------------------
# options and small types
# ------------------------------------------------------------------------------------------------
@dataclass
class IngestOptions:
    """Resolved options of ``ingest`` (see the CLI's help for each)."""

    tower: Path | None = None
    properties: Path | None = None
    focal_spot: str = "utis"
    max_spot_distance_m: float = 25.0
    sun_tolerance_deg: float = 0.1
    azimuth_convention: str = "south"  # or "north-clockwise"
    timezone: str | None = None
    location: tuple[float, float, float] | None = None

    def validate(self) -> "IngestOptions":
        check_choice(self.focal_spot, "focal_spot", "ingest", ("utis", "helios"))
        check_choice(self.azimuth_convention, "azimuth_convention", "ingest",
                     ("south", "north-clockwise"))
        check_float(self.max_spot_distance_m, "max_spot_distance_m", "ingest", 0.0, None, False)
        check_float(self.sun_tolerance_deg, "sun_tolerance_deg", "ingest", 0.0, None, False)
        return self


@dataclass
class Target:
    name: str
    center_enu: np.ndarray
    normal_enu: np.ndarray


@dataclass
class Tower:
    """The plant reference point (WGS84) and its calibration targets (ENU)."""

    path: Path | None
    reference: tuple[float, float, float] | None
    targets: dict[str, Target] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------
# detection
# ------------------------------------------------------------------------------------------------
def _is_paint_folder(path: Path) -> bool:
    if not path.is_dir():
        return False
    if any(path.glob("*-heliostat-properties.json")) or (path / "calibration").is_dir():
        return True
    return any(p.is_dir() and (any(p.glob("*-heliostat-properties.json"))
                               or (p / "calibration").is_dir()) for p in path.iterdir())


def _read_header(path: Path) -> list[str]:
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        import pyarrow.parquet as pq

        try:
            return list(pq.read_schema(path).names)
        except Exception as exc:  # noqa: BLE001 - pyarrow raises several types
            raise InputError(f"{path}: not a readable Parquet file ({_short(exc)}); export the log "
                             "again or give a CSV") from exc
    text = _decode_text(path, path.read_bytes())
    try:
        for cells in csv.reader(io.StringIO(text, newline=""), skipinitialspace=True):
            if cells and any(c.strip() for c in cells):
                return [c.strip() for c in cells]
    except csv.Error as exc:
        raise InputError(f"{path}: malformed CSV header ({_short(exc)}); fix the first line") from exc
    raise InputError(f"{path}: the file is empty; give a calibration log with a header row "
                     "and one row per measurement")


def detect_source(path: str | os.PathLike) -> str:
    """Return the kind of ``path`` (one of :data:`SOURCE_KINDS`) or raise :class:`InputError`."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder; check the path")
    if path.is_dir():
        if _is_paint_folder(path):
            return "paint"
        raise InputError(f"{path}: a folder without PAINT heliostat folders (<HID>/calibration/); "
                         "give a PAINT download folder or a CSV/Parquet log file")
    if path.suffix.lower() not in (".csv", ".txt", ".parquet", ".pq"):
        raise InputError(f"{path}: unknown file type {path.suffix!r}; give a .csv or .parquet "
                         "calibration log or a PAINT folder")
    cols = set(_read_header(path))
    if {"focal_spot_lat", "focal_spot_lon", "focal_spot_alt"} <= cols:
        return "wgs84-log"
    if {"focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"} <= cols:
        return "enu-log"
    if len(cols) == 1 and any(d in next(iter(cols)) for d in ";\t|"):
        raise InputError(f"{path}: the header has one column; the file seems to use "
                         f"{_guess_delimiter(next(iter(cols)))!r} as delimiter: save it "
                         "comma-separated")
    raise InputError(f"{path}: missing required columns: neither focal_spot_lat/lon/alt (WGS84 "
                     "log) nor focal_spot_e_m/n_m/u_m (ENU log); see README 'Input formats'")


def _guess_delimiter(header: str) -> str:
    return max(";\t|", key=header.count)


def _short(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:160]


# ------------------------------------------------------------------------------------------------
# tower file and PAINT properties
# ------------------------------------------------------------------------------------------------
def find_tower_file(source: Path, explicit: Path | None = None, levels: int = 4) -> Path | None:
    """The tower file given explicitly, or ``tower-measurements.json`` beside or above ``source``."""
    if explicit is not None:
        explicit = Path(explicit)
        if not explicit.is_file():
            raise InputError(f"{explicit}: tower file not found; check the --tower path")
        return explicit
    here = source if source.is_dir() else source.parent
    for folder in [here, *here.resolve().parents][: levels + 1]:
        candidate = folder / TOWER_FILENAME
        if candidate.is_file():
            return candidate
    return None


def _load_json(path: Path, what: str):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: {what} is not UTF-8 text; restore the original file") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: {what} is not valid JSON (line {exc.lineno}: {exc.msg}); "
                         "restore the original file") from exc


def read_tower(path: Path | None) -> Tower:
    """Parse a PAINT ``tower-measurements.json``: reference point and targets (ENU)."""
    if path is None:
        return Tower(path=None, reference=None)
    data = _load_json(path, "the tower file")
    try:
        ref = tuple(float(x) for x in data["power_plant_properties"]["coordinates"])
        if len(ref) != 3:
            raise ValueError("coordinates must be [lat, lon, alt]")
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: power_plant_properties.coordinates [lat, lon, alt] is missing or "
                         f"malformed ({_short(exc)}); fix the tower file") from exc
    targets = {}
    for name, spec in data.items():
        if name == "power_plant_properties" or not isinstance(spec, dict):
            continue
        try:
            center = [float(x) for x in spec["coordinates"]["center"]]
            normal = np.asarray([float(x) for x in spec.get("normal_vector", (0, 1, 0))], float)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path}: target {name!r} has no readable coordinates.center "
                             f"({_short(exc)}); fix the tower file") from exc
        e, n, u = wgs84_to_enu(center[0], center[1], center[2], ref)
        targets[name] = Target(name, np.array([float(e), float(n), float(u)]),
                               normal / np.linalg.norm(normal))
    return Tower(path=path, reference=ref, targets=targets)


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


def read_paint_properties(path: Path, reference) -> dict:
    """One heliostats.parquet row from a PAINT ``<HID>-heliostat-properties.json``.

    The axis-1 ``initial_angle`` gets ARTIST's -pi/2 shift (PAINT measures it against another
    reference than ARTIST's kinematic model; AA39's 0.039009536 becomes -1.531787).
    """
    data = _load_json(path, "the heliostat properties file")
    hid = path.name.split("-heliostat-properties.json")[0]
    try:
        lat, lon, alt = (float(x) for x in data["heliostat_position"])
        kin = data["kinematics_properties"]
        actuators = kin["actuators"]
        if len(actuators) != 2:
            raise ValueError(f"{len(actuators)} actuators, expected 2")
        orientation = [float(x) for x in data.get("initial_orientation", (0.0, -1.0, 0.0))]
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
        types = {str(act.get("type_axis", "linear")).lower() for act in actuators}
        if types != {"linear"}:
            raise ValueError(f"actuator types {sorted(types)}; PAINT heliostats have linear actuators")
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: malformed heliostat properties ({_short(exc)}); restore the "
                         "original PAINT file or remove the heliostat's folder") from exc
    row.update(actuator_type="linear", primary_axis_e=np.nan, primary_axis_n=np.nan,
               primary_axis_u=np.nan)
    return row


def _default_properties_row(hid: str, position_enu, wgs84=(np.nan, np.nan, np.nan)) -> dict:
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
            raise InputError(f"{path}: malformed TOML ({_short(exc)}); fix the properties file") from exc
        records = [{"heliostat_id": hid, **vals} for hid, vals in data.get("heliostats", {}).items()]
        for name, spec in data.get("targets", {}).items():
            try:
                c = np.asarray(spec["center_enu_m"], float)
                nrm = np.asarray(spec.get("normal_enu", (0.0, 1.0, 0.0)), float)
            except (KeyError, TypeError, ValueError) as exc:
                raise InputError(f"{path}: target {name!r} needs center_enu_m = [e, n, u] "
                                 f"({_short(exc)}); fix the properties file") from exc
            targets[name] = Target(name, c, nrm / np.linalg.norm(nrm))
    else:
        try:
            records = pd.read_csv(path).to_dict("records")
        except Exception as exc:  # noqa: BLE001 - pandas raises many types
            raise InputError(f"{path}: unreadable properties CSV ({_short(exc)}); fix the file") from exc
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


# ------------------------------------------------------------------------------------------------
# staging: every source becomes a frame of raw values plus provenance columns
# ------------------------------------------------------------------------------------------------
_STAGED_NUMERIC = ("axis_1_steps", "axis_2_steps", "sun_azimuth_deg", "sun_elevation_deg",
                   "focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m",
                   "heliostat_e_m", "heliostat_n_m", "heliostat_u_m",
                   "target_e_m", "target_n_m", "target_u_m",
                   "target_normal_e", "target_normal_n", "target_normal_u")


@dataclass
class _Staged:
    """Raw rows of one source (strings or numbers), plus what the source defines."""

    frame: pd.DataFrame  # canonical names, raw values, source_file, source_row, raw, _reject
    heliostats: dict[str, dict]
    targets: dict[str, Target]
    reference: tuple[float, float, float] | None
    kind: str
    ignored_columns: list[str] = field(default_factory=list)


def _stage_paint(folder: Path, opts: IngestOptions) -> _Staged:
    tower = read_tower(find_tower_file(folder, opts.tower))
    if tower.reference is None:
        raise InputError(f"{folder}: no {TOWER_FILENAME} beside or above the PAINT folder; pass "
                         "--tower PATH to the plant's tower-measurements.json")
    stamps: dict[str, str] = {}
    for cand in [folder, *folder.resolve().parents][:3]:
        if (cand / TIMESTAMPS_FILENAME).is_file():
            stamps = _load_json(cand / TIMESTAMPS_FILENAME, "the timestamps map")
            break
    helio_dirs = [folder] if (folder / "calibration").is_dir() or any(
        folder.glob("*-heliostat-properties.json")) else sorted(p for p in folder.iterdir() if p.is_dir())
    records, heliostats = [], {}
    for hdir in helio_dirs:
        hid = hdir.name
        prop = hdir / f"{hid}-heliostat-properties.json"
        props_ok = prop.is_file()
        if props_ok:
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
            try:
                text = f.read_text(encoding="utf-8")
                rec["raw"] = text
                data = json.loads(text)
                if not isinstance(data, dict):
                    raise ValueError("top level is not an object")
            except (UnicodeDecodeError, ValueError) as exc:
                rec["_reject"] = ("malformed_file", f"not valid JSON: {_short(exc)}")
                if not rec["raw"]:
                    rec["raw"] = f.read_bytes()[:2000].decode("latin-1")
                records.append(rec)
                continue
            if not props_ok:
                rec["_reject"] = ("unknown_heliostat", f"no properties file {prop}")
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
    # focal spot WGS84 -> ENU (vectorised over the rows that have one)
    for col in ("focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"):
        frame[col] = np.nan
    has = frame["_spot_wgs84"].map(lambda s: isinstance(s, tuple)) if "_spot_wgs84" in frame else None
    if has is not None and has.any():
        arr = np.array(frame.loc[has, "_spot_wgs84"].tolist(), float)
        e, n, u = wgs84_to_enu(arr[:, 0], arr[:, 1], arr[:, 2], tower.reference)
        frame.loc[has, "focal_spot_e_m"], frame.loc[has, "focal_spot_n_m"] = e, n
        frame.loc[has, "focal_spot_u_m"] = u
    frame = frame.drop(columns=["_spot_wgs84"], errors="ignore")
    for hid, row in heliostats.items():
        sel = frame["heliostat_id"] == hid
        for a in "enu":
            frame.loc[sel, f"heliostat_{a}_m"] = row[f"heliostat_{a}_m"]
    return _Staged(frame, heliostats, tower.targets, tower.reference, "paint")


def _valid_triplet(v) -> bool:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        return False
    try:
        return all(math.isfinite(float(x)) for x in v)
    except (TypeError, ValueError):
        return False


_LOG_ALIASES = {
    "measurement_id": ("measurement_id", "sample_id", "id"),
    "axis_1_steps": ("axis_1_steps", "axis_1_motor_position"),
    "axis_2_steps": ("axis_2_steps", "axis_2_motor_position"),
    "sun_azimuth_deg": ("sun_azimuth_deg", "sun_azimuth"),
    "sun_elevation_deg": ("sun_elevation_deg", "sun_elevation"),
}
_LOG_RECOGNISED_IGNORED = ("tracking_error_lat", "tracking_error_lon", "tracking_error_alt",
                           "tracking_error_e_m", "tracking_error_n_m", "tracking_error_u_m")


def _decode_text(path: Path, raw: bytes) -> str:
    """Decode a CSV's bytes as UTF-8 (with or without BOM) or raise a one-line InputError."""
    if not raw.strip():
        raise InputError(f"{path}: the file is empty; give a calibration log with a header row "
                         "and one row per measurement")
    if b"\0" in raw[:65536]:
        raise InputError(f"{path}: binary data, not a CSV text file; give a CSV (comma-separated, "
                         "UTF-8) or Parquet calibration log")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise InputError(f"{path}: not UTF-8 text (line {line}, byte {exc.start}); re-save the log "
                         "as UTF-8 CSV") from exc


def _read_csv_records(path: Path) -> tuple[list[str], list[list[str]]]:
    """Header and data rows of a comma-separated UTF-8 file, every cell a stripped string.

    Blank lines are skipped; a short row is padded with empty cells (they become
    ``missing_value`` rejections); a row with more non-empty cells than the header raises
    :class:`InputError` naming the row, since its values cannot be assigned to columns.
    """
    text = _decode_text(path, path.read_bytes())
    reader = csv.reader(io.StringIO(text, newline=""), skipinitialspace=True, strict=True)
    rows: list[list[str]] = []
    header: list[str] | None = None
    try:
        for cells in reader:
            if not cells or (len(cells) == 1 and not cells[0].strip()):
                continue
            cells = [c.strip() for c in cells]
            if header is None:
                header = cells
                continue
            if len(cells) > len(header):
                if any(cells[len(header):]):
                    raise InputError(
                        f"{path}: data row {len(rows) + 1} (line {reader.line_num}) has "
                        f"{len(cells)} fields but the header has {len(header)}; remove the extra "
                        "fields or quote values that contain commas")
                cells = cells[:len(header)]
            rows.append(cells + [""] * (len(header) - len(cells)))
    except csv.Error as exc:
        raise InputError(f"{path}: malformed CSV at line {reader.line_num} ({_short(exc)}); close "
                         "the quote or re-export the log") from exc
    if header is None:  # pragma: no cover - _decode_text refuses blank files
        raise InputError(f"{path}: the file is empty; give a calibration log with a header row")
    return header, rows


def _read_log(path: Path) -> pd.DataFrame:
    if path.suffix.lower() in (".parquet", ".pq"):
        import pyarrow.parquet as pq

        try:
            df = pq.read_table(path).to_pandas()
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"{path}: not a readable Parquet file ({_short(exc)}); export the log "
                             "again") from exc
        df.columns = [str(c) for c in df.columns]
        if len(set(df.columns)) != len(df.columns):
            dup = next(c for c in df.columns if list(df.columns).count(c) > 1)
            raise InputError(f"{path}: duplicated column {dup!r}; remove one of them so each field "
                             "appears once")
        return df.astype(object).where(df.notna(), "")
    header, rows = _read_csv_records(path)
    seen = set()
    for name in header:
        if name in seen:
            raise InputError(f"{path}: duplicated column {name!r}; remove one of them so each "
                             "field appears once")
        seen.add(name)
    if "" in header:
        raise InputError(f"{path}: column {header.index('') + 1} of the header has no name; name "
                         "it or remove the column")
    return pd.DataFrame(rows, columns=header, dtype=object)


def _stage_log(path: Path, opts: IngestOptions, kind: str) -> _Staged:
    raw = _read_log(path)
    if raw.empty:
        raise InputError(f"{path}: header only, no data rows; give a log with at least one "
                         "measurement")
    cols = {str(c).strip(): c for c in raw.columns}
    df = pd.DataFrame(index=raw.index)
    df["source_file"] = str(path)
    df["source_row"] = np.arange(1, len(raw) + 1)
    df["raw"] = [json.dumps(r, default=str) for r in raw.to_dict("records")]
    used = set()

    def take(canonical: str, *names: str, required: bool = False):
        for name in names or (canonical,):
            if name in cols:
                df[canonical] = raw[cols[name]]
                used.add(name)
                return True
        if required:
            raise InputError(f"{path}: missing required column {canonical!r} (or "
                             f"{' / '.join(n for n in names if n != canonical) or 'alias'}); add it "
                             "to the log, see README 'Input formats'")
        df[canonical] = ""
        return False

    take("heliostat_id", required=True)
    take("measurement_id", *_LOG_ALIASES["measurement_id"], required=True)
    take("axis_1_steps", *_LOG_ALIASES["axis_1_steps"], required=True)
    take("axis_2_steps", *_LOG_ALIASES["axis_2_steps"], required=True)
    has_ts = take("timestamp")
    has_az = take("sun_azimuth_deg", *_LOG_ALIASES["sun_azimuth_deg"])
    has_el = take("sun_elevation_deg", *_LOG_ALIASES["sun_elevation_deg"])
    if not (has_az and has_el) and not has_ts:
        raise InputError(f"{path}: missing required columns sun_azimuth/sun_elevation and no "
                         "timestamp to compute them from; add either")
    take("target_name", required=True)
    take("focal_spot_source")
    heliostats: dict[str, dict] = {}
    targets: dict[str, Target] = {}
    reference = None

    if kind == "wgs84-log":
        tower = read_tower(find_tower_file(path, opts.tower))
        reference = tower.reference
        if reference is None:
            raise InputError(f"{path}: no {TOWER_FILENAME} beside or above the log to define the "
                             "plant reference point; pass --tower PATH")
        targets = dict(tower.targets)
        for name in ("focal_spot_lat", "focal_spot_lon", "focal_spot_alt", "heliostat_lat",
                     "heliostat_lon", "heliostat_alt", "target_center_lat", "target_center_lon",
                     "target_center_alt"):
            take(name)
        for src, dst in (("focal_spot", "focal_spot"), ("heliostat", "heliostat"),
                         ("target_center", "target")):
            _wgs84_columns_to_enu(df, src, dst, reference)
        hpos = _to_float_frame(df, ["heliostat_lat", "heliostat_lon", "heliostat_alt"])
        df["_hpos_wgs84"] = list(zip(hpos["heliostat_lat"], hpos["heliostat_lon"], hpos["heliostat_alt"]))
    else:  # enu-log
        for name in ("focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m", "heliostat_e_m",
                     "heliostat_n_m", "heliostat_u_m", "target_e_m", "target_n_m", "target_u_m",
                     "target_normal_e", "target_normal_n", "target_normal_u"):
            take(name)
        reference = opts.location
        if opts.properties is None:
            raise InputError(f"{path}: an ENU log needs the heliostat properties: pass --properties "
                             "FILE.toml|FILE.csv (see README 'Input formats')")
    if opts.properties is not None:
        heliostats, extra_targets = _read_properties_source(Path(opts.properties), reference)
        targets.update(extra_targets)
    if kind == "enu-log" and reference is None and not (has_az and has_el):
        raise InputError(f"{path}: sun angles are missing and no plant location to compute them; "
                         "pass --location LAT,LON,ALT")

    # extra numeric columns -> env_*
    ignored = []
    known = used | set(_LOG_RECOGNISED_IGNORED) | {"focal_spot_source"}
    for name, col in cols.items():
        if name in known or name in df.columns:
            continue
        values = raw[col]
        numeric = pd.to_numeric(values.replace("", np.nan), errors="coerce")
        nonempty = values.astype(str).str.strip() != ""
        if nonempty.any() and numeric[nonempty].notna().mean() >= 0.9:
            env_name = "env_" + re.sub(r"[^0-9a-zA-Z]+", "_", name).strip("_").lower()
            df[env_name] = numeric
        else:
            ignored.append(name)
    ignored += [c for c in _LOG_RECOGNISED_IGNORED if c in cols]
    df["_reject"] = None
    if "focal_spot_source" not in df or (df["focal_spot_source"] == "").all():
        df["focal_spot_source"] = "log"
    df["focal_spot_source"] = df["focal_spot_source"].replace("", "log")
    return _Staged(df, heliostats, targets, reference, kind, ignored)


def _wgs84_columns_to_enu(df: pd.DataFrame, src: str, dst: str, reference) -> None:
    """Columns ``{src}_lat/lon/alt`` (text) -> ``{dst}_e_m/n_m/u_m`` (NaN where any is missing)."""
    names = [f"{src}_lat", f"{src}_lon", f"{src}_alt"]
    wgs = _to_float_frame(df, names)
    ok = wgs.notna().all(axis=1)
    enu = wgs84_to_enu(*(wgs[c].where(ok, 0) for c in names), reference)
    for axis, values in zip("enu", enu):
        df[f"{dst}_{axis}_m"] = np.where(ok, values, np.nan)


def _read_properties_source(path: Path, reference) -> tuple[dict[str, dict], dict[str, Target]]:
    if path.is_dir():
        files = sorted(path.rglob("*-heliostat-properties.json"))
        if not files:
            raise InputError(f"{path}: no *-heliostat-properties.json in this folder; give a PAINT "
                             "folder, a properties CSV or a TOML file")
        if reference is None:
            raise InputError(f"{path}: PAINT properties need the plant reference point; pass --tower")
        rows = [read_paint_properties(f, reference) for f in files]
        return {r["heliostat_id"]: r for r in rows}, {}
    if not path.is_file():
        raise InputError(f"{path}: properties file not found; check the --properties path")
    if path.suffix.lower() not in (".csv", ".toml"):
        raise InputError(f"{path}: properties must be a .csv, .toml or a PAINT folder")
    rows, targets = read_properties_table(path)
    return {r["heliostat_id"]: r for r in rows}, targets


def _to_float_frame(df: pd.DataFrame, names: Sequence[str]) -> pd.DataFrame:
    out = pd.DataFrame(index=df.index)
    for n in names:
        out[n] = _to_float(df[n]) if n in df else np.nan
    return out


def _to_float(series: pd.Series) -> pd.Series:
    s = pd.to_numeric(series.map(lambda v: v.strip() if isinstance(v, str) else v)
                      .replace("", np.nan), errors="coerce")
    return s.astype(float).where(np.isfinite(s.astype(float)))


# ------------------------------------------------------------------------------------------------
# validation: one reason per rejected row, in a fixed order
# ------------------------------------------------------------------------------------------------
def _validate(st: _Staged, opts: IngestOptions) -> tuple[pd.DataFrame, pd.DataFrame]:
    df = st.frame.copy()
    reason = pd.Series([r[0] if r else None for r in df["_reject"]], index=df.index, dtype=object)
    detail = pd.Series([r[1] if r else None for r in df["_reject"]], index=df.index, dtype=object)

    def reject(mask, code: str, text):
        mask = mask & reason.isna()
        if mask.any():
            reason[mask] = code
            detail[mask] = text[mask] if isinstance(text, pd.Series) else text

    def blank(col):
        if col not in df:
            return pd.Series(True, index=df.index)
        return df[col].map(lambda v: v is None or (isinstance(v, float) and math.isnan(v))
                           or (isinstance(v, str) and v.strip() == ""))

    for col in ("heliostat_id", "measurement_id", "target_name"):
        df[col] = df[col].map(lambda v: v.strip() if isinstance(v, str) else v)
    # heliostat position: a log row without one inherits its heliostat's (properties or other rows)
    heliostats = dict(st.heliostats)
    if st.kind in ("wgs84-log", "enu-log"):
        pos = _to_float_frame(df, ["heliostat_e_m", "heliostat_n_m", "heliostat_u_m"])
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
            heliostats[hid] = _default_properties_row(hid, med, wgs)
        for a in "enu":
            df[f"heliostat_{a}_m"] = df["heliostat_id"].map(
                {h: r[f"heliostat_{a}_m"] for h, r in heliostats.items()})

    # a WGS84 log's focal spot is judged on its logged lat/lon/alt (the ENU columns derive from them)
    spot_raw = (["focal_spot_lat", "focal_spot_lon", "focal_spot_alt"] if st.kind == "wgs84-log"
                else ["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"])
    required = ["heliostat_id", "measurement_id", "axis_1_steps", "axis_2_steps", "target_name",
                *spot_raw]
    for col in required:
        reject(blank(col), "missing_value", f"{col} is empty")
    sun_given = ~blank("sun_azimuth_deg") & ~blank("sun_elevation_deg")
    ts_given = ~blank("timestamp") if "timestamp" in df else pd.Series(False, index=df.index)
    reject(~sun_given & ~ts_given, "missing_value", "sun angles and timestamp are empty")

    # numbers
    numeric = {}
    for col in ("axis_1_steps", "axis_2_steps", "sun_azimuth_deg", "sun_elevation_deg", *spot_raw):
        if col not in df:
            continue
        raw_col = df[col]
        val = _to_float(raw_col.astype(object))
        numeric[col] = val
        bad = val.isna() & ~blank(col)
        reject(bad, "unparsable_number", raw_col.map(lambda v, c=col: f"{c}={v!r} is not a finite number"))
    if st.kind == "wgs84-log":
        for col, limit in (("focal_spot_lat", 90.0), ("focal_spot_lon", 180.0)):
            val = numeric[col]
            reject(val.abs() > limit, "unparsable_number",
                   val.map(lambda v, c=col, lim=limit: f"{c}={v!r} is outside [-{lim:g}, {lim:g}] deg"))
        enu = _to_float_frame(df, ["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"])
        reject(enu.isna().any(axis=1), "unparsable_number",
               "focal spot lat/lon/alt cannot be converted to ENU (not a point near the plant)")
    for col, val in numeric.items():
        df[col] = val
    env_cols = [c for c in df.columns if c.startswith("env_")]

    # timestamps
    ts = pd.Series(pd.NaT, index=df.index, dtype="datetime64[us, UTC]")
    if "timestamp" in df:
        ts, bad_ts, naive = _parse_timestamps(df["timestamp"], opts.timezone)
        if naive.any() and naive[ts_given].all() and opts.timezone is None:
            example = df.loc[naive.idxmax(), "timestamp"]
            raise InputError(f"{df['source_file'].iloc[0]}: timestamps have no time zone (e.g. "
                             f"{example!r}); add a UTC offset such as 'Z' or pass --timezone "
                             "Europe/Berlin")
        reject(bad_ts & ts_given, "unparsable_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} is not a UTC time"))
        reject(naive & ts_given, "unparsable_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} has no time zone"))
    df["timestamp"] = ts

    # heliostat and target known
    known_h = df["heliostat_id"].isin(list(heliostats))
    reject(~known_h, "unknown_heliostat",
           df["heliostat_id"].map(lambda h: f"no properties or position for heliostat {h!r}"))
    tgt = _resolve_targets(df, st.targets)
    reject(~tgt, "unknown_target",
           df["target_name"].map(lambda t: f"target {t!r} is not in the tower/targets file"))

    # sun: SPA where missing, comparison where present
    az = df["sun_azimuth_deg"].astype(float) if "sun_azimuth_deg" in df else pd.Series(np.nan, index=df.index)
    el = df["sun_elevation_deg"].astype(float) if "sun_elevation_deg" in df else pd.Series(np.nan, index=df.index)
    if opts.azimuth_convention == "north-clockwise":
        az = pd.Series(wrap_deg(180.0 - az.to_numpy()), index=df.index)
    df["sun_source"] = np.where(az.notna() & el.notna(), "log", "spa")
    df["qa_sun_spa_diff_deg"] = np.nan
    location = _location(st, heliostats)
    can_spa = ts.notna() & reason.isna()
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
            if opts.azimuth_convention == "south" and logged.sum() >= 3:
                _check_azimuth_convention(df, az[logged], el[logged], spa_az[logged], spa_el[logged],
                                          diff, opts)
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

    # actuator range
    for i in (1, 2):
        lo = df["heliostat_id"].map({h: r[f"axis_{i}_min_steps"] for h, r in heliostats.items()})
        hi = df["heliostat_id"].map({h: r[f"axis_{i}_max_steps"] for h, r in heliostats.items()})
        steps = df[f"axis_{i}_steps"].astype(float)
        out = known_h & ((steps < lo) | (steps > hi))
        reject(out, "steps_out_of_range", pd.Series(
            [f"axis_{i}_steps={s:g} outside [{a:g}, {b:g}]" for s, a, b in zip(steps, lo, hi)],
            index=df.index))

    # focal spot near its target
    spot = df[["focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m"]].astype(float).to_numpy()
    center = df[["target_e_m", "target_n_m", "target_u_m"]].astype(float).to_numpy()
    dist = np.linalg.norm(spot - center, axis=1)
    far = pd.Series(dist > opts.max_spot_distance_m, index=df.index) & tgt
    reject(far, "focal_spot_far_from_target", pd.Series(
        [f"focal spot {d:.1f} m from the target centre (limit {opts.max_spot_distance_m:g} m)"
         for d in dist], index=df.index))

    # duplicates (first occurrence kept)
    key = df["heliostat_id"].astype(str) + "\0" + df["measurement_id"].astype(str)
    ok_so_far = reason.isna()
    first_row = df.loc[ok_so_far].groupby(key[ok_so_far])["source_row"].transform("first")
    dup = key[ok_so_far].duplicated(keep="first")
    dup = dup.reindex(df.index, fill_value=False)
    reject(dup, "duplicate_measurement_id", pd.Series(
        [f"measurement id {m!r} already seen in source row {r}" for m, r in
         zip(df["measurement_id"], first_row.reindex(df.index))], index=df.index))

    kept = df.loc[reason.isna()].copy()
    rejected = pd.DataFrame({
        "source_file": df["source_file"], "source_row": df["source_row"],
        "heliostat_id": df["heliostat_id"].map(lambda v: v if isinstance(v, str) and v else None),
        "measurement_id": df["measurement_id"].map(lambda v: v if isinstance(v, str) and v else None),
        "reason": reason, "detail": detail, "raw": df["raw"]}).loc[reason.notna()]
    cols = MEASUREMENTS.column_names()
    kept = kept[cols + env_cols]
    return kept, rejected, heliostats


def _parse_timestamps(values: pd.Series, timezone: str | None):
    """Parse to UTC; returns (timestamps, unparsable mask, no-zone mask)."""
    text = values.map(lambda v: v.strip() if isinstance(v, str) else ("" if v is None else str(v)))
    ts = pd.Series(pd.NaT, index=values.index, dtype="datetime64[us, UTC]")
    bad = pd.Series(False, index=values.index)
    naive = pd.Series(False, index=values.index)
    for idx, t in text.items():
        if not t or t.lower() in ("nan", "nat", "none"):
            continue
        try:
            stamp = pd.Timestamp(t)
        except (ValueError, TypeError, OverflowError):
            bad[idx] = True
            continue
        if stamp is pd.NaT:
            bad[idx] = True
            continue
        if stamp.tzinfo is None:
            if timezone is None:
                naive[idx] = True
                continue
            try:
                stamp = stamp.tz_localize(timezone)
            except Exception:  # noqa: BLE001 - invalid/ambiguous local time
                bad[idx] = True
                continue
        ts[idx] = stamp.tz_convert("UTC")
    return ts, bad, naive


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
    for name, t in targets.items():
        sel = names == name
        if sel.any():
            df.loc[sel, ["target_e_m", "target_n_m", "target_u_m"]] = t.center_enu
            df.loc[sel, ["target_normal_e", "target_normal_n", "target_normal_u"]] = t.normal_enu
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


def _location(st: _Staged, heliostats: dict[str, dict]):
    if st.reference is not None:
        return st.reference
    return None


def _check_azimuth_convention(df, az, el, spa_az, spa_el, diff, opts) -> None:
    """Refuse a log whose azimuths are clearly north-clockwise (0 = north)."""
    if np.median(diff) <= 5 * opts.sun_tolerance_deg + 1.0:
        return
    alt = sun_vector_enu(wrap_deg(180.0 - az.to_numpy()), el)
    alt_diff = np.degrees(np.arccos(np.clip((alt * sun_vector_enu(spa_az, spa_el)).sum(axis=1), -1, 1)))
    if np.median(alt_diff) < 1.0:
        raise InputError(f"{df['source_file'].iloc[0]}: sun azimuths look north-clockwise (0 = "
                         "north); heliocal's convention is 0 = south, positive toward east: pass "
                         "--azimuth-convention north-clockwise")


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
def ingest(sources: Iterable[str | os.PathLike], options: IngestOptions | None = None):
    """Read every source and return (measurements, heliostats, rejected, info) DataFrames.

    Raises :class:`InputError` when a source cannot be read at all; row-level problems become
    rows of ``rejected`` with a reason from :data:`~heliocal.pipeline.schemas.REJECTION_REASONS`.
    """
    opts = (options or IngestOptions()).validate()
    sources = [Path(s) for s in sources]
    if not sources:
        raise InputError("no SOURCE given; pass a PAINT folder or a CSV/Parquet log")
    kept_parts, rejected_parts, heliostats, ignored, kinds = [], [], {}, {}, {}
    rows_read = 0
    for src in sources:
        kind = detect_source(src)
        kinds[str(src)] = kind
        staged = _stage_paint(src, opts) if kind == "paint" else _stage_log(src, opts, kind)
        rows_read += len(staged.frame)
        kept, rejected, helios = _validate(staged, opts)
        for hid, row in helios.items():
            heliostats.setdefault(hid, row)
        kept_parts.append(kept)
        rejected_parts.append(rejected)
        if staged.ignored_columns:
            ignored[str(src)] = staged.ignored_columns
    measurements = pd.concat(kept_parts, ignore_index=True) if kept_parts else pd.DataFrame()
    rejected = pd.concat(rejected_parts, ignore_index=True)
    # duplicates across sources: first source wins
    key = measurements["heliostat_id"] + "\0" + measurements["measurement_id"]
    dup = key.duplicated(keep="first")
    if dup.any():
        extra = measurements.loc[dup]
        rejected = pd.concat([rejected, pd.DataFrame({
            "source_file": extra["source_file"], "source_row": extra["source_row"],
            "heliostat_id": extra["heliostat_id"], "measurement_id": extra["measurement_id"],
            "reason": "duplicate_measurement_id",
            "detail": "measurement id already ingested from an earlier source",
            "raw": extra.drop(columns=["timestamp"]).to_json(orient="records", lines=True).splitlines()})],
            ignore_index=True)
        measurements = measurements.loc[~dup].reset_index(drop=True)
    counts = measurements.groupby("heliostat_id").size()
    helio = pd.DataFrame([{**row, "n_measurements": int(counts.get(hid, 0))}
                          for hid, row in sorted(heliostats.items()) if counts.get(hid, 0) > 0],
                         columns=HELIOSTATS.column_names())
    for col in (c.name for c in HELIOSTATS.columns if c.dtype == "bool"):
        helio[col] = helio[col].astype(bool)
    info = {
        "sources": kinds,
        "rows_read": rows_read,
        "kept": int(len(measurements)),
        "rejected": int(len(rejected)),
        "rejected_by_reason": {k: int(v) for k, v in rejected["reason"].value_counts().sort_index().items()},
        "heliostats": {k: int(v) for k, v in counts.sort_index().items()},
        "heliostats_with_default_geometry": sorted(
            h for h, r in heliostats.items() if r["properties_source"] == "default-juelich"
            and counts.get(h, 0) > 0),
        "sun_mismatch_rows": int(measurements["qa_sun_mismatch"].sum()) if len(measurements) else 0,
        "ignored_columns": ignored,
        "env_columns": sorted(c for c in measurements.columns if c.startswith("env_")),
    }
    if rows_read != info["kept"] + info["rejected"]:  # pragma: no cover - an invariant
        raise RuntimeError(f"ingest lost rows: read {rows_read}, kept {info['kept']}, "
                           f"rejected {info['rejected']}")
    return measurements, helio, rejected, info


def run_ingest(sources: Sequence[str | os.PathLike], workdir: str | os.PathLike,
               options: IngestOptions | None = None) -> dict:
    """The ``ingest`` stage: read ``sources``, write the three artifacts into ``workdir``.

    Returns the summary (rows read, kept, rejected per reason, heliostats).
    """
    opts = options or IngestOptions()
    measurements, helio, rejected, info = ingest(sources, opts)
    if info["kept"] == 0:
        reasons = ", ".join(f"{k}: {v}" for k, v in info["rejected_by_reason"].items())
        raise InputError(f"no measurement of {', '.join(map(str, sources))} could be kept "
                         f"({reasons}); see the reasons and fix the source")
    workdir = Path(workdir)
    inputs = {f"source:{s}": s for s in sources}
    if opts.tower:
        inputs["tower"] = opts.tower
    if opts.properties:
        inputs["properties"] = opts.properties
    resolved = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(opts).items()}
    resolved["sources"] = [str(s) for s in sources]
    for df, schema in ((rejected, REJECTED), (helio, HELIOSTATS), (measurements, MEASUREMENTS)):
        write_artifact(df, workdir, schema, stage="ingest", options=resolved, inputs=inputs)
    info["workdir"] = str(workdir)
    info["artifacts"] = [str(artifact_path(workdir, s)) for s in (MEASUREMENTS, HELIOSTATS, REJECTED)]
    for reason, n in info["rejected_by_reason"].items():
        log.info("rejected %d rows: %s (%s)", n, reason, REJECTION_REASONS.get(reason, ""))
    if info["sun_mismatch_rows"]:
        log.warning("%d kept rows have logged sun angles more than %g deg from NREL SPA "
                    "(column qa_sun_mismatch)", info["sun_mismatch_rows"], opts.sun_tolerance_deg)
    if info["heliostats_with_default_geometry"]:
        log.warning("%d heliostats have no properties file and start from the default Jülich "
                    "geometry (pass --properties to give theirs)",
                    len(info["heliostats_with_default_geometry"]))
    for src, cols in info["ignored_columns"].items():
        log.info("%s: columns not used: %s", src, ", ".join(cols))
    return info
