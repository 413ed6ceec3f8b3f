"""Scene spaces: where a field lives and how a ray is marched through it (nerfstudio's SpatialDistortion, applied
once).

A space owns everything that differs between an object in its box, a forward-facing capture and an unbounded
one: the field's box, the rays' bounds, the map from scene-frame rays into the rays the marcher walks (and depths
back), the steps of the occupancy march (training: packed and jittered; inference: per-ray step ranges for the
early-stopping marcher), the map from scene points to field points and field density to scene density, which
losses and samplers it supports, its record in the manifest, and its serialisation. Callers never ask which
space they hold.

- `Box`: the field spans the scene's box (scene frame); rays march straight through the occupied cells' box.
- `NDCSpace`: the field lives in NDC of the mean camera (`radiance.ndc`); rays are mapped into NDC, marched as in
  a box (near 0, far: the end of the NDC box), and their depths mapped back to scene distances.
- `Contracted`: everything beyond the scene's box contracted into a shell (`radiance.contraction`); rays are
  stepped uniformly in a warped distance and the field's density is per contracted length (chord-scaled).

Conventions: rays_o, rays_d [R, 3] (unit d) in the scene frame; t is distance along the ray; grids are
`radiance.occupancy.OccupancyGrid` over `field_box`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.contraction import (
    CONTRACTED_BOX,
    ChordScale,
    Contraction,
    contraction_chord_scale,
    march_contracted,
    normalized_distance,
    t_of_s,
    warped_range,
)
from nerfpipe.radiance.ndc import NDC
from nerfpipe.radiance.occupancy import OccupancyGrid, Xyz, march_bounds, march_rays, occupied_span

__all__ = ["Packed", "Steps", "Space", "Box", "NDCSpace", "Contracted", "SPACES", "space_from_dict"]

FAR = 1e10
"""The far bound of spaces that reach infinity (NDC, contracted): a float, so that it serialises."""


@dataclass(frozen=True)
class Packed:
    """A training march's samples, packed [N] and sorted by ray then t: intervals [t_starts, t_ends) of ray
    ray_indices, their midpoints in field coordinates, and the factor from the field's density to a density per
    scene length along the ray (None: 1)."""

    ray_indices: Tensor  # [N] long
    t_starts: Tensor  # [N]
    t_ends: Tensor  # [N]
    points: Tensor  # [N, 3] field coordinates
    density_scale: Tensor | None  # [N]


@dataclass(frozen=True)
class Steps:
    """Uniform steps of an inference march, per ray: u = u0 + k step while u < u_end (the last step ends at u_end);
    u is t (box) or the warped distance s (contracted). `warp(u [A, S], rows [A]) -> t`, `point(xyz) -> field and
    occupancy position` of march points given as coordinates held apart (`radiance.occupancy.Xyz`: x, y, z of one
    shape, e.g. [A, S]; far cheaper than rows of 3), `scale(rows [M], t0 [M], t1 [M]) -> field density to world
    density` (or None).
    `k_first`, `k_stop` [R] (float, whole numbers): only steps k_first <= k < k_stop are taken, the others being
    known to be empty; u is still u0 + k step, so the steps taken are the training march's (without jitter)."""

    u0: Tensor  # [R]
    u_end: Tensor  # [R]
    step: float
    warp: Callable[[Tensor, Tensor], Tensor]
    point: Callable[[Xyz], Xyz]
    scale: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None
    k_first: Tensor | None = None  # [R]
    k_stop: Tensor | None = None  # [R]


def _per_ray(value: float | Tensor, rays_o: Tensor) -> Tensor:
    v = torch.as_tensor(value, dtype=rays_o.dtype, device=rays_o.device)
    return v.expand(rays_o.shape[0]) if v.ndim == 0 else v


