"""A periodic pointing error in one axis's motor steps: a gear's or a drive screw's error, which
repeats with every turn of a worm or a spindle.

A rigid-body model cannot describe it, and over the sky it looks like noise: the rows of one
day pass through many periods. Against the steps of the axis it is a sinusoid. The
generalised Lomb-Scargle periodogram (Zechmeister & Kürster 2009: a least-squares fit of
``a cos(w s) + b sin(w s) + c`` at each frequency ``w``, for unevenly spaced ``s``; scipy's
:func:`~scipy.signal.lombscargle` with a floating mean) finds its period in the coarse model's
pointing residuals (:func:`~.gp.pointing_residuals_mrad`, each component on its own).

The searched band (frequencies in cycles per step, the axis's training steps spanning ``R``
steps, ``n`` rows): from :data:`MIN_PERIODS` periods over the span (``MIN_PERIODS / R``) to the
rows' mean Nyquist frequency (``n / (2 R)``), on a grid :data:`OVERSAMPLING` times finer than the
band's resolution ``1 / R``, the best peak refined on a grid :data:`REFINE` times finer again.
Fewer periods over the span are a trend along the axis, which the rigid body and the GP's sun
kernel describe, not an error that repeats with every turn (on the shared PAINT heliostat BE36
a "period" of 22,500 steps, 2.8 over its rows, made the GP's test error worse).

Significance: the normalised power ``p`` (the share of the residuals' variance the sinusoid
explains) of pure noise exceeds ``p0`` at one frequency with probability ``(1 - p0)^((n-3)/2)``
(Zechmeister & Kürster, eq. 24); anywhere below ``f_max``, Baluev's (2008, eq. 14; as
VanderPlas 2018, sec. 7.4 writes it) bound ``1 - (1 - (1 - p0)^((n-3)/2)) exp(-tau)`` with
``tau = gamma(n - 1) W (1 - p0)^((n-4)/2) sqrt((n - 1) p0 / 2)``, ``W = f_max sqrt(4 pi
var(s))`` the band's effective width and ``gamma(N) = sqrt(2 / N) Gamma(N/2) / Gamma((N-1)/2)``.
Both axes and both residual components are searched (4 searches, Bonferroni). A period counts
below :data:`FALSE_ALARM`. On pure noise (tests/test_periodic.py) the bound holds: noise
reaches a stated 0.1 and 0.01 less often than that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lombscargle

__all__ = ["FALSE_ALARM", "MIN_PERIODS", "OVERSAMPLING", "REFINE", "PeriodicError",
           "find_periodic_error"]

#: A periodic error counts when noise alone would give such a peak less often than this.
FALSE_ALARM = 1e-3

#: Periods a repeating error shows at least over the span of the training rows' steps.
MIN_PERIODS = 5

#: Grid points per resolution element ``1 / R`` of the band.
OVERSAMPLING = 5

#: The best peak's frequency is refined on a grid this many times finer.
REFINE = 20

_SEARCHES = 4   # two axes x two residual components


@dataclass(frozen=True)
class PeriodicError:
    """The strongest periodic error found.

    axis : 1 or 2, the axis whose motor steps it repeats in.
    period_steps : its period [steps].
    power : normalised periodogram power at the period (0-1: the share of that residual
        component's variance the sinusoid explains).
    false_alarm : the probability that noise alone gives a peak this high somewhere in the
        searched band (module docstring).
    """

    axis: int
    period_steps: float
    power: float
    false_alarm: float


def _band(steps: np.ndarray) -> np.ndarray | None:
    """Frequencies [cycles per step] searched over ``steps`` (module docstring), or None when
    the rows are too few for :data:`MIN_PERIODS` periods below their mean Nyquist frequency."""
    span = float(np.ptp(steps)) if len(steps) else 0.0
    if not span > 0:
        return None
    f_min, f_max = MIN_PERIODS / span, len(np.unique(steps)) / (2.0 * span)
    if f_max <= f_min:
        return None
    return np.arange(f_min, f_max, 1.0 / (OVERSAMPLING * span))


def _power(steps: np.ndarray, values: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    return lombscargle(steps, values, 2.0 * np.pi * freqs, normalize=True, floating_mean=True)


def _false_alarm(power: float, n: int, steps: np.ndarray, f_max: float) -> float:
    """Baluev's (2008) bound on the probability that noise alone gives a normalised power
    ``power`` somewhere below ``f_max`` [cycles per step] for ``n`` rows at ``steps``, times the
    searches (module docstring)."""
    z = min(max(power, 0.0), 1.0 - 1e-15)
    n_null, n_model = n - 1, n - 3      # parameters: the mean; the mean and a sinusoid
    single = 1.0 - (1.0 - z) ** (0.5 * n_model)
    gamma = math.sqrt(2.0 / n_null) * math.exp(math.lgamma(n_null / 2.0)
                                               - math.lgamma((n_null - 1) / 2.0))
    width = f_max * math.sqrt(4.0 * math.pi * float(np.var(steps)))
    tau = gamma * width * (1.0 - z) ** (0.5 * (n_model - 1)) * math.sqrt(0.5 * n_null * z)
    return min(1.0, _SEARCHES * (1.0 - single * math.exp(-tau)))


def find_periodic_error(steps: np.ndarray, residuals_mrad: np.ndarray,
                        false_alarm: float = FALSE_ALARM) -> PeriodicError | None:
    """The strongest periodic error of ``residuals_mrad`` (n, 2) [mrad] in the motor steps
    ``steps`` (n, 2) (axis 1, axis 2) of the same rows, if its false-alarm probability is below
    ``false_alarm``; None otherwise, or with fewer than 10 finite rows."""
    steps = np.asarray(steps, np.float64).reshape(-1, 2)
    y = np.asarray(residuals_mrad, np.float64).reshape(-1, 2)
    ok = np.isfinite(steps).all(1) & np.isfinite(y).all(1)
    steps, y = steps[ok], y[ok]
    n = len(y)
    if n < 10:
        return None
    best = None
    for axis in (1, 2):
        s = steps[:, axis - 1]
        freqs = _band(s)
        if freqs is None or len(freqs) == 0:
            continue
        for component in y.T - y.mean(0)[:, None]:
            if not np.ptp(component) > 0:
                continue
            p = _power(s, component, freqs)
            i = int(np.argmax(p))
            fine = np.linspace(freqs[max(i - 1, 0)], freqs[min(i + 1, len(freqs) - 1)],
                               2 * REFINE + 1)
            pf = _power(s, component, fine)
            j = int(np.argmax(pf))
            found = PeriodicError(axis, float(1.0 / fine[j]), float(pf[j]),
                                  _false_alarm(float(pf[j]), n, s, float(freqs[-1])))
            if best is None or found.false_alarm < best.false_alarm or (
                    found.false_alarm == best.false_alarm and found.power > best.power):
                best = found
    return best if best is not None and best.false_alarm < false_alarm else None
