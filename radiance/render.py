"""Model-free volume rendering of rays: a sampler, a field callback and the compositing core.

Conventions:
- Rays: `rays_o [R, 3]`, `rays_d [R, 3]` unit length; `t` is distance along the ray; `near`, `far` are a
  float or [R] (far may be inf with a disparity sampler or a marcher; a marcher clips to its grid's box).
- A sampler (`Sampler`) maps (rays_o, rays_d, near [R], far [R]) to `Samples`: intervals [t_start, t_end), padded
  [R, S] (`ray_indices` None) or packed [N] (`ray_indices [N]`). See radiance.compositing for the maths. The
  samplers: `StratifiedSampler`, and `Marcher` (the occupancy march of a scene space, the one `render_marched`
  uses).
- The field is queried once per interval at its midpoint (t_start for an infinite last interval):
  `rgb_sigma_fn(x [N, 3], d [N, 3]) -> (rgb [N, 3], sigma [N])`, `sigma_fn(x [N, 3], d [N, 3]) -> sigma [N]`,
  always with flat [N, 3] inputs whatever the layout; the renderer knows nothing else about the model.
- `render_marched` (occupancy-grid marching in any scene space, `radiance.space`, two passes) splits the
  callbacks instead: `sigma_fn(x [N, 3]) -> sigma [N]` on every sample (position only, like
  OccupancyGrid.update's density_fn), then `rgb_fn(x [K, 3], d [K, 3]) -> rgb [K, 3]` only on the K samples whose
  weight counts (`ColourRule`). Early ray termination is its `min_transmittance` argument: the same steps taken
  front to back in slabs, only on rays whose transmittance is still >= min_transmittance, per-ray outputs only;
  its plain twin is the same call with min_transmittance None (equal with min_transmittance = 0).
- Outputs are dicts; per-ray entries (PER_RAY_KEYS) are [R] or [R, 3], per-sample ones are shaped like t_starts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.radiance.compositing import (
    accumulate,
    beer_lambert,
    composite,
    interval_midpoints,
    median_crossing,
    median_depth,
    optical_depth,
    render_weights,
)
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.safe import safe_div
from nerfpipe.radiance.samplers import resample_intervals, stratified_intervals
from nerfpipe.radiance.space import Space, Steps

__all__ = [
    "PER_RAY_KEYS",
    "Samples",
    "Sampler",
    "StratifiedSampler",
    "sample_points",
    "render_rays",
    "render_rays_hierarchical",
    "ColourRule",
    "RayColour",
    "Marcher",
    "render_marched",
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
class RayColour:
    """A colour callback in two parts, for fields whose view dependence enters through a per-ray term (TensoRF's
    MLP: its first layer's direction columns): `per_ray(d [R, 3]) -> codes [R, D]` once per ray, then
    `colour(x [K, 3], codes [K, D]) -> rgb [K, 3]` per sample, each sample given its ray's code. The same values as
    an `RgbFn` of (x, d), without encoding every sample's direction."""

    per_ray: Callable[[Tensor], Tensor]
    colour: Callable[[Tensor, Tensor], Tensor]


def _per_sample(rgb_fn: RgbFn | RayColour, rays_d: Tensor, rows: Tensor) -> tuple[RgbFn, Tensor]:
    """The colour callback of samples on rays `rows` [K] of rays_d [R, 3] and its second argument for them: the
    directions [K, 3], or for a `RayColour` its per-sample callback and each sample's ray code [K, D]."""
    if isinstance(rgb_fn, RayColour):
        return rgb_fn.colour, rgb_fn.per_ray(rays_d).index_select(0, rows)
    return rgb_fn, rays_d.index_select(0, rows)


@dataclass(frozen=True)
class Samples:
    """Intervals along rays, padded [R, S] (ray_indices None) or packed [N] (ray_indices [N]). A `Marcher`'s
    samples also carry their midpoints in field coordinates and the factor from the field's density to a density
    per ray length (`render_marched` reads them; the other renderers query the callbacks at `sample_points`)."""

    t_starts: Tensor
    t_ends: Tensor
    ray_indices: Tensor | None
    n_rays: int
    points: Tensor | None = None  # [N, 3] field coordinates (a marcher's; None: not known)
    density_scale: Tensor | None = None  # [N] (None: 1)


Sampler = Callable[[Tensor, Tensor, Tensor, Tensor], Samples]
"""(rays_o [R, 3], rays_d [R, 3], near [R], far [R]) -> Samples."""


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
    return {
        **out,
        "sigmas": sigmas,
        "t_starts": samples.t_starts,
        "t_ends": samples.t_ends,
        "ray_indices": samples.ray_indices,
    }


def render_rays(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3]
    *,
    near: float | Tensor,
    far: float | Tensor,
    sampler: Sampler,
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
) -> dict:
    """Vanilla NeRF: a coarse pass, then the fine field on the coarse edges plus n_fine edges drawn
    from the coarse weights (jittered, and from the generator, as the coarse sampler is). Returns the fine pass's
    dict with the coarse pass's under "coarse"."""
    samples = _sample(rays_o, rays_d, near, far, coarse_sampler)
    coarse = _composite_samples(rays_o, rays_d, samples, coarse_fn, background)
    t_starts, t_ends = resample_intervals(
        samples.t_starts,
        samples.t_ends,
        coarse["weights"].detach(),
        n_fine,
        jitter=coarse_sampler.jitter,
        generator=coarse_sampler.generator,
    )
    fine = _composite_samples(rays_o, rays_d, Samples(t_starts, t_ends, None, samples.n_rays), fine_fn, background)
    return {**fine, "coarse": coarse}


