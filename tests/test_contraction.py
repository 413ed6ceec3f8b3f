"""Scene contraction (radiance.contraction): the map, warped marching against its loop twin, and rendering in
contracted space against the box renderer where all density lies inside the box."""

from __future__ import annotations

import pytest
import torch

from nerfpipe.radiance.contraction import (
    CONTRACTED_BOX,
    ChordScale,
    Contraction,
    chord_scale_xyz,
    contraction_chord_scale,
    march_contracted,
    march_contracted_reference,
)
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.render import Marcher, render_marched
from nerfpipe.radiance.space import Box, Contracted

BOX = [[-1.0, -0.5, -2.0], [1.0, 1.5, 0.0]]


def test_contract_is_identity_inside_and_inverts_outside():
    c = Contraction(BOX)
    g = torch.Generator().manual_seed(0)
    inside = c.center + (torch.rand(500, 3, generator=g, dtype=torch.float64) * 2 - 1) * c.half.double()
    y = c.contract(inside)
    assert torch.allclose(y, (inside - c.center.double()) / c.half.double(), atol=1e-12)
    far = (
        torch.randn(500, 3, generator=g, dtype=torch.float64) * torch.logspace(0, 6, 500, dtype=torch.float64)[:, None]
    )
    y = c.contract(far)
    assert float(y.abs().max()) < 2.0 and bool(torch.isfinite(y).all())
    keep = y.abs().amax(-1) < 1.999  # beyond that float64 cannot tell the distance back
    assert torch.allclose(c.uncontract(y[keep]), far[keep], rtol=1e-6, atol=1e-9)


def test_contract_extremes_stay_finite_with_gradients():
    c = Contraction(BOX)
    x = torch.tensor([[1e12, 0.0, 0.0], [0.0, -1e30, 5.0], [0.0, 0.5, -1.0], [1.0, 1.5, 0.0]], requires_grad=True)
    y = c.contract(x)
    y.sum().backward()
    assert bool(torch.isfinite(y).all()) and bool(torch.isfinite(x.grad).all())
    assert bool(torch.isfinite(c.density_scale(x.detach())).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_contract_xyz_and_chord_scale_xyz_equal_their_row_twins(dtype):
    """The fast paths on coordinates held apart give `contract`'s and `contraction_chord_scale`'s values bit for
    bit: inside the box, in the shell, far away, on the box's faces, at extremes and at NaN."""
    c = Contraction(BOX)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(4000, 3, generator=g, dtype=dtype) * torch.logspace(-1, 6, 4000, dtype=dtype)[:, None]
    x[:8] = torch.tensor(
        [
            [1.0, 1.5, 0.0],
            [-1.0, -0.5, -2.0],
            [0.0, 0.5, -1.0],
            [1e30, 0.0, 0.0],
            [0.0, -1e30, 5.0],
            [float("inf"), 0.0, 0.0],
            [float("nan"), 0.0, 0.0],
            [1.0, 0.2, -0.3],
        ],
        dtype=dtype,
    )
    got = torch.stack(c.contract_xyz(tuple(x.T.contiguous())), dim=-1)
    torch.testing.assert_close(got, c.contract(x), rtol=0, atol=0, equal_nan=True)
    o = torch.randn(50, 3, generator=g, dtype=dtype) * 3
    d = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=dtype), dim=-1)
    rows = torch.randint(50, (3000,), generator=g)
    t0 = torch.rand(3000, generator=g, dtype=dtype) * 20
    t1 = t0 + torch.rand(3000, generator=g, dtype=dtype) * torch.logspace(-3, 3, 3000, dtype=dtype)
    t1[:5] = t0[:5]  # zero-length intervals
    fast = chord_scale_xyz(c, tuple(o.T.contiguous()), tuple(d.T.contiguous()), rows, t0, t1)
    assert torch.equal(fast, contraction_chord_scale(c, o[rows], d[rows], t0, t1))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chord_scale_of_rays_equals_the_interval_formula(dtype):
    """`ChordScale` (the per-ray scale for intervals inside the inner box, contracted chords elsewhere) gives
    `chord_scale_xyz`'s values: rays from inside and outside the box, rays that miss it, intervals inside, straddling
    the entry or the exit, beyond it, and of zero length."""
    c = Contraction(BOX)
    g = torch.Generator().manual_seed(5)
    o = torch.tensor([0.0, 0.5, -1.0], dtype=dtype) + torch.randn(60, 3, generator=g, dtype=dtype) * 1.5
    o[:10] = torch.tensor([0.0, 0.5, -1.0], dtype=dtype)  # origins inside the box
    d = torch.nn.functional.normalize(torch.randn(60, 3, generator=g, dtype=dtype), dim=-1)
    rows = torch.randint(60, (5000,), generator=g)
    t0 = torch.rand(5000, generator=g, dtype=dtype) * 4
    t1 = t0 + torch.rand(5000, generator=g, dtype=dtype) * torch.logspace(-4, 0.5, 5000, dtype=dtype)
    t1[:5] = t0[:5]
    scale = ChordScale(c, o, d)
    want = chord_scale_xyz(c, tuple(o.T.contiguous()), tuple(d.T.contiguous()), rows, t0, t1)
    got = scale(rows, t0, t1)
    inside = (t0 >= scale.t_in[rows]) & (t1 <= scale.t_out[rows])
    assert 200 < int(inside.sum()) < 4800  # both cases taken
    torch.testing.assert_close(got[~inside], want[~inside], rtol=0, atol=0)  # the same computation
    # inside, against the chord in float64 (in float32 the chord of a short interval loses digits: b - a cancels)
    o64, d64 = tuple(o.double().T.contiguous()), tuple(d.double().T.contiguous())
    exact = chord_scale_xyz(c, o64, d64, rows, t0.double(), t1.double())
    keep = inside & (t1 > t0)
    torch.testing.assert_close(got[keep].double(), exact[keep], rtol=1e-6 if dtype == torch.float32 else 1e-9, atol=0)


