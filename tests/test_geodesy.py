"""WGS84 <-> ENU (pipeline/geodesy.py, PROJ cart + topocentric)."""

from __future__ import annotations

import numpy as np
import pytest

from heliocal.pipeline.physics.geodesy import enu_to_wgs84, wgs84_to_enu

# Reference point used in the issue; the multi_focus_tower centre from tower-measurements.json.
REF = (50.913421630859, 6.387824755874856, 87.0)
MULTI_FOCUS = (50.91339645088695, 6.387574436728054, 138.97975)
# The figure, from a small-distance (flat-earth) approximation.
APPROX_ENU = np.array([-17.6045, -2.8012, 51.9798])


def test_multi_focus_tower_against_small_distance_approximation():
    enu = np.array([float(x) for x in wgs84_to_enu(*MULTI_FOCUS, REF)])
    # The exact transform lies (-0.000397, -0.000018, -0.000075) m from the approximate figure
    # (printed by this code with pyproj 3.x / PROJ 9); the approximation ignores the earth's
    # curvature over 18 m and rounds to 0.1 mm, so we allow 0.5 mm per axis.
    assert enu - APPROX_ENU == pytest.approx([-0.000397, -0.000018, -0.000075], abs=5e-5)
    assert np.abs(enu - APPROX_ENU).max() < 5e-4


def _ecef(lat, lon, h):
    """Textbook WGS84 geodetic -> ECEF (a = 6378137 m, 1/f = 298.257223563)."""
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    lat, lon = np.radians(lat), np.radians(lon)
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.array([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1 - e2) + h) * np.sin(lat)])


def test_matches_independent_ecef_rotation():
    """PROJ agrees with ECEF difference rotated into the local frame (independent formula)."""
    lat0, lon0 = np.radians(REF[0]), np.radians(REF[1])
    d = _ecef(*MULTI_FOCUS) - _ecef(*REF)
    rot = np.array([[-np.sin(lon0), np.cos(lon0), 0],
                    [-np.sin(lat0) * np.cos(lon0), -np.sin(lat0) * np.sin(lon0), np.cos(lat0)],
                    [np.cos(lat0) * np.cos(lon0), np.cos(lat0) * np.sin(lon0), np.sin(lat0)]])
    expected = rot @ d
    got = np.array([float(x) for x in wgs84_to_enu(*MULTI_FOCUS, REF)])
    assert got == pytest.approx(expected, abs=1e-6)


def test_up_is_the_height_difference_less_the_earths_curvature():
    """Up is measured from the reference height along its ellipsoid normal: a point straight above
    the reference is at (0, 0, dh); a point d away horizontally is dh - d^2 / (2 R) up, R the
    radius of curvature of the ellipsoid's normal section toward it (Euler: 1/R = cos^2(a) / M +
    sin^2(a) / N, a its azimuth; M, N the meridian and prime-vertical radii)."""
    above = [float(x) for x in wgs84_to_enu(REF[0], REF[1], REF[2] + 50.0, REF)]
    assert above == pytest.approx([0.0, 0.0, 50.0], abs=1e-9)
    e, n, u = (float(x) for x in wgs84_to_enu(*MULTI_FOCUS, REF))
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    w = np.sqrt(1 - e2 * np.sin(np.radians(REF[0])) ** 2)
    meridian, prime_vertical = a * (1 - e2) / w**3, a / w
    azimuth = np.arctan2(e, n)
    radius = 1 / (np.cos(azimuth) ** 2 / meridian + np.sin(azimuth) ** 2 / prime_vertical)
    drop = (e * e + n * n) / (2 * radius)  # 2.5e-5 m over the tower's 17.8 m
    assert u == pytest.approx(MULTI_FOCUS[2] - REF[2] - drop, abs=1e-8)


def test_reference_point_is_origin():
    assert [float(x) for x in wgs84_to_enu(*REF, REF)] == pytest.approx([0, 0, 0], abs=1e-9)


def test_enu_wgs84_enu_round_trip_within_0_1_mm():
    rng = np.random.default_rng(0)
    # points of a heliostat field: up to 2 km away, -10 .. 250 m high
    e, n = rng.uniform(-2000, 2000, 200), rng.uniform(-2000, 2000, 200)
    u = rng.uniform(-10, 250, 200)
    lat, lon, alt = enu_to_wgs84(e, n, u, REF)
    e2, n2, u2 = wgs84_to_enu(lat, lon, alt, REF)
    err = np.sqrt((e2 - e) ** 2 + (n2 - n) ** 2 + (u2 - u) ** 2)
    assert err.max() < 1e-4


def test_vectorised_shapes():
    e, n, u = wgs84_to_enu([MULTI_FOCUS[0]] * 3, [MULTI_FOCUS[1]] * 3, [MULTI_FOCUS[2]] * 3, REF)
    assert e.shape == n.shape == u.shape == (3,)
