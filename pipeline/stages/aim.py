"""``aim``: the motor steps that reflect the sun onto an aim point, through each heliostat's
selected model (the hybrid where the sweep chose it, else the coarse model).

:func:`aim_steps` opens the work directory once (:class:`CommittedWorkdir`: every manifest loaded
and checked once, every file read once and checked against its manifest) and reads everything it
needs through it, in small steps: the heliostat and its coarse fit, the sun, the model, the steps
(a fixed point for the hybrid, reported when it does not converge), and the warnings of an aim far
from the heliostat's data.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Mapping

import numpy as np
import pandas as pd
import torch

from ..artifacts.manifests import CommittedWorkdir
from ..artifacts.modelfiles import (check_fine_model_inputs, fine_model_inputs, model_stage,
                                    read_model)
from ..artifacts.schemas import HELIOSTATS, MEASUREMENTS, REGIME_PARAMS, REGIMES
from ..artifacts.store import artifact_columns, artifact_present, read_artifact
from ..errors import (FitError, HeliocalError, InputError, ParameterError, StageInputError,
                      check_choice)
from ..models.fade import epoch_seconds
from ..models.network import MODES, Layers, state_to_layers
from ..models.pretrained import PretrainedModel
from ..physics.kinematics import forward_kinematics, inverse_kinematics
from ..physics.metrics import error_mrad, reflect
from ..physics.parameters import HeliostatSpec, nominal_parameters
from ..physics.sun import sun_angles_from_vector
from ..physics.vectors import unit_vector as _unit
from .aim_choice import aim_models  # the model aim --model auto uses (torch-free; re-exported)
from .aim_network import HybridAims, not_converged_error, solve_fixed_points
from .coarse_prior import field_prior_note
from .fit_coarse import coarse_row_parameters, load_selected_parameters
from ..runtime.process_state import restores_process_state, single_threaded

if TYPE_CHECKING:   # the GP's modules import scikit-learn (about 0.9 s): only a GP aim loads them
    from ..models.gp import GPPrediction

__all__ = [
    "load_model",
    "aim_models",
    "aim_steps",
    "latest_regime",
    "utc_time",
    "FAR_FROM_DATA_DAYS",
]

log = logging.getLogger("heliocal.aim")

#: An aim time more than this many days after the heliostat's last measurement (or before its
#: first) is far from the data its model rests on: ``aim`` answers, with a warning on stderr and
#: in the result's ``warnings`` (docs/reliability.md, "Aiming far from the data").
FAR_FROM_DATA_DAYS = 365.0


# ------------------------------------------------------------------------------------------------
# what a user types: times, points, env values
# ------------------------------------------------------------------------------------------------
def utc_time(value, name: str = "time_utc", func: str = "aim") -> pd.Timestamp | None:
    """``value`` (a time as text or a timestamp; no zone means UTC, an offset is converted) as a
    UTC :class:`pandas.Timestamp`; ``None`` stays ``None``. Anything that is not a time (``noon``,
    ``2023-02-30``, ``NaT``, beyond year 2262) is a :class:`ParameterError` naming ``name``."""
    if value is None:
        return None
    try:
        ts = pd.Timestamp(value)
    except (ValueError, TypeError, OverflowError) as exc:
        why = " ".join(str(exc).split())[:100]
        raise ParameterError(f"The '{name}' parameter of {func} must be a UTC time such as "
                             f"2023-06-21T12:00:00Z. Got {value!r} instead ({why}).") from None
    if ts is pd.NaT or pd.isna(ts):
        raise ParameterError(f"The '{name}' parameter of {func} must be a UTC time such as "
                             f"2023-06-21T12:00:00Z. Got {value!r} instead.")
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def _finite_vector(value, name: str, what: str) -> np.ndarray:
    vec = np.asarray(value, np.float64).reshape(-1)
    if vec.shape != (3,) or not np.isfinite(vec).all():
        raise ParameterError(f"The '{name}' parameter of aim must be {what}: three finite "
                             f"numbers. Got {list(vec)} instead (not finite).")
    return vec


def unreachable_error(heliostat_id: str) -> FitError:
    """The one error of an aim point the heliostat's model cannot reach."""
    return FitError(f"the aim point is not reachable by {heliostat_id} within its actuator limits "
                    "for this sun position")


