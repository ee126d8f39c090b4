"""Coarse models that follow a heliostat through its regimes (issue 17, item 4).

A re-mount or a re-homing moves a few parameters of a heliostat for good: its actuator zero
points and small tilts, the parameters :func:`heliocal.pipeline.models.changes.change_parameters`
names (``axis_1_initial_angle_rad``, ``axis_2_initial_angle_rad`` and Stone's tilts alpha, beta
and delta of the kinematic type). Pivots, lever arms, increments and translations stay. Beside
the plain fit of the selected preset, two candidates on the regimes of ``regimes.parquet``:

``offsets``
    One shared geometry (the preset's free parameters) and per regime an offset of the moved
    parameters [rad]; the first regime with its own offsets is the reference (offset 0).
``drift``
    The same, plus per regime a rate of each actuator zero point [rad/year]: the zero point
    moves linearly in time within a regime, around the mean time of the regime's training rows.
    Linear is the lowest-order smooth motion: two parameters per regime, enough for the slow
    creep of an actuator (the simulator's drift is linear; the Jülich log's drifting heliostats
    move by a few mrad over months), where a spline or a polynomial would follow noise. A
    re-homing starts a new regime and so resets it. The line is trusted only over the time its
    training rows span: a row before the first or after the last training row of its regime
    (a later regime without rows of its own, the latest parameters ``aim`` uses) gets the
    zero point at that end (:data:`DRIFT_EXTRAPOLATION_DAYS`, measured forward in time): a rate
    fitted on a short span extrapolates badly.

Both are fitted by :func:`scipy.optimize.least_squares` with the plain fit's objective
(:mod:`heliocal.pipeline.models.coarse`: residuals ``1000 (n_pred - n_meas)`` [mrad] of every
training row, now at the row's own parameter vector; the exact Jacobian of
:mod:`heliocal.pipeline.physics.jacobian`; the same loss and ``f_scale``) and Gaussian priors:
the shared parameters toward the plain fit with the preset's sigmas
(:func:`~heliocal.pipeline.models.coarse.prior_sigma`; the data's curvature is 10^5 to 10^9
times larger, so this only holds the directions the data do not determine where the plain fit
put them), offsets toward 0 with :data:`OFFSET_PRIOR_SIGMA_RAD`, rates toward 0 with
:data:`DRIFT_PRIOR_SIGMA_RAD_PER_YEAR`. The start is the plain fit with zero offsets and rates.

A regime with fewer than :data:`MIN_REGIME_ROWS` training rows (outside episodes) gets no
offsets of its own: its rows are predicted with the offsets of the fitted regime before it (the
first fitted regime's if none is before) and are left out of the fit.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
import torch
from scipy.optimize import least_squares

from ..errors import check_choice
from ..physics.jacobian import forward_state, residual_and_jacobian
from ..physics.kinematics import forward_kinematics
from ..physics.metrics import measured_normal
from ..physics.parameters import PARAMETER_INDEX, PARAMETER_NAMES, HeliostatSpec
from .changes import change_parameters
from .coarse import MeasurementBatch, metrics_frame, prior_sigma

__all__ = [
    "REGIME_MODELS",
    "DRIFT_PARAMETERS",
    "MIN_REGIME_ROWS",
    "MIN_VALIDATION_DAYS",
    "OFFSET_PRIOR_SIGMA_RAD",
    "DRIFT_PRIOR_SIGMA_RAD_PER_YEAR",
    "RegimeFit",
    "base_preset",
    "fit_regime_model",
    "predict_rows",
    "predict_parameters",
    "table_row_parameters",
    "seconds_utc",
]

#: The candidates, in the order they are fitted.
REGIME_MODELS = ("offsets", "drift")

#: Parameters that drift (``drift``): the actuator zero points.
DRIFT_PARAMETERS = ("axis_1_initial_angle_rad", "axis_2_initial_angle_rad")

#: Training rows a regime needs for offsets of its own: two per moved parameter (each row
#: measures two independent components of the normal, so 10 rows give 20 equations for 5
#: offsets plus, with ``drift``, 2 rates).
MIN_REGIME_ROWS = 10

#: Distinct UTC days the validation rows (outside episodes) must cover for a candidate to be
#: judged: the rows of one day share their sun positions and that day's misfit, so one or two
#: days are one or two samples, not a validation of a model that changes with time (on the
#: Jülich log's time split AK32's 20 validation rows are one burst of 26 minutes: a candidate
#: 45 % better there was 80 % worse on the month of test rows).
MIN_VALIDATION_DAYS = 3

#: Prior sigma of an offset [rad]: 10 mrad, several times the steps of re-mounts seen (simulated
#: 1-4 mrad; the Jülich data's breaks 0.9-5.7 mrad), so it does not bias them, but holds the
#: offsets of a regime whose few rows cannot determine them all.
OFFSET_PRIOR_SIGMA_RAD = 0.01

#: Prior sigma of a drift rate [rad/year]: 10 mrad/year, above the drifts seen (1-3 mrad/year).
DRIFT_PRIOR_SIGMA_RAD_PER_YEAR = 0.01

#: How far [days] a regime's drift line continues past its first and last training row before it
#: is held: 0, hold at the end value. Measured forward in time by
#: ``benchmarks/drift_extrapolation.py`` (docs/regimes.md, "Past the last row"): continuing 90
#: days had the lowest mean on 16 heliostats' time-split test rows (0.868 against 0.915 mrad for
#: hold), a difference small against their spread, while through the whole fit-coarse it made the
#: sample's BE36 worse by 14 % on its kNN test rows; hold never extrapolates and is kept.
DRIFT_EXTRAPOLATION_DAYS = 0.0

_YEAR_S = 365.25 * 86400.0
_DAY_S = 86400.0


def drift_time_s(seconds, first_s, last_s):
    """The time [s since 1970, UTC] a drift line is evaluated at for rows at ``seconds``: their
    own within the regime's training rows (``first_s`` .. ``last_s``) widened by
    :data:`DRIFT_EXTRAPOLATION_DAYS`, else that bound."""
    bound = DRIFT_EXTRAPOLATION_DAYS * _DAY_S
    return np.clip(seconds, np.asarray(first_s) - bound, np.asarray(last_s) + bound)


def base_preset(model: str) -> str:
    """The preset of a coarse model's geometry: ``static-14`` for ``static-14+offsets``."""
    return model.split("+", 1)[0]


