"""``fit-coarse``: the rigid-body coarse model fitted by Levenberg-Marquardt.

For every heliostat the free parameters of a preset (:data:`~heliocal.pipeline.physics.parameters.PRESETS`)
are fitted on its training rows with :func:`scipy.optimize.least_squares`:

* residuals: per measurement the three components of ``1000 * (n_pred - n_meas)`` [mrad], where
  ``n_meas`` is the bisector of the sun direction and the direction from the predicted mirror
  centre to the measured focal spot (:func:`heliocal.pipeline.physics.metrics.measured_normal`); their
  norm is ``2000 sin(error/2)``, i.e. the angular error in mrad to third order;
* Jacobian: exact, from torch's forward-mode autodiff (:func:`torch.func.jacfwd`), no finite
  differences;
* a weak Gaussian prior toward the nominal geometry (one residual ``(p - p0) / sigma`` per free
  parameter, sigma from :data:`PRIOR_SIGMA`) keeps parameters the data cannot determine at their
  nominal values; it is weak enough that determined parameters are not biased measurably
  (data curvature is 10^5 to 10^9 times larger);
* method ``lm`` (MINPACK's Levenberg-Marquardt) for the plain least-squares loss; ``trf`` when a
  robust loss (``soft_l1`` or ``huber``, scale ``f_scale_mrad``) is asked for, since MINPACK has
  none;
* a robust start: a grid search over both actuators' angle offsets (the parameters nominal
  geometry gets most wrong; PAINT's BF41 is off by about a radian) picks the starting point with
  the smallest median error before LM; a fit that moves any parameter by more than
  :data:`PLAUSIBLE_CORRECTION` is reported.

Standard errors come from the Jacobian at the solution: ``cov = s^2 (J^T J)^-1`` with ``s^2`` the
data residual variance (:mod:`.fit_diagnostics`; a singular ``J^T J`` is flagged in the fit's
status). A parameter whose standard error exceeds half its prior sigma is reported as *not
determined by the data* (the prior, not the data, fixes it).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch
from scipy.optimize import least_squares

from ..errors import check_choice
from ..physics.jacobian import forward_state, residual_and_jacobian
from ..physics.kinematics import forward_kinematics, joint_angles
from ..physics.metrics import beam_error_mrad, error_mrad, measured_normal, spot_offset_m
from ..physics.parameters import (PARAMETER_INDEX, PARAMETER_NAMES, PARAMETER_UNITS, PRESET_NAMES,
                                  HeliostatSpec, preset_mask)
from ..vocabulary import CoarseLoss, CoarseSolver
from .fit_diagnostics import fit_diagnostics

__all__ = [
    "AUTO_PRESETS",
    "PRIOR_SIGMA",
    "prior_sigma",
    "PLAUSIBLE_CORRECTION",
    "MeasurementBatch",
    "CoarseFit",
    "fit_heliostat",
    "fit_heliostats_batched",
    "SOLVERS",
    "predict",
    "metrics_frame",
    "normal_errors_mrad",
    "LOSSES",
    "data_degeneracy",
    "parameter_kind",
]


#: Presets tried by ``--preset auto``; the one with the lowest validation error is selected.
AUTO_PRESETS = ("static-6", "stone-8", "static-14", "static-20", "static-28")


LOSSES = CoarseLoss.values()


#: Solvers of ``fit-coarse``: the batched LM (:mod:`heliocal.pipeline.physics.lm`) or scipy per heliostat.
SOLVERS = CoarseSolver.values()


def parameter_kind(name: str) -> str:
    if name.endswith("_increment"):
        return "increment"
    if "_tilt_" in name or name.endswith("_initial_angle_rad"):
        return "angle"
    if "_translation_" in name:
        return "translation"
    return "length"


#: Prior sigma per parameter kind (angles [rad], lengths [m], increments relative to nominal).
PRIOR_SIGMA = {"angle": 0.1, "translation": 0.05, "length": 0.01, "increment": 0.01}


#: Median nominal error above which ``robust_start="auto"`` searches the zero points [mrad].
ROBUST_START_THRESHOLD_MRAD = 50.0


#: Corrections of the nominal geometry beyond which a fit is reported as implausible.
PLAUSIBLE_CORRECTION = {"angle": 0.05, "translation": 0.05, "length": 0.05, "increment": 0.02}


# ------------------------------------------------------------------------------------------------
# data of one heliostat as tensors
# ------------------------------------------------------------------------------------------------
@dataclass
class MeasurementBatch:
    """Tensors of one heliostat's measurements (float64; positions ENU [m])."""

    measurement_id: np.ndarray
    steps: torch.Tensor  # (N, 2)
    sun: torch.Tensor  # (N, 3)
    focal_spot: torch.Tensor  # (N, 3)
    target_center: torch.Tensor  # (N, 3)
    target_normal: torch.Tensor  # (N, 3)

    @classmethod
    def from_frame(cls, df: pd.DataFrame) -> "MeasurementBatch":
        t = lambda cols: torch.from_numpy(np.column_stack(  # noqa: E731 (not df[cols]: a copy)
            [df[c].to_numpy(np.float64) for c in cols]))
        return cls(
            measurement_id=df["measurement_id"].astype(str).to_numpy(),
            steps=t(("axis_1_steps", "axis_2_steps")),
            sun=t(("sun_e", "sun_n", "sun_u")),
            focal_spot=t(("focal_spot_e_m", "focal_spot_n_m", "focal_spot_u_m")),
            target_center=t(("target_e_m", "target_n_m", "target_u_m")),
            target_normal=t(("target_normal_e", "target_normal_n", "target_normal_u")),
        )

    def subset(self, mask: np.ndarray) -> "MeasurementBatch":
        keep = np.array(mask, dtype=bool)  # a writable copy: torch refuses read-only arrays
        m = torch.from_numpy(keep)
        return MeasurementBatch(self.measurement_id[keep], self.steps[m],
                                self.sun[m], self.focal_spot[m], self.target_center[m],
                                self.target_normal[m])

    def __len__(self) -> int:
        return int(self.steps.shape[0])


