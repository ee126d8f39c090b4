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
``simulate``
    A folder written by ``heliocal simulate`` (it holds the simulator's ``ground_truth.json``): read
    as its logs, each with the folder's own properties (:func:`simulate_sources`).

Heliostat ids become file names later (``hybrid/<mode>/<id>.pt``, report figures), so a row whose
id does not match :data:`~heliocal.pipeline.artifacts.schemas.HELIOSTAT_ID_RE` is rejected
(``invalid_heliostat_id``, with a suggested new name).

Nothing is lost: every input row ends in ``measurements.parquet`` or, with a reason, in
``rejected.parquet``. A source that cannot be read at all raises :class:`InputError` (one line
naming the file, the problem and the fix) before any artifact is written.
"""

from __future__ import annotations

import contextlib
import csv
import datetime
import json
import logging
import math
import os
import re
import shutil
import tempfile
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
import pandas as pd
import pyarrow as pa

from ..artifacts.store import _to_table, artifact_path, artifact_writer, write_artifact
from ..errors import InputError, ParameterError, check_choice, check_float, check_int
from ..physics.geodesy import wgs84_to_enu
from ..artifacts.schemas import (HELIOSTAT_ID_RULE, HELIOSTATS, MEASUREMENTS, REJECTED,
                                 REJECTION_REASONS, heliostat_id_problem, suggest_heliostat_id)
from ..io.spill import SortedSpill
from ..physics.sun import spa_sun_position, sun_vector_enu, wrap_deg
from ..artifacts.transaction import stage_transaction
from ..artifacts.workdir_lock import locks_workdir

__all__ = [
    "SOURCE_KINDS",
    "IngestOptions",
    "Tower",
    "detect_source",
    "simulate_sources",
    "find_tower_file",
    "read_tower",
    "read_paint_properties",
    "ingest",
    "run_ingest",
    "DEFAULT_BATCH_ROWS",
    "DEFAULT_JUELICH_PROPERTIES",
]

log = logging.getLogger("heliocal.ingest")

SOURCE_KINDS = ("paint", "wgs84-log", "enu-log", "simulate")
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
#: Earliest plausible measurement time (``--time-min``): camera-target calibration logs of today's
#: heliostat fields start decades later; a year like 1700 or 1970 is a logger or export fault.
DEFAULT_TIME_MIN = "1990-01-01T00:00:00Z"
#: The latest plausible time is now plus this margin (``--time-max`` overrides it): a calibration
#: cannot have been measured in the future; the margin covers clocks and time zones set wrong.
TIME_MAX_MARGIN = pd.Timedelta(days=1)
#: An env value beyond this magnitude is blanked (``qa_env_blanked``): the fine model standardises
#: its inputs with the mean and standard deviation of the column, and squares of values this large
#: overflow float64, which would make the input constant for every row (1e308 is what a logger
#: writes on overflow). No physical reading in any unit comes near it.
ENV_ABS_MAX = 1e100


def _utc_bound(value, name: str = "") -> pd.Timestamp | None:
    """``value`` (text or timestamp) as a UTC timestamp (naive means UTC); ``None`` if it is not
    a readable time."""
    try:
        stamp = pd.Timestamp(value)
    except (ValueError, TypeError, OverflowError):
        return None
    if stamp is pd.NaT:
        return None
    return stamp.tz_localize("UTC") if stamp.tzinfo is None else stamp.tz_convert("UTC")


def _time_bounds(opts: "IngestOptions") -> tuple[pd.Timestamp, pd.Timestamp]:
    """(earliest, latest) plausible timestamp of a run."""
    lo = _utc_bound(opts.time_min)
    hi = (_utc_bound(opts.time_max) if opts.time_max is not None
          else pd.Timestamp.now(tz="UTC") + TIME_MAX_MARGIN)
    return lo, hi
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
    date_format: str | None = None  # strptime format of every timestamp (e.g. "%d.%m.%Y %H:%M:%S%z")
    time_min: str = DEFAULT_TIME_MIN  # earliest plausible timestamp (UTC unless it has a zone)
    time_max: str | None = None  # latest plausible timestamp; None: now + TIME_MAX_MARGIN

    def validate(self) -> "IngestOptions":
        for name in ("time_min", "time_max"):
            value = getattr(self, name)
            if value is not None and _utc_bound(value, name) is None:
                raise ParameterError(f"The '{name}' parameter of ingest must be a date or time "
                                     f"such as 1990-01-01 or 2024-06-01T12:00Z. Got {value!r} "
                                     "instead.")
        if self.date_format is not None and "%" not in str(self.date_format):
            raise ParameterError(f"The 'date_format' parameter of ingest must be a strptime "
                                 f"format such as '%d.%m.%Y %H:%M:%S%z'. Got {self.date_format!r} "
                                 "instead.")
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
    with _open_csv_text(path) as text:
        try:
            for cells in csv.reader(text, skipinitialspace=True):
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
        if _is_simulate_folder(path):
            return "simulate"
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


#: What ``heliocal simulate`` writes into its output folder (see :func:`simulate_sources`).
_SIMULATE_MARKER = "ground_truth.json"


def _is_simulate_folder(path: Path) -> bool:
    marker = path / _SIMULATE_MARKER
    if not marker.is_file():
        return False
    try:
        generator = json.loads(marker.read_text(encoding="utf-8")).get("generator", "")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return False
    return isinstance(generator, str) and generator.startswith("heliocal")


def simulate_sources(folder: str | os.PathLike,
                     options: IngestOptions) -> list[tuple[Path, IngestOptions]]:
    """The sources of a ``heliocal simulate`` output folder, each with its own options.

    The folder holds every simulated measurement once per kinematic type: Jülich-type heliostats
    in ``calibration_log.csv`` (a WGS84 log with the env column ``temperature``; the same
    measurements are also in ``paint/``, which gives their properties) and az-el heliostats in
    ``enu_log.csv`` with ``enu_properties.toml`` (sun positions checked against NREL SPA at the
    plant reference point of ``ground_truth.json`` unless ``--location`` is given). Only these
    fixed names are read. ``--properties`` is refused: the folder brings its own.
    """
    folder = Path(folder)
    if options.properties is not None:
        raise InputError(f"{folder}: a heliocal simulate folder brings its own heliostat properties "
                         "(paint/, enu_properties.toml); drop --properties, or give its logs one "
                         "by one")
    out: list[tuple[Path, IngestOptions]] = []
    log_csv, paint, enu_log, enu_props = (folder / "calibration_log.csv", folder / "paint",
                                          folder / "enu_log.csv", folder / "enu_properties.toml")
    if log_csv.is_file():
        out.append((log_csv, replace(options, properties=paint if paint.is_dir() else None)))
    elif paint.is_dir():
        out.append((paint, options))
    if enu_log.is_file():
        if not enu_props.is_file():
            raise InputError(f"{folder}: enu_log.csv without enu_properties.toml; rerun `heliocal "
                             "simulate` into an empty folder")
        location = options.location
        if location is None:
            ref = _load_json(folder / _SIMULATE_MARKER, "the ground truth").get("reference_wgs84")
            if isinstance(ref, list) and len(ref) == 3 and all(
                    isinstance(x, (int, float)) for x in ref):
                location = tuple(float(x) for x in ref)
        out.append((enu_log, replace(options, properties=enu_props, location=location)))
    if not out:
        raise InputError(f"{folder}: a heliocal simulate folder without calibration_log.csv, "
                         "paint/ or enu_log.csv; rerun `heliocal simulate` into an empty folder")
    return out


def _expand_sources(sources: Sequence[Path],
                    options: IngestOptions) -> list[tuple[Path, IngestOptions]]:
    """Every source with its options; a simulate folder becomes its logs
    (:func:`simulate_sources`)."""
    out = []
    for path in sources:
        if path.is_dir() and _is_simulate_folder(path):
            out += simulate_sources(path, options)
        else:
            out.append((path, options))
    return out


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
        types = {str(act.get("type_axis", "linear")).lower() for act in actuators}
        if types != {"linear"}:
            raise ValueError(f"actuator types {sorted(types)}; PAINT heliostats have linear actuators")
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
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
            if not isinstance(stamps, dict):
                raise InputError(f"{cand / TIMESTAMPS_FILENAME}: the timestamps map is not a JSON "
                                 'object {"<HID>_<id>": "<UTC time>", ...}; restore the original '
                                 "file")
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
    for a in "enu":  # missing (unknown_heliostat) unless the heliostat has a properties file
        frame[f"heliostat_{a}_m"] = np.nan
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


_TEXT_HEAD_BYTES = 65536


@contextlib.contextmanager
def _open_csv_text(path: Path):
    """The CSV as UTF-8 text, read as a stream; the checks of :func:`_decode_text` without
    holding the file: its first 64 KiB are checked for binary data and blankness up front, and a
    decoding error anywhere is reported by :func:`_decode_text` (which then reads the file)."""
    with open(path, "rb") as fh:
        head = fh.read(_TEXT_HEAD_BYTES + 1)
    if (not head.strip() and len(head) <= _TEXT_HEAD_BYTES) or b"\0" in head[:_TEXT_HEAD_BYTES]:
        _decode_text(path, head)
    try:
        with open(path, encoding="utf-8-sig", newline="") as text:
            yield text
    except UnicodeDecodeError:
        _decode_text(path, path.read_bytes())  # raises the InputError naming line and byte
        raise  # pragma: no cover - Python's decoder and _decode_text agree


def _iter_csv_records(path: Path, rows_per_block: int) -> Iterator[tuple[list[str], list[list[str]]]]:
    """Header and blocks of data rows of a comma-separated UTF-8 file, every cell a stripped
    string, streamed: yields ``(header, rows)`` with at most ``rows_per_block`` rows per block.

    Blank lines are skipped; a short row is padded with empty cells (they become
    ``missing_value`` rejections); a row with more non-empty cells than the header raises
    :class:`InputError` naming the row, since its values cannot be assigned to columns.
    """
    with _open_csv_text(path) as text:
        reader = csv.reader(text, skipinitialspace=True, strict=True)
        rows: list[list[str]] = []
        header: list[str] | None = None
        n_rows = 0
        try:
            for cells in reader:
                if not cells or (len(cells) == 1 and not cells[0].strip()):
                    continue
                cells = [c.strip() for c in cells]
                if header is None:
                    header = cells
                    continue
                n_rows += 1
                if len(cells) > len(header):
                    if any(cells[len(header):]):
                        raise InputError(
                            f"{path}: data row {n_rows} (line {reader.line_num}) has "
                            f"{len(cells)} fields but the header has {len(header)}; remove the "
                            "extra fields or quote values that contain commas")
                    cells = cells[:len(header)]
                rows.append(cells + [""] * (len(header) - len(cells)))
                if len(rows) >= rows_per_block:
                    yield header, rows
                    rows = []
        except csv.Error as exc:
            raise InputError(f"{path}: malformed CSV at line {reader.line_num} ({_short(exc)}); "
                             "close the quote or re-export the log") from exc
    if header is None:
        raise InputError(f"{path}: the file is empty; give a calibration log with a header row "
                         "and one row per measurement")
    yield header, rows


def _check_header(path: Path, header: Sequence[str]) -> None:
    seen = set()
    for name in header:
        if name in seen:
            raise InputError(f"{path}: duplicated column {name!r}; remove one of them so each "
                             "field appears once")
        seen.add(name)
    if "" in header:
        raise InputError(f"{path}: column {header.index('') + 1} of the header has no name; name "
                         "it or remove the column")


# The pass over a log: read in batches, keyed by heliostat -------------------------------------
#: Internal columns of the spilled source rows (a log column of the same name is refused).
_KEY = "__heliocal_heliostat_key"
_SEQ = "__heliocal_source_row"
#: Rows parsed from a CSV at a time before they become one Arrow block.
_CSV_BLOCK_ROWS = 16384


def _heliostat_key(values: pd.Series) -> pd.Series:
    """The stripped heliostat id as text ('' when missing): rows of one heliostat share a key."""
    return values.map(lambda v: v.strip() if isinstance(v, str)
                      else ("" if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)))


@dataclass
class _LogRows:
    """The rows of one log after the streaming pass: in memory (one chunk) or spilled in runs."""

    path: Path
    header: list[str]
    rows: int
    parquet_schema: "pa.Schema | None"  # original schema (with pandas metadata) of a Parquet log
    float_columns: set[str]  # Parquet integer columns with nulls somewhere (pandas makes them float)
    extra_stats: dict[str, list]  # column -> [non-empty, numeric non-empty, all integer]
    tables: list  # in-memory blocks (pa.Table) when not spilled
    spill: SortedSpill | None

    def chunks(self, chunk_rows: int | None) -> Iterator["pa.Table"]:
        """Blocks holding every row of a range of heliostats, in heliostat order."""
        if self.spill is None:
            if self.tables:
                yield pa.concat_tables(self.tables)
            return
        yield from self.spill.merged(chunk_rows)

    def frame(self, table: "pa.Table") -> pd.DataFrame:
        """A block as the raw frame :func:`_stage_log_rows` takes: source order, every value as
        read (Parquet: pandas' conversion of the whole file), index = source row - 1."""
        seq = table.column(_SEQ).to_numpy()
        order = np.argsort(seq, kind="stable")
        table = table.take(pa.array(order)).drop_columns([_KEY, _SEQ])
        seq = seq[order]
        if self.parquet_schema is not None:
            for name in self.float_columns:
                i = table.column_names.index(name)
                table = table.set_column(i, name, table.column(name).cast(pa.float64()))
            df = table.replace_schema_metadata(self.parquet_schema.metadata).to_pandas()
            df = df.reset_index(drop=True)
            df.columns = [str(c) for c in df.columns]
            df = df.astype(object).where(df.notna(), "")
        else:
            df = pd.DataFrame({n: table.column(n).to_numpy(zero_copy_only=False)
                               for n in table.column_names}, dtype=object)
        df.index = pd.Index(seq - 1)
        return df


def _log_column_usage(header: Sequence[str], kind: str) -> set[str]:
    """Names of the log columns :func:`_log_context` maps to canonical columns."""
    names = {"heliostat_id", "timestamp", "target_name", "focal_spot_source"}
    for aliases in _LOG_ALIASES.values():
        names.update(aliases)
    if kind == "wgs84-log":
        names.update(f"{p}_{c}" for p in ("focal_spot", "heliostat", "target_center")
                     for c in ("lat", "lon", "alt"))
    else:
        names.update(_ENU_LOG_COLUMNS)
    names.update(_LOG_RECOGNISED_IGNORED)
    return names & set(header)


def _numeric_stats(values: pd.Series) -> tuple[int, int, bool]:
    """(non-empty cells, numeric non-empty cells, all integers) of an extra log column."""
    numeric = pd.to_numeric(values.replace("", np.nan), errors="coerce")
    nonempty = values.astype(str).str.strip() != ""
    return (int(nonempty.sum()), int(numeric[nonempty].notna().sum()),
            bool(pd.api.types.is_integer_dtype(numeric)))


def _read_log_rows(path: Path, kind: str, batch_rows: int | None, spill_dir: Path | None) -> _LogRows:
    """Read a CSV or Parquet log in batches of ``batch_rows`` rows (all at once with ``None``),
    keyed by heliostat; with a ``spill_dir`` and more rows than one batch, every batch is sorted
    by heliostat and spilled there as a run, so memory holds one batch."""
    rows = _LogRows(path, [], 0, None, set(), {}, [], None)
    extra: list[str] = []
    is_parquet = path.suffix.lower() in (".parquet", ".pq")

    def add(table: pa.Table, frame: pd.DataFrame) -> None:
        key = (_heliostat_key(frame[_KEY]) if _KEY in frame.columns
               else pd.Series("", index=frame.index))
        table = table.append_column(_KEY, pa.array(key.tolist(), pa.string()))
        table = table.append_column(_SEQ, pa.array(np.arange(rows.rows + 1, rows.rows + 1
                                                               + table.num_rows), pa.int64()))
        rows.rows += table.num_rows
        for name in extra:
            if name in frame.columns:
                nonempty, numeric, integer = _numeric_stats(frame[name])
                st = rows.extra_stats.setdefault(name, [0, 0, True])
                st[0] += nonempty
                st[1] += numeric
                st[2] = st[2] and integer
        rows.tables.append(table)
        if (batch_rows is not None and spill_dir is not None
                and sum(t.num_rows for t in rows.tables) >= batch_rows):
            if rows.spill is None:
                rows.spill = SortedSpill(spill_dir, f"log-{id(rows):x}", _KEY, _SEQ)
            rows.spill.add(pa.concat_tables(rows.tables))
            rows.tables = []

    def id_column(header: Sequence[str]) -> str | None:
        return next((c for c in header if str(c).strip() == "heliostat_id"), None)

    if is_parquet:
        import pyarrow.parquet as pq

        try:
            pf = pq.ParquetFile(path)
            schema = pf.schema_arrow
            index_cols = {c for c in ((schema.pandas_metadata or {}).get("index_columns") or [])
                          if isinstance(c, str)}
            names = [n for n in schema.names if n not in index_cols]
            rows.parquet_schema = schema
            rows.header = [str(n) for n in names]
            extra = [n for n in rows.header if n not in _log_column_usage(rows.header, kind)]
            nulls: dict[str, int] = {}
            block = batch_rows or (1 << 16)
            for batch in pf.iter_batches(batch_size=min(block, 1 << 16)):
                table = pa.Table.from_batches([batch], schema=schema)
                for n in names:
                    nulls[n] = nulls.get(n, 0) + table.column(n).null_count
                hcol = id_column(names)
                frame = (table.select([hcol, *extra] if hcol else extra)
                         .replace_schema_metadata(None).to_pandas())
                frame = frame.astype(object).where(frame.notna(), "")
                if hcol:
                    frame[_KEY] = frame.pop(hcol) if hcol not in extra else frame[hcol]
                add(table, frame)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - pyarrow raises several types
            raise InputError(f"{path}: not a readable Parquet file ({_short(exc)}); export the log "
                             "again") from exc
        rows.float_columns = {n for n in names if nulls.get(n) and pa.types.is_integer(schema.field(n).type)}
    else:
        header: list[str] = []
        for header, block in _iter_csv_records(path, min(batch_rows or _CSV_BLOCK_ROWS, _CSV_BLOCK_ROWS)):
            if not rows.header:
                rows.header = list(header)
                extra = [n for n in header if n not in _log_column_usage(header, kind)]
            if not block:
                continue
            columns = list(zip(*block))
            names = list(dict.fromkeys(header))  # a duplicated column is refused below
            table = pa.table({n: pa.array(columns[header.index(n)], pa.string()) for n in names})
            frame = pd.DataFrame({n: columns[header.index(n)] for n in extra if n in names},
                                 index=range(len(block)), dtype=object)
            hcol = id_column(names)
            if hcol:
                frame[_KEY] = pd.Series(columns[header.index(hcol)], dtype=object)
            add(table, frame)
        rows.header = list(header)
    _check_header(path, rows.header)
    if _KEY in rows.header or _SEQ in rows.header:
        raise InputError(f"{path}: column names {_KEY!r} and {_SEQ!r} are reserved by heliocal; "
                         "rename the column")
    if rows.spill is not None and rows.tables:
        rows.spill.add(pa.concat_tables(rows.tables))
        rows.tables = []
    return rows


@dataclass
class _LogContext:
    """What a log's header, tower file and properties define for all its rows."""

    path: Path
    kind: str
    columns: dict[str, str]  # canonical name -> log column
    env: dict[str, tuple[str, bool]]  # env_* name -> (log column, integer)
    heliostats: dict[str, dict]
    targets: dict[str, Target]
    reference: tuple[float, float, float] | None
    ignored: list[str]


_ENU_LOG_COLUMNS = ("focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m", "heliostat_e_m",
                    "heliostat_n_m", "heliostat_u_m", "target_e_m", "target_n_m", "target_u_m",
                    "target_normal_e", "target_normal_n", "target_normal_u")


def _staged_names(kind: str) -> set[str]:
    """Columns of a staged log frame (a log column of the same name is neither env_* nor
    reported as ignored)."""
    names = {"source_file", "source_row", "raw", "heliostat_id", "measurement_id", "axis_1_steps",
             "axis_2_steps", "timestamp", "sun_azimuth_deg", "sun_elevation_deg", "target_name",
             "focal_spot_source"}
    if kind == "wgs84-log":
        names |= {f"{p}_{c}" for p in ("focal_spot", "heliostat", "target_center")
                  for c in ("lat", "lon", "alt")}
        names |= {f"{p}_{a}_m" for p in ("focal_spot", "heliostat", "target") for a in "enu"}
        names.add("_hpos_wgs84")
    else:
        names |= set(_ENU_LOG_COLUMNS)
    return names


def _log_context(rows: _LogRows, opts: IngestOptions, kind: str) -> _LogContext:
    """Map a log's columns, read its tower and properties; raise on what no row can fix."""
    path = rows.path
    if rows.rows == 0:
        raise InputError(f"{path}: header only, no data rows; give a log with at least one "
                         "measurement")
    cols = {str(c).strip(): c for c in rows.header}
    mapping: dict[str, str] = {}
    used = set()

    def take(canonical: str, *names: str, required: bool = False):
        for name in names or (canonical,):
            if name in cols:
                mapping[canonical] = cols[name]
                used.add(name)
                return True
        if required:
            raise InputError(f"{path}: missing required column {canonical!r} (or "
                             f"{' / '.join(n for n in names if n != canonical) or 'alias'}); add it "
                             "to the log, see README 'Input formats'")
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
    else:  # enu-log
        for name in _ENU_LOG_COLUMNS:
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

    # extra numeric columns -> env_* (judged on the whole column: 90 % of its cells numbers)
    ignored, env = [], {}
    known = used | set(_LOG_RECOGNISED_IGNORED) | {"focal_spot_source"} | _staged_names(kind)
    for name, col in cols.items():
        if name in known:
            continue
        nonempty, numeric, integer = rows.extra_stats.get(col, (0, 0, True))
        if nonempty and numeric / nonempty >= 0.9:
            env["env_" + re.sub(r"[^0-9a-zA-Z]+", "_", name).strip("_").lower()] = (col, integer)
        else:
            ignored.append(name)
    ignored += [c for c in _LOG_RECOGNISED_IGNORED if c in cols]
    return _LogContext(path, kind, mapping, env, heliostats, targets, reference, ignored)


def _stage_log_rows(raw: pd.DataFrame, ctx: _LogContext) -> _Staged:
    """Rows of a log (a raw frame from :meth:`_LogRows.frame`) as a staged frame."""
    df = pd.DataFrame(index=raw.index)
    df["source_file"] = str(ctx.path)
    df["source_row"] = raw.index.to_numpy() + 1
    df["raw"] = [json.dumps(r, default=str) for r in raw.to_dict("records")]
    for canonical in ("heliostat_id", "measurement_id", "axis_1_steps", "axis_2_steps",
                      "timestamp", "sun_azimuth_deg", "sun_elevation_deg", "target_name",
                      "focal_spot_source"):
        df[canonical] = raw[ctx.columns[canonical]] if canonical in ctx.columns else ""
    if ctx.kind == "wgs84-log":
        for name in ("focal_spot_lat", "focal_spot_lon", "focal_spot_alt", "heliostat_lat",
                     "heliostat_lon", "heliostat_alt", "target_center_lat", "target_center_lon",
                     "target_center_alt"):
            df[name] = raw[ctx.columns[name]] if name in ctx.columns else ""
        for src, dst in (("focal_spot", "focal_spot"), ("heliostat", "heliostat"),
                         ("target_center", "target")):
            _wgs84_columns_to_enu(df, src, dst, ctx.reference)
        hpos = _to_float_frame(df, ["heliostat_lat", "heliostat_lon", "heliostat_alt"])
        df["_hpos_wgs84"] = list(zip(hpos["heliostat_lat"], hpos["heliostat_lon"], hpos["heliostat_alt"]))
    else:
        for name in _ENU_LOG_COLUMNS:
            df[name] = raw[ctx.columns[name]] if name in ctx.columns else ""
    for env_name, (col, integer) in ctx.env.items():
        numeric = pd.to_numeric(raw[col].replace("", np.nan), errors="coerce")
        df[env_name] = numeric if integer else numeric.astype(float)
    df["_reject"] = None
    df["focal_spot_source"] = df["focal_spot_source"].replace("", "log")
    return _Staged(df, ctx.heliostats, ctx.targets, ctx.reference, ctx.kind, ctx.ignored)


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
def _validate(st: _Staged, opts: IngestOptions, checks: "_SourceChecks"):
    """Kept rows, rejected rows and heliostat rows of staged rows (a whole source or a chunk
    holding every row of its heliostats: nothing here looks beyond one heliostat's rows, except
    what goes to ``checks``, which judges the whole source once all its chunks were seen)."""
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
    df["heliostat_id"] = df["heliostat_id"].map(_id_text)
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
    _reject_invalid_ids(df["heliostat_id"], reject)
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

    # env values: non-finite or overflowing cells are blanked (the row is kept), and flagged
    if env_cols:
        blanked = pd.Series("", index=df.index, dtype=object)
        for col in env_cols:
            v = pd.to_numeric(df[col], errors="coerce").astype(float)
            faulty = np.isinf(v) | (v.abs() > ENV_ABS_MAX)
            if faulty.any():
                blanked[faulty] = blanked[faulty] + [f"{col}={x:g}; " for x in v[faulty]]
                df[col] = v.where(~faulty)
        df["qa_env_blanked"] = blanked.str.rstrip("; ")

    # timestamps
    ts = pd.Series(pd.NaT, index=df.index, dtype="datetime64[us, UTC]")
    if "timestamp" in df:
        ts, bad_ts, naive, ambiguous, implausible = _parse_timestamps(
            df["timestamp"], opts.timezone, opts.date_format, _time_bounds(opts))
        checks.add_timestamps(df, ts_given, naive, ambiguous)  # all naive/ambiguous: refused
        reject(bad_ts & ts_given, "unparsable_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} does not match --date-format "
                                             f"{opts.date_format!r}" if opts.date_format else
                                   f"timestamp {v!r} is not a UTC time"))
        reject(ambiguous & ts_given, "ambiguous_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} has day and month as numbers, "
                                             "which heliocal cannot tell apart: give "
                                             "--date-format (e.g. '%d.%m.%Y %H:%M:%S%z')"))
        reject(naive & ts_given, "unparsable_timestamp",
               df["timestamp"].map(lambda v: f"timestamp {v!r} has no time zone"))
        reject(implausible.notna() & ts_given, "implausible_timestamp", implausible)
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
    kept = kept[cols + env_cols + (["qa_env_blanked"] if env_cols else [])]
    return kept, rejected, heliostats


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


