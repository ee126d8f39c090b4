"""What the field teaches each heliostat: an empirical-Bayes prior of the coarse parameters.

Heliostats of one kinematic type, actuator type and geometry source (a properties file, or
the default geometry ingest gives a heliostat without one) are built and mounted alike, so the
fits of the well-determined ones say where a new heliostat's parameters lie. Per group and
preset, and per parameter, the *deviation* of a fit from the heliostat's nominal value
(:func:`deviation`: angles wrapped to (-pi, pi] [rad], translations and lengths [m], increments
relative to the nominal [1], the units of :data:`~.coarse.PRIOR_SIGMA`) is summarised by a
robust location and scale:

* well-determined: heliostats whose fit determines the parameter from its data alone, at the
  fit's own noise (:func:`informs`: the data-only standard error at the fit's RMS residual is
  below half the default prior sigma; the fit's ``determined`` flag states the same for 1 mrad of
  noise, which on data measured to 0.08 mrad leaves out parameters the data pin to 5 % of that
  sigma);
  a parameter gets a field prior only from at least :data:`MIN_HELIOSTATS` of them, else it
  keeps the default prior (:data:`~.coarse.PRIOR_SIGMA` around the nominal value);
* location: the median of their deviations; scale: 1.4826 times the median absolute deviation
  (MAD). Both ignore a minority of heliostats with a wrong geometry (zero points off by
  radians), which would shift a mean and widen a standard deviation;
* the spread of fitted values is the field's spread plus the fits' own noise. From fits under
  the default (weak) prior, which are close to maximum likelihood, the field's variance is
  ``tau^2 = scale^2 - median(std_error^2)``; from fits under a field prior (posterior means,
  shrunk toward it) it is ``scale^2 + median(std_error^2)`` (the EM update of a normal
  hierarchical model). At least :data:`SCALE_FLOOR`;
* the prior sigma a heliostat gets adds the uncertainty of the median itself:
  ``sigma^2 = tau^2 + (pi / 2) scale^2 / n``;
* the measurements' noise ``s``: the median over the sample's fits of their RMS data residual
  per component [mrad]. A fit's data rows are unweighted mrad, so its prior rows must be
  ``(p - mean) / (sigma / s)`` for the MAP to be the Gaussian posterior (data rows over ``s``,
  the common factor taken out). Stated against 1 mrad, as the weak default prior is, a field
  prior would weigh ``(1 mrad / s)^2`` times too much where the noise is below 1 mrad (on a
  simulated field with ``s`` near 0.15 mrad, about 40 times), and pull even heliostats with
  hundreds of rows toward the field's typical geometry. The field's median is where each fit
  starts: :mod:`.prior_noise` re-weighs the prior against the heliostat's own noise.

**Leave-out.** A heliostat's own fit never enters its own prior: the heliostats whose fits
estimate the prior (the group's *sample*) are cut into ``K = min(n, MAX_FOLDS)`` folds by the
CRC-32 of their ids (with at most :data:`MAX_FOLDS` heliostats this is leave-one-out), and a
heliostat of fold ``f`` gets the prior of the other folds. Heliostats outside the sample get the
prior of the whole sample (their fits are not in it). ``field_prior.parquet`` holds the prior of
the whole sample.

**Spatial** (``field+spatial``): neighbours share foundations and mounting crews. The prior mean
of a parameter becomes the median deviation of the :data:`NEIGHBOURS` nearest well-determined
heliostats (east/north, outside the heliostat's fold), with the scale of the deviations from
those local medians, but only for parameters where that scale is at least
:data:`SPATIAL_GAIN` smaller than the field's (so the smoother is kept only where it helps on
the field's own fits).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pandas as pd

from ..physics.parameters import PARAMETER_NAMES
from .coarse import PRIOR_SIGMA, CoarseFit, parameter_kind
from .prior_noise import HeliostatPrior

__all__ = [
    "GEOMETRY_SOURCES",
    "MIN_HELIOSTATS",
    "INFORMED_SHARE",
    "informs",
    "MAX_FOLDS",
    "NEIGHBOURS",
    "SPATIAL_GAIN",
    "SCALE_FLOOR",
    "DEVIATION_UNITS",
    "geometry_source",
    "group_key",
    "deviation",
    "absolute",
    "default_sigma",
    "FitSample",
    "PriorEstimate",
    "estimate_prior",
    "fold_of",
    "GroupPrior",
]

#: Where a heliostat's nominal geometry comes from (heliostats.parquet ``properties_source``).
GEOMETRY_SOURCES = ("properties", "default")

#: Well-determined heliostats (outside a heliostat's own fold) a parameter's field prior needs.
MIN_HELIOSTATS = 8

#: A fit informs the field's prior of a parameter when its data alone, at the fit's own noise,
#: pin the parameter to within this share of the default prior sigma (:func:`informs`), so the
#: fitted value is the data's, not the default prior's.
INFORMED_SHARE = 0.5

#: Folds of the leave-out rule (at most this many heliostats: leave-one-out).
MAX_FOLDS = 20

#: Nearest well-determined heliostats whose median is a parameter's spatial prior mean.
NEIGHBOURS = 8

#: A spatial prior is used for a parameter only if its scale is at most this share of the
#: field's scale.
SPATIAL_GAIN = 0.9

#: Smallest field scale tau per parameter kind, in deviation units (a field of identical
#: heliostats must not pin a new one to a point).
SCALE_FLOOR = {"angle": 1e-4, "translation": 1e-4, "length": 2e-5, "increment": 2e-5}

_KINDS = [parameter_kind(n) for n in PARAMETER_NAMES]
_ANGLE = np.array([k == "angle" for k in _KINDS])
_INCREMENT = np.array([k == "increment" for k in _KINDS])
_FLOOR = np.array([SCALE_FLOOR[k] for k in _KINDS])

#: Unit of each parameter's deviation (field_prior.parquet ``unit``).
DEVIATION_UNITS = {n: {"angle": "rad", "translation": "m", "length": "m",
                       "increment": "1 (relative to nominal)"}[k]
                   for n, k in zip(PARAMETER_NAMES, _KINDS)}


def geometry_source(properties_source) -> str:
    """``default`` for a heliostat whose geometry is ingest's default (heliostats.parquet
    ``properties_source`` starting with ``default``), else ``properties``."""
    return "default" if str(properties_source).startswith("default") else "properties"


def group_key(hrow) -> tuple[str, str, str]:
    """(kinematic_type, actuator_type, geometry source) of a heliostats.parquet row."""
    return (str(hrow["kinematic_type"]), str(hrow["actuator_type"]),
            geometry_source(hrow.get("properties_source", "")))


def _relative(nominal: np.ndarray) -> np.ndarray:
    """|nominal| of the increments (1 where it is 0), 1 for every other parameter."""
    out = np.ones_like(nominal, dtype=np.float64)
    out[..., _INCREMENT] = np.where(nominal[..., _INCREMENT] != 0,
                                    np.abs(nominal[..., _INCREMENT]), 1.0)
    return out


def deviation(fitted, nominal) -> np.ndarray:
    """(..., 28) ``fitted - nominal`` in deviation units: angles wrapped to (-pi, pi] [rad],
    increments relative to the nominal [1], translations and lengths [m]."""
    fitted, nominal = np.asarray(fitted, np.float64), np.asarray(nominal, np.float64)
    d = fitted - nominal
    d[..., _ANGLE] = -np.remainder(-d[..., _ANGLE] + math.pi, 2 * math.pi) + math.pi
    return d / _relative(nominal)


def absolute(nominal, dev) -> np.ndarray:
    """The parameter vector(s) (..., 28) ``nominal`` moved by deviations ``dev``."""
    nominal = np.asarray(nominal, np.float64)
    return nominal + np.asarray(dev, np.float64) * _relative(nominal)


def default_sigma(nominal) -> np.ndarray:
    """:data:`~.coarse.PRIOR_SIGMA` per parameter (28,) [parameter units] (what
    :func:`~.coarse.prior_sigma` gives)."""
    return np.array([PRIOR_SIGMA[k] for k in _KINDS]) * _relative(np.asarray(nominal, float))


def informs(fit: CoarseFit) -> np.ndarray:
    """(28,) bool: the parameters whose value in ``fit`` its data determine, at the fit's own
    noise: free, and a data-only standard error (``data_only_std_error``) below
    :data:`INFORMED_SHARE` of the default prior sigma. A fit without that standard error
    (made elsewhere) gives its ``determined`` flags (the same rule at 1 mrad of noise)."""
    if fit.data_only_std_error is None:
        return fit.free & fit.determined
    with np.errstate(invalid="ignore"):
        below = fit.data_only_std_error < INFORMED_SHARE * default_sigma(fit.nominal.numpy())
    return fit.free & below


@dataclass
class FitSample:
    """The fits of one preset that estimate a group's prior, one row per heliostat.

    Attributes
    ----------
    heliostat_ids : (n,) ids.
    deviations : (n, 28) fitted minus nominal in deviation units (:func:`deviation`).
    std_errors : (n, 28) their standard errors in the same units (NaN where fixed).
    determined : (n, 28) bool: free, and determined by the heliostat's data.
    positions : (n, 2) east, north [m].
    noise_mrad : (n,) each fit's RMS data residual per component [mrad] (NaN: unknown).
    """

    heliostat_ids: np.ndarray
    deviations: np.ndarray
    std_errors: np.ndarray
    determined: np.ndarray
    positions: np.ndarray
    noise_mrad: np.ndarray | None = None

    def __post_init__(self):
        if self.noise_mrad is None:
            self.noise_mrad = np.full(len(self.deviations), np.nan)

    @classmethod
    def of(cls, ids: Sequence[str], fits: Sequence[CoarseFit], positions) -> "FitSample":
        """From one preset's fits (:class:`~.coarse.CoarseFit`) of heliostats ``ids``."""
        if not len(fits):
            empty = np.zeros((0, len(PARAMETER_NAMES)))
            return cls(np.array([], dtype=object), empty, empty, empty.astype(bool),
                       np.zeros((0, 2)), np.zeros(0))
        fitted = np.stack([f.params.numpy() for f in fits])
        nominal = np.stack([f.nominal.numpy() for f in fits])
        ok = np.isfinite(fitted).all(axis=1)
        return cls(np.asarray(ids, dtype=object), deviation(fitted, nominal),
                   np.stack([f.std_error for f in fits]) / _relative(nominal),
                   np.stack([informs(f) for f in fits]) & ok[:, None],
                   np.asarray(positions, np.float64).reshape(-1, 2),
                   np.array([f.noise_mrad for f in fits], np.float64))


