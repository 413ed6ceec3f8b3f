"""Compositing core and safe numerics: closed forms, float-range sweeps, gradcheck, plain twins."""

import math

import pytest
import torch

from nerfpipe.radiance.compositing import (
    accumulate,
    beer_lambert,
    composite,
    median_depth,
    render_weights,
    render_weights_reference,
    segment_cumsum,
    segment_cumsum_reference,
)
from nerfpipe.radiance.safe import eps, safe_div, safe_log, safe_sqrt, shifted_softplus, tol, trunc_exp
from nerfpipe.radiance.stability import run_sweep, summarize

DTYPES = [torch.float16, torch.bfloat16, torch.float32, torch.float64]


def slab_intervals(length: float, n: int, dtype=torch.float64):
    edges = torch.linspace(0, length, n + 1, dtype=dtype)[None]  # [1, n + 1]
    return edges[:, :-1], edges[:, 1:]


def packed_from_padded(x):
    """[R, S] -> ([R * S], ray_indices [R * S])."""
    r, s = x.shape[:2]
    return x.reshape(r * s, *x.shape[2:]), torch.arange(r).repeat_interleave(s)


@pytest.mark.parametrize("n", [1, 3, 64])
def test_homogeneous_slab_matches_closed_form_at_any_sample_count(n):
    sigma, length = 1.7, 2.0
    t0, t1 = slab_intervals(length, n)
    sigmas = torch.full_like(t0, sigma)
    rgbs = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64).expand(1, n, 3)
    out = composite(sigmas, rgbs, t0, t1)
    acc = 1 - math.exp(-sigma * length)
    assert out["acc"].item() == pytest.approx(acc, rel=1e-12)
    torch.testing.assert_close(out["rgb"][0], rgbs[0, 0] * acc)
    # Median: the weight density is sigma exp(-sigma t), so it reaches 0.5 at ln 2 / sigma, exactly.
    assert out["depth_median"].item() == pytest.approx(math.log(2) / sigma, rel=1e-12)
    # Transmittance at each interval's start is exp(-sigma t_start).
    torch.testing.assert_close(out["transmittance"], torch.exp(-sigma * t0))


