"""Scene contraction for unbounded captures (mip-NeRF 360's, with nerfacto's L-infinity norm), and marching in it.

Conventions:
- The inner box (centre c [3], half sides h [3], scene frame) is the object's box: `y = (x - c) / h`; points with
  `|y|_inf <= 1` map to themselves (`contract(x) = y`), the rest of space to the shell `1 < |y'|_inf < 2`:
  `contract(x) = (2 - 1 / n) * y / n` with `n = |y|_inf`. The field and its occupancy grid live in the
  contracted cube [-2, 2]^3.
- The field's density sigma' is per unit of *contracted* length. The renderer works in world t (distance along
  the ray in scene units), so an interval [t0, t1] gets the effective world density
  `sigma = sigma' * |contract(x(t1)) - contract(x(t0))| / (t1 - t0)`: its optical depth is sigma' times the
  interval's contracted (chord) length. Far intervals are long in the world and short in contracted space, so
  the field needs no tiny densities for the background and the occupancy threshold means the same everywhere.
- Sampling (`march_contracted`): each ray is stepped uniformly in a warped distance s (mip-NeRF 360's idea): s = t
  up to the ray's switch distance t_s (where it leaves the inner box, or its closest approach to the centre when
  it misses the box; at least the origin's distance to the centre), and `s = t_s + K (t_s - t_s^2 / t)` beyond (K
  = `OUTER_SHARE` = 0.5), which reaches (1 + K) t_s at infinity; so steps are uniform inside the object and grow
  like t^2 / K outside, as contracted space does, with half the inner density of samples in the shell (the
  background is seen at lower resolution). The last step stops one step short of s = (1 + K) t_s. Intervals whose
  contracted midpoint lies in an unoccupied cell of the grid are dropped. Output is packed like
  `radiance.occupancy.march_rays`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nerfpipe.radiance.aabb import ray_aabb_intersect
from nerfpipe.radiance.occupancy import OccupancyGrid, Xyz

__all__ = [
    "CONTRACTED_BOX",
    "Contraction",
    "contraction_chord_scale",
    "chord_scale_xyz",
    "ChordScale",
    "march_contracted",
    "march_contracted_reference",
    "normalized_distance",
    "t_of_s",
    "warped_range",
]

CONTRACTED_BOX = ((-2.0, -2.0, -2.0), (2.0, 2.0, 2.0))
OUTER_SHARE = 0.5
"""K: samples beyond the switch distance, relative to a uniform step count over the same contracted length."""
"""The box the field and the occupancy grid span in contracted coordinates."""


class Contraction:
    """The L-infinity contraction around an inner box (scene frame)."""

    def __init__(self, inner_aabb):  # [2, 3]
        box = torch.as_tensor(inner_aabb, dtype=torch.float32).reshape(2, 3)
        if not bool((box[1] > box[0]).all()):
            raise ValueError(f"expected an inner box with max > min on every axis, got {box.tolist()}")
        self.center = (box[0] + box[1]) / 2  # [3]
        self.half = (box[1] - box[0]) / 2  # [3]

    @property
    def inner_aabb(self) -> Tensor:  # [2, 3]
        return torch.stack([self.center - self.half, self.center + self.half])

    def to_dict(self) -> dict:
        return {"kind": "linf", "inner_aabb": self.inner_aabb.tolist()}

    @classmethod
    def from_dict(cls, doc: dict) -> Contraction:
        return cls(doc["inner_aabb"])

    def contract(self, x: Tensor) -> Tensor:
        """x [N, 3] scene frame -> [N, 3] in [-2, 2]^3 (identity on the normalised inner box)."""
        y = (x - self.center.to(x)) / self.half.to(x)
        n = y.abs().amax(dim=-1, keepdim=True)  # [N, 1]
        safe_n = n.clamp(min=1.0)
        return torch.where(n <= 1, y, (2 - 1 / safe_n) * y / safe_n)

    def contract_xyz(self, xs: Xyz) -> Xyz:
        """`contract` on coordinates held apart (x, y, z: three tensors of one shape, e.g. [A, S]): the same values,
        element for element, at a fifth of the cost (torch's element-wise maths on rows of 3 vectorises poorly)."""
        center, half = self.center.to(xs[0]), self.half.to(xs[0])
        ys = [(x - center[i]) / half[i] for i, x in enumerate(xs)]
        n = torch.maximum(torch.maximum(ys[0].abs(), ys[1].abs()), ys[2].abs())
        safe_n = n.clamp(min=1.0)
        factor = 2 - 1 / safe_n  # inside (n <= 1): safe_n = 1 and factor = 1, so y comes back unchanged
        return tuple(factor * y / safe_n for y in ys)  # type: ignore[return-value]

    def uncontract(self, y: Tensor) -> Tensor:
        """Inverse of `contract` for y [N, 3] with |y|_inf < 2 (the boundary maps to infinity)."""
        m = y.abs().amax(dim=-1, keepdim=True)
        safe_m = m.clamp(min=1.0, max=2.0 - torch.finfo(y.dtype).eps)
        n = 1 / (2 - safe_m)
        x_n = torch.where(m <= 1, y, y / safe_m * n)
        return x_n * self.half.to(y) + self.center.to(y)

    def density_scale(self, x: Tensor) -> Tensor:
        """Contracted length per scene length at x [N, 3], along the radial direction -> [N] (1/h inside the
        box). For point queries (meshing) where no interval is at hand; rendering uses interval chords."""
        y = (x - self.center.to(x)) / self.half.to(x)
        n = y.abs().amax(dim=-1).clamp(min=1.0)
        return 1.0 / (n * n * self.half.to(x).min())


def _switch_distance(c: Contraction, rays_o: Tensor, rays_d: Tensor, near: Tensor) -> Tensor:
    """Where the warp starts growing, per ray [R]: the exit of the inner box (or the closest approach to its
    centre when the ray misses it), but at least the origin's distance to the centre and the box's largest half
    side, so rays looking away from the box still reach far (about t_s^2 K / step)."""
    _, t_far, hit = ray_aabb_intersect(rays_o, rays_d, c.inner_aabb.to(rays_o))
    centre = c.center.to(rays_o)
    t_closest = ((centre - rays_o) * rays_d).sum(-1).clamp(min=0.0)
    t_s = torch.where(hit, t_far, t_closest)
    t_s = torch.maximum(t_s, torch.linalg.norm(rays_o - centre, dim=-1).clamp(min=float(c.half.max())))
    return torch.maximum(t_s, near + 1e-3 * c.half.min().item())


def warped_range(
    c: Contraction,
    rays_o: Tensor,
    rays_d: Tensor,
    *,
    near: float | Tensor,
    step_size: float,
    jitter: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Each ray's warped marching range: (switch distance t_s [R], first step's s [R], s_end [R]); steps are
    s = s0 + k step_size while s < s_end, the last one ending at s_end (module doc)."""
    near_t = torch.as_tensor(near, dtype=rays_o.dtype, device=rays_o.device).expand(rays_o.shape[0])
    t_s = _switch_distance(c, rays_o, rays_d, near_t)  # [R]
    s0 = near_t + (jitter.to(rays_o) * step_size if jitter is not None else 0.0)
    return t_s, s0, (1 + OUTER_SHARE) * t_s - step_size


def t_of_s(s: Tensor, t_s: Tensor) -> Tensor:
    """Inverse warp: s <= t_s -> t = s; beyond, t = t_s^2 / (t_s - (s - t_s) / K)."""
    rest = (t_s - (s - t_s) / OUTER_SHARE).clamp(min=torch.finfo(s.dtype).tiny)
    return torch.where(s <= t_s, s, t_s * t_s / rest)


def normalized_distance(
    c: Contraction,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    near: float | Tensor,  # scalar or [R]
    t: Tensor,  # [N] world distances
    ray_indices: Tensor,  # [N] long
) -> Tensor:  # [N] in [0, 1]
    """The warped distance s of the marching (module doc) scaled to [0, 1] per ray: 0 at `near`, 1 at s's end
    (1 + K) t_s, i.e. at infinity. Uniform inside the object, compressed like contracted space beyond it (what
    mip-NeRF 360's distortion loss is measured in)."""
    r = rays_o.shape[0]
    near_t = torch.as_tensor(near, dtype=rays_o.dtype, device=rays_o.device).expand(r)
    t_s = _switch_distance(c, rays_o, rays_d, near_t)  # [R]
    ts, n0 = t_s[ray_indices], near_t[ray_indices]
    beyond = ts + OUTER_SHARE * (ts - ts * ts / t.clamp(min=torch.finfo(t.dtype).tiny))
    s = torch.where(t <= ts, t, beyond)
    return ((s - n0) / ((1 + OUTER_SHARE) * ts - n0)).clamp(0.0, 1.0)


def contraction_chord_scale(c: Contraction, rays_o: Tensor, rays_d: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
    """Contracted chord length / world length of each interval: rays_o, rays_d [N, 3] (per sample), t0, t1 [N]
    -> [N]."""
    a = c.contract(rays_o + rays_d * t0[:, None])
    b = c.contract(rays_o + rays_d * t1[:, None])
    return torch.linalg.norm(b - a, dim=-1) / (t1 - t0).clamp(min=torch.finfo(t0.dtype).tiny)


def chord_scale_xyz(c: Contraction, rays_o: Xyz, rays_d: Xyz, rows: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
    """`contraction_chord_scale` of intervals [t0, t1] [M] of rays `rows` [M], the rays given as coordinates held
    apart (x, y, z, each [R]): the same values, element for element."""
    o = [v.index_select(0, rows) for v in rays_o]
    d = [v.index_select(0, rows) for v in rays_d]
    a = c.contract_xyz(tuple(o[i] + d[i] * t0 for i in range(3)))  # type: ignore[arg-type]
    b = c.contract_xyz(tuple(o[i] + d[i] * t1 for i in range(3)))  # type: ignore[arg-type]
    chord = torch.linalg.norm(torch.stack([b[i] - a[i] for i in range(3)], dim=-1), dim=-1)  # norm's own sum
    return chord / (t1 - t0).clamp(min=torch.finfo(t0.dtype).tiny)


class ChordScale:
    """`chord_scale_xyz` for many intervals of the same rays [R, 3], cheaper: an interval inside the inner box (both
    ends between the ray's entry and exit) has the per-ray chord scale |d / half| (the contraction is linear there),
    so only the intervals outside are contracted. The same values up to float rounding."""

    def __init__(self, c: Contraction, rays_o: Tensor, rays_d: Tensor) -> None:
        self.c = c
        self.o_xyz, self.d_xyz = tuple(rays_o.T.contiguous()), tuple(rays_d.T.contiguous())  # x, y, z [R] each
        t_in, t_out, hit = ray_aabb_intersect(rays_o, rays_d, c.inner_aabb.to(rays_o))
        self.t_in = torch.where(hit, t_in, math.inf)  # [R] no interval is inside a ray that misses the box
        self.t_out = t_out  # [R]
        self.inside_scale = torch.linalg.norm(rays_d / c.half.to(rays_d), dim=-1)  # [R] |d / half|

    def __call__(self, rows: Tensor, t0: Tensor, t1: Tensor) -> Tensor:  # rows [M], t0, t1 [M] -> [M]
        inside = (t0 >= self.t_in.index_select(0, rows)) & (t1 <= self.t_out.index_select(0, rows))
        scale = self.inside_scale.index_select(0, rows)
        out = torch.nonzero(~inside)[:, 0]
        if out.numel():
            rows_out, a, b = rows.index_select(0, out), t0.index_select(0, out), t1.index_select(0, out)
            scale.index_copy_(0, out, chord_scale_xyz(self.c, self.o_xyz, self.d_xyz, rows_out, a, b))
        return scale


@torch.no_grad()
def march_contracted(
    grid: OccupancyGrid,  # over CONTRACTED_BOX
    contraction: Contraction,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    near: float | Tensor,
    step_size: float,  # in s (scene units inside the inner box)
    jitter: Tensor | None = None,  # [R] in [0, 1): shifts each ray's steps
) -> tuple[Tensor, Tensor, Tensor]:
    """Warped-distance marching through contracted space (see the module doc).

    Returns packed (ray_indices [N] long, t_starts [N], t_ends [N]) in world t, sorted by ray then t.
    """
    if not step_size > 0:
        raise ValueError(f"expected step_size > 0, got {step_size}")
    r = rays_o.shape[0]
    t_s, s0, s_end = warped_range(contraction, rays_o, rays_d, near=near, step_size=step_size, jitter=jitter)
    span = float((s_end - s0).max()) if r else 0.0
    n_steps = max(0, math.ceil(span / step_size))
    k = torch.arange(n_steps, dtype=rays_o.dtype, device=rays_o.device)  # [M]
    s_a = s0[:, None] + k * step_size  # [R, M]
    s_b = torch.minimum(s_a + step_size, s_end[:, None])
    valid = s_a < s_end[:, None]
    ray_idx, col = torch.nonzero(valid, as_tuple=True)
    ts = t_s[ray_idx]
    t0, t1 = t_of_s(s_a[ray_idx, col], ts), t_of_s(s_b[ray_idx, col], ts)
    mid = rays_o[ray_idx] + rays_d[ray_idx] * (0.5 * (t0 + t1))[:, None]
    keep = grid.query(contraction.contract(mid))
    return ray_idx[keep], t0[keep], t1[keep]


def march_contracted_reference(
    grid: OccupancyGrid, contraction: Contraction, rays_o: Tensor, rays_d: Tensor, *, near: float, step_size: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Plain per-ray loop twin of `march_contracted` (no jitter; for tests)."""
    ids, starts, ends = [], [], []
    for i in range(rays_o.shape[0]):
        o, d = rays_o[i : i + 1], rays_d[i : i + 1]
        t_s = float(_switch_distance(contraction, o, d, torch.full((1,), float(near), dtype=o.dtype))[0])
        s_end = (1 + OUTER_SHARE) * t_s - step_size
        k = 0
        while True:
            s_a = float(near) + k * step_size
            if not s_a < s_end:
                break
            s_b = min(s_a + step_size, s_end)
            t0 = s_a if s_a <= t_s else t_s * t_s / (t_s - (s_a - t_s) / OUTER_SHARE)
            t1 = s_b if s_b <= t_s else t_s * t_s / (t_s - (s_b - t_s) / OUTER_SHARE)
            mid = o + d * (0.5 * (t0 + t1))
            if bool(grid.query(contraction.contract(mid))[0]):
                ids.append(i)
                starts.append(t0)
                ends.append(t1)
            k += 1
    like = dict(dtype=rays_o.dtype)
    return torch.tensor(ids, dtype=torch.long), torch.tensor(starts, **like), torch.tensor(ends, **like)
