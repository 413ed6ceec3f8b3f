"""Occupancy grid on an analytic sphere: marked cells, skip fraction, marching against plain twins."""

import math

import pytest
import torch

from nerfpipe.radiance.occupancy import (
    OccupancyGrid,
    march_bounds,
    march_rays,
    march_rays_reference,
    occupied_span,
    query_reference,
)
from nerfpipe.radiance.render import Marcher, StratifiedSampler, render_rays
from nerfpipe.radiance.space import Box

RADIUS, SIGMA = 0.6, 10.0
AABB = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]


def sphere_density(x):
    return torch.where(x.norm(dim=-1) < RADIUS, SIGMA, 0.0).to(x)


def sphere_rgb_sigma(x, d):
    return torch.sigmoid(x * 3).to(x), sphere_density(x)


@pytest.fixture(scope="module")
def grid():
    g = OccupancyGrid(AABB, resolution=32)
    assert g.update(sphere_density, step=0, points_per_cell=16, generator=torch.Generator().manual_seed(0))
    return g


def rays(n=24, seed=0, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    target = (torch.rand(n, 3, generator=gen) * 1.6 - 0.8).to(dtype)
    o = torch.tensor([0.3, -2.5, 0.4], dtype=dtype).expand(n, 3).clone()
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True)


def test_grid_marks_sphere_cells_and_skip_fraction(grid):
    centres = grid.cell_centers().reshape(32, 32, 32, 3)
    half_diag = math.sqrt(3) / 2 * float(grid.cell_size[0])
    r = centres.norm(dim=-1)
    assert grid.binary[r < RADIUS].all()
    assert not grid.binary[r > RADIUS + half_diag].any()
    frac = lambda rad: (4 / 3 * math.pi * rad**3) / 8  # noqa: E731
    assert 1 - frac(RADIUS + half_diag) <= grid.skip_fraction <= 1 - frac(RADIUS - half_diag)
    assert grid.skip_fraction == pytest.approx(1 - frac(RADIUS), abs=0.05)


def test_query_matches_plain_loop_and_outside_is_empty(grid):
    x = torch.rand(500, 3, generator=torch.Generator().manual_seed(1)) * 2.4 - 1.2
    x[0] = torch.tensor([1.0, 1.0, 1.0])  # max corner belongs to the last cell
    assert torch.equal(grid.query(x), query_reference(grid, x))
    assert not grid.query(torch.tensor([[1.1, 0.0, 0.0], [0.0, 0.0, 0.0]])).tolist()[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_query_xyz_equals_query(grid, dtype):
    """`query_xyz` (coordinates held apart, any shape) gives `query`'s cells: inside, outside, on the faces."""
    x = (torch.rand(40, 25, 3, generator=torch.Generator().manual_seed(2)) * 2.4 - 1.2).to(dtype)
    x[0, :4] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, 0.0, -1.0], [1e30, 0.0, -1e30]])
    got = grid.query_xyz(tuple(x[..., i] for i in range(3)))
    assert got.shape == (40, 25) and torch.equal(got, grid.query(x.reshape(-1, 3)).reshape(40, 25))


def test_fresh_grid_is_all_occupied_and_update_schedule():
    g = OccupancyGrid(AABB, resolution=8)
    assert g.skip_fraction == 0.0
    assert not g.update(sphere_density, step=3, every=16)
    assert g.update(sphere_density, step=0, every=16)
    assert g.skip_fraction > 0.5
    before = g.density.clone()
    assert g.update(lambda x: torch.zeros(x.shape[0]), step=512, every=16, warmup_steps=256)
    assert (g.density <= before).all() and (g.density < before).any()  # decays where refreshed


def test_state_dict_round_trip(grid):
    other = OccupancyGrid(AABB, resolution=32)
    other.load_state_dict(grid.state_dict())
    assert torch.equal(other.binary, grid.binary) and torch.equal(other.density, grid.density)
    assert set(grid.state_dict()) == {"aabb", "density", "binary"}


def test_march_matches_plain_loop_and_stays_in_occupied_cells(grid):
    o, d = rays(12, dtype=torch.float64)
    fast = march_rays(grid, o, d, near=0.1, far=6.0, step_size=0.04)
    ref = march_rays_reference(grid, o, d, near=0.1, far=6.0, step_size=0.04)
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b)
    ray_indices, t0, t1 = fast
    assert ray_indices.numel() > 0 and (ray_indices[1:] >= ray_indices[:-1]).all()
    mid = o[ray_indices] + d[ray_indices] * ((t0 + t1) / 2)[:, None]
    assert grid.query(mid).all()
    assert ((t1 - t0) <= 0.04 + 1e-12).all() and (t1 > t0).all()


