"""Training the sweep's hybrids along the weight-decay path (issue 36: spend it where it can win).

Every band set's networks train along a path of weight decays from strong to weak
(:func:`train_path`, :class:`~heliocal.pipeline.models.config.PathConfig`), warm-started: each
weight decay starts from the previous one's best-validation weights. A chunk of heliostats of
one kinematic type, actuator type and coarse preset trains as one batched torch program per
weight decay (:func:`~heliocal.pipeline.models.training.stack_problems`, aligned with
:data:`~heliocal.pipeline.models.training.MEMBER_ALIGN`, so a heliostat's networks are the same
bits in any chunk). :func:`train_candidates` spends the path where it can win: the screen's
first weight decays for every heliostat, the rest only where the screen passes and, one weight
decay at a time, only while the path keeps gaining (:mod:`.sweep_screen`). Each ensemble is
added to its heliostat's candidate pool (:class:`.selection.CandidatePool`) and sweep rows.
"""

from __future__ import annotations

import dataclasses
from typing import Iterator, Sequence

import numpy as np
import torch

from ..models.config import FineConfig, PathConfig, ScreenConfig, ensemble_seeds
from ..models.selection import SelectionRule
from ..models.training import (MEMBER_ALIGN, FineProblem, MemberResult, build_problem,
                               stack_problems, take_rows, train_members)
from .fit_coarse import coarse_row_parameters
from .sweep_inputs import sweep_row
from .sweep_screen import ScreenVerdict, goes_on, screen_margin, screen_verdicts, stage_gains

__all__ = ["path_order", "train_path", "train_candidates"]


def path_order(weight_decays: Sequence[float]) -> list[float]:
    """The weight decays from strong to weak (0 last), each once."""
    return sorted({float(w) for w in weight_decays}, reverse=True)


def train_path(problem: FineProblem, train_mask, val_mask, seeds: Sequence[int],
               weight_decays: Sequence[float], config: FineConfig,
               path: PathConfig = PathConfig(),
               initial=None, align: int = 1) -> Iterator[tuple[float, MemberResult]]:
    """Train M networks at every weight decay, strong to weak; yield ``(weight_decay, result)``.

    Each weight decay is one :func:`heliocal.pipeline.models.training.train_members` program of the M
    networks (``seeds`` (M,), masks as there). With ``path.warm_start`` the first weight decay
    starts from the seeded weights (or from ``initial``, the layers of the M networks where an
    earlier call left the path: the path goes on from there) and every later one from the
    previous weight decay's best-validation weights, each with the budget of ``path``; since the
    start is the epoch-0 candidate of the early stopping, a network's validation error never
    rises along the path. Without warm start every weight decay is an independent training with
    ``config``'s budget. ``align``: as for ``train_members`` (a problem stacked with it).
    """
    previous = initial
    if path.warm_start:
        config = dataclasses.replace(config, max_epochs=path.stage_epochs,
                                     patience=path.stage_patience)
    for wd in path_order(weight_decays):
        warm = path.warm_start and previous is not None
        result = train_members(problem, train_mask, val_mask, [wd] * len(seeds), list(seeds),
                               config, initial=previous if warm else None, align=align)
        previous = result.layers
        yield wd, result


# ------------------------------------------------------------------------------------------------
# a chunk of heliostats: every band set's path, spent where it can win
# ------------------------------------------------------------------------------------------------
def _take(items: Sequence, index: Sequence[int]) -> list:
    """``items`` at the positions ``index``, in that order."""
    return [items[i] for i in index]


def _fitting_rows(h) -> np.ndarray:
    """bool (N,): the rows of heliostat ``h`` a training uses (train and validation)."""
    return np.isin(h.labels, ("train", "validation"))


def _band_set_problems(helios, cfg):
    """Each heliostat's fine problem of band set ``cfg`` on all its rows, and the same on its
    training and validation rows alone (what a training stacks)."""
    problems = [build_problem(h.rows, h.hrow, coarse_row_parameters(   # each row its regime's
        h.selected, h.rows["timestamp"]), h.selected["free"], cfg) for h in helios]
    return problems, [take_rows(p, torch.as_tensor(_fitting_rows(h)))
                      for p, h in zip(problems, helios)]


