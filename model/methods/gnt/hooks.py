"""GNT's piece of the training loop: each step's rays come from a few training photos (`GntBatches`), so that
only their sources' features are computed with gradients (GNT draws a step's rays from one photo)."""

from __future__ import annotations

import torch
from torch import Tensor

from nerfpipe.model.methods.hooks import Hook, LoopState

__all__ = ["GntBatches"]


class GntBatches(Hook):
    """Draws a step's n rays evenly from `per_step` photos picked at random (uniform pixels within each)."""

    name = "gnt_batches"

    def __init__(self, offsets: Tensor, per_step: int):
        self.offsets = offsets  # [V + 1] int64: photo v's pixels are offsets[v]:offsets[v + 1]
        self.per_step = min(per_step, offsets.numel() - 1)

    def draw(self, loop: LoopState, n: int) -> Tensor:
        v = self.offsets.numel() - 1
        photos = torch.randperm(v, generator=loop.gen)[: self.per_step]  # [P]
        owner = photos[torch.arange(n) % self.per_step]  # [n] each ray's photo
        start, size = self.offsets[owner], self.offsets[owner + 1] - self.offsets[owner]
        return start + (torch.rand(n, generator=loop.gen, dtype=torch.float64) * size).long().clamp(max=size - 1)