def normal_errors_mrad(params: torch.Tensor, spec: HeliostatSpec, data: MeasurementBatch) -> torch.Tensor:
    """error_mrad of every measurement for parameter vector(s) ``params`` (..., 28) -> (..., N)."""
    normal, position = forward_kinematics(params, spec, data.steps)
    meas = measured_normal(data.sun, position, data.focal_spot)
    return error_mrad(normal, meas)


def metrics_frame(data: MeasurementBatch, normal: torch.Tensor, position: torch.Tensor) -> pd.DataFrame:
    """The per-measurement metric columns of coarse_predictions for predicted normals and mirror
    centres (N, 3): error_mrad, beam_error_mrad and the spot offset (defined in metrics)."""
    with torch.no_grad():
        meas = measured_normal(data.sun, position, data.focal_spot)
        err = error_mrad(normal, meas)
        beam = beam_error_mrad(data.sun, normal, position, data.focal_spot)
        h, v, mag = spot_offset_m(data.sun, normal, position, data.focal_spot, data.target_center,
                                  data.target_normal)
    return pd.DataFrame({
        "measurement_id": data.measurement_id,
        "error_mrad": err.numpy(), "beam_error_mrad": beam.numpy(),
        "spot_offset_horizontal_m": h.numpy(), "spot_offset_vertical_m": v.numpy(),
        "spot_offset_m": mag.numpy()})


def predict(params: torch.Tensor, spec: HeliostatSpec, data: MeasurementBatch) -> pd.DataFrame:
    """All error metrics of every measurement for one parameter vector (28,)."""
    with torch.no_grad():
        normal, position = forward_kinematics(params, spec, data.steps)
    return metrics_frame(data, normal, position)


