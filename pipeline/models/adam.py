"""Adam on one leaf tensor, the optimiser of the fine networks' full-batch training.

The update is ``torch.optim.Adam``'s (Kingma and Ba, 2015, with torch's defaults: betas (0.9,
0.999), eps 1e-8, no weight decay: the networks' L2 penalty is in their loss), written out op
for op as torch's single-tensor implementation runs it on the CPU, so a training gives the same
bits with either. Why not torch's own: its optimiser imports torch's compiler front end
(``torch._dynamo`` and ``torch._inductor``) on its first use, about 1.1 s of CPU in every process
that trains, more than all of heliocal's modules take to import; heliocal never compiles.
tests/test_adam.py compares the two, to the bit, over a training's steps and a change of rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["LeafAdam"]


@dataclass
class LeafAdam:
    """Adam's state for the leaf ``param`` (any shape; rows are independent: Adam is
    elementwise).

    ``step()`` applies one update from ``param.grad`` [the gradient of the loss], ``zero_grad()``
    zeroes that gradient in place (torch's ``zero_grad(set_to_none=False)``), and
    :meth:`keep_rows` continues the kept rows on a new leaf."""

    param: torch.Tensor
    lr: float
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    steps: int = 0
    exp_avg: torch.Tensor = field(default=None)      # first moment, like param
    exp_avg_sq: torch.Tensor = field(default=None)   # second moment, like param

    def __post_init__(self) -> None:
        if self.exp_avg is None:
            self.exp_avg = torch.zeros_like(self.param, memory_format=torch.preserve_format)
        if self.exp_avg_sq is None:
            self.exp_avg_sq = torch.zeros_like(self.param, memory_format=torch.preserve_format)

    def zero_grad(self) -> None:
        grad = self.param.grad
        if grad is not None:
            if grad.grad_fn is not None:
                grad.detach_()
            else:
                grad.requires_grad_(False)
            grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One Adam update of ``param`` in place (torch's ``_single_tensor_adam``, amsgrad,
        maximize and weight decay off)."""
        beta1, beta2 = self.betas
        grad = self.param.grad
        self.steps += 1
        self.exp_avg.lerp_(grad, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step = float(self.steps)            # torch keeps the count as a tensor and reads a float
        bias_correction1 = 1 - beta1 ** step
        bias_correction2 = 1 - beta2 ** step
        step_size = self.lr / bias_correction1
        denom = (self.exp_avg_sq.sqrt() / bias_correction2 ** 0.5).add_(self.eps)
        self.param.addcdiv_(self.exp_avg, denom, value=-step_size)

    def keep_rows(self, keep: torch.Tensor) -> tuple[torch.Tensor, "LeafAdam"]:
        """A new leaf of ``param``'s rows ``keep`` (a bool mask or indices of the first
        dimension) and the Adam that continues them from their moments: each kept row follows
        exactly the path it would have followed."""
        new = self.param.detach()[keep].clone().requires_grad_(True)
        return new, LeafAdam(new, self.lr, self.betas, self.eps, self.steps,
                             self.exp_avg[keep].clone(), self.exp_avg_sq[keep].clone())
