"""The early-stopping march's fast paths (issue 28) against the plain ways of computing the same values: colour in
batches against one call, and the march in every space against its differentiable twin."""

from __future__ import annotations

import pytest
import torch

import nerfpipe.radiance.render as render
from nerfpipe.radiance.contraction import CONTRACTED_BOX, Contraction
from nerfpipe.radiance.occupancy import OccupancyGrid
from nerfpipe.radiance.render import Marcher, render_marched
from nerfpipe.radiance.space import Box, Contracted

C = Contraction([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _sigma_contracted(y):
    """A fuzzy ball in the box and a far shell, in contracted coordinates."""
    r = C.uncontract(y).norm(dim=-1)
    return (4.0 * (r < 0.7) + 300.0 * ((r > 20) & (r < 60))).to(y.dtype)


def _sigma_box(x):
    return (4.0 * (x.norm(dim=-1) < 0.7)).to(x.dtype)


def _rays(n: int, dtype):
    g = torch.Generator().manual_seed(4)
    o = torch.tensor([0.1, -3.0, 0.2], dtype=dtype).repeat(n, 1)
    d = torch.randn(n, 3, generator=g, dtype=dtype) * 0.4 + torch.tensor([0.0, 1.0, 0.0], dtype=dtype)
    return o, torch.nn.functional.normalize(d, dim=-1)


def _scene(kind: str):
    if kind == "contract":
        grid = OccupancyGrid(CONTRACTED_BOX, 32)
        grid.update(_sigma_contracted, 0, every=1)
        return Marcher(space=Contracted(contraction=C, near=0.05), grid=grid, step_size=0.02), _sigma_contracted
    grid = OccupancyGrid([[-1.5] * 3, [1.5] * 3], 32)
    grid.update(_sigma_box, 0, every=1)
    return Marcher(space=Box(aabb=((-1.5,) * 3, (1.5,) * 3), near=0.0, far=10.0), grid=grid, step_size=0.02), _sigma_box


@pytest.mark.parametrize("kind", ["contract", "box"])
def test_colour_in_batches_equals_one_call(kind, monkeypatch):
    """The early-stopping march colours its samples COLOUR_BATCH at a time: the same outputs as colouring them in
    one call (to float32 rounding: a batch that is no multiple of the SIMD width moves samples between torch's
    vectorised and scalar loops; at 8192 the trained runs' renders come out bit for bit the same)."""
    marcher, sigma = _scene(kind)
    calls = []

    def rgb(x, d):
        calls.append(x.shape[0])
        return torch.sigmoid(3 * x + d)

    o, d = _rays(96, torch.float32)
    kw = dict(marcher=marcher, sigma_fn=sigma, rgb_fn=rgb, with_median=True, min_transmittance=1e-4)
    monkeypatch.setattr(render, "COLOUR_BATCH", 1 << 30)
    whole = render_marched(o, d, **kw)
    assert len(calls) == 1 and calls[0] > 200
    monkeypatch.setattr(render, "COLOUR_BATCH", 37)
    calls.clear()
    batched = render_marched(o, d, **kw)
    assert len(calls) > 5 and max(calls) == 37
    for key in ("rgb", "acc", "depth", "depth_median"):
        torch.testing.assert_close(batched[key], whole[key], atol=1e-6, rtol=0, msg=key)


@pytest.mark.parametrize("kind", ["contract", "box"])
def test_terminating_march_equals_its_twin_in_float64(kind):
    """With nothing terminated (min_transmittance 0) the slab march (coordinates held apart, index_select gathers,
    the median on every row) gives its differentiable twin's outputs to float64 rounding, with as many densities."""
    marcher, sigma = _scene(kind)
    o, d = _rays(64, torch.float64)
    kw = dict(marcher=marcher, sigma_fn=sigma, rgb_fn=lambda x, d: torch.sigmoid(3 * x + d), with_median=True)
    plain = render_marched(o, d, **kw)
    exact = render_marched(o, d, min_transmittance=0.0, **kw)
    assert exact["samples"] == plain["ray_indices"].numel() > 0
    for key in ("rgb", "acc", "depth", "depth_median"):
        torch.testing.assert_close(exact[key], plain[key], atol=1e-9, rtol=0, equal_nan=True)


@pytest.mark.parametrize("kind", ["contract", "box"])
def test_inference_is_the_same_in_any_chunk_size(kind):
    """On CUDA inference chunks are CUDA_CHUNK_FACTOR times the CPU's (`model.device.rays_per_chunk`): that is safe
    only because inference colours every sample above the threshold (no per-batch budget), so a ray's outputs do not
    depend on the rays rendered with it."""
    from nerfpipe.model.device import CUDA_CHUNK_FACTOR, rays_per_chunk
    from nerfpipe.model.field_model import COLOR_THRESHOLD, INFER_COLOR_PER_RAY

    assert rays_per_chunk(8192, torch.device("cpu")) == 8192
    assert rays_per_chunk(8192, torch.device("cuda")) == 8192 * CUDA_CHUNK_FACTOR
    marcher, sigma = _scene(kind)
    colour = render.ColourRule(threshold=COLOR_THRESHOLD, per_ray=INFER_COLOR_PER_RAY)
    kw = dict(marcher=marcher, sigma_fn=sigma, rgb_fn=lambda x, d: torch.sigmoid(3 * x + d), with_median=True)
    kw |= dict(min_transmittance=1e-4, colour=colour)
    o, d = _rays(96, torch.float32)
    whole = render_marched(o, d, **kw)
    parts = [render_marched(o[i : i + 7], d[i : i + 7], **kw) for i in range(0, 96, 7)]
    for key in ("rgb", "acc", "depth", "depth_median"):
        torch.testing.assert_close(torch.cat([p[key] for p in parts]), whole[key], atol=1e-6, rtol=0, msg=key)
