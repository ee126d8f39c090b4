"""Checking a measurement plan against a simulator's ground truth: the rows a simulated static
heliostat would give at chosen times, and a fitted model's year-round aim error against the true
geometry (``benchmarks/plan_sim.py``, ``tests/test_plan.py``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd
import torch

from ..errors import ParameterError
from ..physics.jacobian import residual_and_jacobian
from ..physics.kinematics import inverse_kinematics
from ..physics.sun import spa_sun_position, sun_vector_enu
from .disturbances import DISTURBANCE_COLUMNS
from .simulator import (SimulatedField, SimulatedHeliostat, integer_steps, noiseless_spots,
                        target_plane_axes)

__all__ = ["simulated_rows", "year_error_mrad"]


def simulated_rows(field_: SimulatedField, h: SimulatedHeliostat, times: Sequence,
                   target_names: Sequence[str], rng: np.random.Generator) -> pd.DataFrame:
    """Rows of static heliostat ``h`` measured at UTC ``times`` on ``target_names``, made the way
    :func:`~heliocal.pipeline.models.simulator.simulate_field` makes them (steps from the true
    geometry's inverse kinematics, rounded; the spot with the field's beam noise along the
    target plane's axes), with the simulator's columns; rows out of reach are left out.
    ``measurement_id`` is left for the caller to set."""
    if h.dynamic or h.changes:
        raise ParameterError(f"simulated_rows takes static heliostats; {h.heliostat_id} has "
                             "disturbances or changes")
    times = pd.DatetimeIndex(pd.to_datetime(pd.Series(times), utc=True))
    az, el = spa_sun_position(times, *field_.reference)
    sun = torch.as_tensor(sun_vector_enu(az, el))
    centre = torch.as_tensor(np.stack([field_.targets[t]["center_enu"] for t in target_names]))
    normal = torch.as_tensor(np.stack([field_.targets[t]["normal_enu"] for t in target_names]))
    params = h.true.expand(len(times), -1)
    steps = integer_steps(params, h.spec, sun, centre)
    ok = torch.isfinite(steps).all(-1)
    spot, position = noiseless_spots(params[ok], h.spec, steps[ok], sun[ok], centre[ok], normal[ok])
    distance = torch.linalg.vector_norm(spot - position, dim=-1).numpy()
    horizontal, vertical = target_plane_axes(normal[ok].numpy())
    z = rng.standard_normal((len(distance), 2))
    sigma = distance * field_.settings["noise_mrad"] / 1000.0
    noisy = spot.numpy() + (sigma * z[:, 0])[:, None] * horizontal + (sigma * z[:, 1])[:, None] * vertical
    keep = ok.numpy()
    frame = pd.DataFrame({
        "heliostat_id": h.heliostat_id, "measurement_id": "", "timestamp": times[keep],
        "sun_azimuth_deg": az[keep], "sun_elevation_deg": el[keep],
        **{f"sun_{a}": sun[ok][:, i].numpy() for i, a in enumerate("enu")},
        "axis_1_steps": steps[ok][:, 0].numpy(), "axis_2_steps": steps[ok][:, 1].numpy(),
        "target_name": np.asarray(target_names)[keep],
        **{f"target_{a}_m": centre[ok][:, i].numpy() for i, a in enumerate("enu")},
        **{f"target_normal_{a}": normal[ok][:, i].numpy() for i, a in enumerate("enu")},
        **{f"focal_spot_{a}_m": noisy[:, i] for i, a in enumerate("enu")},
        **{f"true_spot_{a}_m": spot[:, i].numpy() for i, a in enumerate("enu")},
        "distance_m": distance, "temperature_c": 15.0})
    for column in DISTURBANCE_COLUMNS:
        frame[column] = 0.0
    return frame


def year_error_mrad(params: torch.Tensor, h: SimulatedHeliostat, sun: np.ndarray,
                    aim_point_enu: np.ndarray) -> tuple[float, int]:
    """(mean error [mrad], aims) of aims with fitted ``params`` (28,) at unit sun vectors ``sun``
    (G, 3) onto ``aim_point_enu`` (3,): the steps the fitted model chooses, and at them the angle
    between the true chain's mirror normal and the one that would hit the aim point (the norm of
    the residual ``1000 (n_true - n_required)``, the coarse fit's metric). Aims either model
    cannot reach are left out and not counted."""
    s = torch.as_tensor(np.asarray(sun, float))
    aim = torch.as_tensor(np.broadcast_to(np.asarray(aim_point_enu, float), s.shape).copy())
    steps = inverse_kinematics(params.to(torch.float64), h.spec, s, aim)
    with torch.no_grad():
        r, _ = residual_and_jacobian(h.true, h.spec, steps, s, aim)
    err = torch.linalg.vector_norm(r, dim=-1).numpy()
    ok = np.isfinite(err)
    return float(err[ok].mean()) if ok.any() else float("nan"), int(ok.sum())
