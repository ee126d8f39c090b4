"""A field prior weighed against each heliostat's own measurement noise.

A fit's data rows are unweighted mrad; a field prior N(mean, sigma^2) enters beside them as the
rows ``(p - mean) / (sigma / s)``. The MAP fit is then the Gaussian posterior (data precision
``J^T J / s^2`` plus prior precision ``1 / sigma^2``) only if ``s`` is the noise per residual
component of *this* heliostat's rows. The field's estimate (:mod:`.field_prior`) gives every
heliostat the field's median noise ``s_f``; a heliostat measured twice as precisely would have
its prior weighed four times too much, and one with hundreds of precise rows pulled toward the
field's typical geometry further than its data allow.

:func:`~.coarse_presets.fit_weighed` therefore solves each heliostat under the prior weighed
with ``s_f``, then estimates the heliostat's own noise from that fit's data residuals and solves
again, warm-started at the first solution, only where the estimate is below ``s_f`` by more than
:data:`NOISE_REFIT_FACTOR` (one iteration; the second solution's residuals are not used again).

Only below: the own noise is ``min(s, s_f)``, so the prior never counts more than under the
field's noise. Residuals far above the field's are rarely a noisier instrument: they are a
heliostat the model or its nominal geometry does not describe (on the shared CSV log AH48,
23-86 mrad test error), which is not drawn from the field's distribution either; a prior
strengthened by its residuals pulled it to the field's typical geometry and its time-split
test error from 39 to 86 mrad. A heliostat more precise than the field is the case the
Gaussian posterior must not over-weigh.

The own noise (:func:`own_noise_mrad`) is the moderated variance of a normal model whose noise
variance has a scaled inverse-chi^2 prior with :data:`NOISE_PRIOR_DOF` degrees of freedom and
scale ``s_f^2`` (the field's median; Smyth 2004's moderated variance)::

    s^2 = (d0 s_f^2 + RSS) / (d0 + dof)

``RSS`` [mrad^2] is the sum of the squared data residuals, each weighed as the fit's loss weighs
it at the solution (``rho'``, :func:`~.fit_diagnostics.loss_weights`: under the default soft-l1
loss with a 1 mrad scale a residual of 0.2 mrad counts 0.98 of its square, one of 5 mrad about
its size, not its square: the robust fit is the weighted least-squares problem with those
weights, and its noise is that problem's), and ``dof`` their effective degrees of freedom
under the prior (data rows minus the trace of their hat matrix,
:func:`~.fit_diagnostics.fit_diagnostics`). A heliostat with a handful of rows keeps about the
field's noise (its few residuals say little), one with hundreds of rows gets its own.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["NOISE_PRIOR_DOF", "NOISE_REFIT_FACTOR", "HeliostatPrior", "noise_estimate",
           "own_noise_mrad", "reweighed"]

#: Degrees of freedom of the field's noise as the prior of a heliostat's own (those of 10
#: measurements of three residual components each): a heliostat's own residuals count half at
#: 30 effective degrees of freedom.
NOISE_PRIOR_DOF = 30.0

#: A heliostat is solved again under its own noise only when that differs from the field's by
#: more than this factor either way (its prior's weight by more than the factor squared, 1.56).
NOISE_REFIT_FACTOR = 1.25


class HeliostatPrior(NamedTuple):
    """A heliostat's prior as :func:`~.coarse.fit_heliostat` takes it (a tuple).

    mean, sigma : (28,) [parameter units].
    noise : (28,) [mrad per residual component] each row is weighed against.
    field : (28,) bool, the entries that are the field's, weighed against the field's noise
        and re-weighed against the heliostat's own (:func:`reweighed`); None: never re-weighed.
    """

    mean: np.ndarray
    sigma: np.ndarray
    noise: np.ndarray
    field: np.ndarray | None = None


def own_noise_mrad(rss_mrad2: float, dof: float, field_noise_mrad: float,
                   prior_dof: float = NOISE_PRIOR_DOF) -> float:
    """The heliostat's noise per residual component [mrad]: ``sqrt((d0 s_f^2 + RSS) / (d0 +
    dof))`` (module docstring); ``s_f`` when the fit gives no residuals (no rows, no Jacobian)."""
    if not (math.isfinite(rss_mrad2) and math.isfinite(dof)) or dof <= 0:
        return float(field_noise_mrad)
    return math.sqrt((prior_dof * field_noise_mrad ** 2 + rss_mrad2) / (prior_dof + dof))


def noise_estimate(prior, fit) -> tuple[float, float] | None:
    """(the field's noise ``s_f``, the heliostat's own noise estimated from ``fit``) [mrad per
    residual component] of a fit under a field prior (``prior`` a :class:`HeliostatPrior` with
    field entries, ``fit`` a :class:`~.coarse.CoarseFit` made under it: its ``data_rss_mrad2``
    and ``data_dof``, :func:`own_noise_mrad`); None for any other prior."""
    if not isinstance(prior, HeliostatPrior) or prior.field is None:
        return None
    field = np.asarray(prior.field, bool)
    if not field.any():
        return None
    s_field = float(np.median(np.asarray(prior.noise, np.float64)[field]))
    return s_field, own_noise_mrad(fit.data_rss_mrad2, fit.data_dof, s_field)


def reweighed(prior, fit, factor: float = NOISE_REFIT_FACTOR) -> HeliostatPrior | None:
    """``prior`` with its field entries weighed against the heliostat's own noise estimated from
    ``fit`` (a :class:`~.coarse.CoarseFit` made under ``prior``: its ``data_rss_mrad2`` and
    ``data_dof``; at most the field's noise, module docstring), or None when it needs no second
    solve: not a field prior, or the own noise within ``factor`` below the field's."""
    estimate = noise_estimate(prior, fit)
    if estimate is None:
        return None
    s_field, s_own = estimate[0], min(estimate[1], estimate[0])
    if not (s_field > 0 and s_own > 0) or s_field / s_own <= factor:
        return None
    return prior._replace(noise=np.where(np.asarray(prior.field, bool), s_own, prior.noise))
