"""The density method's surface for `stages.mesh`: the level (or levels), the density on the grid, marching cubes.

The level comes from `stages.mesh.threshold` ("auto": by region, "global": one median level, or a given number).
With levels by region, two passes:
1. the grid samples the density divided by the levels of the rays' own crossings (`LevelField.normalise`),
   refining coarse blocks that straddle REFINE_BAND around 1 (the final level is not known yet);
2. the sampled volume is read (trilinearly, as marching cubes reads it) at the crossing points in the meshed region,
   and the same rule on those values gives a second level field, which the volume is divided by. Why: marching
   cubes sees the grid's interpolation of the density, not the ray's finer samples; on a noisy field the grid's
   values at the crossings spread more than the rays', and the rays' levels alone leave parts of the field's surface
   unmeshed (docs/MEASUREMENTS.md, "Meshes that keep what the field shows").
Marching cubes then runs at 1, so the surface lies at each region's own level, on the volume closed by grey closings
along each axis (`close_gaps`: a max filter then a min filter over `Config.close_gaps` voxels of a line, 3 by default)
whatever the level. They fill the gaps up to 2 voxels thin across an axis that a grid field's line factors leave
(TensoRF's factors along one axis dip to ~0 at isolated samples: `make demo`'s field has horizontal planes of density ~0
through its objects, invisible in renders where a ray crosses them in one step, that cut every object into stacked
closed slices: 12 pieces, the mesh's check suspect), and leave steps and bumps where they were: only a dip narrower than
the window moves, real grooves that thin included. Measured in docs/MEASUREMENTS.md ("Meshes that keep what the field
shows"): the demo's mesh in one piece, the analytic stand-in's Chamfer +0.03 % of the diagonal at 256^3 (its groove
between ball and box: +0.13 % at 96^3). Faces wind counter-clockwise seen from outside (the side of lower density).
Vertices come back in the grid's frame (`stages.mesh.grid`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.stages.mesh.crop import Plane, cut_density
from nerfpipe.stages.mesh.grid import DensityFn, Grid, sample_volume
from nerfpipe.stages.mesh.threshold import Crossings, global_level, level_field, local_levels

__all__ = ["Region", "Level", "choose_level", "close_gaps", "density_surface", "REFINE_BAND"]

REFINE_BAND = 3.0
"""Pass 1 refines the blocks whose coarse samples straddle [1 / REFINE_BAND, REFINE_BAND] of the first levels."""


@dataclass(frozen=True)
class Region:
    """What is meshed: the grid, the support plane cut away (`keep_beyond` of it kept away; None: no plane), and
    how the box was found (for messages)."""

    grid: Grid
    plane: Plane | None
    keep_beyond: float
    how: str

    def inside(self, p: np.ndarray) -> np.ndarray:
        """[N] bool for scene points [N, 3]: in the grid's box and, with a support plane, beyond its cut."""
        grid_from_scene = np.linalg.inv(self.grid.scene_from_grid)
        q = p @ grid_from_scene[:3, :3].T + grid_from_scene[:3, 3]
        ok = ((q >= self.grid.lo) & (q <= self.grid.hi)).all(axis=1)
        return ok & (self.plane.distance(p) > self.keep_beyond) if self.plane is not None else ok


class Level:
    """The level the stage meshes at: `iso` on the function `fn` (the density, or the density over the local
    levels), `value` the level the report names (the median with levels by region), `info` the report's entry."""

    def __init__(self, fn: DensityFn, iso: float, value: float, info: dict, by_region: bool):
        self.fn, self.iso, self.value, self.info, self.by_region = fn, iso, value, info, by_region


def choose_level(threshold: float | str, density: DensityFn, crossings: Crossings, aabb: np.ndarray) -> Level:
    """The level for `threshold` ("auto", "global" or a number; `stages.mesh.threshold`'s rules)."""
    if threshold == "auto":
        field, median, info = local_levels(crossings, aabb)
        if field is None:  # too few crossings: the global rule's fallback level
            return Level(density, median, median, info, False)
        return Level(field.normalise(density), 1.0, median, info, True)
    if threshold == "global":
        level, info = global_level(crossings, aabb)
        return Level(density, level, level, info, False)
    value = float(threshold)
    return Level(density, value, value, {"rule": "given (threshold)"}, False)


def close_gaps(vol: np.ndarray, size: int) -> np.ndarray:
    """`vol` [n0, n1, n2] after a grey closing over `size` voxels along each axis in turn (module doc): a dip
    narrower than `size` along an axis is lifted to the lower of its two sides; a profile with no dip (a step, a
    bump) is left as it was, up to the volume's faces (beyond them lies -inf: a face's voxel is never a dip, the
    pad of zeros that closes the mesh at the box stays). size 1: `vol` itself."""
    import scipy.ndimage

    for axis in range(3) if size > 1 else ():
        pad = [(0, 0)] * 3
        pad[axis] = (size, size)
        window = [1, 1, 1]
        window[axis] = size
        closed = scipy.ndimage.grey_closing(np.pad(vol, pad, constant_values=-np.inf), size=tuple(window))
        vol = closed[tuple(slice(size, -size) if a == axis else slice(None) for a in range(3))]
    return vol


