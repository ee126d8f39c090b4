"""``simulate``: write a simulated field (:func:`heliocal.pipeline.models.simulator.simulate_field`)
as heliocal's input files: one CSV log per heliostat kind, the heliostat properties, the tower
file, and ``ground_truth.json`` with the true parameters and disturbances.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from .. import __version__
from ..artifacts.audit import refuse_links
from ..artifacts.paths import atomic_write_text, flush_to_disk, safe_child, safe_name
from ..artifacts.workdir_lock import LOCK_FILENAME, locks_workdir
from ..errors import InputError
from ..models.changes import event_json
from ..models.disturbances import DISTURBANCE_COLUMNS
from ..models.simulator import SimulatedField
from ..physics.geodesy import enu_to_wgs84
from ..physics.parameters import PARAMETER_INDEX, PARAMETER_NAMES

__all__ = [
    "json_text",
    "tower_json",
    "write_field",
    "OUTPUT_FILES",
]


#: Files (and the folder ``paint/``) that :func:`write_field` writes into its output folder.
OUTPUT_FILES = ("tower-measurements.json", "calibration_log.csv", "ground_truth.json",
                "ground_truth_disturbances.csv", "enu_log.csv", "enu_properties.toml")


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------
def json_text(obj) -> str:
    """The JSON text heliocal writes: indented, no NaN, a final newline."""
    return json.dumps(obj, indent=2, allow_nan=False) + "\n"


def _fmt(x) -> str:
    """Shortest exact text of a number (floats round-trip exactly through repr)."""
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x)).lower()
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    return repr(float(x))


def _csv(header: Sequence[str], rows) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow([v if isinstance(v, str) else _fmt(v) for v in r])
    return buf.getvalue()


def _iso(t: pd.Timestamp) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def _named(vector: torch.Tensor) -> dict[str, float]:
    return {name: float(vector[i]) for i, name in enumerate(PARAMETER_NAMES)}


def tower_json(field_: SimulatedField) -> dict:
    """The tower file (PAINT's tower-measurements.json layout) of a simulated field."""
    out = {"power_plant_properties": {"ID": "SYNTHETIC-HELIOCAL", "coordinates": list(field_.reference)}}
    for name, t in field_.targets.items():
        out[name] = {"type": "planar", "normal_vector": [0, 1, 0],
                     "coordinates": {"center": t["center_wgs84"], **t["corners_wgs84"]}}
    return out


def _ground_truth(field_: SimulatedField, files: dict) -> dict:
    helio = {}
    for hid, h in field_.heliostats.items():
        n = int((field_.measurements["heliostat_id"] == hid).sum())
        deviation = {name: float(h.true[PARAMETER_INDEX[name]] - h.nominal[PARAMETER_INDEX[name]])
                     for name in h.deviated}
        helio[hid] = {
            "kinematic_type": h.kinematic_type, "actuator_type": h.actuator_type,
            "dynamic": h.dynamic, "written_as": "paint" if h.paint_properties else "enu-log",
            "position_enu_m": [float(h.row[f"heliostat_{a}_m"]) for a in "enu"],
            "n_measurements": n,
            "noise_floor_mrad": h.noise_floor_mrad,
            "error_true_static_mrad": h.error_true_static_mrad,
            "error_nominal_mrad": h.error_nominal_mrad,
            "deviated_parameters": list(h.deviated),
            "deviation": deviation,
            "disturbances": h.disturbances,
            "nominal": _named(h.nominal),
            "true": _named(h.true),
        }
        if "changes" in field_.settings:  # only then: a field without changes stays as it was
            helio[hid]["changes"] = [event_json(e) for e in h.changes]
    return {
        "generator": f"heliocal {__version__} simulate",
        "settings": field_.settings,
        "conventions": {
            "parameters": "heliocal's 28 kinematic parameters (heliocal.pipeline.physics.parameters."
                          "PARAMETER_NAMES, units in the names; increments in steps/m for linear "
                          "and steps/rad for ideal actuators); axis_1_initial_angle_rad in ARTIST's "
                          "convention, i.e. the PAINT file's initial_angle minus pi/2, as ingest "
                          "reads it",
            "true": "nominal + deviation; dynamic heliostats add the disturbances per measurement "
                    "(values per measurement in ground_truth_disturbances.csv)",
            "noise_mrad": "standard deviation per target-plane axis (horizontal, vertical) of the "
                          "beam direction's noise: the focal spot moves by distance(mirror centre, "
                          "spot) * noise_mrad / 1000 along each axis",
            "noise_floor_mrad": "mean error_mrad (heliocal.pipeline.physics.metrics) of the true model, "
                                "disturbances included, on the noisy measurements",
            "error_true_static_mrad": "same for the true static geometry without disturbances",
            **({"changes": "per heliostat, its change events in time order (models.changes): "
                           "kind step|episode|drift, start (first day, UTC midnight), end (first "
                           "day back to normal for an episode), size_mrad or rate_mrad_per_year, "
                           "parameters {name: offset [rad] at full size, per year for a drift}, "
                           "n_rows (measurements it affects), effect_mrad (mean angle it turns "
                           "the mirror normal on those rows)"}
               if "changes" in field_.settings else {}),
            "error_nominal_mrad": "same for the nominal geometry",
            "positions": "ENU metres relative to the plant reference point (WGS84 lat, lon, "
                         "ellipsoidal height)",
        },
        "reference_wgs84": list(field_.reference),
        "noise_mrad": field_.settings["noise_mrad"],
        "files": files,
        "heliostats": helio,
    }


def _toml_properties(field_: SimulatedField, hids: Sequence[str]) -> str:
    lines = ["# Properties of the simulated az-el heliostats (ideal drives); heliostats.parquet",
             "# column names, ENU metres relative to the plant reference point.", ""]
    keys = ["kinematic_type", "actuator_type", "heliostat_e_m", "heliostat_n_m", "heliostat_u_m",
            *[f"{j}_translation_{a}_m" for j in ("joint_1", "joint_2", "concentrator") for a in "enu"],
            *[f"axis_{i}_{k}" for i in (1, 2) for k in ("min_steps", "max_steps",
                                                        "gear_ratio_steps_per_rad", "angle_offset_rad")]]
    for hid in hids:
        row = field_.heliostats[hid].row
        lines.append(f"[heliostats.{hid}]")
        for k in keys:
            v = row[k]
            lines.append(f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {_fmt(v)}")
        lines.append("")
    for name, t in field_.targets.items():
        lines.append(f"[targets.{name}]")
        lines.append("center_enu_m = [" + ", ".join(_fmt(v) for v in t["center_enu"]) + "]")
        lines.append("normal_enu = [" + ", ".join(_fmt(v) for v in t["normal_enu"]) + "]")
        lines.append("")
    return "\n".join(lines)


def _clear_previous(out: Path) -> None:
    """Remove the files a previous simulation wrote into ``out`` (nothing else)."""
    for name in OUTPUT_FILES:
        (out / name).unlink(missing_ok=True)
    paint = out / "paint"
    if paint.is_dir():
        (paint / "timestamps.json").unlink(missing_ok=True)
        for hdir in sorted(p for p in paint.iterdir() if p.is_dir()):
            (hdir / f"{hdir.name}-heliostat-properties.json").unlink(missing_ok=True)
            calib = hdir / "calibration"
            if calib.is_dir():
                for f in calib.glob("*-calibration-properties.json"):
                    f.unlink()
            for d in (calib, hdir):
                if d.is_dir() and not any(d.iterdir()):
                    d.rmdir()
        if not any(paint.iterdir()):
            paint.rmdir()


def _write_paint(out: Path, field_: SimulatedField, paint_ids: list[str], is_paint: np.ndarray,
                 spot_wgs: np.ndarray) -> dict[str, str]:
    """The juelich heliostats as a PAINT folder (properties, one calibration file per
    measurement, timestamps.json) and as a WGS84 log (calibration_log.csv); returns the files."""
    files: dict[str, str] = {}
    calibration_dirs = {}
    for hid in paint_ids:
        hdir = safe_child(out / "paint", hid)
        atomic_write_text(safe_child(hdir, f"{hid}-heliostat-properties.json"),
                          json_text(field_.heliostats[hid].paint_properties))
        calibration_dirs[hid] = hdir / "calibration"
    rows = _rows_of(field_.measurements, is_paint)
    stamps = {}
    for r, spot in zip(rows, spot_wgs[is_paint]):
        hid, mid = r["heliostat_id"], r["measurement_id"]
        doc = {"motor_position": {"axis_1_motor_position": int(r["axis_1_steps"]),
                                  "axis_2_motor_position": int(r["axis_2_steps"])},
               "target_name": r["target_name"],
               "sun_elevation": float(r["sun_elevation_deg"]),
               "sun_azimuth": float(r["sun_azimuth_deg"]),
               "focal_spot": {"UTIS": [float(v) for v in spot]}}
        # the heliostat's folder was checked above; each name is checked as a plain file name,
        # and the atomic write renames over the name (never writes through a link there)
        folder = calibration_dirs[hid]
        atomic_write_text(folder / safe_name(f"{mid}-calibration-properties.json", folder),
                          json.dumps(doc) + "\n", durable=False)
        stamps[f"{hid}_{mid}"] = _iso(r["timestamp"])
    flush_to_disk()   # the calibration files at once, before the index that lists them
    atomic_write_text(out / "paint" / "timestamps.json",
                      json_text(dict(sorted(stamps.items()))))
    files["paint"] = "paint/"

    header = ["heliostat_id", "timestamp", "sample_id", "sun_elevation", "sun_azimuth",
              "axis_1_motor_position", "axis_2_motor_position", "target_name",
              "heliostat_lat", "heliostat_lon", "heliostat_alt",
              "focal_spot_lat", "focal_spot_lon", "focal_spot_alt",
              "target_center_lat", "target_center_lon", "target_center_alt", "temperature"]
    lines = []
    for r, spot in zip(rows, spot_wgs[is_paint]):
        h = field_.heliostats[r["heliostat_id"]]
        t = field_.targets[r["target_name"]]["center_wgs84"]
        lines.append([r["heliostat_id"], _iso(r["timestamp"]), r["measurement_id"],
                      r["sun_elevation_deg"], r["sun_azimuth_deg"],
                      int(r["axis_1_steps"]), int(r["axis_2_steps"]), r["target_name"],
                      h.row["latitude_deg"], h.row["longitude_deg"], h.row["altitude_m"],
                      *spot, *t, r["temperature_c"]])
    atomic_write_text(out / "calibration_log.csv", _csv(header, lines))
    files["wgs84_log"] = "calibration_log.csv"
    return files


def _rows_of(measurements: pd.DataFrame, keep: np.ndarray) -> list[dict]:
    """The rows ``keep`` (bool mask) of ``measurements`` as dicts of plain Python values (the
    same text in the files as a row's values through ``.iloc``): one pass over the columns, where
    a row at a time through pandas costs more than writing the row."""
    picked = measurements[keep]
    columns = {c: list(picked[c]) for c in picked.columns}
    return [dict(zip(columns, values)) for values in zip(*columns.values())]


def _write_enu(out: Path, field_: SimulatedField, enu_ids: list[str],
               is_paint: np.ndarray) -> dict[str, str]:
    """The az-el heliostats as an ENU log with its TOML properties; returns the files."""
    files: dict[str, str] = {}
    header = ["heliostat_id", "measurement_id", "timestamp", "sun_azimuth_deg",
              "sun_elevation_deg", "axis_1_steps", "axis_2_steps", "target_name",
              "focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m", "temperature"]
    rows = []
    for r in _rows_of(field_.measurements, ~is_paint):
        rows.append([r["heliostat_id"], r["measurement_id"], _iso(r["timestamp"]),
                     r["sun_azimuth_deg"], r["sun_elevation_deg"], int(r["axis_1_steps"]),
                     int(r["axis_2_steps"]), r["target_name"], r["focal_spot_e_m"],
                     r["focal_spot_n_m"], r["focal_spot_u_m"], r["temperature_c"]])
    atomic_write_text(out / "enu_log.csv", _csv(header, rows))
    atomic_write_text(out / "enu_properties.toml", _toml_properties(field_, enu_ids))
    files["enu_log"] = "enu_log.csv"
    files["enu_properties"] = "enu_properties.toml"
    return files


@locks_workdir("simulate", "out_dir")
def write_field(field_: SimulatedField, out_dir: str | os.PathLike, *, overwrite: bool = False) -> dict:
    """Write a simulated field into ``out_dir`` (created if needed); every file atomically.

    Layout::

        paint/<HID>/<HID>-heliostat-properties.json   juelich heliostats (no facet data)
        paint/<HID>/calibration/<id>-calibration-properties.json
        paint/timestamps.json
        tower-measurements.json                       plant reference point and targets (PAINT)
        calibration_log.csv                           the juelich measurements as a WGS84 log,
                                                      with the env column ``temperature`` [°C]
        enu_log.csv, enu_properties.toml              az-el heliostats (ENU log + properties)
        ground_truth.json                             parameters, disturbances, noise floor
        ground_truth_disturbances.csv                 per measurement: temperature, disturbances

    Parameters
    ----------
    overwrite : replace a previous simulation's files in ``out_dir``; without it a non-empty
        ``out_dir`` is refused.

    Returns
    -------
    dict : summary (folder, files, heliostats with their noise floors).
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder; give a folder for the simulation")
    if out.is_dir():
        refuse_links(out)  # a planted link would have files written or removed outside
    if out.is_dir() and any(p.name != LOCK_FILENAME for p in out.iterdir()):
        if not overwrite:
            raise InputError(f"{out}: the folder is not empty; choose an empty or new folder, or "
                             "pass --overwrite to replace a previous simulation there")
        _clear_previous(out)
    out.mkdir(parents=True, exist_ok=True)
    meas = field_.measurements
    ref = field_.reference
    files: dict[str, str] = {}

    atomic_write_text(out / "tower-measurements.json", json_text(tower_json(field_)))
    files["tower"] = "tower-measurements.json"

    lat, lon, alt = enu_to_wgs84(meas["focal_spot_e_m"].to_numpy(), meas["focal_spot_n_m"].to_numpy(),
                                 meas["focal_spot_u_m"].to_numpy(), ref)
    spot_wgs = np.stack([lat, lon, alt], axis=1)   # (N, 3) lat, lon [deg], alt [m]
    paint_ids = [h for h, v in field_.heliostats.items() if v.paint_properties is not None]
    enu_ids = [h for h in field_.heliostats if h not in paint_ids]
    is_paint = meas["heliostat_id"].isin(paint_ids).to_numpy()

    if paint_ids:
        files.update(_write_paint(out, field_, paint_ids, is_paint, spot_wgs))
    if enu_ids:
        files.update(_write_enu(out, field_, enu_ids, is_paint))
    header = ["heliostat_id", "measurement_id", "timestamp", "temperature_c", *DISTURBANCE_COLUMNS]
    rows = [[r["heliostat_id"], r["measurement_id"], _iso(r["timestamp"]), r["temperature_c"],
             *[r[c] for c in DISTURBANCE_COLUMNS]] for _, r in meas.iterrows()]
    atomic_write_text(out / "ground_truth_disturbances.csv", _csv(header, rows))
    files["disturbances"] = "ground_truth_disturbances.csv"
    files["ground_truth"] = "ground_truth.json"
    atomic_write_text(out / "ground_truth.json", json_text(_ground_truth(field_, files)))
    return {
        "out": str(out), "files": files, "seed": field_.settings["seed"],
        "noise_mrad": field_.settings["noise_mrad"], "measurements": int(len(meas)),
        "heliostats": [{"heliostat_id": hid, "kinematic_type": h.kinematic_type,
                        "dynamic": h.dynamic,
                        "n_measurements": int((meas["heliostat_id"] == hid).sum()),
                        "noise_floor_mrad": h.noise_floor_mrad,
                        "error_true_static_mrad": h.error_true_static_mrad,
                        "error_nominal_mrad": h.error_nominal_mrad}
                       for hid, h in field_.heliostats.items()],
    }
