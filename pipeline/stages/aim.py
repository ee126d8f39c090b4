"""``aim``: the motor steps that reflect the sun onto an aim point, through each heliostat's
selected model (the hybrid where the sweep chose it, else the coarse model).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd
import torch

from ..artifacts.modelfiles import check_fine_model_inputs, fine_model_inputs, read_model
from ..artifacts.schemas import HELIOSTATS, REGIME_PARAMS, REGIMES
from ..artifacts.store import artifact_present, read_artifact
from ..errors import FitError, InputError, ParameterError, StageInputError, check_choice
from ..models.network import MODES, FeatureEncoder, Layers, state_to_layers
from ..models.pretrained import PretrainedModel
from ..models.training import FineProblem, grouped_components
from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import error_mrad, reflect
from ..physics.parameters import HeliostatSpec, nominal_parameters
from ..models.fade import epoch_seconds, fade_weights
from ..models.gp import GPCorrection
from ..models.gp_heliostat import gp_aim_steps
from ..physics.sun import sun_angles_from_vector
from .aim_choice import aim_models  # the model aim --model auto uses (torch-free; re-exported)
from .fit_coarse import load_selected_parameters
from ..runtime.process_state import restores_process_state, single_threaded

__all__ = [
    "load_model",
    "aim_models",
    "aim_steps",
    "latest_regime",
]

# ------------------------------------------------------------------------------------------------
# pretrained-nn (paper 002)
# ------------------------------------------------------------------------------------------------
def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


# ------------------------------------------------------------------------------------------------
# loading a fitted model and aiming
# ------------------------------------------------------------------------------------------------
def load_model(workdir: str | Path, mode: str, heliostat_id: str) -> tuple[dict, Layers] | None:
    """Config dict and weights of a fitted mode for one heliostat (``None`` if not fitted).

    ``mode`` ``selected`` is the sweep's selected model (``DIR/hybrid/selected/``). The files are
    read through their stage's manifest and checked (:func:`heliocal.pipeline.artifacts.modelfiles.read_model`):
    a changed, corrupt or foreign file gives a one-line error naming it and the command to rerun.
    """
    workdir = Path(workdir)
    if mode == "selected":
        stage, hint = "sweep", f"`heliocal sweep --workdir {workdir}`"
    else:
        stage, hint = "fit-hybrid", f"`heliocal fit-hybrid --workdir {workdir} --mode {mode}`"
    found = read_model(workdir, stage, mode, heliostat_id, hint=hint)
    if found is None:
        return None
    cfg, state = found
    return cfg, state if cfg.get("mode") == "gp" else state_to_layers(state)


def _fine_problem_from_config(cfg: dict, spec: HeliostatSpec, nominal: torch.Tensor) -> FineProblem:
    base = torch.tensor(cfg["base_params"], dtype=torch.float64)
    free = torch.tensor(cfg["free"], dtype=torch.bool)
    return FineProblem(spec, base, free, torch.tensor(cfg["scales"], dtype=torch.float64),
                       FeatureEncoder.from_dict(cfg["encoder"]), None, None)


@restores_process_state
@single_threaded
def latest_regime(workdir: str | Path, heliostat_id: str) -> dict | None:
    """The heliostat's latest regime in regimes.parquet (fit-coarse): number, start, the rows
    that support it and the breaks before it; ``None`` without regimes.parquet or rows.

    ``coarse_model`` names the selected regime-aware coarse model (regime_params.parquet) whose
    latest regime's parameters ``aim`` uses, ``fitted_regime`` and ``fitted_rows`` the regime
    and the training rows those parameters rest on (the latest regime's own when it has enough,
    else the regime before it); all three are ``None`` when the plain fit is selected: its
    geometry is one for all regimes, and ``rows`` tells how much of the recent data agrees."""
    if not artifact_present(workdir, REGIMES):
        return None
    r = read_artifact(workdir, REGIMES, heliostats=[heliostat_id])
    seg = r[(r["heliostat_id"] == heliostat_id) & (r["kind"] == "regime")].sort_values("start")
    if seg.empty:
        return None
    last = seg.iloc[-1]
    latest = seg[seg["regime"] == last["regime"]]
    out = {"regime": int(last["regime"]), "since": str(pd.Timestamp(latest["start"].iloc[0])),
           "rows": int(latest["n_rows"].sum()),
           "breaks": int(r["cause"].isin(["detected", "renovation"]).sum()),
           "episodes": int((r["kind"] == "episode").sum()),
           "coarse_model": None, "fitted_regime": None, "fitted_rows": None}
    if artifact_present(workdir, REGIME_PARAMS):
        p = read_artifact(workdir, REGIME_PARAMS, heliostats=[heliostat_id])
        p = p[(p["heliostat_id"] == heliostat_id) & p["selected"] & p["latest"]]
        if len(p):
            out.update(coarse_model=str(p["model"].iloc[0]),
                       fitted_regime=int(p["fitted_regime"].iloc[0]),
                       fitted_rows=int(p["n_train"].iloc[0]))
    return out


def _env_values(names, env: Mapping[str, float] | None, chosen: str, heliostat_id: str):
    """The values of a model's env inputs from ``--env`` (None without env inputs)."""
    if not names:
        return None
    missing = [e for e in names if e not in (env or {})]
    if missing:
        raise ParameterError(f"the {chosen} model of {heliostat_id} uses env inputs {missing}: "
                             "give them with --env NAME=VALUE")
    return [float(env[e]) for e in names]


