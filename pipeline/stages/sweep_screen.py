"""The sweep's screen (issue 36): is a heliostat's full weight-decay path worth training?

The production selection trains, per heliostat, every band set x weight decay x seed as an
ensemble (64 networks by default) and then keeps the coarse model on most real heliostats: a
hybrid must beat the coarse model by the rule's network margin (20 %) on the validation rows
weighted toward the test rows' distances (:mod:`heliocal.pipeline.models.selection`). The
screen trains one ensemble first, the sweep's first band set (the integer bands, which can
represent a gear period) at one weight decay, ``ScreenConfig.weight_decay``, from its seeded
weights for one stage of the path's budget, and judges it exactly as the selection judges a
candidate: at the fade length its weighted validation error likes best, by its relative gain
over the coarse model on the *same weighted* validation rows. Not on training rows: a coarse
fit leaves residual structure between its training rows that a network interpolates (up to
18 % on validation on static heliostats, docs/hybrid.md "Why 20 %") and that does not reach
the test rows, so a test for structure among the training rows would send every heliostat down
the path; and the selection itself would refuse what the screen sees nowhere near its distances.

A heliostat whose screen ensemble gains less than ``ScreenConfig.share`` x the network margin
(10 % by default) cannot, by the measurements of docs/experiments/sweep-screen.md, reach the
margin along the path either: its path is not trained and its candidates are the coarse model
and the GP (which has its own margin and is fitted either way); selection.parquet's ``screen``
says ``failed`` and ``screen_gain`` gives the figure. The screen costs about a tenth of the path
(4 networks for at most one stage, against 2 band sets x 8 weight decays of them).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..models.config import FineConfig, ScreenConfig, ensemble_seeds
from ..models.selection import SelectionRule, choose_fade, paired_gain
from ..models.training import (build_problem, faded_errors_mrad, stack_problems, take_rows,
                               train_members)
from .fit_coarse import coarse_row_parameters

__all__ = ["ScreenVerdict", "screen_margin", "screen_chunk", "SCREEN_OFF", "SCREEN_PASSED",
           "SCREEN_FAILED"]

#: selection.parquet ``screen`` values: not run, path trained, path not trained.
SCREEN_OFF, SCREEN_PASSED, SCREEN_FAILED = "off", "passed", "failed"


@dataclass(frozen=True)
class ScreenVerdict:
    """One heliostat's screen.

    Attributes
    ----------
    status : :data:`SCREEN_OFF`, :data:`SCREEN_PASSED` or :data:`SCREEN_FAILED`.
    gain : relative gain of the screen ensemble over the coarse model on the weighted validation
        rows (1 - its weighted mean / the coarse model's; NaN: not run or no validation rows).
    margin : the gain it had to reach (NaN: not run).
    """

    status: str = SCREEN_OFF
    gain: float = math.nan
    margin: float = math.nan

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


def _relative_gain(pool, errors_by_length: np.ndarray) -> float:
    """The screen ensemble's relative weighted-validation gain over the coarse model at the
    fade length its weighted validation error likes best (as ``CandidatePool.add_network``
    chooses it); NaN without validation rows."""
    if not pool.val.any():
        return math.nan
    k = choose_fade([e[pool.val] for e in errors_by_length], pool.weights)
    d, _, base = paired_gain(pool.coarse_errors[pool.val], errors_by_length[k][pool.val],
                             pool.weights)
    return d / base if base > 0 else math.nan


def screen_chunk(helios: Sequence, pools: Sequence, config: FineConfig, seed: int,
                 screen: ScreenConfig, rule: SelectionRule) -> list[ScreenVerdict]:
    """The screen of a chunk of heliostats (the sweep's ``SweepHeliostat`` and their
    ``CandidatePool``, in order), trained as one batched program of ``config.ensemble`` networks
    per heliostat (seeds :func:`ensemble_seeds` of ``seed``, the path's first seed)."""
    margin = screen_margin(screen, rule)
    if margin is None:
        return [ScreenVerdict() for _ in helios]
    cfg = dataclasses.replace(config, max_epochs=screen.epochs, patience=screen.patience)
    k_ens = cfg.ensemble
    problems = [build_problem(h.rows, h.hrow, coarse_row_parameters(h.selected, h.rows["timestamp"]),
                              h.selected["free"], cfg) for h in helios]
    fitting = [np.isin(h.labels, ("train", "validation")) for h in helios]
    taken = [take_rows(p, torch.as_tensor(f)) for p, f in zip(problems, fitting)]
    stacked, valid = stack_problems([t for t in taken for _ in range(k_ens)])
    n = stacked.data.steps.shape[1]
    labels = np.array([np.resize(h.labels[f], n) for h, f in zip(helios, fitting)
                       for _ in range(k_ens)])
    result = train_members(stacked, torch.as_tensor(labels == "train") & valid,
                           torch.as_tensor(labels == "validation") & valid,
                           [screen.weight_decay] * (len(helios) * k_ens),
                           [s for _ in helios for s in ensemble_seeds(seed, k_ens)], cfg)
    verdicts = []
    for i, (problem, pool) in enumerate(zip(problems, pools)):
        ens = slice(i * k_ens, (i + 1) * k_ens)
        layers = [(w[ens], b[ens]) for w, b in result.layers]
        errors = faded_errors_mrad(problem, layers, None, pool.fade_weights)[:, 0]   # (L, N)
        gain = _relative_gain(pool, errors)
        passed = math.isfinite(gain) and gain >= margin
        verdicts.append(ScreenVerdict(SCREEN_PASSED if passed else SCREEN_FAILED, gain, margin))
    return verdicts