@dataclass(frozen=True, kw_only=True)
class Space:
    """What every scene space provides (see the module doc). Subclasses set the class attributes."""

    name: ClassVar[str]
    """Its name in config.json, the manifest and `train --scene-model`."""
    straight_rays: ClassVar[bool] = True
    """Rays are straight lines of the field's box (stratified sampling in the box, vanilla NeRF, works)."""
    distortion_loss: ClassVar[bool] = False
    """mip-NeRF 360's distortion loss is defined (a normalised warped distance exists)."""
    sparse_depth: ClassVar[bool] = False
    """Sparse structure-from-motion depths help (measured on the fox; see `stages.train`)."""
    object_box: ClassVar[bool] = False
    """The field's box is the object's own box: a box mostly occupied means the object was not isolated."""
    scene_frame: ClassVar[bool] = False
    """Field coordinates are scene coordinates (the occupancy grid can be read as a scene-frame grid)."""

    near: float
    """Where rays start (marcher t)."""
    far: float
    """Where rays end (marcher t; FAR: never)."""

    @property
    def field_box(self) -> Tensor:  # [2, 3]
        raise NotImplementedError

    def step_unit(self) -> float:
        """March units per unit of the field's box (the march step is `box side / resolution x ratio x this`)."""
        return 1.0

    def to_march(self, rays_o: Tensor, rays_d: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """Scene-frame rays -> the rays the marcher walks, and which are valid ([R] bool; None: all)."""
        return rays_o, rays_d, None

    def depth_from_march(self, rays_o: Tensor, rays_d: Tensor, o_m: Tensor, d_m: Tensor, t: Tensor) -> Tensor:
        """Marcher distances t [R] along the mapped rays (o_m, d_m) -> distances along the scene rays."""
        return t

    def march(self, grid: OccupancyGrid, rays_o: Tensor, rays_d: Tensor, step: float, jitter: Tensor | None) -> Packed:
        """The training march: packed samples at `step` in the occupied cells; jitter [R] in [0, 1) shifts each
        ray's steps by jitter x step (None: no shift)."""
        raise NotImplementedError

    def steps(self, grid: OccupancyGrid, rays_o: Tensor, rays_d: Tensor, step: float) -> Steps:
        """The inference march's steps: `march`'s without jitter, empty spans left out where known."""
        raise NotImplementedError

    def box_segment(self, rays_o: Tensor, rays_d: Tensor) -> tuple[Tensor, Tensor]:
        """Each ray's [t_near, t_far] [R] in the field's box within near and far (stratified sampling)."""
        return ray_aabb_segment(rays_o, rays_d, self.field_box.to(rays_o), self.near, self.far)

    def field_points(self, x: Tensor) -> Tensor:
        """Scene points x [N, 3] -> field points [N, 3]."""
        return x

    def density_query(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        """Scene points x [N, 3] -> (field points [N, 3], field density to scene density [N] or None for 1)."""
        return x, None

    def field_directions(self, x: Tensor, d: Tensor) -> Tensor:
        """Scene directions d [N, 3] at scene points x [N, 3] -> the field's view directions."""
        return d

    def normalized_distance(self, rays_o: Tensor, rays_d: Tensor, t: Tensor, ray_indices: Tensor) -> Tensor:
        """Distances t [N] of ray ray_indices -> [0, 1] (the distortion loss's s); only where distortion_loss."""
        raise ValueError(f"the distortion loss is not defined in a {self.name} space")

    def to_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        """The manifest's record of the space."""
        return {**self.to_dict(), "field_box": self.field_box.tolist()}

    def left_out(self, forward_facing: bool) -> dict[str, str]:
        """What the manifest says this space leaves out, and why."""
        return {}


def _occupied_segment(space: Space, grid, rays_o, rays_d) -> tuple[Tensor, Tensor]:
    """Each ray's [t_near, t_far] [R] through the box around the grid's occupied cells, within [near, far]
    (both 0 when nothing is occupied)."""
    near_t, far_t = _per_ray(space.near, rays_o), _per_ray(space.far, rays_o)
    box = grid.occupied_aabb()
    if box is None:
        zero = torch.zeros(rays_o.shape[0], dtype=rays_o.dtype, device=rays_o.device)
        return zero, zero
    return ray_aabb_segment(rays_o, rays_d, box, near_t, far_t)


def _box_march(space: Space, grid, rays_o, rays_d, step, jitter) -> Packed:
    """Occupancy marching at `step` through the box around the occupied cells, within [near, far]."""
    t_near, t_far = _occupied_segment(space, grid, rays_o, rays_d)
    if jitter is not None:
        t_near = t_near + jitter * step
    ray_idx, t0, t1 = march_rays(grid, rays_o, rays_d, near=t_near, far=torch.maximum(t_far, t_near), step_size=step)
    x = rays_o[ray_idx] + rays_d[ray_idx] * (0.5 * (t0 + t1))[:, None]  # [N, 3]
    return Packed(ray_idx, t0, t1, x, None)


def _box_steps(space: Space, grid, rays_o, rays_d, step) -> Steps:
    """`_box_march`'s steps (no jitter), limited to each ray's `occupied_span`: the steps before the span's first
    and after its last have their midpoints in empty cells (no density, no weight), so leaving them out changes
    nothing."""
    t_near, t_far = _occupied_segment(space, grid, rays_o, rays_d)
    u0, u_end = march_bounds(grid, rays_o, rays_d, t_near, torch.maximum(t_far, t_near))
    first, last = occupied_span(grid, rays_o, rays_d, u0, u_end)  # [R]
    k_first = torch.floor((first - u0) / step).clamp(min=0)  # last step starting at or before first
    k_stop = torch.floor((last - u0) / step) + 1  # one past the last step starting at or before last
    k_stop = torch.where(last >= first, k_stop, k_first)  # nothing occupied: no steps
    return Steps(u0, u_end, step, lambda u, rows: u, lambda xyz: xyz, None, k_first, k_stop)


@dataclass(frozen=True, kw_only=True)
class Box(Space):
    """The scene's own box (objects: alpha or a plain background)."""

    name: ClassVar[str] = "box"
    object_box: ClassVar[bool] = True
    scene_frame: ClassVar[bool] = True
    aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    """The scene's box, scene frame."""

    @property
    def field_box(self) -> Tensor:
        return torch.tensor(self.aabb, dtype=torch.float32)

    def march(self, grid, rays_o, rays_d, step, jitter):
        return _box_march(self, grid, rays_o, rays_d, step, jitter)

    def steps(self, grid, rays_o, rays_d, step):
        return _box_steps(self, grid, rays_o, rays_d, step)

    def to_dict(self):
        return {"kind": self.name, "aabb": [list(r) for r in self.aabb], "near": self.near, "far": self.far}

    def left_out(self, forward_facing):
        ndc = (
            "forward-facing scene trained in its box because that was asked for"
            if forward_facing
            else "360-degree scene: NDC only applies to forward-facing captures"
        )
        return {
            "ndc": ndc,
            "contraction": "the scene's box holds everything the photos show (alpha or a plain background)",
        }


@dataclass(frozen=True, kw_only=True)
class NDCSpace(Space):
    """NDC of the mean camera (forward-facing captures): rays mapped in, depths mapped out, marched as in a box."""

    name: ClassVar[str] = "ndc"
    ndc: NDC
    box: tuple[tuple[float, float, float], tuple[float, float, float]]
    """The NDC box holding every training camera's frustum (`radiance.ndc.NDC.box`)."""
    near: float = 0.0
    far: float = FAR

    @property
    def field_box(self) -> Tensor:
        return torch.tensor(self.box, dtype=torch.float32)

    def to_march(self, rays_o, rays_d):
        return self.ndc.rays_to_ndc(rays_o, rays_d)

    def depth_from_march(self, rays_o, rays_d, o_m, d_m, t):
        return self.ndc.world_t(rays_o, rays_d, o_m, d_m, t)

    def march(self, grid, rays_o, rays_d, step, jitter):
        return _box_march(self, grid, rays_o, rays_d, step, jitter)

    def steps(self, grid, rays_o, rays_d, step):
        return _box_steps(self, grid, rays_o, rays_d, step)

    def field_points(self, x):
        return self.ndc.points_to_ndc(x)

    def density_query(self, x):
        """NDC density times NDC length per scene length along the mean camera's ray through x; 0 on or before the
        near plane (outside the modelled frustum)."""
        p, scale, front = self.ndc.density_query(x)
        return p.clamp(-2.0, 2.0), torch.where(front, scale, torch.zeros_like(scale))

    def field_directions(self, x, d):
        return self.ndc.directions_to_ndc(x, d)

    def to_dict(self):
        return {"kind": self.name, "ndc": self.ndc.to_dict(), "box": [list(r) for r in self.box]}

    def describe(self):
        note = (
            "field and occupancy grid live in NDC of the mean camera (radiance.ndc); depths are mapped back to "
            "scene units"
        )
        return {**super().describe(), "note": note}

    def left_out(self, forward_facing):
        return {"aabb": "forward-facing: the field spans the NDC frustum (near plane to infinity), not the aabb"}


@dataclass(frozen=True, kw_only=True)
class Contracted(Space):
    """The scene's box at full resolution, all space beyond it contracted into a shell (unbounded captures)."""

    name: ClassVar[str] = "contract"
    straight_rays: ClassVar[bool] = False
    distortion_loss: ClassVar[bool] = True
    sparse_depth: ClassVar[bool] = True
    contraction: Contraction
    far: float = FAR

    @property
    def field_box(self) -> Tensor:
        return torch.tensor(CONTRACTED_BOX, dtype=torch.float32)

    def step_unit(self) -> float:
        """Contracted units -> scene units inside the inner box."""
        return float(self.contraction.half.mean())

    def march(self, grid, rays_o, rays_d, step, jitter):
        ray_idx, t0, t1 = march_contracted(
            grid, self.contraction, rays_o, rays_d, near=self.near, step_size=step, jitter=jitter
        )
        x = self.contraction.contract(rays_o[ray_idx] + rays_d[ray_idx] * (0.5 * (t0 + t1))[:, None])  # [N, 3]
        scale = contraction_chord_scale(self.contraction, rays_o[ray_idx], rays_d[ray_idx], t0, t1)  # [N]
        return Packed(ray_idx, t0, t1, x, scale)

    def steps(self, grid, rays_o, rays_d, step):
        c = self.contraction
        t_s, s0, s_end = warped_range(c, rays_o, rays_d, near=self.near, step_size=step)
        scale = ChordScale(c, rays_o, rays_d)  # contraction_chord_scale's values
        return Steps(s0, s_end, step, lambda u, rows: t_of_s(u, t_s[rows][:, None]), c.contract_xyz, scale)

    def box_segment(self, rays_o, rays_d):
        raise ValueError("a contracted space has no straight rays through a box: expected a marched field")

    def field_points(self, x):
        return self.contraction.contract(x)

    def density_query(self, x):
        """Contracted-space density times contracted length per scene length (radial; exact inside the box)."""
        return self.contraction.contract(x), self.contraction.density_scale(x)

    def normalized_distance(self, rays_o, rays_d, t, ray_indices):
        return normalized_distance(self.contraction, rays_o, rays_d, self.near, t, ray_indices)

    def to_dict(self):
        return {"kind": self.name, "contraction": self.contraction.to_dict(), "near": self.near}

    def describe(self):
        note = (
            "field and occupancy grid live in contracted space; the scene's box maps to [-1, 1]^3 and "
            "everything beyond it into the shell up to 2"
        )
        return {**super().describe(), "note": note}

    def left_out(self, forward_facing):
        ndc = (
            "forward-facing scene contracted because that was asked for"
            if forward_facing
            else "360-degree scene: NDC only applies to forward-facing captures"
        )
        return {"ndc": ndc}


SPACES: dict[str, type[Space]] = {cls.name: cls for cls in (Box, NDCSpace, Contracted)}
"""Every space by name (the names `train --scene-model` takes)."""


def _pair(rows) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    lo, hi = (tuple(float(v) for v in r) for r in rows)
    if len(lo) != 3 or len(hi) != 3:
        raise ValueError(f"expected a box [[x, y, z], [x, y, z]], got {rows}")
    return lo, hi  # type: ignore[return-value]


def space_from_dict(doc: dict[str, Any]) -> Space:
    """The space a `to_dict()` wrote; ValueError naming what was expected."""
    kind = doc.get("kind") if isinstance(doc, dict) else None
    if kind == Box.name:
        return Box(aabb=_pair(doc["aabb"]), near=float(doc["near"]), far=float(doc["far"]))
    if kind == NDCSpace.name:
        return NDCSpace(ndc=NDC.from_dict(doc["ndc"]), box=_pair(doc["box"]))
    if kind == Contracted.name:
        return Contracted(contraction=Contraction.from_dict(doc["contraction"]), near=float(doc["near"]))
    raise ValueError(f"expected a scene space of kind {', '.join(SPACES)}, got {kind!r}")
