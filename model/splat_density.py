"""Adaptive density control for splats during their optimisation (3DGS section 5, gsplat's default strategy).

Between two refinements `GradStats` sums, for every Gaussian a view draws, the norm of the loss's gradient with
respect to its projected centre, in the half-image units 3DGS thresholds (pixel gradient x (W / 2, H / 2)), and
counts the views. `refine` then, on the mean of that norm:
- above GRAD_THRESHOLD (the Gaussian sits where the image is under-fitted) and small (largest scale at most
  PERCENT_DENSE x the scene extent): cloned (a copy in place; the two drift apart under the optimiser);
- above it and large: split in two, centres drawn from the Gaussian itself, scales / SPLIT_SHRINK;
- opacity below MIN_OPACITY: pruned.
New Gaussians start with zero Adam moments, kept ones keep theirs (`carry_adam`). The count is capped (`limit`):
when more qualify, the ones with the largest gradients go first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.radiance import splats as sp

__all__ = [
    "GRAD_THRESHOLD",
    "PERCENT_DENSE",
    "MIN_OPACITY",
    "SPLIT_SHRINK",
    "GradStats",
    "refine",
    "swap_parameters",
    "carry_adam",
]

GRAD_THRESHOLD = 2e-4
"""Mean view-space gradient norm (half-image units) above which a Gaussian is cloned or split (3DGS)."""
PERCENT_DENSE = 0.01
"""Largest scale, as a fraction of the scene extent, up to which a Gaussian is cloned rather than split (3DGS)."""
MIN_OPACITY = 0.005
"""Gaussians below this opacity are pruned (3DGS)."""
SPLIT_SHRINK = 1.6
"""A split Gaussian's two halves have its scales / this (3DGS)."""


@dataclass
class GradStats:
    """Per-Gaussian sums since the last refinement: gradient norms [N] and views that drew the Gaussian [N]."""

    total: Tensor
    count: Tensor

    @classmethod
    def zeros(cls, n: int, device: torch.device | str = "cpu") -> GradStats:
        return cls(torch.zeros(n, device=device), torch.zeros(n, device=device))

    def add(self, grad2d: Tensor, visible: Tensor, w: int, h: int) -> None:
        """One view's gradient w.r.t. the projected centres [N, 2] (pixels) and the Gaussians it drew [N] bool."""
        norm = torch.linalg.norm(grad2d.detach().float() * grad2d.new_tensor([w / 2, h / 2]).float(), dim=-1)
        self.total += torch.where(visible, norm, torch.zeros_like(norm))
        self.count += visible.float()

    def mean(self) -> Tensor:
        return self.total / self.count.clamp_min(1)


def refine(
    splats: sp.Splats, stats: GradStats, *, extent: float, limit: int, gen: torch.Generator
) -> tuple[sp.Splats, Tensor, Tensor, dict]:
    """Clone, split and prune (module doc) -> (the new Gaussians, detached; `source` [M] the old row each new row
    comes from; `fresh` [M] bool, the rows that are new; counts for the report). At most `limit` Gaussians after."""
    with torch.no_grad():
        n = len(splats)
        grad = stats.mean().to(splats.means.device)
        prune = torch.sigmoid(splats.opacity_logits) < MIN_OPACITY
        grow = (grad > GRAD_THRESHOLD) & ~prune
        room = max(0, limit - int(n - prune.sum()))
        if int(grow.sum()) > room:  # the largest gradients first; a split adds one net, a clone one
            cut = torch.topk(torch.where(grow, grad, torch.full_like(grad, -1.0)), room).indices
            grow = torch.zeros_like(grow)
            grow[cut] = True
        big = torch.exp(splats.log_scales).max(dim=-1).values > PERCENT_DENSE * extent
        clone, split = grow & ~big, grow & big
        keep = ~prune & ~split
        idx_keep, idx_clone, idx_split = (torch.nonzero(m).squeeze(1) for m in (keep, clone, split))
        # two halves of each split Gaussian, centres drawn from it: mean + R (s * z)
        rot = sp.quat_to_rotmat(splats.quats[idx_split]).repeat(2, 1, 1)
        scales = torch.exp(splats.log_scales[idx_split]).repeat(2, 1)
        z = torch.randn(scales.shape, generator=gen, dtype=scales.dtype).to(scales.device)
        halves = splats.means[idx_split].repeat(2, 1) + (rot @ (scales * z)[..., None])[..., 0]
        source = torch.cat([idx_keep, idx_clone, idx_split, idx_split])
        params = [p[source].clone() for p in splats.parameters()]
        s0 = idx_keep.shape[0] + idx_clone.shape[0]
        params[0][s0:] = halves
        params[1][s0:] -= math.log(SPLIT_SHRINK)
        fresh = torch.arange(source.shape[0], device=source.device) >= idx_keep.shape[0]
    counts = {
        "cloned": int(idx_clone.shape[0]),
        "split": int(idx_split.shape[0]),
        "pruned": int(prune.sum()),
        "gaussians": int(source.shape[0]),
    }
    return sp.Splats(*params), source, fresh, counts


def swap_parameters(opt: torch.optim.Optimizer, old: list[Tensor], new: list[Tensor]) -> list[dict]:
    """Put each `new` parameter in `opt` where the `old` one was; returns the old ones' optimiser states, taken out
    of `opt` (in `old`'s order; {} for a parameter that had none yet)."""
    by_id = {id(p): q for p, q in zip(old, new, strict=True)}
    for group in opt.param_groups:
        group["params"] = [by_id.get(id(p), p) for p in group["params"]]
    return [opt.state.pop(p, {}) for p in old]


def carry_adam(opt: torch.optim.Optimizer, old: list[Tensor], new: list[Tensor], source: Tensor, fresh: Tensor) -> None:
    """Put the `new` parameters in `opt` where the `old` ones were (`swap_parameters`), with their Adam moments: row r
    takes old row source[r]'s, zero where `fresh`."""
    for q, state in zip(new, swap_parameters(opt, old, new), strict=True):
        if not state:
            continue
        for key in ("exp_avg", "exp_avg_sq"):
            v = state[key][source]
            v[fresh] = 0
            state[key] = v
        opt.state[q] = state
