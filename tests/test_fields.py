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
        TensoRF(aabb=AABB, resolution=16, density_rank=4, app_rank=6, hidden=16, density_activation="relu"),
        NeRFMLP(width=32),
    ],
    ids=["fast", "fast-lambertian", "fast-relu", "vanilla"],
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
    assert all(torch.isfinite(p.grad).all() for p in field.density_planes)
    with pytest.raises(ValueError, match="density-only"):
        field.color(x, None)
    mlp = NeRFMLP(width=16, has_color=False)
    assert mlp(x)[1] is None


def test_density_finite_for_extreme_inputs_and_zero_outside_box():
    field = TensoRF(aabb=AABB, resolution=8, density_rank=2, has_color=False)
    with torch.no_grad():
        for p in field.grid_parameters():
            p.fill_(1e3)
    x = torch.tensor([[0.0, 0.0, 0.5], [5.0, 0.0, 0.0], [0.0, 0.0, -1e30]])
    sigma = field.density(x)
    assert torch.isfinite(sigma).all()
    assert sigma[0] > 0 and sigma[1] == 0 and sigma[2] == 0


def test_relu_density_is_the_scaled_factor_sum_clipped_at_zero_with_its_gradient():
    """density_activation="relu" (NDC scenes): sigma = density_scale * relu(f), shift 0 unless given; exactly 0 where
    f < 0 with no gradient there, the factors' own gradient times the scale where f > 0; finite for huge factors;
    the inference volume agrees; the config keeps the activation, and a config from before it means softplus."""
    from nerfpipe.radiance.fields.fast import _plane_features

    torch.manual_seed(0)
    field = TensoRF(aabb=AABB, resolution=8, density_rank=(3, 2, 1), has_color=False, density_activation="relu")
    assert field.density_shift == 0.0 and field.config()["density_activation"] == "relu"
    x, _ = _inputs(500, scale=0.9)
    sigma = field.density(x)
    f = sum(p.sum(0) for p in _plane_features(field.density_planes, field.density_lines, field.normalize(x)))
    torch.testing.assert_close(sigma, field.density_scale * f.clamp(min=0))
    assert (f < 0).any() and (f > 0).any() and (sigma[f < 0] == 0).all()
    on = f > 0
    (g_sigma,) = torch.autograd.grad(sigma.sum(), field.density_planes[0])
    (g_f,) = torch.autograd.grad(field.density_scale * f[on].sum(), field.density_planes[0])
    torch.testing.assert_close(g_sigma, g_f)
    with torch.no_grad():
        torch.testing.assert_close(field.density_inference(x), field.density(x), rtol=1e-5, atol=1e-5)
        for p in field.grid_parameters():
            p.fill_(1e3)
        assert torch.isfinite(field.density(x)).all()
        for p in field.density_planes:
            p.fill_(-1.0)
        assert (field.density(x) == 0).all()
    old = {
        k: v for k, v in TensoRF(aabb=AABB, resolution=8, has_color=False).config().items() if k != "density_activation"
    }
    assert make_field(old).density_activation == "softplus" and make_field(old).density_shift == -10.0
    assert make_field(field.config()).density_activation == "relu"
    with pytest.raises(ValueError, match="density_activation"):
        TensoRF(aabb=AABB, resolution=8, density_activation="exp")


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
    assert [tuple(p.shape[2:]) for p in field.density_planes] == [(15, 15)] * 3
    torch.testing.assert_close(after[0], before[0], rtol=0.2, atol=1e-3)
    clone = make_field(field.config())
    clone.load_state_dict(field.state_dict())
    torch.testing.assert_close(clone(x, d)[1], after[1])
    assert make_field(VanillaNeRF(view_dependent=False).config()).view_dependent is False
    with pytest.raises(ValueError, match="unknown field"):
        make_field({"kind": "nope"})


