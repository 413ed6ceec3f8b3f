"""Texel colours from the field's renders of the training cameras, projected onto the mesh (`project_views`).

Why: a texel's colour asked of the field at one point along its inward normal (`texture.bake_texture` without
views) is the field's answer for a direction no camera may have looked from (the view-dependent colour head is
unconstrained there), and one point of a soft surface is not what a pixel composites. Instead every texel takes
the mean of what the field renders at the training cameras that see it: each chosen camera's image is rendered
from the field (only its pixels the mesh covers), each texel's surface point is projected into it, kept where it is
the nearest surface there (the mesh's own depth buffer from that camera, read bilinearly: a slanted surface's depth
changes by more than the tolerance from one pixel to the next) and faces the camera, and read bilinearly;
the texel's colour is the mean over those cameras weighted by the cosine between its normal and the direction to
the camera (`POWER`). Texels no chosen camera sees keep the colour along the normal.

Measured on the fox (bench-real's run, 7 held-out views, `make bench-mesh-texture`; 2026-11-27): against the
photos over the mesh's silhouette, the mesh scored 5.1-9.7 dB below the field (mean 7.2) along the normal, and
2.6-7.7 dB (mean 4.8) from 24 spread training views rendered at half the run's training size; all 43 views at the
training size gave the same mean at five times the cost. Weights cos^0 / cos^1 / cos^2 / cos^8 / cos^32: mean gap
4.9 / 4.8 / 5.1 / 5.3 / 5.8 dB (sharper weights take a texel from fewer views: a patchwork of their exposures).
What is left is the photos' view-dependent appearance, which one texture cannot hold: the fox's 43 training photos,
projected onto the mesh, differ from the texels' mean by gains of 0.86-1.30 per colour channel, smoothly along the
capture; a texture from only the two training views beside a held-out one scores 1.25 dB below the field there.

Conventions: as `stages.mesh.texture` (scene frame, float64 positions, OpenGL world_from_cam [4, 4]); cameras'
`Intrinsics` in pixels with `radiance.camera`'s conventions (lens distortion applied by `project` and undone by
`generate_rays`, so the depth buffer and the rays agree). The renderer is a callback: `render(rays_o [R, 3],
rays_d [R, 3]) -> rgb [R, 3]` (float32 tensors, scene frame, unit directions).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.radiance.camera import Intrinsics, generate_rays, project

__all__ = ["ViewSource", "TEXTURE_VIEWS", "POWER", "COS_MIN", "DEPTH_TOL", "spread_views", "depth_buffer",
           "project_views", "training_views"]  # fmt: skip

TEXTURE_VIEWS = 24
"""Training cameras rendered for a texture by default (spread out, `spread_views`): on the fox 24 of 43 gave the mean
gap of all 43 (4.83 against 4.85 dB), 12 gave 5.13 dB (module doc)."""
VIEW_DOWNSCALE = 2.0
"""The cameras render at 1 / this of the run's training size (the fox: 135x240; 43 views gave a mean gap of 4.85 dB
at this size and 4.82 dB at the training size, with a quarter of the rays)."""
POWER = 1.0
"""A camera's weight at a texel: cos(normal, direction to the camera) ** POWER (module doc: 0, 1, 2, 8, 32)."""
COS_MIN = 0.1
"""Cameras seeing a texel at a grazing angle (cosine below this) are left out for it."""
DEPTH_TOL = 0.01
"""A texel is seen by a camera when its depth is within this fraction of the nearest surface's depth there."""


@dataclass(frozen=True)
class ViewSource:
    """Cameras to project from and the field's renderer (module doc)."""

    cameras: list[tuple[Intrinsics, np.ndarray]]
    """(intrinsics, world_from_cam [4, 4] OpenGL, scene frame) per camera."""
    render: Callable[[Tensor, Tensor], Tensor]
    """rays_o [R, 3], rays_d [R, 3] float32 -> rgb [R, 3] in [0, 1]."""
    info: dict = field(default_factory=dict)
    """What the report says about the cameras (which, at what size)."""


def spread_views(centres: np.ndarray, k: int) -> list[int]:
    """k of the camera centres [N, 3] spread out (farthest-point sampling from the first; deterministic), sorted."""
    n = len(centres)
    if k >= n:
        return list(range(n))
    chosen = [0]
    dist = np.linalg.norm(centres - centres[0], axis=1)
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(centres - centres[nxt], axis=1))
    return sorted(chosen)


