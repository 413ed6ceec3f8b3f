"""NeuS's discrete opacity (Wang et al. 2021) written as an optical depth, and the compositing of a padded batch.

Between two points of a ray with signed distances f0 then f1 (inside negative), NeuS's opacity is
    alpha = max((Phi_s(f0) - Phi_s(f1)) / Phi_s(f0), 0),   Phi_s(f) = sigmoid(s f)  (the logistic CDF),
s the learned sharpness. Written as an optical depth it is
    tau = max(log Phi_s(f0) - log Phi_s(f1), 0),   alpha = -expm1(-tau),
with log Phi = logsigmoid: finite for every finite f and s, where the plain ratio is 0 / 0 once Phi_s(f0)
underflows (a sample deep inside, s f0 < -104 in float32) and loses every digit of alpha near 0 (1 - a ratio
near 1). Transmittance is exp(-exclusive_cumsum(tau)) as everywhere in nerfpipe (`radiance.compositing`), so
the weights are `radiance.compositing`'s for the same tau. `neus_alpha_reference` is the plain formula (the twin
the tests compare outputs and gradients with where it is defined).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfpipe.radiance.compositing import exclusive_cumsum
from nerfpipe.radiance.safe import safe_div

__all__ = ["neus_tau", "neus_alpha_reference", "weights_from_tau", "composite_weights", "composite_tau"]


def neus_tau(f0: Tensor, f1: Tensor, s: Tensor | float) -> Tensor:
    """Optical depth of each interval from the signed distances at its ends, f0 and f1 (any shape), and the
    sharpness s (> 0, scalar or broadcastable): max(logsigmoid(s f0) - logsigmoid(s f1), 0)."""
    return F.relu(F.logsigmoid(s * f0) - F.logsigmoid(s * f1))


def neus_alpha_reference(f0: Tensor, f1: Tensor, s: Tensor | float) -> Tensor:
    """Plain twin: NeuS's clip((Phi(s f0) - Phi(s f1)) / Phi(s f0), 0, 1) (for tests; 0 / 0 is nan)."""
    p0, p1 = torch.sigmoid(s * f0), torch.sigmoid(s * f1)
    return ((p0 - p1) / p0).clamp(0, 1)


def weights_from_tau(tau: Tensor) -> Tensor:
    """tau [R, S] -> compositing weights [R, S]: exp(-exclusive_cumsum(tau)) * -expm1(-tau)."""
    return torch.exp(-exclusive_cumsum(tau)) * -torch.expm1(-tau)


def composite_weights(
    weights: Tensor,  # [R, S]
    rgb: Tensor,  # [R, S, 3]
    t_mid: Tensor,  # [R, S] distance of each interval's colour sample
    background: Tensor,  # [3] or [R, 3]
) -> dict[str, Tensor]:
    """Emission-absorption over padded intervals: rgb [R, 3] (over the background), acc [R], depth [R] (expected t,
    over acc clamped at its dtype's epsilon), depth_median [R] (the first interval where the accumulated weight
    reaches 0.5, at its colour sample; inf when it never does), weights [R, S]."""
    acc = weights.sum(-1)  # [R]
    colour = (weights[..., None] * rgb).sum(-2) + (1 - acc)[:, None] * background.to(rgb)
    depth = safe_div((weights * t_mid).sum(-1), acc)
    with torch.no_grad():
        reached = torch.cumsum(weights, -1) >= 0.5  # [R, S]
        first = reached.int().argmax(-1, keepdim=True)  # [R, 1]
        median = torch.where(reached.any(-1), t_mid.gather(-1, first)[:, 0], torch.full_like(acc, float("inf")))
    return {"rgb": colour, "acc": acc, "depth": depth, "depth_median": median, "weights": weights}


def composite_tau(tau: Tensor, rgb: Tensor, t_mid: Tensor, background: Tensor) -> dict[str, Tensor]:
    """`composite_weights` of `weights_from_tau(tau)` (tau [R, S], rgb [R, S, 3], t_mid [R, S], background [3])."""
    return composite_weights(weights_from_tau(tau), rgb, t_mid, background)
