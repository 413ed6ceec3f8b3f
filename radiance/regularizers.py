"""Losses on the weights along rays (packed layout of radiance.compositing).

`distortion_loss` is mip-NeRF 360's L_dist (Barron et al. 2022, eq. 15): for the intervals [s0_i, s1_i] of one ray
in a normalised distance s (0 at the ray's start, 1 at its end) with weights w_i and midpoints m_i,
    L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s1_i - s0_i),
the mean over rays. It is small when a ray's weight is one compact peak and large for fog spread along it (the
floaters near the cameras of a short real capture). With samples sorted along each ray the double sum is
2 sum_i w_i (m_i W_<i - (wm)_<i), W_<i and (wm)_<i exclusive cumulative sums along the ray: O(N), not O(N^2).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nerfpipe.radiance.compositing import segment_cumsum

__all__ = ["distortion_loss", "distortion_loss_reference", "depth_nll_loss"]


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


def depth_nll_loss(
    weights: Tensor,  # [N] packed
    t_starts: Tensor,  # [N] interval starts along the rays (the units of `depth`)
    t_ends: Tensor,  # [N]
    ray_indices: Tensor,  # [N] long
    depth: Tensor,  # [R] the known distance at which each ray meets a surface
    sigma: Tensor,  # [R] its uncertainty (> 0)
) -> Tensor:  # [] mean over rays
    """DS-NeRF's depth loss (Deng et al. 2022, as nerfstudio's `ds_nerf_depth_loss`), with a normalised kernel:
        L_r = - sum_i log(w_i + eps) * N(m_i; depth_r, sigma_r) * (t1_i - t0_i),
    m_i the interval midpoint, N the Gaussian density, eps the dtype's eps: the negative log-likelihood that the ray
    ends at the known depth. Its minimum puts the ray's weight in one peak there, so it removes the fog in front of
    a surface that sparse structure-from-motion points vouch for. Samples far from the depth carry no loss; a ray
    with no sample near its depth (skipped as empty) contributes 0."""
    if not (weights.shape == t_starts.shape == t_ends.shape == ray_indices.shape) or weights.ndim != 1:
        raise ValueError(
            f"expected weights, t_starts, t_ends, ray_indices [N], got "
            f"{[tuple(t.shape) for t in (weights, t_starts, t_ends, ray_indices)]}"
        )
    if depth.ndim != 1 or depth.shape != sigma.shape or depth.numel() < 1:
        raise ValueError(f"expected depth, sigma [R] with R >= 1, got {tuple(depth.shape)}, {tuple(sigma.shape)}")
    if weights.numel() == 0:
        return weights.sum()
    eps = torch.finfo(weights.dtype).eps
    mid = 0.5 * (t_starts + t_ends)
    z = (mid - depth[ray_indices]) / sigma[ray_indices]
    kernel = torch.exp(-0.5 * z * z) / (sigma[ray_indices] * math.sqrt(2.0 * math.pi))
    return -(torch.log(weights + eps) * kernel * (t_ends - t_starts)).sum() / depth.shape[0]
