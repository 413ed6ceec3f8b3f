"""Several photos of one object: each photo's grid (its own view frame) turned into the first photo's view frame
and merged by averaging the probabilities (3D-R2N2 and Pix2Vox fuse in a canonical frame that ShapeNet's aligned
models give; viewer-centred grids need the cameras' azimuths instead, `data.synthetic.shape_views`).

Azimuths are the cameras' positions about the object's vertical axis, radians, counter-clockwise seen from above;
only their differences matter. A point p0 of the first photo's view frame is the point Rz(-(phi_k - phi_0)) p0 of
photo k's view frame (Rz: rotation about +z).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["turn", "fuse"]


def turn(grid: torch.Tensor, delta: float) -> torch.Tensor:
    """A grid [R, R, R] (x, y, z) in the view frame of a camera at azimuth phi0 + delta, resampled (trilinear) in
    the view frame of the camera at phi0: [R, R, R]; what falls outside the turned cube is 0."""
    if grid.ndim != 3 or len(set(grid.shape)) != 1:
        raise ValueError(f"expected a cubic grid [R, R, R], got {tuple(grid.shape)}")
    r = grid.shape[0]
    if delta % (2 * math.pi) == 0:
        return grid.clone()
    cell = (torch.arange(r, dtype=grid.dtype, device=grid.device) + 0.5) / r - 0.5
    x, y, z = torch.meshgrid(cell, cell, cell, indexing="ij")  # points of the first frame, [R, R, R] each
    c, s = math.cos(-delta), math.sin(-delta)
    xk, yk = c * x - s * y, s * x + c * y  # Rz(-delta) p0: the same point in photo k's frame
    # grid_sample wants the volume as [N, C, D, H, W] = (z, y, x) and sample points (x, y, z) in [-1, 1]
    where = torch.stack([2 * xk, 2 * yk, 2 * z], dim=-1)  # [R, R, R, 3], indexed (i, j, k)
    volume = grid.permute(2, 1, 0)[None, None]
    out = F.grid_sample(volume, where[None], mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[0, 0]  # indexed like `where`: (i, j, k)


def fuse(grids: torch.Tensor, azimuths: torch.Tensor) -> torch.Tensor:
    """Probabilities [V, R, R, R] of V photos at `azimuths` [V] (radians) -> their mean [R, R, R] in the first
    photo's view frame."""
    if grids.ndim != 4 or azimuths.shape != (grids.shape[0],):
        raise ValueError(
            f"expected grids [V, R, R, R] and azimuths [V], got {tuple(grids.shape)}, {tuple(azimuths.shape)}"
        )
    base = float(azimuths[0])
    return torch.stack([turn(g, float(a) - base) for g, a in zip(grids, azimuths, strict=True)]).mean(0)
