"""render_rays and friends on analytic fields: closed forms, hierarchical sampling, occupancy marching,
chunking, X-ray."""

import functools
import math

import pytest
import torch

from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.render import (
    PER_RAY_KEYS,
    ColourRule,
    Marcher,
    RayColour,
    StratifiedSampler,
    chunked,
    render_attenuation,
    render_depth,
    render_marched,
    render_rays,
    render_rays_hierarchical,
)
from nerfpipe.radiance.space import Box

RADIUS, MU = 0.7, 2.0


def sphere_sigma(x, d):
    return torch.where(x.norm(dim=-1) < RADIUS, MU, 0.0).to(x)


def sphere_rgb_sigma(x, d):
    return torch.tensor([0.2, 0.6, 1.0], dtype=x.dtype).expand(x.shape[0], 3), sphere_sigma(x, d)


def rays(n=32, seed=0):
    """Rays from distance 2.5 towards random points in the sphere's bounding square (some miss)."""
    gen = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, 2.5], dtype=torch.float64).expand(n, 3).clone()
    target = torch.cat(
        [torch.rand(n, 2, generator=gen, dtype=torch.float64) * 1.8 - 0.9, torch.zeros(n, 1, dtype=torch.float64)],
        dim=-1,
    )
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True)


def chord(o, d):
    b2 = (o.norm(dim=-1) ** 2 - (o * d).sum(-1) ** 2).clamp(min=0)
    return 2 * (RADIUS**2 - b2).clamp(min=0).sqrt()


def test_beer_lambert_matches_analytic_line_integral_through_sphere():
    o, d = rays()
    n, near, far = 800, 1.5, 3.5
    out = render_attenuation(
        o, d, near=near, far=far, sampler=StratifiedSampler(n_samples=n), sigma_fn=sphere_sigma, i0=100.0
    )
    expected = MU * chord(o, d)
    step = (far - near) / n
    torch.testing.assert_close(out["optical_depth"], expected, atol=2 * MU * step, rtol=0)
    torch.testing.assert_close(out["intensity"], 100.0 * torch.exp(-out["optical_depth"]))
    assert (chord(o, d) == 0).any() and (chord(o, d) > 0).any()


def test_emission_absorption_matches_closed_form_with_background():
    o, d = rays(seed=1)
    bg = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    out = render_rays(
        o, d, near=1.5, far=3.5, sampler=StratifiedSampler(n_samples=800), rgb_sigma_fn=sphere_rgb_sigma, background=bg
    )
    acc = 1 - torch.exp(-MU * chord(o, d))
    torch.testing.assert_close(out["acc"], acc, atol=0.01, rtol=0)
    colour = torch.tensor([0.2, 0.6, 1.0], dtype=torch.float64)
    torch.testing.assert_close(out["rgb"], out["acc"][:, None] * colour + (1 - out["acc"])[:, None] * bg)
    assert out["weights"].shape == (32, 800) and out["ray_indices"] is None
    # Median depth through a homogeneous sphere: entry + ln 2 / mu where the chord absorbs more than half.
    entry = (-(o * d).sum(-1)) - chord(o, d) / 2
    deep = MU * chord(o, d) > math.log(2) + 0.1
    torch.testing.assert_close(out["depth_median"][deep], entry[deep] + math.log(2) / MU, atol=0.01, rtol=0)
    assert torch.isinf(out["depth_median"][chord(o, d) == 0]).all()


def test_density_only_render_shares_the_core():
    o, d = rays(seed=2)
    kw = dict(near=1.5, far=3.5, sampler=StratifiedSampler(n_samples=64))
    a = render_depth(o, d, sigma_fn=sphere_sigma, **kw)
    b = render_rays(o, d, rgb_sigma_fn=sphere_rgb_sigma, **kw)
    for k in ("depth", "depth_median", "acc", "weights"):
        torch.testing.assert_close(a[k], b[k], equal_nan=True)


def test_hierarchical_sampling_concentrates_near_the_surface():
    o, d = rays(8, seed=3)
    gen = torch.Generator().manual_seed(0)
    out = render_rays_hierarchical(
        o,
        d,
        near=1.5,
        far=3.5,
        coarse_sampler=StratifiedSampler(n_samples=16, jitter=True, generator=gen),
        n_fine=32,
        coarse_fn=sphere_rgb_sigma,
        fine_fn=sphere_rgb_sigma,
    )
    assert out["t_starts"].shape == (8, 48) and out["coarse"]["t_starts"].shape == (8, 16)
    torch.testing.assert_close(out["t_starts"][:, 1:], out["t_ends"][:, :-1])
    acc = 1 - torch.exp(-MU * chord(o, d))
    err_fine = (out["acc"] - acc).abs().max()
    err_coarse = (out["coarse"]["acc"] - acc).abs().max()
    assert err_fine <= err_coarse + 1e-12


