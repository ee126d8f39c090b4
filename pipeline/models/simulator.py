"""A seeded simulator of heliostat calibration data with known ground truth.

:func:`simulate_field` builds a synthetic field: heliostats on a radial-staggered layout north
of a tower, calibration targets on the tower, realistic calibration times (daylight, several per
day on days spread over the period, sun elevation above 10 deg from NREL SPA) and, per
measurement, the motor steps and the focal spot that a *true* heliostat geometry produces.
:func:`write_field` writes it in the formats :mod:`heliocal.pipeline.stages.ingest` reads, plus the
ground truth.

The model of one measurement
----------------------------
1. Geometry. Every heliostat has a *nominal* geometry (the values written to its properties file)
   and a *true* geometry = nominal + known deviations on a chosen set of parameters (by default
   those freed by preset ``static-20``; sizes in :data:`DEVIATION_SIZES`). Static heliostats have
   only these. Dynamic heliostats additionally get per-measurement disturbances that no static
   rigid body can capture (:class:`Disturbances`): a seasonal tilt (sinusoid in the day of the
   year), a wear drift of actuator 1 (linear in time), a gear error of actuator 2 (periodic in its
   motor steps) and a temperature effect (a tilt proportional to the logged temperature).
2. Steps. The sun vector comes from SPA (pvlib) at the plant reference point for the UTC time
   (the angles are logged, so ingest finds no SPA mismatch); the aim point is the centre of a
   tower target. The motor steps are the true (disturbed) model's inverse kinematics
   (:func:`heliocal.pipeline.physics.kinematics.inverse_kinematics`), rounded to integer steps.
3. Focal spot. The true model's mirror normal and mirror centre at those rounded steps reflect
   the sun; the beam's intersection with the target plane is the noiseless spot. Noise: the spot
   moves by ``d * noise_mrad / 1000 * z`` along each of the target plane's two axes (horizontal
   ``unit(normal x up)`` and vertical, as in :func:`heliocal.pipeline.physics.metrics.spot_offset_m`),
   with ``d`` the mirror-to-spot distance [m] and ``z`` independent standard normal numbers. So
   ``noise_mrad`` is the standard deviation per axis of the *beam* direction's noise; the mirror
   normal's noise is about half of it.
4. Noise floor. ``noise_floor_mrad`` is the mean ``error_mrad`` (heliocal's metric,
   :func:`heliocal.pipeline.physics.metrics.error_mrad` of the measured normal) of the true model itself
   on the noisy data: no calibration can be expected to get below it on average. For Gaussian
   noise it is about ``noise_mrad / 2 * sqrt(pi / 2)`` (a Rayleigh mean).

Randomness only comes from ``numpy.random.default_rng(seed)``; the same seed gives the same
field and byte-identical files.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..errors import InputError, ParameterError, check_choice, check_float, check_int
from ..io.paint import paint_kinematics_columns
from ..physics.geodesy import enu_to_wgs84, wgs84_to_enu
from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import angle_between_mrad, error_mrad, measured_normal, reflect
from ..physics.parameters import (PARAMETER_NAMES, PRESET_NAMES, HeliostatSpec, nominal_parameters,
                                  preset_parameters)
from ..physics.sun import spa_sun_position, sun_vector_enu
from .changes import Changes, change_offsets, draw_changes
from .disturbances import (DISTURBANCE_COLUMNS, DISTURBANCE_KINDS, Disturbances, deviate_parameters,
                           disturbance_column, disturbance_setup, disturbance_values,
                           params_per_measurement, temperature_c)
from ..vocabulary import SimulatedMounting, SimulatedType
from .mounting import FieldMounting

__all__ = [
    "SIMULATED_TYPES",
    "JUELICH_REFERENCE",
    "SimulatedHeliostat",
    "SimulatedField",
    "simulate_field",
    "integer_steps",
    "noiseless_spots",
    "target_plane_axes",
]

_FUNC = "simulate_field"


#: Kinematic types the simulator can generate: ``juelich`` (PAINT layout, linear actuators) and
#: ``az-el`` (ideal drives, written as an ENU log with a TOML properties file: PAINT cannot hold it).
SIMULATED_TYPES = SimulatedType.values()


#: The plant reference point of the solar tower Jülich (``sample_data/juelich/tower-measurements.json``,
#: ``power_plant_properties.coordinates``): latitude [deg], longitude [deg], ellipsoidal height [m].
JUELICH_REFERENCE = (50.913421122592574, 6.387824755874856, 87.0)


# Tower targets (ENU [m] of the centre, half width, half height), after the Jülich tower's
# calibration targets (their centres in ENU relative to the Jülich reference point, rounded).
_TARGETS = {
    "tower_target_lower": ((0.0, -3.2, 35.9), 3.85, 3.6),
    "tower_target_upper": ((0.0, -3.2, 43.1), 3.85, 3.6),
    "multi_focus_target": ((-17.5, -2.8, 52.0), 2.4, 3.2),
}


#: Relative frequency of the targets in the calibration schedule.
_TARGET_WEIGHTS = (0.45, 0.45, 0.10)


# Nominal Jülich heliostat in PAINT's convention (after BE36 of sample_data/juelich): per axis
# increment [steps/m], initial stroke length, offset, pivot radius [m], initial angle [rad]
# (axis 1 WITHOUT ARTIST's -pi/2 shift, as PAINT stores it), clockwise flag, max steps.
_JUELICH_AXES = (
    {"increment": 154166.6667, "initial_stroke_length": 0.0757, "offset": 0.3353,
     "pivot_radius": 0.3381, "initial_angle": 0.0137, "clockwise_axis_movement": 0,
     "max_increment": 69000},
    {"increment": 154166.6667, "initial_stroke_length": 0.0784, "offset": 0.3408,
     "pivot_radius": 0.3191, "initial_angle": 0.9371, "clockwise_axis_movement": 1,
     "max_increment": 75450},
)


_JUELICH_CONCENTRATOR_N_M = 0.175


# Nominal az-el heliostat with ideal drives: gear ratio [steps/rad], angle at 0 steps [rad],
# max steps. Azimuth covers [-3, 3] rad, elevation [-0.1, 1.7] rad.
_AZEL_AXES = ({"gear": 10000.0, "offset": -3.0, "max": 60000.0},
              {"gear": 20000.0, "offset": -0.1, "max": 36000.0})


_AZEL_CONCENTRATOR_N_M = -0.1


_MIN_ELEVATION_DEG = 10.0


_SLOT_MINUTES = 10


@dataclass
class SimulatedHeliostat:
    """One simulated heliostat.

    ``row`` is its ``heliostats.parquet`` row as ingest will read it (positions after the WGS84
    round trip, axis-1 initial angle in ARTIST's convention); ``nominal`` and ``true`` are
    28-parameter vectors in :data:`~heliocal.pipeline.physics.parameters.PARAMETER_NAMES` order;
    ``params`` (N, 28) is the true geometry of each of its measurements (``true`` plus the
    disturbances; equal to ``true`` for a static heliostat), in the order of its rows of
    :attr:`SimulatedField.measurements`.
    """

    heliostat_id: str
    kinematic_type: str
    actuator_type: str
    dynamic: bool
    row: dict
    spec: HeliostatSpec
    nominal: torch.Tensor
    true: torch.Tensor
    deviated: tuple[str, ...]
    disturbances: dict
    params: torch.Tensor | None = None
    paint_properties: dict | None = None
    changes: list = field(default_factory=list)
    noise_floor_mrad: float = float("nan")
    error_true_static_mrad: float = float("nan")
    error_nominal_mrad: float = float("nan")


@dataclass
class SimulatedField:
    """A simulated field: heliostats, measurements (ENU, with the noiseless spots) and settings.

    ``measurements`` has one row per measurement with heliocal's column names (ENU metres, sun
    angles in heliocal's convention) plus ``temperature_c``, ``true_spot_e_m/n_m/u_m`` (the
    noiseless spot) and ``distance_m`` (mirror centre to spot); rows are in time order.
    """

    reference: tuple[float, float, float]
    targets: dict
    heliostats: dict[str, SimulatedHeliostat]
    measurements: pd.DataFrame
    settings: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------
# options
# ------------------------------------------------------------------------------------------------
def _check_options(n_heliostats, seed, measurements, kinematic_types, dynamic_fraction,
                   disturbances, noise_mrad, deviations, start, end):
    n_heliostats = check_int(n_heliostats, "n_heliostats", _FUNC, 1, 500)
    seed = check_int(seed, "seed", _FUNC, 0)
    try:
        lo, hi = (int(v) for v in measurements)
        ok = 3 <= lo <= hi <= 5000 and all(float(v) == int(v) for v in measurements)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ParameterError(f"The 'measurements' parameter of {_FUNC} must be (MIN, MAX) integers "
                             f"with 3 <= MIN <= MAX <= 5000. Got {measurements!r} instead.")
    if isinstance(kinematic_types, str) or not kinematic_types:
        raise ParameterError(f"The 'kinematic_types' parameter of {_FUNC} must be a non-empty "
                             f"sequence of {SIMULATED_TYPES!r}. Got {kinematic_types!r} instead.")
    for kt in kinematic_types:
        check_choice(kt, "kinematic_types", _FUNC, SIMULATED_TYPES)
    dynamic_fraction = check_float(dynamic_fraction, "dynamic_fraction", _FUNC, 0.0, 1.0)
    if isinstance(disturbances, str):
        disturbances = (disturbances,)
    for d in disturbances:
        check_choice(d, "disturbances", _FUNC, DISTURBANCE_KINDS)
    noise_mrad = check_float(noise_mrad, "noise_mrad", _FUNC, 0.0, 100.0)
    if isinstance(deviations, str):
        check_choice(deviations, "deviations", _FUNC, ("none",) + PRESET_NAMES)
    else:
        for name in deviations:
            check_choice(name, "deviations", _FUNC, PARAMETER_NAMES)
    try:
        t0, t1 = pd.Timestamp(start, tz="UTC"), pd.Timestamp(end, tz="UTC")
    except (ValueError, TypeError) as exc:
        raise ParameterError(f"The 'start' and 'end' parameters of {_FUNC} must be dates like "
                             f"2023-01-01. Got {start!r}, {end!r} instead.") from exc
    if not t1 > t0 + pd.Timedelta(days=1):
        raise ParameterError(f"The 'end' parameter of {_FUNC} must be at least one day after "
                             f"'start'. Got start {start!r}, end {end!r} instead.")
    return (n_heliostats, seed, (lo, hi), tuple(kinematic_types), dynamic_fraction,
            tuple(disturbances), noise_mrad, deviations, t0, t1)


# ------------------------------------------------------------------------------------------------
# layout, targets, times
# ------------------------------------------------------------------------------------------------
def _layout(rng: np.random.Generator, n: int) -> list[tuple[str, np.ndarray]]:
    """Heliostat ids and ENU positions on a radial-staggered field north of the tower."""
    candidates = []
    for k in range(20):  # rows at radius 30 m, 38 m, ... within +-55 deg of north
        radius = 30.0 + 8.0 * k
        count = int(2 * math.radians(55.0) * radius / 5.5)
        shift = 0.5 if k % 2 else 0.0
        for j in range(count):
            az = math.radians(-55.0) + (j + shift) * 2 * math.radians(55.0) / count
            candidates.append((f"S{chr(ord('A') + k)}{j + 1:02d}",
                               np.array([radius * math.sin(az), radius * math.cos(az), 0.0])))
    pick = np.sort(rng.choice(len(candidates), size=n, replace=False))
    out = []
    for i in pick:
        hid, pos = candidates[int(i)]
        pos = pos.copy()
        pos[2] = 1.7 + 0.004 * pos[1] + rng.uniform(-0.05, 0.05)  # pedestal on a gentle slope
        out.append((hid, pos))
    return out


def _roundtrip_enu(enu, reference) -> tuple[np.ndarray, tuple[float, float, float]]:
    """(ENU as ingest will read it back, WGS84 written) for an ENU point."""
    lat, lon, alt = enu_to_wgs84(enu[0], enu[1], enu[2], reference)
    wgs = (float(lat), float(lon), float(alt))
    e, n, u = wgs84_to_enu(*wgs, reference)
    return np.array([float(e), float(n), float(u)]), wgs


def _targets(reference) -> dict:
    """Tower targets: name -> {centre ENU (after the WGS84 round trip), normal, WGS84 data}."""
    out = {}
    for name, (centre, half_w, half_h) in _TARGETS.items():
        c_enu, c_wgs = _roundtrip_enu(np.array(centre), reference)
        corners = {}
        for label, de, du in (("upper_left", half_w, half_h), ("upper_right", -half_w, half_h),
                              ("lower_left", half_w, -half_h), ("lower_right", -half_w, -half_h)):
            corners[label] = list(_roundtrip_enu(np.array(centre) + [de, 0.0, du], reference)[1])
        out[name] = {"center_enu": c_enu, "normal_enu": np.array([0.0, 1.0, 0.0]),
                     "center_wgs84": list(c_wgs), "corners_wgs84": corners}
    return out


def _daylight_slots(reference, t0: pd.Timestamp, t1: pd.Timestamp) -> pd.DatetimeIndex:
    """Start times of every 10-minute slot in [t0, t1) whose start and end have the sun > 10 deg."""
    grid = pd.date_range(t0, t1, freq=f"{_SLOT_MINUTES}min", inclusive="left")
    _, el = spa_sun_position(grid, *reference)
    ok = el > _MIN_ELEVATION_DEG
    ok = ok & np.append(ok[1:], False)
    return grid[ok]


def _schedule(rng: np.random.Generator, slots: pd.DatetimeIndex, count: int) -> pd.DatetimeIndex:
    """``count`` calibration times: days spread over the period, 2 to 8 per day, in daylight."""
    days = slots.normalize()
    unique_days = days.unique()
    order = rng.permutation(len(unique_days))
    chosen: list[pd.Timestamp] = []
    for d in order:
        if len(chosen) >= count:
            break
        day_slots = slots[days == unique_days[d]]
        k = min(int(rng.integers(2, 9)), len(day_slots), count - len(chosen))
        picks = np.sort(rng.choice(len(day_slots), size=k, replace=False))
        offsets = rng.integers(0, _SLOT_MINUTES * 60, size=k)
        chosen += [day_slots[int(p)] + pd.Timedelta(seconds=int(s)) for p, s in zip(picks, offsets)]
    return pd.DatetimeIndex(sorted(chosen))


# ------------------------------------------------------------------------------------------------
# geometry
# ------------------------------------------------------------------------------------------------
def _juelich_heliostat(rng, hid: str, position_enu, reference):
    """PAINT properties dict and the heliostats.parquet row ingest will make of it."""
    pos_enu, pos_wgs = _roundtrip_enu(position_enu, reference)
    actuators = []
    for ax in _JUELICH_AXES:
        a = dict(ax)
        # per-heliostat spread of the nominal geometry, like PAINT's files
        a["initial_stroke_length"] = round(a["initial_stroke_length"] + rng.uniform(-2e-3, 2e-3), 9)
        a["offset"] = round(a["offset"] + rng.uniform(-3e-3, 3e-3), 6)
        a["pivot_radius"] = round(a["pivot_radius"] + rng.uniform(-3e-3, 3e-3), 6)
        a["initial_angle"] = round(a["initial_angle"] + rng.uniform(-5e-3, 5e-3), 9)
        actuators.append({
            "type_axis": "linear", "min_increment": 0, "max_increment": int(a["max_increment"]),
            "increment": a["increment"], "offset_shift": 0,
            "initial_stroke_length": a["initial_stroke_length"], "offset": a["offset"],
            "pivot_radius": a["pivot_radius"], "radius_shift": 0,
            "clockwise_axis_movement": int(a["clockwise_axis_movement"]),
            "initial_angle": a["initial_angle"], "movement_speed": 0})
    kin = {"actuators": actuators}
    for a in "enu":
        kin[f"joint_translation_{a}_1"] = 0.0
    for a in "enu":
        kin[f"joint_translation_{a}_2"] = 0.0
    for a, v in zip("enu", (0.0, _JUELICH_CONCENTRATOR_N_M, 0.0)):
        kin[f"concentrator_translation_{a}"] = v
    paint = {"heliostat_position": list(pos_wgs), "height": 2.56, "width": 3.22,
             "initial_orientation": [0.0, -1.0, 0.0], "kinematics_properties": kin}
    row = {"heliostat_id": hid, "kinematic_type": "juelich", "actuator_type": "linear",
           "properties_source": "simulate",
           "heliostat_e_m": pos_enu[0], "heliostat_n_m": pos_enu[1], "heliostat_u_m": pos_enu[2],
           "latitude_deg": pos_wgs[0], "longitude_deg": pos_wgs[1], "altitude_m": pos_wgs[2],
           "initial_orientation_e": 0.0, "initial_orientation_n": -1.0, "initial_orientation_u": 0.0,
           "primary_axis_e": np.nan, "primary_axis_n": np.nan, "primary_axis_u": np.nan}
    row.update(paint_kinematics_columns(kin))  # exactly what ingest makes of the written file
    return paint, row


def _azel_heliostat(hid: str, position_enu) -> dict:
    """heliostats.parquet row of an az-el heliostat with ideal drives (written as TOML)."""
    row = {"heliostat_id": hid, "kinematic_type": "az-el", "actuator_type": "ideal",
           "properties_source": "simulate",
           "heliostat_e_m": float(position_enu[0]), "heliostat_n_m": float(position_enu[1]),
           "heliostat_u_m": float(position_enu[2]),
           "latitude_deg": np.nan, "longitude_deg": np.nan, "altitude_m": np.nan,
           "initial_orientation_e": 0.0, "initial_orientation_n": -1.0, "initial_orientation_u": 0.0,
           "primary_axis_e": np.nan, "primary_axis_n": np.nan, "primary_axis_u": np.nan}
    for j in ("joint_1", "joint_2", "concentrator"):
        for a in "enu":
            row[f"{j}_translation_{a}_m"] = 0.0
    row["concentrator_translation_n_m"] = _AZEL_CONCENTRATOR_N_M
    for i, ax in enumerate(_AZEL_AXES, start=1):
        row.update({
            f"axis_{i}_increment": np.nan, f"axis_{i}_initial_stroke_length_m": np.nan,
            f"axis_{i}_offset_m": np.nan, f"axis_{i}_pivot_radius_m": np.nan,
            f"axis_{i}_initial_angle_rad": np.nan, f"axis_{i}_clockwise": False,
            f"axis_{i}_min_steps": 0.0, f"axis_{i}_max_steps": ax["max"],
            f"axis_{i}_gear_ratio_steps_per_rad": ax["gear"], f"axis_{i}_angle_offset_rad": ax["offset"]})
    return row


def integer_steps(params, spec, sun, aim) -> torch.Tensor:
    """Integer steps (N, 2) from per-measurement parameters (N, 28); NaN rows are unreachable."""
    steps = inverse_kinematics(params, spec, sun.unsqueeze(-2), aim.unsqueeze(-2)).squeeze(-2)
    return torch.round(steps)


def noiseless_spots(params, spec, steps, sun, centre, normal):
    """Noiseless focal spots (N, 3), mirror centres (N, 3) for integer steps (N, 2)."""
    n_mirror, position = forward_kinematics(params, spec, steps.unsqueeze(-2))
    n_mirror, position = n_mirror.squeeze(-2), position.squeeze(-2)
    beam = reflect(-sun, n_mirror)
    distance = ((centre - position) * normal).sum(-1) / (beam * normal).sum(-1)
    return position + distance.unsqueeze(-1) * beam, position


def target_plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit horizontal and vertical axes (N, 3) of target planes with normals (N, 3)."""
    up = np.array([0.0, 0.0, 1.0])
    horizontal = np.cross(normal, up)
    horizontal /= np.linalg.norm(horizontal, axis=-1, keepdims=True)
    return horizontal, np.cross(horizontal, normal)


