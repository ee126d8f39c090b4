"""Sun position: angles in heliocal's convention, unit vectors, and NREL SPA through pvlib.

Convention (PAINT/ARTIST, used everywhere in heliocal):

* ``sun_azimuth_deg``: 0 = south, positive toward east (so east = +90, west = -90).
  pvlib's azimuth (0 = north, clockwise toward east) converts as ``180 - azimuth_pvlib``,
  wrapped to (-180, 180] (checked against PAINT's logged angles: pvlib 228.92 deg, a
  south-western afternoon sun, is PAINT's -48.92 deg).
* ``sun_elevation_deg``: angle above the horizon [deg].
* Sun vector (unit, from the heliostat toward the sun) in ENU:
  e = cos(el) sin(az), n = -cos(el) cos(az), u = sin(el).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = [
    "sun_vector_enu",
    "sun_angles_from_vector",
    "spa_sun_position",
    "wrap_deg",
]


def wrap_deg(angle_deg):
    """Wrap angles to (-180, 180] [deg]."""
    a = np.mod(np.asarray(angle_deg, float) + 180.0, 360.0) - 180.0
    return np.where(a == -180.0, 180.0, a)


def sun_vector_enu(azimuth_deg, elevation_deg):
    """Unit vector toward the sun, ENU, from azimuth (0 = south, + east) and elevation [deg].

    Returns an array of shape (..., 3).
    """
    az = np.radians(np.asarray(azimuth_deg, float))
    el = np.radians(np.asarray(elevation_deg, float))
    return np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)], axis=-1)


def sun_angles_from_vector(vector_enu):
    """Inverse of :func:`sun_vector_enu`: (azimuth_deg, elevation_deg) of ENU unit vectors."""
    v = np.asarray(vector_enu, float)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    el = np.degrees(np.arcsin(np.clip(v[..., 2], -1.0, 1.0)))
    az = np.degrees(np.arctan2(v[..., 0], -v[..., 1]))
    return az, el


def spa_sun_position(timestamps_utc, latitude_deg, longitude_deg, altitude_m=0.0,
                     refraction: bool = True):
    """Sun azimuth and elevation in heliocal's convention from NREL's SPA (pvlib).

    Parameters
    ----------
    timestamps_utc : UTC timestamps (anything :func:`pandas.to_datetime` reads with utc=True).
    latitude_deg, longitude_deg : site [deg]: one site (floats), or one per timestamp (arrays;
        SPA's site terms are elementwise, so many sites' times take one call, each row as it
        would alone).
    altitude_m : site height [m] (a float or one per timestamp).
    refraction : return the apparent (refraction-corrected) elevation, as camera-target
        logs record it; ``False`` gives the geometric elevation.

    Returns
    -------
    (azimuth_deg, elevation_deg) : numpy arrays, azimuth 0 = south, positive toward east.
    """
    from pvlib import solarposition

    times = pd.DatetimeIndex(pd.to_datetime(pd.Series(timestamps_utc), utc=True))
    pos = solarposition.get_solarposition(times, latitude_deg, longitude_deg,
                                          altitude=altitude_m, method="nrel_numpy")
    el = pos["apparent_elevation" if refraction else "elevation"].to_numpy(float)
    az = wrap_deg(180.0 - pos["azimuth"].to_numpy(float))
    return np.asarray(az, float), el