def box_marcher(g, step_size):
    """The box space's marcher over `g` (rays from 0 to 10)."""
    return Marcher(space=Box(aabb=((-1.0,) * 3, (1.0,) * 3), near=0.0, far=10.0), grid=g, step_size=step_size)


def test_marched_render_matches_dense_render_and_closed_form(grid):
    o, d = rays(64, seed=2, dtype=torch.float64)
    kw = dict(near=0.0, far=10.0, rgb_sigma_fn=sphere_rgb_sigma, background=torch.tensor([1.0, 0.0, 0.0]))
    marched = render_rays(o, d, sampler=box_marcher(grid, 0.01), **kw)
    n_dense = 400  # 0.01 over the longest chord of the box (about 3.5)
    dense = render_rays(o, d, sampler=StratifiedSampler(n_samples=n_dense), **{**kw, "near": 1.0, "far": 5.0})
    unmarched = render_rays(o, d, sampler=box_marcher(OccupancyGrid(AABB, resolution=32), 0.01), **kw)  # all occupied
    assert marched["t_starts"].numel() < 0.5 * unmarched["t_starts"].numel()
    for k in ("rgb", "acc"):
        torch.testing.assert_close(marched[k], dense[k], atol=SIGMA * 0.01, rtol=0)  # one step's optical depth
    # Closed form: acc = 1 - exp(-sigma * chord) through the sphere.
    b2 = (o.norm(dim=-1) ** 2 - (o * d).sum(-1) ** 2).clamp(min=0)
    chord = 2 * (RADIUS**2 - b2).clamp(min=0).sqrt()
    torch.testing.assert_close(marched["acc"], 1 - torch.exp(-SIGMA * chord), atol=2 * SIGMA * 0.01, rtol=0)


def test_march_misses_and_empty_grid():
    g = OccupancyGrid(AABB, resolution=4)
    g.update(lambda x: torch.zeros(x.shape[0]), step=0)
    o, d = rays(5)
    ri, t0, t1 = march_rays(g, o, d, step_size=0.1)
    assert ri.numel() == t0.numel() == t1.numel() == 0
    out = render_rays(
        o, d, near=0.0, far=5.0, sampler=box_marcher(g, 0.1), rgb_sigma_fn=sphere_rgb_sigma, background=torch.ones(3)
    )
    torch.testing.assert_close(out["rgb"], torch.ones(5, 3))
    assert (out["acc"] == 0).all()


