"""Occupancy grid over an axis-aligned box, and ray marching that samples only occupied cells.

Conventions:
- The grid covers `aabb [2, 3]` (min, max) with G x G x G cells, indexed [ix, iy, iz] along x, y, z;
  cell (i, j, k) spans lo + (i, j, k) * cell_size to lo + (i + 1, j + 1, k + 1) * cell_size.
- `density [G, G, G]` is a running estimate of the field's density sigma (1 / length) per cell:
  at each update, updated cells become max(decay * old, sigma at random points in the cell).
  `binary [G, G, G]` marks cells with density > min(threshold, mean density) (nerfacc's rule).
  Before the first update every cell counts as occupied.
- Points outside the box are never occupied.
- Marching: rays (unit directions, t = distance) step from max(near, t_box_in) to min(far, t_box_out) in
  intervals of `step_size` (the last one shorter); intervals whose midpoint lies in an unoccupied cell are
  dropped. Output is packed: `ray_indices [N]` (non-decreasing), `t_starts [N]`, `t_ends [N]`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from nerfpipe.radiance.aabb import as_aabb, ray_aabb_intersect

__all__ = [
    "Xyz",
    "OccupancyGrid",
    "march_bounds",
    "march_rays",
    "march_rays_reference",
    "query_reference",
    "occupied_span",
]

Xyz = tuple[Tensor, Tensor, Tensor]
"""Points as coordinates held apart: x, y, z, three tensors of one shape (element-wise maths on them vectorises;
on [N, 3] rows of 3 torch's CPU kernels run 4-6x slower)."""

SPAN_FACTORS = (4, 1)
"""`occupied_span`'s passes: coarse cells this many fine cells a side, each pass within the span of the last."""


class OccupancyGrid(torch.nn.Module):
    """[G, G, G] occupancy over a box, kept as buffers (saved by state_dict, moved by .to())."""

    def __init__(self, aabb, resolution: int = 128, *, threshold: float = 0.01, decay: float = 0.95):
        super().__init__()
        if resolution < 1:
            raise ValueError(f"expected resolution >= 1, got {resolution}")
        if not 0 <= decay <= 1:
            raise ValueError(f"expected decay in [0, 1], got {decay}")
        self.resolution = resolution
        self.threshold = threshold
        self.decay = decay
        g = resolution
        self.register_buffer("aabb", as_aabb(aabb, dtype=torch.float32).clone())  # [2, 3]
        self.register_buffer("density", torch.zeros(g, g, g))  # [G, G, G]
        self.register_buffer("binary", torch.ones(g, g, g, dtype=torch.bool))  # [G, G, G]

    @property
    def cell_size(self) -> Tensor:  # [3]
        return (self.aabb[1] - self.aabb[0]) / self.resolution

    @property
    def skip_fraction(self) -> float:
        """Fraction of cells marked empty (what marching skips)."""
        return 1.0 - float(self.binary.float().mean())

    def occupied_aabb(self) -> Tensor | None:
        """[2, 3] box around the occupied cells, padded by one cell and kept inside the grid's box
        (None when no cell is occupied)."""
        ijk = torch.nonzero(self.binary)  # [K, 3]
        if ijk.shape[0] == 0:
            return None
        lo = (ijk.amin(dim=0) - 1).clamp(min=0).to(self.aabb.dtype)
        hi = (ijk.amax(dim=0) + 2).clamp(max=self.resolution).to(self.aabb.dtype)
        return torch.stack([self.aabb[0] + lo * self.cell_size, self.aabb[0] + hi * self.cell_size])

    def cell_index(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x [N, 3] -> (cell index [N, 3], whole numbers in x's float dtype, clamped into the grid; inside-the-box
        mask [N])."""
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"expected x [N, 3], got {tuple(x.shape)}")
        lo, hi = self.aabb[0].to(x), self.aabb[1].to(x)
        inside = ((x >= lo) & (x <= hi)).all(dim=-1)  # [N]
        return torch.floor((x - lo) / (hi - lo) * self.resolution).clamp_(0, self.resolution - 1), inside

    def query(self, x: Tensor) -> Tensor:
        """Occupancy of points x [N, 3] -> bool [N] (False outside the box): the cells of `cell_index`, the flat
        index taken as a float dot product where it is exact (G^3 <= 2^24) and looked up by index_select (about
        2x three long index tensors and aten::index on CPU)."""
        ijk, inside = self.cell_index(x)
        g = self.resolution
        if g**3 <= 2**24:
            flat = (ijk @ torch.tensor([g * g, g, 1], dtype=x.dtype, device=x.device)).long()
        else:
            ijk = ijk.long()
            flat = (ijk[:, 0] * g + ijk[:, 1]) * g + ijk[:, 2]
        return self.binary.view(-1).index_select(0, flat) & inside

    def query_xyz(self, xs: Xyz) -> Tensor:
        """`query` of points given as coordinates held apart (x, y, z of one shape) -> bool of that shape: the same
        cells (the same float maths per coordinate), at a fifth of the cost."""
        lo, hi = self.aabb[0].to(xs[0]), self.aabb[1].to(xs[0])
        g, exact = self.resolution, self.resolution**3 <= 2**24
        inside, flat = None, None
        for i, x in enumerate(xs):
            ins = (x >= lo[i]) & (x <= hi[i])
            cell = torch.floor((x - lo[i]) / (hi[i] - lo[i]) * g).clamp_(0, g - 1)
            cell = cell if exact else cell.long()
            inside = ins if inside is None else inside & ins
            flat = cell if flat is None else flat * g + cell  # whole numbers < 2^24 when exact: no rounding
        return self.binary.view(-1).index_select(0, flat.reshape(-1).long()).view(flat.shape) & inside

    def cell_centers(self) -> Tensor:
        """Centres of all cells, flattened in [ix, iy, iz] order: [G^3, 3]."""
        return self._points_in_cells(torch.arange(self.resolution**3, device=self.aabb.device), None)

    def _points_in_cells(self, flat: Tensor, generator: torch.Generator | None) -> Tensor:
        g = self.resolution
        ijk = torch.stack([flat // (g * g), (flat // g) % g, flat % g], dim=-1).float()  # [M, 3]
        if generator is None:
            offset = torch.full_like(ijk, 0.5)
        else:
            offset = torch.rand(ijk.shape, generator=generator, device=ijk.device)
        return self.aabb[0] + (ijk + offset) * self.cell_size  # [M, 3]

    @torch.no_grad()
    def update(
        self,
        density_fn: Callable[[Tensor], Tensor],  # x [M, 3] -> sigma [M]
        step: int,
        *,
        every: int = 16,
        warmup_steps: int = 256,
        points_per_cell: int = 1,
        chunk: int = 1 << 18,
        generator: torch.Generator | None = None,
        full: bool = False,
    ) -> bool:
        """EMA update from the field's density; runs only when step % every == 0. Returns whether it ran.

        Before warmup_steps (or with `full`) every cell is refreshed; afterwards a random quarter of all cells
        plus a random quarter's worth of occupied cells (nerfacc's schedule). Each refreshed cell takes the max
        of `points_per_cell` densities at uniform random points inside it.
        """
        if step % every != 0 and not full:
            return False
        n_cells, device = self.resolution**3, self.aabb.device
        if full or step < warmup_steps:
            cells = torch.arange(n_cells, device=device)
        else:
            n = max(1, n_cells // 4)
            rand_cells = torch.randint(n_cells, (n,), generator=generator, device=device)
            occupied = torch.nonzero(self.binary.reshape(-1))[:, 0]
            if occupied.numel():
                pick = torch.randint(occupied.numel(), (n,), generator=generator, device=device)
                rand_cells = torch.cat([rand_cells, occupied[pick]])
            cells = torch.unique(rand_cells)
        if generator is None:
            generator = torch.Generator(device=device).manual_seed(step)
        sigma = torch.zeros(cells.shape[0], device=device)  # [M]
        for _ in range(points_per_cell):
            parts = [
                density_fn(self._points_in_cells(cells[i : i + chunk], generator)).reshape(-1).float()
                for i in range(0, cells.shape[0], chunk)
            ]
            got = torch.cat(parts)
            # NaN (a diverging field; training's non-finite-loss guard deals with it) counts as occupied, never
            # as empty space to skip; inf is the largest finite density (the threshold is a comparison).
            got = torch.where(torch.isnan(got), torch.full_like(got, math.inf), got)
            sigma = torch.maximum(sigma, got.clamp(max=torch.finfo(torch.float32).max))
        flat = self.density.view(-1)
        flat[cells] = torch.maximum(flat[cells] * self.decay, sigma)
        thresh = min(self.threshold, float(self.density.mean()))
        self.binary.copy_(self.density > thresh)
        return True


def query_reference(grid: OccupancyGrid, x: Tensor) -> Tensor:
    """Plain per-point loop twin of `OccupancyGrid.query` (for tests)."""
    lo, hi = grid.aabb[0].tolist(), grid.aabb[1].tolist()
    g, out = grid.resolution, []
    for p in x.tolist():
        if not all(lo[k] <= p[k] <= hi[k] for k in range(3)):
            out.append(False)
            continue
        ijk = [min(max(math.floor((p[k] - lo[k]) / (hi[k] - lo[k]) * g), 0), g - 1) for k in range(3)]
        out.append(bool(grid.binary[ijk[0], ijk[1], ijk[2]]))
    return torch.tensor(out, dtype=torch.bool)


def _coarse_dilated(binary: Tensor, factor: int) -> Tensor:
    """[G, G, G] bool -> [Gc, Gc, Gc] bool, Gc = ceil(G / factor): a coarse cell is set when any fine cell of it
    or of its 26 neighbours is (max-pool, then a 3 x 3 x 3 dilation)."""
    x = binary[None, None].to(torch.float32)  # [1, 1, G, G, G]
    x = torch.nn.functional.max_pool3d(x, factor, stride=factor, ceil_mode=True)
    return torch.nn.functional.max_pool3d(x, 3, stride=1, padding=1)[0, 0] > 0


@torch.no_grad()
def occupied_span(
    grid: OccupancyGrid,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    t0: Tensor,  # [R]
    t1: Tensor,  # [R]
    factors: tuple[int, ...] = SPAN_FACTORS,
) -> tuple[Tensor, Tensor]:
    """A conservative span [first, last] [R], [R] of each ray's occupied points within [t0, t1]: every t in
    [t0, t1] whose point `grid.query` calls occupied has first <= t <= last; first > last when there is none.

    The ray is sampled every h (0.9 of the smallest coarse-cell side, `factor` fine cells) against the coarse
    grid dilated by one cell (`_coarse_dilated`), samples outside the box clamped onto its border cells. An
    occupied point is within h / 2 of a sample, hence at most one coarse cell from it on every axis, so that
    sample is set; first / last are the first / last set sample -+ h / 2. Rays should be clipped to the box
    first (`march_bounds`): beyond it the clamping only widens the span.
    Costs about (t1 - t0) / h queries a ray, `factor` x fewer than marching at half a fine cell. With several
    `factors` (coarse to fine) each pass samples only the span the last one found, a conservative span itself."""
    if rays_o.ndim != 2 or rays_o.shape != rays_d.shape or t0.shape != rays_o.shape[:1] or t1.shape != t0.shape:
        raise ValueError(
            f"expected rays [R, 3] and t0, t1 [R], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}, "
            f"{tuple(t0.shape)}, {tuple(t1.shape)}"
        )
    if not factors or min(factors) < 1:
        raise ValueError(f"expected factors >= 1, got {factors}")
    first, last = t0, t1
    for factor in factors:
        first, last = _span_pass(grid, rays_o, rays_d, first, last, factor)
    return first, last


def _coarse_cached(grid: OccupancyGrid, factor: int) -> Tensor:
    """`_coarse_dilated(grid.binary, factor)`, kept until the grid's binary changes (its version counter)."""
    cache = grid.__dict__.setdefault("_span_cache", {})  # factor -> (binary's key, coarse grid)
    key = (grid.binary._version, grid.binary.data_ptr(), grid.binary.shape, grid.binary.device)
    if factor not in cache or cache[factor][0] != key:
        cache[factor] = (key, _coarse_dilated(grid.binary, factor))
    return cache[factor][1]


def _span_pass(grid, rays_o, rays_d, t0, t1, factor) -> tuple[Tensor, Tensor]:
    """One pass of `occupied_span` at coarse cells `factor` fine cells a side, on the rays whose span is open;
    samples packed (each ray gets ceil(length / h) + 1 of them), in chunks of about 4 M. Positions are taken in
    fine-cell units u = (x - lo) / cell: the cell `OccupancyGrid.cell_index` gives is floor(u), clamped."""
    coarse = _coarse_cached(grid, factor)
    gc, res = coarse.shape[0], grid.resolution
    h = 0.9 * float((grid.cell_size * factor).min())
    first = torch.full_like(t0, math.inf)
    last = torch.full_like(t0, -math.inf)
    rows = torch.nonzero(t1 > t0)[:, 0]  # [A]
    if rows.numel() == 0:
        return first, last
    per_cell = (res / (grid.aabb[1] - grid.aabb[0])).to(rays_o)  # [3] fine cells per unit length
    start = (rays_o[rows] + rays_d[rows] * t0[rows, None] - grid.aabb[0].to(rays_o)) * per_cell  # [A, 3] u at t0
    du = rays_d[rows] * (per_cell * h)  # [A, 3] u per sample
    start_xyz, du_xyz = start.T.contiguous(), du.T.contiguous()  # [3, A]: per sample, coordinates held apart
    span = t1[rows] - t0[rows]  # [A]
    count = torch.ceil(span / h).long() + 1  # [A] samples a ray
    ends = torch.cumsum(count, 0)  # [A]
    exact = gc**3 <= 2**24  # flat cell indices as whole floats
    i, budget = 0, 1 << 22
    while i < rows.numel():
        done = int(ends[i - 1]) if i else 0
        j = max(i + 1, int(torch.searchsorted(ends, done + budget, right=True)))  # rays [i, j) in this chunk
        c = count[i:j]
        ray = torch.repeat_interleave(torch.arange(j - i, device=t0.device), c)  # [N]
        k = torch.arange(ray.numel(), device=t0.device) - (torch.cumsum(c, 0) - c).index_select(0, ray)  # [N]
        k = torch.minimum(k.to(t0.dtype), (span[i:j] / h).index_select(0, ray))  # the last sample at t1
        cell = None  # [N] flat coarse cell
        for s_a, du_a in zip(start_xyz, du_xyz, strict=True):
            u = torch.addcmul(s_a[i:j].index_select(0, ray), du_a[i:j].index_select(0, ray), k)  # [N] on one axis
            c_a = u.clamp_(0, res - 1).floor_().div_(factor).floor_()  # [N] coarse cell on this axis
            c_a = c_a if exact else c_a.long()
            cell = c_a if cell is None else cell * gc + c_a
        hit = coarse.view(-1).index_select(0, cell.long())  # [N]
        t = t0[rows[i:j]].index_select(0, ray) + h * k  # [N]
        big = torch.tensor(math.inf, dtype=t.dtype, device=t.device)
        lo_t = torch.full((j - i,), math.inf, dtype=t0.dtype, device=t0.device)
        hi_t = torch.full((j - i,), -math.inf, dtype=t0.dtype, device=t0.device)
        lo_t = lo_t.scatter_reduce(0, ray, torch.where(hit, t, big), "amin")
        hi_t = hi_t.scatter_reduce(0, ray, torch.where(hit, t, -big), "amax")
        r = rows[i:j]
        first[r] = torch.maximum(lo_t - 0.5 * h, t0[r])
        last[r] = torch.minimum(hi_t + 0.5 * h, t1[r])
        i = j
    return first, last


def march_bounds(grid: OccupancyGrid, rays_o: Tensor, rays_d: Tensor, near, far) -> tuple[Tensor, Tensor]:
    """Each ray's marching range [t0, t1) [R], [R]: [near, far] within the grid's box (t1 = t0 when it misses)."""
    t_near, t_far, hit = ray_aabb_intersect(rays_o, rays_d, grid.aabb.to(rays_o))
    near_t = torch.as_tensor(near, dtype=rays_o.dtype, device=rays_o.device).expand_as(t_near)
    far_t = torch.as_tensor(far, dtype=rays_o.dtype, device=rays_o.device).expand_as(t_near)
    t0, t1 = torch.maximum(t_near, near_t), torch.minimum(t_far, far_t)  # [R]
    return t0, torch.where(hit, t1, t0)  # missed rays: empty range


@torch.no_grad()
def march_rays(
    grid: OccupancyGrid,
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    near: float | Tensor = 0.0,  # scalar or [R]
    far: float | Tensor = float("inf"),  # scalar or [R]
    step_size: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Uniform steps inside the box, keeping intervals whose midpoint is occupied.

    Returns packed (ray_indices [N] long, t_starts [N], t_ends [N]) in rays' dtype, sorted by ray then t.
    Memory is R x (longest chord / step_size); chunk the rays for big batches.
    """
    if not step_size > 0:
        raise ValueError(f"expected step_size > 0, got {step_size}")
    t0, t1 = march_bounds(grid, rays_o, rays_d, near, far)  # [R]
    span = float((t1 - t0).max()) if t0.numel() else 0.0
    n_steps = max(0, math.ceil(span / step_size) + 1)
    k = torch.arange(n_steps, dtype=rays_o.dtype, device=rays_o.device)  # [M]
    starts = t0[:, None] + k * step_size  # [R, M]
    ends = torch.minimum(starts + step_size, t1[:, None])  # [R, M]
    valid = starts < t1[:, None]  # [R, M]
    ray_idx, col = torch.nonzero(valid, as_tuple=True)  # row-major: sorted by ray, then t
    s, e = starts[ray_idx, col], ends[ray_idx, col]  # [N']
    mid = rays_o[ray_idx] + rays_d[ray_idx] * (0.5 * (s + e))[:, None]  # [N', 3]
    keep = grid.query(mid)  # [N']
    return ray_idx[keep], s[keep], e[keep]


def march_rays_reference(
    grid: OccupancyGrid, rays_o: Tensor, rays_d: Tensor, *, near=0.0, far=float("inf"), step_size: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Plain per-ray while-loop twin of `march_rays` (for tests)."""
    t0, t1 = march_bounds(grid, rays_o, rays_d, near, far)
    ids, starts, ends = [], [], []
    for r in range(rays_o.shape[0]):
        k = 0
        while True:
            s = t0[r] + torch.tensor(float(k), dtype=rays_o.dtype) * step_size
            if not s < t1[r]:
                break
            e = torch.minimum(s + step_size, t1[r])
            mid = rays_o[r] + rays_d[r] * (0.5 * (s + e))
            if query_reference(grid, mid[None])[0]:
                ids.append(r)
                starts.append(s)
                ends.append(e)
            k += 1
    like = dict(dtype=rays_o.dtype)
    if not ids:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, **like), torch.zeros(0, **like)
    return torch.tensor(ids, dtype=torch.long), torch.stack(starts), torch.stack(ends)