@pytest.mark.parametrize(("channels", "sizes"), [((8, 4, 6), (12, 12, 12)), ((5, 8, 4), (12, 10, 3))])
def test_plane_features_match_their_reference_twin(channels, sizes):
    """The channel-split grid_sample path gives the plain one's products and gradients (float rounding), with each
    plane's own component count (split in groups of 2, of 1, or not split) and sizes (x, y, z texels)."""
    from nerfpipe.radiance.fields.fast import LINE_AXIS, PLANE_AXES, _plane_features, _plane_features_reference

    g = torch.Generator().manual_seed(1)
    axes = zip(channels, PLANE_AXES, strict=True)
    planes = [torch.randn(1, c, sizes[v], sizes[u], generator=g) for c, (u, v) in axes]
    lines = [torch.randn(1, c, sizes[a], 1, generator=g) for c, a in zip(channels, LINE_AXIS, strict=True)]
    xn = torch.cat([torch.rand(200, 3, generator=g) * 2 - 1, torch.tensor([[1.0, -1.0, 1.0], [-1.0, 1.0, 0.0]])])
    outs, grads = [], []
    for fn in (_plane_features, _plane_features_reference):
        ps = [p.clone().requires_grad_() for p in planes]
        ls = [ln.clone().requires_grad_() for ln in lines]
        out = torch.cat(fn(ps, ls, xn))
        (out * torch.linspace(-1, 2, out.numel()).reshape(out.shape)).sum().backward()
        outs.append(out.detach())
        grads.append([t.grad for t in ps + ls])
    assert outs[0].shape == (sum(channels), xn.shape[0])
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-6, atol=1e-6)
    for a, b in zip(grads[0], grads[1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert [f.shape for f in _plane_features(planes, lines, xn[:0])] == [(c, 0) for c in channels]


def test_planes_take_their_own_components():
    """density_rank / app_rank per plane (xy, xz, yz) give each factor its component count, kept through an
    upsampling and round-tripped through config(); train's 2 or 6 counts split into them; a bad count is refused."""
    from nerfpipe.radiance.fields.fast import split_rank

    field = TensoRF(aabb=AABB, resolution=16, density_rank=(4, 2, 2), app_rank=(6, 3, 3), hidden=8)
    assert [tuple(p.shape) for p in field.density_planes] == [(1, 4, 16, 16), (1, 2, 16, 16), (1, 2, 16, 16)]
    assert [tuple(p.shape) for p in field.app_lines] == [(1, 6, 16, 1), (1, 3, 16, 1), (1, 3, 16, 1)]
    assert field.basis.in_features == 12
    x, d = _inputs(64, scale=0.9)
    field.upsample(40)
    assert [tuple(p.shape[1:]) for p in field.app_planes] == [(6, 40, 40), (3, 40, 40), (3, 40, 40)]
    clone = make_field(field.config())
    clone.load_state_dict(field.state_dict())
    torch.testing.assert_close(clone(x, d)[1], field(x, d)[1])
    assert field.config()["density_rank"] == [4, 2, 2]
    assert TensoRF(aabb=AABB, resolution=8, density_rank=3).config()["density_rank"] == 3
    with pytest.raises(ValueError, match="density_rank as one count or three"):
        TensoRF(aabb=AABB, density_rank=(4, 0, 2))
    assert split_rank((2, 3)) == (2, 3) and split_rank((16, 4, 4, 48, 12, 12)) == ((16, 4, 4), (48, 12, 12))
    for bad in ((2, 3, 4), (2, 0), (1, 1, 1, 1, 1, 0)):
        with pytest.raises(ValueError, match="expected rank as 2 counts"):
            split_rank(bad)


def test_a_checkpoint_with_stacked_factors_still_loads():
    """Fields saved before per-plane factors hold each group as one [3, C, R, R] tensor (lines [3, C, R, 1]): they
    load into today's field unchanged, plane by plane."""
    field = TensoRF(aabb=AABB, resolution=8, density_rank=2, app_rank=3, hidden=8)
    state = {k: v for k, v in field.state_dict().items() if not k.split(".")[0].endswith(("_planes", "_lines"))}
    g = torch.Generator().manual_seed(3)
    for name, c in (("density", 2), ("app", 3)):
        state[f"{name}_planes"] = torch.randn(3, c, 8, 8, generator=g)
        state[f"{name}_lines"] = torch.randn(3, c, 8, 1, generator=g)
    field.load_state_dict(state)
    for m in range(3):
        torch.testing.assert_close(field.app_planes[m].data, state["app_planes"][m : m + 1])
        torch.testing.assert_close(field.density_lines[m].data, state["density_lines"][m : m + 1])


def test_sampled_tv_is_unbiased_and_its_direct_gradient_matches_autograd():
    """The per-step TV estimate averages to the full TV; the in-place gradient equals autograd of the estimate."""
    from nerfpipe.radiance.fields.fast import _plane_tv, add_plane_tv_grad_, plane_tv_sampled, tv_pairs

    g = torch.Generator().manual_seed(2)
    planes = torch.randn(3, 5, 9, 7, generator=g, dtype=torch.float64).cumsum(2)  # rougher along H than W
    full = float(_plane_tv(planes))
    draws = torch.tensor(
        [float(plane_tv_sampled(planes, tv_pairs(planes.shape, 64, g, planes.device))) for _ in range(2000)],
        dtype=torch.float64,
    )
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
    assert all(float(p.grad.abs().max()) == 0.0 for p in f.density_planes)
    assert all(p.grad is not None for p in f.app_planes)
    with torch.no_grad():
        f.density_planes[1].normal_()
    assert float(f.tv().detach()) > 0 and f.add_tv_grad_(1.0, 16) > 0


def test_density_volume_matches_the_factors_and_follows_their_updates():
    """Inference density through the node volume equals `density` (bilinear plane x linear line = trilinear on
    the same nodes), inside, on the faces and outside the box, on a non-cubic box, with a component count per
    plane; an optimizer step, a load and an
    upsample each refresh it."""
    torch.manual_seed(0)
    field = TensoRF(
        aabb=[[-1.0, -0.5, 0.0], [2.0, 0.5, 1.5]],
        resolution=12,
        density_rank=(3, 2, 1),
        app_rank=2,
        app_dim=4,
        hidden=8,
        density_shift=0.0,
        density_scale=1.0,
    )
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
    if field.density_planes[0]._version == 0:  # the case touch() is for
        assert not torch.allclose(field.density_inference(x), field.density(x).detach(), rtol=1e-4, atol=1e-6)
    field.touch()
    torch.testing.assert_close(field.density_inference(x), field.density(x).detach(), rtol=1e-4, atol=1e-5)
