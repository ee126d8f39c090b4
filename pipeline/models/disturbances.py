"""What the simulator does to a heliostat beyond its nominal geometry: static deviations of the
kinematic parameters (sizes per parameter kind) and the time-dependent disturbances (drift,
thermal, re-mounting, re-homing ...) the fine model is for; the ground truth of ``simulate``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..physics.parameters import PARAMETER_INDEX, STONE_MAPPING
from ..vocabulary import DisturbanceKind

__all__ = [
    "DISTURBANCE_COLUMNS",
    "deviate_parameters",
    "deviation_kind",
    "disturbance_column",
    "disturbance_setup",
    "disturbance_values",
    "params_per_measurement",
    "temperature_c",
    "DISTURBANCE_KINDS",
    "DEVIATION_SIZES",
    "Disturbances",
]


#: The disturbances a dynamic heliostat gets (all of them by default).
DISTURBANCE_KINDS = DisturbanceKind.values()


#: Size of a true-minus-nominal deviation per parameter kind: magnitude drawn uniformly from
#: (low, high) with a random sign. Tilts and initial angles [rad], translations and actuator
#: lengths (initial stroke, offset, pivot radius) [m], increments relative to the nominal [1].
DEVIATION_SIZES = {
    "tilt": (1.0e-3, 5.0e-3),
    "initial_angle": (3.0e-3, 7.0e-3),
    "translation": (0.01, 0.02),
    "length": (0.5e-3, 1.5e-3),
    "increment": (2.0e-4, 1.0e-3),
}


#: Columns of the per-measurement disturbances (SimulatedField.measurements and
#: ground_truth_disturbances.csv): the change of the disturbed parameter, in its unit; 0 where a
#: heliostat has no such disturbance.
DISTURBANCE_COLUMNS = ("seasonal_tilt_rad", "actuator_drift_m", "actuator_drift_rad",
                        "gear_error_rad", "temperature_tilt_rad")


def disturbance_column(kind: str, setup: dict) -> str:
    if kind == "actuator_drift":
        return "actuator_drift_m" if setup["parameter"].endswith("_m") else "actuator_drift_rad"
    return f"{kind}_rad"


_SECONDS_PER_YEAR = 365.25 * 86400.0


@dataclass(frozen=True)
class Disturbances:
    """Sizes of the dynamic disturbances (each heliostat draws its own phases and signs).

    Attributes
    ----------
    seasonal_tilt_rad : amplitude [rad] of a sinusoid in the day of the year added to the tilt of
        axis 1 (Stone's alpha: ``joint_1_tilt_n_rad`` for juelich, ``joint_1_tilt_e_rad`` for az-el),
        e.g. a foundation that heaves with the seasons.
    drift_stroke_m_per_year : linear actuators: wear drift of actuator 1's initial stroke length
        [m per year since the start of the period].
    drift_angle_rad_per_year : ideal drives: drift of actuator 1's angle offset [rad per year].
    gear_error_rad : amplitude [rad] of a gear error of actuator 2 (added to its initial angle),
        periodic in its motor steps.
    gear_period_steps : period of that error [steps].
    temperature_tilt_rad_per_k : tilt of the mirror (Stone's delta: ``concentrator_tilt_e_rad``
        for juelich, ``concentrator_tilt_u_rad`` for az-el) per kelvin of the logged temperature
        above ``temperature_reference_c`` [rad/K].
    temperature_reference_c : temperature without thermal tilt [°C].
    """

    seasonal_tilt_rad: float = 1.0e-3
    drift_stroke_m_per_year: float = 0.5e-3
    drift_angle_rad_per_year: float = 1.5e-3
    gear_error_rad: float = 0.5e-3
    gear_period_steps: float = 4000.0
    temperature_tilt_rad_per_k: float = 5.0e-5
    temperature_reference_c: float = 15.0


def temperature_c(rng: np.random.Generator, times: pd.DatetimeIndex, longitude_deg: float) -> np.ndarray:
    """Air temperature [°C] at 0.1 K resolution: seasonal + diurnal cycle + weather noise."""
    doy = times.day_of_year.to_numpy(float)
    solar_hour = (times.hour.to_numpy(float) + times.minute.to_numpy(float) / 60.0
                  + longitude_deg / 15.0)
    t = (10.0 - 9.0 * np.cos(2 * np.pi * (doy - 15.0) / 365.25)
         + 4.0 * np.sin(2 * np.pi * (solar_hour - 9.0) / 24.0) + rng.normal(0.0, 1.5, len(times)))
    return np.round(t, 1)


def deviation_kind(name: str) -> str:
    """The kind of a parameter in :data:`DEVIATION_SIZES`."""
    if name.endswith("_increment"):
        return "increment"
    if name.endswith("_initial_angle_rad"):
        return "initial_angle"
    if "_tilt_" in name:
        return "tilt"
    if "_translation_" in name:
        return "translation"
    return "length"


def deviate_parameters(rng, nominal: torch.Tensor, names: Sequence[str]) -> torch.Tensor:
    true = nominal.clone()
    for name in names:
        kind = deviation_kind(name)
        low, high = DEVIATION_SIZES[kind]
        size = float(rng.uniform(low, high)) * (1.0 if rng.random() < 0.5 else -1.0)
        i = PARAMETER_INDEX[name]
        true[i] = nominal[i] * (1.0 + size) if kind == "increment" else nominal[i] + size
    return true


def disturbance_setup(rng, kinematic_type: str, actuator_type: str, kinds, sizes: Disturbances):
    """Per-heliostat disturbance descriptions (parameter, unit, amplitude, phase)."""
    stone = STONE_MAPPING[kinematic_type]
    out = {}
    for kind in kinds:
        sign = 1.0 if rng.random() < 0.5 else -1.0
        if kind == "seasonal_tilt":
            out[kind] = {"parameter": stone["alpha"], "unit": "rad",
                         "amplitude": sign * sizes.seasonal_tilt_rad,
                         "peak_day_of_year": float(np.round(rng.uniform(0.0, 365.25), 1)),
                         "law": "amplitude * cos(2 pi (day_of_year - peak_day_of_year) / 365.25)"}
        elif kind == "actuator_drift":
            if actuator_type == "linear":
                out[kind] = {"parameter": "axis_1_initial_stroke_length_m", "unit": "m/year",
                             "rate": sign * sizes.drift_stroke_m_per_year}
            else:
                out[kind] = {"parameter": "axis_1_initial_angle_rad", "unit": "rad/year",
                             "rate": sign * sizes.drift_angle_rad_per_year}
            out[kind]["law"] = "rate * (time - start) / 365.25 days"
        elif kind == "gear_error":
            out[kind] = {"parameter": "axis_2_initial_angle_rad", "unit": "rad",
                         "amplitude": sizes.gear_error_rad, "period_steps": sizes.gear_period_steps,
                         "phase_rad": float(np.round(rng.uniform(0.0, 2 * np.pi), 4)),
                         "law": "amplitude * sin(2 pi axis_2_steps / period_steps + phase_rad)"}
        elif kind == "temperature_tilt":
            out[kind] = {"parameter": stone["delta"], "unit": "rad/K",
                         "coefficient": sign * sizes.temperature_tilt_rad_per_k,
                         "reference_temperature_c": sizes.temperature_reference_c,
                         "law": "coefficient * (temperature - reference_temperature_c)"}
    return out


def disturbance_values(setup: dict, times: pd.DatetimeIndex, t0: pd.Timestamp,
                        temperature: np.ndarray, axis_2_steps: np.ndarray) -> dict[str, np.ndarray]:
    """Per-measurement value of each disturbance, in its parameter's unit."""
    out = {}
    for kind, d in setup.items():
        if kind == "seasonal_tilt":
            doy = times.day_of_year.to_numpy(float)
            out[kind] = d["amplitude"] * np.cos(2 * np.pi * (doy - d["peak_day_of_year"]) / 365.25)
        elif kind == "actuator_drift":
            years = (times - t0).total_seconds().to_numpy(float) / _SECONDS_PER_YEAR
            out[kind] = d["rate"] * years
        elif kind == "gear_error":
            out[kind] = d["amplitude"] * np.sin(2 * np.pi * axis_2_steps / d["period_steps"]
                                                + d["phase_rad"])
        elif kind == "temperature_tilt":
            out[kind] = d["coefficient"] * (temperature - d["reference_temperature_c"])
    return out


def params_per_measurement(true: torch.Tensor, setup: dict, values: dict, n: int) -> torch.Tensor:
    """Parameters (n, 28): ``true`` (28,) or (n, 28) plus each disturbance's values."""
    params = true.clone() if true.dim() == 2 else true.unsqueeze(0).repeat(n, 1)
    for kind, v in values.items():
        i = PARAMETER_INDEX[setup[kind]["parameter"]]
        params[:, i] = params[:, i] + torch.as_tensor(v, dtype=torch.float64)
    return params
