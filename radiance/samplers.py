"""Samplers along rays: stratified intervals and hierarchical (inverse-CDF) resampling.

Conventions:
- `t` is distance along the ray (rays_d unit length). A ray's samples are intervals [t_start, t_end):
  `t_starts [R, S]`, `t_ends [R, S]`, contiguous (t_ends[:, i] == t_starts[:, i + 1]) and covering [near, far].
- `bins [R, S + 1]` are the interval edges (`t_starts[:, :1]` followed by `t_ends`).
- `far` may be inf with `spacing="disparity"` (edges uniform in 1/t); the last interval is then [t, inf).
- Jitter draws from `generator` (a torch.Generator on the rays' device) so runs are reproducible.
- Samplers return detached t: positions are not learned.
"""

from __future__ import annotations

import bisect

import torch
from torch import Tensor

__all__ = [
    "stratified_intervals",
    "append_infinite_interval",
    "bins_from_intervals",
    "invert_cdf",
    "invert_cdf_reference",
    "sample_pdf",
    "resample_intervals",
]

SPACINGS = ("linear", "disparity")


def _check_near_far(near: Tensor, far: Tensor) -> None:
    if near.ndim != 1 or far.shape != near.shape:
        raise ValueError(f"expected near, far [R], got {tuple(near.shape)} and {tuple(far.shape)}")
    if bool((far < near).any()) or bool((near < 0).any()):
        raise ValueError("expected 0 <= near <= far on every ray, got near > far or near < 0")


@torch.no_grad()
def stratified_intervals(
    near: Tensor,  # [R]
    far: Tensor,  # [R]
    n_samples: int,
    *,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    spacing: str = "linear",
) -> tuple[Tensor, Tensor]:
    """S = n_samples contiguous intervals covering [near, far] per ray: (t_starts [R, S], t_ends [R, S]).

    spacing "linear": edges uniform in t (far must be finite); "disparity": uniform in 1/t (near > 0,
    far may be inf). With jitter, each interior edge moves uniformly between its neighbouring bin centres;
    the first and last edges stay at near and far, so the intervals always cover [near, far] exactly.
    """
    _check_near_far(near, far)
    if n_samples < 1:
        raise ValueError(f"expected n_samples >= 1, got {n_samples}")
    if spacing not in SPACINGS:
        raise ValueError(f"expected spacing in {SPACINGS}, got {spacing!r}")
    n_rays, like = near.shape[0], dict(dtype=near.dtype, device=near.device)
    u = torch.linspace(0, 1, n_samples + 1, **like).expand(n_rays, -1)  # [R, S + 1]
    if jitter and n_samples > 1:
        k = torch.arange(1, n_samples, **like)  # interior edges
        rand = torch.rand(n_rays, n_samples - 1, generator=generator, **like)  # [R, S - 1]
        inner = (k - 0.5 + rand) / n_samples
        u = torch.cat([u[:, :1], inner, u[:, -1:]], dim=-1)
    near_, far_ = near[:, None], far[:, None]  # [R, 1]
    if spacing == "linear":
        if not bool(torch.isfinite(far).all()):
            raise ValueError("expected a finite far with spacing='linear', got inf (use spacing='disparity')")
        edges = near_ + u * (far_ - near_)  # [R, S + 1]
    else:
        if not bool((near > 0).all()):
            raise ValueError("expected near > 0 with spacing='disparity', got near <= 0")
        edges = 1 / (1 / near_ + u * (1 / far_ - 1 / near_))  # [R, S + 1]
    edges = torch.cat([near_, edges[:, 1:-1], far_], dim=-1)  # exact end points
    return edges[:, :-1].contiguous(), edges[:, 1:].contiguous()


def append_infinite_interval(t_starts: Tensor, t_ends: Tensor) -> tuple[Tensor, Tensor]:
    """Add a last interval [far, inf) to every ray: [R, S] -> [R, S + 1] (what NeRF's 1e10 delta stood for)."""
    last = t_ends[:, -1:]
    return torch.cat([t_starts, last], dim=-1), torch.cat([t_ends, torch.full_like(last, float("inf"))], dim=-1)


def bins_from_intervals(t_starts: Tensor, t_ends: Tensor) -> Tensor:
    """Contiguous intervals [R, S] -> edges [R, S + 1]."""
    if t_starts.ndim != 2 or t_ends.shape != t_starts.shape:
        raise ValueError(f"expected t_starts, t_ends [R, S], got {tuple(t_starts.shape)}, {tuple(t_ends.shape)}")
    return torch.cat([t_starts[:, :1], t_ends], dim=-1)


def _cdf(weights: Tensor, padding: float) -> Tensor:
    """weights [R, B] -> cdf [R, B + 1] from 0 to exactly 1 (padding keeps every bin reachable)."""
    w = weights.clamp(min=0) + padding  # [R, B]
    pdf = w / w.sum(dim=-1, keepdim=True)
    zeros, ones = pdf[:, :1].new_zeros(pdf.shape[0], 1), pdf.new_ones(pdf.shape[0], 1)
    return torch.cat([zeros, torch.cumsum(pdf[:, :-1], dim=-1).clamp(max=1), ones], dim=-1)