def test_gradients_flow_to_the_field():
    o, d = rays(4, seed=4)
    scale = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    fn = lambda x, d: (torch.sigmoid(x) * scale, sphere_sigma(x, d) * scale)  # noqa: E731
    out = render_rays(o, d, near=1.5, far=3.5, sampler=StratifiedSampler(n_samples=32), rgb_sigma_fn=fn)
    out["rgb"].sum().backward()
    assert torch.isfinite(scale.grad) and scale.grad != 0


def test_infinite_far_plane_renders_finite():
    o, d = rays(8, seed=5)
    out = render_rays(
        o,
        d,
        near=0.5,
        far=math.inf,
        sampler=StratifiedSampler(n_samples=64, spacing="disparity"),
        rgb_sigma_fn=sphere_rgb_sigma,
        background=torch.ones(3),
    )
    for k in ("rgb", "depth", "acc"):
        assert torch.isfinite(out[k]).all()
    assert torch.isinf(out["t_ends"][:, -1]).all()


def test_chunked_equals_one_batch_and_has_no_grad():
    o, d = rays(50, seed=6)
    render = lambda o_, d_: render_rays(  # noqa: E731
        o_, d_, near=1.5, far=3.5, sampler=StratifiedSampler(n_samples=32), rgb_sigma_fn=sphere_rgb_sigma
    )
    whole = render(o, d)
    parts = chunked(render, o, d, chunk=7)
    assert set(parts) == set(PER_RAY_KEYS)
    for k in PER_RAY_KEYS:
        torch.testing.assert_close(parts[k], whole[k], equal_nan=True)
        assert not parts[k].requires_grad
    with pytest.raises(ValueError, match="chunk"):
        chunked(render, o, d, chunk=0)


def test_render_validates_inputs():
    o, d = rays(4)
    with pytest.raises(ValueError, match="rays_o"):
        render_rays(
            o[:, :2], d, near=1.0, far=2.0, sampler=StratifiedSampler(n_samples=4), rgb_sigma_fn=sphere_rgb_sigma
        )
    with pytest.raises(ValueError, match="near"):
        render_rays(
            o, d, near=torch.ones(3), far=2.0, sampler=StratifiedSampler(n_samples=4), rgb_sigma_fn=sphere_rgb_sigma
        )
    with pytest.raises(ValueError, match="background"):
        render_rays(
            o,
            d,
            near=1.0,
            far=2.0,
            sampler=StratifiedSampler(n_samples=4),
            rgb_sigma_fn=sphere_rgb_sigma,
            background=torch.ones(2),
        )


# Occupancy-marched rendering of a Gaussian blob: compact enough that the grid's occupied box is much smaller
# than its aabb, so marching clips rays, skips cells and drops faint colour samples.
BLOB_SIGMA, BLOB_WIDTH = 8.0, 0.15


def blob_sigma(x):
    return BLOB_SIGMA * torch.exp(-(x**2).sum(-1) / (2 * BLOB_WIDTH**2))


def blob_rgb(x, d):
    return torch.sigmoid(4 * x + d)


def blob_rays(n, seed):
    """Rays from distance 2.5 towards random points within 0.5 of the blob's centre (some miss)."""
    o, d = rays(n, seed)
    target = o + d * (2.5 / -d[:, 2:])  # on the plane z = 0, within 0.9 of the axis
    d = target * (0.5 / 0.9) - o
    return o, d / d.norm(dim=-1, keepdim=True)


def box_marcher(grid, near=0.5, far=5.0, step_size=0.004, segment=32):
    """The box space's marcher over `grid` with rays from near to far."""
    box = Box(aabb=tuple(tuple(r) for r in grid.aabb.tolist()), near=near, far=far)
    return Marcher(space=box, grid=grid, step_size=step_size, segment=segment)


