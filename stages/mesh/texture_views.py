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
2.7-7.7 dB (mean 4.8) from 24 spread training views rendered at half the run's training size; all 43 views at the
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

from nerfpipe.data.errors import UserError
from nerfpipe.radiance.camera import Intrinsics, generate_rays, project

__all__ = [
    "ViewSource",
    "TEXTURE_VIEWS",
    "VIEW_DOWNSCALE",
    "VIEW_MAX_SIDE",
    "PHOTO_MAX_SIDE",
    "training_photos",
    "POWER",
    "COS_MIN",
    "DEPTH_TOL",
    "BEHIND_TOL",
    "spread_views",
    "depth_buffer",
    "project_views",
    "training_views",
]

TEXTURE_VIEWS = 24
"""Training cameras rendered for a texture by default (spread out, `spread_views`): on the fox 24 of 43 gave the mean
gap of all 43 (4.83 against 4.85 dB), 12 gave 5.13 dB (module doc)."""
VIEW_DOWNSCALE = 2.0
"""The cameras render at 1 / this of the run's training size (the fox: 135x240; 43 views gave a mean gap of 4.85 dB
at this size and 4.82 dB at the training size, with a quarter of the rays)."""
VIEW_MAX_SIDE = 480
"""... and at most this many pixels on their long side (a run that trained at full size: a phone's 1920 px)."""
PHOTO_MAX_SIDE = 1024
"""Training photos are read at the size the run trained at, and at most this many pixels on their long side."""
POWER = 1.0
"""A camera's weight at a texel: cos(normal, direction to the camera) ** POWER (module doc: 0, 1, 2, 8, 32)."""
COS_MIN = 0.1
"""Cameras seeing a texel at a grazing angle (cosine below this) are left out for it."""
DEPTH_TOL = 0.01
"""A texel is hidden from a camera when its depth is more than this fraction beyond the nearest surface's there."""
BEHIND_TOL = 0.1
"""A pixel whose nearest surface lies more than this fraction beyond the texel shows something behind it (the
texel at its surface's silhouette, the wall past it): it gives the texel no colour. A slanted surface's depth
changes by up to ~5 % a pixel at the steepest angle kept (COS_MIN, f ~ 200 px), so its own pixels stay."""


@dataclass(frozen=True, kw_only=True)
class ViewSource:
    """Cameras to project from, and what each shows: its photo, or the field's render (module doc)."""

    cameras: tuple[tuple[Intrinsics, np.ndarray], ...]
    """(intrinsics, world_from_cam [4, 4] OpenGL, scene frame) per camera."""
    render: Callable[[Tensor, Tensor], Tensor] | None = None
    """rays_o [R, 3], rays_d [R, 3] float32 -> rgb [R, 3] in [0, 1]; used where `photos` is None."""
    photos: tuple[np.ndarray, ...] | None = None
    """Per camera its photo at the camera's size, float32 [H, W, 4] in [0, 1]: straight colour and alpha (1 for an
    opaque photo; 0 where a mask or the photo's alpha says the object is not there)."""
    info: dict = field(default_factory=dict)
    """What the report says about the cameras (which, at what size, photos or renders)."""


def spread_views(world_from_cams: np.ndarray, k: int) -> list[int]:
    """k of the cameras world_from_cams [N, 4, 4] spread out, sorted: farthest-point sampling from the first
    (deterministic) on the centres and the viewing directions (a unit direction counts as the cameras' median
    distance from their mean centre), stopping early when every camera left sits on a chosen one."""
    c2w = np.asarray(world_from_cams, np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
        raise ValueError(f"expected world_from_cams [N, 4, 4], got {c2w.shape}")
    if k <= 0 or len(c2w) == 0:
        return []
    centres, forward = c2w[:, :3, 3], -c2w[:, :3, 2]  # OpenGL: the camera looks down -z
    radius = float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1))) or 1.0
    feats = np.concatenate([centres, radius * forward], axis=1)
    chosen = [0]
    dist = np.linalg.norm(feats - feats[0], axis=1)
    while len(chosen) < min(k, len(feats)) and dist.max() > 0:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(feats - feats[nxt], axis=1))
    return sorted(chosen)


