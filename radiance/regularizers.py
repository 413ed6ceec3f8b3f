"""Losses on the weights along rays (packed layout of radiance.compositing).

`distortion_loss` is mip-NeRF 360's L_dist (Barron et al. 2022, eq. 15): for the intervals [s0_i, s1_i] of one ray
in a normalised distance s (0 at the ray's start, 1 at its end) with weights w_i and midpoints m_i,
    L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s1_i - s0_i),
the mean over rays. It is small when a ray's weight is one compact peak and large for fog spread along it (the
floaters near the cameras of a short real capture). With samples sorted along each ray the double sum is
2 sum_i w_i (m_i W_<i - (wm)_<i), W_<i and (wm)_<i exclusive cumulative sums along the ray: O(N), not O(N^2).
"""

from __future__ import annotations

from torch import Tensor

from radiance.compositing import segment_cumsum

__all__ = ["distortion_loss", "distortion_loss_reference"]


def distortion_loss(
    weights: Tensor,  # [N] packed, sorted by ray then s
    s0: Tensor,  # [N] normalised interval starts
    s1: Tensor,  # [N] normalised interval ends
    ray_indices: Tensor,  # [N] long, non-decreasing
    n_rays: int,
) -> Tensor:  # [] mean over rays
    if not (weights.shape == s0.shape == s1.shape == ray_indices.shape) or weights.ndim != 1:
        raise ValueError(
            f"expected weights, s0, s1, ray_indices [N], got {[tuple(t.shape) for t in (weights, s0, s1)]}"
        )
    if n_rays < 1:
        raise ValueError(f"expected n_rays >= 1, got {n_rays}")
    if weights.numel() == 0:
        return weights.sum()
    m = 0.5 * (s0 + s1)
    w_before = segment_cumsum(weights, ray_indices, n_rays)  # [N] exclusive
    wm_before = segment_cumsum(weights * m, ray_indices, n_rays)
    cross = 2.0 * (weights * (m * w_before - wm_before)).sum()
    own = (weights * weights * (s1 - s0)).sum() / 3.0
    return (cross + own) / n_rays


def distortion_loss_reference(weights: Tensor, s0: Tensor, s1: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:
    """Plain O(N^2)-per-ray twin of `distortion_loss` (for tests; keeps autograd)."""
    total = weights.new_zeros(())
    m = 0.5 * (s0 + s1)
    for r in range(n_rays):
        sel = ray_indices == r
        w, mr, d = weights[sel], m[sel], (s1 - s0)[sel]
        total = total + (w[:, None] * w[None, :] * (mr[:, None] - mr[None, :]).abs()).sum() + (w * w * d).sum() / 3
    return total / n_rays
