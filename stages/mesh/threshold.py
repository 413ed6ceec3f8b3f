"""The iso-level of `stages.mesh`: the density where training rays become half opaque, region by region.

Conventions:
- Everything is in the scene (training) frame: rays from the run's training views (`radiance.camera`), the box
  `aabb` [2, 3], densities per scene-frame unit.
- A ray is cut into equal steps of `diag(aabb) / samples` from max(near, box entry) to min(far, box exit)
  (`radiance.aabb.ray_aabb_segment`); the density is sampled at each step's midpoint and taken as constant
  over the step (midpoint rule); steps past the box exit have density 0.
- The crossing depth (accumulated opacity 0.5) is `radiance.compositing.median_depth`, exact for that
  piecewise-constant density; the density there is interpolated linearly between the neighbouring samples.

Rules (`Crossings` holds what the rays found; the stage picks the rule):
- `local_levels` (the default, "auto"): a level that varies over space (`LevelField`). Each crossing ray gives a
  level, the density at its crossing, at its crossing point; the level at x is the geometric mean of the levels of
  the crossings near x (a Gaussian of `LEVEL_RADIUS` of the box diagonal), pulled towards the global median where
  few crossings are near (`PRIOR_WEIGHT` crossings' worth). Why: one level for the whole scene is set by its
  largest surface. On the demo (138 and 675 training steps) the disk's crossings have a median level 3-4 times its
  objects' (docs/DESIGN.md, "Mesh level"): at the disk's level the objects' sides are below it and only their tops
  or nothing is meshed, and what is left of them is removed by the cleanup as small pieces. Where the field shows a
  surface the mesh is put where the training views' depth puts it, region by region.
- `global_level` ("global"): the median over all crossing rays; fewer than max(16, 1 %) of the rays crossing: the
  level falls back to ln 2 / (1 % of the aabb diagonal), the density at which 1 % of the box diagonal is half
  opaque.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.ndimage
import torch

from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.camera import generate_rays
from nerfpipe.radiance.compositing import median_depth
from nerfpipe.stages.mesh.grid import DensityFn

__all__ = [
    "Crossings",
    "LevelField",
    "march_crossings",
    "training_rays",
    "global_level",
    "local_levels",
    "auto_threshold",
    "level_field",
    "LEVEL_RADIUS",
    "PRIOR_WEIGHT",
    "LEVEL_SPREAD",
]

LN2 = math.log(2.0)
LEVEL_RADIUS = 0.02
"""The local level's Gaussian (its standard deviation), as a fraction of the box diagonal."""
PRIOR_WEIGHT = 2.0
"""The global statistics count as this many crossings at every point (where no crossing is near, they rule)."""
LEVEL_SPREAD = 1.0
"""The level lies this many standard deviations of the log crossing levels below their mean (module doc)."""
LEVEL_CELLS = 48
"""Cells of the level grid along the box's longest side (about 2 per LEVEL_RADIUS)."""


@dataclass(frozen=True, kw_only=True)
class Crossings:
    """Training rays marched through the field: where each becomes half opaque, and the density there."""

    origins: np.ndarray  # [R, 3] float64
    dirs: np.ndarray  # [R, 3] float64, unit
    depth: np.ndarray  # [R] distance along the ray to the crossing; inf where the ray never becomes half opaque
    level: np.ndarray  # [R] density at the crossing; nan where none
    opacity: np.ndarray  # [R] the ray's opacity through the whole box, 1 - exp(-sum sigma step)
    frame: np.ndarray  # [R] int: the training frame (index into scene.frames) of each ray
    pixel: np.ndarray  # [R, 2] float64: the pixel (u, v) of each ray in its frame's full-size image
    stride: dict[int, int]  # frame -> the pixel lattice's stride
    step: float

    @property
    def crossed(self) -> np.ndarray:  # [R] bool
        return np.isfinite(self.depth)

    @property
    def points(self) -> np.ndarray:  # [R', 3] the crossing points of the rays that cross
        c = self.crossed
        return self.origins[c] + self.depth[c, None] * self.dirs[c]