def test_bad_inner_box_is_refused():
    with pytest.raises(ValueError, match="max > min"):
        Contraction([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0]])


def _rays(n: int, dtype=torch.float32):
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([0.0, -3.0, 0.1], dtype=dtype).repeat(n, 1)
    d = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor([0.0, 1.0, 0.0], dtype=dtype)
    return o, torch.nn.functional.normalize(d, dim=-1)


def test_march_contracted_matches_its_loop_twin():
    c = Contraction([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = OccupancyGrid(CONTRACTED_BOX, 16)
    grid.binary[:, :, :8] = False  # carve a slab of empty cells so culling is exercised
    o, d = _rays(6, torch.float64)
    fast = march_contracted(grid, c, o, d, near=0.1, step_size=0.05)
    ref = march_contracted_reference(grid, c, o, d, near=0.1, step_size=0.05)
    assert torch.equal(fast[0], ref[0])
    assert torch.allclose(fast[1], ref[1], rtol=1e-9) and torch.allclose(fast[2], ref[2], rtol=1e-9)
    assert bool((fast[2] > fast[1]).all()) and float(fast[2].max()) > 50  # reaches far beyond the box


def test_contracted_rendering_matches_the_box_where_density_is_inside():
    c = Contraction([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def sigma_world(p):  # an opaque-ish ball of radius 0.5 at the origin
        return (p.norm(dim=-1) < 0.5).to(p.dtype) * 20.0

    o, d = _rays(64)
    box_space = Box(aabb=tuple(tuple(r) for r in c.inner_aabb.tolist()), near=0.1, far=1e10)
    box = render_marched(
        o,
        d,
        marcher=Marcher(space=box_space, grid=OccupancyGrid(c.inner_aabb, 16), step_size=0.005),
        sigma_fn=sigma_world,
        rgb_fn=None,
    )
    # in contracted space the field's density is per contracted length: sigma' = sigma * h (h = 1 here)
    marcher = Marcher(
        space=Contracted(contraction=c, near=0.1), grid=OccupancyGrid(CONTRACTED_BOX, 16), step_size=0.005
    )
    con = render_marched(o, d, marcher=marcher, sigma_fn=lambda y: sigma_world(c.uncontract(y)), rgb_fn=None)
    assert float(box["acc"].max()) > 0.99 and float(box["acc"].min()) < 0.01  # hits and misses both present
    assert torch.allclose(box["acc"], con["acc"], atol=2e-3)
    hit = box["acc"] > 0.5
    assert torch.allclose(box["depth"][hit], con["depth"][hit], atol=0.02)


def test_far_background_is_rendered_at_world_distance():
    """A shell of density far outside the box (r in [20, 60] round the centre) stops every ray of a camera 3 units
    from the centre (outside the box, as captures are) at about that distance, whichever way it looks."""
    c = Contraction([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def sigma_contracted(y):
        x = c.uncontract(y)
        r = x.norm(dim=-1)
        return ((r > 20) & (r < 60)).to(y.dtype) * 500.0  # per contracted length: the shell is ~0.03 thick

    o = torch.tensor([[0.0, -3.0, 0.1]]).repeat(32, 1)
    d = torch.nn.functional.normalize(torch.randn(32, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    marcher = Marcher(
        space=Contracted(contraction=c, near=0.05), grid=OccupancyGrid(CONTRACTED_BOX, 32), step_size=0.02
    )
    out = render_marched(o, d, marcher=marcher, sigma_fn=sigma_contracted, rgb_fn=None)
    assert float(out["acc"].min()) > 0.99
    hit_r = (o + d * out["depth"][:, None]).norm(dim=-1)  # where the rays stop, as a radius
    assert float(hit_r.min()) > 19 and float(hit_r.max()) < 40  # the front part of the shell


def test_contracted_terminating_matches_its_plain_twin():
    """render_marched with early termination against its plain twin in a contracted space: equal without
    termination, within min_transmittance with it, with fewer densities evaluated, on an opaque ball in front of a
    far shell."""
    c = Contraction([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    counted = []

    def sigma_contracted(y):
        counted.append(y.shape[0])
        x = c.uncontract(y)
        r = x.norm(dim=-1)
        return ((r < 0.5) * 40.0 + ((r > 20) & (r < 60)) * 500.0).to(y.dtype)

    def rgb(y, d):
        return torch.sigmoid(3 * y + d)

    grid = OccupancyGrid(CONTRACTED_BOX, 32)
    grid.update(sigma_contracted, 0, every=1)
    o, d = _rays(64, torch.float64)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    marcher = Marcher(space=Contracted(contraction=c, near=0.05), grid=grid, step_size=0.01, segment=9)
    kw = dict(marcher=marcher, sigma_fn=sigma_contracted, rgb_fn=rgb, background=bg, with_median=True)
    plain = render_marched(o, d, **kw)
    n_plain = counted.pop()
    exact = render_marched(o, d, min_transmittance=0.0, **kw)
    assert exact["samples"] == n_plain
    for key in ("rgb", "acc", "depth", "depth_median"):
        torch.testing.assert_close(exact[key], plain[key], atol=1e-9, rtol=0, equal_nan=True)
    counted.clear()
    fast = render_marched(o, d, min_transmittance=1e-3, **kw)
    assert (plain["acc"] > 0.999).sum() > 16 and sum(counted) < 0.7 * n_plain
    assert float((fast["acc"] - plain["acc"]).abs().max()) <= 1e-3
    assert float((fast["rgb"] - plain["rgb"]).abs().max()) <= 2e-3
    torch.testing.assert_close(fast["depth_median"], plain["depth_median"], atol=1e-9, rtol=0)