def _parse_timestamps(values: pd.Series, timezone: str | None, date_format: str | None = None,
                      bounds: tuple[pd.Timestamp, pd.Timestamp] | None = None):
    """Parse to UTC; returns (timestamps, unparsable, no-zone, ambiguous, implausible) where the
    last is a Series of reasons (``None`` for a plausible or missing time).

    A time outside ``bounds`` is reported as implausible and left missing; each time is converted
    to microseconds on its own, so a year outside pandas' nanosecond range never fails the whole
    column."""
    text = values.map(lambda v: v.strip() if isinstance(v, str) else ("" if v is None else str(v)))
    stamps = [None] * len(text)  # filled in a list: a Series item assignment per row is slow
    bad = np.zeros(len(text), bool)
    naive = np.zeros(len(text), bool)
    ambiguous = np.zeros(len(text), bool)
    implausible = [None] * len(text)
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
            except Exception:  # noqa: BLE001 - invalid/ambiguous local time
                bad[i] = True
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
    ts = pd.Series(pd.DatetimeIndex(micro).tz_localize("UTC"), index=values.index)
    return (ts, pd.Series(bad, index=values.index), pd.Series(naive, index=values.index),
            pd.Series(ambiguous, index=values.index), pd.Series(implausible, index=values.index,
                                                                dtype=object))


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


