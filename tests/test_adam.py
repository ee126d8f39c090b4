"""The fine networks' optimiser (pipeline/models/adam.py) and what a training imports.

Reference: ``torch.optim.Adam`` with its defaults, the optimiser ``LeafAdam`` writes out op for
op. Same start, same gradients: the parameters and both moments must agree to the bit at every
step, in float32 (the training's dtype) and float64, also after the rows of stopped members are
dropped mid-training (what train_members does when a quarter of its members stop).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from heliocal.pipeline.models.adam import LeafAdam

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
