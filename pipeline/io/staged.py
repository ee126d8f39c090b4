"""What every reader of ``ingest`` produces: the options of reading (:class:`IngestOptions`) and the
staged rows (:class:`Staged`), raw values in canonical column names before validation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import ParameterError, check_choice, check_float
from ..vocabulary import (DEFAULT_MAX_SPOT_DISTANCE_M, DEFAULT_SUN_TOLERANCE_DEG,
                          DEFAULT_TIME_MAX_MARGIN_DAYS, DEFAULT_TIME_MIN, AzimuthConvention,
                          FocalSpotDetector)

__all__ = [
    "IngestOptions",
    "utc_bound",
    "time_bounds",
    "STAGED_NUMERIC",
    "Staged",
    "TIME_MAX_MARGIN",
    "ENV_ABS_MAX",
    "Target",
]


# ------------------------------------------------------------------------------------------------
# options and small types
# ------------------------------------------------------------------------------------------------


#: The latest plausible time is now plus this margin (``--time-max`` overrides it; see
#: :data:`~heliocal.pipeline.vocabulary.DEFAULT_TIME_MAX_MARGIN_DAYS`).
TIME_MAX_MARGIN = pd.Timedelta(days=DEFAULT_TIME_MAX_MARGIN_DAYS)


#: An env value beyond this magnitude is blanked (``qa_env_blanked``): the fine model standardises
#: its inputs with the mean and standard deviation of the column, and squares of values this large
#: overflow float64, which would make the input constant for every row (1e308 is what a logger
#: writes on overflow). No physical reading in any unit comes near it.
ENV_ABS_MAX = 1e100


def utc_bound(value, name: str = "") -> pd.Timestamp | None:
    """``value`` (text or timestamp) as a UTC timestamp (naive means UTC); ``None`` if it is not
    a readable time."""
    try:
        stamp = pd.Timestamp(value)
    except (ValueError, TypeError, OverflowError):
        return None
    if stamp is pd.NaT:
        return None
    return stamp.tz_localize("UTC") if stamp.tzinfo is None else stamp.tz_convert("UTC")


def time_bounds(opts: "IngestOptions") -> tuple[pd.Timestamp, pd.Timestamp]:
    """(earliest, latest) plausible timestamp of a run."""
    lo = utc_bound(opts.time_min)
    hi = (utc_bound(opts.time_max) if opts.time_max is not None
          else pd.Timestamp.now(tz="UTC") + TIME_MAX_MARGIN)
    return lo, hi


def _is_time_zone(name: str) -> bool:
    """Whether pandas knows ``name`` as a time zone (what localising a naive timestamp needs)."""
    try:
        pd.Timestamp("2000-01-01").tz_localize(name)
    except Exception:  # noqa: BLE001 - zoneinfo, pytz and dateutil raise different types
        return False
    return True


@dataclass
class IngestOptions:
    """Resolved options of ``ingest`` (see the CLI's help for each)."""

    tower: Path | None = None
    properties: Path | None = None
    focal_spot: str = FocalSpotDetector.utis.value
    max_spot_distance_m: float = DEFAULT_MAX_SPOT_DISTANCE_M
    sun_tolerance_deg: float = DEFAULT_SUN_TOLERANCE_DEG
    azimuth_convention: str = AzimuthConvention.south.value
    timezone: str | None = None
    location: tuple[float, float, float] | None = None
    date_format: str | None = None  # strptime format of every timestamp (e.g. "%d.%m.%Y %H:%M:%S%z")
    time_min: str = DEFAULT_TIME_MIN  # earliest plausible timestamp (UTC unless it has a zone)
    time_max: str | None = None  # latest plausible timestamp; None: now + TIME_MAX_MARGIN

    def validate(self) -> "IngestOptions":
        for name in ("time_min", "time_max"):
            value = getattr(self, name)
            if value is not None and utc_bound(value, name) is None:
                raise ParameterError(f"The '{name}' parameter of ingest must be a date or time "
                                     f"such as 1990-01-01 or 2024-06-01T12:00Z. Got {value!r} "
                                     "instead.")
        if self.date_format is not None and "%" not in str(self.date_format):
            raise ParameterError(f"The 'date_format' parameter of ingest must be a strptime "
                                 f"format such as '%d.%m.%Y %H:%M:%S%z'. Got {self.date_format!r} "
                                 "instead.")
        if self.timezone is not None and not _is_time_zone(self.timezone):
            raise ParameterError(f"The 'timezone' parameter of ingest must be an IANA time zone "
                                 f"such as Europe/Berlin or UTC. Got {self.timezone!r} instead.")
        check_choice(self.focal_spot, "focal_spot", "ingest", FocalSpotDetector.values())
        check_choice(self.azimuth_convention, "azimuth_convention", "ingest",
                     AzimuthConvention.values())
        check_float(self.max_spot_distance_m, "max_spot_distance_m", "ingest", 0.0, None, False)
        check_float(self.sun_tolerance_deg, "sun_tolerance_deg", "ingest", 0.0, None, False)
        return self


@dataclass
class Target:
    name: str
    center_enu: np.ndarray
    normal_enu: np.ndarray


# ------------------------------------------------------------------------------------------------
# staging: every source becomes a frame of raw values plus provenance columns
# ------------------------------------------------------------------------------------------------
STAGED_NUMERIC = ("axis_1_steps", "axis_2_steps", "sun_azimuth_deg", "sun_elevation_deg",
                   "focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m",
                   "heliostat_e_m", "heliostat_n_m", "heliostat_u_m",
                   "target_e_m", "target_n_m", "target_u_m",
                   "target_normal_e", "target_normal_n", "target_normal_u")


@dataclass
class Staged:
    """Raw rows of one source (strings or numbers), plus what the source defines."""

    frame: pd.DataFrame  # canonical names, raw values, source_file, source_row, raw, _reject
    heliostats: dict[str, dict]
    targets: dict[str, Target]
    reference: tuple[float, float, float] | None
    kind: str
    ignored_columns: list[str] = field(default_factory=list)
