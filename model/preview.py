"""Interactive rendering of a trained run (what `nerfpipe view` shows): fast, inference only, no depth median.

`render_preview(trained, intr, world_from_cam, coarse=...)` returns what `model.render_view` returns without
`depth_median` (rgb [H, W, 3], z-depth [H, W] in scene units, acc [H, W], numpy float32). For
a `fast` field (box, NDC or contracted) it marches with early ray termination (`model.field_model.Inference`:
rays stop once their transmittance is below `MIN_TRANSMITTANCE`, where `render` stops at the dtype's epsilon);
`coarse=True` also doubles the marching step (`COARSE_STEP`) and colours only the samples carrying at least
`COARSE_COLOR_KEEP` of a ray's light (and each ray's largest), rescaled to the ray's full weight: what the viewer
shows while the camera moves. A run that ignores `infer` (the nerf method's, a plugin's) renders as `render` does.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from nerfpipe.model.field_model import Inference
from nerfpipe.radiance.camera import Intrinsics, generate_rays

__all__ = ["MIN_TRANSMITTANCE", "COARSE_STEP", "COARSE_COLOR_KEEP", "render_preview", "preview_rays"]

MIN_TRANSMITTANCE = 1e-3
"""A ray stops once less than this much light gets through (acc and rgb off by at most this)."""
COARSE_STEP = 2.0
"""While the camera moves, march at this many times the run's inference step (its training step)."""
COARSE_COLOR_KEEP = 1e-2
"""While the camera moves, colour only samples of at least this weight (`model.field_model.Inference.color_keep`):
about 30 % faster for an invisible difference (docs/MEASUREMENTS.md, "Viewer")."""


@torch.no_grad()
def preview_rays(trained: Any, rays_o: torch.Tensor, rays_d: torch.Tensor, *, coarse: bool = False) -> dict:
    """rays [R, 3] (unit d) -> dict(rgb [R, 3], depth [R] (expected t), acc [R]) on the run's device."""
    infer = Inference(
        min_transmittance=MIN_TRANSMITTANCE,
        step_scale=COARSE_STEP if coarse else 1.0,
        color_keep=COARSE_COLOR_KEEP if coarse else None,
    )
    return trained.render_rays(rays_o, rays_d, infer=infer, median=False)


def render_preview(trained: Any, intr: Intrinsics, world_from_cam: np.ndarray, *, coarse: bool = False):
    """One camera (scene frame, OpenGL axes) -> dict(rgb [H, W, 3], depth [H, W] z-depth, acc [H, W]) numpy."""
    pose = torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64))
    rays_o, rays_d = generate_rays(intr, pose)  # float64 [R, 3]
    cos = (rays_d @ -pose[:3, 2]).to(torch.float32).reshape(intr.h, intr.w).numpy()  # t -> z-depth
    device = trained.device
    out = preview_rays(trained, rays_o.to(device, torch.float32), rays_d.to(device, torch.float32), coarse=coarse)

    def grab(key: str, shape: tuple[int, ...]) -> np.ndarray:
        return out[key].detach().float().cpu().reshape(shape).numpy()

    h, w = intr.h, intr.w
    return {"rgb": grab("rgb", (h, w, 3)), "depth": grab("depth", (h, w)) * cos, "acc": grab("acc", (h, w))}
