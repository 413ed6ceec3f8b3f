"""Model-free compositing: emission-absorption (photos) and Beer-Lambert attenuation (X-ray).

Conventions:
- A ray is cut into intervals [t_start, t_end); `delta = t_end - t_start >= 0`; `t` is distance along the ray.
  The last interval may be infinite (t_end = inf); zero-length intervals (delta = 0) contribute nothing,
  which is how padded rays with fewer samples are written.
- `sigma >= 0` is density (or X-ray attenuation mu) constant over each interval; the caller guarantees >= 0.
- Optical depth `tau_i = sigma_i * delta_i`, taken as 0 where sigma_i = 0 or delta_i = 0 (so 0 * inf = 0),
  and as a constant inf where sigma_i = inf or delta_i = inf (and the other > 0): an opaque interval,
  alpha = 1, T = 0 behind it, zero gradient through its tau (alpha is flat there), so gradients stay finite.
- Transmittance `T_i = exp(-sum_{j<i} tau_j)` (exclusive cumsum), alpha `a_i = -expm1(-tau_i)`,
  weights `w_i = T_i a_i`; `acc = sum_i w_i <= 1` (+ rounding); the ray's remaining transmittance is 1 - acc.
- Interval "midpoint" `t_mid = (t_start + t_end) / 2`, or t_start for an infinite interval (the far plane).
- Two layouts, one core:
  padded: tensors [R, S] (S samples per ray, pad with zero-length intervals);
  packed: flat [N] samples with `ray_indices [N]` (non-decreasing, nerfacc style) and `n_rays`.
  Both go through `exclusive_cumsum` (packed: scattered to [R, S_max] and back, so one ray's huge
  optical depth never cancels against another's, as a global cumsum would).
- Half precision inputs (fp16, bf16) are computed in float32 and returned in the input dtype.
"""

from __future__ import annotations

import torch
from torch import Tensor

from nerfpipe.radiance.safe import safe_div

__all__ = [
    "interval_midpoints",
    "optical_depth",
    "exclusive_cumsum",
    "segment_cumsum",
    "segment_cumsum_reference",
    "render_weights",
    "render_weights_reference",
    "accumulate",
    "median_depth",
    "median_crossing",
    "composite",
    "beer_lambert",
    "over_background",
]


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.promote_types(dtype, torch.float32)


def _check_layout(x: Tensor, ray_indices: Tensor | None, n_rays: int | None, name: str) -> None:
    if ray_indices is None:
        if x.ndim != 2:
            raise ValueError(f"expected padded {name} [R, S] (or packed [N] with ray_indices), got {tuple(x.shape)}")
        return
    if x.ndim != 1 or ray_indices.shape != x.shape:
        raise ValueError(
            f"expected packed {name} [N] and ray_indices [N], got {tuple(x.shape)} and {tuple(ray_indices.shape)}"
        )
    if n_rays is None:
        raise ValueError("expected n_rays with ray_indices, got None")


def interval_midpoints(t_starts: Tensor, t_ends: Tensor) -> Tensor:
    """(t_start + t_end) / 2, or t_start where t_end is infinite. Any shape."""
    return torch.where(torch.isinf(t_ends), t_starts, 0.5 * (t_starts + t_ends))


def optical_depth(sigmas: Tensor, t_starts: Tensor, t_ends: Tensor) -> Tensor:
    """tau = sigma * (t_end - t_start), 0 where sigma = 0 or delta = 0 (no 0 * inf). Any shape, float32+."""
    dtype = _compute_dtype(sigmas.dtype)
    sigmas = sigmas.to(dtype)
    deltas = (t_ends - t_starts).to(dtype)
    empty = (sigmas == 0) | (deltas == 0)
    opaque = ~empty & (torch.isinf(sigmas) | torch.isinf(deltas))  # tau = inf, alpha = 1 for any finite change
    special = empty | opaque
    # where() on the inputs too, so the backward pass never sees inf * 0 in the masked entries.
    zero = torch.zeros((), dtype=dtype, device=sigmas.device)
    tau = torch.where(special, zero, sigmas) * torch.where(special, zero, deltas)
    return torch.where(opaque, torch.full_like(tau, float("inf")), tau)


