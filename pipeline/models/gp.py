"""The Gaussian-process fine model (``fit-hybrid --mode gp``; the sweep's candidate ``gp``): a
correction of the coarse model's pointing as a function of the sun position, the time and the
env columns, whose prior mean is the coarse model itself (issue 35).

The model
---------
For a measurement the coarse model predicts a mirror normal ``n`` (with its mirror centre); the
measured normal ``m`` is the bisector of the sun and the direction to the measured focal spot
(docs/kinematics.md). Its *pointing residual* is the small angle from ``n`` to ``m`` in the
plane tangent to ``n`` [mrad]::

    r = 1000 ((m - n) . h, (m - n) . v),   h = unit(up x n) (horizontal),  v = n x h,

so ``|r|`` is the coarse model's ``error_mrad`` to first order. Two independent Gaussian
processes with one shared kernel model the two components, ``r ~ GP(0, k(x, x'))``, on the
inputs ``x`` = (sun azimuth [deg], sun elevation [deg], time [days since the first training row],
env columns standardised). Prior mean zero means: where the GP knows nothing, it predicts the
coarse model. The corrected normal is ``unit(n + 1e-3 (g_h h + g_v v))`` for the posterior mean
``g`` times the fade (:mod:`heliocal.pipeline.models.fade`).

Kernels (scikit-learn's, hyperparameters by maximum marginal likelihood on the training rows,
L-BFGS-B with ``restarts`` seeded restarts; the structure with the highest log marginal
likelihood of :attr:`GPConfig.structures` is kept per heliostat). Components, with ``C`` a
signal variance in units of the training residuals' mean square (bounds 1e-4 .. 1e2):

- sun: ``C Matern_5/2(azimuth, elevation)`` with one length per angle in [2, 1000] deg: smooth
  over the sky (a rigid body's misfit is smooth in the sun position); below 2 deg, half the
  training rows' typical spacing, it would follow single rows;
- time: ``C Matern_1/2(time)`` (an Ornstein-Uhlenbeck process) with length in [0.5, 10,000]
  days: a level that wanders and jumps, so it follows drift (long lengths) and episodes and
  days of common misfit (short lengths) alike; the 3/2 form, measured beside it, gave the same
  marginal likelihoods within 1 on the Jülich heliostats;
- env (with ``env`` columns): ``C RBF(env)`` with one length per column in [0.1, 100] std;
- periodic (where :func:`~.periodic.find_periodic_error` finds a periodic error in the training
  residuals against one axis's motor steps, false-alarm probability below 1e-3): ``C
  ExpSineSquared(steps)`` with the periodogram's period held fixed and its length in [1, 20]
  (close to a sinusoid): a gear's or a drive screw's error, which repeats with each turn.
  Over the sky it looks like noise (a day's rows pass through many periods), so neither the sun
  nor the time kernel can follow it; in the steps it extrapolates by its period. ``aim`` solves the steps and the
  correction together (:func:`~.gp_heliostat.gp_aim_steps`);
- noise: ``WhiteKernel`` in [1e-4, 10].

Structures: ``sun`` (sun + noise), ``sun+time`` (additive: a sky pattern plus a level in time),
``sun*time`` (product: a sky pattern that changes over time), each ``+env`` with env columns.
Why these defaults: docs/hybrid.md ("The Gaussian-process correction").

The predictive variance of the correction is kept (:class:`GPPrediction`): the variance of the
latent residual at a row, summed over both components [mrad^2], without the measurement noise,
plus the square of the part of the mean the fade takes away (the expected squared error of the
faded correction about the GP's residual), beside the latent prior variance and the white noise.
``aim``'s expected error reads it through :attr:`GPPrediction.explained_variance_mrad2`: the
GP's prior variance is the part of the coarse model's error level that the correction models,
and at an aim only ``w (2 - w)`` of its reduction to the posterior variance is gained
(:mod:`heliocal.pipeline.stages.aim_budget`; docs/hybrid.md, section "`aim`").
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import pandas as pd
import torch
from sklearn.gaussian_process.kernels import (RBF, ConstantKernel, ExpSineSquared, Matern,
                                              WhiteKernel)

from ..errors import ParameterError, check_int
from .fade import NO_FADE, Fade, epoch_seconds
from .gp_likelihood import OnColumns, Regressor
from .periodic import PeriodicError, find_periodic_error

__all__ = [
    "GP_STRUCTURES",
    "GPConfig",
    "GPInputs",
    "GPCorrection",
    "GPPrediction",
    "pointing_frame",
    "pointing_residuals_mrad",
    "correct_normals",
    "fit_gp_corrections",
    "fit_gp_correction",
    "best_structure",
    "gp_correction",
]

_FUNC = "fit_gp_correction"
_DAY_S = 86400.0

#: Kernel structures of the GP (module docstring).
GP_STRUCTURES = ("sun", "sun+time", "sun*time")


@dataclass(frozen=True)
class GPConfig:
    """Settings of the Gaussian-process correction (``__init__`` only stores them).

    Attributes
    ----------
    structures : kernel structures fitted per heliostat (:data:`GP_STRUCTURES`); the one with the
        highest log marginal likelihood is kept.
    env : ``env_*`` columns (without the prefix) used as inputs.
    restarts : seeded restarts of the marginal-likelihood optimisation (from log-uniform draws
        within the bounds) besides the start at the defaults.
    seed : seed of the restarts and of the subsample.
    max_train_rows : a heliostat with more training rows uses a seeded subsample of this many
        (the fit costs O(n^3) per step).
    time_nu : smoothness of the time kernel's Matern form (0.5: Ornstein-Uhlenbeck; 1.5).
    periodic : look for a periodic error in the motor steps of an axis
        (:func:`~.periodic.find_periodic_error` on the training rows' residuals) and, where one
        is found, add a periodic term in those steps to every structure (module docstring).
    """

    structures: tuple[str, ...] = ("sun", "sun+time")
    env: tuple[str, ...] = ()
    restarts: int = 1
    seed: int = 0
    max_train_rows: int = 600
    time_nu: float = 0.5
    periodic: bool = True

    def validated(self) -> "GPConfig":
        if not self.structures:
            raise ParameterError(f"The 'structures' parameter of {_FUNC} must list at least one "
                                 f"of {', '.join(GP_STRUCTURES)}. Got () instead.")
        for s in self.structures:
            if s not in GP_STRUCTURES:
                raise ParameterError(f"The 'structures' parameter of {_FUNC} must list structures "
                                     f"of {', '.join(GP_STRUCTURES)}. Got {s!r} instead.")
        check_int(self.restarts, "restarts", _FUNC, 0)
        check_int(self.seed, "seed", _FUNC, 0)
        check_int(self.max_train_rows, "max_train_rows", _FUNC, 10)
        if self.time_nu not in (0.5, 1.5, 2.5):
            raise ParameterError(f"The 'time_nu' parameter of {_FUNC} must be one of 0.5, 1.5, "
                                 f"2.5. Got {self.time_nu!r} instead.")
        return self

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["structures"], d["env"] = list(self.structures), list(self.env)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "GPConfig":
        d = dict(d)
        d["structures"] = tuple(d.get("structures", cls.structures))
        d["env"] = tuple(d.get("env", ()))
        return cls(**d)


# ------------------------------------------------------------------------------------------------
# pointing residuals in the plane tangent to the predicted normal
# ------------------------------------------------------------------------------------------------
def pointing_frame(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit vectors ``h = unit(up x n)`` (horizontal) and ``v = n x h`` tangent to the unit
    normals ``normal`` (..., 3)."""
    up = torch.zeros_like(normal)
    up[..., 2] = 1.0
    h = torch.linalg.cross(up, normal)
    h = h / torch.linalg.vector_norm(h, dim=-1, keepdim=True)
    return h, torch.linalg.cross(normal, h)


def pointing_residuals_mrad(predicted: torch.Tensor, measured: torch.Tensor) -> np.ndarray:
    """(N, 2) residuals ``1000 ((m - n) . h, (m - n) . v)`` [mrad] of measured unit normals ``m``
    about predicted ones ``n`` (N, 3) (module docstring)."""
    with torch.no_grad():
        h, v = pointing_frame(predicted)
        d = measured - predicted
        return (1000.0 * torch.stack([(d * h).sum(-1), (d * v).sum(-1)], -1)).numpy()


def correct_normals(predicted: torch.Tensor, correction_mrad) -> torch.Tensor:
    """Unit normals (N, 3) turned from ``predicted`` (N, 3) by ``correction_mrad`` (N, 2) [mrad]
    along (h, v) of :func:`pointing_frame`."""
    g = torch.as_tensor(np.asarray(correction_mrad, np.float64), dtype=predicted.dtype)
    h, v = pointing_frame(predicted)
    n = predicted + 1e-3 * (g[..., :1] * h + g[..., 1:] * v)
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GPInputs:
    """The GP's input encoding: sun azimuth and elevation [deg], time [days since ``t0_s``], the
    env columns standardised and, with a periodic error (``periodic_axis`` 1 or 2, of period
    ``period_steps``), that axis's motor steps [steps]; rows without a time get ``fill_time_s``
    (the training rows' median), missing env values the mean (0 after standardising), missing
    steps ``fill_steps`` (the training rows' median)."""

    t0_s: float
    fill_time_s: float
    env: tuple[str, ...] = ()
    env_mean: tuple[float, ...] = ()
    env_std: tuple[float, ...] = ()
    periodic_axis: int = 0
    period_steps: float = math.nan
    fill_steps: float = math.nan

    @classmethod
    def fit(cls, rows: pd.DataFrame, env: Sequence[str] = (),
            periodic: PeriodicError | None = None) -> "GPInputs":
        """Constants from the training rows (inputs only) and the periodic error found in their
        residuals (:func:`~.periodic.find_periodic_error`; None: no steps input)."""
        t = epoch_seconds(rows["timestamp"]) if "timestamp" in rows else np.array([np.nan])
        t = t[np.isfinite(t)]
        t0, fill = (float(t.min()), float(np.median(t))) if len(t) else (0.0, 0.0)
        means, stds = [], []
        for name in env:
            col = f"env_{name}"
            if col not in rows.columns:
                avail = sorted(c[4:] for c in rows.columns if c.startswith("env_"))
                raise ParameterError(f"The 'env' parameter of {_FUNC} must name env columns of "
                                     f"the measurements ({avail or 'none'}). Got {name!r} instead.")
            v = pd.to_numeric(rows[col], errors="coerce").to_numpy(np.float64)
            v = v[np.isfinite(v)]
            means.append(float(v.mean()) if len(v) else 0.0)
            stds.append(float(v.std()) if len(v) and v.std() > 0 else 1.0)
        if periodic is None:
            return cls(t0, fill, tuple(env), tuple(means), tuple(stds))
        steps = rows[f"axis_{periodic.axis}_steps"].to_numpy(np.float64)
        return cls(t0, fill, tuple(env), tuple(means), tuple(stds), periodic.axis,
                   float(periodic.period_steps), float(np.nanmedian(steps)))

    @property
    def period(self) -> float | None:
        """The periodic error's period [steps], None without one."""
        return float(self.period_steps) if self.periodic_axis else None

    @property
    def n_inputs(self) -> int:
        return 3 + len(self.env) + (1 if self.periodic_axis else 0)

    def encode(self, azimuth_deg, elevation_deg, time_s, env_values=None,
               steps=None) -> np.ndarray:
        """(N, n_inputs) inputs from sun angles [deg], times [s since 1970] (NaN: the fill time),
        raw env values (N, E) (NaN: the mean) and motor steps (N, 2) (axis 1, axis 2; None or
        NaN: the fill steps)."""
        az = np.asarray(azimuth_deg, np.float64).reshape(-1)
        t = np.asarray(time_s, np.float64).reshape(-1) if time_s is not None else np.full(len(az), np.nan)
        t = np.where(np.isfinite(t), t, self.fill_time_s)
        cols = [az, np.asarray(elevation_deg, np.float64).reshape(-1), (t - self.t0_s) / _DAY_S]
        if self.env:
            e = np.asarray(env_values, np.float64).reshape(len(az), len(self.env))
            z = (e - np.asarray(self.env_mean)) / np.asarray(self.env_std)
            cols += list(np.nan_to_num(z, nan=0.0).T)
        if self.periodic_axis:
            s = (np.full(len(az), np.nan) if steps is None else
                 np.asarray(steps, np.float64).reshape(len(az), 2)[:, self.periodic_axis - 1])
            cols.append(np.where(np.isfinite(s), s, self.fill_steps))
        return np.column_stack(cols)

    def encode_rows(self, rows: pd.DataFrame) -> np.ndarray:
        """:meth:`encode` of measurement rows."""
        env = (rows[[f"env_{e}" for e in self.env]].apply(pd.to_numeric, errors="coerce")
               .to_numpy(np.float64) if self.env else None)
        time = epoch_seconds(rows["timestamp"]) if "timestamp" in rows else None
        steps = (rows[["axis_1_steps", "axis_2_steps"]].to_numpy(np.float64)
                 if self.periodic_axis and {"axis_1_steps", "axis_2_steps"} <= set(rows) else None)
        return self.encode(rows["sun_azimuth_deg"].to_numpy(np.float64),
                           rows["sun_elevation_deg"].to_numpy(np.float64), time, env, steps)

    def to_dict(self) -> dict:
        d = {"t0_s": self.t0_s, "fill_time_s": self.fill_time_s, "env": list(self.env),
             "env_mean": list(self.env_mean), "env_std": list(self.env_std)}
        if self.periodic_axis:
            d.update(periodic_axis=self.periodic_axis, period_steps=self.period_steps,
                     fill_steps=self.fill_steps)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "GPInputs":
        return cls(float(d["t0_s"]), float(d["fill_time_s"]), tuple(d.get("env", ())),
                   tuple(float(v) for v in d.get("env_mean", ())),
                   tuple(float(v) for v in d.get("env_std", ())),
                   int(d.get("periodic_axis", 0)), float(d.get("period_steps", math.nan)),
                   float(d.get("fill_steps", math.nan)))


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------
def _kernel(structure: str, n_env: int, time_nu: float = 0.5, period_steps: float | None = None):
    """The kernel of ``structure`` (module docstring) with its bounds and starting values, with
    the periodic term of a period ``period_steps`` [steps] (its input the column after the env
    columns); the last term is the noise."""
    on = OnColumns
    var = lambda: ConstantKernel(0.5, (1e-4, 1e2))  # noqa: E731
    sun = lambda: on(Matern([20.0, 20.0], (2.0, 1e3), nu=2.5), (0, 1))  # noqa: E731
    time = lambda: on(Matern(30.0, (0.5, 1e4), nu=time_nu), (2,))  # noqa: E731
    if structure == "sun":
        k = var() * sun()
    elif structure == "sun+time":
        k = var() * sun() + var() * time()
    elif structure == "sun*time":
        k = var() * sun() * time()
    else:
        raise ParameterError(f"The 'structures' parameter of {_FUNC} must list structures of "
                             f"{', '.join(GP_STRUCTURES)}. Got {structure!r} instead.")
    if n_env:
        k = k + var() * on(RBF([1.0] * n_env, (0.1, 1e2)), tuple(range(3, 3 + n_env)))
    if period_steps is not None:
        k = k + var() * on(ExpSineSquared(2.0, period_steps, (1.0, 20.0), "fixed"), (3 + n_env,))
    return k + WhiteKernel(0.5, (1e-4, 1e1))


def _regressor(kernel, restarts: int, seed: int, optimize: bool = True):
    return Regressor(kernel, optimizer="fmin_l_bfgs_b" if optimize else None,
                     n_restarts_optimizer=restarts if optimize else 0,
                     normalize_y=False, random_state=seed, copy_X_train=False)


# ------------------------------------------------------------------------------------------------
# the fitted model
# ------------------------------------------------------------------------------------------------
@dataclass
class GPPrediction:
    """The GP's correction at some rows.

    Attributes
    ----------
    mean_mrad : (N, 2) faded posterior mean of the pointing residual (h, v) [mrad]: the correction.
    variance_mrad2 : (N,) its expected squared error [mrad^2], both components summed: the
        latent residual's posterior variance (no measurement noise) plus the square of the mean
        the fade takes away, ``latent + |(1 - w) g|^2``.
    fade : (N,) the fade ``w`` applied (1 near the training rows).
    latent_variance_mrad2 : (N,) the latent residual's posterior variance [mrad^2], both
        components summed, without the measurement noise.
    prior_variance_mrad2 : (N,) its prior variance there (the kernel without the white noise)
        [mrad^2], both components summed: what the posterior returns to far from the data.
    noise_mrad2 : the white-noise variance [mrad^2], both components summed: the measurement
        scatter no correction removes.
    """

    mean_mrad: np.ndarray
    variance_mrad2: np.ndarray
    fade: np.ndarray
    latent_variance_mrad2: np.ndarray
    prior_variance_mrad2: np.ndarray
    noise_mrad2: float

    @property
    def explained_variance_mrad2(self) -> np.ndarray:
        """(N,) by how much the faded correction is expected to lower the coarse model's mean
        squared pointing error [mrad^2]: ``w (2 - w) (prior - latent)``.

        Under the GP's prior the residual ``r`` has variance ``prior``; its posterior mean ``g``
        varies with the data by ``prior - latent`` and ``r - g`` (variance ``latent``) is
        independent of it. The coarse model errs by ``r``, the corrected one by
        ``r - w g = (r - g) + (1 - w) g``, of mean square ``latent + (1 - w)^2 (prior -
        latent)``: the difference is the formula. 0 far from the data (``latent = prior`` or
        ``w = 0``), ``prior - latent`` on the training rows."""
        w = self.fade
        return w * (2.0 - w) * np.clip(self.prior_variance_mrad2 - self.latent_variance_mrad2,
                                       0.0, None)


@dataclass
class GPCorrection:
    """A fitted GP correction of one heliostat (everything needed to predict; plain data).

    Attributes
    ----------
    structure : the kernel structure kept (highest log marginal likelihood).
    theta : the kernel's log hyperparameters (scikit-learn's ``kernel_.theta``).
    inputs : the input encoding.
    x_train : (n, 3 + E) encoded training inputs; y_train_mrad : (n, 2) their residuals [mrad].
    y_scale_mrad : the residuals are divided by it for the fit (root mean square of the
        training residuals), so the variance bounds are relative.
    log_marginal_likelihood : of the kept structure (of the scaled residuals).
    kernel : the fitted kernel as text (for people; not read back).
    fade : the fade (:class:`heliocal.pipeline.models.fade.Fade`).
    """

    structure: str
    theta: np.ndarray
    inputs: GPInputs
    x_train: np.ndarray
    y_train_mrad: np.ndarray
    y_scale_mrad: float
    log_marginal_likelihood: float
    kernel: str
    fade: Fade = NO_FADE
    time_nu: float = 0.5

    def __post_init__(self):
        self._gp = None

    @property
    def uses_time(self) -> bool:
        return "time" in self.structure

    def _fitted(self):
        """scikit-learn's regressor at the stored hyperparameters (no optimisation: the same
        posterior as the fit's, from the stored training rows)."""
        if self._gp is None:
            kernel = _kernel(self.structure, len(self.inputs.env), self.time_nu,
                             self.inputs.period)
            kernel = kernel.clone_with_theta(np.asarray(self.theta, np.float64))
            self._gp = _regressor(kernel, 0, 0, optimize=False).fit(
                self.x_train, self.y_train_mrad / self.y_scale_mrad)
        return self._gp

    @property
    def noise_mrad2(self) -> float:
        """Variance of the white-noise term per component [mrad^2]."""
        return float(self._fitted().kernel_.k2.noise_level) * self.y_scale_mrad ** 2

    def predict(self, x: np.ndarray, fade: np.ndarray | None = None) -> GPPrediction:
        """The correction at encoded inputs ``x`` (N, 3 + E), faded by ``fade`` (N,) (None: 1)."""
        gp = self._fitted()
        x = np.asarray(x, np.float64).reshape(-1, self.inputs.n_inputs)
        mean, std = gp.predict(x, return_std=True)
        std = std.reshape(len(x), -1)[:, 0]        # one kernel: the same for both components
        noise = float(gp.kernel_.k2.noise_level)
        scale2 = 2.0 * self.y_scale_mrad ** 2       # both components, back to mrad^2
        latent = np.clip(std ** 2 - noise, 0.0, None) * scale2
        prior = np.clip(gp.kernel_.diag(x) - noise, 0.0, None) * scale2
        mean = np.asarray(mean, np.float64).reshape(len(x), 2) * self.y_scale_mrad
        w = np.ones(len(x)) if fade is None else np.asarray(fade, np.float64).reshape(-1)
        faded = w[:, None] * mean
        var = latent + (((1.0 - w)[:, None] * mean) ** 2).sum(-1)
        return GPPrediction(faded, var, w, latent, prior, noise * scale2)

    def predict_rows(self, rows: pd.DataFrame) -> GPPrediction:
        """The faded correction at measurement rows (a structure without time has an infinite
        time fade length: :func:`fit_gp_correction`)."""
        return self.predict(self.inputs.encode_rows(rows), self.fade.weights_of_rows(rows))

    def with_fade(self, fade: Fade) -> "GPCorrection":
        out = dataclasses.replace(self, fade=fade)
        out._gp = self._gp
        return out

    def to_state(self) -> dict:
        """The tensors of the model file (``hybrid/<mode>/<HID>.pt``)."""
        return {"gp.x_train": torch.as_tensor(self.x_train, dtype=torch.float64),
                "gp.y_train_mrad": torch.as_tensor(self.y_train_mrad, dtype=torch.float64)}

    def to_dict(self) -> dict:
        """The JSON configuration (everything but the training rows' tensors)."""
        return {"structure": self.structure, "theta": [float(t) for t in self.theta],
                "inputs": self.inputs.to_dict(), "y_scale_mrad": float(self.y_scale_mrad),
                "log_marginal_likelihood": float(self.log_marginal_likelihood),
                "kernel": self.kernel, "fade": self.fade.to_dict(), "time_nu": self.time_nu}

    @classmethod
    def from_model(cls, config: Mapping, state: Mapping) -> "GPCorrection":
        """The model from its configuration (:meth:`to_dict`, under ``gp``) and tensors."""
        g = config["gp"]
        return cls(str(g["structure"]), np.asarray(g["theta"], np.float64),
                   GPInputs.from_dict(g["inputs"]),
                   state["gp.x_train"].to(torch.float64).numpy(),
                   state["gp.y_train_mrad"].to(torch.float64).numpy(),
                   float(g["y_scale_mrad"]), float(g["log_marginal_likelihood"]),
                   str(g.get("kernel", "")), Fade.from_dict(g.get("fade") or {}),
                   float(g.get("time_nu", 0.5)))


def fit_gp_corrections(rows: pd.DataFrame, residuals_mrad: np.ndarray,
                       config: GPConfig = GPConfig()) -> dict[str, GPCorrection]:
    """Fit the GP correction of one heliostat on its training rows, every structure of
    ``config.structures``.

    Parameters
    ----------
    rows : the training rows (measurements.parquet columns: sun angles, timestamp, env).
    residuals_mrad : (n, 2) their coarse pointing residuals (:func:`pointing_residuals_mrad`).
    config : :class:`GPConfig`.

    Returns
    -------
    structure -> :class:`GPCorrection`, in the order of ``config.structures``; each fade has no
    length yet (``inf``) and the rows' sun positions and times (the caller chooses lengths).
    """
    config = config.validated()
    y = np.asarray(residuals_mrad, np.float64).reshape(-1, 2)
    if len(rows) != len(y) or len(y) < 2:
        raise ParameterError(f"The 'residuals_mrad' parameter of {_FUNC} must have one (h, v) "
                             f"row per training row (at least 2). Got {len(y)} for {len(rows)} "
                             "rows instead.")
    rows = rows.reset_index(drop=True)
    if len(rows) > config.max_train_rows:
        keep = np.sort(np.random.default_rng(config.seed).choice(
            len(rows), config.max_train_rows, replace=False))
        rows, y = rows.iloc[keep].reset_index(drop=True), y[keep]
    periodic = None
    if config.periodic and {"axis_1_steps", "axis_2_steps"} <= set(rows):
        periodic = find_periodic_error(rows[["axis_1_steps", "axis_2_steps"]].to_numpy(), y)
    inputs = GPInputs.fit(rows, config.env, periodic)
    x = inputs.encode_rows(rows)
    scale = float(np.sqrt(np.mean(y ** 2))) or 1.0
    out = {}
    for structure in dict.fromkeys(config.structures):
        gp = _regressor(_kernel(structure, len(config.env), config.time_nu, inputs.period),
                        config.restarts, config.seed)
        with warnings.catch_warnings():
            # a length at its upper bound is a finding (that input does not matter), not a fault
            warnings.simplefilter("ignore")
            gp.fit(x, y / scale)
        model = GPCorrection(structure, np.asarray(gp.kernel_.theta, np.float64), inputs, x, y,
                             scale, float(gp.log_marginal_likelihood_value_), str(gp.kernel_),
                             Fade.of_rows(rows), config.time_nu)
        model._gp = gp
        out[structure] = model
    return out


def best_structure(models: Mapping[str, GPCorrection]) -> GPCorrection:
    """The model of the highest log marginal likelihood (ties: the first, the simpler)."""
    return max(models.values(), key=lambda m: m.log_marginal_likelihood)


def fit_gp_correction(rows: pd.DataFrame, residuals_mrad: np.ndarray,
                      config: GPConfig = GPConfig()) -> GPCorrection:
    """:func:`fit_gp_corrections` and the structure of the highest log marginal likelihood."""
    return best_structure(fit_gp_corrections(rows, residuals_mrad, config))


def gp_correction(model: GPCorrection | tuple[Mapping, Mapping], rows: pd.DataFrame) -> GPPrediction:
    """The mean correction [mrad] (h, v) and its variance [mrad^2] at measurement rows (sun angles,
    timestamp, env columns), faded: the one call for users of a fitted GP (``model``: a
    :class:`GPCorrection` or a model file's (configuration, tensors))."""
    if not isinstance(model, GPCorrection):
        model = GPCorrection.from_model(*model)
    return model.predict_rows(rows)