# ------------------------------------------------------------------------------------------------
# whole-source checks, accumulated over the chunks of a source
# ------------------------------------------------------------------------------------------------
class _MedianVsThreshold:
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


class _SourceChecks:
    """Checks of :func:`_validate` that judge a whole source (time zones, azimuth convention):
    the chunks of one source add their rows here, :meth:`finish` raises once all were seen."""

    def __init__(self, opts: IngestOptions):
        self.opts = opts
        self.first: tuple | None = None  # (row label, source file) of the source's first row
        self.ts_given = 0
        self.naive = 0
        self.naive_example: tuple | None = None  # (row label, timestamp)
        self.ambiguous = 0
        self.ambiguous_example: tuple | None = None
        self.sun_diff = _MedianVsThreshold(5 * opts.sun_tolerance_deg + 1.0)
        self.sun_alt_diff = _MedianVsThreshold(1.0)

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


# ------------------------------------------------------------------------------------------------
# the stage: sources -> chunks of whole heliostats -> artifacts
# ------------------------------------------------------------------------------------------------
#: Rows per batch read from a log (``--batch-rows``): peak memory grows with it, not with the log.
DEFAULT_BATCH_ROWS = 25_000
#: Rows per row group of measurements.parquet (sorted by heliostat, so a heliostat's rows sit in
#: one or two row groups and ``read_artifact(..., heliostats=...)`` skips the others).
MEASUREMENTS_ROW_GROUP_ROWS = 32_768


