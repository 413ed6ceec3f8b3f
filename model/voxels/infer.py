"""The network's occupancy for photos: one forward pass, or the mean with the mirrored photo's (the default).

Pretraining mirrors half its photos left-right together with their grids (`model.voxels.pretrain`: a mirrored
object is an object too), so the network has learnt both halves of that pair. Predicting the mirrored photo too
and mirroring its grid back gives a second estimate of the same shape in the same view frame; their mean is
mirror-consistent by construction (mirroring the photo mirrors the prediction exactly) and scored better on
held-out objects (docs/VOXELS.md). It costs a second forward pass.
"""

from __future__ import annotations

import torch

__all__ = ["occupancy"]


def occupancy(net: torch.nn.Module, x: torch.Tensor, *, mirror: bool = True, batch: int = 64) -> torch.Tensor:
    """x [B, C, S, S] float in [0, 1] (`model.voxels.inputs.prepare`) -> probabilities [B, R, R, R], indexed (x, y,
    z) in each photo's view frame; `mirror`: the mean of the photo's and its mirror's (module doc). On the net's
    device, `batch` photos at a time; returned on the CPU."""
    if x.ndim != 4:
        raise ValueError(f"expected photos [B, C, S, S], got shape {tuple(x.shape)}")
    device = next(net.parameters()).device
    net.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(x), batch):
            chunk = x[i : i + batch].to(device=device, dtype=torch.float32)
            prob = torch.sigmoid(net(chunk))  # [b, R, R, R]
            if mirror:
                prob = 0.5 * (prob + torch.sigmoid(net(chunk.flip(-1))).flip(1))  # image columns <-> grid x
            out.append(prob.cpu())
    return torch.cat(out)
