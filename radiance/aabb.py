"""Ray versus axis-aligned bounding box intersection (slab method).

Conventions:
- `aabb`: [2, 3] rows (min corner, max corner), or [6] as (xmin, ymin, zmin, xmax, ymax, zmax).
- Rays: `rays_o [R, 3]`, `rays_d [R, 3]` in the same frame as the box; `t` is the ray parameter
  (`x = o + t d`; Euclidean distance when `d` has unit length).
- Only the part of the ray with t >= 0 counts: a ray starting inside the box has t_near = 0.
- A direction component exactly 0 (either sign) makes that slab either all of t (origin between the two
  planes, inclusive) or empty (origin outside); no 0 * inf NaNs.
- Missed rays get `hit = False` and t_near = t_far = 0. A ray grazing a face or edge (t_near == t_far) is a hit.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["as_aabb", "ray_aabb_intersect", "ray_aabb_segment", "ray_aabb_intersect_reference"]


def as_aabb(aabb, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Normalise a box to a [2, 3] tensor (min, max); accepts [2, 3] or [6] (tensor, array or sequence)."""
    box = torch.as_tensor(aabb, dtype=dtype, device=device)
    if box.shape == (6,):
        box = box.reshape(2, 3)
    if box.shape != (2, 3):
        raise ValueError(f"expected aabb [2, 3] or [6], got {tuple(box.shape)}")
    if not bool((box[1] >= box[0]).all()):
        raise ValueError(f"expected aabb min <= max, got {box.tolist()}")
    return box


def _check_rays(rays_o: Tensor, rays_d: Tensor) -> None:
    if rays_o.ndim != 2 or rays_o.shape[-1] != 3:
        raise ValueError(f"expected rays_o [R, 3], got {tuple(rays_o.shape)}")
    if rays_d.shape != rays_o.shape:
        raise ValueError(f"expected rays_d {tuple(rays_o.shape)}, got {tuple(rays_d.shape)}")


def ray_aabb_intersect(rays_o: Tensor, rays_d: Tensor, aabb) -> tuple[Tensor, Tensor, Tensor]:
    """Intersect rays with a box.

    rays_o, rays_d: [R, 3]; aabb: [2, 3] or [6].
    Returns (t_near [R], t_far [R], hit [R] bool); t_near >= 0, and t_near = t_far = 0 where not hit.
    """
    _check_rays(rays_o, rays_d)
    box = as_aabb(aabb, dtype=rays_o.dtype, device=rays_o.device)  # [2, 3]
    inside_slab = (rays_o >= box[0]) & (rays_o <= box[1])  # [R, 3]
    zero = rays_d == 0  # [R, 3]
    d_safe = torch.where(zero, torch.ones_like(rays_d), rays_d)
    t0 = (box[0] - rays_o) / d_safe  # [R, 3]
    t1 = (box[1] - rays_o) / d_safe  # [R, 3]
    lo, hi = torch.minimum(t0, t1), torch.maximum(t0, t1)  # [R, 3]
    inf = torch.full_like(lo, float("inf"))
    # Zero direction: the slab is all of t when the origin lies between its planes, else empty.
    lo = torch.where(zero, torch.where(inside_slab, -inf, inf), lo)
    hi = torch.where(zero, torch.where(inside_slab, inf, -inf), hi)
    t_near = lo.amax(dim=-1).clamp(min=0)  # [R]
    t_far = hi.amin(dim=-1)  # [R]
    hit = t_far >= t_near  # [R]
    zeros = torch.zeros_like(t_near)
    return torch.where(hit, t_near, zeros), torch.where(hit, t_far, zeros), hit


def ray_aabb_segment(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3]
    aabb,  # [2, 3] or [6]
    near: float | Tensor,  # scalar or [R]
    far: float | Tensor,  # scalar or [R]
) -> tuple[Tensor, Tensor]:
    """The part of [near, far] inside the box: (t0 [R], t1 [R]) with t0 >= near and t1 >= t0.

    t0 = max(t_near, near); t1 = min(t_far, far) for hit rays, t1 = t0 (empty) for missed rays and where
    the box ends before `near`.
    """
    t0, t1, hit = ray_aabb_intersect(rays_o, rays_d, aabb)
    like = dict(dtype=t0.dtype, device=t0.device)
    t0 = torch.maximum(t0, torch.as_tensor(near, **like))
    t1 = torch.where(hit, torch.minimum(t1, torch.as_tensor(far, **like)), t0)
    return t0, torch.maximum(t1, t0)


def ray_aabb_intersect_reference(rays_o: Tensor, rays_d: Tensor, aabb) -> tuple[Tensor, Tensor, Tensor]:
    """Plain per-ray, per-axis loop twin of `ray_aabb_intersect` (for tests)."""
    _check_rays(rays_o, rays_d)
    box = as_aabb(aabb, dtype=torch.float64).tolist()
    t_near, t_far, hit = [], [], []
    for o, d in zip(rays_o.tolist(), rays_d.tolist(), strict=True):
        near, far = 0.0, float("inf")
        for k in range(3):
            if d[k] == 0:
                if not box[0][k] <= o[k] <= box[1][k]:
                    near, far = float("inf"), -float("inf")
                continue
            a, b = (box[0][k] - o[k]) / d[k], (box[1][k] - o[k]) / d[k]
            near, far = max(near, min(a, b)), min(far, max(a, b))
        ok = far >= near
        t_near.append(near if ok else 0.0)
        t_far.append(far if ok else 0.0)
        hit.append(ok)
    like = dict(dtype=rays_o.dtype, device=rays_o.device)
    return torch.tensor(t_near, **like), torch.tensor(t_far, **like), torch.tensor(hit, device=rays_o.device)