def depth_buffer(
    verts: np.ndarray, faces: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics
) -> np.ndarray | None:
    """The mesh's (verts [V, 3], faces [F, 3]) z-depth at each pixel centre seen by the camera (nearest surface,
    perspective-correct), [H, W] float64, inf where no face covers the centre; None when a face crosses the camera's
    plane (the mesh around the camera: its depth there is not a triangle's on the screen)."""
    from nerfpipe.stages.mesh.texture import rasterize

    if verts.ndim != 2 or verts.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"expected verts [V, 3] and faces [F, 3], got {verts.shape} and {faces.shape}")
    px, z = (
        a.numpy() for a in project(torch.as_tensor(verts), torch.as_tensor(world_from_cam, dtype=torch.float64), intr)
    )
    front = z[faces] > 1e-9
    if (front.any(axis=1) & ~front.all(axis=1)).any():
        return None
    f = faces[front.all(axis=1)]
    tri = np.stack([px[f][..., 0] / intr.w, 1.0 - px[f][..., 1] / intr.h], axis=-1)  # rasterize's frame: y up
    rows, cols, face, bary = rasterize(tri, intr.w, intr.h)
    depth = 1.0 / (bary / z[f][face]).sum(axis=1)  # perspective-correct: 1/z is linear on the screen
    out = np.full(intr.h * intr.w, np.inf)
    np.minimum.at(out, rows * intr.w + cols, depth)
    return out.reshape(intr.h, intr.w)


def _view_image(
    source: ViewSource, k: int, intr: Intrinsics, world_from_cam: np.ndarray, covered: np.ndarray
) -> np.ndarray:
    """Camera k's photo, or the field's render of its covered pixels (zero elsewhere), [H, W, 4] float32 (alpha 1
    for a render)."""
    if source.photos is not None:
        return source.photos[k]
    ys, xs = np.nonzero(covered)
    image = np.zeros((intr.h, intr.w, 4), np.float32)
    if len(ys) == 0:
        return image
    image[ys, xs, 3] = 1.0
    uv = torch.as_tensor(np.stack([xs + 0.5, ys + 0.5], axis=1), dtype=torch.float64)
    rays_o, rays_d = generate_rays(intr, torch.as_tensor(world_from_cam, dtype=torch.float64), uv)
    with torch.inference_mode():
        rgb = source.render(rays_o.float(), rays_d.float())
    image[ys, xs, :3] = torch.as_tensor(rgb).detach().float().cpu().clamp(0, 1).numpy()
    return image


def project_views(
    points: np.ndarray, normals: np.ndarray, verts: np.ndarray, faces: np.ndarray, source: ViewSource
) -> tuple[np.ndarray, np.ndarray, int]:
    """Texel points [N, 3] with unit outward normals [N, 3] on the mesh (verts, faces) -> (rgb [N, 3] float32, the
    weights' sum [N]: 0 where no camera sees the texel, its rgb is then 0; the cameras skipped because the mesh
    reaches round them, `depth_buffer`). See the module doc."""
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"expected points and normals [N, 3], got {points.shape} and {normals.shape}")
    acc = np.zeros((len(points), 3), np.float64)
    wsum = np.zeros(len(points), np.float64)
    skipped = 0
    for k, (intr, world_from_cam) in enumerate(source.cameras):
        to_cam = np.asarray(world_from_cam, np.float64)[:3, 3] - points
        cos = np.einsum("nd,nd->n", to_cam, normals) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-12)
        ids = np.flatnonzero(cos > COS_MIN)
        if len(ids) == 0:
            continue
        zbuf = depth_buffer(verts, faces, world_from_cam, intr)
        if zbuf is None:
            skipped += 1
            continue
        covered = np.isfinite(zbuf)
        if not covered.any():
            continue
        image = _view_image(source, k, intr, world_from_cam, covered)
        uv, z = (a.numpy() for a in project(torch.as_tensor(points[ids]), torch.as_tensor(world_from_cam), intr))
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= intr.w) & (uv[:, 1] <= intr.h)
        ids, uv, z = ids[inside], uv[inside], z[inside]
        u = np.clip(uv[:, 0] - 0.5, 0, intr.w - 1)  # pixel-centre coordinates; the outer half pixel clamps
        v = np.clip(uv[:, 1] - 0.5, 0, intr.h - 1)
        u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        u1, v1 = np.minimum(u0 + 1, intr.w - 1), np.minimum(v0 + 1, intr.h - 1)
        fu, fv = u - u0, v - v0
        col, depth, cov, opaque = np.zeros((len(ids), 3)), np.zeros(len(ids)), np.zeros(len(ids)), np.zeros(len(ids))
        for r, c, b in (
            (v0, u0, (1 - fu) * (1 - fv)),
            (v0, u1, fu * (1 - fv)),
            (v1, u0, (1 - fu) * fv),
            (v1, u1, fu * fv),
        ):  # bilinear over the pixels that show this surface or one before it
            zt = zbuf[r, c]
            b = np.where(covered[r, c] & (zt <= z * (1.0 + BEHIND_TOL)), b, 0.0)
            a = b * image[r, c, 3]  # a photo's alpha: its colour counts where it shows the object
            col += image[r, c, :3] * a[:, None]
            opaque += a
            depth += np.where(b > 0, zt, 0.0) * b
            cov += b
        seen = (cov > 1e-6) & (opaque > 1e-6)
        seen[seen] = z[seen] <= depth[seen] / cov[seen] * (1.0 + DEPTH_TOL)  # the nearest surface there
        ids = ids[seen]
        weight = np.clip(cos[ids], 0.0, 1.0) ** POWER * np.minimum(opaque[seen] / cov[seen], 1.0)
        acc[ids] += col[seen] / opaque[seen, None] * weight[:, None]
        wsum[ids] += weight
    rgb = np.divide(acc, wsum[:, None], out=np.zeros_like(acc), where=wsum[:, None] > 0)
    return rgb.astype(np.float32), wsum, skipped