def _marching_cubes(vol: np.ndarray, level: float, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    from skimage.measure import marching_cubes

    # "ascent": density grows into the object, so faces wind counter-clockwise seen from outside
    verts, faces, _, _ = marching_cubes(vol, level=level, gradient_direction="ascent", allow_degenerate=False)
    verts = grid.lo + (verts.astype(np.float64) - 1.0) * grid.h  # volume index -> grid frame (pad offset)
    return verts, faces.astype(np.int64)


def _level_checks(run_dir: Any, given: bool, level: Level, stats: dict, grid: Grid, how: str) -> None:
    lo, hi = stats["min"], stats["max"]
    where = f"box {np.round(grid.lo, 4).tolist()}..{np.round(grid.hi, 4).tolist()} ({how})"
    if hi <= 0:
        raise UserError(f"{run_dir}: the field is empty (density 0 everywhere in the {where}); nothing to mesh")
    if given and not lo < level.iso < hi:
        raise UserError(
            f"--threshold {level.iso:g} is outside the sampled density range [{lo:g}, {hi:g}] of the {where}; "
            "pick a value inside it or use --threshold auto"
        )
    said = "the levels by region" if level.by_region else f"the auto threshold {level.iso:g}"
    unit = " times the local level" if level.by_region else ""
    if level.iso >= hi:
        raise UserError(
            f"{run_dir}: the field is empty at {said} (max density {hi:g}{unit} in the {where}); nothing to mesh"
        )
    if level.iso <= lo:
        raise UserError(
            f"{run_dir}: the whole {where} is denser than {said} (min {lo:g}{unit}); give --bbox or --threshold"
        )


def _relevel(vol: np.ndarray, grid: Grid, crossings: Crossings, inside, aabb: np.ndarray) -> dict:
    """Pass 2 (module doc): divide `vol` (in place) by the level field of its own values at the crossings inside
    the meshed region (`inside(points_scene) -> mask`). -> the report's figures."""
    import scipy.ndimage

    points = crossings.points
    points = points[inside(points)]
    grid_from_scene = np.linalg.inv(grid.scene_from_grid)
    index = ((points @ grid_from_scene[:3, :3].T + grid_from_scene[:3, 3]) - grid.lo) / grid.h + 1.0  # pad offset
    values = scipy.ndimage.map_coordinates(vol, index.T, order=1, mode="nearest")
    kept = values > 0  # a crossing the support plane's cut emptied says nothing of the level
    if kept.sum() < 16:
        return {"pass_2": f"skipped: {int(kept.sum())} crossings in the meshed region"}
    field, figures = level_field(points[kept], values[kept], aabb)
    m = grid.scene_from_grid
    n1, n2 = vol.shape[1], vol.shape[2]
    jj, kk = np.meshgrid(np.arange(n1) - 1.0, np.arange(n2) - 1.0, indexing="ij")
    for i in range(vol.shape[0]):  # plane by plane: the volume's positions never all at once
        g = np.stack([np.full(jj.size, i - 1.0), jj.ravel(), kk.ravel()], axis=1) * grid.h + grid.lo
        x = torch.as_tensor(g @ m[:3, :3].T + m[:3, 3], dtype=torch.float32)
        vol[i] /= field(x).numpy().reshape(n1, n2)
    return {"pass_2": {"crossings": int(kept.sum()), **figures}}


def density_surface(
    level: Level,
    region: Region,
    *,
    crossings: Crossings | None,
    aabb: np.ndarray,
    run_dir: Any,
    given: bool,
    device: torch.device,
    chunk: int,
    close: int,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Marching cubes of `level` on the region's grid (its support plane cut first; with levels by region the second
    pass on the crossings in the meshed region; the volume closed over `close` voxels, `close_gaps`) -> (verts [V, 3]
    grid frame, faces [F, 3] int64, the sampling statistics). UserError where nothing is left to mesh."""
    grid, plane, keep_beyond, how = region.grid, region.plane, region.keep_beyond, region.how
    fn = cut_density(level.fn, plane, keep_beyond) if plane is not None else level.fn
    band = REFINE_BAND if level.by_region else 1.0
    vol, stats = sample_volume(fn, grid, level.iso, device=device, chunk=chunk, band=band)
    if level.by_region:
        level.info.update(_relevel(vol, grid, crossings, region.inside, aabb))
        inner = vol[1:-1, 1:-1, 1:-1]
        stats.update(min=float(inner.min()), max=float(inner.max()))
    _level_checks(run_dir, given, level, stats, grid, how)
    verts, faces = _marching_cubes(close_gaps(vol, close), level.iso, grid)
    return verts, faces, stats