@dataclass
class _Chunk:
    kept: pd.DataFrame  # MEASUREMENTS columns + env_*, plus _src and _seq
    rejected: pd.DataFrame  # REJECTED columns plus _src, _seq, _cross
    derived: dict[str, dict]  # heliostat rows derived from the log rows (no properties)


class _Source:
    """One source: read (and spilled) on construction, validated chunk by chunk by :meth:`chunks`."""

    def __init__(self, index: int, path: Path, opts: IngestOptions, batch_rows: int | None,
                 spill_dir: Path | None):
        self.index, self.path, self.opts, self.batch_rows = index, path, opts, batch_rows
        self.kind = detect_source(path)
        if self.kind == "paint":
            self._paint = _stage_paint(path, opts)
            self.rows = len(self._paint.frame)
            self.heliostats = self._paint.heliostats
            self.ignored = self._paint.ignored_columns
            self.env: dict[str, bool] = {}
        else:
            self._log = _read_log_rows(path, self.kind, batch_rows, spill_dir)
            self._ctx = _log_context(self._log, opts, self.kind)
            self.rows = self._log.rows
            self.heliostats = self._ctx.heliostats
            self.ignored = self._ctx.ignored
            self.env = {name: integer for name, (_, integer) in self._ctx.env.items()}

    def _staged(self) -> Iterator[_Staged]:
        if self.kind == "paint":
            yield self._paint
            return
        for table in self._log.chunks(self.batch_rows):
            yield _stage_log_rows(self._log.frame(table), self._ctx)

    def chunks(self) -> Iterator[_Chunk]:
        """Validated chunks holding every row of a range of heliostats, in heliostat order."""
        checks = _SourceChecks(self.opts)
        for staged in self._staged():
            checks.add_rows(staged.frame)
            kept, rejected, helios = _validate(staged, self.opts, checks)
            kept = kept.assign(_src=self.index, _seq=kept.index.to_numpy())
            if self.kind == "paint":
                kept = kept.sort_values("heliostat_id", kind="mergesort")
            rejected = rejected.assign(_src=self.index, _seq=rejected.index.to_numpy(), _cross=0)
            derived = {h: r for h, r in helios.items() if h not in self.heliostats}
            yield _Chunk(kept, rejected, derived)
        checks.finish()


