"""The signed-distance field: an ellipsoid inscribed in the box (a sphere in a cube box) to start from plus a
coarse dense grid (`dense` nodes per axis, read trilinearly, starting at 0: the coarse shape) plus a learned VM grid
(the density field's planes and lines, `radiance.fields.fast`: the detail), a colour network that sees the surface
normal, and NeuS's learned sharpness. Without the dense grid the low-rank factors alone carve flat faces out of the
ellipsoid in axis-aligned stripes (docs/SDF.md).

Units: the field works in the box's unit coordinates u = (x - centre) / half (half: half the box's longest side),
so the starting shape, the sharpness and the finite-difference step mean the same in every scene; `sdf` answers in scene
units (times half). The grid samples box coordinates xn in [-1, 1]^3 per axis (the VM field's own), clamped at the
box's faces, where the starting shape's term carries on (outside the box the distance only grows).

Normals and the Eikonal term come from central differences one grid cell wide (gradient_i = (f(x + h e_i) -
f(x - h e_i)) / 2h), as Neuralangelo takes its numerical gradient: smooth, no double backward through grid_sample,
second-order accurate, and the mean of the six values is the distance at the centre to second order (h^2 lap f / 6).
The cheaper four-point tetrahedron is only first-order accurate (its error is h times the Hessian's off-diagonal:
4 % of the normal on a sphere seven cells wide), so it is not used.

At inference (the module in eval mode, no gradient) the grid is read from caches built from its factors, as the
density field reads its own: the distance grid's plane-times-line sums at every node, one volume read trilinearly
(a plane's bilinear interpolation times its line's linear one is the trilinear interpolation of their products at
the nodes: the same values up to float rounding, from 8 reads a point instead of 3 x (4 + 2) x rank), and the
appearance factors as `VmTables`. The caches follow the factors (their storage, versions and shapes) and are
dropped whenever the module's mode changes, since an optimiser step may change the factors in place behind their
version counters (fused Adam). The factor path is their plain twin (tests/test_sdf_method.py).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfpipe.radiance.fields.encodings import positional_encoding
from nerfpipe.radiance.fields.fast import _plane_features, factors_key, vm_node_volume
from nerfpipe.radiance.fields.vm_tables import VmTables
from nerfpipe.radiance.safe import eps

__all__ = ["SdfField", "AXES"]

AXES = torch.cat([torch.eye(3), -torch.eye(3)])
"""The six central-difference offsets (module doc): +x, +y, +z, -x, -y, -z."""
VIEW_FREQS = 2
PLANE_STD, LINE_STD = 0.1, 0.02
"""The geometry factors' initial spread: products ~0.002 a component, so the start is the ellipsoid within ~1 % of
the box."""
MAX_VOLUME_NODES = 256**3
"""The distance grid's inference volume is built up to this many nodes (64 MB in float32); above, the factors are
read."""


def _factors(rank: int, resolution: int, plane_std: float, line_std: float) -> tuple[nn.ParameterList, ...]:
    planes = nn.ParameterList([plane_std * torch.randn(1, rank, resolution, resolution) for _ in range(3)])
    lines = nn.ParameterList([line_std * torch.randn(1, rank, resolution, 1) for _ in range(3)])
    return planes, lines


class SdfField(nn.Module):
    """Signed distance (start ellipsoid + VM grid), colour given the normal, and the sharpness s (module doc)."""

    def __init__(
        self,
        *,
        aabb: Tensor | list,
        resolution: int,
        rank: int = 8,
        app_rank: int = 24,
        app_dim: int = 27,
        hidden: int = 64,
        view_dependent: bool = True,
        radius: float = 0.5,
        sharpness: float = 20.0,
        dense: int = 0,
    ) -> None:
        super().__init__()
        aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3)
        if not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"expected aabb [[min], [max]] with max > min, got {aabb.tolist()}")
        if not (resolution >= 2 and radius > 0 and sharpness > 0):
            raise ValueError(
                f"expected resolution >= 2, radius > 0, sharpness > 0, got {resolution}, {radius}, {sharpness}"
            )
        self.register_buffer("aabb", aabb)
        self.resolution, self.rank, self.app_rank, self.app_dim, self.hidden = (
            resolution,
            rank,
            app_rank,
            app_dim,
            hidden,
        )
        self.view_dependent, self.radius, self.initial_sharpness = view_dependent, radius, sharpness
        self.planes, self.lines = _factors(rank, resolution, PLANE_STD, LINE_STD)
        self.app_planes, self.app_lines = _factors(app_rank, resolution, 0.1, 0.1)
        self.basis = nn.Linear(3 * app_rank, app_dim, bias=False)
        n_in = app_dim + 3 + ((3 + 2 * VIEW_FREQS * 3) if view_dependent else 0)
        self.mlp = nn.Sequential(
            nn.Linear(n_in, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, 3),
        )
        self.log_sharpness = nn.Parameter(torch.tensor(math.log(sharpness)))
        self.dense = nn.Parameter(torch.zeros(1, 1, dense, dense, dense)) if dense else None
        self._caches: dict[str, tuple] = {}  # inference caches (module doc): name -> (factors' key, value)

    # ------------------------------------------------------------------------------------------------ frames
    @property
    def half(self) -> Tensor:
        """Half the box's longest side (scene units per unit of u)."""
        return (self.aabb[1] - self.aabb[0]).max() / 2

    @property
    def centre(self) -> Tensor:
        return self.aabb.mean(0)

    def to_unit(self, x: Tensor) -> Tensor:
        """Scene points [N, 3] -> u [N, 3]."""
        return (x - self.centre) / self.half

    @property
    def cell(self) -> float:
        """One grid cell in u (along the longest side; the finite-difference step)."""
        return 2.0 / (self.resolution - 1)

    @property
    def sharpness(self) -> Tensor:
        """s of Phi_s(f) = sigmoid(s f), per unit of u."""
        return self.log_sharpness.exp()

    # ------------------------------------------------------------------------------------------------ queries
    def _grid_coords(self, u: Tensor) -> Tensor:
        lo, hi = self.to_unit(self.aabb[0]), self.to_unit(self.aabb[1])
        return ((u - lo) * (2.0 / (hi - lo)) - 1.0).clamp(-1, 1)

    @property
    def semi_axes(self) -> Tensor:
        """[3] the starting ellipsoid's semi-axes in u: `radius` times the box's half-extents (a sphere in a cube)."""
        return self.radius * (self.aabb[1] - self.aabb[0]) / (2 * self.half)

    def start(self, u: Tensor) -> Tensor:
        """u [N, 3] -> the starting shape's signed distance [N]: the ellipsoid inscribed in the box at `radius`, by
        Quilez's bound k0 (k0 - 1) / k1 (k0 = |u / a|, k1 = |u / a^2|): exact for a sphere, a close bound near the
        surface of an ellipsoid (a flat box starts as a flat ellipsoid, not a ball poking out of it)."""
        a = self.semi_axes.to(u)
        k0 = torch.linalg.vector_norm(u / a, dim=-1)
        k1 = torch.linalg.vector_norm(u / (a * a), dim=-1)
        centre = k1 <= eps(u.dtype)  # the limit there is -min(a) (0 / 0 as written)
        return torch.where(centre, -a.min(), k0 * (k0 - 1) / torch.where(centre, torch.ones_like(k1), k1))

    def sdf_unit(self, u: Tensor) -> Tensor:
        """u [N, 3] -> signed distance [N] in u units (negative inside): the start plus the dense grid plus the
        factors (at inference the factors read from their node volume, module doc)."""
        xn = self._grid_coords(u)
        base = self.start(u)
        if self.dense is not None:
            base = base + F.grid_sample(self.dense, xn[None, :, None, None, :], align_corners=True).reshape(-1)
        if self._inferring() and self.resolution**3 <= MAX_VOLUME_NODES:
            grid = xn[None, :, None, None, :].to(self.planes[0].dtype)  # [1, N, 1, 1, 3] (x, y, z)
            return base + F.grid_sample(self._sdf_volume(), grid, align_corners=True).reshape(-1).to(u.dtype)
        return base + sum(p.sum(0) for p in _plane_features(self.planes, self.lines, xn))

    def _inferring(self) -> bool:
        return not self.training and not torch.is_grad_enabled()

    def _cached(self, name: str, factors: list[Tensor], build) -> object:
        key = factors_key(factors)
        hit = self._caches.get(name)
        if hit is None or hit[0] != key:
            with torch.no_grad():
                hit = (key, build())
            self._caches[name] = hit
        return hit[1]

    def _sdf_volume(self) -> Tensor:
        """The grid's plane-times-line sums at every node (`vm_node_volume`), cached: module doc."""
        return self._cached("sdf_volume", [*self.planes, *self.lines], lambda: vm_node_volume(self.planes, self.lines))

    def train(self, mode: bool = True) -> SdfField:
        self._caches.clear()  # a step between two modes may change the factors behind their versions (module doc)
        return super().train(mode)

    def sdf(self, x: Tensor) -> Tensor:
        """Scene points x [N, 3] -> signed distance [N] in scene units (negative inside)."""
        return self.sdf_unit(self.to_unit(x)) * self.half

    def sdf_and_gradient(self, u: Tensor, step: float | None = None) -> tuple[Tensor, Tensor]:
        """u [N, 3] -> (signed distance [N] (the six points' mean), gradient [N, 3]), central differences one grid
        cell wide (or `step`) in u units (module doc)."""
        h = self.cell if step is None else step
        f = self.sdf_unit((u[:, None, :] + h * AXES.to(u)).reshape(-1, 3)).reshape(-1, 6)  # [N, 6]
        return f.mean(-1), (f[:, :3] - f[:, 3:]) / (2 * h)

    def color(self, u: Tensor, normal: Tensor, d: Tensor | None) -> Tensor:
        """u [N, 3], unit normal [N, 3], unit view direction d [N, 3] (None: not view dependent) -> rgb [N, 3]."""
        xn = self._grid_coords(u)
        if self._inferring():
            factors = [*self.app_planes, *self.app_lines]
            tables = self._cached("app_tables", factors, lambda: VmTables.build(self.app_planes, self.app_lines))
            feat = self.basis(tables.features(xn))
        else:
            feat = self.basis(torch.cat(_plane_features(self.app_planes, self.app_lines, xn)).T)
        parts = [feat, normal]
        if self.view_dependent:
            if d is None:
                raise ValueError("this field is view dependent: pass directions d [N, 3]")
            parts += [d, positional_encoding(d, VIEW_FREQS, include_input=False)]
        return torch.sigmoid(self.mlp(torch.cat(parts, dim=-1)))

    # ------------------------------------------------------------------------------------------------ training
    def param_groups(self, lr: float) -> list[dict]:
        """The grids at lr, the colour network at lr / 20 (the density field's split), the log-sharpness at lr."""
        grids = [*self.planes, *self.lines, *self.app_planes, *self.app_lines]
        grids += [self.dense] if self.dense is not None else []
        nets = [*self.basis.parameters(), *self.mlp.parameters()]
        return [
            {"params": grids, "lr": lr, "lr_scale": 1.0},
            {"params": nets, "lr": lr / 20, "lr_scale": 1 / 20},
            {"params": [self.log_sharpness], "lr": lr, "lr_scale": 1.0},
        ]

    @torch.no_grad()
    def upsample(self, resolution: int) -> None:
        """Resample the planes and lines to `resolution` (coarse-to-fine; the optimiser must start afresh)."""
        for group in (self.planes, self.lines, self.app_planes, self.app_lines):
            for i, p in enumerate(group):
                size = (resolution, resolution) if p.shape[-1] > 1 else (resolution, 1)
                group[i] = nn.Parameter(F.interpolate(p.data, size=size, mode="bilinear", align_corners=True))
        self.resolution = int(resolution)

    def config(self) -> dict:
        """What rebuilds the field (its state dict fills it)."""
        return {
            "aabb": self.aabb.tolist(),
            "resolution": self.resolution,
            "rank": self.rank,
            "app_rank": self.app_rank,
            "app_dim": self.app_dim,
            "hidden": self.hidden,
            "view_dependent": self.view_dependent,
            "radius": self.radius,
            "sharpness": self.initial_sharpness,
            "dense": self.dense.shape[-1] if self.dense is not None else 0,
        }
