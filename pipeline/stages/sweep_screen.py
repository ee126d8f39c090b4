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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from ..models.config import ScreenConfig
from ..models.selection import SelectionRule, paired_gain

__all__ = ["ScreenVerdict", "screen_margin", "best_gain", "screen_verdicts", "SCREEN_OFF",
           "SCREEN_PASSED", "SCREEN_FAILED"]

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


def best_gain(pool) -> float:
    """The best relative gain over the coarse model on the weighted validation rows among the
    network candidates of ``pool`` (a ``CandidatePool``: each at its chosen fade, as the rule
    sees it); NaN without validation rows or candidates."""
    gains = []
    if pool.val.any():
        for c in pool.candidates:
            d, _, base = paired_gain(pool.coarse_errors[pool.val], c.val_errors, pool.weights)
            if math.isfinite(d) and base > 0:
                gains.append(d / base)
    return max(gains) if gains else math.nan


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