# ------------------------------------------------------------------------------------------------
# loading a fitted model
# ------------------------------------------------------------------------------------------------
def load_model(workdir, mode: str, heliostat_id: str) -> tuple[dict, Layers] | None:
    """Config dict and weights of a fitted mode for one heliostat (``None`` if not fitted).

    ``mode`` ``selected`` is the sweep's selected model (``DIR/hybrid/selected/``). The files are
    read through their stage's manifest and checked (:func:`heliocal.pipeline.artifacts.modelfiles.read_model`):
    a changed, corrupt, foreign or swapped file gives a one-line error naming it and the command to
    rerun. ``workdir`` is the work directory or its :class:`CommittedWorkdir`.
    """
    wd = CommittedWorkdir.of(workdir)
    stage, hint = model_stage(wd, mode)
    found = read_model(wd, stage, mode, heliostat_id, hint=hint)
    if found is None:
        return None
    cfg, state = found
    return cfg, state if cfg.get("mode") == "gp" else state_to_layers(state)


@restores_process_state
@single_threaded
def latest_regime(workdir, heliostat_id: str) -> dict | None:
    """The heliostat's latest regime in regimes.parquet (fit-coarse): number, start, the rows
    that support it and the breaks before it; ``None`` without regimes.parquet or rows.

    ``coarse_model`` names the selected regime-aware coarse model (regime_params.parquet) whose
    latest regime's parameters ``aim`` uses, ``fitted_regime`` and ``fitted_rows`` the regime
    and the training rows those parameters rest on (the latest regime's own when it has enough,
    else the regime before it); all three are ``None`` when the plain fit is selected: its
    geometry is one for all regimes, and ``rows`` tells how much of the recent data agrees."""
    wd = CommittedWorkdir.of(workdir)
    if not artifact_present(wd, REGIMES):
        return None
    r = read_artifact(wd, REGIMES, heliostats=[heliostat_id])
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
    if artifact_present(wd, REGIME_PARAMS):
        p = read_artifact(wd, REGIME_PARAMS, heliostats=[heliostat_id])
        p = p[(p["heliostat_id"] == heliostat_id) & p["selected"] & p["latest"]]
        if len(p):
            out.update(coarse_model=str(p["model"].iloc[0]),
                       fitted_regime=int(p["fitted_regime"].iloc[0]),
                       fitted_rows=int(p["n_train"].iloc[0]))
    return out


# ------------------------------------------------------------------------------------------------
# the steps of an aim
# ------------------------------------------------------------------------------------------------
@dataclass
class AimHeliostat:
    """What aim reads of one heliostat: its heliostats.parquet row, kinematic spec and selected
    coarse parameters (the latest regime's, for a regime-aware model)."""

    id: str
    row: pd.Series
    spec: HeliostatSpec
    coarse: torch.Tensor
    selected: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    gp_prediction: GPPrediction | None = None   # a GP's at the aim (for the expected error)


def read_heliostat(wd: CommittedWorkdir, heliostat_id: str) -> AimHeliostat:
    check_fine_model_inputs(wd)
    helio = read_artifact(wd, HELIOSTATS, heliostats=[heliostat_id])
    if helio.empty:
        raise InputError(f"heliostat {heliostat_id!r} is not in {wd}/heliostats.parquet")
    selected = load_selected_parameters(wd, [heliostat_id])
    return heliostat_of(wd, helio.iloc[0], selected.get(heliostat_id))


def heliostat_of(wd: CommittedWorkdir, row: pd.Series, selected: dict | None) -> AimHeliostat:
    """What aim reads of one heliostat, from its heliostats.parquet ``row`` and its
    :func:`~.fit_coarse.load_selected_parameters` entry ``selected`` (None: it has no coarse
    fit, :class:`StageInputError`); the note of a field-prior geometry is logged."""
    heliostat_id = str(row["heliostat_id"])
    if selected is None:
        raise StageInputError(f"heliostat {heliostat_id!r} has no coarse fit: run `heliocal "
                              f"fit-coarse --workdir {wd}` first")
    h = AimHeliostat(heliostat_id, row, HeliostatSpec.from_row(row), selected["params"], selected)
    note = field_prior_note(wd, row, selected["preset"])
    if note:
        h.warnings.append(note)
        log.warning("%s", note)
    return h


def _target_point(wd: CommittedWorkdir, name: str) -> np.ndarray:
    """The median centre [m] ENU of the calibration target ``name`` in the measurements."""
    m = read_artifact(wd, MEASUREMENTS, columns=["target_name", "target_e_m", "target_n_m",
                                                 "target_u_m"])
    rows = m[m["target_name"] == name]
    if rows.empty:
        names = sorted(m["target_name"].dropna().unique())
        raise InputError(f"unknown target {name!r}: give E,N,U in metres or one of {names}")
    return rows[["target_e_m", "target_n_m", "target_u_m"]].median().to_numpy(np.float64)