def _merge_sources(sources: list[_Source], on_rejected) -> Iterator[tuple[list[pd.DataFrame], dict]]:
    """Kept rows of all sources merged by heliostat: yields (parts in source order, heliostat
    rows) where the parts hold every kept row of a range of heliostats and the heliostat rows are
    the first source's (as :func:`ingest` always did). Rejected chunks go to ``on_rejected``."""
    iters = [s.chunks() for s in sources]
    buffers: list[pd.DataFrame | None] = [None] * len(sources)
    done = [False] * len(sources)
    derived: list[dict] = [{} for _ in sources]

    def pull(i: int) -> None:
        chunk = next(iters[i], None)
        if chunk is None:
            done[i] = True
            return
        on_rejected(chunk.rejected)
        derived[i].update(chunk.derived)
        buffers[i] = chunk.kept if buffers[i] is None or buffers[i].empty else pd.concat(
            [buffers[i], chunk.kept])

    while True:
        for i in range(len(sources)):
            while not done[i] and (buffers[i] is None or buffers[i].empty):
                pull(i)
        growing = [i for i in range(len(sources)) if not done[i]]
        live = [i for i in range(len(sources)) if buffers[i] is not None and not buffers[i].empty]
        if not live:
            return
        # rows of a heliostat below the smallest last heliostat of a source still read are complete
        cutoff = min(buffers[i]["heliostat_id"].max() for i in growing) if growing else None
        parts = []
        for i in live:
            take = (buffers[i]["heliostat_id"] < cutoff if cutoff is not None
                    else pd.Series(True, index=buffers[i].index))
            if take.any():
                parts.append(buffers[i].loc[take.to_numpy()])
                buffers[i] = buffers[i].loc[~take.to_numpy()]
        if not parts:
            for i in growing:
                if buffers[i]["heliostat_id"].max() == cutoff:
                    pull(i)
            continue
        ids = set().union(*(p["heliostat_id"].unique() for p in parts))
        rows = {}
        for hid in ids:
            for i, s in enumerate(sources):
                row = s.heliostats.get(hid) or derived[i].get(hid)
                if row is not None:
                    rows[hid] = row
                    break
            for d in derived:
                d.pop(hid, None)
        yield parts, rows


