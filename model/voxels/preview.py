"""Pictures of a predicted grid: the probabilities rendered as a volume whose density ramps from 0 to `DENSITY`
across `level` +- `RAMP` (what is drawn is what `level` keeps, with smooth edges), shaded grey by the grid's
gradient (Lambert, one light from the camera's upper left), on white.

Cameras: in the grid's view frame (`data.synthetic.shape_views`: x right, y away from the photo's camera, z up);
`turn` degrees about z from the photo's own camera (0: seen as in the photo; 180: from behind), `elevation`
degrees above the horizon, `DISTANCE` units from the centre, the photos' field of view.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from nerfpipe.radiance.camera import Intrinsics, generate_rays
from nerfpipe.radiance.compositing import composite
from nerfpipe.radiance.paths import look_at

__all__ = ["DENSITY", "DISTANCE", "render_grid"]

DENSITY = 200.0
"""Density of a cell well above the level (per unit length: a cell, 1/32, is then ~6 optical depths)."""
RAMP = 0.1
DISTANCE = 2.2
SAMPLES = 160


def _sample(volume: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Trilinear values of volume [C, R, R, R] (x, y, z) at points p [N, 3] of the cube [-0.5, 0.5]^3: [N, C]."""
    v = volume.permute(0, 3, 2, 1)[None]  # [1, C, z, y, x]
    g = (2 * p).view(1, -1, 1, 1, 3)
    return F.grid_sample(v, g, mode="bilinear", padding_mode="zeros", align_corners=False)[0, :, :, 0, 0].T


def render_grid(
    prob: torch.Tensor, turn: float, elevation: float, size: int, level: float = 0.5, fov_deg: float = 40.0
) -> np.ndarray:
    """prob [R, R, R] -> an image [size, size, 3] float32 in [0, 1] (module doc)."""
    if prob.ndim != 3:
        raise ValueError(f"expected a grid [R, R, R], got {tuple(prob.shape)}")
    prob = prob.float().cpu()
    grad = torch.stack(torch.gradient(prob, spacing=1.0 / prob.shape[0]), 0)  # [3, R, R, R]: d/dx, d/dy, d/dz
    volume = torch.cat([prob[None], grad], 0)
    a, e = math.radians(turn - 90.0), math.radians(elevation)  # turn 0: the camera on -y
    eye = DISTANCE * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    world_from_cam = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    intr = Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2)
    o, d = generate_rays(intr, torch.from_numpy(world_from_cam).float())  # [P, 3] each
    near, far = DISTANCE - 0.9, DISTANCE + 0.9
    edges = torch.linspace(near, far, SAMPLES + 1)
    t0, t1 = edges[:-1].expand(len(o), -1), edges[1:].expand(len(o), -1)  # [P, S]
    p = o[:, None, :] + 0.5 * (t0 + t1)[..., None] * d[:, None, :]  # [P, S, 3]
    vals = _sample(volume, p.reshape(-1, 3)).view(len(o), SAMPLES, 4)
    sigma = DENSITY * ((vals[..., 0] - level + RAMP) / (2 * RAMP)).clamp(0.0, 1.0)
    normal = -F.normalize(vals[..., 1:], dim=-1, eps=torch.finfo(torch.float32).eps)
    light = F.normalize(torch.from_numpy(world_from_cam[:3, :3] @ np.array([-0.4, 0.5, 1.0])).float(), dim=0)
    grey = 0.25 + 0.7 * (normal @ light).clamp(min=0.0)  # [P, S]
    out = composite(
        sigma,
        grey[..., None].expand(-1, -1, 3).contiguous(),
        t0.contiguous(),
        t1.contiguous(),
        background=torch.ones(3),
    )
    return out["rgb"].view(size, size, 3).clamp(0.0, 1.0).numpy()
