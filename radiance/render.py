"""Model-free volume rendering of rays: a sampler, a field callback and the compositing core.

Conventions:
- Rays: `rays_o [R, 3]`, `rays_d [R, 3]` unit length; `t` is distance along the ray; `near`, `far` are a
  float or [R] (far may be inf with a disparity sampler; the occupancy sampler clips to the grid's box).
- A sampler maps (rays_o, rays_d, near [R], far [R]) to `Samples`: intervals [t_start, t_end), padded [R, S]
  (`ray_indices` None) or packed [N] (`ray_indices [N]`). See radiance.compositing for the maths.
- The field is queried once per interval at its midpoint (t_start for an infinite last interval):
  `rgb_sigma_fn(x [N, 3], d [N, 3]) -> (rgb [N, 3], sigma [N])`, `sigma_fn(x [N, 3], d [N, 3]) -> sigma [N]`,
  always with flat [N, 3] inputs whatever the layout; the renderer knows nothing else about the model.
- `render_marched` (occupancy-grid marching, two passes) splits the callbacks instead:
  `sigma_fn(x [N, 3]) -> sigma [N]` on every sample (position only, like OccupancyGrid.update's density_fn),
  then `rgb_fn(x [K, 3], d [K, 3]) -> rgb [K, 3]` only on the K samples whose weight counts.
- `render_marched_terminating` / `render_contracted_terminating` are `render_marched` / `render_contracted` for
  inference (no grad, no jitter): the same steps taken front to back in slabs of `segment` steps, only on rays
  whose transmittance is still >= `min_transmittance` (early ray termination), per-ray outputs only; their plain
  twins are `render_marched` / `render_contracted` (equal with min_transmittance = 0).
- Outputs are dicts; per-ray entries (PER_RAY_KEYS) are [R] or [R, 3], per-sample ones are shaped like t_starts.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from radiance.aabb import ray_aabb_segment
from radiance.compositing import (
    accumulate,
    beer_lambert,
    composite,
    interval_midpoints,
    median_crossing,
    median_depth,
    optical_depth,
    render_weights,
)
from radiance.contraction import Contraction, contraction_chord_scale, march_contracted, t_of_s, warped_range
from radiance.occupancy import OccupancyGrid, march_bounds, march_rays, occupied_span
from radiance.safe import safe_div
from radiance.samplers import resample_intervals, stratified_intervals

__all__ = [
    "PER_RAY_KEYS",
    "Samples",
    "StratifiedSampler",
    "OccupancySampler",
    "sample_points",
    "render_rays",
    "render_rays_hierarchical",
    "render_marched",
    "render_marched_terminating",
    "render_contracted",
    "render_contracted_terminating",
    "render_depth",
    "render_attenuation",
    "chunked",
]

PER_RAY_KEYS = ("rgb", "depth", "depth_median", "acc")

RgbSigmaFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
SigmaFn = Callable[[Tensor, Tensor], Tensor]
PositionSigmaFn = Callable[[Tensor], Tensor]
RgbFn = Callable[[Tensor, Tensor], Tensor]


@dataclass(frozen=True)
class Samples:
    """Intervals along rays, padded [R, S] (ray_indices None) or packed [N] (ray_indices [N])."""

    t_starts: Tensor
    t_ends: Tensor
    ray_indices: Tensor | None
    n_rays: int


@dataclass(frozen=True, kw_only=True)
class StratifiedSampler:
    """n_samples contiguous intervals over [near, far] per ray (padded), see samplers.stratified_intervals."""

    n_samples: int
    """Intervals per ray."""
    spacing: str = "linear"
    """'linear' in t, or 'disparity' (uniform in 1/t, allows far = inf)."""
    jitter: bool = False
    """Jitter interior edges (training); off for evaluation."""
    generator: torch.Generator | None = None
    """Random source for the jitter."""

    def __call__(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor) -> Samples:
        t_starts, t_ends = stratified_intervals(
            near, far, self.n_samples, jitter=self.jitter, generator=self.generator, spacing=self.spacing
        )
        return Samples(t_starts, t_ends, None, rays_o.shape[0])


@dataclass(frozen=True, kw_only=True)
class OccupancySampler:
    """Packed samples at step_size, only in the grid's occupied cells, see occupancy.march_rays."""

    grid: OccupancyGrid
    """The occupancy grid (its box bounds the march)."""
    step_size: float
    """Interval length along the ray (scene units)."""

    def __call__(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor) -> Samples:
        ray_indices, t_starts, t_ends = march_rays(
            self.grid, rays_o, rays_d, near=near, far=far, step_size=self.step_size
        )
        return Samples(t_starts, t_ends, ray_indices, rays_o.shape[0])