def exclusive_cumsum(x: Tensor) -> Tensor:
    """out[..., i] = sum_{j<i} x[..., j] along the last dim, by shifting (no subtraction, so inf is safe)."""
    if x.shape[-1] == 0:
        return x.clone()
    return torch.nn.functional.pad(torch.cumsum(x[..., :-1], dim=-1), (1, 0))


def _packed_positions(ray_indices: Tensor, n_rays: int) -> tuple[Tensor, int]:
    """Each sample's position within its ray ([N] long) and the largest count of samples on a ray."""
    if ray_indices.numel() == 0:
        return ray_indices.new_zeros(0), 0
    if bool((ray_indices[1:] < ray_indices[:-1]).any()):
        raise ValueError("expected ray_indices sorted (non-decreasing), got unsorted ray_indices")
    if int(ray_indices[0]) < 0 or int(ray_indices[-1]) >= n_rays:
        raise ValueError(f"expected ray_indices in [0, {n_rays}), got [{int(ray_indices[0])}, {int(ray_indices[-1])}]")
    counts = torch.bincount(ray_indices, minlength=n_rays)  # [R]
    firsts = torch.cumsum(counts, 0) - counts  # [R] index of each ray's first sample
    pos = torch.arange(ray_indices.numel(), device=ray_indices.device) - firsts[ray_indices]  # [N]
    return pos, int(counts.max())


def _to_padded(x: Tensor, ray_indices: Tensor, pos: Tensor, n_rays: int, width: int, fill: float = 0.0) -> Tensor:
    """Packed [N, ...] -> padded [R, S_max, ...] (differentiable)."""
    out = x.new_full((n_rays, width, *x.shape[1:]), fill)
    return out.index_put((ray_indices, pos), x)


def segment_cumsum(
    x: Tensor,  # [N] packed or [R, S] padded
    ray_indices: Tensor | None = None,  # [N]
    n_rays: int | None = None,
    *,
    exclusive: bool = True,
) -> Tensor:
    """Cumulative sum along each ray (exclusive by default), in either layout; same shape as x."""
    _check_layout(x, ray_indices, n_rays, "x")
    scan = exclusive_cumsum if exclusive else (lambda v: torch.cumsum(v, dim=-1))
    if ray_indices is None:
        return scan(x)
    pos, width = _packed_positions(ray_indices, n_rays)
    return scan(_to_padded(x, ray_indices, pos, n_rays, width))[ray_indices, pos]


def segment_cumsum_reference(x: Tensor, ray_indices: Tensor, *, exclusive: bool = True) -> Tensor:
    """Plain loop twin of `segment_cumsum` for the packed layout (for tests; keeps autograd)."""
    out, running, prev = [], None, None
    for i, r in enumerate(ray_indices.tolist()):
        if r != prev:
            running, prev = x.new_zeros(()), r
        if exclusive:
            out.append(running)
        running = running + x[i]
        if not exclusive:
            out.append(running)
    return torch.stack(out) if out else x.new_zeros(0)