@dataclass
class PriorEstimate:
    """A group's prior for one preset, in deviation units (module docstring).

    Attributes
    ----------
    mean : (28,) the field's typical deviation (0 where not estimated).
    sigma : (28,) the prior sigma a heliostat gets (NaN where not estimated: default prior).
    tau : (28,) the field's spread without the fits' noise (NaN where not estimated).
    n : (28,) well-determined heliostats that estimate it.
    spatial : (28,) bool, the parameter's mean is the neighbours' (``field+spatial``).
    local_mean : (m, 28) with ``spatial``: the prior mean of each queried heliostat.
    noise_mrad : the measurements' noise the prior is weighed against [mrad per residual
        component]: the median of the sample fits' (NaN: unknown, 1 mrad is assumed).
    """

    mean: np.ndarray
    sigma: np.ndarray
    tau: np.ndarray
    n: np.ndarray
    spatial: np.ndarray = field(default_factory=lambda: np.zeros(len(PARAMETER_NAMES), bool))
    local_mean: np.ndarray | None = None
    noise_mrad: float = float("nan")

    @property
    def used(self) -> np.ndarray:
        """(28,) bool: the parameter has a field prior."""
        return np.isfinite(self.sigma)

    def heliostat_prior(self, nominal, k: int | None = None) -> HeliostatPrior | None:
        """(mean (28,), sigma (28,), noise (28,), field (28,)) [parameter units; mrad] for a
        heliostat with ``nominal`` (28,): the field's where estimated (``field``; weighed
        against the field's noise, and by the fit against the heliostat's own,
        :mod:`.prior_noise`), the default prior elsewhere (noise 1 mrad, the scale the default
        prior is stated in); ``k``: its row of ``local_mean``. None when no parameter has a
        field prior. With the field's noise unknown (1 mrad assumed) ``field`` is None."""
        if not self.used.any():
            return None
        mean = self.mean if self.local_mean is None or k is None else self.local_mean[k]
        nominal = np.asarray(nominal, np.float64)
        sigma = np.where(self.used, np.nan_to_num(self.sigma) * _relative(nominal),
                         default_sigma(nominal))
        known = bool(np.isfinite(self.noise_mrad) and self.noise_mrad > 0)
        noise = self.noise_mrad if known else 1.0
        return HeliostatPrior(absolute(nominal, np.where(self.used, mean, 0.0)), sigma,
                              np.where(self.used, noise, 1.0), self.used.copy() if known else None)