def _rejected_order(df: pd.DataFrame) -> pd.Series:
    """Sort key of rejected rows: by source file and row, then (as ingest concatenated them)
    validation rejections before cross-source duplicates, by source and row."""
    return pd.Series([f"{f}\0{r:020d}\0{c}\0{s:06d}\0{q:020d}" for f, r, c, s, q in zip(
        df["source_file"], df["source_row"].astype("int64"), df["_cross"], df["_src"], df["_seq"])],
        index=df.index, dtype=object)


class _IngestRun:
    """The ingest stage over all sources, handing out its results chunk by chunk."""

    def __init__(self, sources: Sequence[Path], opts: IngestOptions, batch_rows: int | None,
                 spill_dir: Path | None):
        self.opts = opts
        self.sources = [_Source(i, p, o, batch_rows, spill_dir)
                        for i, (p, o) in enumerate(_expand_sources(sources, opts))]
        env: dict[str, bool] = {}
        for s in self.sources:  # first appearance order, as pandas concatenated the sources
            for name, integer in s.env.items():
                env[name] = env.get(name, True) and integer
        for name in env:  # a source without the column gives it missing values: float
            env[name] = env[name] and all(name in s.env for s in self.sources)
        self.env_integer = env
        self.columns = MEASUREMENTS.column_names() + list(env) + (["qa_env_blanked"] if env else [])
        self.invalid_id_example: str | None = None  # detail of the first invalid_heliostat_id row

    def extra_types(self) -> dict:
        types = {"qa_sun_spa_diff_deg": pa.float64(), "qa_sun_mismatch": pa.bool_(),
                 "qa_env_blanked": pa.string()}
        types.update({n: pa.int64() if i else pa.float64() for n, i in self.env_integer.items()})
        return {n: types[n] for n in self.columns if n not in MEASUREMENTS.column_names()}

    def _complete(self, df: pd.DataFrame) -> pd.DataFrame:
        """``df`` with every env column of the run, in the dtype of the whole table."""
        df = df.reindex(columns=self.columns + ["_src", "_seq"])
        for name, integer in self.env_integer.items():
            if not integer:
                df[name] = df[name].astype(float)
        if self.env_integer:  # a source without env columns has nothing blanked
            df["qa_env_blanked"] = df["qa_env_blanked"].fillna("")
        return df

    def execute(self, on_measurements, on_heliostats, on_rejected) -> dict:
        """Validate every source; hand over measurements (with ``_src``/``_seq``), heliostat rows
        and rejected rows (with ``_src``/``_seq``/``_cross``) chunk by chunk; return the summary."""
        counts: dict[str, int] = {}
        reasons: dict[str, int] = {}
        default_geometry: list[str] = []
        n_kept = n_rejected = mismatch = 0

        def rejected(df: pd.DataFrame) -> None:
            nonlocal n_rejected
            n_rejected += len(df)
            for reason, n in df["reason"].value_counts().items():
                reasons[reason] = reasons.get(reason, 0) + int(n)
            bad_id = df["reason"] == "invalid_heliostat_id"
            if self.invalid_id_example is None and bad_id.any():
                self.invalid_id_example = str(df.loc[bad_id, "detail"].iloc[0])
            if len(df):
                on_rejected(df)

        for parts, rows in _merge_sources(self.sources, rejected):
            group = self._complete(pd.concat(parts))
            # duplicates across sources: first source wins
            key = group["heliostat_id"].astype(str) + "\0" + group["measurement_id"].astype(str)
            dup = key.duplicated(keep="first").to_numpy()
            if dup.any():
                extra = group.loc[dup]
                rejected(pd.DataFrame({
                    "source_file": extra["source_file"], "source_row": extra["source_row"],
                    "heliostat_id": extra["heliostat_id"], "measurement_id": extra["measurement_id"],
                    "reason": "duplicate_measurement_id",
                    "detail": "measurement id already ingested from an earlier source",
                    "raw": extra.drop(columns=["timestamp", "_src", "_seq"]).to_json(
                        orient="records", lines=True).splitlines(),
                    "_src": extra["_src"], "_seq": extra["_seq"], "_cross": 1}))
                group = group.loc[~dup]
            n = group.groupby("heliostat_id").size()
            helio = pd.DataFrame([{**rows[hid], "n_measurements": int(k)} for hid, k in sorted(n.items())],
                                 columns=HELIOSTATS.column_names())
            for col in (c.name for c in HELIOSTATS.columns if c.dtype == "bool"):
                helio[col] = helio[col].astype(bool)
            counts.update({h: int(k) for h, k in n.items()})
            default_geometry += [h for h in n.index if rows[h]["properties_source"] == "default-juelich"]
            n_kept += len(group)
            mismatch += int(group["qa_sun_mismatch"].sum())
            on_measurements(group)
            on_heliostats(helio)
        rows_read = sum(s.rows for s in self.sources)
        info = {
            "sources": {str(s.path): s.kind for s in self.sources},
            "rows_read": rows_read,
            "kept": n_kept,
            "rejected": n_rejected,
            "rejected_by_reason": dict(sorted(reasons.items())),
            "heliostats": dict(sorted(counts.items())),
            "heliostats_with_default_geometry": sorted(default_geometry),
            "sun_mismatch_rows": mismatch,
            "ignored_columns": {str(s.path): s.ignored for s in self.sources if s.ignored},
            "env_columns": sorted(self.env_integer),
        }
        if rows_read != n_kept + n_rejected:  # pragma: no cover - an invariant
            raise RuntimeError(f"ingest lost rows: read {rows_read}, kept {n_kept}, "
                               f"rejected {n_rejected}")
        return info


