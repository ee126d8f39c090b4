"""The networks' optimisers, written out: torch's own, op for op, without torch's compiler.

* :class:`LeafAdam`: Adam on one leaf tensor, the fine networks' full-batch training. The update
  is ``torch.optim.Adam``'s (Kingma and Ba, 2015, with torch's defaults: betas (0.9, 0.999), eps
  1e-8, no weight decay: the networks' L2 penalty is in their loss).
* :class:`Adamax` and :class:`ReduceOnPlateau`: the pre-trained network's (paper 002,
  :mod:`.pretrained`) ``torch.optim.Adamax`` with its defaults over a list of leaves, and
  ``torch.optim.lr_scheduler.ReduceLROnPlateau`` with its defaults (mode min, relative
  threshold 1e-4, no cooldown, no floor, eps 1e-8).

Each is written out as torch's single-tensor implementation runs it on the CPU, so a training
gives the same bits with either. Why not torch's own: its optimisers import torch's compiler
front end (``torch._dynamo`` and ``torch._inductor``) on their first use, about 1.1 s of CPU in
every process that trains, more than all of heliocal's modules take to import; heliocal never
compiles. tests/test_adam.py compares each with torch's, to the bit, over a training's steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["Adamax", "LeafAdam", "ReduceOnPlateau"]


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


@dataclass
class Adamax:
    """Adamax's state for the leaves ``params`` (Kingma and Ba, 2015, section 7: Adam with the
    infinity norm; torch's defaults: betas (0.9, 0.999), eps 1e-8, no weight decay).

    ``step()`` applies one update from each leaf's ``grad``; ``zero_grad()`` drops the gradients
    (torch's default ``zero_grad(set_to_none=True)``); :class:`ReduceOnPlateau` lowers ``lr``."""

    params: list[torch.Tensor]
    lr: float
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    steps: int = 0
    exp_avg: list[torch.Tensor] = field(default=None)    # first moments, like params
    exp_inf: list[torch.Tensor] = field(default=None)    # infinity norms, like params

    def __post_init__(self) -> None:
        self.params = list(self.params)
        if self.exp_avg is None:
            self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format)
                            for p in self.params]
        if self.exp_inf is None:
            self.exp_inf = [torch.zeros_like(p, memory_format=torch.preserve_format)
                            for p in self.params]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One Adamax update of every leaf in place (torch's ``_single_tensor_adamax``,
        maximize and weight decay off; every leaf has a gradient: each is in the loss)."""
        beta1, beta2 = self.betas
        self.steps += 1
        step = float(self.steps)            # torch keeps the count as a tensor and reads a float
        clr = self.lr / (1 - beta1 ** step)
        for param, exp_avg, exp_inf in zip(self.params, self.exp_avg, self.exp_inf):
            grad = param.grad
            exp_avg.lerp_(grad, 1 - beta1)
            torch.maximum(exp_inf.mul_(beta2), grad.abs().add_(self.eps), out=exp_inf)
            param.addcdiv_(exp_avg, exp_inf, value=-clr)


@dataclass
class ReduceOnPlateau:
    """Halve (``factor``) the optimiser's ``lr`` when the watched loss has not improved for more
    than ``patience`` steps: torch's ``ReduceLROnPlateau`` with its defaults (an improvement is
    below the best so far times ``1 - threshold``; a change of ``lr`` by no more than ``eps`` is
    not made)."""

    optimizer: Adamax
    factor: float = 0.1
    patience: int = 10
    threshold: float = 1e-4
    eps: float = 1e-8
    best: float = float("inf")
    bad_epochs: int = 0

    def step(self, loss: float) -> None:
        current = float(loss)
        if current < self.best * (1.0 - self.threshold):
            self.best, self.bad_epochs = current, 0
        else:
            self.bad_epochs += 1
        if self.bad_epochs > self.patience:
            old_lr = float(self.optimizer.lr)
            new_lr = max(old_lr * self.factor, 0.0)
            if old_lr - new_lr > self.eps:
                self.optimizer.lr = new_lr
            self.bad_epochs = 0
