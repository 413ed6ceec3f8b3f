"""The splat stage's output: the visible Gaussians in the output frame, as `data.splat_ply` stores them."""

from __future__ import annotations

import numpy as np
import torch

from nerfpipe.data.splat_ply import SplatData
from nerfpipe.radiance import splats as sp

__all__ = ["to_file"]


def to_file(splats: sp.Splats, out_from_scene: np.ndarray) -> tuple[SplatData, int]:
    """Visible Gaussians (opacity >= `radiance.splats.ALPHA_MIN`) in the output frame (`out_from_scene` [4, 4], a
    similarity: means mapped, log-scales shifted, orientations and SH bands turned with it), as the files store
    them; and how many were dropped."""
    keep = torch.sigmoid(splats.opacity_logits) >= sp.ALPHA_MIN
    moved = sp.transformed(splats.subset(keep), torch.as_tensor(out_from_scene, dtype=torch.float64))
    f_rest = np.transpose(moved.sh[:, 1:].numpy(), (0, 2, 1))  # [N, 3, K - 1], channel-major (INRIA)
    data = SplatData(
        means=moved.means.numpy(),
        f_dc=moved.sh[:, 0].numpy(),
        f_rest=f_rest,
        opacity=moved.opacity_logits.numpy(),
        scales=moved.log_scales.numpy(),
        quats=moved.quats.numpy(),
    )
    return data, int((~keep).sum())
