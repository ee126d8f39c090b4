"""The sweep's screen (issue 36): is the rest of a heliostat's weight-decay path worth training?

The production selection trains, per heliostat, every band set x weight decay x seed as an
ensemble (2 x 8 x 4 networks by default) and then keeps the coarse model on most real
heliostats: a hybrid must beat the coarse model by the rule's network margin (20 %) on the
validation rows weighted toward the test rows' distances
(:mod:`heliocal.pipeline.models.selection`).

The screen is the start of that path: the first band set (the integer bands, which can represent
a gear period), trained for every heliostat up to the ``ScreenConfig.stages``-th weight decay (1,
0.1 and 0.01 on the default grid, up to 600 epochs warm-started). Its ensembles are candidates
like any other, judged exactly as the selection judges them: each at the fade length its
weighted validation error likes best, by its relative gain over the coarse model on the *same
weighted* validation rows. Not on training rows: a coarse fit leaves residual structure between
its training rows that a network interpolates (up to 18 % on validation on static heliostats,
docs/hybrid.md "Why 20 %") and that does not reach the test rows, so a test for structure among
the training rows would send every heliostat down the path, for a model the selection then
refuses.

Where the best of those ensembles gains at least ``ScreenConfig.share`` x the network margin (10
% by default), the path goes on from where it stopped and the other band sets are trained: the
screen costs such a heliostat nothing. Elsewhere the path stops: the heliostat's candidates are
the coarse model, the screen's ensembles and the GP (fitted either way); selection.parquet's
``screen`` says ``failed`` and ``screen_gain`` gives the figure. Why half the margin, and what it
costs and saves: docs/experiments/sweep-screen.md.

Past the screen, a band set's path goes on one weight decay at a time only while it keeps
gaining: each band set trains its first ``ScreenConfig.stages`` weight decays, and the next one
only where the last raised the band set's best gain by at least ``ScreenConfig.stage_gain`` (1 %
of the coarse model's weighted validation error). Warm-started from the last, a weaker weight
decay starts where the stronger one was best, so a path that has stopped gaining mostly trains
the same networks again (:func:`goes_on`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from ..models.config import ScreenConfig
from ..models.selection import SelectionRule, paired_gain

__all__ = ["ScreenVerdict", "screen_margin", "best_gain", "screen_verdicts", "stage_gains",
           "goes_on", "SCREEN_OFF", "SCREEN_PASSED", "SCREEN_FAILED"]

#: selection.parquet ``screen`` values: not run, path trained, path stopped after the screen.
SCREEN_OFF, SCREEN_PASSED, SCREEN_FAILED = "off", "passed", "failed"


@dataclass(frozen=True)
class ScreenVerdict:
    """One heliostat's screen.

    Attributes
    ----------
    status : :data:`SCREEN_OFF`, :data:`SCREEN_PASSED` or :data:`SCREEN_FAILED`.
    gain : the best relative gain of the screen's ensembles over the coarse model on the weighted
        validation rows (1 - its weighted mean / the coarse model's; NaN: not run, or no
        validation rows).
    """

    status: str = SCREEN_OFF
    gain: float = math.nan

    @property
    def trains_path(self) -> bool:
        return self.status != SCREEN_FAILED


def screen_margin(screen: ScreenConfig, rule: SelectionRule) -> float | None:
    """The relative gain the screen asks for (``share`` x the rule's network margin), or None
    when there is nothing to screen for (screen disabled, or a network margin that is not
    positive: then any gain could pass the rule)."""
    if not screen.enabled or not rule.min_improvement > 0:
        return None
    return float(screen.share * rule.min_improvement)


def _relative_gain(pool, candidate) -> float:
    """``candidate``'s relative gain over the coarse model on ``pool``'s weighted validation rows
    (at its chosen fade, as the rule sees it); NaN without validation rows."""
    if not pool.val.any():
        return math.nan
    d, _, base = paired_gain(pool.coarse_errors[pool.val], candidate.val_errors, pool.weights)
    return d / base if math.isfinite(d) and base > 0 else math.nan


def best_gain(pool) -> float:
    """The best relative gain over the coarse model on the weighted validation rows among the
    network candidates of ``pool`` (a ``CandidatePool``); NaN without validation rows or
    candidates."""
    gains = [g for g in (_relative_gain(pool, c) for c in pool.candidates) if math.isfinite(g)]
    return max(gains) if gains else math.nan


def stage_gains(pool, kind: str) -> list[float]:
    """The best relative gain of band set ``kind``'s ensembles in ``pool`` after each weight
    decay of its path trained so far, in the order trained (a running maximum over the
    weight decay's seeds and the ones before; NaN until a stage has a finite gain)."""
    by_decay: dict[float, list[float]] = {}
    for c in pool.candidates:
        if c.model == kind:
            by_decay.setdefault(c.info["weight_decay"], []).append(_relative_gain(pool, c))
    out, best = [], math.nan
    for gains in by_decay.values():
        finite = [g for g in gains if math.isfinite(g)]
        if finite:
            best = max(finite) if math.isnan(best) else max(best, *finite)
        out.append(best)
    return out


def goes_on(gains: Sequence[float], stage_gain: float) -> bool:
    """Whether a band set's path trains its next weight decay, given its :func:`stage_gains`:
    where its last weight decay raised the best gain by at least ``stage_gain`` (``0``: always;
    a gain that is not finite stops it)."""
    if stage_gain <= 0:
        return True
    return len(gains) >= 2 and gains[-1] - gains[-2] >= stage_gain


def screen_verdicts(pools: Sequence, margin: float | None) -> list[ScreenVerdict]:
    """Each pool's verdict after the screen's stages (``margin``: :func:`screen_margin`; None:
    every heliostat trains its path, status off)."""
    if margin is None:
        return [ScreenVerdict() for _ in pools]
    out = []
    for pool in pools:
        gain = best_gain(pool)
        passed = math.isfinite(gain) and gain >= margin
        out.append(ScreenVerdict(SCREEN_PASSED if passed else SCREEN_FAILED, gain))
    return out
