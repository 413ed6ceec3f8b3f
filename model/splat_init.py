"""Gaussian splats from a trained field ("NeRF to Gaussian splats"): where the training rays end.

`gaussians_from_field` sends rounds of `count` x INIT_RAYS_PER_GAUSSIAN rays through random pixels of the training
views (views drawn in proportion to their pixels), until `count` of them hit a surface or `count` x
INIT_MAX_RAYS_PER_GAUSSIAN were sent, and renders them with `Trained.render_rays`. A ray whose accumulated opacity
reaches OPAQUE and whose expected depth is within INIT_DEPTH_AGREEMENT of its median depth (the ray ends on one
surface) gives a Gaussian at its median depth, coloured with the field's colour there (the render with the background
taken out: (rgb - (1 - acc) bg) / acc), isotropic, its size INIT_KNN_FRACTION x the root mean square distance to its
3 nearest neighbours (scipy cKDTree), at least the pixel footprint t / f of its ray (the local sample spacing),
opacity INIT_OPACITY, SH degree 0. `count` of those rays are kept at random.

Why the median depth and these sizes: the expected depth puts a ray that meets a floater and then the wall half way
between them, and those Gaussians cover the other views; more opaque or larger Gaussians scored lower. The stage
starts from fewer (50k): a weaker start, but more optimisation steps in its budget, and a better end (figures:
docs/MEASUREMENTS.md, "Splats").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.model.cameras import OPAQUE
from nerfpipe.radiance import splats as sp
from nerfpipe.radiance.camera import Intrinsics, generate_rays

__all__ = [
    "gaussians_from_field",
    "INIT_RAYS_PER_GAUSSIAN",
    "INIT_MAX_RAYS_PER_GAUSSIAN",
    "INIT_OPACITY",
    "INIT_DEPTH_AGREEMENT",
    "INIT_KNN_FRACTION",
]

INIT_RAYS_PER_GAUSSIAN = 2
"""Rays sent a round, per Gaussian asked for; rounds go on until as many rays as Gaussians hit a surface."""
INIT_MAX_RAYS_PER_GAUSSIAN = 8
"""Rounds stop after this many rays per Gaussian asked for (an object that fills a quarter of its views still gets
its count)."""
INIT_OPACITY = 0.3
INIT_DEPTH_AGREEMENT = 0.1
"""A ray gives a Gaussian only when its expected depth is within this fraction of its median depth (one surface)."""
INIT_KNN_FRACTION = 0.3
"""A Gaussian's initial size: this fraction of the rms distance to its 3 nearest neighbours (at least the footprint)."""


def gaussians_from_field(
    trained: Any, intrinsics: list[Intrinsics], world_from_cams: list[Tensor], count: int, gen: torch.Generator
) -> tuple[sp.Splats, dict]:
    """At most `count` Gaussians (scene frame, float32, CPU) from `trained` (a `model.Trained`) seen through the
    training cameras (`intrinsics`, OpenGL `world_from_cams` [4, 4]); and what was used, for the manifest (module
    doc). UserError when fewer than 4 rays end on a surface."""
    from scipy.spatial import cKDTree

    sizes = torch.tensor([i.w * i.h for i in intrinsics], dtype=torch.float64)
    pts, cols, foot = [], [], []
    bg = trained.background.detach().float().cpu().reshape(3)
    n_rays, hits = 0, 0
    while hits < count and n_rays < count * INIT_MAX_RAYS_PER_GAUSSIAN:  # rounds until `count` rays hit
        batch = min(count * INIT_RAYS_PER_GAUSSIAN, count * INIT_MAX_RAYS_PER_GAUSSIAN - n_rays)
        n_rays += batch
        per_view = torch.multinomial(sizes, batch, replacement=True, generator=gen)
        for k, m in enumerate(torch.bincount(per_view, minlength=len(sizes)).tolist()):
            intr = intrinsics[k]
            pix = torch.randint(intr.w * intr.h, (m,), generator=gen)
            uv = torch.stack([pix % intr.w, pix // intr.w], dim=-1).double() + 0.5
            o, d = generate_rays(intr, world_from_cams[k], uv)
            out = trained.render_rays(o.float(), d.float(), median=True)
            rgb, mean_t, t, acc = (out[key].detach().float().cpu() for key in ("rgb", "depth", "depth_median", "acc"))
            hit = (acc >= OPAQUE) & torch.isfinite(t) & (t > 0) & ((mean_t - t).abs() <= INIT_DEPTH_AGREEMENT * t)
            pts.append((o.float() + d.float() * t[:, None])[hit])
            cols.append(((rgb - (1 - acc[:, None]) * bg) / acc[:, None].clamp_min(1e-6)).clamp(0, 1)[hit])
            foot.append(t[hit] / max(intr.fx, intr.fy))
            hits += int(hit.sum())
    means, colors, footprint = torch.cat(pts), torch.cat(cols), torch.cat(foot)
    if means.shape[0] < 4:
        raise UserError(
            f"{trained.scene.root}: fewer than 4 of {n_rays} training rays end on one surface in the field "
            f"(opacity >= {OPAQUE}, expected depth within {INIT_DEPTH_AGREEMENT:g} of the median): nothing "
            "to put Gaussians on (an empty or untrained run?)"
        )
    keep = torch.randperm(means.shape[0], generator=gen)[:count]
    means, colors, footprint = means[keep], colors[keep], footprint[keep]
    dist, _ = cKDTree(means.numpy()).query(means.numpy(), k=4)
    knn = torch.from_numpy(np.sqrt(np.mean(dist[:, 1:] ** 2, axis=1))).float()
    scale = torch.maximum(INIT_KNN_FRACTION * knn, footprint).clamp_min(1e-7)
    n = means.shape[0]
    splats = sp.Splats(
        means=means,
        log_scales=torch.log(scale)[:, None].expand(n, 3).contiguous(),
        quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4).contiguous(),
        opacity_logits=torch.full((n,), math.log(INIT_OPACITY / (1 - INIT_OPACITY))),
        sh=sp.rgb_to_sh0(colors)[:, None, :],
    )
    used = {
        "rays": n_rays,
        "rays_hit": hits,
        "gaussians": n,
        "rule": f"median depth of training rays with acc >= {OPAQUE} whose expected depth is within "
        f"{INIT_DEPTH_AGREEMENT:g} of it; colour (rgb - (1 - acc) bg) / acc; size "
        f"{INIT_KNN_FRACTION:g} x rms distance to 3 nearest neighbours, at least t / f; opacity "
        f"{INIT_OPACITY:g}; SH degree 0",
    }
    return splats, used