def _picked(trained: Any, count: int) -> tuple[list[int], int]:
    """`count` spread-out training frames (indices into scene.frames) and how many training frames there are."""
    scene = trained.scene
    train = list(scene.split("train")) if count > 0 else []
    if not train:
        return [], 0
    c2w = np.stack([np.asarray(scene.frames[i].world_from_cam, np.float64) for i in train])
    return [train[k] for k in spread_views(c2w, count)], len(train)


def _photo(scene: Any, i: int, intr: Intrinsics) -> np.ndarray:
    """Frame i's photo (its mask applied) at `intr`'s size, float32 [H, W, 4] straight colour and alpha."""
    import cv2

    from nerfpipe.data.masks import load_masked_image

    img = load_masked_image(scene, i)
    full = scene.frame_intrinsics(i)
    if img.shape[:2] != (full.h, full.w):
        raise ValueError(f"{scene.image_path(i)}: image is {img.shape[1]}x{img.shape[0]}, expected {full.w}x{full.h}")
    if img.shape[-1] == 3:
        img = np.concatenate([img, np.ones_like(img[..., :1])], axis=-1)
    if (intr.w, intr.h) != (full.w, full.h):
        premultiplied = np.concatenate([img[..., :3] * img[..., 3:], img[..., 3:]], axis=-1)  # resize colour x alpha
        small = cv2.resize(premultiplied, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
        alpha = small[..., 3:]
        img = np.concatenate([small[..., :3] / np.maximum(alpha, 1e-6), alpha], axis=-1)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def training_photos(trained: Any, count: int) -> tuple[ViewSource | None, str]:
    """`count` of the run's training cameras (spread out) with their photos, at the size the run trained at (at most
    PHOTO_MAX_SIDE pixels long); (None, why) when count is 0, the run has no training views or a photo cannot be
    read (the stage then takes the field's renders)."""
    scene = trained.scene
    picked, of = _picked(trained, count)
    if not picked:
        return None, "no training views (or texture_views 0)"
    downscale = trained.downscale
    cameras, photos = [], []
    for i in picked:
        intr = scene.frame_intrinsics(i)
        intr = intr.scaled(min(1.0 / downscale, PHOTO_MAX_SIDE / max(intr.w, intr.h)))
        try:
            photos.append(_photo(scene, i, intr))
        except (OSError, ValueError, UserError) as exc:
            return None, f"a training photo cannot be read: {exc}"
        cameras.append((intr, np.asarray(scene.frames[i].world_from_cam, np.float64)))
    sizes = sorted({(intr.w, intr.h) for intr, _ in cameras})
    info = {
        "source": "photos",
        "views": len(cameras),
        "of": of,
        "sizes": [list(wh) for wh in sizes],
        "weights": f"cos^{POWER:g} x the photo's alpha",
        "rule": "the training photos of spread-out cameras, projected onto the texels they see",
    }
    return ViewSource(cameras=tuple(cameras), photos=tuple(photos), info=info), ""


def training_views(trained: Any, count: int) -> ViewSource | None:
    """`count` of the run's training cameras (spread out), at 1 / VIEW_DOWNSCALE of the size the run trained at (at
    most VIEW_MAX_SIDE pixels long), and the run's renderer; None when count is 0 or the run has no training views."""
    scene = trained.scene
    picked, of = _picked(trained, count)
    if not picked:
        return None
    downscale = VIEW_DOWNSCALE * trained.downscale
    cameras = []
    for i in picked:
        intr = scene.frame_intrinsics(i)
        scale = min(1.0 / downscale, VIEW_MAX_SIDE / max(intr.w, intr.h))
        cameras.append((intr.scaled(scale), np.asarray(scene.frames[i].world_from_cam, np.float64)))

    def render(rays_o: Tensor, rays_d: Tensor) -> Tensor:
        return trained.render_rays(rays_o, rays_d, median=False)["rgb"]

    sizes = sorted({(intr.w, intr.h) for intr, _ in cameras})
    info = {
        "source": "field",
        "views": len(cameras),
        "of": of,
        "sizes": [list(wh) for wh in sizes],
        "weights": f"cos^{POWER:g}",
        "rule": "the field's renders of spread-out training cameras, projected onto the texels seen",
    }
    return ViewSource(cameras=tuple(cameras), render=render, info=info)
