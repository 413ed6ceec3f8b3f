"""The automatic iso-level of `stages.mesh`: the density where training rays become half opaque.

Conventions:
- Everything is in the scene (training) frame: rays from the run's training views (`radiance.camera`), the box
  `aabb` [2, 3], densities per scene-frame unit.
- A ray is cut into equal steps of `diag(aabb) / samples` from max(near, box entry) to min(far, box exit)
  (`radiance.aabb.ray_aabb_segment`); the density is sampled at each step's midpoint and taken as constant
  over the step (midpoint rule); steps past the box exit have density 0.
- The crossing depth (accumulated opacity 0.5) is `radiance.compositing.median_depth`, exact for that
  piecewise-constant density; the density there is interpolated linearly between the neighbouring samples.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.camera import generate_rays
from nerfpipe.radiance.compositing import median_depth
from nerfpipe.stages.mesh.grid import DensityFn

__all__ = ["auto_threshold"]

LN2 = math.log(2.0)


def _training_rays(scene: Any, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """About n_rays rays on a regular pixel lattice over the training views (deterministic). [R, 3] x 2."""
    frames = scene.split("train") or tuple(range(len(scene.frames)))
    per_frame = max(1, n_rays // len(frames))
    origins, dirs = [], []
    for i in frames:
        intr = scene.frame_intrinsics(i)
        stride = max(1, int(math.sqrt(intr.w * intr.h / per_frame)))
        u = torch.arange(stride / 2, intr.w, stride, dtype=torch.float64)
        v = torch.arange(stride / 2, intr.h, stride, dtype=torch.float64)
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        uv = torch.stack([uu.reshape(-1), vv.reshape(-1)], dim=-1)
        o, d = generate_rays(intr, torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64), uv)
        origins.append(o)
        dirs.append(d)
    return torch.cat(origins), torch.cat(dirs)


def _crossing_levels(
    density: DensityFn,
    o: torch.Tensor,  # [r, 3] float64
    d: torch.Tensor,  # [r, 3] float64
    t0: torch.Tensor,  # [r] segment start
    t1: torch.Tensor,  # [r] segment end
    step: float,
    samples: int,
    device: torch.device,
) -> torch.Tensor:
    """Density at the half-opacity point of each ray of the chunk that reaches it: [r'] float64."""
    k = torch.arange(samples, dtype=torch.float64)
    t = t0[:, None] + (k + 0.5) * step  # [r, S] sample midpoints
    inside = t < t1[:, None]
    x = (o[:, None, :] + t[..., None] * d[:, None, :])[inside]  # [M, 3]
    sigma = torch.zeros_like(t)
    if x.shape[0]:
        sigma[inside] = density(x.to(device, torch.float32)).double().cpu()
    t_starts = t - 0.5 * step
    depth = median_depth(sigma, t_starts, t_starts + step)  # [r], inf where opacity stays below 0.5
    crossed = torch.isfinite(depth)
    sigma, depth, t_first = sigma[crossed], depth[crossed], t[crossed, 0]
    pos = (depth - t_first) / step  # in sample-index units (sample i at i)
    i0 = pos.floor().long().clamp(0, samples - 1)
    i1 = (i0 + 1).clamp(max=samples - 1)
    w = (pos - i0.double()).clamp(0, 1)
    rows = torch.arange(len(i0))
    return (1 - w) * sigma[rows, i0] + w * sigma[rows, i1]


def auto_threshold(
    density: DensityFn,
    scene: Any,
    aabb: np.ndarray,
    *,
    n_rays: int = 2048,
    samples: int = 512,
    device: torch.device | str = "cpu",
    chunk: int = 1 << 18,
) -> tuple[float, dict]:
    """Iso-level from the field: the median, over training rays that become half opaque inside `aabb`, of the
    density where the accumulated opacity first reaches 0.5 (rule and fallback: `stages.mesh`'s module doc;
    sampling: this module's). Returns (level, info for the report).
    """
    device = torch.device(device)
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    diag = float(np.linalg.norm(aabb[1] - aabb[0]))
    step = diag / samples
    o, d = _training_rays(scene, n_rays)
    t0, t1 = ray_aabb_segment(o, d, torch.as_tensor(aabb), float(scene.near), float(scene.far))
    valid = t1 > t0
    o, d, t0, t1 = o[valid], d[valid], t0[valid], t1[valid]
    rays_per_chunk = max(1, chunk // samples)
    levels = [
        _crossing_levels(density, *(v[a : a + rays_per_chunk] for v in (o, d, t0, t1)), step, samples, device)
        for a in range(0, o.shape[0], rays_per_chunk)
    ]
    n_valid = int(o.shape[0])
    lv = torch.cat(levels) if levels else torch.zeros(0, dtype=torch.float64)
    info: dict[str, Any] = {
        "rule": "median over training rays of the density where accumulated opacity first reaches 0.5",
        "rays": n_valid,
        "rays_reaching_half_opacity": int(lv.numel()),
        "step": step,
    }
    if lv.numel() < max(16, int(0.01 * n_valid)):
        level = LN2 / (0.01 * diag)
        info.update(
            rule="fallback: ln 2 / (1 % of the aabb diagonal): too few training rays reach 0.5 opacity", fallback=True
        )
        return level, info
    q = torch.quantile(lv, torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)).tolist()
    info.update(fallback=False, quartiles=q)
    return float(q[1]), info