def _mean_error(params, spec, steps, sun, spots) -> float:
    with torch.no_grad():
        n_pred, position = forward_kinematics(params, spec, steps.unsqueeze(-2))
        meas = measured_normal(sun, position.squeeze(-2), torch.as_tensor(spots))
        return float(error_mrad(n_pred.squeeze(-2), meas).mean())


# ------------------------------------------------------------------------------------------------
# the simulator
# ------------------------------------------------------------------------------------------------
def simulate_field(n_heliostats: int = 4, *, seed: int = 0, measurements: tuple[int, int] = (150, 150),
                   kinematic_types: Sequence[str] = ("juelich",), dynamic_fraction: float = 0.5,
                   disturbances: Sequence[str] = DISTURBANCE_KINDS,
                   disturbance_sizes: Disturbances | None = None, noise_mrad: float = 0.2,
                   deviations: str | Sequence[str] = "static-20", start: str = "2023-01-01",
                   end: str = "2024-01-01",
                   reference: tuple[float, float, float] = JUELICH_REFERENCE,
                   changes: Changes | None = None, mounting: str = "independent") -> SimulatedField:
    """Simulate a calibrated field with known ground truth (see the module docstring).

    Parameters
    ----------
    n_heliostats : number of heliostats [1, 500].
    seed : seed of every random draw (same seed, same field).
    measurements : (MIN, MAX) measurements per heliostat, drawn uniformly per heliostat.
    kinematic_types : types assigned round-robin (``("juelich", "az-el")`` alternates them).
    dynamic_fraction : share of dynamic heliostats in [0, 1] (rounded; the last ones are dynamic).
    disturbances : the disturbances of dynamic heliostats, a subset of :data:`DISTURBANCE_KINDS`.
    disturbance_sizes : their sizes (default :class:`Disturbances`).
    noise_mrad : standard deviation per target-plane axis of the beam direction's noise [mrad]
        (spot noise = mirror-to-spot distance times this angle); 0 gives exact spots.
    deviations : the parameters whose true value differs from the nominal one: a preset name
        (the parameters it frees for each heliostat's type), ``"none"``, or explicit names.
    start, end : calibration period [start, end) (UTC dates).
    reference : plant reference point (lat [deg], lon [deg], ellipsoidal height [m]).
    changes : regime steps, episodes and drift (:class:`~heliocal.pipeline.models.changes.Changes`;
        default none); drawn from their own generator, so without them the field is the same.
    mounting : ``independent`` (each heliostat's deviations drawn on their own) or ``field``
        (from its type's distribution with spatially correlated mounting errors,
        :mod:`.mounting`; their own generator: the times and noise are those of the same field
        with independent deviations).

    Returns
    -------
    SimulatedField
    """
    (n_heliostats, seed, (m_lo, m_hi), kinematic_types, dynamic_fraction, disturbances, noise_mrad,
     deviations, t0, t1) = _check_options(n_heliostats, seed, measurements, kinematic_types,
                                          dynamic_fraction, disturbances, noise_mrad, deviations,
                                          start, end)
    sizes = disturbance_sizes or Disturbances()
    reference = tuple(float(x) for x in reference)
    rng = np.random.default_rng(seed)
    change_rng = np.random.default_rng([seed, 17])
    check_choice(mounting, "mounting", _FUNC, SimulatedMounting.values())
    targets = _targets(reference)
    target_names = list(targets)
    slots = _daylight_slots(reference, t0, t1)
    if len(slots) == 0:  # pragma: no cover - a polar night
        raise ParameterError(f"The 'start' and 'end' parameters of {_FUNC} must span daylight with "
                             f"the sun above {_MIN_ELEVATION_DEG:g} deg. Got {start!r}, {end!r} instead.")
    n_dynamic = int(round(dynamic_fraction * n_heliostats))
    heliostats: dict[str, SimulatedHeliostat] = {}
    frames = []
    layout = _layout(rng, n_heliostats)
    field_mounting = (FieldMounting(np.random.default_rng([seed, 34]),
                                    np.array([p[:2] for _, p in layout]),
                                    [kinematic_types[k % len(kinematic_types)]
                                     for k in range(len(layout))])
                      if mounting == "field" else None)
    for k, (hid, position) in enumerate(layout):
        kt = kinematic_types[k % len(kinematic_types)]
        dynamic = k >= n_heliostats - n_dynamic
        paint = None
        if kt == "juelich":
            paint, row = _juelich_heliostat(rng, hid, position, reference)
        else:
            row = _azel_heliostat(hid, position)
        spec = HeliostatSpec.from_row(row)
        nominal = nominal_parameters(row)
        if isinstance(deviations, str):
            names = () if deviations == "none" else preset_parameters(deviations, spec.actuator_type, kt)
        else:
            names = tuple(n for n in PARAMETER_NAMES if n in set(deviations))
        true = deviate_parameters(rng, nominal, names)   # drawn either way: the same field
        if field_mounting is not None:
            true = field_mounting.true(k, kt, nominal, names)
        setup = disturbance_setup(rng, kt, spec.actuator_type, disturbances, sizes) if dynamic else {}
        count = int(rng.integers(m_lo, m_hi + 1))
        h = SimulatedHeliostat(hid, kt, spec.actuator_type, dynamic, row, spec, nominal, true, names,
                               setup, paint_properties=paint)
        if changes is not None and changes.any:
            h.changes = draw_changes(change_rng, changes, kt, t0, t1)
        frames.append(_simulate_measurements(rng, h, count, slots, t0, targets, target_names,
                                             reference, noise_mrad))
        heliostats[hid] = h
    meas = pd.concat(frames, ignore_index=True)
    meas = meas.sort_values(["timestamp", "heliostat_id"], kind="mergesort").reset_index(drop=True)
    meas.insert(1, "measurement_id", [str(100001 + i) for i in range(len(meas))])
    for hid, h in heliostats.items():  # per-measurement params in the heliostat's row order
        order = meas.index[meas["heliostat_id"] == hid].to_numpy()
        h.params = h.params[torch.as_tensor(np.array(meas.loc[order, "_row"], dtype=np.int64))]
    meas = meas.drop(columns=["_row"])
    settings = {"n_heliostats": n_heliostats, "seed": seed, "measurements": [m_lo, m_hi],
                "kinematic_types": list(kinematic_types), "dynamic_fraction": dynamic_fraction,
                "disturbances": list(disturbances), "disturbance_sizes": asdict(sizes),
                "noise_mrad": noise_mrad,
                "deviations": deviations if isinstance(deviations, str) else list(deviations),
                "start": str(t0.date()), "end": str(t1.date()), "reference": list(reference)}
    if mounting != "independent":   # only then: an independent field's settings stay as they were
        settings["mounting"] = mounting
    if changes is not None and changes.any:
        settings["changes"] = asdict(changes)
    return SimulatedField(reference, targets, heliostats, meas, settings)


