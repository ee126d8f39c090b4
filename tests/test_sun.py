"""Sun position (pipeline/sun.py): PAINT's azimuth convention, unit vectors, NREL SPA via pvlib."""

from __future__ import annotations

import numpy as np
import pytest

from heliocal.pipeline.physics.sun import (spa_sun_position, sun_angles_from_vector, sun_vector_enu,
                                           wrap_deg)

# Plant reference point of the Jülich tower (tower-measurements.json).
JUELICH = (50.913421122592574, 6.387824755874856, 87.0)
# PAINT's logged sun for BE36 calibration 118671 at 2022-06-12T13:27:37Z (timestamps.json):
# paint/BE36/calibration/118671-calibration-properties.json.
PAINT_AZIMUTH_DEG = -48.91974860208279
PAINT_ELEVATION_DEG = 54.66615202629741


def test_spa_matches_paint_logged_angle():
    az, el = spa_sun_position(["2022-06-12T13:27:37Z"], *JUELICH)
    # pvlib's apparent elevation is 54.66591 deg: 0.00024 deg below PAINT's value
    assert el[0] == pytest.approx(PAINT_ELEVATION_DEG, abs=1e-3)
    # pvlib's azimuth 228.92049 deg (north-clockwise) is -48.92049 deg in PAINT's convention:
    # 0.00075 deg from PAINT's value
    assert az[0] == pytest.approx(PAINT_AZIMUTH_DEG, abs=2e-3)


def test_spa_geometric_elevation_lacks_refraction():
    _, apparent = spa_sun_position(["2022-06-12T13:27:37Z"], *JUELICH)
    _, geometric = spa_sun_position(["2022-06-12T13:27:37Z"], *JUELICH, refraction=False)
    # refraction at 55 deg elevation is about 0.68 arcmin = 0.0118 deg (value printed by pvlib)
    assert apparent[0] - geometric[0] == pytest.approx(0.0118, abs=0.001)


def test_solar_noon_azimuth_is_near_zero():
    # Solar noon at 6.3878 deg E on 2022-06-21 is about 11:36:00 UTC (12:00 - 25.55 min for the
    # longitude + 1.6 min for the equation of time, NOAA solar calculator); the sun is due south
    # (azimuth 0) then. Near noon the azimuth moves ~0.5 deg per minute, so allow 0.5 deg.
    az, el = spa_sun_position(["2022-06-21T11:36:00Z"], *JUELICH)
    assert abs(az[0]) < 0.5
    # noon elevation = 90 - latitude + declination 23.44 deg (+ refraction ~0.01)
    assert el[0] == pytest.approx(90 - 50.9134 + 23.4385, abs=0.05)


def test_sun_vector_convention():
    v = sun_vector_enu(PAINT_AZIMUTH_DEG, PAINT_ELEVATION_DEG)
    # afternoon sun: west (e < 0) and south (n < 0) of the zenith
    assert v[0] < 0 and v[1] < 0 and v[2] == pytest.approx(np.sin(np.radians(PAINT_ELEVATION_DEG)))
    assert np.linalg.norm(v) == pytest.approx(1.0)
    assert sun_vector_enu(90.0, 0.0) == pytest.approx([1.0, 0.0, 0.0], abs=1e-12)  # east
    assert sun_vector_enu(0.0, 0.0) == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)  # south


def test_angles_vector_round_trip():
    rng = np.random.default_rng(1)
    az, el = rng.uniform(-179.9, 179.9, 100), rng.uniform(0.5, 89.5, 100)
    az2, el2 = sun_angles_from_vector(sun_vector_enu(az, el))
    assert az2 == pytest.approx(az, abs=1e-9) and el2 == pytest.approx(el, abs=1e-9)


def test_wrap_deg():
    assert wrap_deg([-180.0, 180.0, 190.0, -190.0, 540.0]).tolist() == [180.0, 180.0, -170.0, 170.0, 180.0]
