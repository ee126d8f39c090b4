"""How ``simulate --mounting field`` draws the heliostats' true geometries: from their type's
distribution, with spatially correlated mounting errors (the ground truth of the field prior,
issue 34).

A heliostat's deviation from its nominal geometry, per deviated parameter (the units of
:data:`~.disturbances.DEVIATION_SIZES`: tilts and zero points [rad], translations and actuator
lengths [m], increments relative to the nominal [1]), is the sum of

* the type's systematic deviation (one draw per kinematic type and parameter: a magnitude
  uniform in :data:`~.disturbances.DEVIATION_SIZES` with a random sign, the size an independent
  heliostat's deviation has), e.g. homing sensors all set a few mrad off;
* for the *mounting* parameters (:data:`MOUNTING_PARAMETERS`: the pedestal's tilt, Stone's
  alpha and beta, and its position, ``joint_1_translation_*``) a Gaussian random field over the
  field's east/north positions with a squared-exponential correlation of length
  :data:`CORRELATION_LENGTH_M` and the standard deviation :data:`SPATIAL_SD`: neighbours share a
  foundation crew, soil and survey;
* an individual deviation, normal with the standard deviation :data:`INDIVIDUAL_SD`.

The draws come from their own generator (``numpy.random.default_rng([seed, 34])``), so a field
simulated with ``independent`` mounting (the default) is byte-identical to earlier versions.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..physics.parameters import PARAMETER_INDEX, STONE_MAPPING
from .disturbances import DEVIATION_SIZES, deviation_kind

__all__ = ["CORRELATION_LENGTH_M", "SPATIAL_SD", "INDIVIDUAL_SD", "MOUNTING_PARAMETERS",
           "mounting_parameters", "FieldMounting"]

#: Correlation length of the mounting errors' random field [m] (about five rows of a field).
CORRELATION_LENGTH_M = 40.0

#: Standard deviation of the spatial part of a mounting parameter (deviation units).
SPATIAL_SD = {"tilt": 1.5e-3, "translation": 0.01}

#: Standard deviation of each heliostat's individual deviation (deviation units).
INDIVIDUAL_SD = {"tilt": 0.5e-3, "initial_angle": 1.0e-3, "translation": 3e-3, "length": 0.3e-3,
                 "increment": 2e-4}

#: The mounting parameters: Stone's alpha and beta (the pedestal's tilt) and the pedestal's
#: position, per kinematic type.
MOUNTING_PARAMETERS = {
    kt: (m["alpha"], m["beta"], "joint_1_translation_e_m", "joint_1_translation_n_m",
         "joint_1_translation_u_m")
    for kt, m in STONE_MAPPING.items()}


def mounting_parameters(kinematic_type: str) -> tuple[str, ...]:
    """The parameters with a spatially correlated part (:data:`MOUNTING_PARAMETERS`)."""
    return MOUNTING_PARAMETERS[kinematic_type]


def _random_field(rng: np.random.Generator, positions: np.ndarray, sd: float) -> np.ndarray:
    """One draw (n,) of a zero-mean Gaussian field with squared-exponential covariance
    ``sd^2 exp(-d^2 / (2 L^2))`` at ``positions`` (n, 2) [m]."""
    d2 = ((positions[:, None, :] - positions[None, :, :]) ** 2).sum(-1)
    cov = sd ** 2 * np.exp(-d2 / (2.0 * CORRELATION_LENGTH_M ** 2))
    w, v = np.linalg.eigh(cov)   # semi-definite: a Cholesky factor may not exist
    return v @ (np.sqrt(np.clip(w, 0.0, None)) * rng.standard_normal(len(positions)))


class FieldMounting:
    """The true geometries of one simulated field's heliostats (module docstring): the spatial
    fields of every type's mounting parameters are drawn when the field is laid out; the
    type's systematic deviation of a parameter when a heliostat first needs it; each
    heliostat's individual deviations with its geometry (:meth:`true`).

    Parameters
    ----------
    rng : the mounting draws' own generator.
    positions : (n, 2) east, north [m] of the field's heliostats.
    kinematic_types : (n,) their types.
    """

    def __init__(self, rng: np.random.Generator, positions, kinematic_types: Sequence[str]):
        self.rng = rng
        positions = np.asarray(positions, np.float64).reshape(-1, 2)
        kinds = np.asarray(list(kinematic_types), dtype=object)
        self.systematic: dict[tuple[str, str], float] = {}
        self.spatial: dict[tuple[str, str], np.ndarray] = {}
        for kt in sorted(set(kinds)):
            members = kinds == kt
            for name in mounting_parameters(kt):
                values = np.zeros(len(positions))
                values[members] = _random_field(rng, positions[members],
                                                SPATIAL_SD[deviation_kind(name)])
                self.spatial[(kt, name)] = values

    def _systematic(self, kt: str, name: str) -> float:
        if (kt, name) not in self.systematic:
            low, high = DEVIATION_SIZES[deviation_kind(name)]
            sign = 1.0 if self.rng.random() < 0.5 else -1.0
            self.systematic[(kt, name)] = float(self.rng.uniform(low, high)) * sign
        return self.systematic[(kt, name)]

    def true(self, k: int, kinematic_type: str, nominal: torch.Tensor,
             names: Sequence[str]) -> torch.Tensor:
        """The true parameters (28,) of heliostat ``k`` (its row of ``positions``) with
        ``nominal`` (28,) and deviated parameters ``names``."""
        true = nominal.clone()
        for name in names:
            kind = deviation_kind(name)
            spatial = self.spatial.get((kinematic_type, name))
            size = (self._systematic(kinematic_type, name)
                    + (0.0 if spatial is None else float(spatial[k]))
                    + float(self.rng.normal(0.0, INDIVIDUAL_SD[kind])))
            i = PARAMETER_INDEX[name]
            true[i] = nominal[i] * (1.0 + size) if kind == "increment" else nominal[i] + size
        return true