def _sun(h: AimHeliostat, sun_vector_enu, time_utc: pd.Timestamp | None) -> torch.Tensor:
    """Unit vector toward the sun (1, 3): the one given, or NREL SPA's at the heliostat."""
    from ..physics.sun import spa_sun_position
    from ..physics.sun import sun_vector_enu as _sunvec

    if sun_vector_enu is None:
        if time_utc is None:
            raise ParameterError("aim needs the sun: give a time or a sun azimuth and elevation")
        lat, lon, alt = h.row["latitude_deg"], h.row["longitude_deg"], h.row["altitude_m"]
        if lat is None or not np.isfinite(lat):
            raise InputError(f"heliostat {h.id!r} has no WGS84 location, so the sun cannot "
                             "be computed from the time: give --sun-azimuth and --sun-elevation")
        alt = alt if alt is not None and np.isfinite(alt) else 0.0
        az, el = spa_sun_position([time_utc], float(lat), float(lon), float(alt))
        sun_vector_enu = _sunvec(az[0], el[0])
    vec = _finite_vector(sun_vector_enu, "sun_vector_enu", "a direction")
    if not np.linalg.norm(vec) > 0:
        raise ParameterError("The 'sun_vector_enu' parameter of aim must be a direction. Got "
                             "[0, 0, 0] instead.")
    sun = _unit(torch.tensor(vec, dtype=torch.float64).reshape(1, 3))
    if float(sun[0, 2]) <= 0:
        raise InputError("the sun is below the horizon at that time")
    return sun


def choose_model(wd: CommittedWorkdir, h: AimHeliostat, model: str, choice: dict | None = None
                  ) -> tuple[str, tuple | None]:
    """(the model used, its (config, layers) or None for coarse), checked fresh; ``choice``:
    the heliostat's :func:`aim_models` entry (strict) when the caller has it (``auto``)."""
    chosen, fitted, rerun = model, None, None
    if model == "auto":
        if choice is None:
            choice = aim_models(wd, [h.id], strict=True).get(h.id, {})
        if choice.get("model") == "nominal":
            return use_nominal(h, choice["fallback"]), None
        if choice.get("model") in ("hybrid", "pretrained-nn", "gp"):
            fitted = load_model(wd, choice["model_dir"], h.id)
            if choice["source"] == "sweep":
                rerun = f"`heliocal sweep --workdir {wd}`"
        chosen = choice["model"] if fitted is not None else "coarse"
    elif model != "coarse":
        fitted = load_model(wd, model, h.id)
        if fitted is None:
            raise StageInputError(f"no {model} model for {h.id}: run `heliocal fit-hybrid "
                                  f"--workdir {wd} --mode {model}` first")
    if fitted is not None:
        current = fine_model_inputs(wd)
        if any(fitted[0].get("inputs", {}).get(k) != v for k, v in current.items()):
            rerun = rerun or f"`heliocal fit-hybrid --workdir {wd} --mode {chosen}`"
            raise StageInputError(f"the {chosen} model of {h.id} is stale (its inputs "
                                  f"changed): rerun {rerun} first")
    return chosen, fitted


def use_nominal(h: AimHeliostat, reason: str) -> str:
    """Aim ``h`` with its nominal geometry (its fit is worse than that on held-out rows:
    :func:`heliocal.pipeline.stages.aim_choice.nominal_fallback`) and say so in its warnings."""
    h.coarse = nominal_parameters(h.row)
    h.warnings.append(f"{h.id}: {reason}")
    log.warning("%s", h.warnings[-1])
    return "nominal"


def check_env(wd: CommittedWorkdir, env: Mapping[str, float]) -> dict[str, float]:
    """``env`` (name without ``env_`` -> value), every name an env column of the measurements and
    every value finite."""
    env = dict(env or {})
    if not env:
        return env
    known = sorted(c[4:] for c in artifact_columns(wd, MEASUREMENTS) if c.startswith("env_"))
    unknown = sorted(set(env) - set(known))
    if unknown:
        raise ParameterError(f"unknown env input(s) {unknown}: the env columns of "
                             f"{wd}/measurements.parquet are {known or 'none'}; give --env "
                             "NAME=VALUE with one of them")
    bad = {k: v for k, v in env.items() if not math.isfinite(float(v))}
    if bad:
        raise ParameterError(f"--env values must be finite numbers. Got {bad} instead.")
    return env


