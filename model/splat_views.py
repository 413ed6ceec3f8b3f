"""The splat stage's training photos: each view's photo at the optimisation's size, put on the run's background
(photos with alpha), as uint8 [H, W, 3], with its camera (pinhole `Intrinsics`, OpenGL world_from_cam [4, 4]
float64, scene frame)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.data.masks import load_masked_image
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["TrainingPhotos", "load_training_photos"]


@dataclass
class TrainingPhotos:
    """Training photos on the background (uint8 [H, W, 3] each) and their cameras."""

    photos: list[Tensor]
    world_from_cams: list[Tensor]  # [4, 4] float64 each
    intrinsics: list[Intrinsics]

    def target(self, k: int, device: torch.device) -> Tensor:
        return self.photos[k].to(device).float() / 255.0


def load_training_photos(
    scene: Any, indices: tuple[int, ...], downscale: float, background: np.ndarray
) -> TrainingPhotos:
    """The views `indices` of `scene` at 1 / downscale (INTER_AREA), alpha composited over `background` [3] in [0, 1];
    UserError naming the image when its size is not the one transforms.json gives."""
    import cv2

    photos, poses, intrs = [], [], []
    for i in indices:
        intr = scene.frame_intrinsics(i)
        img = load_masked_image(scene, i)
        if img.shape[:2] != (intr.h, intr.w):
            raise UserError(
                f"{scene.image_path(i)}: image is {img.shape[1]}x{img.shape[0]}, transforms.json says {intr.w}x{intr.h}"
            )
        if downscale != 1.0:
            intr = intr.scaled(1.0 / downscale)
            img = cv2.resize(img, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
        if img.shape[-1] == 4:
            img = img[..., :3] * img[..., 3:] + background * (1 - img[..., 3:])
        photos.append(torch.from_numpy(np.round(np.clip(img[..., :3], 0, 1) * 255).astype(np.uint8)))
        poses.append(torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64))
        intrs.append(Intrinsics(w=intr.w, h=intr.h, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy))
    return TrainingPhotos(photos, poses, intrs)
