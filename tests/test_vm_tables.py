"""The appearance factors as channels-last tables (`radiance.fields.vm_tables`) against their plain twin
(`radiance.fields.fast._plane_features`, grid_sample), and the field's inference colour built on them."""

from __future__ import annotations

import pytest
import torch

from nerfpipe.radiance.fields import TensoRF
from nerfpipe.radiance.fields.fast import LINE_AXIS, PLANE_AXES, _plane_features
from nerfpipe.radiance.fields.vm_tables import VmTables


def _factors(channels, size, dtype, g):
    planes = [torch.randn(1, c, size, size, generator=g, dtype=dtype) for c in channels]
    lines = [torch.randn(1, c, size, 1, generator=g, dtype=dtype) for c in channels]
    return planes, lines


def _points(n, dtype, g):
    """Inside, on every face and corner, and at the texel centres' exact positions."""
    xn = torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1
    edges = torch.tensor([[1.0, -1.0, 1.0], [-1.0, 1.0, 0.0], [1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [0.0, 0.0, 0.0]])
    return torch.cat([xn, edges.to(dtype)])


@pytest.mark.parametrize(("channels", "size"), [((6, 6, 6), 9), ((4, 4, 4), 2)])
def test_tables_give_grid_samples_values_and_gradients(channels, size):
    """Values [N, 3 C] equal the twin's in float64, and so do the gradients for the factors and the points, also at
    the smallest grid (2 texels)."""
    g = torch.Generator().manual_seed(4)
    planes, lines = _factors(channels, size, torch.float64, g)
    xn = _points(300, torch.float64, g)
    results = []
    for fast in (True, False):
        ps = [p.clone().requires_grad_() for p in planes]
        ls = [ln.clone().requires_grad_() for ln in lines]
        x = xn.clone().requires_grad_()
        if fast:
            out = VmTables.build(ps, ls).features(x)
            assert out.shape == (xn.shape[0], 3 * channels[0])
        else:
            out = torch.cat(_plane_features(ps, ls, x)).T
        (out * torch.linspace(-1, 2, out.numel(), dtype=out.dtype).reshape(out.shape)).sum().backward()
        results.append((out.detach(), [t.grad for t in ps + ls], x.grad))
    (a, grads_a, x_a), (b, grads_b, x_b) = results
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for ga, gb in zip(grads_a, grads_b, strict=True):
        torch.testing.assert_close(ga, gb, rtol=1e-10, atol=1e-10)
    inner = (xn.abs() < 1).all(dim=1)  # on a face the twins take one-sided derivatives of their own
    torch.testing.assert_close(x_a[inner], x_b[inner], rtol=1e-8, atol=1e-8)


def test_tables_refuse_factors_they_cannot_hold():
    """A component count per plane, planes of two sizes, a line of another length: refused (the field's colour
    takes grid_sample's path there)."""
    g = torch.Generator().manual_seed(0)
    planes, lines = _factors((2, 2, 2), 5, torch.float32, g)
    assert VmTables.fits(planes, lines)
    for bad_planes, bad_lines in (
        (planes[:2], lines[:2]),
        ([planes[0], planes[1], torch.zeros(1, 2, 4, 4)], lines),
        ([planes[0], planes[1], torch.zeros(1, 3, 5, 5)], [lines[0], lines[1], torch.zeros(1, 3, 5, 1)]),
        (planes, [lines[0], lines[1], torch.zeros(1, 2, 6, 1)]),
    ):
        assert not VmTables.fits(bad_planes, bad_lines)
        with pytest.raises(ValueError, match="of one C and one R"):
            VmTables.build(bad_planes, bad_lines)
    assert PLANE_AXES == ((0, 1), (0, 2), (1, 2)) and LINE_AXIS == (2, 1, 0)  # the layout the tables assume


@pytest.mark.parametrize("app_rank", [6, (6, 2, 3)])
def test_inference_colour_equals_colour_and_follows_the_factors(app_rank):
    """`color_inference` gives `color`'s values (float32 rounding) inside, on the faces and beyond the box; an
    optimizer step, a load, an upsample and (for fused steps that keep the version counters) `touch` refresh its
    tables."""
    torch.manual_seed(0)
    field = TensoRF(aabb=[[-1.0, -0.5, 0.0], [2.0, 0.5, 1.5]], resolution=10, app_rank=app_rank, app_dim=5, hidden=8)
    lo, hi = field.aabb[0], field.aabb[1]
    x = lo + (hi - lo) * (torch.rand(2000, 3) * 1.4 - 0.2)
    x[:2] = torch.stack([lo, hi])
    d = torch.nn.functional.normalize(torch.randn(2000, 3), dim=-1)

    def agree():
        with torch.no_grad():
            torch.testing.assert_close(field.color_inference(x, d), field.color(x, d), rtol=1e-5, atol=1e-6)

    agree()
    opt = torch.optim.Adam(field.parameters(), lr=0.5)
    field.color(x, d).sum().backward()
    opt.step()
    agree()
    field.load_state_dict({k: v * 0.5 if "app" in k or "basis" in k else v for k, v in field.state_dict().items()})
    agree()
    field.upsample(13)
    agree()
    with torch.no_grad():
        for p in field.app_planes:
            p.data.mul_(-1.0)  # behind the version counter, as a fused step
    field.touch()
    agree()


def test_inference_colour_is_refused_without_colour_or_directions():
    field = TensoRF(aabb=[[-1, -1, -1], [1, 1, 1]], resolution=4, has_color=False)
    with pytest.raises(ValueError, match="density-only"):
        field.color_inference(torch.zeros(2, 3), None)
    field = TensoRF(aabb=[[-1, -1, -1], [1, 1, 1]], resolution=4, app_dim=3, hidden=4)
    with pytest.raises(ValueError, match="pass directions"):
        field.color_inference(torch.zeros(2, 3), None)
    with pytest.raises(ValueError, match="expected direction codes for a view-dependent field"):
        field.color_from_codes(torch.zeros(2, 3), None)
    flat = TensoRF(aabb=[[-1, -1, -1], [1, 1, 1]], resolution=4, app_dim=3, hidden=4, view_dependent=False)
    assert flat.color_from_codes(torch.zeros(2, 3), None).shape == (2, 3)
    with pytest.raises(ValueError, match="None otherwise"):
        flat.color_from_codes(torch.zeros(2, 3), torch.zeros(2, 4))
