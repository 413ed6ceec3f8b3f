"""Fields: shapes, finite outputs and gradients, density-only mode, the paper's architecture, upsampling."""

from __future__ import annotations

import pytest
import torch

from nerfpipe.radiance.fields import NeRFMLP, TensoRF, VanillaNeRF, make_field
from nerfpipe.radiance.fields.encodings import encoded_size, positional_encoding

AABB = [[-1.0, -1.0, -0.5], [1.0, 1.0, 1.5]]


def _inputs(n: int = 257, scale: float = 1.0):
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(n, 3, generator=g) * 2 - 1) * scale + torch.tensor([0.0, 0.0, 0.5])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return x, d


@pytest.mark.parametrize(
    "field",
    [
        TensoRF(aabb=AABB, resolution=16, density_rank=4, app_rank=6, hidden=16),
        TensoRF(aabb=AABB, resolution=16, density_rank=4, app_rank=6, hidden=16, view_dependent=False),
        NeRFMLP(width=32),
    ],
    ids=["fast", "fast-lambertian", "vanilla"],
)
def test_field_shapes_finite_and_gradients(field):
    x, d = _inputs()
    sigma, rgb = field(x, d if field.view_dependent else None)
    assert sigma.shape == (x.shape[0],) and rgb.shape == (x.shape[0], 3)
    assert torch.isfinite(sigma).all() and (sigma >= 0).all()
    assert ((rgb >= 0) & (rgb <= 1)).all()
    (sigma.sum() + rgb.sum()).backward()
    grads = [p.grad for p in field.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_density_only_field():
    field = TensoRF(aabb=AABB, resolution=8, density_rank=2, has_color=False)
    x, _ = _inputs()
    sigma, rgb = field(x, None)
    assert rgb is None and sigma.shape == (x.shape[0],)
    assert not hasattr(field, "app_planes")
    sigma.sum().backward()
    assert torch.isfinite(field.density_planes.grad).all()
    with pytest.raises(ValueError, match="density-only"):
        field.color(x, None)
    mlp = NeRFMLP(width=16, has_color=False)
    assert mlp(x)[1] is None


def test_density_finite_for_extreme_inputs_and_zero_outside_box():
    field = TensoRF(aabb=AABB, resolution=8, density_rank=2, has_color=False)
    with torch.no_grad():
        field.density_planes.fill_(1e3)
        field.density_lines.fill_(1e3)
    x = torch.tensor([[0.0, 0.0, 0.5], [5.0, 0.0, 0.0], [0.0, 0.0, -1e30]])
    sigma = field.density(x)
    assert torch.isfinite(sigma).all()
    assert sigma[0] > 0 and sigma[1] == 0 and sigma[2] == 0


def test_view_dependent_field_requires_directions():
    field = TensoRF(aabb=AABB, resolution=8, density_rank=2, app_rank=2, hidden=8)
    x, _ = _inputs(5)
    with pytest.raises(ValueError, match="view dependent"):
        field(x, None)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        field(x[:, :2], None)


def test_vanilla_matches_the_paper():
    net = NeRFMLP()
    assert encoded_size(3, 10) == 63 and encoded_size(3, 4) == 27
    assert len(net.layers) == 8 and all(layer.out_features == 256 for layer in net.layers)
    assert net.layers[0].in_features == 63 and net.layers[5].in_features == 256 + 63  # skip after layer 5
    assert net.rgb_hidden.in_features == 256 + 27 and net.rgb_hidden.out_features == 128
    model = VanillaNeRF()
    assert (model.n_coarse, model.n_fine) == (64, 128)
    assert model.coarse is not model.fine


def test_positional_encoding_includes_identity():
    x = torch.tensor([[0.25, -0.5, 1.0]])
    enc = positional_encoding(x, 2)
    assert enc.shape == (1, 15)
    torch.testing.assert_close(enc[:, :3], x)
    torch.testing.assert_close(enc[:, 3:6], torch.sin(x))
    torch.testing.assert_close(enc[:, 9:12], torch.cos(x))
    torch.testing.assert_close(enc[:, 6:9], torch.sin(2 * x))


def test_upsample_keeps_the_function_and_config_round_trips():
    torch.manual_seed(0)
    field = TensoRF(aabb=AABB, resolution=8, density_rank=2, app_rank=3, hidden=8)
    x, d = _inputs(64, scale=0.9)
    before = field(x, d)
    field.upsample(15)  # 8 -> 15 with align_corners: a refinement of the same piecewise-linear lines
    after = field(x, d)
    assert field.density_planes.shape[-1] == 15
    torch.testing.assert_close(after[0], before[0], rtol=0.2, atol=1e-3)
    clone = make_field(field.config())
    clone.load_state_dict(field.state_dict())
    torch.testing.assert_close(clone(x, d)[1], after[1])
    assert make_field(VanillaNeRF(view_dependent=False).config()).view_dependent is False
    with pytest.raises(ValueError, match="unknown field"):
        make_field({"kind": "nope"})


@pytest.mark.parametrize("channels", [8, 4, 6, 5])  # split in 4 groups of 2, 4 of 1; 6, 5: not split
def test_vm_features_match_their_reference_twin(channels):
    """The channel-split grid_sample path gives the plain one's products and gradients (float rounding)."""
    from nerfpipe.radiance.fields.fast import _vm_features, _vm_features_reference

    g = torch.Generator().manual_seed(1)
    planes = torch.randn(3, channels, 12, 12, generator=g)
    lines = torch.randn(3, channels, 12, 1, generator=g)
    xn = torch.cat([torch.rand(200, 3, generator=g) * 2 - 1, torch.tensor([[1.0, -1.0, 1.0], [-1.0, 1.0, 0.0]])])
    outs, grads = [], []
    for fn in (_vm_features, _vm_features_reference):
        p, ln = planes.clone().requires_grad_(), lines.clone().requires_grad_()
        out = fn(p, ln, xn)
        (out * torch.linspace(-1, 2, out.numel()).reshape(out.shape)).sum().backward()
        outs.append(out.detach())
        grads.append((p.grad, ln.grad))
    assert outs[0].shape == (3, channels, xn.shape[0])
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(grads[0][0], grads[1][0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grads[0][1], grads[1][1], rtol=1e-5, atol=1e-5)
    assert _vm_features(planes, lines, xn[:0]).shape == (3, channels, 0)


def test_sampled_tv_is_unbiased_and_its_direct_gradient_matches_autograd():
    """The per-step TV estimate averages to the full TV; the in-place gradient equals autograd of the estimate."""
    from nerfpipe.radiance.fields.fast import _plane_tv, add_plane_tv_grad_, plane_tv_sampled, tv_pairs

    g = torch.Generator().manual_seed(2)
    planes = torch.randn(3, 5, 9, 7, generator=g, dtype=torch.float64).cumsum(2)  # rougher along H than W
    full = float(_plane_tv(planes))
    draws = torch.tensor([float(plane_tv_sampled(planes, tv_pairs(planes.shape, 64, g, planes.device)))
                          for _ in range(2000)], dtype=torch.float64)  # fmt: skip
    assert abs(float(draws.mean()) - full) < 4 * float(draws.std()) / 2000**0.5
    pairs = tv_pairs(planes.shape, 64, g, planes.device)
    assert int(pairs.max()) < 9 * 7 and int(pairs.min()) >= 0
    p = torch.nn.Parameter(planes.clone())
    (0.3 * plane_tv_sampled(p, pairs)).backward()
    expected, p.grad = p.grad.clone(), torch.ones_like(p)  # an existing gradient is added to, not replaced
    value = add_plane_tv_grad_(p, pairs, 0.3)
    torch.testing.assert_close(p.grad - 1, expected)
    assert value == pytest.approx(float(plane_tv_sampled(planes, pairs)))
    with pytest.raises(ValueError, match="texels >= 2"):
        tv_pairs(planes.shape, 1, g, planes.device)


def test_tv_is_zero_for_constant_planes_and_field_adds_its_gradient():
    f = TensoRF(aabb=AABB, resolution=8, density_rank=2, app_rank=2, hidden=8)
    with torch.no_grad():
        for p in f.grid_parameters():
            p.fill_(0.5)
    assert float(f.tv().detach()) == 0.0
    assert f.add_tv_grad_(1.0, 16, torch.Generator().manual_seed(0)) == 0.0
    assert float(f.density_planes.grad.abs().max()) == 0.0 and f.app_planes.grad is not None
    with torch.no_grad():
        f.density_planes.normal_()
    assert float(f.tv().detach()) > 0 and f.add_tv_grad_(1.0, 16) > 0


def test_density_volume_matches_the_factors_and_follows_their_updates():
    """Inference density through the node volume equals `density` (bilinear plane x linear line = trilinear on
    the same nodes), inside, on the faces and outside the box, on a non-cubic box; an optimizer step, a load and an
    upsample each refresh it."""
    torch.manual_seed(0)
    field = TensoRF(aabb=[[-1.0, -0.5, 0.0], [2.0, 0.5, 1.5]], resolution=12, density_rank=3, app_rank=2,
                    app_dim=4, hidden=8, density_shift=0.0, density_scale=1.0)  # fmt: skip
    lo, hi = field.aabb[0], field.aabb[1]
    x = lo + (hi - lo) * (torch.rand(3000, 3) * 1.4 - 0.2)  # 20 % beyond each face
    x[:4] = torch.stack([lo, hi, (lo + hi) / 2, torch.stack([lo[0], hi[1], lo[2]])])  # corners and the centre
    with torch.no_grad():
        torch.testing.assert_close(field.density_inference(x), field.density(x), rtol=1e-5, atol=1e-6)
    assert (field.density_inference(x[(x < lo).any(1) | (x > hi).any(1)]) == 0).all()
    opt = torch.optim.Adam(field.parameters(), lr=0.5)
    field.density(x).sum().backward()
    opt.step()
    with torch.no_grad():
        torch.testing.assert_close(field.density_inference(x), field.density(x), rtol=1e-5, atol=1e-6)
        field.load_state_dict({k: v * 0.5 if "density" in k else v for k, v in field.state_dict().items()})
        torch.testing.assert_close(field.density_inference(x), field.density(x), rtol=1e-5, atol=1e-6)
        field.upsample(17)
        torch.testing.assert_close(field.density_inference(x), field.density(x), rtol=1e-5, atol=1e-6)


def test_density_volume_follows_a_fused_adam_step_through_touch():
    """torch's fused Adam updates the factors without bumping their version counters: the training loop calls
    `touch()` after each step, and the inference volume then follows (before, training's held-out PSNR read a stale
    volume: lego_400 30.73 dB at the end of training against 33.17 from the saved checkpoint)."""
    torch.manual_seed(0)
    field = TensoRF(aabb=[[-1, -1, -1], [1, 1, 1]], resolution=8, has_color=False)
    x = torch.rand(64, 3) * 2 - 1
    field.density_inference(x)  # builds the cache
    opt = torch.optim.Adam(field.parameters(), lr=0.5, fused=True)
    field.density(x).sum().backward()
    opt.step()
    if field.density_planes._version == 0:  # the case touch() is for
        assert not torch.allclose(field.density_inference(x), field.density(x).detach(), rtol=1e-4, atol=1e-6)
    field.touch()
    torch.testing.assert_close(field.density_inference(x), field.density(x).detach(), rtol=1e-4, atol=1e-5)