def seconds_utc(times) -> np.ndarray:
    """UTC times (anything pandas reads) as float seconds since 1970; NaN for missing (the
    integer count of the times' unit divided by its count per second, as pandas'
    ``total_seconds``)."""
    from .regimes import utc_values

    t = utc_values(times if isinstance(times, (pd.Series, np.ndarray))
                   else pd.Series(np.asarray(times)))
    per_second = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}[np.datetime_data(t.dtype)[0]]
    return np.where(np.isnat(t), np.nan, t.view(np.int64) / per_second)


@dataclass
class RegimeFit:
    """A fitted regime-aware model of one heliostat (module docstring).

    Attributes
    ----------
    model : ``offsets`` or ``drift``.
    preset : the preset of the shared geometry.
    base : (28,) the reference regime's parameters (the shared geometry).
    moved, drifting : names of the parameters with offsets and with rates.
    fitted : (F,) regime numbers with their own offsets, ascending.
    offsets : (F, len(moved)) [rad] (row 0 is zero: the reference).
    rates : (F, len(drifting)) [rad/year].
    reference_s : (F,) drift reference time per fitted regime [s since 1970, UTC].
    span_s : (F, 2) first and last training row's time per fitted regime [s]: the drift is
        held outside (:data:`DRIFT_EXTRAPOLATION_DAYS` beyond it).
    n_train : (F,) training rows of each fitted regime.
    condition_number : of the data Jacobian at the solution, columns scaled by the prior sigmas.
    """

    model: str
    preset: str
    base: torch.Tensor
    moved: tuple[str, ...]
    drifting: tuple[str, ...]
    fitted: np.ndarray
    offsets: np.ndarray
    rates: np.ndarray
    reference_s: np.ndarray
    span_s: np.ndarray
    n_train: np.ndarray
    iterations: int
    cost: float
    status: str
    condition_number: float
    wall_time_s: float

    @property
    def name(self) -> str:
        """The model's name in coarse_params and coarse_predictions: ``<preset>+<model>``."""
        return f"{self.preset}+{self.model}"   # base_preset() inverts it

    def source(self, regime) -> np.ndarray:
        """Index into :attr:`fitted` of the offsets each regime number uses."""
        k = np.searchsorted(self.fitted, np.asarray(regime, np.int64), side="right") - 1
        return np.maximum(k, 0)

    def row_parameters(self, regime, times) -> torch.Tensor:
        """Parameters (N, 28) of rows in regimes ``regime`` (N,) at UTC ``times`` (N,); a row
        without a time is taken at its regime's reference time."""
        return _row_parameters(self.base, self.moved, self.drifting, self.offsets, self.rates,
                               self.reference_s, self.span_s, self.source(regime),
                               seconds_utc(times))