def render_weights(
    sigmas: Tensor,  # [R, S] or [N]
    t_starts: Tensor,  # same
    t_ends: Tensor,  # same
    ray_indices: Tensor | None = None,  # [N] for packed
    n_rays: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Compositing weights. Returns (weights, transmittance, alphas), each shaped like sigmas, sigmas' dtype."""
    _check_layout(sigmas, ray_indices, n_rays, "sigmas")
    if t_starts.shape != sigmas.shape or t_ends.shape != sigmas.shape:
        raise ValueError(
            f"expected t_starts, t_ends {tuple(sigmas.shape)}, got {tuple(t_starts.shape)}, {tuple(t_ends.shape)}"
        )
    tau = optical_depth(sigmas, t_starts, t_ends)  # float32+
    trans = torch.exp(-segment_cumsum(tau, ray_indices, n_rays))
    alphas = -torch.expm1(-tau)
    weights = trans * alphas
    return weights.to(sigmas.dtype), trans.to(sigmas.dtype), alphas.to(sigmas.dtype)


def render_weights_reference(sigmas: Tensor, t_starts: Tensor, t_ends: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Plain loop twin of `render_weights` (padded [R, S]): T carried as a running product of exp(-tau)."""
    rows_w, rows_t, rows_a = [], [], []
    for r in range(sigmas.shape[0]):
        trans = sigmas.new_ones(())
        ws, ts, alphas = [], [], []
        for i in range(sigmas.shape[1]):
            sigma, delta = sigmas[r, i], t_ends[r, i] - t_starts[r, i]
            tau = sigma * 0 if (sigma == 0 or delta == 0) else sigma * delta
            alpha = -torch.expm1(-tau)
            ws.append(trans * alpha)
            ts.append(trans)
            alphas.append(alpha)
            trans = trans * torch.exp(-tau)
        rows_w.append(torch.stack(ws))
        rows_t.append(torch.stack(ts))
        rows_a.append(torch.stack(alphas))
    return torch.stack(rows_w), torch.stack(rows_t), torch.stack(rows_a)


def accumulate(
    weights: Tensor,  # [R, S] or [N]
    values: Tensor | None = None,  # [R, S, C] / [R, S] or [N, C] / [N]; None: accumulate 1 (opacity)
    ray_indices: Tensor | None = None,  # [N] for packed
    n_rays: int | None = None,
) -> Tensor:
    """sum_i w_i v_i per ray: [R] or [R, C] in weights' dtype (summed in float32+)."""
    _check_layout(weights, ray_indices, n_rays, "weights")
    dtype = _compute_dtype(weights.dtype)
    w = weights.to(dtype)
    if values is not None:
        v = values.to(dtype)
        w = w[..., None] * v if v.ndim == w.ndim + 1 else w * v
    if ray_indices is None:
        out = w.sum(dim=1)
    else:
        out = w.new_zeros((n_rays, *w.shape[1:])).index_add(0, ray_indices, w)
    return out.to(weights.dtype)


@torch.no_grad()
def median_depth(
    sigmas: Tensor,  # [R, S] or [N]
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
    *,
    fill: float = float("inf"),
) -> Tensor:
    """t where the ray's accumulated weight reaches 0.5: [R], not differentiable.

    Exact for piecewise-constant density (solved inside the crossing interval, not at its midpoint).
    Rays whose total weight stays below 0.5 get `fill` (default inf: no surface).
    """
    _check_layout(sigmas, ray_indices, n_rays, "sigmas")
    dtype = _compute_dtype(sigmas.dtype)
    s, t0, t1 = sigmas.to(dtype), t_starts.to(dtype), t_ends.to(dtype)
    if ray_indices is not None:
        pos, width = _packed_positions(ray_indices, n_rays)
        s, t0, t1 = (_to_padded(x, ray_indices, pos, n_rays, width) for x in (s, t0, t1))
    n, width = s.shape
    if width == 0:
        return torch.full((n,), fill, dtype=sigmas.dtype, device=sigmas.device)
    tau = optical_depth(s, t0, t1)  # [R, S]
    trans = torch.exp(-exclusive_cumsum(tau))  # [R, S]
    w = trans * -torch.expm1(-tau)  # [R, S]
    crossed, depth = median_crossing(s, t0, t1, trans, w, exclusive_cumsum(w))
    return torch.where(crossed, depth, torch.full_like(depth, fill)).to(sigmas.dtype)


def median_crossing(
    sigmas: Tensor,  # [R, S] padded rows, float32+
    t_starts: Tensor,  # [R, S]
    t_ends: Tensor,  # [R, S]
    trans: Tensor,  # [R, S] transmittance before each interval
    weights: Tensor,  # [R, S]
    w_before: Tensor,  # [R, S] weight accumulated before each interval (earlier rows' part included)
) -> tuple[Tensor, Tensor]:
    """Where each row's accumulated weight reaches 0.5 within these intervals: (crossed [R] bool, t [R]; t is
    meaningless where not crossed). Solved inside the crossing interval for its constant density; shared by
    `median_depth` and renderers that composite a ray in pieces (front to back)."""
    width = sigmas.shape[-1]
    idx = ((w_before + weights) < 0.5).sum(dim=-1, keepdim=True)  # [R, 1] first interval reaching 0.5
    crossed = idx[:, 0] < width
    idx = idx.clamp(max=width - 1)
    s_i, t0_i, t1_i, trans_i, wb_i = (x.gather(1, idx)[:, 0] for x in (sigmas, t_starts, t_ends, trans, w_before))
    # Inside the interval: wb + T (1 - exp(-sigma x)) = 0.5  ->  x = -log1p(-(0.5 - wb) / T) / sigma.
    ratio = safe_div(0.5 - wb_i, trans_i).clamp(0, 1)
    x = -torch.log1p(-ratio) / torch.where(s_i > 0, s_i, torch.ones_like(s_i))
    x = torch.where(s_i > 0, x, torch.zeros_like(x))
    x = torch.minimum(x.clamp(min=0), t1_i - t0_i)
    return crossed, t0_i + x


def composite(
    sigmas: Tensor,  # [R, S] or [N]
    rgbs: Tensor,  # [R, S, 3] or [N, 3]
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
    *,
    background: Tensor | None = None,  # [3] or [R, 3]
) -> dict[str, Tensor]:
    """Emission-absorption: colour, expected and median depth, opacity, on an optional background.

    Returns rgb [R, 3], depth [R] (sum w t_mid / acc, eps-clamped), depth_median [R], acc [R],
    weights and transmittance (shaped like sigmas).
    """
    weights, trans, _ = render_weights(sigmas, t_starts, t_ends, ray_indices, n_rays)
    n = sigmas.shape[0] if ray_indices is None else n_rays
    if rgbs.shape != (*sigmas.shape, rgbs.shape[-1]):
        raise ValueError(f"expected rgbs {(*sigmas.shape, 'C')}, got {tuple(rgbs.shape)}")
    acc = accumulate(weights, None, ray_indices, n_rays)  # [R]
    rgb = accumulate(weights, rgbs, ray_indices, n_rays)  # [R, C]
    t_mid = interval_midpoints(t_starts, t_ends)
    depth = safe_div(accumulate(weights, t_mid, ray_indices, n_rays), acc)  # [R]
    if background is not None:
        bg = background.to(rgb)
        if bg.shape not in ((rgb.shape[-1],), tuple(rgb.shape)):
            raise ValueError(f"expected background [C] or [R, C] with R={n}, got {tuple(bg.shape)}")
        rgb = rgb + (1 - acc)[:, None] * bg
    return {
        "rgb": rgb,
        "depth": depth,
        "depth_median": median_depth(sigmas, t_starts, t_ends, ray_indices, n_rays),
        "acc": acc,
        "weights": weights,
        "transmittance": trans,
    }


def beer_lambert(
    mus: Tensor,  # [R, S] or [N] attenuation coefficient (1 / length)
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
    *,
    i0: float | Tensor = 1.0,  # scalar or [R] source intensity
) -> dict[str, Tensor]:
    """X-ray line integral: I = I0 exp(-sum_i mu_i delta_i).

    Returns intensity [R], optical_depth [R] (= -log(I / I0), the line integral) and
    transmittance [R] (= I / I0), in mus' dtype.
    """
    _check_layout(mus, ray_indices, n_rays, "mus")
    tau = optical_depth(mus, t_starts, t_ends)  # float32+
    if ray_indices is None:
        total = tau.sum(dim=-1)
    else:
        total = tau.new_zeros(n_rays).index_add(0, ray_indices, tau)
    trans = torch.exp(-total)
    i0_t = torch.as_tensor(i0, dtype=trans.dtype, device=trans.device)
    return {
        "intensity": (i0_t * trans).to(mus.dtype),
        "optical_depth": total.to(mus.dtype),
        "transmittance": trans.to(mus.dtype),
    }


def over_background(rgb, alpha, background):
    """Straight-alpha colour over a background: rgb * alpha + (1 - alpha) * background.

    rgb [..., 3], alpha [..., 1] (or broadcastable), background [3] or [..., 3]; torch tensors or numpy arrays
    (plain arithmetic). The one place photos with alpha meet a background, in training targets and evaluation.
    """
    return rgb * alpha + (1 - alpha) * background
