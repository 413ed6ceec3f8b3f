"""Density sampling on a regular grid for `stages.mesh`, coarse-to-fine, with bounded memory.

Conventions:
- A `Grid` holds sample points `lo + index * h` (index 0 .. shape - 1 per axis) in the *grid frame*, which is
  the scene frame or the user's frame; `scene_from_grid` (4x4 similarity) maps them to the scene frame where
  the field is queried. Voxels are cubes of side `h`; `shape - 1` is a multiple of `stride` on every axis.
- The returned volume is float32 `[n0 + 2, n1 + 2, n2 + 2]`: the samples, padded by one layer of zeros, so a
  surface that reaches the box is capped there (the mesh is closed at the crop) and marching cubes sees the
  box boundary. Index `i` of the volume is sample `i - 1`.
- Coarse-to-fine (stride s > 1): every s-th sample is evaluated first; a block of s^3 voxels is evaluated in
  full when its 8 coarse corners straddle the level (or it touches the box with a corner above it), dilated
  by one block. Other samples take the value of the nearest coarse sample, which lies on the same side of the
  level, so they produce no surface. A feature thinner than ~s voxels that no coarse sample sees is missed:
  keep `s * h` small (the stage picks s so the coarse grid has ~128 cells on the long axis).
- Memory: the volume (4 bytes per sample) plus one chunk of points; never a float64 copy of the volume.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.ndimage
import torch

__all__ = ["Grid", "make_grid", "sample_volume", "DensityFn"]

DensityFn = Callable[[torch.Tensor], torch.Tensor]  # x [N, 3] float32 scene frame -> sigma [N]


@dataclass(frozen=True, kw_only=True)
class Grid:
    """Sample positions of the density volume."""

    lo: np.ndarray
    """[3] first sample, grid frame."""
    h: float
    """Voxel side, grid-frame units."""
    shape: tuple[int, int, int]
    """Samples per axis (cells + 1)."""
    stride: int
    """Coarse stride (1: evaluate every sample)."""
    scene_from_grid: np.ndarray
    """[4, 4] grid frame -> scene frame (a similarity)."""

    @property
    def hi(self) -> np.ndarray:  # [3] last sample
        return self.lo + (np.asarray(self.shape) - 1) * self.h

    @property
    def voxel(self) -> float:
        """Voxel side in scene units (`scene_from_grid` is a similarity)."""
        return self.h * float(np.cbrt(abs(np.linalg.det(self.scene_from_grid[:3, :3]))))


def make_grid(
    lo: np.ndarray, hi: np.ndarray, resolution: int, stride: int, scene_from_grid: np.ndarray | None = None
) -> Grid:
    """Cubic voxels with `resolution` cells along the box's longest side; other sides rounded up to whole
    coarse blocks and centred on the box."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    extent = hi - lo
    h = float(extent.max()) / resolution
    cells = np.maximum(np.ceil(extent / h - 1e-6), 1).astype(int)
    cells = (np.ceil(cells / stride) * stride).astype(int)
    centre = 0.5 * (lo + hi)
    start = centre - 0.5 * cells * h
    m = np.eye(4) if scene_from_grid is None else np.asarray(scene_from_grid, np.float64)
    return Grid(lo=start, h=h, shape=tuple(int(c) + 1 for c in cells), stride=int(stride), scene_from_grid=m)


class _Evaluator:
    """Batches grid points into chunks for the density function; scatters the results back."""

    def __init__(self, density: DensityFn, grid: Grid, device: torch.device, chunk: int):
        self.density, self.grid, self.device, self.chunk = density, grid, device, chunk
        m = grid.scene_from_grid
        # sample index -> scene frame, float32 (indices < 2^24 and one rounding per product: ~1e-7 relative)
        self.rot = torch.tensor(m[:3, :3] * grid.h, dtype=torch.float32, device=device)
        self.off = torch.tensor(m[:3, :3] @ grid.lo + m[:3, 3], dtype=torch.float32, device=device)
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []  # (ijk [M, 3] int, flat index in `out`)
        self.count = 0
        self.evaluated = 0

    def add(self, ijk: np.ndarray, dest: np.ndarray, out: np.ndarray) -> None:
        self.pending.append((ijk, dest))
        self.count += len(ijk)
        if self.count >= self.chunk:
            self.flush(out)

    def flush(self, out: np.ndarray) -> None:
        if not self.pending:
            return
        ijk = np.concatenate([p[0] for p in self.pending])
        dest = np.concatenate([p[1] for p in self.pending])
        self.pending, self.count = [], 0
        x = torch.from_numpy(ijk).to(self.device, torch.float32) @ self.rot.T + self.off  # [M, 3]
        sigma = self.density(x).reshape(-1).float()
        if bool(torch.isnan(sigma).any()):
            raise ValueError(f"the field returned NaN density at {int(torch.isnan(sigma).sum())} grid points")
        sigma = sigma.clamp(max=float(np.finfo(np.float32).max)).cpu().numpy()  # inf: densest finite value
        out.reshape(-1)[dest] = sigma
        self.evaluated += len(ijk)