def _check_rays(rays_o: Tensor, rays_d: Tensor) -> None:
    if rays_o.ndim != 2 or rays_o.shape[-1] != 3 or rays_d.shape != rays_o.shape:
        raise ValueError(f"expected rays_o, rays_d [R, 3], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")


def _per_ray(value: float | Tensor, rays_o: Tensor, name: str) -> Tensor:
    v = torch.as_tensor(value, dtype=rays_o.dtype, device=rays_o.device)
    if v.ndim == 0:
        return v.expand(rays_o.shape[0])
    if v.shape != (rays_o.shape[0],):
        raise ValueError(f"expected {name} a float or [R] with R={rays_o.shape[0]}, got {tuple(v.shape)}")
    return v


def sample_points(rays_o: Tensor, rays_d: Tensor, samples: Samples) -> tuple[Tensor, Tensor]:
    """Midpoints of the intervals as flat positions x [N, 3] and directions d [N, 3] (N = R * S if padded)."""
    t_mid = interval_midpoints(samples.t_starts, samples.t_ends)
    if samples.ray_indices is None:
        s = t_mid.shape[1]
        d = rays_d[:, None, :].expand(-1, s, -1).reshape(-1, 3)  # [R * S, 3]
        o = rays_o[:, None, :].expand(-1, s, -1).reshape(-1, 3)
        return o + d * t_mid.reshape(-1, 1), d
    d = rays_d[samples.ray_indices]  # [N, 3]
    return rays_o[samples.ray_indices] + d * t_mid[:, None], d


def _sample(rays_o, rays_d, near, far, sampler) -> Samples:
    _check_rays(rays_o, rays_d)
    return sampler(rays_o, rays_d, _per_ray(near, rays_o, "near"), _per_ray(far, rays_o, "far"))


def _eval_sigma(rays_o, rays_d, samples: Samples, sigma_fn: SigmaFn) -> Tensor:
    shape = samples.t_starts.shape
    if samples.t_starts.numel() == 0:
        return samples.t_starts.new_zeros(shape)
    x, d = sample_points(rays_o, rays_d, samples)
    return sigma_fn(x, d).reshape(shape)


def _composite_samples(rays_o, rays_d, samples: Samples, rgb_sigma_fn: RgbSigmaFn, background) -> dict:
    shape = samples.t_starts.shape
    if samples.t_starts.numel() == 0:
        sigmas, rgbs = samples.t_starts.new_zeros(shape), samples.t_starts.new_zeros((*shape, 3))
    else:
        x, d = sample_points(rays_o, rays_d, samples)
        rgbs, sigmas = rgb_sigma_fn(x, d)
        rgbs, sigmas = rgbs.reshape(*shape, -1), sigmas.reshape(shape)
    out = composite(
        sigmas, rgbs, samples.t_starts, samples.t_ends, samples.ray_indices, samples.n_rays, background=background
    )
    return {**out, "sigmas": sigmas, "t_starts": samples.t_starts, "t_ends": samples.t_ends,
            "ray_indices": samples.ray_indices}  # fmt: skip


def render_rays(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3]
    *,
    near: float | Tensor,
    far: float | Tensor,
    sampler: Callable[[Tensor, Tensor, Tensor, Tensor], Samples],
    rgb_sigma_fn: RgbSigmaFn,
    background: Tensor | None = None,  # [3] or [R, 3]
) -> dict:
    """Emission-absorption render: rgb [R, 3], depth [R] (expected t), depth_median [R], acc [R],
    plus weights, transmittance, sigmas, t_starts, t_ends, ray_indices (per sample)."""
    samples = _sample(rays_o, rays_d, near, far, sampler)
    return _composite_samples(rays_o, rays_d, samples, rgb_sigma_fn, background)


