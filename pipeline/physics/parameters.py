"""The kinematic parameters: the 28 names (unit in each name) and their order, the kinematic types
and their joint axes, the parameter presets (which parameters a fit frees), the heliostat
specification (:class:`HeliostatSpec`, the fixed data of each heliostat) and the nominal
parameter vector read from heliostats.parquet. The chain that uses them is
:mod:`heliocal.pipeline.physics.kinematics`; presets and degeneracies are explained in
``docs/kinematics.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import ParameterError, check_choice
from .actuators import ACTUATOR_TYPES
from ..vocabulary import CoarsePreset

__all__ = [
    "PARAMETER_NAMES",
    "PARAMETER_INDEX",
    "PARAMETER_UNITS",
    "KINEMATIC_TYPES",
    "REFERENCE_NORMALS",
    "IDEAL_UNUSED_PARAMETERS",
    "PRESET_NAMES",
    "PRESETS",
    "KINEMATIC_PRESETS",
    "STONE_MAPPING",
    "HeliostatSpec",
    "nominal_parameters",
    "preset_mask",
    "preset_parameters",
    "JOINT_AXES",
]


_BODIES = ("joint_1", "joint_2", "concentrator")


_ENU = ("e", "n", "u")


_ACTUATOR_FIELDS = ("increment", "initial_stroke_length_m", "offset_m", "pivot_radius_m",
                    "initial_angle_rad")


PARAMETER_NAMES: tuple[str, ...] = tuple(
    [f"{b}_{kind}_{d}_{unit}" for b in _BODIES for kind, unit in (("translation", "m"), ("tilt", "rad"))
     for d in _ENU]
    + [f"axis_{i}_{f}" for i in (1, 2) for f in _ACTUATOR_FIELDS]
)
"""The 28 kinematic parameters in their fixed order (units in the names).