def _sources(sources: Iterable[str | os.PathLike]) -> list[Path]:
    sources = [Path(s) for s in sources]
    if not sources:
        raise InputError("no SOURCE given; pass a PAINT folder or a CSV/Parquet log")
    return sources


def ingest(sources: Iterable[str | os.PathLike], options: IngestOptions | None = None):
    """Read every source and return (measurements, heliostats, rejected, info) DataFrames.

    Everything is held in memory (see :func:`run_ingest` for the streaming stage). Raises
    :class:`InputError` when a source cannot be read at all; row-level problems become rows of
    ``rejected`` with a reason from :data:`~heliocal.pipeline.artifacts.schemas.REJECTION_REASONS`.
    Rows come in source order (the artifacts sort them).
    """
    opts = (options or IngestOptions()).validate()
    run = _IngestRun(_sources(sources), opts, None, None)
    kept, helio, rejected = [], [], []
    info = run.execute(kept.append, helio.append, rejected.append)
    measurements = (pd.concat(kept) if kept else run._complete(pd.DataFrame()))
    measurements = measurements.sort_values(["_src", "_seq"], kind="mergesort")
    measurements = measurements.drop(columns=["_src", "_seq"]).reset_index(drop=True)
    helio = pd.concat(helio, ignore_index=True) if helio else pd.DataFrame(columns=HELIOSTATS.column_names())
    rej_cols = REJECTED.column_names()
    if rejected:
        rej = pd.concat(rejected).sort_values(["_cross", "_src", "_seq"], kind="mergesort")
        rej = rej[rej_cols].reset_index(drop=True)
    else:
        rej = pd.DataFrame(columns=rej_cols)
    return measurements, helio, rej, info