def render_rays_hierarchical(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3]
    *,
    near: float | Tensor,
    far: float | Tensor,
    coarse_sampler: StratifiedSampler,
    n_fine: int,
    coarse_fn: RgbSigmaFn,
    fine_fn: RgbSigmaFn,
    background: Tensor | None = None,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> dict:
    """Vanilla NeRF: a coarse pass, then the fine field on the coarse edges plus n_fine edges drawn
    from the coarse weights. Returns the fine pass's dict with the coarse pass's under "coarse"."""
    samples = _sample(rays_o, rays_d, near, far, coarse_sampler)
    coarse = _composite_samples(rays_o, rays_d, samples, coarse_fn, background)
    t_starts, t_ends = resample_intervals(
        samples.t_starts, samples.t_ends, coarse["weights"].detach(), n_fine, jitter=jitter, generator=generator
    )
    fine = _composite_samples(rays_o, rays_d, Samples(t_starts, t_ends, None, samples.n_rays), fine_fn, background)
    return {**fine, "coarse": coarse}


def _march_occupied(rays_o, rays_d, grid, near, far, step_size, jitter, generator) -> tuple[Tensor, ...]:
    """Packed samples of `render_marched` (and its terminating twin): occupancy marching at `step_size` through
    the box around the occupied cells, each ray shifted by U[0, step_size) when `jitter`. Returns ray_indices [N],
    t_starts [N], t_ends [N] and the midpoints x [N, 3]."""
    n = rays_o.shape[0]
    near_t, far_t = _per_ray(near, rays_o, "near"), _per_ray(far, rays_o, "far")
    box = grid.occupied_aabb()
    if box is None:
        t_near = t_far = torch.zeros(n, dtype=rays_o.dtype, device=rays_o.device)
    else:
        t_near, t_far = ray_aabb_segment(rays_o, rays_d, box, near_t, far_t)
    if jitter:
        u = torch.rand(t_near.shape, generator=generator, dtype=t_near.dtype, device=t_near.device)
        t_near = t_near + u * step_size
    ray_idx, t0, t1 = march_rays(grid, rays_o, rays_d, near=t_near, far=torch.maximum(t_far, t_near),
                                 step_size=step_size)  # fmt: skip
    x = rays_o[ray_idx] + rays_d[ray_idx] * (0.5 * (t0 + t1))[:, None]  # [N, 3]
    return ray_idx, t0, t1, x


def render_marched(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    grid: OccupancyGrid,
    sigma_fn: PositionSigmaFn,  # x [N, 3] -> sigma [N]
    rgb_fn: RgbFn | None,  # (x [K, 3], d [K, 3]) -> rgb [K, 3]; None: density only
    near: float | Tensor,
    far: float | Tensor,
    step_size: float,
    background: Tensor | None = None,  # [3] or [R, 3]
    color_threshold: float = 1e-4,
    color_per_ray: float = 16.0,
    color_min_per_ray: float = 0.0,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    with_median: bool = False,
) -> dict:
    """Occupancy-grid marching (packed samples) in two passes: density on every sample, colour where it counts.

    Marches only through the box around the grid's occupied cells (TensoRF's shrink, recomputed on the fly),
    at `step_size`; `jitter` shifts each ray's steps by U[0, step_size) (drawn from `generator`, the global
    source when None) so training sees every depth. Colour is evaluated only where the weight exceeds
    `color_threshold` (TensoRF's rule), and at most at the `color_per_ray * R` largest weights of the batch,
    which bounds the cost early on when every sample is faint, and at least at the `color_min_per_ray * R` largest
    (training: a gradient reaches the density even when every weight is below the threshold); samples left out
    contribute no colour (their weight still counts in `acc`).

    Returns acc [R], depth [R] (expected t), rgb [R, 3] (on the background; absent when rgb_fn is None),
    depth_median [R] (only with_median), and per sample (packed [N]) weights, sigmas, t_starts, t_ends,
    ray_indices.
    """
    _check_rays(rays_o, rays_d)
    ray_idx, t0, t1, x = _march_occupied(rays_o, rays_d, grid, near, far, step_size, jitter, generator)
    sigma = sigma_fn(x)  # [N]
    shade = dict(color_threshold=color_threshold, color_per_ray=color_per_ray, color_min_per_ray=color_min_per_ray,
                 with_median=with_median)  # fmt: skip
    return _shade_packed(rays_o, rays_d, ray_idx, t0, t1, x, sigma, rgb_fn=rgb_fn, background=background, **shade)