def blob_grid():
    grid = OccupancyGrid([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 32)
    grid.update(blob_sigma, 0, every=1)
    assert grid.skip_fraction > 0.5
    return grid


def test_marched_render_matches_dense_stratified_reference():
    o, d = blob_rays(32, seed=7)
    grid = blob_grid()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    scale = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    out = render_marched(
        o,
        d,
        marcher=box_marcher(grid),
        sigma_fn=lambda x: blob_sigma(x) * scale,
        rgb_fn=lambda x, d_: blob_rgb(x, d_) * scale,
        background=bg,
        colour=ColourRule(threshold=0.0, per_ray=1e6),
        with_median=True,
    )
    ref = render_rays(
        o,
        d,
        near=1.5,
        far=3.5,
        sampler=StratifiedSampler(n_samples=2000),
        background=bg,
        rgb_sigma_fn=lambda x, d_: (blob_rgb(x, d_), blob_sigma(x)),
    )
    assert out["ray_indices"].numel() < 32 * 500  # marched: far fewer samples than a dense sweep of the box
    assert (ref["acc"] < 1e-3).any() and (ref["acc"] > 0.5).any()
    torch.testing.assert_close(out["acc"], ref["acc"], atol=5e-3, rtol=0)
    torch.testing.assert_close(out["rgb"], ref["rgb"], atol=5e-3, rtol=0)
    hit = ref["acc"] > 0.05
    torch.testing.assert_close(out["depth"][hit], ref["depth"][hit], atol=0.01, rtol=0)
    deep = ref["acc"] > 0.6
    torch.testing.assert_close(out["depth_median"][deep], ref["depth_median"][deep], atol=0.01, rtol=0)
    (out["rgb"].sum() + out["depth"].sum()).backward()
    for k in ("rgb", "depth", "acc"):
        assert torch.isfinite(out[k]).all()
    assert torch.isfinite(scale.grad) and scale.grad != 0


def test_marched_density_only_budget_jitter_and_empty_grid():
    o, d = blob_rays(32, seed=8)
    grid = blob_grid()
    seen = []

    def rgb_fn(x, d_):
        seen.append(x.shape[0])
        return blob_rgb(x, d_)

    kw = dict(marcher=box_marcher(grid), sigma_fn=blob_sigma, with_median=True)
    gen = torch.Generator().manual_seed(1)
    colour = render_marched(o, d, rgb_fn=rgb_fn, colour=ColourRule(per_ray=2.0), jitter=gen, **kw)
    assert seen[0] <= 2 * 32 < colour["ray_indices"].numel()  # colour only at the batch's 64 largest weights
    dens = render_marched(o, d, rgb_fn=None, jitter=torch.Generator().manual_seed(1), **kw)
    assert "rgb" not in dens
    for k in ("acc", "depth", "depth_median", "weights", "t_starts"):
        torch.testing.assert_close(dens[k], colour[k], equal_nan=True)
    other = render_marched(o, d, rgb_fn=None, jitter=torch.Generator().manual_seed(2), **kw)
    assert not torch.equal(other["t_starts"][:10], dens["t_starts"][:10])  # jitter follows the generator
    grid.binary.zero_()
    empty = render_marched(o, d, rgb_fn=blob_rgb, background=torch.ones(3), **kw)
    assert empty["ray_indices"].numel() == 0 and (empty["acc"] == 0).all()
    torch.testing.assert_close(empty["rgb"], torch.ones(32, 3, dtype=torch.float64))


def test_marcher_is_the_sampler_render_marched_uses():
    """The marcher's sampler call gives render_marched's samples (the same jitter draw), so render_depth through it
    gives render_marched's density-only outputs; near, far that do not hold the space's march raise."""
    o, d = blob_rays(32, seed=10)
    marcher = box_marcher(blob_grid())
    marched = render_marched(
        o, d, marcher=marcher, sigma_fn=blob_sigma, rgb_fn=None, jitter=torch.Generator().manual_seed(3)
    )
    sampler = functools.partial(marcher, jitter=torch.Generator().manual_seed(3))
    via = render_depth(o, d, near=0.5, far=5.0, sampler=sampler, sigma_fn=lambda x, d_: blob_sigma(x))
    assert marched["ray_indices"].numel() > 0
    for k in ("ray_indices", "t_starts", "t_ends"):
        assert torch.equal(via[k], marched[k])
    for k in ("acc", "depth", "weights", "sigmas"):
        torch.testing.assert_close(via[k], marched[k], atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="near, far"):
        render_depth(o, d, near=2.5, far=5.0, sampler=marcher, sigma_fn=lambda x, d_: blob_sigma(x))


def test_terminating_march_matches_its_plain_twin():
    """Early ray termination against render_marched on the same steps: equal without termination (any slab
    size), within min_transmittance with it, and fewer densities evaluated; the median is unaffected."""
    o, d = blob_rays(48, seed=9)
    grid = blob_grid()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    counted = []

    def sigma(x):
        counted.append(x.shape[0])
        return blob_sigma(x) * 20  # opaque enough that rays stop inside the blob

    kw = dict(rgb_fn=blob_rgb, background=bg, with_median=True)
    plain = render_marched(o, d, marcher=box_marcher(grid), sigma_fn=sigma, **kw)
    n_plain = counted.pop()
    for segment in (1, 7, 32):
        marcher = box_marcher(grid, segment=segment)
        exact = render_marched(o, d, marcher=marcher, sigma_fn=sigma, min_transmittance=0.0, **kw)
        assert exact["samples"] == n_plain == sum(counted)
        counted.clear()
        for key in ("rgb", "acc", "depth", "depth_median"):
            torch.testing.assert_close(exact[key], plain[key], atol=1e-9, rtol=0, equal_nan=True)
    fast = render_marched(o, d, marcher=box_marcher(grid), sigma_fn=sigma, min_transmittance=1e-3, **kw)
    assert (plain["acc"] > 0.999).any() and fast["samples"] < 0.85 * n_plain
    assert float((fast["acc"] - plain["acc"]).abs().max()) <= 1e-3
    assert float((fast["rgb"] - plain["rgb"]).abs().max()) <= 2e-3
    torch.testing.assert_close(fast["depth_median"], plain["depth_median"], atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="min_transmittance"):
        render_marched(o, d, marcher=box_marcher(grid), sigma_fn=sigma, min_transmittance=1.0, **kw)


def test_ray_colour_in_two_parts_gives_the_plain_callbacks_colour():
    """A `RayColour` (a per-ray code, then per-sample colour from it) renders what the plain (x, d) callback
    renders, in the terminating march and the differentiable one, each sample given its own ray's code."""
    o, d = blob_rays(40, seed=2)
    grid = blob_grid()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    per_ray_calls = []

    def per_ray(rays_d):
        per_ray_calls.append(rays_d.shape[0])
        return torch.cat([rays_d, rays_d.sum(-1, keepdim=True)], dim=-1)  # [R, 4]: any code that carries d

    two_parts = RayColour(per_ray=per_ray, colour=lambda x, code: blob_rgb(x, code[:, :3]))
    kw = dict(marcher=box_marcher(grid), sigma_fn=lambda x: 20 * blob_sigma(x), background=bg)
    for extra in (dict(min_transmittance=1e-3), {}):
        want = render_marched(o, d, rgb_fn=blob_rgb, **kw, **extra)
        got = render_marched(o, d, rgb_fn=two_parts, **kw, **extra)
        torch.testing.assert_close(got["rgb"], want["rgb"], atol=1e-12, rtol=0)
        assert per_ray_calls.pop() == o.shape[0]


def test_coarse_colour_rule_keeps_the_full_weight():
    """ColourRule.keep (the viewer's coarse preview): a constant-colour field keeps its colour exactly (the coloured
    samples stand for the ray's whole weight; faint rays keep their largest sample) with far fewer colour
    queries, where the same threshold as a plain colour threshold darkens the rays."""
    o, d = blob_rays(48, seed=4)
    grid = blob_grid()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    colour = torch.tensor([0.9, 0.5, 0.2], dtype=torch.float64)
    queried = []

    def rgb(x, d):
        queried.append(x.shape[0])
        return colour.expand(x.shape[0], 3)

    kw = dict(
        marcher=box_marcher(grid),
        sigma_fn=lambda x: 20 * blob_sigma(x),
        rgb_fn=rgb,
        background=bg,
        min_transmittance=0.0,
    )
    exact = render_marched(o, d, **kw)
    coarse = render_marched(o, d, colour=ColourRule(keep=0.02), **kw)
    dark = render_marched(o, d, colour=ColourRule(threshold=0.02), **kw)
    want = exact["acc"][:, None] * colour + (1 - exact["acc"][:, None]) * bg
    hit = exact["acc"] > 1e-3
    assert (exact["acc"][hit] < 0.5).any()  # faint rays too
    torch.testing.assert_close(coarse["rgb"][hit], want[hit], atol=1e-9, rtol=0)
    assert float((want - dark["rgb"]).abs().max()) > 0.05
    assert queried[1] < 0.5 * queried[0]


def test_colour_samples_threshold_budget_and_floor():
    """Which samples get a colour: above the threshold, at most per_ray x R of the largest, and at least
    min_per_ray x R of the largest when fewer pass (a faint batch at initialisation still gets a gradient)."""
    from nerfpipe.radiance.render import _colour_samples

    w = torch.tensor([0.5, 2e-4, 5e-5, 1e-5, 3e-6, 0.0])
    assert _colour_samples(w, 2, 1e-4, 16.0, 0.0).tolist() == [True, True, False, False, False, False]
    assert _colour_samples(w, 2, 1e-4, 0.5, 0.0).tolist() == [True, False, False, False, False, False]  # budget 1
    faint = w * 1e-4  # every weight below the threshold
    assert not _colour_samples(faint, 2, 1e-4, 16.0, 0.0).any()  # no floor: no colour, no gradient
    assert _colour_samples(faint, 2, 1e-4, 16.0, 1.0).tolist() == [True, True, False, False, False, False]
    assert _colour_samples(w, 2, 1e-4, 16.0, 1.0).sum() == 2  # enough pass: the floor adds nothing
    assert _colour_samples(w[:1], 4, 1e-4, 16.0, 1.0).tolist() == [True]  # floor capped at the samples there are