``axis_i_increment`` is [steps/m] of stroke for linear actuators and the gear ratio [steps/rad]
for ideal ones; ``axis_i_initial_angle_rad`` is the joint angle at 0 steps (for ideal actuators:
the angle offset). ``axis_i_initial_stroke_length_m``, ``axis_i_offset_m`` and
``axis_i_pivot_radius_m`` are unused (and never freed) for ideal actuators.
"""


PARAMETER_INDEX: dict[str, int] = {name: i for i, name in enumerate(PARAMETER_NAMES)}
"""Position of each parameter name in the vector."""


PARAMETER_UNITS: dict[str, str] = {
    name: ("m" if name.endswith("_m") else "rad" if name.endswith("_rad")
           else "steps/m (linear) | steps/rad (ideal)")
    for name in PARAMETER_NAMES
}
"""Unit of each parameter."""


KINEMATIC_TYPES = ("juelich", "az-el", "target-aligned")
"""Kinematic types understood by :func:`forward_kinematics`."""


# Joint axes per type: (axis index in the parent frame 0=e 1=n 2=u, sense +1/-1).
JOINT_AXES = {
    "juelich": ((0, 1.0), (2, 1.0)),
    "az-el": ((2, 1.0), (0, -1.0)),
    "target-aligned": ((2, 1.0), (0, 1.0)),
}


REFERENCE_NORMALS: dict[str, tuple[float, float, float]] = {
    "juelich": (0.0, -1.0, 0.0),
    "az-el": (0.0, -1.0, 0.0),
    "target-aligned": (0.0, 0.0, 1.0),
}
"""Mirror normal at zero joint angles, in the local frame of each kinematic type."""


IDEAL_UNUSED_PARAMETERS: tuple[str, ...] = tuple(
    f"axis_{i}_{f}" for i in (1, 2) for f in ("initial_stroke_length_m", "offset_m", "pivot_radius_m")
)
"""Parameters without meaning for ideal actuators (always fixed, nominal value 0)."""


PRESET_NAMES = tuple(p.value for p in CoarsePreset if p is not CoarsePreset.auto)
"""Names of the parameter presets (see ``docs/kinematics.md``)."""


# Stone's (paper 002, eq. 2) tilt angles alpha, beta (tilt of axis 1), gamma (non-orthogonality of
# the two axes) and delta (mirror tilt) as our parameter names, per kinematic type. They are the
# four tilts that are neither about a joint's own rotation axis nor about the reference normal.
_STONE_TILTS = {
    "juelich": ("joint_1_tilt_n_rad", "joint_1_tilt_u_rad", "joint_2_tilt_n_rad",
                "concentrator_tilt_e_rad"),
    "az-el": ("joint_1_tilt_e_rad", "joint_1_tilt_n_rad", "joint_2_tilt_n_rad",
              "concentrator_tilt_u_rad"),
    "target-aligned": ("joint_1_tilt_e_rad", "joint_1_tilt_n_rad", "joint_2_tilt_n_rad",
                       "concentrator_tilt_n_rad"),
}


STONE_MAPPING: dict[str, dict[str, str]] = {
    kt: {
        "alpha": tilts[0], "beta": tilts[1], "gamma": tilts[2], "delta": tilts[3],
        "theta_k": "axis_1_initial_angle_rad", "tau_k": "axis_2_initial_angle_rad",
        "GR1": "axis_1_increment", "GR2": "axis_2_increment",
    }
    for kt, tilts in _STONE_TILTS.items()
}
"""Paper 002 (eq. 2) symbols -> our parameter names, per kinematic type."""


def _presets_for(kinematic_type: str) -> dict[str, tuple[str, ...]]:
    stone_tilts = _STONE_TILTS[kinematic_type]
    offsets = ("axis_1_initial_angle_rad", "axis_2_initial_angle_rad")
    increments = ("axis_1_increment", "axis_2_increment")
    static_6 = stone_tilts + offsets
    translations_14 = tuple(f"{b}_translation_{d}_m" for b in ("joint_1", "concentrator") for d in _ENU)
    static_14 = static_6 + increments + translations_14
    geometry = tuple(f"axis_{i}_{f}" for i in (1, 2)
                     for f in ("initial_stroke_length_m", "offset_m", "pivot_radius_m"))
    static_20 = static_14 + geometry
    rest = tuple(n for n in PARAMETER_NAMES if n not in static_20)
    static_28 = static_20 + rest
    return {
        "static-6": static_6,
        "static-14": static_14,
        "static-20": static_20,
        "static-28": static_28,
        "stone-8": static_6 + increments,
    }


KINEMATIC_PRESETS: dict[str, dict[str, tuple[str, ...]]] = {
    kt: _presets_for(kt) for kt in KINEMATIC_TYPES
}
"""Preset name -> freed parameter names, per kinematic type (ideal-actuator filtering is done
by :func:`preset_mask`)."""


PRESETS: dict[str, tuple[str, ...]] = KINEMATIC_PRESETS["juelich"]
"""Presets of the Juelich (PAINT/ARTIST) kinematic type."""


def preset_parameters(name: str, actuator_type: str, kinematic_type: str = "juelich") -> tuple[str, ...]:
    """Names of the parameters a preset frees, in :data:`PARAMETER_NAMES` order.

    Parameters
    ----------
    name : one of :data:`PRESET_NAMES`.
    actuator_type : ``"linear"`` or ``"ideal"``; for ideal actuators the three unused actuator
        slots per axis (:data:`IDEAL_UNUSED_PARAMETERS`) are never freed.
    kinematic_type : one of :data:`KINEMATIC_TYPES` (the tilts that are observable depend on it).
    """
    check_choice(name, "name", "preset_parameters", PRESET_NAMES)
    check_choice(actuator_type, "actuator_type", "preset_parameters", ACTUATOR_TYPES)
    check_choice(kinematic_type, "kinematic_type", "preset_parameters", KINEMATIC_TYPES)
    chosen = set(KINEMATIC_PRESETS[kinematic_type][name])
    if actuator_type == "ideal":
        chosen -= set(IDEAL_UNUSED_PARAMETERS)
    return tuple(n for n in PARAMETER_NAMES if n in chosen)


def preset_mask(name: str, actuator_type: str, kinematic_type: str = "juelich") -> torch.Tensor:
    """Boolean mask over the 28 parameters: True = freed (fitted) by preset ``name``.

    Parameters are those of :func:`preset_parameters`.

    Returns
    -------
    torch.Tensor
        Bool tensor of shape (28,).
    """
    chosen = set(preset_parameters(name, actuator_type, kinematic_type))
    return torch.tensor([n in chosen for n in PARAMETER_NAMES], dtype=torch.bool)


def _f64(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=torch.float64)


def _get(row, key, default=float("nan")):
    try:
        value = row[key]
    except (KeyError, IndexError):
        return default
    if value is None:
        return default
    return value


def _as_bool(value) -> bool:
    if value is None:
        return False
    if isinstance(value, float) and math.isnan(value):
        return False
    return bool(value)


@dataclass(frozen=True)
class HeliostatSpec:
    """Fixed (not fitted) description of one heliostat or of a batch of heliostats of one type.

    Tensor fields carry a batch shape ``S`` (empty for one heliostat) that must broadcast with
    the batch shape of the parameter vectors passed to :func:`forward_kinematics`.

    Attributes
    ----------
    kinematic_type : one of :data:`KINEMATIC_TYPES` (one per spec; group heliostats by type).
    actuator_type : ``"linear"`` or ``"ideal"``.
    clockwise : bool tensor (S, 2): linear actuators' ``clockwise_axis_movement`` per axis
        (ignored for ideal actuators, whose sense is the sign of the gear ratio).
    min_steps, max_steps : float64 (S, 2): actuator limits [steps] (NaN = unbounded).
    position_enu : float64 (S, 3): heliostat position (the chain's origin) [m] ENU relative to
        the plant reference point.
    initial_orientation : float64 (S, 3): PAINT's ``initial_orientation``. It only names the
        frame the surface model is given in; like ARTIST (which rotates the surface from it onto
        its standard south orientation before the chain) the kinematics does not use it.
    primary_axis : float64 (S, 3): unit primary-axis direction in ENU (target-aligned only, NaN
        otherwise).
    heliostat_id : the id(s), for bookkeeping only.
    """

    kinematic_type: str
    actuator_type: str
    clockwise: torch.Tensor
    min_steps: torch.Tensor
    max_steps: torch.Tensor
    position_enu: torch.Tensor
    initial_orientation: torch.Tensor = field(
        default_factory=lambda: torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    primary_axis: torch.Tensor = field(
        default_factory=lambda: torch.full((3,), float("nan"), dtype=torch.float64))
    heliostat_id: object = None

    def __post_init__(self):
        check_choice(self.kinematic_type, "kinematic_type", "HeliostatSpec", KINEMATIC_TYPES)
        check_choice(self.actuator_type, "actuator_type", "HeliostatSpec", ACTUATOR_TYPES)
        object.__setattr__(self, "clockwise", torch.as_tensor(self.clockwise).to(torch.bool))
        for name in ("min_steps", "max_steps", "position_enu", "initial_orientation", "primary_axis"):
            object.__setattr__(self, name, torch.as_tensor(getattr(self, name), dtype=torch.float64))
        if self.kinematic_type == "target-aligned":
            p = self.primary_axis
            norm = torch.linalg.vector_norm(p, dim=-1, keepdim=True)
            if not bool(torch.all(torch.isfinite(p))) or bool(torch.any(norm < 1e-12)):
                raise ParameterError(
                    "The 'primary_axis' parameter of HeliostatSpec must be a finite non-zero ENU "
                    f"vector for kinematic_type 'target-aligned'. Got {p.tolist()!r} instead.")
            object.__setattr__(self, "primary_axis", p / norm)

    @property
    def batch_shape(self) -> torch.Size:
        """Batch shape ``S`` of the tensor fields."""
        return self.position_enu.shape[:-1]

    @classmethod
    def from_row(cls, row) -> "HeliostatSpec":
        """Build the spec of one heliostat from one row of ``heliostats.parquet``.

        Parameters
        ----------
        row : pandas Series or mapping with the columns of ``heliostats.parquet`` (missing
            optional columns are treated as NaN / False).
        """
        kinematic_type = str(_get(row, "kinematic_type", "juelich"))
        actuator_type = str(_get(row, "actuator_type", "linear"))
        return cls(
            kinematic_type=kinematic_type,
            actuator_type=actuator_type,
            clockwise=torch.tensor([_as_bool(_get(row, f"axis_{i}_clockwise", False)) for i in (1, 2)]),
            min_steps=_f64([_get(row, f"axis_{i}_min_steps") for i in (1, 2)]),
            max_steps=_f64([_get(row, f"axis_{i}_max_steps") for i in (1, 2)]),
            position_enu=_f64([_get(row, f"heliostat_{d}_m", 0.0) for d in _ENU]),
            initial_orientation=_f64([_get(row, f"initial_orientation_{d}", v)
                                      for d, v in zip(_ENU, (0.0, -1.0, 0.0))]),
            primary_axis=_f64([_get(row, f"primary_axis_{d}") for d in _ENU]),
            heliostat_id=_get(row, "heliostat_id", None),
        )

    @classmethod
    def from_frame(cls, frame) -> "HeliostatSpec":
        """Build one batched spec (batch shape (H,)) from several rows of ``heliostats.parquet``.

        All rows must share ``kinematic_type`` and ``actuator_type`` (group by them first).
        """
        specs = [cls.from_row(row) for _, row in frame.iterrows()]
        if not specs:
            raise ParameterError("The 'frame' parameter of HeliostatSpec.from_frame must have at "
                                 "least one row. Got 0 rows instead.")
        types = {(s.kinematic_type, s.actuator_type) for s in specs}
        if len(types) != 1:
            raise ParameterError(
                "The 'frame' parameter of HeliostatSpec.from_frame must hold one kinematic_type "
                f"and actuator_type; group the rows by them first. Got {sorted(types)!r} instead.")
        return cls(
            kinematic_type=specs[0].kinematic_type,
            actuator_type=specs[0].actuator_type,
            clockwise=torch.stack([s.clockwise for s in specs]),
            min_steps=torch.stack([s.min_steps for s in specs]),
            max_steps=torch.stack([s.max_steps for s in specs]),
            position_enu=torch.stack([s.position_enu for s in specs]),
            initial_orientation=torch.stack([s.initial_orientation for s in specs]),
            primary_axis=torch.stack([s.primary_axis for s in specs]),
            heliostat_id=tuple(s.heliostat_id for s in specs),
        )


def _finite_or(value, default: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


def _nominal_row(row) -> list[float]:
    actuator_type = str(_get(row, "actuator_type", "linear"))
    values = {name: 0.0 for name in PARAMETER_NAMES}
    for body in _BODIES:
        for d in _ENU:
            name = f"{body}_translation_{d}_m"
            values[name] = _finite_or(_get(row, name), 0.0)
            tilt = f"{body}_tilt_{d}_rad"
            values[tilt] = _finite_or(_get(row, tilt), 0.0)
    for i in (1, 2):
        if actuator_type == "ideal":
            gear = _finite_or(_get(row, f"axis_{i}_gear_ratio_steps_per_rad"),
                              _finite_or(_get(row, f"axis_{i}_increment"), float("nan")))
            offset = _finite_or(_get(row, f"axis_{i}_angle_offset_rad"),
                                _finite_or(_get(row, f"axis_{i}_initial_angle_rad"), 0.0))
            values[f"axis_{i}_increment"] = gear
            values[f"axis_{i}_initial_angle_rad"] = offset
        else:
            for f in _ACTUATOR_FIELDS:
                values[f"axis_{i}_{f}"] = _finite_or(_get(row, f"axis_{i}_{f}"), float("nan"))
    return [values[n] for n in PARAMETER_NAMES]


def nominal_parameters(row) -> torch.Tensor:
    """Nominal 28-parameter vector from ``heliostats.parquet`` row(s).

    Translations and actuator values are copied from the columns of the same name; tilts are 0
    (not in ``heliostats.parquet``). For ideal actuators ``axis_i_increment`` is the gear ratio
    ``axis_i_gear_ratio_steps_per_rad`` [steps/rad] and ``axis_i_initial_angle_rad`` the
    ``axis_i_angle_offset_rad`` [rad]; the three unused actuator slots are 0.

    Parameters
    ----------
    row : pandas Series / mapping (one heliostat) or DataFrame (several).

    Returns
    -------
    torch.Tensor
        float64, shape (28,) for one row or (H, 28) for a DataFrame, in :data:`PARAMETER_NAMES`
        order.
    """
    if hasattr(row, "iterrows"):
        return _f64([_nominal_row(r) for _, r in row.iterrows()]).reshape(-1, len(PARAMETER_NAMES))
    return _f64(_nominal_row(row))