class _SpillFolder(os.PathLike):
    """A hidden folder in the workdir for sorted runs, made when the first run is written and
    removed (with its runs) when the stage ends, also on an error; usable as the folder of a
    :class:`SortedSpill`."""

    def __init__(self, workdir: Path):
        self.workdir = workdir
        self.path: Path | None = None

    def __fspath__(self) -> str:
        if self.path is None:
            self.path = Path(tempfile.mkdtemp(prefix=".ingest-spill-", dir=self.workdir))
        return str(self.path)

    def __truediv__(self, name: str) -> Path:
        return Path(self) / name

    def __enter__(self) -> "_SpillFolder":
        return self

    def __exit__(self, *exc) -> None:
        if self.path is not None:
            shutil.rmtree(self.path, ignore_errors=True)


class _RejectedSink:
    """Rejected rows in memory up to ``batch_rows``, beyond that sorted runs in the spill folder;
    :meth:`chunks` yields them in the order of rejected.parquet."""

    _KEY = "__heliocal_order"

    def __init__(self, spill_dir: Path, batch_rows: int):
        self.batch_rows = batch_rows
        self.held: list[pd.DataFrame] = []
        self.held_rows = 0
        self.spill = SortedSpill(spill_dir, "rejected", self._KEY)  # a _SpillFolder

    def _table(self, frames: list[pd.DataFrame]) -> pa.Table:
        df = pd.concat(frames)
        key = _rejected_order(df).to_numpy()
        order = np.argsort(key, kind="stable")  # the order _to_table's sort keeps
        table = _to_table(df.iloc[order][REJECTED.column_names()], REJECTED)
        return table.append_column(self._KEY, pa.array(key[order].tolist(), pa.string()))

    def add(self, df: pd.DataFrame) -> None:
        self.held.append(df)
        self.held_rows += len(df)
        if self.held_rows >= self.batch_rows:
            self.spill.add(self._table(self.held))
            self.held, self.held_rows = [], 0

    @property
    def spilled(self) -> bool:
        return bool(self.spill.runs)

    def chunks(self) -> Iterator[pd.DataFrame]:
        if self.held and self.spill.runs:
            self.spill.add(self._table(self.held))
            self.held = []
        if self.held:
            yield from (self._table(self.held).sort_by(self._KEY).drop_columns([self._KEY])
                        .to_pandas(),)
            return
        for table in self.spill.merged(self.batch_rows):
            yield table.drop_columns([self._KEY]).to_pandas()


@locks_workdir("ingest")
@stage_transaction("ingest")
def run_ingest(sources: Sequence[str | os.PathLike], workdir: str | os.PathLike,
               options: IngestOptions | None = None, batch_rows: int = DEFAULT_BATCH_ROWS) -> dict:
    """The ``ingest`` stage: read ``sources``, write the three artifacts into ``workdir``.

    Logs are read ``batch_rows`` rows at a time; a log longer than that is spilled, sorted by
    heliostat, to a hidden folder in ``workdir`` and validated heliostat range by heliostat range,
    so memory is bounded by the batch (and the largest heliostat), not by the field. The
    artifacts are written chunk by chunk to temporary files that replace the previous ones only
    when the whole stage succeeded. Returns the summary (rows read, kept, rejected per reason,
    heliostats).
    """
    opts = (options or IngestOptions()).validate()
    batch_rows = check_int(batch_rows, "batch_rows", "ingest", 1)
    sources = _sources(sources)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    inputs = {f"source:{s}": s for s in sources}
    if opts.tower:
        inputs["tower"] = opts.tower
    if opts.properties:
        inputs["properties"] = opts.properties
    resolved = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(opts).items()}
    resolved["sources"] = [str(s) for s in sources]
    prov = dict(stage="ingest", options=resolved, inputs=inputs)
    with _SpillFolder(workdir) as spill, contextlib.ExitStack() as stack:
        run = _IngestRun(sources, opts, batch_rows, spill)
        rejected = _RejectedSink(spill, batch_rows)
        helio: list[pd.DataFrame] = []
        # measurements.parquet is written while the sources are validated; it replaces the
        # previous one last, after rejected.parquet and heliostats.parquet
        measurements = stack.enter_context(artifact_writer(
            workdir, MEASUREMENTS, extra=run.extra_types(),
            row_group_size=MEASUREMENTS_ROW_GROUP_ROWS, **prov))
        info = run.execute(lambda df: measurements.write(df.drop(columns=["_src", "_seq"])),
                           helio.append, rejected.add)
        if info["kept"] == 0:
            reasons = ", ".join(f"{k}: {v}" for k, v in info["rejected_by_reason"].items())
            how = (f": {run.invalid_id_example}" if run.invalid_id_example
                   else "; see the reasons and fix the source")
            raise InputError(f"no measurement of {', '.join(map(str, sources))} could be kept "
                             f"({reasons}){how}")
        if rejected.spilled:
            with artifact_writer(workdir, REJECTED, **prov) as writer:
                for chunk in rejected.chunks():
                    writer.write(chunk)
        else:
            write_artifact(next(rejected.chunks(), pd.DataFrame(columns=REJECTED.column_names())),
                           workdir, REJECTED, **prov)
        write_artifact(pd.concat(helio, ignore_index=True), workdir, HELIOSTATS, **prov)
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
    if info["rejected_by_reason"].get("invalid_heliostat_id"):
        log.warning("%s", invalid_id_message(info["rejected_by_reason"]["invalid_heliostat_id"]))
    return info


def invalid_id_message(n: int) -> str:
    """One line for the summary: rows rejected for their heliostat id and how to fix them."""
    return (f"{n} rows rejected as invalid_heliostat_id: heliostat ids must be {HELIOSTAT_ID_RULE} "
            "(they become file names); rename them in the source (rejected.parquet's detail "
            "suggests a name) and rerun ingest")