@dataclass(frozen=True, kw_only=True)
class ColourRule:
    """Which samples of a march get a colour (TensoRF's rule): weight above `threshold`, at most the
    `per_ray x R` largest of a batch of R rays (training: bounds the cost early on, when every sample is faint;
    None: no budget, every sample above the threshold), at least
    the `min_per_ray x R` largest when fewer pass (training: a gradient reaches the density even when every weight
    is below the threshold). `keep` (inference only, the viewer's coarse preview): of those, only the samples of
    weight >= keep and each ray's largest, each ray's colour rescaled to its full weight. Samples left out
    contribute no colour (their weight still counts in `acc`)."""

    threshold: float = 1e-4
    per_ray: float | None = 16.0
    min_per_ray: float = 0.0
    keep: float | None = None


@dataclass(frozen=True, kw_only=True)
class Marcher:
    """Occupancy-grid marching in a scene space (`radiance.space`): the space's steps of `step_size` through the
    grid's occupied cells. Rays given to it are the space's march rays (`Space.to_march`).

    Calling it is the sampler call (`Sampler`: `render_rays`, `render_depth`, `render_attenuation`), the same call
    `render_marched` takes its samples from. Its samples carry their field points and density scale; the other
    renderers query their callbacks at the scene points along the march rays instead, which are the field's
    points in a `Box` space only (NDC, contracted: map them with `Space.density_query`)."""

    space: Space
    grid: OccupancyGrid
    """Over the space's field box."""
    step_size: float
    """In march units (`Space.step_unit`)."""
    segment: int = 32
    """Early-stopping march: steps taken per slab between transmittance checks."""

    def __call__(
        self,
        rays_o: Tensor,  # [R, 3] march rays
        rays_d: Tensor,  # [R, 3] unit
        near: Tensor | None = None,  # [R]
        far: Tensor | None = None,  # [R]
        jitter: bool | torch.Generator = False,
    ) -> Samples:
        """Packed samples [N] (`Space.march`): steps of step_size through the occupied cells within the space's
        near, far and the grid's box, with their field points and density scale.

        near, far: a check, not a bound: the range is the space's, so a sample outside [near, far] raises
        (narrow the space's near, far instead); None: no check. jitter shifts each ray's steps by U[0, step)
        (True: the global random source; a Generator: that one); a jittered sampler for `render_attenuation` is
        `functools.partial(marcher, jitter=generator)`."""
        u = None
        if jitter is not False:
            gen = jitter if isinstance(jitter, torch.Generator) else None
            u = torch.rand(rays_o.shape[0], generator=gen, dtype=rays_o.dtype, device=rays_o.device)
        p = self.space.march(self.grid, rays_o, rays_d, self.step_size, u)
        if near is not None or far is not None:
            inf = torch.full((rays_o.shape[0],), torch.inf, dtype=rays_o.dtype, device=rays_o.device)
            lo = (near if near is not None else -inf).index_select(0, p.ray_indices)  # [N]
            hi = (far if far is not None else inf).index_select(0, p.ray_indices)
            if bool(((p.t_starts < lo) | (p.t_ends > hi)).any()):
                raise ValueError(
                    f"expected near, far around the {self.space.name} space's march (near "
                    f"{self.space.near}, far {self.space.far} within the grid's box), got samples "
                    "outside them: narrow the space's near, far instead"
                )
        return Samples(p.t_starts, p.t_ends, p.ray_indices, rays_o.shape[0], p.points, p.density_scale)


