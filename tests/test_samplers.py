"""Samplers (stratified, inverse-CDF, hierarchical) and ray-box intersection, against plain twins."""

import math

import pytest
import torch

from nerfpipe.radiance.aabb import ray_aabb_intersect, ray_aabb_intersect_reference
from nerfpipe.radiance.samplers import (
    append_infinite_interval,
    invert_cdf,
    invert_cdf_reference,
    resample_intervals,
    sample_pdf,
    stratified_intervals,
)


def near_far(n=5, near=0.5, far=4.0, dtype=torch.float64):
    return torch.full((n,), near, dtype=dtype), torch.full((n,), far, dtype=dtype)


@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("spacing", ["linear", "disparity"])
def test_stratified_covers_near_far_contiguously(jitter, spacing):
    near, far = near_far()
    g = torch.Generator().manual_seed(0)
    t0, t1 = stratified_intervals(near, far, 8, jitter=jitter, generator=g, spacing=spacing)
    assert t0.shape == t1.shape == (5, 8)
    torch.testing.assert_close(t0[:, 0], near)
    torch.testing.assert_close(t1[:, -1], far)
    torch.testing.assert_close(t0[:, 1:], t1[:, :-1])
    assert (t1 > t0).all()
    if spacing == "linear" and not jitter:
        torch.testing.assert_close(t1 - t0, torch.full_like(t0, 3.5 / 8))
    if jitter:  # reproducible, and different across rays
        g2 = torch.Generator().manual_seed(0)
        t0b, _ = stratified_intervals(near, far, 8, jitter=True, generator=g2, spacing=spacing)
        torch.testing.assert_close(t0, t0b)
        assert not torch.allclose(t0[0], t0[1])


def test_stratified_jitter_stays_between_bin_centres():
    near, far = near_far(n=2000, near=0.0, far=1.0)
    t0, _ = stratified_intervals(near, far, 4, jitter=True, generator=torch.Generator().manual_seed(1))
    inner = t0[:, 1:]  # edges 1..3 lie in [(k - 0.5) / 4, (k + 0.5) / 4]
    k = torch.arange(1, 4, dtype=torch.float64)
    assert ((inner >= (k - 0.5) / 4) & (inner <= (k + 0.5) / 4)).all()
    torch.testing.assert_close(inner.mean(0), k / 4, atol=0.01, rtol=0)


def test_infinite_far_plane():
    near, far = near_far(far=math.inf)
    t0, t1 = stratified_intervals(near, far, 6, spacing="disparity")
    assert torch.isinf(t1[:, -1]).all() and torch.isfinite(t1[:, :-1]).all() and torch.isfinite(t0).all()
    with pytest.raises(ValueError, match="finite far"):
        stratified_intervals(near, far, 6)
    t0, t1 = append_infinite_interval(*stratified_intervals(*near_far(), 4))
    assert t0.shape == (5, 5) and torch.isinf(t1[:, -1]).all() and (t0[:, -1] == 4.0).all()


def test_stratified_validates():
    near, far = near_far()
    with pytest.raises(ValueError, match="near <= far"):
        stratified_intervals(far, near, 4)
    with pytest.raises(ValueError, match="spacing"):
        stratified_intervals(near, far, 4, spacing="log")
    with pytest.raises(ValueError, match="n_samples"):
        stratified_intervals(near, far, 0)


def test_invert_cdf_matches_plain_loop_and_gradcheck():
    g = torch.Generator().manual_seed(2)
    bins = torch.sort(torch.rand(4, 7, generator=g, dtype=torch.float64) * 5, dim=-1).values
    weights = torch.rand(4, 6, generator=g, dtype=torch.float64)
    weights[0] = 0.0  # all-zero weights: uniform over bins
    weights[1, 2:] = 0.0
    u = torch.sort(torch.rand(4, 9, generator=g, dtype=torch.float64), dim=-1).values
    u[:, 0], u[:, -1] = 0.0, 1.0
    fast_bins, ref_bins = bins.clone().requires_grad_(True), bins.clone().requires_grad_(True)
    fast, ref = invert_cdf(fast_bins, weights, u), invert_cdf_reference(ref_bins, weights, u)
    torch.testing.assert_close(fast, ref)
    fast.sum().backward()
    ref.sum().backward()
    torch.testing.assert_close(fast_bins.grad, ref_bins.grad)
    torch.autograd.gradcheck(lambda b: invert_cdf(b, weights, u), (bins.clone().requires_grad_(True),))


