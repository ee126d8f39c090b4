"""Small vector helpers shared by the physics and the models (torch, any leading dimensions)."""

from __future__ import annotations

import torch

__all__ = ["unit_vector"]


def unit_vector(v: torch.Tensor) -> torch.Tensor:
    """``v`` (..., 3) scaled to length 1 along its last axis (a zero vector gives NaN)."""
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)