def _row_parameters(base, moved, drifting, offsets, rates, reference_s, span_s, k, seconds):
    # numpy: a few small index operations per heliostat, where torch's per-call cost dominated
    p = np.repeat(base.to(torch.float64).numpy()[None], len(k), axis=0)
    p[:, [PARAMETER_INDEX[n] for n in moved]] += offsets[k]
    if drifting:
        held = drift_time_s(seconds, span_s[k, 0], span_s[k, 1])
        years = np.nan_to_num((held - reference_s[k]) / _YEAR_S)
        p[:, [PARAMETER_INDEX[n] for n in drifting]] += rates[k] * years[:, None]
    return torch.from_numpy(p)


def predict_rows(fit: RegimeFit, spec: HeliostatSpec, data: MeasurementBatch, regime,
                 times) -> pd.DataFrame:
    """coarse_predictions' metric columns of every row of ``data`` (each at its own parameters)."""
    return predict_parameters(fit.row_parameters(regime, times), spec, data)


@dataclass
class RegimeLayout:
    """One heliostat's candidate problem (:func:`regime_layout`): which regimes get offsets,
    which parameters move, and per fitted row (training rows of those regimes, ``use``) its
    index ``k`` into ``fitted``, its time and its years from its regime's reference time."""

    fitted: np.ndarray        # (F,) regime numbers with their own offsets
    moved: tuple[str, ...]
    drifting: tuple[str, ...]
    free_idx: np.ndarray      # (P,) the shared geometry's free parameters
    use: np.ndarray           # (N,) bool: the rows fitted
    k: np.ndarray             # (n,) index into fitted of each fitted row
    seconds: np.ndarray       # (n,) [s since 1970, UTC]
    reference_s: np.ndarray   # (F,)
    span_s: np.ndarray        # (F, 2)
    years: np.ndarray         # (n,) from the row's regime's reference time
    n_train: np.ndarray       # (F,)


def regime_layout(spec: HeliostatSpec, free, regime, times, train,
                  model: str) -> RegimeLayout | None:
    """The layout of a candidate (arguments as :func:`fit_regime_model`); None when fewer than
    two regimes have :data:`MIN_REGIME_ROWS` training rows."""
    regime = np.asarray(regime, np.int64)
    train = np.asarray(train, bool)
    numbers, counts = np.unique(regime[train], return_counts=True)
    fitted = numbers[counts >= MIN_REGIME_ROWS]
    if len(fitted) < 2:
        return None
    use = train & np.isin(regime, fitted)
    k = np.maximum(np.searchsorted(fitted, regime, side="right") - 1, 0)[use]
    sec = seconds_utc(times)[use]
    n_f = len(fitted)
    reference_s = np.array([np.nanmean(sec[k == f]) if np.isfinite(sec[k == f]).any() else 0.0
                            for f in range(n_f)])
    span_s = np.array([[np.nanmin(sec[k == f]), np.nanmax(sec[k == f])]
                       if np.isfinite(sec[k == f]).any() else [0.0, 0.0] for f in range(n_f)])
    return RegimeLayout(fitted, tuple(change_parameters(spec.kinematic_type)),
                        DRIFT_PARAMETERS if model == "drift" else (),
                        np.flatnonzero(np.asarray(free, bool)), use, k, sec, reference_s, span_s,
                        np.nan_to_num((sec - reference_s[k]) / _YEAR_S),
                        np.array([int((k == f).sum()) for f in range(n_f)]))