def _time_warnings(wd: CommittedWorkdir, h: AimHeliostat, time_utc: pd.Timestamp | None
                   ) -> float | None:
    """Days from the heliostat's last measurement to ``time_utc`` (negative: before it), and a
    warning in ``h.warnings`` (logged) when the time is more than :data:`FAR_FROM_DATA_DAYS`
    after the last or before the first measurement."""
    if time_utc is None:
        return None
    t = read_artifact(wd, MEASUREMENTS, columns=["heliostat_id", "timestamp"],
                      heliostats=[h.id])
    t = pd.to_datetime(t.loc[t["heliostat_id"] == h.id, "timestamp"], utc=True).dropna()
    if t.empty:
        return None
    day = pd.Timedelta(days=1)
    after, before = (time_utc - t.max()) / day, (t.min() - time_utc) / day
    if after > FAR_FROM_DATA_DAYS or before > FAR_FROM_DATA_DAYS:
        where = (f"{after:.0f} days after its last measurement ({t.max():%Y-%m-%d})"
                 if after > 0 else f"{before:.0f} days before its first ({t.min():%Y-%m-%d})")
        h.warnings.append(f"{time_utc:%Y-%m-%dT%H:%M:%SZ} is {where}: the model of {h.id} is "
                          "extrapolated that far (more than "
                          f"{FAR_FROM_DATA_DAYS:g} days from its data); check the steps")
        log.warning("%s", h.warnings[-1])
    return float(after)


def _fixed_point(h: AimHeliostat, chosen: str, fitted: tuple, sun, aim, steps, time_utc, env,
                 max_iterations: int, tolerance_steps: float):
    """(steps, parameters, iterations, None) of the hybrid: the steps whose parameters (the
    network's deviations at those steps, times its fade) aim at the point, found by fixed-point
    iteration from the coarse steps until the steps change by less than ``tolerance_steps``. A
    loop that does not get there in ``max_iterations`` raises :class:`FitError` with the last
    change."""
    hybrid = HybridAims.of(fitted, h.spec, nominal_parameters(h.row), h.id, chosen, sun, aim,
                           [time_utc], [env])
    [(steps, iterations, delta)] = solve_fixed_points([hybrid], [steps], max_iterations,
                                                      tolerance_steps)
    if not bool(torch.isfinite(steps).all()):
        raise unreachable_error(h.id)
    if iterations[0] == max_iterations and not delta[0] < tolerance_steps:
        raise not_converged_error(h.id, chosen, max_iterations, float(delta[0]), tolerance_steps)
    return steps, hybrid.params_at(steps)[0], int(iterations[0]), None   # (28,): the one aim's


def gp_env_values(h: AimHeliostat, cfg: dict, env: Mapping[str, float], time_utc) -> list[float]:
    """The values of the GP model's env inputs (in its order) for one aim, which must give every
    one of them, and a time when the model has the date as input."""
    names = cfg["gp"]["inputs"].get("env", ())
    missing = [e for e in names if e not in env]
    if missing:
        raise ParameterError(f"the gp model of {h.id} uses env inputs {missing}: give them with "
                             "--env NAME=VALUE")
    if time_utc is None and "time" in cfg["gp"]["structure"]:
        raise ParameterError(f"the gp model of {h.id} uses the date as input: give --time")
    return [float(env[e]) for e in names]


def _gp_aim_steps(cfg: dict, state, *args, **kwargs):
    """:func:`heliocal.pipeline.models.gp_heliostat.gp_aim_steps` of the GP model ``(cfg,
    state)``; the GP's modules are imported here, so that aiming any other model does not."""
    from ..models.gp import GPCorrection
    from ..models.gp_heliostat import gp_aim_steps

    return gp_aim_steps(GPCorrection.from_model(cfg, state), *args, **kwargs)


def _gp_solve(h: AimHeliostat, fitted, sun, aim, time_utc, env, max_iterations: int,
              tolerance_steps: float):
    """(steps, coarse parameters, iterations, corrected normal) of a GP correction
    (:func:`heliocal.pipeline.models.gp_heliostat.gp_aim_steps`)."""
    cfg, state = fitted
    env_values = gp_env_values(h, cfg, env, time_utc)
    fit = _gp_aim_steps(cfg, state, h.coarse, h.spec, sun, aim,
                        None if time_utc is None else epoch_seconds([time_utc])[0],
                        env_values or None,
                        max_iterations=max_iterations, tolerance_steps=tolerance_steps)
    if not bool(torch.isfinite(fit.steps).all()):
        raise unreachable_error(h.id)
    h.gp_prediction = fit.prediction
    return fit.steps, h.coarse, int(fit.iterations[0]), fit.normal