def test_nan_and_inf_densities_count_as_occupied_not_empty():
    """A diverging field's NaN must never open a hole that rays skip; inf is simply very dense."""

    def broken(x):
        sigma = sphere_density(x)
        sigma[x[:, 0] > 0.5] = torch.nan  # a slab of NaN outside the sphere
        sigma[x[:, 0] < -0.8] = torch.inf
        return sigma

    g = OccupancyGrid(AABB, resolution=16)
    g.update(broken, step=0, points_per_cell=4, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(g.density).all()
    centres = g.cell_centers().reshape(16, 16, 16, 3)
    assert g.binary[centres[..., 0] > 0.6].all() and g.binary[centres[..., 0] < -0.9].all()
    assert not g.binary[(centres.norm(dim=-1) > 0.8) & (centres[..., 0].abs() < 0.4)].any()


def test_empty_cells_follow_the_opacity_of_one_training_step(tmp_path):
    """The density method's grid: a cell is empty when sigma x step < EMPTY_OPACITY, whatever the scene's scale."""
    from nerfpipe.data.transforms import read_scene
    from nerfpipe.model.field_model import EMPTY_OPACITY
    from nerfpipe.model.methods.density import DensityOptions, density_model
    from nerfpipe.model.spaces import make_space
    from nerfpipe.radiance.space import Box
    from nerfpipe.stages import scene as scene_stage

    scene_stage.run(scene_stage.Config(out_dir=tmp_path / "s", kind="posed", size=16, views=4, seed=0))
    options = DensityOptions(
        resolution=(16, 32),
        rank=(16, 48),
        step_ratio=2.0,
        occupancy_resolution=8,
        view_dependent=True,
        density_activation="softplus",
        mlp_width=64,
        render_step_factor=0.5,
    )
    model = density_model(options, make_space(Box, read_scene(tmp_path / "s")), torch.device("cpu"), None)
    step = model.step_size
    for opacity, occupied in ((0.5 * EMPTY_OPACITY, False), (2 * EMPTY_OPACITY, True)):
        model.grid.density.fill_(1e3)  # mean density high: the threshold is the opacity rule's
        model.grid.density[0, 0, 0] = opacity / step
        model.grid.update(lambda x: model.grid.density.new_zeros(x.shape[0]), step=1, every=1)  # decay only
        assert bool(model.grid.binary[0, 0, 0]) == occupied


@pytest.mark.parametrize("factors", [(1,), (3,), (8,), (4, 1)])
def test_occupied_span_holds_every_occupied_point(factors):
    """Every point along a ray that `query` calls occupied (dense sampling, 1/50 of a cell) lies in the span;
    rays that miss all occupied cells get an empty span; sparse grids give spans much shorter than the box."""
    gen = torch.Generator().manual_seed(sum(factors))
    g = OccupancyGrid([-1.0, -0.5, -2.0, 1.0, 1.5, 0.0], resolution=24)
    g.binary.copy_(torch.rand(24, 24, 24, generator=gen) < 0.0005)  # a few scattered cells
    g.binary[10:13, 14:17, 6:9] = True  # and a compact object
    n = 400
    o = torch.randn(n, 3, generator=gen) * 3
    target = g.aabb[0] + torch.rand(n, 3, generator=gen) * (g.aabb[1] - g.aabb[0])
    d = torch.nn.functional.normalize(target - o, dim=1)
    t0, t1 = march_bounds(g, o, d, 0.0, 100.0)  # clipped to the box, as the renderer does
    first, last = occupied_span(g, o, d, t0, t1, factors)
    t = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0, 1, 20000)  # [n, 20000]
    occ = g.query((o[:, None] + d[:, None] * t[..., None]).reshape(-1, 3)).reshape(n, -1)
    inf = torch.tensor(math.inf)
    lo, hi = torch.where(occ, t, inf).amin(1), torch.where(occ, t, -inf).amax(1)
    hit = occ.any(1)
    assert hit.sum() > 10 and (~hit).sum() > 10
    assert bool((first[hit] <= lo[hit]).all()) and bool((last[hit] >= hi[hit]).all())
    assert bool((first >= t0).all()) and bool((last <= t1).all())
    span = (last - first).clamp(min=0)
    if min(factors) <= 3:  # coarse cells small against the box: misses skip most of it (factor 8: 3 x 3 x 3 cells)
        assert float(span[~hit].mean()) < 0.5 * float((t1 - t0)[~hit].mean())
    with pytest.raises(ValueError, match="expected rays"):
        occupied_span(g, o, d, t0[:3], t1, factors)
    g.binary.copy_(torch.zeros_like(g.binary))  # the cached coarse grids follow the grid's updates
    first, last = occupied_span(g, o, d, t0, t1, factors)
    assert bool((first > last).all())


@pytest.mark.parametrize("infer", [True, False], ids=["early-stopping", "differentiable"])
def test_inference_colours_every_sample_of_a_long_faint_ray(infer):
    """A field model rendering (not training) colours every sample whose weight passes the threshold, however many
    a ray has: a constant colour c in a faint fog crossed in ~600 steps gives rgb = acc c + (1 - acc) bg exactly.
    The training budget of 16 coloured samples a ray darkened such rays (the fern at a fine render step)."""
    from nerfpipe.model.field_model import Inference, MarchedModel
    from nerfpipe.radiance.space import Box

    colour = torch.tensor([0.9, 0.6, 0.3])

    class Fog:
        has_color, view_dependent = True, False

        def density_inference(self, x):
            return torch.full((x.shape[0],), 0.5)

        density = density_inference

        def color(self, x, d):
            return colour.expand(x.shape[0], 3)

        def color_from_codes(self, x, codes):  # inference's colour (TensoRF's); view-independent: no codes
            return self.color(x, None)

    grid = OccupancyGrid([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 8)
    grid.binary.fill_(True)
    space = Box(aabb=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), near=0.1, far=10.0)
    model = MarchedModel(field=Fog(), space=space, grid=grid, step_size=0.003, render_step_factor=1.0)
    o = torch.tensor([[0.0, 0.0, 3.0], [0.3, -0.2, 3.0], [0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = model.render(o, d, bg, train=False, infer=Inference() if infer else None)
    assert (out["acc"] > 0.5).all() and (out["acc"] < 0.99).all()  # faint: every step's weight is about 1e-3
    want = out["acc"][:, None] * colour + (1 - out["acc"][:, None]) * bg
    torch.testing.assert_close(out["rgb"], want, atol=1e-5, rtol=0)