def prior_rows(base: torch.Tensor, free_idx, n_f: int, n_off: int, n_rate: int,
               prior_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(mean, sigma) of the priors of a candidate's variables: the shared free parameters (at
    the plain fit, :func:`~heliocal.pipeline.models.coarse.prior_sigma`), then ``(n_f - 1) *
    n_off`` offsets and ``n_f * n_rate`` rates (at 0; module docstring)."""
    sigma = np.concatenate([prior_sigma(base)[free_idx],
                            np.full((n_f - 1) * n_off, OFFSET_PRIOR_SIGMA_RAD),
                            np.full(n_f * n_rate, DRIFT_PRIOR_SIGMA_RAD_PER_YEAR)])
    mean = np.concatenate([base[torch.as_tensor(free_idx)].numpy(),
                           np.zeros(len(sigma) - len(free_idx))])
    return mean, sigma / np.sqrt(prior_weight)


def fit_regime_model(spec: HeliostatSpec, preset: str, params: torch.Tensor, free,
                     data: MeasurementBatch, regime: Sequence[int], times, train, model: str, *,
                     loss: str = "soft_l1", f_scale_mrad: float = 1.0, max_nfev: int = 100,
                     tolerance: float = 1e-6, start: "RegimeFit | None" = None,
                     prior_weight: float = 1.0) -> RegimeFit | None:
    """Fit a regime-aware candidate on one heliostat's training rows.

    Parameters
    ----------
    spec : the heliostat.
    preset, params, free : the plain fit's preset, parameters (28,) and free mask (28,): the
        shared geometry's free parameters and the start.
    data : all its rows; regime : (N,) regime number of each row (``regime_of_rows``);
        times : (N,) UTC times; train : (N,) bool, the rows to fit (training rows outside
        episodes).
    model : one of :data:`REGIME_MODELS`.
    loss, f_scale_mrad : the plain fit's (``fit-coarse``'s options).
    max_nfev, tolerance : scipy's limit and its xtol = ftol = gtol (1e-6: a candidate is judged
        by its validation error to a few per cent; 1e-8 moved a simulated two-step heliostat's
        validation error by less than 1e-4 mrad and took half as long again).
    prior_weight : multiplier of every prior's curvature (1: the sigmas of the module
        docstring; a tiny value leaves the data alone to decide, as in the noiseless tests).
    start : a fit of the same rows (``offsets`` for ``drift``) to start from instead of the
        plain fit (the priors stay those of the plain fit).

    Returns
    -------
    The fit, or ``None`` when fewer than two regimes have :data:`MIN_REGIME_ROWS` training rows
    (nothing to offset: the plain fit is the model of one regime).
    """
    check_choice(model, "model", "fit_regime_model", REGIME_MODELS)
    t0 = time.perf_counter()
    lay = regime_layout(spec, free, regime, times, train, model)
    if lay is None:
        return None
    fitted, moved, drifting, free_idx = lay.fitted, lay.moved, lay.drifting, lay.free_idx
    moved_idx = [PARAMETER_INDEX[n] for n in moved]
    drift_idx = [PARAMETER_INDEX[n] for n in drifting]
    k, sec, reference_s, span_s, years = lay.k, lay.seconds, lay.reference_s, lay.span_s, lay.years
    sub = data.subset(lay.use)
    steps, sun, focal = sub.steps.unsqueeze(1), sub.sun.unsqueeze(1), sub.focal_spot.unsqueeze(1)
    n, n_free, n_off, n_rate = len(sub), len(free_idx), len(moved), len(drifting)
    n_f = len(fitted)
    base = params.to(torch.float64).clone()
    onehot = np.eye(n_f)[k]                                         # (n, F)

    def unpack(x):
        shared = base.clone()
        shared[torch.as_tensor(free_idx)] = torch.as_tensor(x[:n_free])
        offsets = np.vstack([np.zeros(n_off), x[n_free:n_free + (n_f - 1) * n_off].reshape(-1, n_off)])
        rates = x[n_free + (n_f - 1) * n_off:].reshape(n_f, n_rate)
        return shared, offsets, rates

    def rows(x):
        shared, offsets, rates = unpack(x)
        return _row_parameters(shared, moved, drifting, offsets, rates, reference_s, span_s, k,
                               sec)

    mean, scale = prior_rows(base, free_idx, n_f, n_off, n_rate, prior_weight)
    states: dict = {}

    def fun(x):
        with torch.no_grad():
            state = forward_state(rows(x), spec, steps)
            meas = measured_normal(sun, state[2], focal)
            r = torch.nan_to_num(1000.0 * (state[1] - meas).reshape(-1), nan=1e4).numpy()
        states.clear()
        states[x.tobytes()] = state
        return np.concatenate([r, (x - mean) / scale])

    def jac(x):
        with torch.no_grad():
            _, j28 = residual_and_jacobian(rows(x), spec, steps, sun, focal,
                                           state=states.get(x.tobytes()))
        j28 = torch.nan_to_num(j28[:, 0], nan=0.0, posinf=0.0, neginf=0.0).numpy()  # (n, 3, 28)
        blocks = [j28[:, :, free_idx]]
        if n_f > 1:   # offsets of the regimes after the reference: columns (regime, parameter)
            blocks.append((onehot[:, None, 1:, None] * j28[:, :, None, moved_idx]).reshape(n, 3, -1))
        if n_rate:
            w = onehot * years[:, None]
            blocks.append((w[:, None, :, None] * j28[:, :, None, drift_idx]).reshape(n, 3, -1))
        return np.vstack([np.concatenate(blocks, axis=2).reshape(3 * n, -1), np.diag(1.0 / scale)])

    x0 = mean.copy()
    if start is not None and np.array_equal(start.fitted, fitted):
        x0[:n_free] = start.base[torch.as_tensor(free_idx)].numpy()
        x0[n_free:n_free + (n_f - 1) * n_off] = start.offsets[1:].reshape(-1)
    method = "lm" if loss == "linear" else "trf"
    kwargs = dict(jac=jac, method=method, x_scale=scale, max_nfev=max_nfev, xtol=tolerance,
                  ftol=tolerance, gtol=tolerance)
    if method == "trf":
        kwargs.update(loss=loss, f_scale=f_scale_mrad)
    res = least_squares(fun, x0, **kwargs)
    shared, offsets, rates = unpack(res.x)
    n_train = lay.n_train
    js = np.asarray(res.jac)[:3 * n] * scale   # the data rows, columns in prior-sigma units
    ev = np.linalg.eigvalsh(js.T @ js)
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
    return RegimeFit(model, preset, shared.detach(), moved, drifting, fitted, offsets, rates,
                     reference_s, span_s, n_train, int(res.njev or res.nfev), float(res.cost),
                     str(res.message), cond, time.perf_counter() - t0)


def table_row_parameters(params: torch.Tensor, table: pd.DataFrame, regimes: pd.DataFrame,
                         timestamps) -> torch.Tensor:
    """Per-row parameters (N, 28) of a regime-aware model from the artifacts, as
    :meth:`RegimeFit.row_parameters` gives them at fit time.

    Parameters
    ----------
    params : (28,) the model's latest regime's parameters (coarse_params' ``fitted``); the
        parameters without offsets are the shared geometry.
    table : the model's regime_params.parquet rows (one heliostat, one model).
    regimes : the heliostat's regimes.parquet rows (which regime each time is in).
    timestamps : (N,) UTC times of the rows; a regime the table does not list takes the latest.
    """
    from .regimes import regime_of_rows

    hid = str(table["heliostat_id"].iloc[0])
    times = pd.Series(np.asarray(timestamps))
    regime = regime_of_rows(regimes, hid, times)["regime"].to_numpy()
    latest = int(table.loc[table["latest"].astype(bool), "regime"].max()
                 if table["latest"].any() else table["regime"].max())
    seconds = seconds_utc(times)
    out = params.to(torch.float64).expand(len(regime), len(PARAMETER_NAMES)).clone()
    t = table.drop_duplicates(["parameter", "regime"])      # per parameter, a regime's first row
    names, numbers = t["parameter"].to_numpy(object), t["regime"].to_numpy(np.int64)
    value, rate = t["value_rad"].to_numpy(np.float64), t["drift_rad_per_year"].to_numpy(np.float64)
    first, last, reference = (seconds_utc(t[c]) for c in ("drift_from", "drift_to",
                                                          "drift_reference"))
    for name in pd.unique(names):
        mine = np.flatnonzero(names == name)
        at = dict(zip(numbers[mine].tolist(), mine.tolist()))
        k = np.array([at.get(r, at[latest]) for r in regime.tolist()], dtype=np.int64)
        held = drift_time_s(seconds, first[k], last[k])
        years = np.nan_to_num((held - reference[k]) / _YEAR_S)
        out[:, PARAMETER_INDEX[name]] = torch.as_tensor(value[k] + rate[k] * years)
    return out


def predict_parameters(params: torch.Tensor, spec: HeliostatSpec,
                       data: MeasurementBatch) -> pd.DataFrame:
    """coarse_predictions' metric columns of every row of ``data`` at its own parameters
    (N, 28)."""
    with torch.no_grad():
        normal, position = forward_kinematics(params, spec, data.steps.unsqueeze(1))
    return metrics_frame(data, normal[:, 0], position[:, 0])