def _solve(h: AimHeliostat, chosen: str, fitted, sun, aim, time_utc, env, max_iterations: int,
           tolerance_steps: float):
    """(steps, parameters, iterations, the normal where the parameters do not give it (a GP's
    corrected one; else None)) that aim the chosen model's beam at ``aim``."""
    steps = inverse_kinematics(h.coarse, h.spec, sun, aim)
    if not bool(torch.isfinite(steps).all()):
        raise unreachable_error(h.id)
    if chosen in ("coarse", "nominal"):
        return steps, h.coarse, 0, None
    if chosen == "gp":
        return _gp_solve(h, fitted, sun, aim, time_utc, env, max_iterations, tolerance_steps)
    if chosen == "pretrained-nn":
        cfg, layers = fitted
        with torch.no_grad():
            steps = PretrainedModel.from_dict(cfg, layers).steps(sun, aim, spec=h.spec)
        if not bool(torch.isfinite(steps).all()):
            raise unreachable_error(h.id)
        return steps, h.coarse, 0, None
    return _fixed_point(h, chosen, fitted, sun, aim, steps, time_utc, env, max_iterations,
                        tolerance_steps)


def solve_aim(h: AimHeliostat, chosen: str, fitted, sun, aim, time_utc, env,
              max_iterations: int = 50, tolerance_steps: float = 1e-6):
    """(steps (1, 2), iterations, inverse residual [mrad]) of one aim of ``h`` with the chosen
    model (:func:`choose_model`), :func:`_solve` on the parameters at ``time_utc`` (a
    regime-aware coarse model's regime and drift then; ``h.coarse`` is set to them, for the
    expected error). An aim the forward model cannot reach (non-finite residual) raises."""
    if chosen != "nominal" and time_utc is not None and h.selected.get("regime_table") is not None:
        h.coarse = coarse_row_parameters(h.selected, [time_utc])[0]   # its regime, its drift
    steps, params, iterations, corrected = _solve(h, chosen, fitted, sun, aim, time_utc, env,
                                                  max_iterations, tolerance_steps)
    with torch.no_grad():
        normal, position = forward_kinematics(params, h.spec, steps)
        normal = normal if corrected is None else corrected
        inverse_residual = float(error_mrad(reflect(-sun, normal), aim - position)[0])
    if not math.isfinite(inverse_residual):
        raise unreachable_error(h.id)
    return steps, iterations, inverse_residual


def _expected_error(wd: CommittedWorkdir, h: AimHeliostat, chosen: str, fitted, steps, sun, aim,
                    time_utc) -> dict:
    """``expected_error_mrad``, ``level_source`` and ``sun_distance_deg`` of one aim (its level
    at the aim's days since the heliostat's last row, when the aim has a time; through a GP's
    predictive variance at the aim, ``h.gp_prediction``: :func:`.aim_budget.fine_level_mrad`,
    held to the GP's held-out rows where the sweep selected it, as the batch aim holds it)."""
    from .aim_budget import days_since, error_budgets, expected_error_mrad, sun_distance_deg

    models = {h.id: {"model": chosen if chosen in ("nominal", "gp") else "coarse",
                     "source": None if fitted is None else fitted[0].get("selected_by")}}
    budget = error_budgets(wd, {h.id: h.spec}, {h.id: h.selected}, models)[h.id]
    fine = h.gp_prediction if chosen == "gp" else None
    expected = expected_error_mrad(
        budget, h.spec, h.coarse, steps, sun, aim, [days_since(budget, time_utc)],
        explained_mrad2=0.0 if fine is None else fine.explained_variance_mrad2,
        fine_noise_mrad2=0.0 if fine is None else fine.noise_mrad2)
    return {"expected_error_mrad": float(expected[0]), "level_source": budget.level_source,
            "sun_distance_deg": float(sun_distance_deg(budget, sun.numpy())[0])}