@dataclass(frozen=True)
class _Steps:
    """Uniform steps of a march, per ray: u = u0 + k step while u < u_end (the last step ends at u_end); u is t
    (box) or the warped distance s (contracted). `warp(u [A, S], rows [A]) -> t`, `point(x [M, 3]) -> field
    and occupancy position`, `scale(rows [M], t0 [M], t1 [M]) -> field density to world density` (or None).
    `k_first`, `k_stop` [R] (float, whole numbers): only steps k_first <= k < k_stop are taken, the others being
    known to be empty (`_skip_empty`); u is still u0 + k step, so the steps taken are the plain twin's."""

    u0: Tensor  # [R]
    u_end: Tensor  # [R]
    step: float
    warp: Callable[[Tensor, Tensor], Tensor]
    point: Callable[[Tensor], Tensor]
    scale: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None
    k_first: Tensor | None = None  # [R]
    k_stop: Tensor | None = None  # [R]


def _box_steps(rays_o, rays_d, grid, near, far, step_size) -> _Steps:
    """The steps `_march_occupied` takes (no jitter): through the occupied cells' box, within [near, far]."""
    near_t, far_t = _per_ray(near, rays_o, "near"), _per_ray(far, rays_o, "far")
    box = grid.occupied_aabb()
    if box is None:
        t_near = t_far = torch.zeros(rays_o.shape[0], dtype=rays_o.dtype, device=rays_o.device)
    else:
        t_near, t_far = ray_aabb_segment(rays_o, rays_d, box, near_t, far_t)
    t0, t1 = march_bounds(grid, rays_o, rays_d, t_near, torch.maximum(t_far, t_near))
    return _Steps(t0, t1, step_size, lambda u, rows: u, lambda x: x)


def _skip_empty(steps: _Steps, grid: OccupancyGrid, rays_o: Tensor, rays_d: Tensor) -> _Steps:
    """Box steps limited to each ray's `occupied_span`: the steps before the span's first step and after its last
    have their midpoints in empty cells (no density, no weight), so leaving them out changes nothing."""
    first, last = occupied_span(grid, rays_o, rays_d, steps.u0, steps.u_end)  # [R]
    k_first = torch.floor((first - steps.u0) / steps.step).clamp(min=0)  # last step starting at or before first
    k_stop = torch.floor((last - steps.u0) / steps.step) + 1  # one past the last step starting at or before last
    k_stop = torch.where(last >= first, k_stop, k_first)  # nothing occupied: no steps
    return dataclasses.replace(steps, k_first=k_first, k_stop=k_stop)


def _contracted_steps(rays_o, rays_d, contraction, near, step_size) -> _Steps:
    """The steps `march_contracted` takes (no jitter), in warped distance s; the field sees contracted points."""
    t_s, s0, s_end = warped_range(contraction, rays_o, rays_d, near=near, step_size=step_size)

    def scale(rows, t0, t1):
        return contraction_chord_scale(contraction, rays_o[rows], rays_d[rows], t0, t1)

    return _Steps(s0, s_end, step_size, lambda u, rows: t_of_s(u, t_s[rows][:, None]), contraction.contract, scale)


