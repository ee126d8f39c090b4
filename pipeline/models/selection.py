"""Which model a heliostat keeps: the coarse model or one of its fine candidates (issue 35).

The sweep trains many fine candidates per heliostat (weight decays x band sets of the hybrid
networks, the Gaussian-process correction, optionally the pre-trained network) and judges them
on 20 validation rows. Two things make that judgement optimistic:

1. **The validation rows are nearer the training rows than the test rows.** The kNN split puts
   the most isolated rows in test (about 11 deg from training on the Jülich heliostats) and the
   next ones in validation (about 6 deg): a candidate that interpolates well and extrapolates
   badly looks best on validation. :func:`validation_weights` gives every validation row half an
   equal share and half a share of the test rows' distances: each test row spreads one unit of
   weight over the ``k`` validation rows whose distances to training are nearest its own. The
   weighted validation mean leans toward the distances the test rows have while keeping about
   twice the effective rows a full matching leaves (6-7 of 20 on the Jülich heliostats, too few
   to judge on). Only the rows' sun positions are used, never a test error.
2. **The best of many candidates on 20 rows is optimistic.** :func:`select` asks a candidate's
   weighted mean gain ``D`` over the coarse model to reach a relative margin that grows with the
   candidate's flexibility (:attr:`SelectionRule.min_improvement_gp` for the GP,
   :attr:`SelectionRule.min_improvement` for the networks), and its studentised gain ``D / s``
   (``s`` from the weighted spread of the paired per-row gains) to exceed what the best of all
   variants compared (every candidate at every fade length) reaches by noise alone: the
   (1 - ``alpha``) quantile of their largest studentised gain when each row's gains get a random
   sign, shared by all variants (Westfall and Young's max-T: it counts the weight-decay path's
   nearly equal neighbours and nested fades as the few candidates they are; a Bonferroni bound
   counts each). Of the candidates that pass, the simplest whose weighted mean is within one
   standard error of the best's weighted mean is kept (the one-standard-error rule): near-ties
   go to the simpler, more regularised model, so a choice does not flip with the last bits of a
   training (docs/hybrid.md, "Training precision").

Simplicity (:attr:`Candidate.complexity`, smaller is simpler) orders the GP without time < with
time < the hybrid networks by decreasing weight decay (octave bands before integer bands at the
same weight decay) < the pre-trained network; a shorter fade (closer to the coarse model) before
a longer one. The settings were chosen on the Jülich heliostats and simulated static and dynamic
ones (docs/hybrid.md, "Selection"; benchmarks/fine_selection.py).

Everything here is plain numpy on per-row errors; the sweep (``stages/selection.py``) computes
them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Sequence

import numpy as np

from ..errors import ParameterError, check_float, check_int

__all__ = [
    "SelectionRule",
    "Candidate",
    "Judgement",
    "validation_weights",
    "row_validation_weights",
    "paired_gain",
    "max_t_threshold",
    "choose_fade",
    "select",
]

_FUNC = "select"

#: :attr:`SelectionRule.one_se_of`'s values.
ONE_SE_OF = ("gain", "error", "difference")


@dataclass(frozen=True)
class SelectionRule:
    """The selection's settings (module docstring).

    Attributes
    ----------
    min_improvement : least relative gain of a network (hybrid, pretrained-nn) over the coarse
        model's weighted validation error: a network interpolates the coarse fit's residual
        structure and gains up to 18 % on static heliostats without gaining on test
        (docs/hybrid.md, "Selection").
    min_improvement_gp : the same for the GP correction, which returns to the coarse model away
        from its data.
    alpha : the studentised gain must exceed the (1 - alpha) quantile of the largest one noise
        alone makes among the variants compared (0.5: their median); 1 switches it off.
    match_k : validation rows each test row spreads its weight over (0: equal weights).
    match_share : share of the weights from the matching; the rest is equal per row.
    one_se : keep the simplest candidate within one standard error of the best.
    one_se_of : which standard error sets that band: ``error`` (default), the best's weighted
        mean error (the one-standard-error rule of Breiman et al.); ``gain``, the best's paired
        gain over the coarse model (the rule before the fourteenth session: as wide as the
        coarse errors vary from row to row, 0.03-0.10 mrad on the 200-heliostat benchmark
        field's dynamic heliostats, where it kept candidates up to 31 % worse on validation
        than the best); ``difference``, each candidate's paired difference from the best.
        Measured: docs/experiments/fine-selection.md, "The one-standard-error band".
    multiplicity : ``maxt`` (module docstring) or ``bonferroni`` (``Phi^-1(1 - alpha / m)``).
    draws : random sign patterns of ``maxt`` (seeded with ``seed``).
    """

    min_improvement: float = 0.20
    min_improvement_gp: float = 0.10
    alpha: float = 0.5
    match_k: int = 3
    match_share: float = 0.5
    one_se: bool = True
    one_se_of: str = "error"
    multiplicity: str = "maxt"
    draws: int = 2000
    seed: int = 0

    def validated(self) -> "SelectionRule":
        check_float(self.min_improvement, "min_improvement", _FUNC, -math.inf, 1.0)
        check_float(self.min_improvement_gp, "min_improvement_gp", _FUNC, -math.inf, 1.0)
        check_float(self.alpha, "alpha", _FUNC, 0.0, 1.0, low_inclusive=False)
        check_int(self.match_k, "match_k", _FUNC, 0)
        check_float(self.match_share, "match_share", _FUNC, 0.0, 1.0)
        check_int(self.draws, "draws", _FUNC, 10)
        check_int(self.seed, "seed", _FUNC, 0)
        if self.one_se_of not in ONE_SE_OF:
            raise ParameterError(f"The 'one_se_of' parameter of {_FUNC} must be one of "
                                 f"{', '.join(ONE_SE_OF)}. Got {self.one_se_of!r} instead.")
        if self.multiplicity not in ("maxt", "bonferroni"):
            raise ParameterError(f"The 'multiplicity' parameter of {_FUNC} must be one of maxt, "
                                 f"bonferroni. Got {self.multiplicity!r} instead.")
        return self

    def margin_of(self, model: str) -> float:
        """The relative margin of a candidate of ``model`` (``gp...``: the GP's)."""
        return self.min_improvement_gp if model.startswith("gp") else self.min_improvement

    def z(self, n_candidates: int) -> float:
        """The one-sided Bonferroni quantile for ``n_candidates`` (``-inf`` with ``alpha`` 1)."""
        if self.alpha >= 1.0:
            return -math.inf
        return NormalDist().inv_cdf(1.0 - self.alpha / max(int(n_candidates), 1))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class Candidate:
    """A fine candidate of one heliostat, as the selection sees it.

    Attributes
    ----------
    model : ``gp``, ``hybrid``, ``hybrid-octaves``, ``pretrained-nn``, ...
    val_errors : (n_val,) its error_mrad on the validation rows (in the rows' order).
    complexity : sort key, smaller is simpler (module docstring).
    info : anything the caller needs back (weight decay, seed, fade length, its state).
    """

    model: str
    val_errors: np.ndarray
    complexity: tuple
    info: dict = field(default_factory=dict)


@dataclass
class Judgement:
    """One candidate's figures under the rule (all on the weighted validation rows).

    Attributes
    ----------
    mean_mrad : weighted mean error; gain_mrad : the coarse model's minus it (D); se_mrad : the
    standard error of D; relative_gain : D / the coarse model's weighted mean; passed : both
    margins met.
    """

    mean_mrad: float
    gain_mrad: float
    se_mrad: float
    relative_gain: float
    passed: bool


def validation_weights(val_distance_deg, test_distance_deg, k: int = 3,
                       share: float = 1.0) -> np.ndarray:
    """Weights (n_val,) summing to 1 that make the validation rows look like the test rows in
    their distance to training (module docstring, 1): a ``share`` of the weight from the test
    rows, each adding ``1 / k`` to each of the ``k`` validation rows whose distance is nearest
    its own (ties: the farther row, then the earlier), the rest equal per row. ``k`` 0, or no
    test distances: equal weights."""
    val = np.asarray(val_distance_deg, np.float64).reshape(-1)
    test = np.asarray(test_distance_deg, np.float64).reshape(-1)
    test = test[np.isfinite(test)]
    n = len(val)
    if n == 0:
        return np.zeros(0)
    if k <= 0 or not len(test) or not np.isfinite(val).all():
        return np.full(n, 1.0 / n)
    k = min(int(k), n)
    w = np.zeros(n)
    order = np.lexsort((np.arange(n), -val))   # farther first, then row order: the tie-break
    for d in test:
        gap = np.abs(val[order] - d)
        nearest = order[np.argsort(gap, kind="stable")[:k]]
        w[nearest] += 1.0 / k
    return share * w / w.sum() + (1.0 - share) / n


def row_validation_weights(rows, labels, k: int = 3, share: float = 1.0) -> np.ndarray:
    """:func:`validation_weights` of a heliostat's ``validation`` rows (in the rows' order) from
    the sun positions of ``rows`` (measurements.parquet columns) and their split ``labels``: each
    validation and test row's distance to the nearest ``train`` row, Euclidean in the (azimuth,
    elevation) plane [deg] (:func:`heliocal.pipeline.models.fade.sun_distance_deg`; so any split
    can be weighted, also the time split, which split.parquet has no distances for)."""
    from .fade import sun_distance_deg

    labels = np.asarray(labels, dtype=object)
    az = rows["sun_azimuth_deg"].to_numpy(np.float64)
    el = rows["sun_elevation_deg"].to_numpy(np.float64)
    train = np.column_stack([az, el])[labels == "train"]
    dist = lambda m: sun_distance_deg(az[m], el[m], train)  # noqa: E731
    return validation_weights(dist(labels == "validation"), dist(labels == "test"), k, share)


def paired_gain(coarse_errors, errors, weights) -> tuple[float, float, float]:
    """(D, s, coarse weighted mean): the weighted mean of the per-row gains ``coarse - errors``
    [mrad], its standard error and the coarse model's weighted mean error. ``s`` uses the
    weights' effective number of rows ``n_eff = 1 / sum(w^2)``: ``s^2 = n_eff / (n_eff - 1)
    sum(w^2 (g - D)^2)`` (the usual ``sd / sqrt(n)`` for equal weights)."""
    c = np.asarray(coarse_errors, np.float64)
    e = np.asarray(errors, np.float64)
    w = np.asarray(weights, np.float64)
    ok = np.isfinite(c) & np.isfinite(e) & (w > 0)
    if not ok.any():
        return float("nan"), float("nan"), float("nan")
    c, e, w = c[ok], e[ok], w[ok] / w[ok].sum()
    d, se = _weighted_mean_se(c - e, w)
    return d, se, float((w * c).sum())


def _weighted_mean_se(values: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """(weighted mean, its standard error) of finite ``values`` under weights ``w`` that sum to
    1, the standard error by the weights' effective number of rows (:func:`paired_gain`);
    infinite with at most one effective row."""
    mean = float((w * values).sum())
    n_eff = 1.0 / float((w ** 2).sum())
    if n_eff <= 1.0:
        return mean, float("inf")
    return mean, math.sqrt(n_eff / (n_eff - 1.0) * float((w ** 2 * (values - mean) ** 2).sum()))


def choose_fade(errors_by_length: Sequence[np.ndarray], weights) -> int:
    """Index of the fade length whose errors (one (n_val,) array per length, longest first) have
    the lowest weighted mean; a tie goes to the shorter fade (later in the list)."""
    w = np.asarray(weights, np.float64)
    means = [float(np.nansum(w * np.asarray(e, np.float64))) for e in errors_by_length]
    best = min(means)
    return max(i for i, m in enumerate(means) if m <= best + 1e-12)


def _studentised(gains: np.ndarray, w: np.ndarray) -> np.ndarray:
    """D / s of :func:`paired_gain` along the last axis of per-row ``gains`` (..., n)."""
    d = (gains * w).sum(-1)
    n_eff = 1.0 / float((w ** 2).sum())
    if n_eff <= 1.0:
        return np.zeros_like(d)
    se = np.sqrt(n_eff / (n_eff - 1.0) * (w ** 2 * (gains - d[..., None]) ** 2).sum(-1))
    return np.where(se > 0, d / np.where(se > 0, se, 1.0), np.where(d > 0, np.inf, 0.0))


def max_t_threshold(coarse_errors, variant_errors: Sequence[np.ndarray], weights, alpha: float,
                    draws: int = 2000, seed: int = 0) -> float:
    """Westfall and Young's max-T margin: the (1 - ``alpha``) quantile of the largest studentised
    gain (:func:`paired_gain`'s D / s) among all ``variant_errors`` ((n_val,) each: every
    candidate at every fade length it was chosen from) when each validation row's gains over the
    coarse model get one random sign, shared by all variants. If no variant were better than the
    coarse model, a row's gain would be as likely negative as positive, so this is the largest
    studentised gain noise alone makes, with the variants' correlation (one weight-decay path,
    nested fades) kept. Seeded (``seed``, ``draws`` patterns)."""
    c = np.asarray(coarse_errors, np.float64)
    w = np.asarray(weights, np.float64)
    e = np.stack([np.asarray(v, np.float64) for v in variant_errors])          # (V, n)
    ok = np.isfinite(c) & np.isfinite(e).all(0) & (w > 0)
    if not ok.any() or not len(e):
        return math.inf
    gains, w = c[ok] - e[:, ok], w[ok] / w[ok].sum()
    signs = np.random.default_rng(seed).choice((-1.0, 1.0), size=(int(draws), 1, len(w)))
    t = _studentised(signs * gains[None], w)                                    # (draws, V)
    return float(np.quantile(t.max(axis=1), 1.0 - alpha, method="higher"))


def judge(coarse_errors, candidate: Candidate, weights, rule: SelectionRule,
          margin: float) -> Judgement:
    """One candidate's :class:`Judgement` against the coarse model: passed when its relative
    gain reaches its family's margin (:meth:`SelectionRule.margin_of`), its studentised gain
    exceeds ``margin`` and its plain (unweighted) validation mean is not above the coarse
    model's."""
    d, se, base = paired_gain(coarse_errors, candidate.val_errors, weights)
    if not math.isfinite(d) or not base > 0:
        return Judgement(float("nan"), d, se, float("nan"), False)
    rel = d / base
    # paper 000's guarantee on the plain validation mean too: the weighting may not buy a
    # candidate that is worse than the coarse model on the validation rows as they are
    plain = float(np.nanmean(candidate.val_errors)) <= float(np.nanmean(coarse_errors))
    passed = rel >= rule.margin_of(candidate.model) and d > margin * se and plain
    return Judgement(base - d, d, se, rel, bool(passed))


def select(coarse_errors, candidates: Sequence[Candidate], weights,
           rule: SelectionRule = SelectionRule(), n_candidates: int | None = None,
           variants: Sequence[np.ndarray] | None = None) -> tuple[int | None, list[Judgement]]:
    """The index of the kept candidate (None: the coarse model stays) and every candidate's
    :class:`Judgement`.

    Parameters
    ----------
    coarse_errors : (n_val,) the coarse model's error_mrad on the validation rows.
    candidates : the fine candidates (their errors on the same rows).
    weights : (n_val,) :func:`validation_weights`.
    rule : :class:`SelectionRule`.
    n_candidates : how many candidates were compared (the Bonferroni ``m``; default
        ``len(candidates)``; a candidate whose fade length was chosen among L lengths counts L).
    variants : with ``maxt``, the validation errors of every variant compared (each candidate
        at each fade length it was chosen from; default: the candidates' own).
    """
    rule = rule.validated()
    m = len(candidates) if n_candidates is None else int(n_candidates)
    if len(np.asarray(weights)) != len(np.asarray(coarse_errors)):
        raise ParameterError(f"The 'weights' parameter of {_FUNC} must have one weight per "
                             f"validation row ({len(np.asarray(coarse_errors))}). Got "
                             f"{len(np.asarray(weights))} instead.")
    if rule.alpha >= 1.0 or not candidates:
        margin = -math.inf
    elif rule.multiplicity == "maxt":
        margin = max_t_threshold(coarse_errors, variants if variants is not None else
                                 [c.val_errors for c in candidates], weights, rule.alpha,
                                 rule.draws, rule.seed)
    else:
        margin = rule.z(m)
    judged = [judge(coarse_errors, c, weights, rule, margin) for c in candidates]
    passed = [i for i, j in enumerate(judged) if j.passed]
    if not passed:
        return None, judged
    best = min(passed, key=lambda i: (judged[i].mean_mrad, candidates[i].complexity))
    if not rule.one_se:
        return best, judged
    near = _within_one_se(candidates, judged, passed, best, weights, rule.one_se_of)
    return min(near, key=lambda i: (candidates[i].complexity, judged[i].mean_mrad)), judged


def _within_one_se(candidates: Sequence[Candidate], judged: Sequence["Judgement"],
                   passed: Sequence[int], best: int, weights, one_se_of: str) -> list[int]:
    """The candidates of ``passed`` within one standard error of ``best`` on the weighted
    validation rows, the standard error as :attr:`SelectionRule.one_se_of` says (the best's
    own band is worked out once; ``difference`` pairs each candidate with the best)."""
    if one_se_of == "difference":
        near = []
        for i in passed:
            d, se, _ = paired_gain(candidates[i].val_errors, candidates[best].val_errors, weights)
            if not d > se:
                near.append(i)
        return near
    se = (_error_se(candidates[best].val_errors, weights) if one_se_of == "error"
          else judged[best].se_mrad)
    limit = judged[best].mean_mrad + se
    return [i for i in passed if judged[i].mean_mrad <= limit]


def _error_se(errors, weights) -> float:
    """The standard error of the weighted mean of ``errors`` [mrad] over its finite rows of
    positive weight (:func:`_weighted_mean_se`); NaN without such rows."""
    errors, w = np.asarray(errors, np.float64), np.asarray(weights, np.float64)
    ok = np.isfinite(errors) & (w > 0)
    return _weighted_mean_se(errors[ok], w[ok] / w[ok].sum())[1] if ok.any() else math.nan