def aim_steps(workdir: str | Path, heliostat_id: str, *, aim_point_enu, sun_vector_enu=None,
              time_utc=None, env: Mapping[str, float] | None = None, model: str = "auto",
              max_iterations: int = 50, tolerance_steps: float = 1e-6) -> dict:
    """Motor steps that reflect the sun onto ``aim_point_enu`` with the best fitted model.

    Parameters
    ----------
    aim_point_enu : (3,) aim point [m] ENU.
    sun_vector_enu : (3,) direction toward the sun; default from NREL SPA at ``time_utc``.
    time_utc : time of the aim (needed by models with time inputs, and for the sun by default).
    env : values of the model's env inputs (name without ``env_`` -> value).
    model : ``auto`` (the sweep's selection where ``sweep`` ran, else the fit-hybrid hybrid where
        fitted, else coarse), ``coarse``, ``hybrid``, ``nn-only`` or
        ``pretrained-nn``.

    Returns
    -------
    dict with ``axis_1_steps``, ``axis_2_steps``, ``model``, ``iterations``, ``aim_error_mrad``
    (angle between the forward model's reflected beam at those steps and the direction to the aim
    point), ``sun_azimuth_deg``, ``sun_elevation_deg``.
    """
    from ..physics.sun import spa_sun_position
    from ..physics.sun import sun_vector_enu as _sunvec

    check_choice(model, "model", "aim", ("auto", "coarse") + MODES)
    workdir = Path(workdir)
    check_fine_model_inputs(workdir)
    helio = read_artifact(workdir, HELIOSTATS, heliostats=[heliostat_id])
    if helio.empty:
        raise InputError(f"heliostat {heliostat_id!r} is not in {workdir}/heliostats.parquet")
    hrow = helio.iloc[0]
    selected = load_selected_parameters(workdir, [heliostat_id])
    if heliostat_id not in selected:
        raise StageInputError(f"heliostat {heliostat_id!r} has no coarse fit: run `heliocal "
                              f"fit-coarse --workdir {workdir}` first")
    spec = HeliostatSpec.from_row(hrow)
    if sun_vector_enu is None:
        if time_utc is None:
            raise ParameterError("aim needs the sun: give a time or a sun azimuth and elevation")
        lat, lon = hrow["latitude_deg"], hrow["longitude_deg"]
        if lat is None or not np.isfinite(lat):
            raise InputError(f"heliostat {heliostat_id!r} has no WGS84 location, so the sun cannot "
                             "be computed from the time: give --sun-azimuth and --sun-elevation")
        alt = hrow["altitude_m"] if hrow["altitude_m"] is not None and np.isfinite(hrow["altitude_m"]) else 0.0
        az, el = spa_sun_position([time_utc], float(lat), float(lon), float(alt))
        sun_vector_enu = _sunvec(az[0], el[0])
    sun = _unit(torch.as_tensor(np.asarray(sun_vector_enu, np.float64)).reshape(1, 3))
    if float(sun[0, 2]) <= 0:
        raise InputError("the sun is below the horizon at that time")
    aim = torch.as_tensor(np.asarray(aim_point_enu, np.float64)).reshape(1, 3)
    coarse = selected[heliostat_id]["params"]
    chosen = model
    fitted = None
    rerun = None
    if model == "auto":
        choice = aim_models(workdir, [heliostat_id], strict=True).get(heliostat_id, {})
        if choice.get("model") in ("hybrid", "pretrained-nn", "gp"):
            fitted = load_model(workdir, choice["model_dir"], heliostat_id)
            if choice["source"] == "sweep":
                rerun = f"`heliocal sweep --workdir {workdir}`"
        chosen = choice["model"] if fitted is not None else "coarse"
    elif model != "coarse":
        fitted = load_model(workdir, model, heliostat_id)
        if fitted is None:
            raise StageInputError(f"no {model} model for {heliostat_id}: run `heliocal fit-hybrid "
                                  f"--workdir {workdir} --mode {model}` first")
    if fitted is not None:
        cfg = fitted[0]
        current = fine_model_inputs(workdir)
        if any(cfg.get("inputs", {}).get(k) != v for k, v in current.items()):
            rerun = rerun or f"`heliocal fit-hybrid --workdir {workdir} --mode {chosen}`"
            raise StageInputError(f"the {chosen} model of {heliostat_id} is stale (its inputs "
                                  f"changed): rerun {rerun} first")
    steps = inverse_kinematics(coarse, spec, sun, aim)
    iterations = 0
    if not bool(torch.isfinite(steps).all()):
        raise FitError(f"the aim point is not reachable by {heliostat_id} within its actuator "
                       "limits for this sun position")
    corrected = None
    if chosen == "coarse":
        params = coarse
    elif chosen == "gp":
        params = coarse
        if time_utc is None and "time" in fitted[0]["gp"]["structure"]:
            raise ParameterError(f"the gp model of {heliostat_id} uses the date as input: give "
                                 "--time")
        fit = gp_aim_steps(GPCorrection.from_model(*fitted), coarse, spec, sun, aim,
                           None if time_utc is None else epoch_seconds([time_utc])[0],
                           _env_values(fitted[0]["gp"]["inputs"].get("env", ()), env, chosen,
                                       heliostat_id), max_iterations=max_iterations,
                           tolerance_steps=tolerance_steps)
        if not bool(torch.isfinite(fit.steps).all()):
            raise FitError(f"the aim point is not reachable by {heliostat_id} within its "
                           "actuator limits for this sun position")
        steps, iterations, corrected = fit.steps, fit.iterations, fit.normal
    elif chosen == "pretrained-nn":
        cfg, layers = fitted
        pm = PretrainedModel.from_dict(cfg, layers)
        with torch.no_grad():
            steps = pm.steps(sun, aim, spec=spec)
        if not bool(torch.isfinite(steps).all()):
            raise FitError(f"the aim point is not reachable by {heliostat_id} within its "
                           "actuator limits for this sun position")
        params = coarse
    else:
        cfg, layers = fitted
        problem = _fine_problem_from_config(cfg, spec, nominal_parameters(hrow))
        enc = problem.encoder
        if enc.env:
            env = env or {}
            missing = [e for e in enc.env if e not in env]
            if missing:
                raise ParameterError(f"the {chosen} model of {heliostat_id} uses env inputs "
                                     f"{missing}: give them with --env NAME=VALUE")
        if time_utc is None:
            raise ParameterError(f"the {chosen} model of {heliostat_id} uses the date as input: "
                                 "give --time")
        context = enc.context([time_utc], np.array([[float((env or {})[e]) for e in enc.env]])
                              if enc.env else None)
        az, el = sun_angles_from_vector(sun.numpy())
        fade = fade_weights(cfg, az, el, [time_utc])     # the fine model's fade (models.fade)

        def params_at(s):
            with torch.no_grad():
                return grouped_components(problem, layers, enc.encode(s, context), None,
                                          fade).stacked()[0, 0]

        for iterations in range(1, max_iterations + 1):
            params = params_at(steps)
            new = inverse_kinematics(params, spec, sun, aim)
            if not bool(torch.isfinite(new).all()):
                raise FitError(f"the aim point is not reachable by {heliostat_id} within its "
                               "actuator limits for this sun position")
            delta = float((new - steps).abs().max())
            steps = new
            if delta < tolerance_steps:
                break
        params = params_at(steps)
    with torch.no_grad():
        normal, position = forward_kinematics(params, spec, steps)
        normal = normal if corrected is None else corrected
        beam = reflect(-sun, normal)
        aim_err = float(error_mrad(beam, aim - position)[0])
    az, el = sun_angles_from_vector(sun.numpy())
    return {"heliostat_id": heliostat_id, "model": chosen,
            "time_utc": None if time_utc is None else str(pd.Timestamp(time_utc)),
            "sun_azimuth_deg": float(az[0]), "sun_elevation_deg": float(el[0]),
            "aim_point_enu_m": aim[0].tolist(), "axis_1_steps": float(steps[0, 0]),
            "axis_2_steps": float(steps[0, 1]), "iterations": iterations,
            "aim_error_mrad": aim_err, "regime": latest_regime(workdir, heliostat_id)}