def _coarse(density: DensityFn, grid: Grid, device: torch.device, chunk: int) -> tuple[np.ndarray, int]:
    """Samples at every `stride`-th index: [m0 + 1, m1 + 1, m2 + 1] float32."""
    s = grid.stride
    shape = tuple((n - 1) // s + 1 for n in grid.shape)
    out = np.zeros(shape, np.float32)
    ev = _Evaluator(density, grid, device, chunk)
    jj, kk = np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij")
    jj, kk = jj.reshape(-1), kk.reshape(-1)
    plane = shape[1] * shape[2]
    for a in range(shape[0]):
        ijk = np.stack([np.full(plane, a * s), jj * s, kk * s], axis=1).astype(np.int32)
        ev.add(ijk, a * plane + np.arange(plane), out)
    ev.flush(out)
    return out, ev.evaluated


def _refine_blocks(coarse: np.ndarray, level: float, band: float = 1.0) -> np.ndarray:
    """Blocks [m0, m1, m2] to evaluate in full: corners straddle the band [level / band, level * band] (some above
    its bottom, not all above its top), or a box-face corner is above its bottom."""
    inside = coarse > level / band
    above = coarse > level * band
    boundary = np.zeros_like(inside)
    boundary[[0, -1]] = True
    boundary[:, [0, -1]] = True
    boundary[:, :, [0, -1]] = True
    cap = inside & boundary
    corners = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]

    def corner(arr: np.ndarray, a: int, b: int, c: int) -> np.ndarray:
        return arr[a : arr.shape[0] - 1 + a, b : arr.shape[1] - 1 + b, c : arr.shape[2] - 1 + c]

    any_in = np.logical_or.reduce([corner(inside, *o) for o in corners])
    all_in = np.logical_and.reduce([corner(above, *o) for o in corners])
    any_cap = np.logical_or.reduce([corner(cap, *o) for o in corners])
    selected = (any_in & ~all_in) | any_cap
    return scipy.ndimage.binary_dilation(selected, structure=np.ones((3, 3, 3), bool))


def _expand_blocks(sel: np.ndarray, s: int, axis: int) -> np.ndarray:
    """Per-block flags -> per-sample flags along `axis` (m blocks -> m * s + 1 samples): a sample is flagged
    when a block holding it is (samples on a block face belong to both blocks)."""
    sel = np.moveaxis(sel, axis, 0)
    m = sel.shape[0]
    out = np.concatenate([np.repeat(sel, s, axis=0), sel[-1:]])
    out[s : m * s : s] |= sel[:-1]
    return np.moveaxis(out, 0, axis)


def _nearest_upsample(coarse: np.ndarray, s: int, n: int, axis: int) -> np.ndarray:
    """Each of n fine samples along `axis` takes the value of the nearest coarse sample (index rint(f / s))."""
    counts = np.bincount(np.rint(np.arange(n) / s).astype(int), minlength=coarse.shape[axis])
    return np.repeat(coarse, counts, axis=axis)


def sample_volume(
    density: DensityFn,
    grid: Grid,
    level: float | None,
    *,
    device: torch.device,
    chunk: int = 1 << 18,
    band: float = 1.0,
) -> tuple[np.ndarray, dict]:
    """Density on `grid` as a zero-padded float32 volume (see module doc), and sampling statistics.

    `level` drives the coarse-to-fine refinement (blocks straddling [level / band, level * band]: a band > 1 when
    the final level is not known yet); with `level=None` or `stride=1` every sample is evaluated.
    Statistics: {evaluated, samples, refined_blocks, blocks, min, max} (min/max over evaluated samples).
    """
    n0, n1, n2 = grid.shape
    s = grid.stride
    vol = np.zeros((n0 + 2, n1 + 2, n2 + 2), np.float32)
    evaluated = 0
    if s > 1 and level is not None:
        coarse, evaluated = _coarse(density, grid, device, chunk)
        blocks = _refine_blocks(coarse, level, band)
    else:
        coarse, blocks = None, None
    ev = _Evaluator(density, grid, device, chunk)
    s1, s2 = vol.shape[1], vol.shape[2]
    fills: dict[int, np.ndarray] = {}  # coarse plane -> its nearest-upsampled [n1, n2] plane
    todo: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # blocks key -> (jk [M, 2] int32, flat offsets [M])

    def samples_to_evaluate(key: tuple) -> tuple[np.ndarray, np.ndarray]:
        if key not in todo:
            if blocks is None:
                need = np.ones((n1, n2), bool)
            else:
                sel = blocks[key[0]] | blocks[key[1]]  # [m1, m2]
                need = _expand_blocks(_expand_blocks(sel, s, 0), s, 1)  # [n1, n2]
            j, k = np.nonzero(need)
            todo.clear()  # keys repeat only for consecutive planes
            todo[key] = (np.stack([j, k], axis=1).astype(np.int32), (j + 1) * s2 + (k + 1))
        return todo[key]

    for i in range(n0):
        key: tuple = (0, 0)
        if coarse is not None:
            c = int(round(i / s))
            if c not in fills:
                fills.clear()
                fills[c] = _nearest_upsample(_nearest_upsample(coarse[c], s, n1, 0), s, n2, 1)
            vol[i + 1, 1:-1, 1:-1] = fills[c]
            own = min(i // s, blocks.shape[0] - 1)
            key = (own, i // s - 1 if (i % s == 0 and i > 0) else own)
        jk, offsets = samples_to_evaluate(key)
        if len(jk):
            ijk = np.concatenate([np.full((len(jk), 1), i, np.int32), jk], axis=1)
            ev.add(ijk, (i + 1) * s1 * s2 + offsets, vol)
    ev.flush(vol)
    evaluated += ev.evaluated
    inner = vol[1:-1, 1:-1, 1:-1]
    stats = {
        "samples": int(n0 * n1 * n2),
        "evaluated": int(evaluated),
        "blocks": int(blocks.size) if blocks is not None else None,
        "refined_blocks": int(blocks.sum()) if blocks is not None else None,
        "min": float(inner.min()),
        "max": float(inner.max()),
    }
    return vol, stats