def invert_cdf(
    bins: Tensor,  # [R, B + 1] finite, non-decreasing
    weights: Tensor,  # [R, B] >= 0
    u: Tensor,  # [R, n] in [0, 1]
    padding: float = 1e-5,
) -> Tensor:
    """Inverse transform sampling of the piecewise-constant pdf ∝ weights + padding over bins: t [R, n].

    Differentiable with respect to bins (t is linear in them); weights are treated as constants.
    """
    if bins.ndim != 2 or weights.shape != (bins.shape[0], bins.shape[1] - 1):
        raise ValueError(
            f"expected bins [R, B + 1] and weights [R, B], got {tuple(bins.shape)}, {tuple(weights.shape)}"
        )
    if u.ndim != 2 or u.shape[0] != bins.shape[0]:
        raise ValueError(f"expected u [R, n] with R={bins.shape[0]}, got {tuple(u.shape)}")
    n_bins = weights.shape[1]
    cdf = _cdf(weights.detach().to(bins.dtype), padding)  # [R, B + 1]
    u = u.to(cdf).contiguous()
    idx = torch.searchsorted(cdf, u, right=True)  # [R, n]: number of cdf entries <= u
    below, above = (idx - 1).clamp(0, n_bins), idx.clamp(max=n_bins)
    cdf_b, cdf_a = cdf.gather(1, below), cdf.gather(1, above)
    bin_b, bin_a = bins.gather(1, below), bins.gather(1, above)
    denom = cdf_a - cdf_b
    frac = torch.where(denom > 0, (u - cdf_b) / torch.where(denom > 0, denom, torch.ones_like(denom)), 0)
    return bin_b + frac.clamp(0, 1) * (bin_a - bin_b)


def invert_cdf_reference(bins: Tensor, weights: Tensor, u: Tensor, padding: float = 1e-5) -> Tensor:
    """Plain per-sample loop twin of `invert_cdf` (bisect on a Python list; keeps autograd through bins)."""
    out = []
    for r in range(bins.shape[0]):
        w = [max(float(x), 0.0) + padding for x in weights[r].tolist()]
        total, cdf = sum(w), [0.0]
        for x in w[:-1]:
            cdf.append(min(cdf[-1] + x / total, 1.0))
        cdf.append(1.0)
        row = []
        for v in u[r].tolist():
            i = bisect.bisect_right(cdf, v)
            lo, hi = min(max(i - 1, 0), len(w)), min(i, len(w))
            d = cdf[hi] - cdf[lo]
            frac = min(max((v - cdf[lo]) / d, 0.0), 1.0) if d > 0 else 0.0
            row.append(bins[r, lo] + frac * (bins[r, hi] - bins[r, lo]))
        out.append(torch.stack(row))
    return torch.stack(out)


def sample_pdf(
    bins: Tensor,  # [R, B + 1]
    weights: Tensor,  # [R, B]
    n_samples: int,
    *,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    padding: float = 1e-5,
) -> Tensor:
    """NeRF's sample_pdf: n_samples sorted t [R, n] drawn from the pdf ∝ weights over bins.

    Without jitter u = linspace(0, 1, n); with jitter u is stratified, (k + U[0, 1)) / n, still sorted.
    """
    n_rays, like = bins.shape[0], dict(dtype=bins.dtype, device=bins.device)
    if jitter:
        u = (torch.arange(n_samples, **like) + torch.rand(n_rays, n_samples, generator=generator, **like)) / n_samples
    else:
        u = torch.linspace(0, 1, n_samples, **like).expand(n_rays, -1)
    return invert_cdf(bins, weights, u, padding)


@torch.no_grad()
def resample_intervals(
    t_starts: Tensor,  # [R, S] contiguous
    t_ends: Tensor,  # [R, S]
    weights: Tensor,  # [R, S] coarse compositing weights
    n_samples: int,
    *,
    include_coarse: bool = True,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    padding: float = 1e-5,
) -> tuple[Tensor, Tensor]:
    """Hierarchical sampling: intervals for the fine pass from the coarse pass's weights.

    include_coarse: the coarse edges plus n_samples new edges -> S + n_samples intervals (NeRF's union of
    coarse and fine samples), still covering [near, far]; otherwise n_samples + 1 new edges -> n_samples
    intervals between the first and last drawn edge. An infinite last interval (every ray or none) is left
    out of the pdf and kept as it is (include_coarse) since no finite sample can be drawn from it.
    """
    bins = bins_from_intervals(t_starts, t_ends)  # [R, S + 1]
    if weights.shape != t_starts.shape:
        raise ValueError(f"expected weights {tuple(t_starts.shape)}, got {tuple(weights.shape)}")
    infinite = torch.isinf(t_ends[:, -1])  # [R]
    if bool(infinite.any()):
        if not bool(infinite.all()) or t_starts.shape[1] < 2:
            raise ValueError("expected an infinite last interval on every ray (or none) and S >= 2")
        fine = sample_pdf(
            bins[:, :-1],
            weights[:, :-1],
            n_samples + (0 if include_coarse else 1),
            jitter=jitter,
            generator=generator,
            padding=padding,
        )
    else:
        fine = sample_pdf(
            bins, weights, n_samples + (0 if include_coarse else 1), jitter=jitter, generator=generator, padding=padding
        )
    edges = torch.sort(torch.cat([bins, fine], dim=-1), dim=-1).values if include_coarse else fine
    return edges[:, :-1].contiguous(), edges[:, 1:].contiguous()
