"""The occupancy marcher as the X-ray renderer's sampler (issue 28): line integrals through a sphere of constant mu
against its analytic chord, with far fewer samples than the stratified sampler at the same step."""

from __future__ import annotations

import functools
import math

import pytest
import torch

from nerfpipe.model.xray import field_line_integrals, xray_marcher
from nerfpipe.radiance.aabb import ray_aabb_segment
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.render import StratifiedSampler, render_attenuation

RADIUS, MU, STEP = 0.6, 3.0, 0.01
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)


def sphere_mu(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x.norm(dim=-1) < RADIUS, MU, 0.0).to(x)


class Sphere:
    """A field: density(x [N, 3]) -> mu [N]."""

    def density(self, x):
        return sphere_mu(x)


def sphere_grid(resolution: int = 32) -> OccupancyGrid:
    """Cells that meet the sphere marked occupied (centre within RADIUS + half a cell diagonal), the rest empty."""
    grid = OccupancyGrid(BOX, resolution)
    centres = grid.cell_centers()  # [G^3, 3]
    half_diag = 0.5 * float(grid.cell_size.norm())
    grid.binary.copy_((centres.norm(dim=-1) < RADIUS + half_diag).reshape(grid.binary.shape))
    return grid


def rays(n: int = 64, seed: int = 0):
    """Rays from random points on a sphere of radius 3 towards random points within 0.8 of the centre (some miss
    the sphere of mu, all cross the box)."""
    gen = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1) * 3.0
    target = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 0.8
    return o, torch.nn.functional.normalize(target - o, dim=-1)


def chord(o, d):
    """Length of each ray's chord through the sphere of radius RADIUS at the origin [R]."""
    b2 = (o.norm(dim=-1) ** 2 - (o * d).sum(-1) ** 2).clamp(min=0)
    return 2 * (RADIUS**2 - b2).clamp(min=0).sqrt()


def box_chord(o, d):
    """Each ray's [near, far] [R] through the box."""
    return ray_aabb_segment(o, d, BOX, 0.0, math.inf)


def test_marcher_line_integrals_match_the_chord_and_skip_empty_cells():
    """Same line integrals as the stratified sampler at the same step (within MU x step of the analytic MU x
    chord: one step's midpoint either side of the sphere), from samples in the occupied cells only."""
    o, d = rays()
    near, far = box_chord(o, d)
    marcher = xray_marcher(sphere_grid(), STEP)
    marched = render_attenuation(o, d, near=near, far=far, sampler=marcher, sigma_fn=lambda x, d_: sphere_mu(x))
    n_dense = math.ceil(float((far - near).max()) / STEP)
    dense = render_attenuation(
        o, d, near=near, far=far, sampler=StratifiedSampler(n_samples=n_dense), sigma_fn=lambda x, d_: sphere_mu(x)
    )
    want = MU * chord(o, d)
    assert (want == 0).any() and (want > 1.0).any()
    tol = MU * STEP * (1 + 1e-9)
    torch.testing.assert_close(marched["optical_depth"], want, atol=tol, rtol=0)
    torch.testing.assert_close(dense["optical_depth"], want, atol=MU * float((far - near).max()) / n_dense, rtol=0)
    # samples: about the sphere's chords (the cells meeting it), not the box's
    n_marched = marched["ray_indices"].numel()
    in_box = float(((far - near) / STEP).ceil().sum())
    assert float((chord(o, d) / STEP - 1).clamp(min=0).sum()) <= n_marched < 0.6 * in_box
    assert torch.equal(marched["ray_indices"], torch.sort(marched["ray_indices"]).values)


def test_field_line_integrals_take_a_jittered_marcher():
    """field_line_integrals with the marcher as its sampler (jittered from a generator: reproducible, and still
    within a step of the chord), and its argument checks."""
    o, d = rays(48, seed=1)
    grid = sphere_grid()

    def jittered(seed: int):
        return functools.partial(xray_marcher(grid, STEP), jitter=torch.Generator().manual_seed(seed))

    p = field_line_integrals(Sphere(), o, d, BOX, sampler=jittered(2))
    assert torch.equal(p, field_line_integrals(Sphere(), o, d, BOX, sampler=jittered(2)))
    torch.testing.assert_close(p, MU * chord(o, d), atol=MU * STEP * (1 + 1e-9), rtol=0)
    plain = field_line_integrals(Sphere(), o, d, BOX, sampler=xray_marcher(grid, STEP))
    assert not torch.equal(p, plain)  # the jitter moved the steps
    with pytest.raises(ValueError, match="n_samples and sampler"):
        field_line_integrals(Sphere(), o, d, BOX, 32, sampler=jittered(2))
    with pytest.raises(ValueError, match="n_samples and sampler"):
        field_line_integrals(Sphere(), o, d, BOX)
    with pytest.raises(ValueError, match="jitter"):
        field_line_integrals(Sphere(), o, d, BOX, sampler=jittered(2), jitter=True)


def test_marched_line_integrals_are_differentiable_and_inside_the_chord():
    """A trainable mu: the gradient of the marched line integrals reaches it; every sample is inside the box's
    chord (the marcher's range check passes)."""
    o, d = rays(16, seed=3)
    near, far = box_chord(o, d)
    scale = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    out = render_attenuation(
        o, d, near=near, far=far, sampler=xray_marcher(sphere_grid(), STEP), sigma_fn=lambda x, d_: sphere_mu(x) * scale
    )
    out["optical_depth"].sum().backward()
    torch.testing.assert_close(scale.grad, out["optical_depth"].sum().detach(), rtol=1e-12, atol=0)
    assert (out["t_starts"] >= near[out["ray_indices"]]).all() and (out["t_ends"] <= far[out["ray_indices"]]).all()