def render_marched(
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    marcher: Marcher,
    sigma_fn: PositionSigmaFn,  # field x [N, 3] -> sigma [N] per field length
    rgb_fn: RgbFn | RayColour | None,  # (field x [K, 3], ray d [K, 3]) -> rgb [K, 3]; None: density only
    background: Tensor | None = None,  # [3] or [R, 3]
    colour: ColourRule = ColourRule(),
    jitter: bool | torch.Generator = False,
    with_median: bool = False,
    min_transmittance: float | None = None,
) -> dict:
    """Occupancy-grid marching (packed samples) in two passes: density on every sample, colour where it counts
    (`colour`); the field's densities become densities per ray length through the space's scale (contracted: the
    interval's contracted chord per world length), so weights, depths (ray t) and the median are the same maths
    in every space.

    min_transmittance None (training, test-time optimisation): every step at once, differentiable; `jitter`
    shifts each ray's steps by U[0, step) (True: the global random source; a Generator: that one) so training
    sees every depth. Returns acc [R], depth [R] (expected t), rgb [R, 3] (on the background; absent when rgb_fn
    is None), depth_median [R] (only with_median), and per sample (packed [N]) weights, sigmas, t_starts, t_ends,
    ray_indices.

    min_transmittance a float (inference): the same steps (no jitter), taken front to back in slabs of
    `marcher.segment` steps over the rays whose transmittance before the slab is >= min_transmittance (early ray
    termination; the spans the grid knows to be empty are skipped); no grad. The light lost is at most
    min_transmittance per ray (acc, rgb off by <= that; the median is unaffected below 0.5); with 0 the result is
    the differentiable path's. Returns the per-ray outputs and `samples`, the number of occupied samples whose
    density was evaluated; no per-sample outputs.
    """
    _check_rays(rays_o, rays_d)
    if min_transmittance is not None:
        with torch.no_grad():
            steps = marcher.space.steps(marcher.grid, rays_o, rays_d, marcher.step_size)
            return _march_terminating(
                rays_o,
                rays_d,
                steps,
                marcher,
                sigma_fn,
                rgb_fn,
                background=background,
                colour=colour,
                min_transmittance=min_transmittance,
                with_median=with_median,
            )
    if colour.keep is not None:
        raise ValueError("expected ColourRule.keep None when training (it is an inference preview rule)")
    s = marcher(rays_o, rays_d, jitter=jitter)  # the sampler call
    sigma = sigma_fn(s.points)  # [N]
    if s.density_scale is not None:
        sigma = sigma * s.density_scale  # [N] per ray length
    return _shade_packed(
        rays_o,
        rays_d,
        s.ray_indices,
        s.t_starts,
        s.t_ends,
        s.points,
        sigma,
        rgb_fn=rgb_fn,
        background=background,
        colour=colour,
        with_median=with_median,
    )


