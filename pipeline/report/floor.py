"""The measurement floor the report draws on the error distribution: given, or the simulator's
noise floor of a simulated field. Standard library only: an unchanged report rerun compares it
before anything is imported (:mod:`heliocal.pipeline.artifacts.unchanged`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from ..artifacts.manifests import load_manifest

__all__ = ["MeasurementFloor", "find_measurement_floor"]


@dataclass
class MeasurementFloor:
    """The measurement floor drawn on the error distribution, and why there is none."""

    value_mrad: float | None
    source: str                 # where the value comes from ("" without one)
    problems: list[str]         # a ground_truth.json that could not be used, and why


def find_measurement_floor(workdir: Path, floor_mrad: float | None) -> MeasurementFloor:
    """``floor_mrad`` when given, else the median ``noise_floor_mrad`` of the heliostats in the
    ``ground_truth.json`` of a simulated field the sources came from (``heliocal simulate`` writes
    it beside them), with every ``ground_truth.json`` that could not be used and why (the report
    logs them and lists them in its notes)."""
    if floor_mrad is not None:
        return MeasurementFloor(float(floor_mrad), "given with --floor-mrad", [])
    m = load_manifest(workdir, "ingest")
    sources = (m.data.get("options", {}).get("sources") or []) if m is not None else []
    problems = []
    for src in sources:
        p = Path(src)
        truth = (p if p.is_dir() else p.parent) / "ground_truth.json"
        if not truth.is_file():
            continue
        try:
            vals = _noise_floors_mrad(truth)
        except ValueError as exc:
            problems.append(f"{truth}: {exc}; the report has no measurement floor from it "
                            "(give --floor-mrad)")
            continue
        if vals:
            mid = len(vals) // 2
            med = vals[mid] if len(vals) % 2 else (vals[mid - 1] + vals[mid]) / 2
            return MeasurementFloor(med, "simulator's noise floor, median over the field",
                                    problems)
    return MeasurementFloor(None, "", problems)


def _noise_floors_mrad(truth: Path) -> list[float]:
    """The heliostats' finite ``noise_floor_mrad`` values [mrad] of a ``ground_truth.json``,
    sorted; ValueError saying what is wrong with a file that is not one."""
    try:
        data = json.loads(truth.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"not valid JSON ({exc.msg}, line {exc.lineno} column "
                         f"{exc.colno})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot be read as text ({exc})") from None
    helios = data.get("heliostats", {}) if isinstance(data, dict) else None
    if not isinstance(helios, dict):
        raise ValueError("'heliostats' is not an object of heliostats")
    vals = []
    for hid, h in helios.items():
        value = h.get("noise_floor_mrad", "nan") if isinstance(h, dict) else None
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"heliostat {hid!r} has no number as noise_floor_mrad") from None
        if math.isfinite(value):
            vals.append(value)
    return sorted(vals)