def test_piecewise_constant_medium_is_exact_and_background_composites():
    # Three slabs with different densities; intervals refine the slab boundaries at several sample counts.
    bounds, dens = [0.0, 0.5, 1.25, 3.0], [0.3, 4.0, 0.0]
    optical = sum(d * (b - a) for a, b, d in zip(bounds[:-1], bounds[1:], dens, strict=True))
    for per_slab in (1, 2, 7):
        pieces = [
            torch.linspace(a, b, per_slab + 1, dtype=torch.float64)[:-1]
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)
        ]
        edges = torch.cat([*pieces, torch.tensor([3.0], dtype=torch.float64)])
        t0, t1 = edges[None, :-1], edges[None, 1:]
        sigmas = torch.tensor(dens, dtype=torch.float64).repeat_interleave(per_slab)[None]
        rgbs = torch.ones(*t0.shape, 3, dtype=torch.float64)
        bg = torch.tensor([0.0, 1.0, 0.5], dtype=torch.float64)
        out = composite(sigmas, rgbs, t0, t1, background=bg)
        t_final = math.exp(-optical)
        assert out["acc"].item() == pytest.approx(1 - t_final, rel=1e-12)
        torch.testing.assert_close(out["rgb"][0], (1 - t_final) + t_final * bg)
        x = beer_lambert(sigmas, t0, t1, i0=2.5)
        assert x["optical_depth"].item() == pytest.approx(optical, rel=1e-12)
        assert x["intensity"].item() == pytest.approx(2.5 * t_final, rel=1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sweep_finite_outputs_and_gradients(dtype):
    # radiance.stability: the same sweep `make study` tabulates (tau = 1e-12..1e12, zero-length, infinite far).
    sweep = run_sweep(dtype)
    sigmas, t0, t1, out = sweep.sigmas, sweep.t_starts, sweep.t_ends, sweep.outputs
    w = out["weights"].double()
    assert torch.isfinite(w).all() and (w >= 0).all() and (w <= 1).all()
    assert (w.sum(-1) <= 1 + eps(dtype)).all()
    for k in ("rgb", "depth", "acc", "depth_median"):
        assert out[k].dtype == dtype
        assert torch.isfinite(out[k]).all() or k == "depth_median", k
    # A ray whose total weight stays below 0.5 has no median (inf); every other ray has a finite one.
    # (fp16: unless the median t itself is beyond fp16's range.)
    median64 = median_depth(sigmas.double(), t0.double(), t1.double())
    reached = (w.sum(-1) >= 0.5) & (median64 < torch.finfo(dtype).max)
    assert (
        torch.isfinite(out["depth_median"][reached]).all() and torch.isinf(out["depth_median"][w.sum(-1) < 0.5]).all()
    )
    assert torch.isfinite(sweep.sigma_grad).all() and torch.isfinite(sweep.rgb_grad).all()
    assert torch.isfinite(sweep.transmittance).all() and (sweep.transmittance <= 1).all()
    # Against the 40-digit reference on the dtype-rounded inputs: within 8 eps (worst now: fp32 rgb, 3.8 eps),
    # except fp16 depth of rays whose opacity is below eps(fp16) (sum w t / eps of subnormal fp16 weights: 79 eps).
    summary = summarize(sweep)
    assert summary["values_finite"] and summary["gradients_finite"] and summary["weights_sum_le_one"]
    for k, err in summary["worst_rel_error"].items():
        assert err <= (200 if (dtype, k) == (torch.float16, "depth") else 8) * eps(dtype), (k, err)


@pytest.mark.parametrize("dtype", DTYPES)
def test_low_precision_agrees_with_float64(dtype):
    g = torch.Generator().manual_seed(1)
    sigmas = torch.rand(8, 16, generator=g, dtype=torch.float64) * 3
    t0, t1 = slab_intervals(2.0, 16)
    t0, t1 = t0.expand(8, -1), t1.expand(8, -1)
    ref, _, _ = render_weights(sigmas, t0, t1)
    w, _, _ = render_weights(sigmas.to(dtype), t0.to(dtype), t1.to(dtype))
    rtol, atol = tol(dtype)
    torch.testing.assert_close(w.double(), ref, rtol=rtol, atol=atol * 10)


def test_gradcheck_float64_padded_and_packed():
    g = torch.Generator().manual_seed(2)
    sigmas = (torch.rand(3, 5, generator=g, dtype=torch.float64) * 2).requires_grad_(True)
    rgbs = torch.rand(3, 5, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    edges = torch.sort(torch.rand(3, 6, generator=g, dtype=torch.float64) * 3, dim=-1).values
    t0, t1 = edges[:, :-1].clone(), edges[:, 1:].clone().requires_grad_(True)

    def padded(s, c, e):
        out = composite(s, c, t0, e)
        return out["rgb"], out["depth"], out["acc"]

    torch.autograd.gradcheck(padded, (sigmas, rgbs, t1))

    ri = torch.arange(3).repeat_interleave(5)

    def packed(s, c):
        out = composite(s, c, t0.reshape(-1), t1.detach().reshape(-1), ri, 3)
        return out["rgb"], out["depth"], out["acc"]

    torch.autograd.gradcheck(
        packed, (sigmas.reshape(-1).detach().requires_grad_(True), rgbs.reshape(-1, 3).detach().requires_grad_(True))
    )
    torch.autograd.gradcheck(lambda s: beer_lambert(s, t0, t1.detach())["intensity"], (sigmas,))


def test_render_weights_matches_plain_loop_outputs_and_gradients():
    g = torch.Generator().manual_seed(3)
    sigmas = torch.rand(4, 6, generator=g, dtype=torch.float64) * 2
    sigmas[0, 2] = 0.0
    edges = torch.sort(torch.rand(4, 7, generator=g, dtype=torch.float64) * 3, dim=-1).values
    edges[1, 3] = edges[1, 2]  # a zero-length interval
    t0, t1 = edges[:, :-1], edges[:, 1:]
    fast_in, ref_in = sigmas.clone().requires_grad_(True), sigmas.clone().requires_grad_(True)
    fast, ref = render_weights(fast_in, t0, t1), render_weights_reference(ref_in, t0, t1)
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b)
    probe = torch.rand(4, 6, generator=g, dtype=torch.float64)
    (fast[0] * probe).sum().backward()
    (ref[0] * probe).sum().backward()
    torch.testing.assert_close(fast_in.grad, ref_in.grad)


def test_packed_equals_padded_and_segment_cumsum_matches_loop():
    g = torch.Generator().manual_seed(4)
    counts = [3, 0, 5, 1]  # a ray with no samples
    ri = torch.repeat_interleave(torch.arange(4), torch.tensor(counts))
    x = torch.rand(ri.shape[0], generator=g, dtype=torch.float64).requires_grad_(True)
    for exclusive in (True, False):
        torch.testing.assert_close(
            segment_cumsum(x, ri, 4, exclusive=exclusive), segment_cumsum_reference(x, ri, exclusive=exclusive)
        )
    # Padded with zero-length padding == packed.
    sigmas = torch.rand(4, 5, generator=g, dtype=torch.float64) * 3
    t = torch.sort(torch.rand(4, 6, generator=g, dtype=torch.float64) * 2, dim=-1).values
    t0, t1 = t[:, :-1], t[:, 1:]
    rgbs = torch.rand(4, 5, 3, generator=g, dtype=torch.float64)
    out_pad = composite(sigmas, rgbs, t0, t1)
    ps, pri = packed_from_padded(sigmas)
    out_pack = composite(ps, packed_from_padded(rgbs)[0], t0.reshape(-1), t1.reshape(-1), pri, 4)
    for k in ("rgb", "depth", "depth_median", "acc"):
        torch.testing.assert_close(out_pack[k], out_pad[k])
    torch.testing.assert_close(out_pack["weights"], out_pad["weights"].reshape(-1))


def test_packed_rejects_unsorted_and_shape_errors():
    with pytest.raises(ValueError, match="sorted"):
        segment_cumsum(torch.ones(3), torch.tensor([1, 0, 1]), 2)
    with pytest.raises(ValueError, match="expected"):
        render_weights(torch.ones(3, 4), torch.zeros(3, 4), torch.ones(3, 5))
    with pytest.raises(ValueError, match="n_rays"):
        accumulate(torch.ones(3), None, torch.zeros(3, dtype=torch.long))


def test_median_depth_fill_for_transparent_rays():
    t0, t1 = slab_intervals(1.0, 4)
    d = median_depth(torch.full_like(t0, 0.1), t0, t1, fill=-1.0)
    assert d.item() == -1.0


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32])
def test_density_activations_never_overflow(dtype):
    x = torch.tensor([-1e4, -20.0, 0.0, 20.0, 1e4, torch.finfo(dtype).max], dtype=dtype, requires_grad=True)
    for act in (trunc_exp, shifted_softplus):
        y = act(x)
        assert torch.isfinite(y).all() and (y >= 0).all()
        (grad,) = torch.autograd.grad(y.sum(), x)
        assert torch.isfinite(grad).all()
    # trunc_exp keeps a non-zero gradient above the clamp (instant-ngp's behaviour).
    (grad,) = torch.autograd.grad(trunc_exp(x).sum(), x)
    assert grad[-1] > 0


def test_safe_helpers():
    z = torch.tensor([0.0, -1.0, 4.0], dtype=torch.float32, requires_grad=True)
    for f in (safe_log, safe_sqrt, lambda v: safe_div(torch.ones_like(v), v)):
        y = f(z)
        assert torch.isfinite(y).all()
        assert torch.isfinite(torch.autograd.grad(y.sum(), z)[0]).all()
    assert safe_sqrt(torch.tensor(4.0)).item() == 2.0
    with pytest.raises(ValueError, match="expected a floating dtype"):
        tol(torch.int32)


@pytest.mark.parametrize("dtype", DTYPES)
def test_weights_sum_at_most_one_with_many_samples(dtype):
    g = torch.Generator().manual_seed(5)
    sigmas = (
        torch.rand(32, 2048, generator=g, dtype=torch.float64) * torch.logspace(-3, 3, 32, dtype=torch.float64)[:, None]
    )
    edges = torch.sort(torch.rand(32, 2049, generator=g, dtype=torch.float64) * 10, dim=-1).values
    w, _, _ = render_weights(sigmas.to(dtype), edges[:, :-1].to(dtype), edges[:, 1:].to(dtype))
    assert (w.double().sum(-1) <= 1 + eps(dtype)).all()