def _train_stages(helios, problems, taken, pools, out_rows, kind, cfg, weight_decays, seeds,
                  path, initial=None):
    """Train one band set's weight decays ``weight_decays`` (strong to weak) for ``helios``
    (one batched program per weight decay; ``problems``, ``taken``: :func:`_band_set_problems`),
    add each ensemble to its heliostat's pool and sweep rows (in place; every list in the same
    order) and return the last weight decay's layers, or ``initial`` when there was none.
    ``initial``: the layers to go on from (the members in the order this call stacks them:
    heliostat, seed, ensemble network)."""
    n_seeds, k_ens = len(seeds), cfg.ensemble
    per_h = n_seeds * k_ens           # networks per heliostat: seeds x ensemble
    # aligned: each heliostat's networks train to the same bits in any chunk (MEMBER_ALIGN)
    stacked, valid = stack_problems([t for t in taken for _ in range(per_h)], MEMBER_ALIGN)
    n = stacked.data.steps.shape[1]
    labels_fit = np.array([np.resize(h.labels[_fitting_rows(h)], n) for h in helios
                           for _ in range(per_h)])
    net_seeds = [x for _ in helios for s in seeds for x in ensemble_seeds(s, k_ens)]
    last = initial
    for wd, result in train_path(stacked, torch.as_tensor(labels_fit == "train") & valid,
                                 torch.as_tensor(labels_fit == "validation") & valid,
                                 net_seeds, weight_decays, cfg, path, initial=initial,
                                 align=MEMBER_ALIGN):
        wall = result.wall_time_s / (len(helios) * n_seeds)
        last = result.layers
        for i, (h, problem) in enumerate(zip(helios, problems)):
            for j, s in enumerate(seeds):
                ens = slice(i * per_h + j * k_ens, i * per_h + (j + 1) * k_ens)
                err, length = pools[i].add_network(
                    kind, cfg, wd, s, problem, [(w[ens], b[ens]) for w, b in result.layers],
                    path)
                out_rows[i].append(sweep_row(h.hid, kind, h.n_full, wd, s, err, h.labels,
                                             h.train, h.test_distance, h.selected["preset"],
                                             wall, length))
    return last


def _members_of(layers, keep: Sequence[int], per_h: int):
    """The layers of the networks of the heliostats ``keep`` (indices into the stacking order,
    ``per_h`` networks each), stacked in that order."""
    if layers is None:
        return None
    index = torch.as_tensor([i * per_h + k for i in keep for k in range(per_h)])
    return [(w[index], b[index]) for w, b in layers]


def _go_on(helios, problems, taken, pools, out_rows, kind, cfg, weight_decays, seeds, path,
           stage_gain, last):
    """The rest of one band set's path, ``weight_decays`` (strong to weak), one at a time, for
    the heliostats whose path still gains (:func:`~.sweep_screen.goes_on` with
    ``stage_gain``), each from its networks in ``last`` (stacked as ``helios``; the lists as
    for :func:`_train_stages`, in place)."""
    per_h = len(seeds) * cfg.ensemble
    going = list(range(len(helios)))
    for wd in weight_decays:
        on = [k for k, i in enumerate(going) if goes_on(stage_gains(pools[i], kind), stage_gain)]
        if not on:
            return
        going, last = _take(going, on), _members_of(last, on, per_h)
        last = _train_stages(*(_take(xs, going) for xs in (helios, problems, taken, pools,
                                                           out_rows)),
                             kind, cfg, [wd], seeds, path, initial=last)


def train_candidates(helios, pools, out_rows, variants, weight_decays, seeds, path,
                      screen: ScreenConfig, rule: SelectionRule) -> list[ScreenVerdict]:
    """Every band set's weight-decay path for the heliostats that pass the screen (in place, as
    :func:`_train_stages`); return each heliostat's :class:`ScreenVerdict`. The screen is the
    first band set's path up to its ``screen.stages``-th weight decay, trained for every
    heliostat; where it passes, every band set trains as many weight decays and goes on past
    them while its path keeps gaining (:mod:`.sweep_screen`)."""
    (kind, cfg), others = variants[0], variants[1:]
    order = path_order(weight_decays)
    margin = screen_margin(screen, rule)
    n_first = len(order) if margin is None else min(screen.stages, len(order))
    problems, taken = _band_set_problems(helios, cfg)
    last = _train_stages(helios, problems, taken, pools, out_rows, kind, cfg, order[:n_first],
                         seeds, path)
    verdicts = screen_verdicts(pools, margin)
    keep = [i for i, v in enumerate(verdicts) if v.trains_path]
    if not keep:
        return verdicts
    helios, pools, out_rows = _take(helios, keep), _take(pools, keep), _take(out_rows, keep)
    _go_on(helios, _take(problems, keep), _take(taken, keep), pools, out_rows, kind, cfg,
           order[n_first:], seeds, path, screen.stage_gain,
           _members_of(last, keep, len(seeds) * cfg.ensemble))
    for kind_, cfg_ in others:
        problems, taken = _band_set_problems(helios, cfg_)
        last = _train_stages(helios, problems, taken, pools, out_rows, kind_, cfg_,
                             order[:n_first], seeds, path)
        _go_on(helios, problems, taken, pools, out_rows, kind_, cfg_, order[n_first:], seeds,
               path, screen.stage_gain, last)
    return verdicts
