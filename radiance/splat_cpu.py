"""CPU compositing of binned Gaussians, compiled with numba: `splats.rasterize`'s fast path on CPU tensors.

The same rules as `radiance.splats` (its module doc), evaluated the way the CUDA rasterisers do it: each pixel walks
its tile's Gaussians front to back, skips alphas below ALPHA_MIN, clamps at ALPHA_MAX and stops before the Gaussian
that would bring its transmittance below T_MIN; the backward pass walks the same Gaussians back to front from each
pixel's last contributor, recovering T_i = T_{i+1} / (1 - alpha_i) (3DGS's backward kernel). Where the torch path
evaluates every Gaussian of a tile at all of its pixels and keeps autograd's intermediates, this one touches a
Gaussian only until a pixel is opaque and keeps two numbers a pixel, which is what makes it fast
(docs/DESIGN.md, "Splat rasteriser kernels on CPU").

Gradients (d = pixel centre - mean, q = a dx^2 + 2 b dx dy + c dy^2, e = o exp(-q / 2), alpha = min(e, ALPHA_MAX)):
- colour C = sum_i alpha_i T_i c_i + T_N bg: dC/dc_i = alpha_i T_i, dC/dalpha_i = T_i (c_i - R_i) with
  R_i = alpha_{i+1} c_{i+1} + (1 - alpha_{i+1}) R_{i+1} the normalised colour behind i (R = bg behind the last);
- alpha output A = 1 - T_N: dA/dalpha_i = T_N / (1 - alpha_i); dC/dbg = T_N;
- de = dalpha where e < ALPHA_MAX, else 0 (the clamp, as torch's clamp_max); do = de exp(-q / 2); with
  g = e de: dmean = g (a dx + b dy, b dx + c dy), dconic = g (-dx^2 / 2, -dx dy, -dy^2 / 2).

The kernels read one row per (tile, Gaussian) pair, gathered in torch (`composite`), so each pair's gradient lands in
its own row, written by the one thread that owns its tile (no atomics), and autograd's gather backward sums the rows
into the Gaussians. A Gaussian whose alpha is under ALPHA_MIN at a pixel is rejected on q alone (q > 2 ln(o /
ALPHA_MIN)), without the exponential. Works in float32 and float64 (numba compiles one version per dtype; cached
next to this file).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["available", "composite", "Tiles"]

try:
    import numba
    from numba import njit, prange

    # OpenMP first: thread-safe (the viewer renders from its own threads), and no warning about an old TBB found
    # beside it (numba's default order tries TBB first)
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
except ImportError:  # pragma: no cover - numba is a dependency; without it splats.rasterize uses the torch path
    numba = None


def available() -> bool:
    """numba imports (the fast path can run)."""
    return numba is not None


def _jit(fn):  # pragma: no cover - compiled on first call
    """numba's parallel compile, its machine code cached next to this file (or in the user's cache folder); where
    neither can be written, numba refuses to cache at decoration time, and the kernels compile in each process."""
    try:
        return njit(parallel=True, cache=True)(fn)
    except RuntimeError:
        return njit(parallel=True)(fn)


if numba is not None:

    @_jit
    def _forward(pairs, qmax, starts, bg, w, h, tile, nx, amax, tmin):  # pragma: no cover
        n_tiles = starts.shape[0] - 1
        color = np.zeros((h, w, 3), dtype=pairs.dtype)
        trans = np.ones((h, w), dtype=pairs.dtype)
        last = np.zeros((h, w), dtype=np.int32)
        for t in prange(n_tiles):
            s0, s1 = starts[t], starts[t + 1]
            x0, y0 = (t % nx) * tile, (t // nx) * tile
            for py in range(y0, min(y0 + tile, h)):
                for px in range(x0, min(x0 + tile, w)):
                    cx, cy = px + 0.5, py + 0.5
                    tr = 1.0
                    r, g, b = 0.0, 0.0, 0.0
                    n = 0
                    for k in range(s0, s1):
                        dx, dy = cx - pairs[k, 0], cy - pairs[k, 1]
                        q = pairs[k, 2] * dx * dx + 2.0 * pairs[k, 3] * dx * dy + pairs[k, 4] * dy * dy
                        if q > qmax[k]:
                            continue  # alpha < ALPHA_MIN, decided without the exponential
                        e = pairs[k, 5] * np.exp(-0.5 * q)
                        alpha = min(e, amax)
                        test = tr * (1.0 - alpha)
                        if test < tmin:
                            break
                        wgt = alpha * tr
                        r += wgt * pairs[k, 6]
                        g += wgt * pairs[k, 7]
                        b += wgt * pairs[k, 8]
                        tr = test
                        n = k - s0 + 1
                    color[py, px, 0] = r + tr * bg[0]
                    color[py, px, 1] = g + tr * bg[1]
                    color[py, px, 2] = b + tr * bg[2]
                    trans[py, px] = tr
                    last[py, px] = n
        return color, trans, last

    @_jit
    def _backward(pairs, qmax, starts, bg, w, h, tile, nx, amax, trans, last, g_rgb, g_alpha):  # pragma: no cover
        n_tiles = starts.shape[0] - 1
        d_pairs = np.zeros(pairs.shape, dtype=pairs.dtype)
        d_bg = np.zeros((n_tiles, 3), dtype=pairs.dtype)
        for t in prange(n_tiles):
            s0 = starts[t]
            x0, y0 = (t % nx) * tile, (t // nx) * tile
            for py in range(y0, min(y0 + tile, h)):
                for px in range(x0, min(x0 + tile, w)):
                    cx, cy = px + 0.5, py + 0.5
                    t_final = trans[py, px]
                    gr, gg, gb = g_rgb[py, px, 0], g_rgb[py, px, 1], g_rgb[py, px, 2]
                    ga = g_alpha[py, px]
                    d_bg[t, 0] += t_final * gr
                    d_bg[t, 1] += t_final * gg
                    d_bg[t, 2] += t_final * gb
                    tr = t_final
                    rr, rg, rb = bg[0], bg[1], bg[2]  # the normalised colour behind the current Gaussian
                    for k in range(s0 + last[py, px] - 1, s0 - 1, -1):
                        dx, dy = cx - pairs[k, 0], cy - pairs[k, 1]
                        a, b, c = pairs[k, 2], pairs[k, 3], pairs[k, 4]
                        q = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
                        if q > qmax[k]:
                            continue
                        gauss_v = np.exp(-0.5 * q)
                        e = pairs[k, 5] * gauss_v
                        alpha = min(e, amax)
                        one_m = 1.0 - alpha
                        tr = tr / one_m  # T before this Gaussian
                        wgt = alpha * tr
                        d_pairs[k, 6] += wgt * gr
                        d_pairs[k, 7] += wgt * gg
                        d_pairs[k, 8] += wgt * gb
                        c0, c1, c2 = pairs[k, 6], pairs[k, 7], pairs[k, 8]
                        d_alpha = tr * ((c0 - rr) * gr + (c1 - rg) * gg + (c2 - rb) * gb) + ga * t_final / one_m
                        rr = alpha * c0 + one_m * rr
                        rg = alpha * c1 + one_m * rg
                        rb = alpha * c2 + one_m * rb
                        if e >= amax:
                            continue  # clamped: alpha does not depend on the Gaussian here
                        d_pairs[k, 5] += d_alpha * gauss_v
                        gq = e * d_alpha
                        d_pairs[k, 0] += gq * (a * dx + b * dy)
                        d_pairs[k, 1] += gq * (b * dx + c * dy)
                        d_pairs[k, 2] += -0.5 * gq * dx * dx
                        d_pairs[k, 3] += -gq * dx * dy
                        d_pairs[k, 4] += -0.5 * gq * dy * dy
        return d_pairs, d_bg.sum(0)


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pairs, bg, qmax, starts, w, h, tile, nx, consts):  # noqa: D102
        color, trans, last = _forward(_np(pairs), _np(qmax), _np(starts), _np(bg), w, h, tile, nx, *consts)
        ctx.save_for_backward(pairs, bg, qmax, starts)
        ctx.kept = (torch.from_numpy(trans.copy()), torch.from_numpy(last), w, h, tile, nx, consts)
        return torch.from_numpy(color), torch.from_numpy(trans)

    @staticmethod
    def backward(ctx, g_color, g_trans):  # noqa: D102
        pairs, bg, qmax, starts = ctx.saved_tensors
        trans, last, w, h, tile, nx, (amax, _) = ctx.kept
        dtype = pairs.dtype
        g_color = torch.zeros(h, w, 3, dtype=dtype) if g_color is None else g_color.to(dtype)
        g_alpha = torch.zeros(h, w, dtype=dtype) if g_trans is None else -g_trans.to(dtype)  # alpha = 1 - trans
        d_pairs, d_bg = _backward(
            _np(pairs),
            _np(qmax),
            _np(starts),
            _np(bg),
            w,
            h,
            tile,
            nx,
            amax,
            _np(trans),
            _np(last),
            _np(g_color),
            _np(g_alpha),
        )
        return torch.from_numpy(d_pairs), torch.from_numpy(d_bg), None, None, None, None, None, None, None


@dataclass(frozen=True)
class Tiles:
    """Gaussians binned to tiles: `gauss` [M] int64 (tile by tile, each tile's front to back), `starts` [T + 1]
    int64 (tile t holds gauss[starts[t]:starts[t+1]]; tiles row-major, `nx` a row), on a `w` x `h` image cut into
    `tile` x `tile` tiles."""

    gauss: Tensor
    starts: Tensor
    w: int
    h: int
    tile: int
    nx: int


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    rgb: Tensor,
    background: Tensor,
    tiles: Tiles,
    *,
    alpha_min: float,
    alpha_max: float,
    t_min: float,
) -> tuple[Tensor, Tensor]:
    """Per-Gaussian `means2d` [N, 2] px, `conics` [N, 3] (a, b, c), `opacities` [N] (each >= alpha_min), `rgb`
    [N, 3], `background` [3] (one floating dtype, CPU), binned in `tiles` -> (rgb [H, W, 3] over the background,
    transmittance [H, W]); differentiable in the five float inputs (module doc). The kernels read one row per
    (tile, Gaussian) pair [M, 9] (gathered here, so each tile's rows are contiguous and its gradients land in its
    own rows: no two threads add to one number)."""
    if numba is None:
        raise RuntimeError("numba is not installed; expected splats.rasterize to take its torch path")
    dtype = means2d.dtype
    floats = (means2d, conics, opacities, rgb, background)
    if any(x.device.type != "cpu" or x.dtype != dtype for x in floats):
        raise ValueError(f"expected CPU tensors of one dtype, got {[(x.device.type, x.dtype) for x in floats]}")
    gauss, starts, w, h, tile, nx = tiles.gauss, tiles.starts, tiles.w, tiles.h, tiles.tile, tiles.nx
    if starts.shape[0] != nx * (-(-h // tile)) + 1:
        raise ValueError(f"expected starts [{nx * (-(-h // tile)) + 1}], got {list(starts.shape)}")
    gauss = gauss.long()
    pairs = torch.cat([means2d, conics, opacities[:, None], rgb], dim=-1)[gauss]  # [M, 9]
    with torch.no_grad():  # alpha < alpha_min exactly where q > 2 log(o / alpha_min)
        qmax = 2 * torch.log(opacities.detach()[gauss] / alpha_min)
    return _Composite.apply(
        pairs, background, qmax, starts.long(), int(w), int(h), int(tile), int(nx), (float(alpha_max), float(t_min))
    )