def _march_terminating(
    rays_o, rays_d, steps: _Steps, grid, sigma_fn, rgb_fn, *, background, color_threshold, color_per_ray,
    min_transmittance, segment, with_median, color_keep=None,
) -> dict:  # fmt: skip
    """Front-to-back marching in slabs of `segment` steps over the rays still alive (transmittance before the
    slab >= min_transmittance, steps left): occupancy, density on occupied steps, then the slab's weights from
    the optical depth carried over; acc, depth and the median accumulate per ray, colour candidates are kept.
    Colour is evaluated once at the end, chosen by `_shade_packed`'s rule (weight above color_threshold, at most
    color_per_ray x R of the largest), so with min_transmittance = 0 the result is the plain twin's.
    color_keep (the viewer's coarse preview): of those, colour only the samples whose weight is >= color_keep and
    each ray's largest, and scale each ray's colour by acc / (the coloured samples' weight), so that leaving out
    the faint samples does not darken the ray."""
    if not 0 <= min_transmittance < 1 or segment < 1:
        raise ValueError(f"expected min_transmittance in [0, 1) and segment >= 1, got {min_transmittance}, {segment}")
    n, like = rays_o.shape[0], dict(dtype=rays_o.dtype, device=rays_o.device)
    tau, acc, depth = (torch.zeros(n, **like) for _ in range(3))  # [R] optical depth, sum w, sum w t
    median = torch.full((n,), math.inf, **like) if with_median else None
    log_t_min = -math.log(min_transmittance) if min_transmittance > 0 else math.inf
    k_first = steps.k_first if steps.k_first is not None else torch.zeros(n, **like)  # [R]
    k_stop = steps.k_stop if steps.k_stop is not None else torch.full((n,), math.inf, **like)  # [R]
    alive = torch.nonzero((steps.u0 + k_first * steps.step < steps.u_end) & (k_first < k_stop))[:, 0]  # [A]
    picks: list[tuple[Tensor, Tensor, Tensor]] = []  # colour candidates: rows, field points, weights
    n_samples, k0 = 0, 0
    while alive.numel():
        k = k_first[alive, None] + torch.arange(k0, k0 + segment, **like)  # [A, S]
        u_end = steps.u_end[alive, None]  # [A, 1]
        u_a = steps.u0[alive, None] + k * steps.step  # [A, S]
        u_b = torch.minimum(u_a + steps.step, u_end)
        t0, t1 = steps.warp(u_a, alive), steps.warp(u_b, alive)  # [A, S]
        valid = (u_a < u_end) & (k < k_stop[alive, None])  # [A, S]
        t_mid = torch.where(valid, 0.5 * (t0 + t1), 0.0)  # steps past the end: no inf t (0 x inf in the depth)
        x = steps.point((rays_o[alive, None] + rays_d[alive, None] * t_mid[..., None]).reshape(-1, 3))  # [A S, 3]
        occ = torch.nonzero(valid.reshape(-1) & grid.query(x))[:, 0]  # [M] flat indices
        sigma = x.new_zeros(t0.shape)  # [A, S]
        if occ.numel():
            n_samples += occ.numel()
            s = sigma_fn(x[occ]).to(sigma.dtype)
            if steps.scale is not None:
                s = s * steps.scale(alive[occ // segment], t0.reshape(-1)[occ], t1.reshape(-1)[occ])
            sigma.view(-1)[occ] = s
            tau_s = optical_depth(sigma, t0, t1)  # [A, S]
            cum = torch.cumsum(tau_s, dim=1)
            trans = torch.exp(-(tau[alive, None] + cum - tau_s))  # [A, S] before each step
            w = trans * -torch.expm1(-tau_s)  # [A, S]
            if median is not None:
                undone = torch.isinf(median[alive])
                wb = acc[alive, None] + torch.cumsum(w, dim=1) - w
                crossed, t_med = median_crossing(sigma[undone], t0[undone], t1[undone], trans[undone], w[undone],
                                                 wb[undone])  # fmt: skip
                rows = alive[undone]
                median[rows[crossed]] = t_med[crossed]
            acc.index_add_(0, alive, w.sum(dim=1))
            depth.index_add_(0, alive, (w * t_mid).sum(dim=1))
            tau.index_add_(0, alive, cum[:, -1])
            if rgb_fn is not None:
                pick = torch.nonzero(w.reshape(-1) > color_threshold)[:, 0]
                picks.append((alive[pick // segment], x[pick], w.reshape(-1)[pick]))
        k0 += segment
        k_next = k_first[alive] + float(k0)
        nxt = (steps.u0[alive] + k_next * steps.step < steps.u_end[alive]) & (k_next < k_stop[alive])
        alive = alive[nxt & (tau[alive] <= log_t_min)]  # T = exp(-tau) >= min_transmittance
    out = {"acc": acc, "depth": safe_div(depth, acc), "samples": n_samples}
    if median is not None:
        out["depth_median"] = median
    if rgb_fn is not None:
        if not picks:
            picks.append((torch.zeros(0, dtype=torch.long, device=acc.device), acc.new_zeros(0, 3), acc.new_zeros(0)))
        rows, x, w = (torch.cat([p[i] for p in picks]) for i in range(3))
        keep = _colour_samples(w, n, color_threshold, color_per_ray, 0.0)  # the twin's rule (the picks pass it)
        if color_keep is not None:  # fewer: above color_keep or the ray's largest weight
            largest = torch.zeros(n, **like).scatter_reduce(0, rows, w, "amax")  # [R]
            keep = (keep & (w >= color_keep)) | (w >= largest[rows])
        rows, x, w = rows[keep], x[keep], w[keep]
        rgb = accumulate(w, rgb_fn(x, rays_d[rows]), rows, n) if rows.numel() else acc.new_zeros(n, 3)
        if color_keep is not None:  # the coloured samples stand for all of the ray's weight
            rgb = rgb * safe_div(acc, accumulate(w, None, rows, n))[:, None]
        out["rgb"] = rgb if background is None else rgb + (1 - acc)[:, None] * background.to(rgb)
    return out


@torch.no_grad()
def render_marched_terminating(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    grid: OccupancyGrid,
    sigma_fn: PositionSigmaFn,  # x [N, 3] -> sigma [N]
    rgb_fn: RgbFn | None,  # (x [K, 3], d [K, 3]) -> rgb [K, 3]; None: density only
    near: float | Tensor,
    far: float | Tensor,
    step_size: float,
    background: Tensor | None = None,  # [3] or [R, 3]
    color_threshold: float = 1e-4,
    color_per_ray: float = 16.0,
    min_transmittance: float = 1e-3,
    segment: int = 32,
    with_median: bool = False,
    color_keep: float | None = None,
) -> dict:
    """`render_marched` for inference, with early ray termination: the same steps (occupancy marching at
    `step_size`, no jitter), taken front to back in slabs of `segment` steps over the rays whose transmittance
    before the slab is >= `min_transmittance`; the rest of a ray is never sampled. The light lost is at most
    `min_transmittance` per ray (acc, rgb off by <= that; the median is unaffected below 0.5). Returns the per-ray
    outputs of `render_marched` (acc, depth, rgb when rgb_fn, depth_median with_median) and `samples`, the number
    of occupied samples whose density was evaluated; no per-sample outputs."""
    _check_rays(rays_o, rays_d)
    steps = _skip_empty(_box_steps(rays_o, rays_d, grid, near, far, step_size), grid, rays_o, rays_d)
    return _march_terminating(rays_o, rays_d, steps, grid, sigma_fn, rgb_fn, background=background,
                              color_threshold=color_threshold, color_per_ray=color_per_ray,
                              min_transmittance=min_transmittance, segment=segment,
                              with_median=with_median, color_keep=color_keep)  # fmt: skip


@torch.no_grad()
def render_contracted_terminating(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    grid: OccupancyGrid,  # over radiance.contraction.CONTRACTED_BOX
    contraction: Contraction,
    sigma_fn: PositionSigmaFn,  # contracted x' [N, 3] -> sigma' [N] per contracted length
    rgb_fn: RgbFn | None,  # (contracted x' [K, 3], world d [K, 3]) -> rgb [K, 3]
    near: float | Tensor,
    step_size: float,
    background: Tensor | None = None,  # [3] or [R, 3]
    color_threshold: float = 1e-4,
    color_per_ray: float = 16.0,
    min_transmittance: float = 1e-3,
    segment: int = 32,
    with_median: bool = False,
    color_keep: float | None = None,
) -> dict:
    """`render_contracted` for inference with early ray termination, as `render_marched_terminating` is for
    `render_marched`: the same warped steps (no jitter), slab by slab while the transmittance is >=
    `min_transmittance`. Outputs as `render_marched_terminating`."""
    _check_rays(rays_o, rays_d)
    steps = _contracted_steps(rays_o, rays_d, contraction, near, step_size)
    return _march_terminating(rays_o, rays_d, steps, grid, sigma_fn, rgb_fn, background=background,
                              color_threshold=color_threshold, color_per_ray=color_per_ray,
                              min_transmittance=min_transmittance, segment=segment,
                              with_median=with_median, color_keep=color_keep)  # fmt: skip


def render_contracted(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    grid: OccupancyGrid,  # over radiance.contraction.CONTRACTED_BOX
    contraction: Contraction,
    sigma_fn: PositionSigmaFn,  # contracted x' [N, 3] -> sigma' [N] per contracted length
    rgb_fn: RgbFn | None,  # (contracted x' [K, 3], world d [K, 3]) -> rgb [K, 3]
    near: float | Tensor,
    step_size: float,
    background: Tensor | None = None,  # [3] or [R, 3]
    color_threshold: float = 1e-4,
    color_per_ray: float = 16.0,
    color_min_per_ray: float = 0.0,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    with_median: bool = False,
) -> dict:
    """`render_marched` for unbounded scenes: the field lives in contracted space (radiance.contraction).

    Samples come from `march_contracted` (warped steps, occupancy in contracted space); the field is queried at
    contracted midpoints and its density turned into a world density by the interval's contracted chord per
    world length, so weights, depths (world t) and the median are computed exactly as in `render_marched`.
    """
    _check_rays(rays_o, rays_d)
    n = rays_o.shape[0]
    u = torch.rand(n, generator=generator, dtype=rays_o.dtype, device=rays_o.device) if jitter else None
    ray_idx, t0, t1 = march_contracted(grid, contraction, rays_o, rays_d, near=near, step_size=step_size, jitter=u)
    x = contraction.contract(rays_o[ray_idx] + rays_d[ray_idx] * (0.5 * (t0 + t1))[:, None])  # [N, 3]
    scale = contraction_chord_scale(contraction, rays_o[ray_idx], rays_d[ray_idx], t0, t1)  # [N]
    sigma = sigma_fn(x) * scale  # [N] per world length
    shade = dict(color_threshold=color_threshold, color_per_ray=color_per_ray, color_min_per_ray=color_min_per_ray,
                 with_median=with_median)  # fmt: skip
    return _shade_packed(rays_o, rays_d, ray_idx, t0, t1, x, sigma, rgb_fn=rgb_fn, background=background, **shade)


def _shade_packed(
    rays_o, rays_d, ray_idx, t0, t1, x, sigma, *, rgb_fn, background, color_threshold, color_per_ray, with_median,
    color_min_per_ray=0.0,
) -> dict:  # fmt: skip
    """Weights from packed densities; colour only where the weight counts (see render_marched)."""
    n = rays_o.shape[0]
    t_mid = 0.5 * (t0 + t1)
    weights, _, _ = render_weights(sigma, t0, t1, ray_idx, n)
    acc = accumulate(weights, None, ray_idx, n)  # [R]
    out = {"acc": acc}
    if rgb_fn is not None:
        keep = _colour_samples(weights.detach(), n, color_threshold, color_per_ray, color_min_per_ray)  # [N]
        rgb_s = rgb_fn(x[keep], rays_d[ray_idx[keep]])  # [K, 3]
        rgb = accumulate(weights[keep], rgb_s, ray_idx[keep], n)
        out["rgb"] = rgb if background is None else rgb + (1 - acc)[:, None] * background.to(rgb)
    out["depth"] = safe_div(accumulate(weights, t_mid, ray_idx, n), acc)
    if with_median:
        out["depth_median"] = median_depth(sigma, t0, t1, ray_idx, n)
    return {**out, "weights": weights, "sigmas": sigma, "t_starts": t0, "t_ends": t1, "ray_indices": ray_idx}


def _colour_samples(w: Tensor, n: int, threshold: float, per_ray: float, min_per_ray: float) -> Tensor:
    """Which samples get a colour, from their weights w [N] in a batch of n rays -> bool [N]: weight above
    `threshold`, at most the `per_ray * n` largest; and at least the `min_per_ray * n` largest when fewer pass
    (a faint batch: at initialisation every weight is below any threshold)."""
    keep = w > threshold
    budget = int(per_ray * n)
    if w.numel() > budget:
        keep &= w >= torch.topk(w, budget, sorted=False).values.min()
    floor = min(int(min_per_ray * n), w.numel())
    if floor > 0 and int(keep.sum()) < floor:
        keep = w >= torch.topk(w, floor, sorted=False).values.min()
    return keep


def render_depth(
    rays_o: Tensor,
    rays_d: Tensor,
    *,
    near: float | Tensor,
    far: float | Tensor,
    sampler: Callable[[Tensor, Tensor, Tensor, Tensor], Samples],
    sigma_fn: SigmaFn,
) -> dict:
    """Density-only emission-absorption: depth [R], depth_median [R], acc [R], weights (no colour)."""
    s = _sample(rays_o, rays_d, near, far, sampler)
    sigmas = _eval_sigma(rays_o, rays_d, s, sigma_fn)
    weights, trans, _ = render_weights(sigmas, s.t_starts, s.t_ends, s.ray_indices, s.n_rays)
    acc = accumulate(weights, None, s.ray_indices, s.n_rays)
    t_mid = interval_midpoints(s.t_starts, s.t_ends)
    return {
        "depth": safe_div(accumulate(weights, t_mid, s.ray_indices, s.n_rays), acc),
        "depth_median": median_depth(sigmas, s.t_starts, s.t_ends, s.ray_indices, s.n_rays),
        "acc": acc,
        "weights": weights,
        "transmittance": trans,
        "sigmas": sigmas,
        "t_starts": s.t_starts,
        "t_ends": s.t_ends,
        "ray_indices": s.ray_indices,
    }


def render_attenuation(
    rays_o: Tensor,
    rays_d: Tensor,
    *,
    near: float | Tensor,
    far: float | Tensor,
    sampler: Callable[[Tensor, Tensor, Tensor, Tensor], Samples],
    sigma_fn: SigmaFn,
    i0: float | Tensor = 1.0,
) -> dict:
    """X-ray (Beer-Lambert): intensity [R] = i0 exp(-optical_depth), optical_depth [R], transmittance [R]."""
    s = _sample(rays_o, rays_d, near, far, sampler)
    mus = _eval_sigma(rays_o, rays_d, s, sigma_fn)
    out = beer_lambert(mus, s.t_starts, s.t_ends, s.ray_indices, s.n_rays, i0=i0)
    return {**out, "sigmas": mus, "t_starts": s.t_starts, "t_ends": s.t_ends, "ray_indices": s.ray_indices}


def chunked(
    fn: Callable[..., dict],
    *tensors: Tensor,  # each [R, ...], sliced together along dim 0
    chunk: int = 8192,
    keys: tuple[str, ...] | None = PER_RAY_KEYS,
) -> dict[str, Tensor]:
    """Run fn on slices of `chunk` rays under no_grad and concatenate its outputs along dim 0.

    keys: which outputs to keep (default the per-ray ones; None keeps every tensor output, which must then
    all be per-ray). Keeps peak memory to one chunk's samples.
    """
    if chunk < 1:
        raise ValueError(f"expected chunk >= 1, got {chunk}")
    if not tensors or any(t.shape[0] != tensors[0].shape[0] for t in tensors):
        raise ValueError(f"expected tensors with one leading size, got {[tuple(t.shape) for t in tensors]}")
    parts: dict[str, list[Tensor]] = {}
    with torch.no_grad():
        for i in range(0, tensors[0].shape[0], chunk):
            out = fn(*(t[i : i + chunk] for t in tensors))
            for k, v in out.items():
                if isinstance(v, Tensor) and (keys is None or k in keys):
                    parts.setdefault(k, []).append(v)
    return {k: torch.cat(v, dim=0) for k, v in parts.items()}
