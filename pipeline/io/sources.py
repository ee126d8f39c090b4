"""Input sources of ``ingest``: which kind a path is (PAINT folder, WGS84 or ENU log, a simulated
field), where the tower file lives, and the tower's targets.

The kinds are described in :mod:`heliocal.pipeline.stages.ingest` and docs/input_formats.md.
"""

from __future__ import annotations

import csv
import json
import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..artifacts.paths import kind_of
from ..errors import InputError
from ..physics.geodesy import wgs84_to_enu
from .staged import IngestOptions, Target
from .text import guess_delimiter, load_json, open_csv_text, shorten

__all__ = [
    "SOURCE_KINDS",
    "Tower",
    "detect_source",
    "simulate_sources",
    "find_tower_file",
    "read_tower",
    "expand_sources",
    "TIMESTAMPS_FILENAME",
    "TOWER_FILENAME",
]

log = logging.getLogger("heliocal.ingest")


SOURCE_KINDS = ("paint", "wgs84-log", "enu-log", "simulate")


TOWER_FILENAME = "tower-measurements.json"


TIMESTAMPS_FILENAME = "timestamps.json"


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
            raise InputError(f"{path}: not a readable Parquet file ({shorten(exc)}); export the log "
                             "again or give a CSV") from exc
    with open_csv_text(path) as text:
        try:
            for cells in csv.reader(text, skipinitialspace=True):
                if cells and any(c.strip() for c in cells):
                    return [c.strip() for c in cells]
        except csv.Error as exc:
            raise InputError(f"{path}: malformed CSV header ({shorten(exc)}); fix the first line") from exc
    raise InputError(f"{path}: the file is empty; give a calibration log with a header row "
                     "and one row per measurement")


def detect_source(path: str | os.PathLike) -> str:
    """Return the kind of ``path`` (one of :data:`SOURCE_KINDS`) or raise :class:`InputError`."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder; check the path")
    if not path.is_dir() and not path.is_file():  # a FIFO or device: never opened, it could block
        raise InputError(f"{path} is {kind_of(path.stat().st_mode)}, not a file or folder; save "
                         "the log to a file and give that")
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
                         f"{guess_delimiter(next(iter(cols)))!r} as delimiter: save it "
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
            ref = load_json(folder / _SIMULATE_MARKER, "the ground truth").get("reference_wgs84")
            if isinstance(ref, list) and len(ref) == 3 and all(
                    isinstance(x, (int, float)) for x in ref):
                location = tuple(float(x) for x in ref)
        out.append((enu_log, replace(options, properties=enu_props, location=location)))
    if not out:
        raise InputError(f"{folder}: a heliocal simulate folder without calibration_log.csv, "
                         "paint/ or enu_log.csv; rerun `heliocal simulate` into an empty folder")
    return out


def expand_sources(sources: Sequence[Path],
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


def read_tower(path: Path | None) -> Tower:
    """Parse a PAINT ``tower-measurements.json``: reference point and targets (ENU)."""
    if path is None:
        return Tower(path=None, reference=None)
    data = load_json(path, "the tower file")
    try:
        ref = tuple(float(x) for x in data["power_plant_properties"]["coordinates"])
        if len(ref) != 3:
            raise ValueError("coordinates must be [lat, lon, alt]")
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: power_plant_properties.coordinates [lat, lon, alt] is missing or "
                         f"malformed ({shorten(exc)}); fix the tower file") from exc
    targets = {}
    for name, spec in data.items():
        if name == "power_plant_properties" or not isinstance(spec, dict):
            continue
        try:
            center = [float(x) for x in spec["coordinates"]["center"]]
            normal = np.asarray([float(x) for x in spec.get("normal_vector", (0, 1, 0))], float)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path}: target {name!r} has no readable coordinates.center "
                             f"({shorten(exc)}); fix the tower file") from exc
        e, n, u = wgs84_to_enu(center[0], center[1], center[2], ref)
        targets[name] = Target(name, np.array([float(e), float(n), float(u)]),
                               normal / np.linalg.norm(normal))
    return Tower(path=path, reference=ref, targets=targets)