def _change_effects(h: SimulatedHeliostat, params, steps, times) -> None:
    """Per event: rows it affects and the mean angle [mrad] it turns the normal on them."""
    for event in h.changes:
        without = params - change_offsets([event], times)
        active = (without != params).any(-1)
        event["n_rows"] = int(active.sum())
        if not bool(active.any()):
            event["effect_mrad"] = 0.0
            continue
        with torch.no_grad():
            n_with, _ = forward_kinematics(params[active], h.spec, steps[active].unsqueeze(-2))
            n_without, _ = forward_kinematics(without[active], h.spec, steps[active].unsqueeze(-2))
        event["effect_mrad"] = float(angle_between_mrad(n_with, n_without).mean())


def _simulate_measurements(rng, h: SimulatedHeliostat, count: int, slots, t0, targets, target_names,
                           reference, noise_mrad: float) -> pd.DataFrame:
    """Times, steps and spots of one heliostat; also sets h.params and its error summaries."""
    spec = h.spec
    rows = []
    have = 0
    for _ in range(6):  # unreachable rows (NaN steps) are replaced by new times
        need = count - have
        if need <= 0:
            break
        times = _schedule(rng, slots, need + max(2, need // 10))
        az, el = spa_sun_position(times, *reference)
        keep = el > _MIN_ELEVATION_DEG
        times, az, el = times[keep], az[keep], el[keep]
        which = rng.choice(len(target_names), size=len(times), p=_TARGET_WEIGHTS)
        temperature = temperature_c(rng, times, reference[1])
        sun = torch.as_tensor(sun_vector_enu(az, el))
        centre = torch.as_tensor(np.stack([targets[target_names[w]]["center_enu"] for w in which]))
        normal = torch.as_tensor(np.stack([targets[target_names[w]]["normal_enu"] for w in which]))
        n = len(times)
        base = {k: v for k, v in disturbance_values(h.disturbances, times, t0, temperature,
                                                    np.zeros(n)).items() if k != "gear_error"}
        true = h.true + change_offsets(h.changes, times) if h.changes else h.true
        params = params_per_measurement(true, h.disturbances, base, n)
        steps = integer_steps(params, spec, sun, centre)
        values = base
        if "gear_error" in h.disturbances:  # the gear error depends on the steps: fixed point
            for _ in range(3):
                values = disturbance_values(h.disturbances, times, t0, temperature,
                                             np.nan_to_num(steps[:, 1].numpy()))
                params = params_per_measurement(true, h.disturbances, values, n)
                steps = integer_steps(params, spec, sun, centre)
            values = disturbance_values(h.disturbances, times, t0, temperature,
                                         np.nan_to_num(steps[:, 1].numpy()))
            params = params_per_measurement(true, h.disturbances, values, n)
        ok = torch.isfinite(steps).all(-1).numpy()
        ok &= np.cumsum(ok) <= need
        sel = torch.as_tensor(ok)
        spot, position = noiseless_spots(params[sel], spec, steps[sel], sun[sel], centre[sel], normal[sel])
        rows.append({"times": times[ok], "az": az[ok], "el": el[ok], "sun": sun[sel],
                     "target": [target_names[w] for w in which[ok]], "centre": centre[sel],
                     "normal": normal[sel], "temperature": temperature[ok], "steps": steps[sel],
                     "params": params[sel], "spot": spot, "position": position,
                     "values": {k: v[ok] for k, v in values.items()}})
        have += int(ok.sum())
    if have < count:  # pragma: no cover - the layout keeps every heliostat reachable
        raise InputError(f"heliostat {h.heliostat_id}: only {have} of {count} calibration times "
                         "are reachable; try another seed")
    cat = lambda key: torch.cat([r[key] for r in rows])  # noqa: E731
    times = rows[0]["times"].append([r["times"] for r in rows[1:]])
    sun, steps, params, spot, position = cat("sun"), cat("steps"), cat("params"), cat("spot"), cat("position")
    centre, normal = cat("centre"), cat("normal")
    distance = torch.linalg.vector_norm(spot - position, dim=-1).numpy()
    horizontal, vertical = target_plane_axes(normal.numpy())
    z = rng.standard_normal((len(distance), 2))
    sigma = distance * noise_mrad / 1000.0
    noisy = (spot.numpy() + (sigma * z[:, 0])[:, None] * horizontal
             + (sigma * z[:, 1])[:, None] * vertical)
    h.params = params
    h.noise_floor_mrad = _mean_error(params, spec, steps, sun, noisy)
    static = h.true.unsqueeze(0).expand_as(params)
    h.error_true_static_mrad = _mean_error(static, spec, steps, sun, noisy)
    h.error_nominal_mrad = _mean_error(h.nominal.unsqueeze(0).expand_as(params), spec, steps, sun, noisy)
    _change_effects(h, params, steps, times)
    frame = pd.DataFrame({
        "heliostat_id": h.heliostat_id,
        "timestamp": times,
        "sun_azimuth_deg": np.concatenate([r["az"] for r in rows]),
        "sun_elevation_deg": np.concatenate([r["el"] for r in rows]),
        "sun_e": sun[:, 0].numpy(), "sun_n": sun[:, 1].numpy(), "sun_u": sun[:, 2].numpy(),
        "axis_1_steps": steps[:, 0].numpy(), "axis_2_steps": steps[:, 1].numpy(),
        "target_name": [t for r in rows for t in r["target"]],
        "target_e_m": centre[:, 0].numpy(), "target_n_m": centre[:, 1].numpy(),
        "target_u_m": centre[:, 2].numpy(),
        "target_normal_e": normal[:, 0].numpy(), "target_normal_n": normal[:, 1].numpy(),
        "target_normal_u": normal[:, 2].numpy(),
        "focal_spot_e_m": noisy[:, 0], "focal_spot_n_m": noisy[:, 1], "focal_spot_u_m": noisy[:, 2],
        "true_spot_e_m": spot[:, 0].numpy(), "true_spot_n_m": spot[:, 1].numpy(),
        "true_spot_u_m": spot[:, 2].numpy(), "distance_m": distance,
        "temperature_c": np.concatenate([r["temperature"] for r in rows]),
    })
    for column in DISTURBANCE_COLUMNS:
        frame[column] = 0.0
    for kind, d in h.disturbances.items():
        frame[disturbance_column(kind, d)] = np.concatenate([r["values"][kind] for r in rows])
    frame["_row"] = np.arange(len(frame))
    return frame
