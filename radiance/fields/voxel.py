"""A dense voxel grid of attenuation (density only): the fast field for X-ray reconstruction on a CPU.

mu(x) = mu_scale * max(theta(x), 0), theta trilinearly interpolated from a [nx, ny, nz] grid whose samples sit
at the voxel centres of the box `aabb` (radiance.xray's VoxelGrid convention: voxel i covers
[min + i s, min + (i + 1) s), centre at + 0.5 s), so at full resolution theta is the reconstructed volume itself.
Outside the box mu = 0. `upsample(shape)` resamples theta (coarse-to-fine); `tv()` is the mean absolute
difference between neighbouring voxels (anisotropic total variation), the usual sparse-view prior.
No colour, no view direction (`has_color = False`). Not registered in `radiance.fields.make_field`; the X-ray
run library (`model.xray`) builds it from its `config()`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfpipe.radiance.fields.base import Field, check_points

__all__ = ["VoxelField"]


class VoxelField(Field):
    """Attenuation on a dense grid, trilinear, non-negative."""

    has_color = False
    view_dependent = False

    def __init__(
        self, *, aabb: Tensor | list, shape: tuple[int, int, int] | list, mu_scale: float = 1.0, init: float = 0.5
    ) -> None:
        super().__init__()
        aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3)
        if not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"expected aabb [[min], [max]] with max > min, got {aabb.tolist()}")
        shape = tuple(int(n) for n in shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"expected shape (nx, ny, nz) >= 1, got {shape}")
        self.register_buffer("aabb", aabb)
        self.shape, self.mu_scale, self.init = shape, float(mu_scale), float(init)
        # grid_sample layout [1, 1, D=z, H=y, W=x]
        self.theta = nn.Parameter(torch.full((1, 1, shape[2], shape[1], shape[0]), float(init)))

    def normalize(self, x: Tensor) -> Tensor:
        """Scene frame [N, 3] -> [-1, 1]^3 over the box (grid_sample, align_corners=False)."""
        return (x - self.aabb[0]) * (2.0 / (self.aabb[1] - self.aabb[0])) - 1.0

    def density(self, x: Tensor) -> Tensor:
        check_points(x)
        xn = self.normalize(x)
        theta = F.grid_sample(
            self.theta, xn.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border", align_corners=False
        ).reshape(-1)
        mu = self.mu_scale * theta.clamp(min=0)
        return torch.where((xn.abs() <= 1.0).all(dim=-1), mu, torch.zeros_like(mu))

    def volume(self) -> Tensor:
        """mu at the grid's own voxel centres [nx, ny, nz]."""
        return (self.mu_scale * self.theta.clamp(min=0))[0, 0].permute(2, 1, 0)

    def tv(self) -> Tensor:
        """Mean |theta_i - theta_neighbour| over the three axes."""
        t = self.theta[0, 0]
        return (t.diff(dim=0).abs().mean() + t.diff(dim=1).abs().mean() + t.diff(dim=2).abs().mean()) / 3

    @torch.no_grad()
    def clamp_(self) -> None:
        """Project theta onto theta >= 0 (after an optimiser step)."""
        self.theta.clamp_(min=0)

    @torch.no_grad()
    def upsample(self, shape: tuple[int, int, int]) -> None:
        """Resample theta to `shape` (nx, ny, nz): a new Parameter, so rebuild the optimizer."""
        shape = tuple(int(n) for n in shape)
        t = F.interpolate(self.theta.data, size=(shape[2], shape[1], shape[0]), mode="trilinear", align_corners=False)
        self.theta = nn.Parameter(t)
        self.shape = shape

    def config(self) -> dict:
        return {
            "kind": "voxel",
            "aabb": self.aabb.tolist(),
            "shape": list(self.shape),
            "mu_scale": self.mu_scale,
            "init": self.init,
        }
