"""The networks' optimisers (pipeline/models/adam.py) and what a training imports.

References: ``torch.optim.Adam`` with its defaults, which ``LeafAdam`` writes out op for op, and
``torch.optim.Adamax`` with ``torch.optim.lr_scheduler.ReduceLROnPlateau``, which ``Adamax`` and
``ReduceOnPlateau`` write out. Same start, same gradients: the parameters and the optimiser's
state must agree to the bit at every step, in float32 (the training's dtype) and float64, also
after the rows of stopped members are dropped mid-training (what train_members does when a
quarter of its members stop) and across the learning-rate cuts of a plateau.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from heliocal.pipeline.models.adam import Adamax, LeafAdam, ReduceOnPlateau

TESTS = Path(__file__).resolve().parent


def _loss(theta: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """A smooth, non-quadratic loss per row (rows independent), summed."""
    return (torch.sin(theta * 3.0) * target + 0.1 * theta ** 4 + 0.5 * theta * target).sum()


def _torch_keep_rows(theta, opt, keep, lr):
    """Dropping rows with torch's Adam: a new leaf, a new Adam with the kept rows' moments."""
    state = opt.state[theta]
    new = theta.detach()[keep].clone().requires_grad_(True)
    new_opt = torch.optim.Adam([new], lr=lr)
    new_opt.state[new] = {"step": state["step"].clone(), "exp_avg": state["exp_avg"][keep].clone(),
                          "exp_avg_sq": state["exp_avg_sq"][keep].clone()}
    return new, new_opt


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_leaf_adam_takes_torch_adams_steps_to_the_bit(dtype):
    gen = torch.Generator().manual_seed(7)
    start = torch.randn(6, 40, generator=gen, dtype=dtype)
    target = torch.randn(6, 40, generator=gen, dtype=dtype)
    lr = 3e-3
    ours = start.clone().requires_grad_(True)
    theirs = start.clone().requires_grad_(True)
    opt_ours, opt_theirs = LeafAdam(ours, lr=lr), torch.optim.Adam([theirs], lr=lr)
    keep = torch.tensor([True, False, True, True, False, True])
    for step in range(120):
        if step == 50:  # two members stopped: their rows leave the program
            ours, opt_ours = opt_ours.keep_rows(keep)
            theirs, opt_theirs = _torch_keep_rows(theirs, opt_theirs, keep, lr)
            target = target[keep]
        for theta, opt in ((ours, opt_ours), (theirs, opt_theirs)):
            opt.zero_grad() if opt is opt_ours else opt.zero_grad(set_to_none=False)
            _loss(theta, target).backward()
            opt.step()
        assert torch.equal(ours, theirs), step
        state = opt_theirs.state[theirs]
        assert torch.equal(opt_ours.exp_avg, state["exp_avg"]), step
        assert torch.equal(opt_ours.exp_avg_sq, state["exp_avg_sq"]), step
    assert ours.shape == (4, 40) and opt_ours.steps == 120
    # the loss went down: the steps are real ones, not a comparison of two idle leaves
    assert float(_loss(ours.detach(), target)) < float(_loss(start[keep], target)) - 1.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_adamax_and_its_plateau_take_torchs_steps_to_the_bit(dtype):
    # three leaves of a network's shapes; the scheduler watches a loss that stops improving
    # after step 40 (a plateau held by the watched value), so torch cuts the rate twice
    gen = torch.Generator().manual_seed(11)
    shapes = [(5, 6), (6,), (1, 6)]
    starts = [torch.randn(*sh, generator=gen, dtype=dtype) for sh in shapes]
    targets = [torch.randn(*sh, generator=gen, dtype=dtype) for sh in shapes]
    ours = [t.clone().requires_grad_(True) for t in starts]
    theirs = [t.clone().requires_grad_(True) for t in starts]
    opt_ours = Adamax(ours, lr=2e-2)
    opt_theirs = torch.optim.Adamax(theirs, lr=2e-2)
    sched_ours = ReduceOnPlateau(opt_ours, factor=0.5, patience=4)
    sched_theirs = torch.optim.lr_scheduler.ReduceLROnPlateau(opt_theirs, factor=0.5, patience=4)
    for step in range(90):
        watched = []
        for leaves, opt in ((ours, opt_ours), (theirs, opt_theirs)):
            opt.zero_grad()
            loss = sum(_loss(theta, target) for theta, target in zip(leaves, targets))
            loss.backward()
            opt.step()
            watched.append(min(float(loss.detach()), 10.0 - step) if step < 40 else 1.0)
        sched_ours.step(watched[0])
        sched_theirs.step(watched[1])
        assert opt_ours.lr == opt_theirs.param_groups[0]["lr"], step
        for k, (a, b) in enumerate(zip(ours, theirs)):
            state = opt_theirs.state[b]
            assert torch.equal(a, b), (step, k)
            assert torch.equal(opt_ours.exp_avg[k], state["exp_avg"]), (step, k)
            assert torch.equal(opt_ours.exp_inf[k], state["exp_inf"]), (step, k)
    # the plateau cut the rate (2e-2 -> 1e-2 -> ... : every 5 steps after step 40)
    assert opt_ours.lr < 2e-2 / 2 ** 5
    start_loss = sum(float(_loss(t, g)) for t, g in zip(starts, targets))
    assert sum(float(_loss(t.detach(), g)) for t, g in zip(ours, targets)) < start_loss - 1.0


def test_a_training_imports_neither_torch_compiler_nor_its_configuration():
    """A fresh process that sets the deterministic flag and trains networks, as a sweep's worker
    does, never imports torch._dynamo or torch._inductor (about 1.1 s of CPU each process), and
    the flag it set is the one torch reads."""
    script = (
        "import sys\n"
        f"sys.path.insert(0, {str(TESTS)!r})\n"
        "import dataclasses, numpy as np, torch\n"
        "from heliocal.pipeline.runtime.process_state import deterministic_torch\n"
        "from heliocal.pipeline.models.training import train_members\n"
        "from test_hybrid import FAST, _problem, synthetic_measurements\n"
        "deterministic_torch()\n"
        "rows = synthetic_measurements(40)\n"
        "val = np.arange(len(rows)) % 4 == 0\n"
        "res = train_members(_problem(rows), ~val, val, [0.0, 1.0], [0, 1],\n"
        "                    dataclasses.replace(FAST, max_epochs=30))\n"
        "print(torch.are_deterministic_algorithms_enabled(),\n"
        "      torch.is_deterministic_algorithms_warn_only_enabled(),\n"
        "      bool(np.isfinite(res.best_val_mrad.numpy()).all()),\n"
        "      'torch._dynamo' in sys.modules, 'torch._inductor' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, PYTHONPATH=str(TESTS)))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["True", "True", "True", "False", "False"]
