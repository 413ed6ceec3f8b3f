"""A photo and its mask to the voxel network's input: the one preprocessing of training and inference.

Pix2Vox's users ask why a released model gives near-random output on their photos: it saw centred renders on white
and gets photos framed otherwise. Here every photo (a generated one in training, the user's at inference) goes
through `prepare`: the object's mask picks the object, the crop is the square about the mask's bounding box with
`MARGIN` on each side (the object fills the input whatever its framing), the background is removed (colour times
mask: black), and the mask is a fourth channel. Only the mask's shape and the object's colours reach the network.

Conventions: images are float arrays in [0, 1], rows top to bottom; the input is float32 [4, SIDE, SIDE] (R, G, B
premultiplied by the mask, then the mask).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["SIDE", "MARGIN", "MASK_LEVEL", "prepare", "crop_box"]

SIDE = 64
"""Side of the network's input, pixels."""
MARGIN = 0.06
"""Border added on each side of the mask's bounding box, as a fraction of its larger side."""
MASK_LEVEL = 0.5
"""A pixel belongs to the object where its mask is at least this."""


def crop_box(mask: np.ndarray) -> tuple[float, float, float]:
    """The square crop about the mask's bounding box: (centre row, centre col, side), pixels (float)."""
    if mask.ndim != 2:
        raise ValueError(f"expected a mask [H, W], got {mask.shape}")
    rows, cols = np.nonzero(mask >= MASK_LEVEL)
    if len(rows) == 0:
        raise ValueError(f"the mask is empty (no pixel >= {MASK_LEVEL}): nothing to predict a shape of")
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    side = max(r1 - r0, c1 - c0) * (1 + 2 * MARGIN)
    return 0.5 * (r0 + r1), 0.5 * (c0 + c1), float(side)


def prepare(rgb: np.ndarray, mask: np.ndarray, side: int = SIDE) -> torch.Tensor:
    """rgb [H, W, 3] and mask [H, W] (floats in [0, 1]) -> input [4, side, side] float32 (module doc).

    The crop may reach past the photo's edge: what lies outside is background (zeros). Resampled by area
    averaging (a crop larger than `side` is filtered, not aliased)."""
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or rgb.shape[:2] != mask.shape:
        raise ValueError(f"expected rgb [H, W, 3] and mask [H, W] of one size, got {rgb.shape} and {mask.shape}")
    cr, cc, s = crop_box(mask)
    r0, c0 = int(round(cr - s / 2)), int(round(cc - s / 2))
    h, w = mask.shape
    m = np.clip(mask, 0.0, 1.0).astype(np.float32)
    stack = np.concatenate([np.clip(rgb, 0.0, 1.0).astype(np.float32) * m[..., None], m[..., None]], -1)
    canvas = np.zeros((int(np.ceil(s)) + 1, int(np.ceil(s)) + 1, 4), np.float32)
    rr0, cc0 = max(r0, 0), max(c0, 0)
    rr1, cc1 = min(r0 + canvas.shape[0], h), min(c0 + canvas.shape[1], w)
    canvas[rr0 - r0 : rr1 - r0, cc0 - c0 : cc1 - c0] = stack[rr0:rr1, cc0:cc1]
    x = torch.from_numpy(canvas).permute(2, 0, 1)[None]  # [1, 4, S, S]
    if canvas.shape[0] >= side:
        return F.adaptive_avg_pool2d(x, side)[0].contiguous()
    return F.interpolate(x, size=(side, side), mode="bilinear", align_corners=False)[0].contiguous()
