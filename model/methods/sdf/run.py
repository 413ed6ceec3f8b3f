"""An SDF run for the stages (`model.run.Run`): capabilities rays, sdf, color; and its self-check.

The run answers in the scene frame: `sdf(x)` in scene units (negative inside; `mesh` extracts its zero level set),
`color(x, d)` with the normal from the distance's gradient, `render_rays` through the model's own quadrature. It
gives no density (export-points and splat say so in one line): NeuS's opacity belongs to an interval of a ray, not
to a point.

Self-check (`sdf_checks`, the train manifest's `checks`), on a grid of points over the box:
- eikonal_residual: mean | |grad f| - 1 | where |f| is within a few cells of the surface: a distance whose
  gradient is far from unit length is not a distance, and its zero level set is unreliable;
- surface_found: the share of the box inside the surface: 0 means no surface (the start shape vanished), a share near 1
  means the surface left the box (the object was not isolated);
- sharpness: NeuS's band 1 / s in grid cells: the opacity still smeared over more than a cell means training
  stopped before the surface converged (an under-trained run).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import torch
from torch import Tensor

from nerfpipe.data.checks import Check
from nerfpipe.data.transforms import Scene
from nerfpipe.model.appearance import Appearance
from nerfpipe.model.device import rays_per_chunk, render_in_chunks
from nerfpipe.model.methods.sdf.model import SdfModel
from nerfpipe.radiance.safe import eps
from nerfpipe.radiance.space import Space

__all__ = ["SdfRun", "sdf_checks", "EIKONAL_LIMIT", "INSIDE_LIMITS", "BAND_LIMIT"]

EIKONAL_LIMIT = 0.2
"""Largest mean | |grad f| - 1 | near the surface of a run that checks ok."""
INSIDE_LIMITS = (1e-4, 0.5)
"""Share of the box inside the surface of a run that checks ok (an object in its box)."""
BAND_LIMIT = 1.0
"""Largest NeuS band 1 / s, in grid cells, of a run that checks ok."""
CHECK_GRID = 48


@dataclass
class SdfRun:
    """An SDF method's run, ready for rendering and queries (no grad, chunked; module doc)."""

    scene: Scene
    model: SdfModel
    device: torch.device
    background: Tensor  # [3] evaluation background
    downscale: float = 1.0
    pose_refinement: dict | None = None
    method: str = "sdf"
    capabilities: frozenset = frozenset({"rays", "sdf", "color"})
    occupancy = None

    @property
    def far(self) -> float:
        return float(self.model.space.far)

    @property
    def space(self) -> Space:
        """The scene space (a contracted scene's mesh crops to the looked-at box: `stages.mesh.crop`)."""
        return self.model.space

    @property
    def aabb(self) -> Tensor:
        return self.model.field.aabb.to(self.device)  # the signed distance's box (a contracted scene's inner box)

    @property
    def chunk(self) -> int:
        return rays_per_chunk(self.model.chunk, self.device)

    @property
    def appearance(self) -> Appearance | None:
        return self.model.appearance

    @torch.no_grad()
    def render_rays(self, rays_o: Tensor, rays_d: Tensor, *, infer=None, median: bool = True) -> dict[str, Tensor]:
        """rays_o, rays_d [R, 3] (unit) -> dict(rgb [R, 3], depth [R], acc [R], and with `median` depth_median [R])."""
        render = partial(self.model.render, background=self.background, train=False)
        return render_in_chunks(render, rays_o, rays_d, self.chunk, self.device, median=median)

    @torch.no_grad()
    def sdf(self, x: Tensor) -> Tensor:
        """x [N, 3] scene frame -> signed distance [N] in scene units (negative inside)."""
        field = self.model.field
        out = [field.sdf(x[i : i + 65536].to(self.device, torch.float32)) for i in range(0, x.shape[0], 65536)]
        return torch.cat(out) if out else x.new_zeros(0)

    @torch.no_grad()
    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        """x [N, 3], d [N, 3] unit or None (looking along -normal) -> rgb [N, 3] in [0, 1]."""
        field, out = self.model.field, []
        for i in range(0, x.shape[0], self.chunk):
            u = field.to_unit(x[i : i + self.chunk].to(self.device, torch.float32))
            _, g = field.sdf_and_gradient(u)
            normal = g / torch.linalg.vector_norm(g, dim=-1, keepdim=True).clamp_min(eps(g.dtype))
            di = None
            if field.view_dependent:
                di = -normal if d is None else d[i : i + self.chunk].to(u)
            out.append(field.color(u, normal, di))
        return torch.cat(out) if out else x.new_zeros(0, 3)


@torch.no_grad()
def sdf_checks(model: SdfModel, resolution: int = CHECK_GRID) -> list[Check]:
    """The run's self-check (module doc) on a resolution^3 grid of the box."""
    field = model.field
    box = field.aabb
    axes = [torch.linspace(0, 1, resolution, device=box.device) for _ in range(3)]
    frac = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    u = field.to_unit(box[0] + frac * (box[1] - box[0]))
    f, g = [], []
    for i in range(0, u.shape[0], 65536):
        fi, gi = field.sdf_and_gradient(u[i : i + 65536])
        f.append(fi)
        g.append(gi)
    f, g = torch.cat(f), torch.cat(g)
    near = f.abs() < 3 * field.cell
    residual = float((torch.linalg.vector_norm(g[near], dim=-1) - 1).abs().mean()) if bool(near.any()) else math.nan
    inside = float((f < 0).float().mean())
    band = 1.0 / (float(field.sharpness.detach()) * field.cell)
    return [
        Check.upper(
            "eikonal_residual",
            residual,
            EIKONAL_LIMIT,
            says="the signed distance's gradient is far from unit length near its surface: not a distance, its "
            "zero level set is unreliable (nan: no surface)",
        ),
        Check.lower(
            "surface_found",
            inside if inside <= INSIDE_LIMITS[1] else -inside,
            INSIDE_LIMITS[0],
            says=f"share of the box inside the surface outside ({INSIDE_LIMITS[0]:g}, {INSIDE_LIMITS[1]:g}]: no "
            "surface, or one that fills the box (negative: the share, too large)",
        ),
        Check.upper(
            "sharpness_band",
            band,
            BAND_LIMIT,
            unit=" cells",
            says="NeuS's opacity is still spread over more than a grid cell (1 / sharpness): training stopped "
            "before the surface converged",
        ),
    ]