# ------------------------------------------------------------------------------------------------
# one heliostat, one preset
# ------------------------------------------------------------------------------------------------
@dataclass
class CoarseFit:
    """Result of :func:`fit_heliostat`."""

    preset: str
    params: torch.Tensor  # (28,) fitted
    nominal: torch.Tensor  # (28,)
    free: np.ndarray  # bool (28,)
    std_error: np.ndarray  # (28,) NaN where fixed
    determined: np.ndarray  # bool (28,)
    iterations: int
    cost: float
    condition_number: float
    status: str
    implausible: list[str]
    wall_time_s: float
    noise_mrad: float = float("nan")  # RMS data residual per component, on the dof [mrad]
    data_rss_mrad2: float = float("nan")  # squared data residuals' sum [mrad^2] (fit_diagnostics)
    data_dof: float = float("nan")  # their effective degrees of freedom (fit_diagnostics)
    prior_shrinkage: np.ndarray | None = None  # (28,) the prior's share (fit_diagnostics) or None
    own_noise_mrad: float = float("nan")  # under a field prior: its own noise estimate [mrad]
    prior_noise_mrad: float = float("nan")  # ... and the noise its prior was weighed against
    data_only_std_error: np.ndarray | None = None  # (28,) the data's alone, at its noise


def prior_sigma(nominal: torch.Tensor) -> np.ndarray:
    """Prior sigma (28,) of each parameter: :data:`PRIOR_SIGMA` of its kind (increments relative)."""
    sig = np.empty(len(PARAMETER_NAMES))
    for i, name in enumerate(PARAMETER_NAMES):
        kind = parameter_kind(name)
        relative = (abs(float(nominal[i])) or 1.0) if kind == "increment" else 1.0
        sig[i] = PRIOR_SIGMA[kind] * relative
    return sig


