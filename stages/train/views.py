"""Training and test rays of a scene's views, held in memory: origins per view, directions and colours per ray.

Rays are in the scene frame with unit directions (`radiance.camera.generate_rays`); colours are uint8 RGBA
(alpha 255 for RGB images). `evenly_spaced` picks the test views `train` renders in full at the end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from data.errors import UserError
from data.masks import load_masked_image
from data.transforms import Scene
from radiance.camera import generate_rays

__all__ = ["Views", "load_views", "evenly_spaced", "auto_downscale"]


@dataclass
class Views:
    """Rays of a set of views: origins per view, directions and colours per ray (flattened views)."""

    origins: Tensor  # [V, 3] float32
    view: Tensor  # [M] int32, view of each ray
    dirs: Tensor  # [M, 3] float32
    rgba: Tensor  # [M, 4] uint8 (alpha 255 for RGB images)
    shapes: list[tuple[int, int]]  # (h, w) per view

    def batch(self, idx: Tensor, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Rays idx [B] -> origins [B, 3], directions [B, 3], rgb [B, 3] and alpha [B] in [0, 1] on device."""
        o = self.origins[self.view[idx].long()].to(device)
        d = self.dirs[idx].to(device)
        c = self.rgba[idx].to(device).float() / 255.0
        return o, d, c[:, :3], c[:, 3]

    def mask_colour(self, colour: tuple[float, float, float], tolerance: int = 4) -> None:
        """Pixels within `tolerance` (of 255) of `colour` on every channel become transparent (alpha 0)."""
        c = torch.tensor([round(v * 255) for v in colour], dtype=torch.int16)
        close = ((self.rgba[:, :3].to(torch.int16) - c).abs() <= tolerance).all(dim=1)
        self.rgba[close, 3] = 0

    def pixels_of(self, v: int) -> Tensor:
        """Ray indices [h * w] of view v."""
        start = sum(h * w for h, w in self.shapes[:v])
        h, w = self.shapes[v]
        return torch.arange(start, start + h * w)


def load_views(scene: Scene, indices: tuple[int, ...], downscale: float = 1.0) -> Views:
    """Every pixel's ray of the views `indices`, images shrunk by `downscale` (area filter, intrinsics scaled);
    UserError when an image's size disagrees with transforms.json."""
    import cv2

    origins, views, dirs, rgba, shapes = [], [], [], [], []
    for k, i in enumerate(indices):
        img = load_masked_image(scene, i)  # a frame's mask_path makes its masked-out pixels transparent
        intr = scene.frame_intrinsics(i)
        if img.shape[:2] != (intr.h, intr.w):
            raise UserError(f"{scene.image_path(i)}: image is {img.shape[1]}x{img.shape[0]}, "
                            f"transforms.json says {intr.w}x{intr.h}")  # fmt: skip
        if downscale != 1.0:
            intr = intr.scaled(1.0 / downscale)
            img = cv2.resize(img, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
        if img.shape[-1] == 3:
            img = np.concatenate([img, np.ones_like(img[..., :1])], axis=-1)
        world_from_cam = torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64)
        o, d = generate_rays(intr, world_from_cam)
        origins.append(o[0].float())
        dirs.append(d.float())
        views.append(torch.full((d.shape[0],), k, dtype=torch.int32))
        rgba.append(torch.from_numpy(np.round(img.reshape(-1, 4) * 255).astype(np.uint8)))
        shapes.append((intr.h, intr.w))
    return Views(torch.stack(origins), torch.cat(views), torch.cat(dirs), torch.cat(rgba), shapes)


def evenly_spaced(n: int, k: int | None) -> list[int]:
    """k indices spread evenly over range(n), first and last included (all n when k is None or >= n)."""
    if k is None or k >= n:
        return list(range(n))
    if k < 1:
        raise ValueError(f"expected k >= 1 views, got {k}")
    return sorted({int(i) for i in np.linspace(0, n - 1, k).round()})


def auto_downscale(scene: Scene, indices: tuple[int, ...], max_side: int) -> float:
    """The smallest power of two that brings the largest image's long side to at most max_side pixels."""
    side = max(max(scene.frame_intrinsics(i).w, scene.frame_intrinsics(i).h) for i in indices)
    factor = 1
    while side / factor > max_side:
        factor *= 2
    return float(factor)