def depth_buffer(verts: np.ndarray, faces: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """The mesh's z-depth at each pixel centre seen by the camera (nearest surface, perspective-correct), [H, W]
    float64, inf where no face covers the centre."""
    from nerfpipe.stages.mesh.texture import rasterize

    px, z = (a.numpy() for a in project(torch.as_tensor(verts), torch.as_tensor(world_from_cam, dtype=torch.float64),
                                        intr))  # fmt: skip
    f = faces[(z[faces] > 1e-9).all(axis=1)]
    tri = np.stack([px[f][..., 0] / intr.w, 1.0 - px[f][..., 1] / intr.h], axis=-1)  # rasterize's frame: y up
    rows, cols, face, bary = rasterize(tri, intr.w, intr.h)
    depth = 1.0 / (bary / z[f][face]).sum(axis=1)  # perspective-correct: 1/z is linear on the screen
    out = np.full(intr.h * intr.w, np.inf)
    np.minimum.at(out, rows * intr.w + cols, depth)
    return out.reshape(intr.h, intr.w)


def _view_image(source: ViewSource, intr: Intrinsics, world_from_cam: np.ndarray,
                covered: np.ndarray) -> np.ndarray:  # fmt: skip
    """The field's render of the camera's covered pixels, [H, W, 3] float32 (zero elsewhere)."""
    ys, xs = np.nonzero(covered)
    image = np.zeros((intr.h, intr.w, 3), np.float32)
    if len(ys) == 0:
        return image
    uv = torch.as_tensor(np.stack([xs + 0.5, ys + 0.5], axis=1), dtype=torch.float64)
    rays_o, rays_d = generate_rays(intr, torch.as_tensor(world_from_cam, dtype=torch.float64), uv)
    with torch.inference_mode():
        rgb = source.render(rays_o.float(), rays_d.float())
    image[ys, xs] = torch.as_tensor(rgb).detach().float().cpu().clamp(0, 1).numpy()
    return image


def project_views(points: np.ndarray, normals: np.ndarray, verts: np.ndarray, faces: np.ndarray,
                  source: ViewSource) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Texel points [N, 3] with unit outward normals [N, 3] on the mesh (verts, faces) -> (rgb [N, 3] float32, the
    weights' sum [N]: 0 where no camera sees the texel, its rgb is then 0). See the module doc."""
    acc = np.zeros((len(points), 3), np.float64)
    wsum = np.zeros(len(points), np.float64)
    for intr, world_from_cam in source.cameras:
        centre = np.asarray(world_from_cam, np.float64)[:3, 3]
        to_cam = centre - points
        cos = np.einsum("nd,nd->n", to_cam, normals) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-12)
        ids = np.flatnonzero(cos > COS_MIN)
        zbuf = depth_buffer(verts, faces, world_from_cam, intr)
        covered = np.isfinite(zbuf)
        if len(ids) == 0 or not covered.any():
            continue
        image = _view_image(source, intr, world_from_cam, covered)
        uv, z = (a.numpy() for a in project(torch.as_tensor(points[ids]), torch.as_tensor(world_from_cam), intr))
        u, v = uv[:, 0] - 0.5, uv[:, 1] - 0.5  # pixel-centre coordinates
        inside = (z > 0) & (u >= 0) & (v >= 0) & (u <= intr.w - 1) & (v <= intr.h - 1)
        ids, u, v, z = ids[inside], u[inside], v[inside], z[inside]
        u0 = np.minimum(np.floor(u).astype(np.int64), max(intr.w - 2, 0))
        v0 = np.minimum(np.floor(v).astype(np.int64), max(intr.h - 2, 0))
        fu, fv = u - u0, v - v0
        col, depth, cov = np.zeros((len(ids), 3)), np.zeros(len(ids)), np.zeros(len(ids))
        for r, c, b in ((v0, u0, (1 - fu) * (1 - fv)), (v0, u0 + 1, fu * (1 - fv)), (v0 + 1, u0, (1 - fu) * fv),
                        (v0 + 1, u0 + 1, fu * fv)):  # bilinear over the covered pixels only  # fmt: skip
            b = np.where(covered[r, c], b, 0.0)
            col += image[r, c] * b[:, None]
            depth += np.where(covered[r, c], zbuf[r, c], 0.0) * b
            cov += b
        seen = cov > 1e-6
        seen[seen] = z[seen] <= depth[seen] / cov[seen] * (1.0 + DEPTH_TOL)  # the nearest surface there
        ids = ids[seen]
        weight = np.clip(cos[ids], 0.0, 1.0) ** POWER
        acc[ids] += col[seen] / cov[seen, None] * weight[:, None]
        wsum[ids] += weight
    rgb = np.divide(acc, wsum[:, None], out=np.zeros_like(acc), where=wsum[:, None] > 0)
    return rgb.astype(np.float32), wsum


def training_views(trained: Any, count: int) -> ViewSource | None:
    """`count` of the run's training cameras (spread out), at 1 / VIEW_DOWNSCALE of the size the run trained at,
    and the run's renderer; None when count is 0 or the run has no training views."""
    scene = trained.scene
    train = list(scene.split("train")) if count > 0 else []
    if not train:
        return None
    centres = np.stack([np.asarray(scene.frames[i].world_from_cam, np.float64)[:3, 3] for i in train])
    picked = [train[k] for k in spread_views(centres, count)]
    scale = 1.0 / (VIEW_DOWNSCALE * float(trained.run_config.get("downscale") or 1.0))
    cameras = [(scene.frame_intrinsics(i).scaled(scale), np.asarray(scene.frames[i].world_from_cam, np.float64))
               for i in picked]  # fmt: skip

    def render(rays_o: Tensor, rays_d: Tensor) -> Tensor:
        return trained.render_rays(rays_o, rays_d, median=False)["rgb"]

    w, h = cameras[0][0].w, cameras[0][0].h
    info = {"views": len(cameras), "of": len(train), "size": [w, h], "weights": f"cos^{POWER:g}",
            "rule": "the field's renders of spread-out training cameras, projected onto the texels seen"}  # fmt: skip
    return ViewSource(cameras=cameras, render=render, info=info)