def _robust(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of ``values`` (n, p) with NaN for missing: median and 1.4826 MAD."""
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(values, axis=0)
            mad = 1.4826 * np.nanmedian(np.abs(values - med), axis=0)
    return med, mad


def _tau(scale: np.ndarray, noise2: np.ndarray, posterior: bool) -> np.ndarray:
    """The field's spread from the robust scale of fitted values and their median variance."""
    tau2 = scale ** 2 + noise2 if posterior else scale ** 2 - noise2
    return np.sqrt(np.maximum(np.nan_to_num(tau2, nan=0.0), _FLOOR ** 2))


def estimate_prior(sample: FitSample, *, keep: np.ndarray | None = None, posterior: bool = False,
                   min_heliostats: int = MIN_HELIOSTATS) -> PriorEstimate:
    """The prior of one group and preset from the fits of ``sample`` (its rows ``keep``, default
    all); ``posterior``: the fits were made under a field prior (module docstring)."""
    keep = np.ones(len(sample.deviations), bool) if keep is None else np.asarray(keep, bool)
    det = sample.determined & keep[:, None]
    n = det.sum(axis=0)
    dev = np.where(det, sample.deviations, np.nan)
    med, scale = _robust(dev)
    noise2 = _robust(np.where(det, sample.std_errors ** 2, np.nan))[0]
    tau = _tau(scale, noise2, posterior)
    used = n >= min_heliostats
    with np.errstate(all="ignore"):
        sigma = np.sqrt(tau ** 2 + (math.pi / 2) * np.nan_to_num(scale) ** 2 / np.maximum(n, 1))
    noise = sample.noise_mrad[keep]
    noise = float(np.median(noise[np.isfinite(noise)])) if np.isfinite(noise).any() else math.nan
    return PriorEstimate(np.where(used, med, 0.0), np.where(used, sigma, np.nan),
                         np.where(used, tau, np.nan), n, noise_mrad=noise)


def _local_medians(sample: FitSample, candidates: np.ndarray, queries: np.ndarray,
                   query_fold: np.ndarray, fold: np.ndarray, k: int) -> np.ndarray:
    """(m, 28) per query position (m, 2) and parameter: the median deviation of the ``k``
    nearest well-determined heliostats of ``sample`` among ``candidates`` (bool (n,)) outside
    the query's fold (``query_fold`` (m,), -1: none; ``fold`` (n,)); NaN with fewer than k."""
    d2 = ((queries[:, None, :] - sample.positions[None, :, :]) ** 2).sum(-1)   # (m, n)
    allowed = candidates[None, :] & (fold[None, :] != query_fold[:, None])
    order = np.argsort(np.where(allowed, d2, np.inf), axis=1, kind="stable")
    out = np.full((len(queries), len(PARAMETER_NAMES)), np.nan)
    rows = np.arange(len(queries))[:, None]
    for j in range(len(PARAMETER_NAMES)):
        ok = (sample.determined[:, j][order] & allowed[rows, order])           # (m, n) sorted
        take = ok & (np.cumsum(ok, axis=1) <= k)
        if not take.any():
            continue
        vals = np.where(take, sample.deviations[:, j][order], np.nan)
        full = take.sum(axis=1) >= k
        out[full, j] = _robust(vals[full].T)[0]
    return out


def spatial_prior(sample: FitSample, base: PriorEstimate, fold: np.ndarray, *, keep: np.ndarray,
                  queries: np.ndarray, query_fold: np.ndarray, posterior: bool,
                  k: int = NEIGHBOURS) -> PriorEstimate:
    """``base`` (the field prior of the sample's rows ``keep``) with the spatial mean where it
    helps (module docstring): ``local_mean`` for the query positions (m, 2) (each outside its
    ``query_fold``), the gate and the scale judged on the rows ``keep`` themselves, each against
    its neighbours outside its own fold."""
    own = _local_medians(sample, keep, sample.positions[keep], fold[keep], fold, k)
    det = sample.determined[keep] & np.isfinite(own)
    resid = np.where(det, sample.deviations[keep] - own, np.nan)
    _, scale = _robust(resid)
    noise2 = _robust(np.where(det, sample.std_errors[keep] ** 2, np.nan))[0]
    tau = _tau(scale, noise2, posterior)
    n = det.sum(axis=0)
    spatial = base.used & (n >= base.n // 2) & (tau <= SPATIAL_GAIN * base.tau)
    local = _local_medians(sample, keep, queries, query_fold, fold, k)
    local_mean = np.where(spatial[None, :] & np.isfinite(local), local, base.mean[None, :])
    with np.errstate(all="ignore"):
        sigma = np.sqrt(tau ** 2 + (math.pi / 2) * np.nan_to_num(scale) ** 2 / k)
    return PriorEstimate(base.mean, np.where(spatial, sigma, base.sigma),
                         np.where(spatial, tau, base.tau), base.n, spatial, local_mean,
                         base.noise_mrad)


def fold_of(ids: Sequence[str], max_folds: int = MAX_FOLDS) -> np.ndarray:
    """Fold (n,) of each heliostat of a sample: ranked by (CRC-32 of the id, id), rank modulo
    ``min(n, max_folds)`` (with at most ``max_folds`` heliostats each is its own fold)."""
    ids = [str(h) for h in ids]
    order = sorted(range(len(ids)), key=lambda i: (zlib.crc32(ids[i].encode()), ids[i]))
    folds = np.empty(len(ids), dtype=np.int64)
    folds[order] = np.arange(len(ids)) % max(min(len(ids), max_folds), 1)
    return folds


@dataclass
class GroupPrior:
    """The priors of one group and preset: the whole sample's (``whole``, field_prior.parquet)
    and one per fold (``by_fold``), plus the per-heliostat spatial means when asked.

    ``prior_of(hid, nominal)`` is what a heliostat's fit gets.
    """

    whole: PriorEstimate
    by_fold: dict[int, PriorEstimate]
    fold: dict[str, int]                 # sample heliostat -> its fold
    row: dict[str, int] = field(default_factory=dict)   # heliostat -> its row of local_mean

    @classmethod
    def estimate(cls, sample: FitSample, *, posterior: bool, spatial: bool = False,
                 queries: dict[str, np.ndarray] | None = None,
                 min_heliostats: int = MIN_HELIOSTATS) -> "GroupPrior":
        """The whole and per-fold priors of ``sample``; with ``spatial`` the local means of
        every heliostat of ``queries`` (id -> (east, north) [m]; sample members in their fold's
        estimate, the others in the whole one)."""
        folds = fold_of(sample.heliostat_ids)
        fold = {str(h): int(f) for h, f in zip(sample.heliostat_ids, folds)}
        ids = list(queries or {})
        pos = np.array([queries[h] for h in ids], np.float64).reshape(-1, 2)
        qfold = np.array([fold.get(h, -1) for h in ids], np.int64)
        everyone = np.ones(len(folds), bool)

        def one(keep: np.ndarray, which: np.ndarray) -> PriorEstimate:
            base = estimate_prior(sample, keep=keep, posterior=posterior,
                                  min_heliostats=min_heliostats)
            if not spatial or not base.used.any() or not which.any():
                return base
            return spatial_prior(sample, base, folds, keep=keep, queries=pos[which],
                                 query_fold=qfold[which], posterior=posterior)

        outside = qfold == -1
        whole = one(everyone, outside)
        by_fold = {int(f): one(folds != f, qfold == f) for f in np.unique(folds)}
        rows: dict[str, int] = {}
        for f in [-1, *by_fold]:
            for r, h in enumerate(np.array(ids, dtype=object)[qfold == f]):
                rows[str(h)] = r
        return cls(whole, by_fold, fold, rows)

    def estimate_of(self, heliostat_id: str) -> PriorEstimate:
        """The estimate a heliostat's fit gets (its fold's, or the whole sample's)."""
        f = self.fold.get(heliostat_id)
        return self.whole if f is None else self.by_fold[f]

    def prior_of(self, heliostat_id: str, nominal) -> tuple[np.ndarray, np.ndarray] | None:
        """(mean (28,), sigma (28,)) [parameter units] of the heliostat's fit, or None."""
        return self.estimate_of(heliostat_id).heliostat_prior(nominal,
                                                              self.row.get(heliostat_id))

    def table(self) -> pd.DataFrame:
        """The whole sample's prior per parameter (field_prior.parquet's value columns)."""
        w = self.whole
        return pd.DataFrame({
            "parameter_index": np.arange(len(PARAMETER_NAMES)), "parameter": PARAMETER_NAMES,
            "unit": [DEVIATION_UNITS[n] for n in PARAMETER_NAMES],
            "mean": w.mean, "scale": w.sigma, "n_heliostats": w.n.astype(np.int64),
            "noise_mrad": np.where(w.used, w.noise_mrad, np.nan),
            "spatial": w.spatial})