def _march_terminating(
    rays_o,
    rays_d,
    steps: Steps,
    marcher: Marcher,
    sigma_fn,
    rgb_fn,
    *,
    background,
    colour: ColourRule,
    min_transmittance: float,
    with_median: bool,
) -> dict:
    """Front-to-back marching in slabs of `segment` steps over the rays still alive (transmittance before the
    slab >= min_transmittance, steps left): occupancy, density on occupied steps, then the slab's weights from
    the optical depth carried over; acc, depth and the median accumulate per ray, colour candidates are kept.
    Colour is evaluated once at the end, chosen by `_shade_packed`'s rule (`ColourRule` without its min_per_ray),
    so with min_transmittance = 0 the result is the differentiable path's. colour.keep (the viewer's coarse
    preview): of those, colour only the samples whose weight is >= keep and each ray's largest, and scale each
    ray's colour by acc / (the coloured samples' weight), so that leaving out the faint samples does not darken
    the ray."""
    segment, grid = marcher.segment, marcher.grid
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
        o_a, d_a = rays_o[alive], rays_d[alive]  # [A, 3]
        xyz = steps.point(tuple(o_a[:, i, None] + d_a[:, i, None] * t_mid for i in range(3)))  # 3 x [A, S]
        occ = torch.nonzero((valid & grid.query_xyz(xyz)).view(-1))[:, 0]  # [M] flat indices
        sigma = t0.new_zeros(t0.shape)  # [A, S]
        if occ.numel():
            n_samples += occ.numel()
            s = sigma_fn(_gather_rows(xyz, occ)).to(sigma.dtype)
            if steps.scale is not None:
                rows = alive.index_select(0, occ // segment)
                s = s * steps.scale(rows, t0.view(-1).index_select(0, occ), t1.view(-1).index_select(0, occ))
            sigma.view(-1).index_copy_(0, occ, s)
            tau_s = optical_depth(sigma, t0, t1)  # [A, S]
            cum = torch.cumsum(tau_s, dim=1)
            trans = torch.exp(-(tau[alive, None] + cum - tau_s))  # [A, S] before each step
            w = trans * -torch.expm1(-tau_s)  # [A, S]
            if median is not None:
                wb = acc[alive, None] + torch.cumsum(w, dim=1) - w
                crossed, t_med = median_crossing(sigma, t0, t1, trans, w, wb)  # row by row: rows already done too
                crossed &= torch.isinf(median[alive])
                median[alive[crossed]] = t_med[crossed]
            acc.index_add_(0, alive, w.sum(dim=1))
            depth.index_add_(0, alive, (w * t_mid).sum(dim=1))
            tau.index_add_(0, alive, cum[:, -1])
            if rgb_fn is not None:
                pick = torch.nonzero(w.view(-1) > colour.threshold)[:, 0]
                rows = alive.index_select(0, pick // segment)
                picks.append((rows, _gather_rows(xyz, pick), w.view(-1).index_select(0, pick)))
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
        keep = _colour_samples(w, n, colour.threshold, colour.per_ray, 0.0)  # the twin's rule (the picks pass it)
        if colour.keep is not None:  # fewer: above colour.keep or the ray's largest weight
            largest = torch.zeros(n, **like).scatter_reduce(0, rows, w, "amax")  # [R]
            keep = (keep & (w >= colour.keep)) | (w >= largest[rows])
        rows, x, w = rows[keep], x[keep], w[keep]
        if rows.numel():
            fn, per_sample = _per_sample(rgb_fn, rays_d, rows)
            rgb = accumulate(w, _in_batches(fn, x, per_sample), rows, n)
        else:
            rgb = acc.new_zeros(n, 3)
        if colour.keep is not None:  # the coloured samples stand for all of the ray's weight
            rgb = rgb * safe_div(acc, accumulate(w, None, rows, n))[:, None]
        out["rgb"] = rgb if background is None else rgb + (1 - acc)[:, None] * background.to(rgb)
    return out


def _gather_rows(xyz: tuple[Tensor, Tensor, Tensor], flat: Tensor) -> Tensor:
    """Points `flat` [M] (flat indices) of coordinates held apart (x, y, z of one shape) -> rows [M, 3]."""
    return torch.stack([v.reshape(-1).index_select(0, flat) for v in xyz], dim=-1)


COLOUR_BATCH = 8192
"""Samples per colour call of the early-stopping march. The colour of a chunk's samples (up to 16 a ray, 131k for
8192 rays) in one call builds [3, C, N] feature tensors far beyond the caches; in batches of 8192 the same values
cost 1.3 instead of 2.4-3.4 us a sample (fox, 150 s run, one thread; 4096: 1.3-1.7, 16384: 1.3-2.2). On CUDA
`COLOUR_BATCH_CUDA`: there a call costs a launch per layer, not cache misses."""
COLOUR_BATCH_CUDA = 1 << 20


def _in_batches(fn: RgbFn, x: Tensor, d: Tensor) -> Tensor:
    """fn(x [K, 3], d [K, 3] or codes [K, D]) -> [K, 3], called on COLOUR_BATCH samples at a time. The field
    colours every sample on its own, so the values are one call's (bit for bit with the fields' colour at 8192, a
    multiple of every SIMD width, which keeps each sample in the same vectorised loop; another size may move a sample
    to torch's scalar loop: float32 rounding)."""
    size = COLOUR_BATCH_CUDA if x.device.type == "cuda" else COLOUR_BATCH
    if x.shape[0] <= size:
        return fn(x, d)
    return torch.cat([fn(x[i : i + size], d[i : i + size]) for i in range(0, x.shape[0], size)])


def _shade_packed(
    rays_o, rays_d, ray_idx, t0, t1, x, sigma, *, rgb_fn, background, colour: ColourRule, with_median: bool
) -> dict:
    """Weights from packed densities; colour only where the weight counts (see render_marched)."""
    n = rays_o.shape[0]
    t_mid = 0.5 * (t0 + t1)
    weights, _, _ = render_weights(sigma, t0, t1, ray_idx, n)
    acc = accumulate(weights, None, ray_idx, n)  # [R]
    out = {"acc": acc}
    if rgb_fn is not None:
        keep = _colour_samples(weights.detach(), n, colour.threshold, colour.per_ray, colour.min_per_ray)  # [N]
        fn, per_sample = _per_sample(rgb_fn, rays_d, ray_idx[keep])
        rgb_s = fn(x[keep], per_sample)  # [K, 3]
        rgb = accumulate(weights[keep], rgb_s, ray_idx[keep], n)
        out["rgb"] = rgb if background is None else rgb + (1 - acc)[:, None] * background.to(rgb)
    out["depth"] = safe_div(accumulate(weights, t_mid, ray_idx, n), acc)
    if with_median:
        out["depth_median"] = median_depth(sigma, t0, t1, ray_idx, n)
    return {**out, "weights": weights, "sigmas": sigma, "t_starts": t0, "t_ends": t1, "ray_indices": ray_idx}


def _colour_samples(w: Tensor, n: int, threshold: float, per_ray: float | None, min_per_ray: float) -> Tensor:
    """Which samples get a colour, from their weights w [N] in a batch of n rays -> bool [N]: weight above
    `threshold`, at most the `per_ray * n` largest (None: no budget); and at least the `min_per_ray * n` largest
    when fewer pass (a faint batch: at initialisation every weight is below any threshold)."""
    keep = w > threshold
    budget = w.numel() if per_ray is None else int(per_ray * n)
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
    sampler: Sampler,
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
    sampler: Sampler,
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
