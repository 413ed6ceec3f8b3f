"""The step `pretrain-voxels` runs on the one training loop (`model.loop.TrainingLoop`).

A shapes dataset (`nerfpipe shapes`: inputs uint8 [N, 4, SIDE, SIDE], occupancy bits [N, RES^3 / 8]) is held in
memory; each step draws `batch` examples, mirrors half of them left-right (the photo's columns and the grid's x:
a mirrored object is an object too), and takes one Adam step on the binary cross-entropy of the logits against
the occupancy (a cell is occupied where at least half of it is inside the shape). Logged: the loss and the batch's
IoU at 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from nerfpipe.model.loop import NetStepper
from nerfpipe.model.voxels.net import VoxelNet

__all__ = ["ShapeSet", "unpack", "iou", "VoxelStep"]


@dataclass
class ShapeSet:
    inputs: torch.Tensor  # [N, 4, SIDE, SIDE] uint8
    bits: torch.Tensor  # [N, RES^3 / 8] uint8 (numpy packbits order, big-endian bits)
    res: int


def unpack(bits: np.ndarray | torch.Tensor, res: int) -> torch.Tensor:
    """Occupancy bits [B, res^3 / 8] -> float32 [B, res, res, res] of 0 / 1."""
    b = bits.numpy() if isinstance(bits, torch.Tensor) else bits
    return torch.from_numpy(np.unpackbits(b, axis=-1).reshape(-1, res, res, res).astype(np.float32))


def iou(prob: torch.Tensor, truth: torch.Tensor, level: float = 0.5) -> float:
    """Intersection over union of `prob >= level` and `truth >= 0.5` (any matching shapes); nan when both empty."""
    p, t = prob >= level, truth >= 0.5
    union = (p | t).sum().item()
    return (p & t).sum().item() / union if union else float("nan")


@dataclass(eq=False, kw_only=True)
class VoxelStep(NetStepper):
    """A `model.loop.Stepper` (module doc)."""

    net: VoxelNet
    data: ShapeSet
    gen: torch.Generator
    device: torch.device
    batch: int
    on_log: Any  # (step, loss, iou, lr) -> None, after each good step
    last_loss: float = float("nan")
    last_iou: float = float("nan")

    def train_step(self, lr: float) -> bool:
        self.net.train()
        idx = torch.randint(len(self.data.inputs), (self.batch,), generator=self.gen)
        x = self.data.inputs[idx].float().div_(255.0)
        y = unpack(self.data.bits[idx], self.data.res)
        flip = torch.rand(self.batch, generator=self.gen) < 0.5
        x[flip] = x[flip].flip(-1)  # image columns
        y[flip] = y[flip].flip(1)  # grid x
        x, y = x.to(self.device), y.to(self.device)
        logits = self.net(x)
        loss = F.binary_cross_entropy_with_logits(logits, y)
        if not torch.isfinite(loss):
            return False
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.last_loss = float(loss.detach())
        self.last_iou = iou(torch.sigmoid(logits.detach()), y)
        return True

    def log(self, lr: float) -> None:
        self.on_log(self.step, self.last_loss, self.last_iou, lr)
