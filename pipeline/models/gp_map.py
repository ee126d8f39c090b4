"""The GP correction's sky map (the report's figure): computed once by the stage that fits the
model, stored in the model's configuration, read back with numpy and json alone.

The map is the faded correction on a grid of sun positions around the training rows
(:func:`heliocal.pipeline.models.gp_heliostat.correction_grid`). Only its mean needs the GP
(scikit-learn, with torch for the model file): ``fit-hybrid --mode gp`` and ``sweep`` have the
model at hand, so they evaluate it there and store it in the configuration's
:data:`MAP_KEY` section. The grid's axes and fade are cheap numpy on the configuration's ``fade``
entry (:class:`heliocal.pipeline.models.fade.Fade`), so they are computed again from it by the
same code as at the fit: the report draws the same arrays without importing torch or
scikit-learn (about 1.5 s of CPU). This module imports neither.

The section (:func:`map_section`)::

    "correction_map": {"n_azimuth": 64, "n_elevation": 40, "margin_deg": 15.0,
                       "time_s": 1690000000.0 or null (no training row has a time),
                       "encoding": "base64 <f8",
                       "mean_h_mrad": "...", "mean_v_mrad": "..."}

``mean_h_mrad`` and ``mean_v_mrad`` are the faded correction [mrad] (horizontal, vertical on the
mirror) at (elevation, azimuth), row-major (E, A), as the base64 text of their little-endian
float64 bytes: the same bits as computed (exact), in about 11 bytes a value where decimal text in
the indented configuration takes about 25.
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import pandas as pd

from .fade import Fade

__all__ = ["MAP_KEY", "MapGrid", "map_grid", "map_figure_data", "map_section",
           "stored_correction_map", "structure_label"]

#: The configuration's key of the stored map.
MAP_KEY = "correction_map"
_ENCODING = "base64 <f8"


@dataclass(frozen=True)
class MapGrid:
    """The sun positions and time a correction map is evaluated at.

    Attributes
    ----------
    azimuth_deg : (A,) sun azimuths [deg]; elevation_deg : (E,) sun elevations [deg].
    time_s : the time of every point [s since 1970 UTC] (NaN: none).
    margin_deg : how far the grid reaches beyond the training rows [deg].
    """

    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    time_s: float
    margin_deg: float

    @property
    def shape(self) -> tuple[int, int]:
        """(E, A): the maps' shape."""
        return len(self.elevation_deg), len(self.azimuth_deg)

    def points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """azimuth_deg, elevation_deg, time_s (E * A,) of every grid point, row-major (E, A)."""
        aa, ee = np.meshgrid(self.azimuth_deg, self.elevation_deg)
        return aa.ravel(), ee.ravel(), np.full(aa.size, self.time_s)


def map_grid(fade: Fade, time_s: float | None = None, *, n_azimuth: int = 64,
             n_elevation: int = 40, margin_deg: float = 15.0) -> MapGrid:
    """The grid around the training rows of ``fade`` (``margin_deg`` beyond them, elevation within
    0-90 deg) at ``time_s`` [s since 1970] (default: the latest training row's)."""
    train = fade.train_sun_deg
    times = fade.train_time_s[np.isfinite(fade.train_time_s)]
    if time_s is None:
        time_s = float(times.max()) if len(times) else math.nan
    az = np.linspace(train[:, 0].min() - margin_deg, train[:, 0].max() + margin_deg, n_azimuth)
    el = np.linspace(max(0.0, train[:, 1].min() - margin_deg),
                     min(90.0, train[:, 1].max() + margin_deg), n_elevation)
    return MapGrid(az, el, float(time_s), float(margin_deg))


def map_figure_data(grid: MapGrid, fade: Fade, mean_mrad: np.ndarray, structure: str) -> dict:
    """What the report's figure draws (:func:`heliocal.pipeline.report.figures.plot_gp_correction`)
    from the grid, the fade and the faded mean (E * A, 2) [mrad] at :meth:`MapGrid.points`."""
    shape = grid.shape
    aa, ee, t = grid.points()
    mean = np.asarray(mean_mrad, np.float64).reshape(-1, 2)
    when = (pd.Timestamp(grid.time_s, unit="s", tz="UTC").strftime("%Y-%m-%d")
            if math.isfinite(grid.time_s) else "no date")
    return {"azimuth_deg": grid.azimuth_deg, "elevation_deg": grid.elevation_deg,
            "mean_h": mean[:, 0].reshape(shape), "mean_v": mean[:, 1].reshape(shape),
            "fade": fade.weights(aa, ee, t).reshape(shape), "train_sun_deg": fade.train_sun_deg,
            "structure": structure, "fade_length_deg": fade.length_deg, "when": when}


def structure_label(gp: Mapping) -> str:
    """The kernel structure of a GP model's configuration (its ``gp`` section) as the map's title
    names it: with a periodic term (:mod:`.periodic`), its axis and period."""
    inputs = gp.get("inputs") or {}
    axis = int(inputs.get("periodic_axis", 0) or 0)
    if not axis:
        return str(gp["structure"])
    return f"{gp['structure']}, periodic in axis {axis}: {float(inputs['period_steps']):,.0f} steps"


def map_section(grid: MapGrid, mean_mrad: np.ndarray) -> dict:
    """The configuration's :data:`MAP_KEY` section of a map (the module's docstring)."""
    mean = np.asarray(mean_mrad, "<f8").reshape(-1, 2)
    return {"n_azimuth": len(grid.azimuth_deg), "n_elevation": len(grid.elevation_deg),
            "margin_deg": grid.margin_deg,
            "time_s": grid.time_s if math.isfinite(grid.time_s) else None,
            "encoding": _ENCODING, "mean_h_mrad": _encode(mean[:, 0]),
            "mean_v_mrad": _encode(mean[:, 1])}


def stored_correction_map(config: Mapping) -> dict | None:
    """The figure's data (:func:`map_figure_data`) from a GP model's configuration, or ``None``
    when it has no stored map (written before maps were stored: compute it from the model).

    Raises
    ------
    ValueError : the section is malformed (the message says how).
    """
    section = config.get(MAP_KEY)
    if section is None:
        return None
    if not isinstance(section, Mapping) or section.get("encoding") != _ENCODING:
        raise ValueError(f"its {MAP_KEY} is not an object of encoding {_ENCODING!r}")
    fade = Fade.from_dict(config["gp"].get("fade") or {})
    time_s = section.get("time_s")
    grid = map_grid(fade, math.nan if time_s is None else float(time_s),
                    n_azimuth=int(section["n_azimuth"]), n_elevation=int(section["n_elevation"]),
                    margin_deg=float(section["margin_deg"]))
    n = grid.shape[0] * grid.shape[1]
    mean = np.stack([_decode(section["mean_h_mrad"], n), _decode(section["mean_v_mrad"], n)], -1)
    return map_figure_data(grid, fade, mean, structure_label(config["gp"]))


def _encode(values: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(values, "<f8").tobytes()).decode("ascii")


def _decode(text, n: int) -> np.ndarray:
    """(n,) float64 from :func:`_encode`'s text."""
    raw = base64.b64decode(str(text), validate=True)
    if len(raw) != 8 * n:
        raise ValueError(f"its {MAP_KEY} holds {len(raw) // 8} values where the grid has {n}")
    return np.frombuffer(raw, "<f8").astype(np.float64)