def _robust_start(p0: torch.Tensor, spec: HeliostatSpec, data: MeasurementBatch,
                  free: np.ndarray) -> torch.Tensor:
    """A start for LM that survives a badly wrong nominal actuator geometry.

    The measured normals are inverted to joint angles under the nominal geometry (closed-form
    two-axis solution, both branches); then, per axis, the free actuator zero-point parameters
    (``axis_i_initial_angle_rad`` and, for linear actuators, ``axis_i_initial_stroke_length_m``)
    are chosen on a grid to minimise the median angle residual of ``steps -> angle``, followed by
    a finer grid around the best. Axes decouple, so each search is 2-D and cheap. The result is
    kept only if it lowers the median normal error of the start.
    """
    from ..physics.kinematics import solve_angles  # the closed-form inverse of the chain

    with torch.no_grad():
        _, position = forward_kinematics(p0, spec, data.steps)
        meas = measured_normal(data.sun, position, data.focal_spot)
        linear = spec.actuator_type == "linear"
        candidates = []
        for branch in (0, 1):  # both axes must come from the same branch of the inverse
            target_both = solve_angles(p0, spec, meas, branch)  # (N, 2)
            cand_p, total = p0.clone(), 0.0
            for axis in (1, 2):
                i_ang = PARAMETER_INDEX[f"axis_{axis}_initial_angle_rad"]
                i_str = PARAMETER_INDEX[f"axis_{axis}_initial_stroke_length_m"]
                search_stroke = linear and bool(free[i_str])
                if not free[i_ang] and not search_stroke:
                    continue
                target = target_both[..., axis - 1]
                ok = torch.isfinite(target)
                if int(ok.sum()) < 3:
                    total = math.inf
                    break
                angles = (torch.linspace(-math.pi, math.pi, 181, dtype=torch.float64)[:-1]
                          if free[i_ang] else p0[i_ang:i_ang + 1])
                if search_stroke:
                    reach = float(p0[PARAMETER_INDEX[f"axis_{axis}_offset_m"]]
                                  + p0[PARAMETER_INDEX[f"axis_{axis}_pivot_radius_m"]])
                    strokes = torch.linspace(0.0, max(reach, 0.05), 61, dtype=torch.float64)
                else:
                    strokes = p0[i_str:i_str + 1]
                for _ in range(3):  # global grid, then two finer grids around the best
                    pred = _grid_joint_angles(p0, spec, data.steps[ok], axis, angles, strokes)
                    diff = torch.remainder(pred - target[ok] + math.pi, 2 * math.pi) - math.pi
                    score = torch.nan_to_num(diff.abs(), nan=10.0).median(dim=-1).values
                    k = int(torch.argmin(score))           # row k: angle k // S, stroke k % S
                    a0, s0 = float(angles[k // len(strokes)]), float(strokes[k % len(strokes)])
                    da = float(angles[1] - angles[0]) if len(angles) > 1 else 0.0
                    ds = float(strokes[1] - strokes[0]) if len(strokes) > 1 else 0.0
                    if da:
                        angles = torch.linspace(a0 - da, a0 + da, 21, dtype=torch.float64)
                    if ds:
                        strokes = torch.linspace(max(s0 - ds, 0.0), s0 + ds, 21, dtype=torch.float64)
                cand_p[i_ang], cand_p[i_str] = a0, s0
                total += float(score[k])
            candidates.append((total, cand_p))
        best_p = min(candidates, key=lambda c: c[0])[1]
        before = torch.nan_to_num(normal_errors_mrad(p0, spec, data), nan=1e6).median()
        after = torch.nan_to_num(normal_errors_mrad(best_p, spec, data), nan=1e6).median()
    return best_p if after < before else p0


def _grid_joint_angles(p0: torch.Tensor, spec: HeliostatSpec, steps: torch.Tensor, axis: int,
                       angles: torch.Tensor, strokes: torch.Tensor) -> torch.Tensor:
    """Axis ``axis``'s joint angles [rad] at ``steps`` (n, 2) for every (zero-point angle,
    initial stroke) pair of the grid ``angles`` x ``strokes``: (A S, n), rows in
    ``meshgrid(angles, strokes, indexing="ij")`` order, the other parameters ``p0``'s.

    Both actuator laws add the zero-point angle last (``angle0 + ...``), so the law runs once per
    stroke, at angle 0, and each grid angle is added to that: the same floating-point sums as
    running the law once per pair, at 1/A of its cost."""
    i_ang = PARAMETER_INDEX[f"axis_{axis}_initial_angle_rad"]
    i_str = PARAMETER_INDEX[f"axis_{axis}_initial_stroke_length_m"]
    per_stroke = p0.unsqueeze(0).repeat(len(strokes), 1)
    per_stroke[:, i_ang] = 0.0
    per_stroke[:, i_str] = strokes
    relative = joint_angles(per_stroke, spec, steps)[..., axis - 1]          # (S, n)
    return (angles[:, None, None] + relative[None]).reshape(-1, relative.shape[-1])


def _fit_setup(spec: HeliostatSpec, nominal: torch.Tensor, train: MeasurementBatch, preset: str,
               *, robust_start, start: torch.Tensor | None, start_cache: dict | None,
               prior_weight: float, prior: tuple | None = None):
    """What both solvers share before LM: free mask (28,), the default prior sigma (28,) (the
    variables' scale), the start (28,) (the prior's mean: nominal or ``prior``'s; explicit; or
    the robust start's) and the free parameters' prior sigma (P,): ``prior``'s sigma (28,),
    except for zero points the robust start moved (the field's spread of them does not apply
    to a heliostat whose zero points are off by far more), which keep the default."""
    free = preset_mask(preset, spec.actuator_type, spec.kinematic_type).numpy()
    free_idx = np.flatnonzero(free)
    sigma = prior_sigma(nominal)
    centre = nominal if prior is None else torch.as_tensor(prior[0], dtype=torch.float64)
    sig_prior = sigma.copy() if prior is None else np.asarray(prior[1], np.float64).copy()
    if prior is not None and len(prior) > 2:  # weighed against noise s: data rows are in mrad
        sig_prior = sig_prior / np.asarray(prior[2], np.float64)
    x0_full = start.clone() if start is not None else centre.clone()
    mode = {True: "always", False: "never"}.get(robust_start, robust_start)
    check_choice(mode, "robust_start", "fit_heliostat", ("always", "auto", "never"))
    if mode != "never" and start is None and len(train):
        zero_point = tuple(bool(free[PARAMETER_INDEX[f"axis_{i}_{f}"]]) for i in (1, 2)
                           for f in ("initial_angle_rad", "initial_stroke_length_m"))
        cache = start_cache if start_cache is not None else {}
        key = zero_point if prior is None else (zero_point, centre.numpy().tobytes())
        if key not in cache:
            needed = mode == "always"
            if not needed:
                with torch.no_grad():
                    med = torch.nan_to_num(normal_errors_mrad(centre, spec, train), nan=1e9).median()
                needed = float(med) > ROBUST_START_THRESHOLD_MRAD
            cache[key] = _robust_start(x0_full, spec, train, free) if needed else x0_full
        x0_full = cache[key].clone()
        moved = (x0_full != centre).numpy()
        sig_prior[moved] = sigma[moved]
    sig_free = torch.as_tensor(sig_prior[free_idx]) / math.sqrt(max(prior_weight, 1e-300))
    return free, sigma, x0_full, sig_free


def fit_heliostat(spec: HeliostatSpec, nominal: torch.Tensor, train: MeasurementBatch, preset: str,
                  *, loss: str = "linear", f_scale_mrad: float = 1.0, robust_start: bool = True,
                  max_nfev: int = 200, start: torch.Tensor | None = None,
                  prior_weight: float = 1.0, tolerance: float = 1e-10,
                  jacobian: str = "exact", start_cache: dict | None = None,
                  prior: tuple | None = None) -> CoarseFit:
    """Fit one heliostat's free parameters (preset) on its training measurements.

    Parameters
    ----------
    spec : the heliostat's fixed description.
    nominal : (28,) nominal parameters (prior mean and default start).
    train : training measurements.
    preset : one of :data:`~heliocal.pipeline.physics.parameters.PRESET_NAMES`.
    loss : ``linear`` (MINPACK LM), ``soft_l1`` or ``huber`` (trust-region reflective).
    f_scale_mrad : residual scale of the robust loss [mrad].
    robust_start : ``True``/``"always"`` grid-searches the actuator zero points first (see
        :func:`_robust_start`); ``"auto"`` only when the nominal geometry's median error exceeds
        :data:`ROBUST_START_THRESHOLD_MRAD` (a wrong nominal geometry); ``False``/``"never"``
        starts LM from the nominal values.
    start : explicit start (28,) instead of the nominal/grid start.
    jacobian : ``exact`` (geometric Jacobian, :mod:`heliocal.pipeline.physics.jacobian`) or scipy's
        ``2-point`` finite differences (only for the benchmark's comparison).
    start_cache : dict shared between the presets of one heliostat, so the robust start is
        searched once per set of free zero-point parameters.
    tolerance : xtol = ftol = gtol of the solver (relative changes of step, cost, gradient).
    prior_weight : multiplier of the prior's curvature (1 = :data:`PRIOR_SIGMA`; 0 = no prior,
        plain least squares, as in the noiseless recovery tests).
    prior : (mean (28,), sigma (28,)[, noise (28,)]) [parameter units; noise mrad]: a Gaussian
        prior (e.g. the field's, :mod:`.field_prior`) instead of :data:`PRIOR_SIGMA` around the
        nominal values; its mean is the start. ``noise``: the measurement noise per residual
        component it is weighed against (rows ``sigma / noise``; the data rows are unweighted
        mrad); without it 1 mrad, as the default prior's. None: the default.
    """
    check_choice(preset, "preset", "fit_heliostat", PRESET_NAMES)
    check_choice(loss, "loss", "fit_heliostat", LOSSES)
    t0 = time.perf_counter()
    nominal = nominal.to(torch.float64)
    free, sigma, x0_full, sig_free = _fit_setup(spec, nominal, train, preset,
                                                robust_start=robust_start, start=start,
                                                start_cache=start_cache, prior_weight=prior_weight,
                                                prior=prior)
    free_idx = np.flatnonzero(free)
    free_idx_t = torch.as_tensor(free_idx)
    # the prior's mean is the start: the nominal geometry, with the actuator zero points the
    # robust start corrected from the data
    nom_free = x0_full[free_idx_t]
    n_data = 3 * len(train)

    def full(x_free: torch.Tensor) -> torch.Tensor:
        return x0_full.index_put((free_idx_t,), x_free)

    use_prior = prior_weight > 0
    prior_scale = (1.0 / sig_free).numpy()
    cache: dict = {}
    states: dict = {}

    def _prior_rows(x, r, jf=None):
        if not use_prior:
            return r, jf
        r = np.concatenate([r, (np.asarray(x) - nom_free.numpy()) * prior_scale])
        return r, (None if jf is None else np.vstack([jf, np.diag(prior_scale)]))

    def fun(x):
        """Residuals at x (forward pass only; trial steps LM rejects need no Jacobian)."""
        key = np.asarray(x, dtype=np.float64).tobytes()
        if key in cache:
            return cache[key][0]
        with torch.no_grad():
            p = full(torch.as_tensor(x, dtype=torch.float64))
            state = forward_state(p, spec, train.steps)
            meas = measured_normal(train.sun, state[2], train.focal_spot)
            # NaN where an actuator leaves its geometric range (law of cosines): a large, flat
            # residual that LM backs away from
            r = torch.nan_to_num(1000.0 * (state[1] - meas).reshape(-1), nan=1e4).numpy()
        states.clear()
        states[key] = state  # the Jacobian at an accepted x reuses this forward pass
        return _prior_rows(x, r)[0]

    def jac(x):
        """Exact Jacobian at x (geometric, :mod:`heliocal.pipeline.physics.jacobian`)."""
        key = np.asarray(x, dtype=np.float64).tobytes()
        if key not in cache:
            cache.clear()
            p = full(torch.as_tensor(x, dtype=torch.float64))
            r, jac_full = residual_and_jacobian(p, spec, train.steps, train.sun, train.focal_spot,
                                                state=states.get(key))
            r = torch.nan_to_num(r.reshape(-1), nan=1e4).numpy()
            jf = torch.nan_to_num(jac_full[:, :, free_idx_t].reshape(-1, len(free_idx)),
                                  nan=0.0, posinf=0.0, neginf=0.0).numpy()
            cache[key] = _prior_rows(x, r, jf)
        return cache[key][1]

    x0 = x0_full[free_idx_t].numpy()
    if len(free_idx) == 0 or len(train) == 0:
        res_x, nfev, cost, status, J = x0, 0, float(0.5 * (fun(x0) ** 2).sum()), "nothing to fit", None
    else:
        method = "lm" if loss == "linear" else "trf"
        check_choice(jacobian, "jacobian", "fit_heliostat", ("exact", "2-point"))
        kwargs = dict(x_scale=sigma[free_idx], jac=jac if jacobian == "exact" else "2-point",
                      method=method, max_nfev=max_nfev,
                      xtol=tolerance, ftol=tolerance, gtol=tolerance)
        if method == "trf":
            kwargs.update(loss=loss, f_scale=f_scale_mrad)
        if method == "lm" and n_data + len(free_idx) < len(free_idx):  # pragma: no cover
            method = "trf"
        res = least_squares(fun, x0, **kwargs)
        res_x, nfev, cost, status = res.x, int(res.njev or res.nfev), float(res.cost), str(res.message)
        J = jac(res_x)
    fitted = full(torch.as_tensor(res_x, dtype=torch.float64)).detach()

    d = fit_diagnostics(J, fun(res_x) if J is not None else None, n_data, free_idx, sigma,
                        loss, f_scale_mrad)
    implausible = _implausible(fitted, nominal, free_idx)
    return CoarseFit(preset, fitted, nominal, free, d.std_error, d.determined, nfev, cost,
                     d.condition_number, d.flag_status(status), implausible,
                     time.perf_counter() - t0, d.noise_mrad, d.data_rss_mrad2, d.data_dof,
                     d.prior_shrinkage, data_only_std_error=d.data_only_std_error)


def fit_heliostats_batched(specs: Sequence[HeliostatSpec], nominals: Sequence[torch.Tensor],
                           trains: Sequence[MeasurementBatch], preset: str, *,
                           loss: str = "linear", f_scale_mrad: float = 1.0,
                           robust_start: bool | str = True, max_nfev: int = 200,
                           prior_weight: float = 1.0, tolerance: float = 1e-10,
                           start_caches: Sequence[dict] | None = None,
                           priors: Sequence[tuple | None] | None = None,
                           starts: Sequence[torch.Tensor | None] | None = None) -> list[CoarseFit]:
    """:func:`fit_heliostat` for many heliostats of one kinematic and actuator type at once.

    ``starts`` (per heliostat (28,) or None) warm-starts Levenberg-Marquardt there (e.g. the fit
    of the same heliostat on fewer rows) without changing the objective: the prior stays
    centred where a cold fit centres it (the nominal geometry, or the robust start of
    ``start_caches``, which the caller keeps across such fits).

    The objective (data rows, prior rows, loss) and the start (including the robust start, per
    heliostat) are those of :func:`fit_heliostat`; the minimisation is one batched
    Levenberg-Marquardt program (:func:`heliocal.pipeline.physics.lm.solve_batched`) instead of one
    scipy solve per heliostat. Standard errors, 'determined' flags and the condition number
    come from the same per-heliostat diagnostics at the solution. Heliostats without training
    rows are left to :func:`fit_heliostat` ("nothing to fit"). ``priors``: per heliostat
    :func:`fit_heliostat`'s ``prior`` (None: the default).
    """
    from ..physics.lm import BatchedProblem, solve_batched, stack_specs

    check_choice(preset, "preset", "fit_heliostat", PRESET_NAMES)
    check_choice(loss, "loss", "fit_heliostat", LOSSES)
    t0 = time.perf_counter()
    n_helio = len(specs)
    caches = list(start_caches) if start_caches is not None else [{} for _ in range(n_helio)]
    fits: list[CoarseFit | None] = [None] * n_helio
    priors = list(priors) if priors is not None else [None] * n_helio
    setups, batch = [], []
    for k in range(n_helio):
        if len(trains[k]) == 0:
            fits[k] = fit_heliostat(specs[k], nominals[k], trains[k], preset, loss=loss,
                                    f_scale_mrad=f_scale_mrad, robust_start=robust_start,
                                    max_nfev=max_nfev, prior_weight=prior_weight,
                                    tolerance=tolerance, start_cache=caches[k], prior=priors[k])
            continue
        nominal = nominals[k].to(torch.float64)
        setups.append((nominal,) + _fit_setup(specs[k], nominal, trains[k], preset,
                                              robust_start=robust_start, start=None,
                                              start_cache=caches[k], prior_weight=prior_weight,
                                              prior=priors[k]))
        batch.append(k)
    if not batch:
        return fits
    free = setups[0][1]
    free_idx = np.flatnonzero(free)
    free_idx_t = torch.as_tensor(free_idx)
    n_rows = [len(trains[k]) for k in batch]
    n_max = max(n_rows)

    def padded(field: str) -> torch.Tensor:
        # pad with copies of the heliostat's first row (finite geometry); the mask zeroes them
        out = []
        for k, n in zip(batch, n_rows):
            t = getattr(trains[k], field)
            out.append(torch.cat([t, t[:1].expand(n_max - n, *t.shape[1:])]) if n < n_max else t)
        return torch.stack(out)

    base = torch.stack([x0 for _, _, _, x0, _ in setups])
    sigma = np.stack([sig for _, _, sig, _, _ in setups])
    problem = BatchedProblem(
        spec=stack_specs([specs[k] for k in batch]), base=base, free_idx=free_idx_t,
        steps=padded("steps"), sun=padded("sun"), focal_spot=padded("focal_spot"),
        row_mask=torch.arange(n_max).unsqueeze(0) < torch.tensor(n_rows).unsqueeze(1),
        prior_mean=base[:, free_idx_t],
        prior_scale=(1.0 / torch.stack([sf for *_, sf in setups])) if prior_weight > 0 else None,
        x_scale=torch.as_tensor(sigma[:, free_idx]))
    x0 = base[:, free_idx_t].clone()
    for j, k in enumerate(batch):
        if starts is not None and starts[k] is not None:
            x0[j] = starts[k].to(torch.float64)[free_idx_t]
    sol = solve_batched(problem, x0, loss=loss, f_scale=f_scale_mrad,
                        max_nfev=max_nfev, tolerance=tolerance)
    wall = (time.perf_counter() - t0) / len(batch)
    data_rows = 3 * n_max
    for j, k in enumerate(batch):
        nominal, _, sig, x0_full, _ = setups[j]
        n_data = 3 * n_rows[j]
        keep = np.r_[0:n_data, data_rows:problem.n_rows]  # real data rows, then prior rows
        J = sol.jacobian[j].numpy()[keep]
        r = sol.residual[j].numpy()[keep]
        fitted = x0_full.index_put((free_idx_t,), sol.x[j])
        d = fit_diagnostics(J, r, n_data, free_idx, sig, loss, f_scale_mrad)
        fits[k] = CoarseFit(preset, fitted, nominal, free, d.std_error, d.determined,
                            int(sol.njev[j]), float(sol.cost[j]), d.condition_number,
                            d.flag_status(f"batched LM: {sol.status[j]}"),
                            _implausible(fitted, nominal, free_idx), wall, d.noise_mrad,
                            d.data_rss_mrad2, d.data_dof, d.prior_shrinkage,
                            data_only_std_error=d.data_only_std_error)
    return fits


#: The simplest preset. Training rows that cannot determine its parameters are degenerate (all
#: alike, or too little spread in sun position): a larger preset is determined less still, and a
#: small error of such a fit only says that the fit reproduces the few directions it saw.
IDENTIFIABILITY_PRESET = "static-6"


def data_degeneracy(spec: HeliostatSpec, params: torch.Tensor, nominal: torch.Tensor,
                    train: MeasurementBatch, jacobian: tuple | None = None) -> str:
    """Why ``train`` cannot determine the parameters of :data:`IDENTIFIABILITY_PRESET` (``""`` if
    it can), judged with the data-only Jacobian at ``params`` (``jacobian``: residual_and_jacobian
    there, if computed) and the same 'determined' rule as the fit's (a parameter is determined
    when 1 mrad noise leaves it less than half its prior sigma uncertain, :func:`fit_diagnostics`)."""
    n = len(train)
    if n == 0:
        return "no training rows"
    rows = torch.cat([train.steps, train.sun, train.focal_spot], dim=1).numpy()
    distinct = len(np.unique(rows, axis=0))
    sun = train.sun.numpy() / np.linalg.norm(train.sun.numpy(), axis=1, keepdims=True)
    spread = float(np.degrees(np.arccos(np.clip((sun @ sun.T).min(), -1.0, 1.0))))
    if distinct == 1:
        return "only one training row" if n == 1 else f"all {n} training rows are identical"
    free = preset_mask(IDENTIFIABILITY_PRESET, spec.actuator_type, spec.kinematic_type).numpy()
    free_idx = np.flatnonzero(free)
    with torch.no_grad():
        r, jac = jacobian or residual_and_jacobian(params.to(torch.float64), spec, train.steps,
                                                   train.sun, train.focal_spot)
    J = torch.nan_to_num(jac[:, :, torch.as_tensor(free_idx)].reshape(-1, len(free_idx)),
                         nan=0.0, posinf=0.0, neginf=0.0).numpy()
    r = torch.nan_to_num(r.reshape(-1), nan=0.0).numpy()
    determined = fit_diagnostics(J, r, len(r), free_idx, prior_sigma(nominal)).determined
    n_det = int(determined[free_idx].sum())
    if n_det == len(free_idx):
        return ""
    return (f"the {n} training rows ({distinct} distinct, sun positions within {spread:.2g} deg "
            f"of each other) determine only {n_det} of the {len(free_idx)} parameters of "
            f"{IDENTIFIABILITY_PRESET}")


def _implausible(fitted: torch.Tensor, nominal: torch.Tensor, free_idx: np.ndarray) -> list[str]:
    """Free parameters corrected beyond :data:`PLAUSIBLE_CORRECTION`, as text."""
    implausible = []
    for i in free_idx:
        name = PARAMETER_NAMES[i]
        kind = parameter_kind(name)
        delta = float(fitted[i] - nominal[i])
        bound = PLAUSIBLE_CORRECTION[kind] * (abs(float(nominal[i])) if kind == "increment" else 1.0)
        if abs(delta) > bound:
            unit = PARAMETER_UNITS[name].split(" ")[0]
            implausible.append(f"{name} {delta:+.4g} {unit}")
    return implausible
