"""WGS84 geodetic coordinates to local east-north-up (ENU) metres and back.

The transform is exact: geodetic (lat, lon, ellipsoidal height) to Earth-centred Earth-fixed
(ECEF) Cartesian coordinates, then the topocentric rotation to ENU at the plant reference point,
both through PROJ (``pyproj``; pipeline ``+proj=cart +ellps=WGS84`` then ``+proj=topocentric``).
Heights are WGS84 ellipsoidal heights [m] as given by PAINT.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from pyproj import Transformer

__all__ = ["wgs84_to_enu", "enu_to_wgs84"]


@lru_cache(maxsize=64)
def _transformer(ref_lat_deg: float, ref_lon_deg: float, ref_alt_m: float) -> Transformer:
    pipeline = (
        "+proj=pipeline "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={ref_lat_deg!r} +lon_0={ref_lon_deg!r} "
        f"+h_0={ref_alt_m!r}"
    )
    return Transformer.from_pipeline(pipeline)


def wgs84_to_enu(lat_deg, lon_deg, alt_m, reference):
    """Convert WGS84 coordinates to ENU metres relative to ``reference``.

    Parameters
    ----------
    lat_deg, lon_deg : latitude and longitude [deg] (scalars or arrays).
    alt_m : ellipsoidal height [m].
    reference : (lat [deg], lon [deg], alt [m]) of the plant reference point.

    Returns
    -------
    (e_m, n_m, u_m) : numpy arrays [m].
    """
    t = _transformer(*(float(x) for x in reference))
    lon = np.asarray(lon_deg, dtype=float)
    lat = np.asarray(lat_deg, dtype=float)
    alt = np.asarray(alt_m, dtype=float)
    e, n, u = t.transform(lon, lat, alt)
    return np.asarray(e, float), np.asarray(n, float), np.asarray(u, float)


def enu_to_wgs84(e_m, n_m, u_m, reference):
    """Inverse of :func:`wgs84_to_enu`: ENU metres to (lat [deg], lon [deg], alt [m])."""
    t = _transformer(*(float(x) for x in reference))
    lon, lat, alt = t.transform(np.asarray(e_m, float), np.asarray(n_m, float),
                                np.asarray(u_m, float), direction="INVERSE")
    return np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float)