def test_sample_pdf_follows_weights():
    bins = torch.linspace(0, 1, 11, dtype=torch.float64).expand(3, -1)
    weights = torch.zeros(3, 10, dtype=torch.float64)
    weights[:, 6] = 1.0
    for jitter in (False, True):
        t = sample_pdf(bins, weights, 64, jitter=jitter, generator=torch.Generator().manual_seed(3))
        assert t.shape == (3, 64) and (t[:, 1:] >= t[:, :-1]).all()
        inside = ((t >= 0.6) & (t <= 0.7)).double().mean()
        assert inside > 0.95


@pytest.mark.parametrize("include_coarse", [True, False])
def test_resample_intervals(include_coarse):
    near, far = near_far(n=3)
    t0, t1 = stratified_intervals(near, far, 8)
    w = torch.zeros(3, 8, dtype=torch.float64)
    w[:, 3] = 1.0
    f0, f1 = resample_intervals(t0, t1, w, 16, include_coarse=include_coarse)
    assert f0.shape == (3, 24 if include_coarse else 16)
    torch.testing.assert_close(f0[:, 1:], f1[:, :-1])
    assert (f1 >= f0).all()
    if include_coarse:
        torch.testing.assert_close(f0[:, 0], near)
        torch.testing.assert_close(f1[:, -1], far)
    # Most new intervals fall in the weighted bin.
    lo, hi = t0[0, 3], t1[0, 3]
    assert ((f0[0] >= lo) & (f1[0] <= hi)).sum() >= 14


def test_resample_keeps_infinite_last_interval():
    near, far = near_far(n=2, far=math.inf)
    t0, t1 = stratified_intervals(near, far, 6, spacing="disparity")
    f0, f1 = resample_intervals(t0, t1, torch.rand(2, 6, dtype=torch.float64), 8)
    assert f0.shape == (2, 14) and torch.isinf(f1[:, -1]).all() and torch.isfinite(f1[:, :-1]).all()


def test_ray_aabb_matches_plain_loop_including_zero_directions():
    g = torch.Generator().manual_seed(4)
    o = torch.rand(200, 3, generator=g, dtype=torch.float64) * 6 - 3
    d = torch.randn(200, 3, generator=g, dtype=torch.float64)
    d[::3, 0] = 0.0
    d[1::5, 1] = -0.0
    d[::7, 2] = 0.0
    o[:20] = torch.rand(20, 3, generator=g, dtype=torch.float64) * 2 - 1  # some start inside
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    fast, ref = ray_aabb_intersect(o, d, aabb), ray_aabb_intersect_reference(o, d, aabb)
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b)
    t_near, t_far, hit = fast
    assert hit[:20].all() and (t_near[:20] == 0).all()
    assert hit.any() and (~hit).any()
    hit = hit & torch.isfinite(t_far)  # a zero direction starting inside has t_far = inf
    x_in = o[hit] + d[hit] * ((t_near + t_far) / 2)[hit, None]
    assert (x_in.abs() <= 1 + 1e-9).all()


def test_ray_aabb_axis_aligned_cases():
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 2.0, 0.0], [0.0, 0.0, 0.0], [-3.0, 1.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t_near, t_far, hit = ray_aabb_intersect(o, d, [-1, -1, -1, 1, 1, 1])
    assert hit.tolist() == [True, False, True, True]  # the last one grazes the face y = 1
    assert t_near.tolist() == [2.0, 0.0, 0.0, 2.0] and t_far.tolist() == [4.0, 0.0, 1.0, 4.0]
    with pytest.raises(ValueError, match="rays_o"):
        ray_aabb_intersect(o[:, :2], d, [-1, -1, -1, 1, 1, 1])