def training_rays(scene: Any, n_rays: int, frames: list[int] | None = None):
    """About n_rays rays on a regular pixel lattice over the training views (or `frames`), deterministic.
    -> (origins [R, 3], dirs [R, 3] float64 tensors, frame [R] int, pixel [R, 2], {frame: stride})."""
    if frames is None:
        frames = list(scene.split("train") or range(len(scene.frames)))
    per_frame = max(1, n_rays // max(1, len(frames)))
    origins, dirs, which, pixels, strides = [], [], [], [], {}
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
        which.append(np.full(len(uv), i))
        pixels.append(uv.numpy())
        strides[int(i)] = stride
    return torch.cat(origins), torch.cat(dirs), np.concatenate(which), np.concatenate(pixels), strides


def _march_chunk(
    density: DensityFn,
    o: torch.Tensor,  # [r, 3] float64
    d: torch.Tensor,  # [r, 3] float64
    t0: torch.Tensor,  # [r] segment start
    t1: torch.Tensor,  # [r] segment end
    step: float,
    samples: int,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(crossing depth [r] (inf: none), density there [r] (nan: none), opacity through the box [r]) of each ray of
    the chunk."""
    k = torch.arange(samples, dtype=torch.float64)
    t = t0[:, None] + (k + 0.5) * step  # [r, S] sample midpoints
    inside = t < t1[:, None]
    x = (o[:, None, :] + t[..., None] * d[:, None, :])[inside]  # [M, 3]
    sigma = torch.zeros_like(t)
    if x.shape[0]:
        sigma[inside] = density(x.to(device, torch.float32)).double().cpu()
    t_starts = t - 0.5 * step
    depth = median_depth(sigma, t_starts, t_starts + step)  # [r], inf where opacity stays below 0.5
    level = torch.full_like(depth, math.nan)
    crossed = torch.isfinite(depth)
    s, pos = sigma[crossed], (depth[crossed] - t[crossed, 0]) / step  # in sample-index units (sample i at i)
    i0 = pos.floor().long().clamp(0, samples - 1)
    i1 = (i0 + 1).clamp(max=samples - 1)
    w = (pos - i0.double()).clamp(0, 1)
    rows = torch.arange(len(i0))
    level[crossed] = (1 - w) * s[rows, i0] + w * s[rows, i1]
    opacity = -torch.expm1(-(sigma * step).sum(dim=1))
    return depth, level, opacity


def march_crossings(
    density: DensityFn,
    scene: Any,
    aabb: np.ndarray,
    *,
    n_rays: int = 2048,
    samples: int = 512,
    device: torch.device | str = "cpu",
    chunk: int = 1 << 18,
) -> Crossings:
    """March about `n_rays` training rays (`training_rays`) through `aabb` (module doc) -> `Crossings` (rays that
    miss the box are left out)."""
    device = torch.device(device)
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    step = float(np.linalg.norm(aabb[1] - aabb[0])) / samples
    o, d, frame, pixel, strides = training_rays(scene, n_rays)
    t0, t1 = ray_aabb_segment(o, d, torch.as_tensor(aabb), float(scene.near), float(scene.far))
    valid = t1 > t0
    o, d, t0, t1 = o[valid], d[valid], t0[valid], t1[valid]
    keep = valid.numpy()
    per = max(1, chunk // samples)
    parts = [
        _march_chunk(density, *(v[a : a + per] for v in (o, d, t0, t1)), step, samples, device)
        for a in range(0, o.shape[0], per)
    ]
    depth, level, opacity = (
        torch.cat([p[k] for p in parts]) if parts else torch.zeros(0, dtype=torch.float64) for k in range(3)
    )
    return Crossings(
        origins=o.numpy(),
        dirs=d.numpy(),
        depth=depth.numpy(),
        level=level.numpy(),
        opacity=opacity.numpy(),
        frame=frame[keep],
        pixel=pixel[keep],
        stride=strides,
        step=step,
    )


def global_level(crossings: Crossings, aabb: np.ndarray) -> tuple[float, dict]:
    """The median crossing level, or the fallback (module doc). -> (level, info for the report)."""
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    lv = crossings.level[crossings.crossed]
    n_valid = len(crossings.depth)
    info: dict[str, Any] = {
        "rule": "median over training rays of the density where accumulated opacity first reaches 0.5",
        "rays": n_valid,
        "rays_reaching_half_opacity": int(lv.size),
        "step": crossings.step,
    }
    if lv.size < max(16, int(0.01 * n_valid)):
        level = LN2 / (0.01 * float(np.linalg.norm(aabb[1] - aabb[0])))
        info.update(
            rule="fallback: ln 2 / (1 % of the aabb diagonal): too few training rays reach 0.5 opacity", fallback=True
        )
        return level, info
    q = np.quantile(lv, [0.25, 0.5, 0.75]).tolist()
    info.update(fallback=False, quartiles=q)
    return float(q[1]), info


@dataclass(frozen=True, kw_only=True)
class LevelField:
    """A level varying over space: log-levels on a grid of cubic cells over a box (scene frame), trilinear between
    cell centres, constant beyond the outer ones."""

    lo: np.ndarray  # [3] the box's corner
    cell: float  # cell side
    log_level: np.ndarray  # [n0, n1, n2] float64

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """x [N, 3] scene frame -> level [N] (x's dtype and device): trilinear in the log level between cell
        centres (`grid_sample`, align_corners: its -1 and 1 are the outer centres), clamped beyond them (border)."""
        grid = torch.as_tensor(self.log_level, dtype=torch.float32, device=x.device)[None, None]  # [1, 1, n0, n1, n2]
        n = torch.tensor(self.log_level.shape, dtype=torch.float32, device=x.device)
        f = (x.float() - torch.as_tensor(self.lo, dtype=torch.float32, device=x.device)) / self.cell - 0.5
        g = torch.where(n > 1, 2.0 * f / (n - 1).clamp(min=1) - 1.0, torch.zeros_like(f))  # [N, 3] in [-1, 1]
        # grid_sample's last axis is (x, y, z) = (n2, n1, n0): the volume's axes reversed
        out = torch.nn.functional.grid_sample(
            grid, g.flip(-1)[None, :, None, None], mode="bilinear", padding_mode="border", align_corners=True
        )
        return torch.exp(out.reshape(-1)).to(x.dtype)

    def normalise(self, density: DensityFn) -> DensityFn:
        """The density divided by the level: its iso-surface at 1 is the density's at the local level."""

        def normalised(x: torch.Tensor) -> torch.Tensor:
            sigma = density(x)
            return sigma / self(x.to(sigma.device)).to(sigma.dtype)

        return normalised


def level_field(points: np.ndarray, levels: np.ndarray, aabb: np.ndarray) -> tuple[LevelField, dict]:
    """The local rule (module doc) from levels [N] > 0 at points [N, 3] (scene frame) in `aabb` [2, 3]: per cell of
    the level grid the Gaussian-weighted mean m and standard deviation s of the log levels, the global ones counting
    PRIOR_WEIGHT crossings; the level is exp(m - LEVEL_SPREAD s). -> (field, figures for the report)."""
    extent = aabb[1] - aabb[0]
    cell = float(extent.max()) / LEVEL_CELLS
    shape = np.maximum(np.ceil(extent / cell - 1e-9), 1).astype(int)
    idx = tuple(np.clip(np.floor((points - aabb[0]) / cell).astype(int), 0, shape - 1).T)
    logs = np.log(np.maximum(levels, np.finfo(np.float64).tiny))
    sums = [np.zeros(shape) for _ in range(3)]  # weight, sum of logs, sum of squared logs
    for total, values in zip(sums, (np.ones_like(logs), logs, logs * logs), strict=True):
        np.add.at(total, idx, values)
    sigma = LEVEL_RADIUS * float(np.linalg.norm(extent)) / cell
    norm = (2 * math.pi * sigma**2) ** 1.5  # a Gaussian's peak is 1 / norm of its total: one crossing counts 1 there
    w, s1, s2 = (scipy.ndimage.gaussian_filter(t, sigma, mode="constant") * norm for t in sums)
    mean0, var0 = float(np.median(logs)), float(np.var(logs))
    mean = (s1 + PRIOR_WEIGHT * mean0) / (w + PRIOR_WEIGHT)
    var = np.maximum((s2 + PRIOR_WEIGHT * (var0 + mean0 * mean0)) / (w + PRIOR_WEIGHT) - mean * mean, 0.0)
    log_level = mean - LEVEL_SPREAD * np.sqrt(var)
    field = LevelField(lo=aabb[0], cell=cell, log_level=log_level)
    at = np.exp(log_level[idx])
    info = {
        "cells": shape.tolist(),
        "at_crossings_quartiles": np.quantile(at, [0.25, 0.5, 0.75]).tolist(),
        "range": [float(np.exp(log_level.min())), float(np.exp(log_level.max()))],
    }
    return field, info


def local_levels(crossings: Crossings, aabb: np.ndarray) -> tuple[LevelField | None, float, dict]:
    """(the level field from the rays' own crossing levels, the global median level, info for the report): module
    doc. None (and the global rule's level) where too few rays cross for the global median (its fallback)."""
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    median, info = global_level(crossings, aabb)
    if info["fallback"]:
        return None, median, info
    field, figures = level_field(crossings.points, crossings.level[crossings.crossed], aabb)
    info.update(
        rule=f"by region: exp(m - {LEVEL_SPREAD:g} s), m and s the mean and standard deviation of the log crossing "
        f"levels within a Gaussian of {LEVEL_RADIUS:.0%} of the box diagonal (the global ones counting "
        f"{PRIOR_WEIGHT:g} crossings)",
        global_median=median,
        rays_pass=figures,
    )
    return field, median, info


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
    """The global rule (`global_level`) in one call: (level, info)."""
    crossings = march_crossings(density, scene, aabb, n_rays=n_rays, samples=samples, device=device, chunk=chunk)
    return global_level(crossings, aabb)
