"""Screened Poisson meshing for `stages.mesh` (`method="poisson"`): the surface through the points where the
training views' rays end, instead of a level set of the density.

Conventions: points are taken in the scene frame (where the field lives) and meshed in the grid frame of the
stage's box (`stages.mesh.grid`: the scene frame, or the user's frame with a bbox), so the stage's own path
(box-cut pieces, cleanup, decimation, colours, export, report) takes the mesh as it takes marching cubes'.
Distances in the report are in the grid frame.

Steps:
1. Points (`model.surface_points.gather_points`): the training cameras at the size the run trained at, rays
   rendered in passes until `points` rays gave a point (accumulated opacity >= `acc_threshold`) inside the box and,
   when the stage cuts a support plane (`stages.mesh.crop`), beyond its cut. A point lies at the ray's median depth
   (where it becomes half opaque: the surface it sees), as the auto threshold and the looked-at box read it.
2. Normals (`model.surface_points.surface_normals`): -grad sigma by central differences, step `normal_step` of the
   scene box's diagonal (a run with a signed distance: +grad f, the same differences), flipped where they face away
   from the camera whose ray gave the point.
3. Screened Poisson (Kazhdan & Hoppe 2013; pymeshlab `generate_surface_reconstruction_screened_poisson`) at octree
   depth `depth`, or by default the depth whose finest cells match the stage's `resolution`:
   ceil(log2(resolution)). Its octree spans the points' bounding cube, grown by 10 %.
4. Trim: Poisson closes every surface, and where no sample supports it (the back of a head on a wall, the side of
   an object no view saw) it invents a smooth hull. Its per-vertex density (the sample density the octree estimated
   there; pymeshlab's vertex quality, read as its vertex scalar) is lowest there; vertices below the `trim` quantile
   of it go, with their faces. The density falls off smoothly, so a quantile that takes the whole hull would eat
   into the surface; what is left of the hull, the skirts Poisson spreads past the edge of an open surface (the
   plaque's rim on the fox, a membrane to a picture frame beside it), is far from every point: vertices farther than
   `support` finest octree cells from the nearest point go too. On the fox a 5 % quantile alone leaves a picture
   frame joined to the plaque by such a membrane; with the 2-cell cut it is gone.
5. Crop: faces with a vertex outside the box (half a voxel of slack) or within the support plane's cut go, as the
   density method's zero padding and plane cut do.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from nerfpipe.data.errors import UserError
from nerfpipe.model.cameras import CameraPath, camera_path
from nerfpipe.model.surface_points import facing_share, gather_points, surface_normals
from nerfpipe.stages.mesh.crop import Plane
from nerfpipe.stages.mesh.field_access import as_np
from nerfpipe.stages.mesh.grid import Grid

__all__ = ["Poisson", "poisson_depth", "poisson_surface", "screened_poisson", "trim_and_crop", "unsupported"]


@dataclass(frozen=True, kw_only=True)
class Poisson:
    """What `method="poisson"` does (module doc)."""

    points: int = 300_000
    """Surface points to gather inside the box (rays rendered until this many gave one)."""
    depth: int | None = None
    """Octree depth (2^depth finest cells across the points' cube); None: ceil(log2(resolution))."""
    trim: float = 0.05
    """Drop the vertices whose Poisson density is below this quantile (0: keep Poisson's closed surface)."""
    support: float = 2.0
    """Drop the vertices farther than this many finest octree cells from every point (0: keep them)."""
    acc_threshold: float = 0.5
    """A ray gives a point when its accumulated opacity is at least this."""
    normal_step: float = 0.002
    """Central-difference step of the normals, as a fraction of the scene box's diagonal."""
    samples_per_node: float = 1.5
    """Poisson: minimum samples per octree node (more smooths noisy points)."""
    point_weight: float = 4.0
    """Poisson: screening weight, how closely the surface keeps to the points (0: plain Poisson)."""
    seed: int = 0
    """Seed of the ray passes' order."""
    threads: int = 0
    """Poisson's threads; 0: torch's thread count (OMP_NUM_THREADS)."""

    def __post_init__(self) -> None:
        if self.points < 100:
            raise UserError(f"poisson.points: expected at least 100, got {self.points}")
        if self.depth is not None and not 4 <= self.depth <= 14:
            raise UserError(f"poisson.depth: expected 4..14 or None, got {self.depth}")
        if not 0 <= self.trim < 1:
            raise UserError(f"poisson.trim: expected a quantile in [0, 1), got {self.trim}")
        if not self.support >= 0:
            raise UserError(f"poisson.support: expected 0 (off) or a number of octree cells > 0, got {self.support}")
        if not 0 < self.acc_threshold <= 1:
            raise UserError(f"poisson.acc_threshold: expected a value in (0, 1], got {self.acc_threshold}")
        if not 0 < self.normal_step < 1:
            raise UserError(f"poisson.normal_step: expected a fraction in (0, 1), got {self.normal_step}")


def poisson_depth(params: Poisson, resolution: int) -> int:
    """The octree depth: `params.depth`, or ceil(log2(resolution)) (module doc)."""
    return params.depth if params.depth is not None else max(4, math.ceil(math.log2(resolution) - 1e-9))


def screened_poisson(
    points: np.ndarray, normals: np.ndarray, *, depth: int, params: Poisson
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poisson surface of oriented points [N, 3] (unit normals [N, 3], outward): (verts [V, 3] float64,
    faces [F, 3] int64, density [V] float64: pymeshlab's vertex scalar (quality))."""
    import pymeshlab

    if points.shape != normals.shape or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"expected points, normals [N, 3], got {points.shape}, {normals.shape}")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(
        pymeshlab.Mesh(vertex_matrix=np.asarray(points, np.float64), v_normals_matrix=np.asarray(normals, np.float64))
    )
    threads = params.threads or torch.get_num_threads()
    ms.generate_surface_reconstruction_screened_poisson(
        depth=depth,
        samplespernode=params.samples_per_node,
        pointweight=params.point_weight,
        preclean=True,
        threads=max(1, threads),
    )
    m = ms.current_mesh()
    return (
        m.vertex_matrix().astype(np.float64),
        m.face_matrix().astype(np.int64),
        m.vertex_scalar_array().astype(np.float64),
    )


def trim_and_crop(verts: np.ndarray, faces: np.ndarray, keep_vertex: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Keep the faces whose three vertices are all kept (`keep_vertex` [V] bool), drop unused vertices:
    (verts [V', 3], faces [F', 3], faces removed)."""
    keep_face = keep_vertex[faces].all(axis=1)
    used = np.zeros(len(verts), bool)
    used[faces[keep_face].ravel()] = True
    index = np.cumsum(used) - 1
    return verts[used], index[faces[keep_face]], int((~keep_face).sum())


def unsupported(verts: np.ndarray, points: np.ndarray, distance: float) -> np.ndarray:
    """[V] bool: the vertex [V, 3] is farther than `distance` from every point [N, 3]."""
    from scipy.spatial import cKDTree

    return cKDTree(points).query(verts, distance_upper_bound=distance)[0] > distance


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points [N, 3] mapped by the 4x4 affine m."""
    return x @ m[:3, :3].T + m[:3, 3]


def _oriented_points(
    trained: Any, cams: CameraPath, keep: Callable[[np.ndarray], np.ndarray], params: Poisson, device: torch.device
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Steps 1-2 of the module doc: (points [N, 3] scene frame, outward unit normals [N, 3], report entries)."""
    g = gather_points(
        trained,
        cams,
        target=params.points,
        acc_threshold=params.acc_threshold,
        keep=keep,
        seed=params.seed,
        depth="median",
    )
    if len(g.points) < 100:
        raise UserError(
            f"{len(g.points)} of {g.rays} training rays end inside the box (accumulated opacity >= "
            f"{params.acc_threshold}): too few surface points for Poisson (need 100); use method density"
        )
    box = as_np(trained.aabb).reshape(2, 3)
    step = params.normal_step * float(np.linalg.norm(box[1] - box[0]))
    normals, from_gradient, rule = surface_normals(
        trained, g.points, g.dirs, step, device, stage="mesh --method poisson"
    )
    facing = facing_share(normals[from_gradient], g.dirs[from_gradient])
    flip = np.einsum("ij,ij->i", normals, g.dirs.astype(np.float64)) > 0  # away from the camera that saw it
    normals[flip] *= -1
    info = {
        "points_gathered": len(g.points),
        "rays": g.rays,
        "opaque_rays": g.opaque,
        "rays_outside_box": g.outside,
        "passes": g.passes,
        "point_depth": "median (opacity 0.5)",
        "normal_rule": rule.words,
        "normal_step_scene": step,
        "normals_from_view_direction": int((~from_gradient).sum()),
        "normals_flipped": int(flip.sum()),
        "normals_facing_camera_before_flip": facing,
    }
    return g.points, normals, info


def _trimmed(
    verts: np.ndarray, faces: np.ndarray, density: np.ndarray, points: np.ndarray, cell: float, params: Poisson
) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Step 4 of the module doc: (verts, faces, the report's steps)."""
    level = float(np.quantile(density, params.trim)) if params.trim > 0 and len(density) else -math.inf
    verts, faces, removed = trim_and_crop(verts, faces, density >= level)
    steps = [
        {
            "step": "trim_low_density",
            "vertices": len(verts),
            "faces": len(faces),
            "removed_faces": removed,
            "quantile": params.trim,
            "density_below": level,
        }
    ]
    if params.support > 0 and len(verts):
        verts, faces, removed = trim_and_crop(verts, faces, ~unsupported(verts, points, params.support * cell))
        steps.append(
            {
                "step": "trim_unsupported",
                "vertices": len(verts),
                "faces": len(faces),
                "removed_faces": removed,
                "farther_than": params.support * cell,
            }
        )
    return verts, faces, steps


def poisson_surface(
    trained: Any,
    grid: Grid,
    plane: Plane | None,
    keep_beyond: float,
    *,
    resolution: int,
    params: Poisson,
    device: torch.device,
    lap: Callable[[str, float], float],
) -> tuple[np.ndarray, np.ndarray, list[dict], dict]:
    """The trimmed Poisson surface in `grid`'s box (module doc): (verts [V, 3] grid frame, faces [F, 3] int64,
    the report's steps, the report's `method` entry). `plane`: the support plane to cut (`keep_beyond` scene
    units of it kept away), or None; `lap(name, t0) -> now` records each step's time."""
    t = time.perf_counter()
    grid_from_scene = np.linalg.inv(grid.scene_from_grid)
    lo, hi = grid.lo - 0.5 * grid.h, grid.hi + 0.5 * grid.h

    def inside(points_scene: np.ndarray, points_grid: np.ndarray | None = None) -> np.ndarray:  # [K, 3] -> [K]
        p = _apply(grid_from_scene, points_scene) if points_grid is None else points_grid
        ok = ((p >= lo) & (p <= hi)).all(axis=1)
        return ok & (plane.distance(points_scene) > keep_beyond) if plane is not None else ok

    downscale = float(getattr(trained, "downscale", 1.0))
    cams = camera_path(trained.scene, "train", downscale=downscale)
    points, normals, points_info = _oriented_points(trained, cams, inside, params, device)
    t = lap("points", t)

    points_g = _apply(grid_from_scene, points)
    normals_g = normals @ np.linalg.inv(grid_from_scene[:3, :3])  # covectors: the inverse transpose
    normals_g /= np.maximum(np.linalg.norm(normals_g, axis=1, keepdims=True), np.finfo(np.float64).tiny)
    depth = poisson_depth(params, resolution)
    cell = 1.1 * float(np.ptp(points_g, axis=0).max()) / 2**depth  # PoissonRecon's cube: the points' box x 1.1
    verts, faces, density = screened_poisson(points_g, normals_g, depth=depth, params=params)
    steps: list[dict] = [{"step": "screened_poisson", "vertices": len(verts), "faces": len(faces)}]
    verts, faces, trim_steps = _trimmed(verts, faces, density, points_g, cell, params)
    steps += trim_steps
    verts, faces, removed = trim_and_crop(verts, faces, inside(_apply(grid.scene_from_grid, verts), verts))
    steps.append({"step": "crop_to_box", "vertices": len(verts), "faces": len(faces), "removed_faces": removed})
    lap("poisson", t)
    depth_rule = "given" if params.depth is not None else "ceil(log2(resolution))"
    info = {
        "name": "poisson",
        **asdict(params),
        "octree_depth": depth,
        "depth_rule": depth_rule,
        "octree_cell": cell,
        **points_info,
    }
    return verts, faces, steps, info