def aim_steps(workdir, heliostat_id: str, *, aim_point_enu=None, target: str | None = None,
              sun_vector_enu=None, time_utc=None, env: Mapping[str, float] | None = None,
              model: str = "auto", max_iterations: int = 50,
              tolerance_steps: float = 1e-6,
              max_expected_error_mrad: float | None = None) -> dict:
    """Motor steps that reflect the sun onto ``aim_point_enu`` with the best fitted model.

    Parameters
    ----------
    workdir : the work directory (or its open :class:`CommittedWorkdir`).
    aim_point_enu : (3,) aim point [m] ENU; or
    target : the name of a calibration target of the measurements (its median centre).
    sun_vector_enu : (3,) direction toward the sun; default from NREL SPA at ``time_utc``.
    time_utc : time of the aim (needed by models with time inputs, and for the sun by default);
        text or a timestamp, no zone meaning UTC (:func:`utc_time`).
    env : values of the model's env inputs (name without ``env_`` -> value); every name must be
        an env column of the measurements.
    model : ``auto`` (the sweep's selection where ``sweep`` ran, else the fit-hybrid hybrid where
        fitted, else coarse), ``coarse``, ``hybrid``, ``nn-only``, ``pretrained-nn`` or ``gp``.
    max_iterations, tolerance_steps : the hybrid's fixed-point iteration stops when the steps
        change by less than ``tolerance_steps`` [steps]; without that in ``max_iterations`` it
        raises :class:`FitError`.
    max_expected_error_mrad : refuse (:class:`FitError`, one line) an aim whose
        ``expected_error_mrad`` is larger.

    Returns
    -------
    dict with ``axis_1_steps``, ``axis_2_steps``, ``model`` (``nominal`` when the fit is worse
    than the nominal geometry on held-out rows; a warning says so), ``iterations``,
    ``expected_error_mrad`` (the error a measurement of this aim is expected to show:
    :mod:`heliocal.pipeline.stages.aim_budget`; through a GP, with its predictive variance at
    the aim), its ``level_source``, ``sun_distance_deg``
    (the aim's sun to the nearest training row's), ``inverse_residual_mrad`` (the angle between
    the forward model's reflected beam at the returned steps and the direction to the aim
    point: how exactly the steps solve the model, not how well the heliostat will point),
    ``sun_azimuth_deg``, ``sun_elevation_deg``, ``regime``, ``days_after_last_measurement``
    (None without a time) and ``warnings`` (texts, also logged: an aim far from the data).
    """
    check_choice(model, "model", "aim", ("auto", "coarse") + MODES)
    if (aim_point_enu is None) == (target is None):
        raise ParameterError("aim needs one aim point: give aim_point_enu or target")
    time_utc = utc_time(time_utc)
    wd = CommittedWorkdir.of(workdir)
    env = check_env(wd, env)
    point = (_target_point(wd, target) if target is not None
             else _finite_vector(aim_point_enu, "aim_point_enu", "a point [m] ENU"))
    h = read_heliostat(wd, heliostat_id)
    sun = _sun(h, sun_vector_enu, time_utc)
    aim = torch.tensor(point, dtype=torch.float64).reshape(1, 3)
    chosen, fitted = choose_model(wd, h, model)
    days = _time_warnings(wd, h, time_utc)
    steps, iterations, inverse_residual = solve_aim(h, chosen, fitted, sun, aim, time_utc, env,
                                                    max_iterations, tolerance_steps)
    expected = _expected_error(wd, h, chosen, fitted, steps, sun, aim, time_utc)
    if max_expected_error_mrad is not None and not expected["expected_error_mrad"] <= max_expected_error_mrad:
        raise FitError(f"the aim of {h.id} is expected to be off by "
                       f"{expected['expected_error_mrad']:.3g} mrad, more than "
                       f"--max-expected-error {max_expected_error_mrad:g} mrad; recalibrate it or "
                       "raise the limit")
    az, el = sun_angles_from_vector(sun.numpy())
    out = {"heliostat_id": heliostat_id, "model": chosen,
           "time_utc": None if time_utc is None else str(time_utc),
           "sun_azimuth_deg": float(az[0]), "sun_elevation_deg": float(el[0]),
           "aim_point_enu_m": aim[0].tolist(), "axis_1_steps": float(steps[0, 0]),
           "axis_2_steps": float(steps[0, 1]), "iterations": iterations,
           **expected, "inverse_residual_mrad": inverse_residual,
           "regime": latest_regime(wd, heliostat_id),
           "days_after_last_measurement": days, "warnings": h.warnings}
    if target is not None:
        out["target"] = target
    return out

