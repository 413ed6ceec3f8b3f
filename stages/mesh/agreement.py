"""The mesh against the field, seen from the training cameras: the self-check's `missed_surface` and
`extra_surface` (`stages.mesh.checks`).

The level's rays (`threshold.Crossings`: a pixel lattice over every training view, marched through the field to
where each becomes half opaque) are used again, so this costs no field query:
For CHECK_VIEWS spread training views the mesh's depth is rasterised at the lattice's pixels
(`texture_views.depth_buffer`, the view's intrinsics scaled by the lattice's stride so that its pixel centres are the
lattice's), and along each of their rays:
- `missed`: the field's surface (the crossing point) lies in the meshed region (the grid's box, on the cameras' side
  of a support plane's cut), the ray meets no mesh within `tol` of it or before it (no face, or the nearest one
  more than `tol` beyond: the objects missing, a disk where the field shows a cylinder on it, a hole through an
  object), and no mesh surface lies within NEAR_VOXELS voxels of the point in space (points sampled on the mesh
  every half voxel): a ray that grazes an edge becomes half opaque through the density's soft rim a voxel or two
  outside the level set, where the ray itself never meets the mesh; that surface is not missing. Nor is the field's
  surface within NEAR_VOXELS of a piece the stage cut away on purpose (`cut_away`: the looked-at box's pieces at its
  edge, `crop.drop_box_cut_pieces`): those rays count in `cut_away`, not in `field_surface`.
- `extra`: the ray hits the mesh more than `tol` before the field's crossing, or where the field stays nearly
  transparent (opacity through the box below EMPTY_OPACITY): fog, floaters or a fattened surface meshed.
`tol` = TOL_VOXELS voxels of the grid + TOL_DEPTH of the depth along the ray.

Conventions: scene frame; the mesh's vertices [V, 3] float64 and faces [F, 3] int64 in it; `inside(points [N, 3])
-> bool [N]` says what the mesh covers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.stages.mesh.texture_views import depth_buffer, spread_views
from nerfpipe.stages.mesh.threshold import Crossings

__all__ = [
    "TOL_VOXELS",
    "TOL_DEPTH",
    "EMPTY_OPACITY",
    "NEAR_VOXELS",
    "CHECK_VIEWS",
    "Agreement",
    "mesh_agreement",
    "surface_samples",
]

TOL_VOXELS = 4.0
"""Depth tolerance along a ray, in voxels of the meshing grid."""
TOL_DEPTH = 0.01
"""... plus this fraction of the field's depth along the ray."""
NEAR_VOXELS = 2.0
"""A field surface point with mesh this near (voxels, in space) is not missed."""
EMPTY_OPACITY = 0.25
"""A ray whose opacity through the whole box stays below this shows nothing there: a mesh it hits is extra."""
CHECK_VIEWS = 12
"""Training views rasterised for the extra test (spread out, `texture_views.spread_views`): a 300k-face mesh costs
~0.4 s a view on the shared 2-core machine."""


@dataclass(frozen=True, kw_only=True)
class Agreement:
    """What the mesh and the field show along the level's rays (module doc)."""

    field_surface: int
    """Rays of the rasterised views whose field surface lies in the meshed region."""
    missed: int
    """... of which the mesh lacks that surface (module doc)."""
    mesh_surface: int
    """Rays of the rasterised views that hit the mesh."""
    extra: int
    """... of which the mesh is more than tol before the field's surface, or where the field shows nothing."""
    views: int
    """Training views rasterised (a view whose camera the mesh surrounds is skipped)."""
    cut_away: int = 0
    """Rays whose field surface lies on a piece the stage removed on purpose (module doc): not counted above."""
    tol: float
    """The tolerance's voxel part, scene units."""

    @property
    def missed_share(self) -> float:
        return self.missed / self.field_surface if self.field_surface else 0.0

    @property
    def extra_share(self) -> float:
        return self.extra / self.mesh_surface if self.mesh_surface else 0.0

    def report(self) -> dict:
        return {
            "rays_with_field_surface": self.field_surface,
            "missed": self.missed,
            "rays_hitting_mesh": self.mesh_surface,
            "extra": self.extra,
            "views": self.views,
            "on_pieces_cut_away": self.cut_away,
            "tolerance": f"along a ray {TOL_VOXELS:g} voxels ({self.tol:.4g} scene units) + {TOL_DEPTH:.0%} of the "
            f"depth; in space {NEAR_VOXELS:g} voxels",
        }


def surface_samples(verts: np.ndarray, faces: np.ndarray, spacing: float, seed: int = 0) -> np.ndarray:
    """Points [N, 3] on the mesh, area-uniform, about one per spacing^2 of area (at least the vertices' count,
    at most 2M), the vertices included; deterministic."""
    tri = verts[faces]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = int(np.clip(area.sum() / spacing**2, len(verts), 2_000_000))
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(faces), n, p=area / area.sum()) if area.sum() > 0 else np.zeros(0, np.int64)
    u, v = rng.random((2, len(pick)))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[pick]
    return np.concatenate([verts, t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])])


def _lattice_intrinsics(intr: Intrinsics, stride: int) -> Intrinsics:
    """Intrinsics whose pixel centres (k + 0.5) are the full-size lattice's ((k + 0.5) * stride)."""
    return Intrinsics(
        w=-(-intr.w // stride),
        h=-(-intr.h // stride),
        fx=intr.fx / stride,
        fy=intr.fy / stride,
        cx=intr.cx / stride,
        cy=intr.cy / stride,
        k1=intr.k1,
        k2=intr.k2,
        k3=intr.k3,
        p1=intr.p1,
        p2=intr.p2,
    )


def mesh_agreement(
    verts: np.ndarray,
    faces: np.ndarray,
    crossings: Crossings,
    scene,
    inside: Callable[[np.ndarray], np.ndarray],
    voxel: float,
    max_views: int = CHECK_VIEWS,
    cut_away: tuple[np.ndarray, np.ndarray] | None = None,
) -> Agreement:
    """Compare the mesh (scene frame) with the field along the crossings' rays of `max_views` spread-out training
    views (module doc); `voxel` the grid's voxel side in scene units; `cut_away` the pieces removed on purpose
    (vertices [V, 3] in the scene frame, faces [K, 3]; None: none)."""
    from scipy.spatial import cKDTree

    tol0 = TOL_VOXELS * voxel
    frames = np.unique(crossings.frame)
    if len(faces) == 0 or len(frames) == 0:
        seen = int(inside(crossings.points).sum()) if crossings.crossed.any() else 0
        return Agreement(field_surface=seen, missed=seen, mesh_surface=0, extra=0, views=0, tol=tol0)
    tree = cKDTree(surface_samples(verts, faces, 0.5 * voxel))
    cut_tree = None
    if cut_away is not None and len(cut_away[1]):
        cut_tree = cKDTree(surface_samples(*cut_away, 0.5 * voxel))
    c2ws = np.stack([np.asarray(scene.frames[int(i)].world_from_cam, np.float64) for i in frames])
    field_surface = missed = hits = extra = views = on_cut = 0
    for i in frames[spread_views(c2ws, max_views)]:
        rows = np.flatnonzero(crossings.frame == i)
        stride = crossings.stride[int(i)]
        intr = _lattice_intrinsics(scene.frame_intrinsics(int(i)), stride)
        c2w = np.asarray(scene.frames[int(i)].world_from_cam, np.float64)
        zbuf = depth_buffer(verts, faces, c2w, intr)
        if zbuf is None:
            continue
        views += 1
        col = np.floor(crossings.pixel[rows, 0] / stride).astype(int).clip(0, intr.w - 1)
        row = np.floor(crossings.pixel[rows, 1] / stride).astype(int).clip(0, intr.h - 1)
        cos = crossings.dirs[rows] @ -c2w[:3, 2]  # the ray's cosine with the optical axis (OpenGL: looks down -z)
        t_mesh = zbuf[row, col] / np.maximum(cos, 1e-9)  # inf where no face
        t_field = crossings.depth[rows]
        crossed = np.isfinite(t_field)
        tol = tol0 + TOL_DEPTH * np.where(crossed, t_field, 0.0)
        seen = np.zeros(len(rows), bool)
        if crossed.any():
            p = crossings.origins[rows[crossed]] + t_field[crossed, None] * crossings.dirs[rows[crossed]]
            seen[crossed] = inside(p)
        lacking = seen & ~(t_mesh <= t_field + tol)
        if lacking.any():
            idx = np.flatnonzero(lacking)
            p = crossings.origins[rows[idx]] + t_field[idx, None] * crossings.dirs[rows[idx]]
            far = np.isinf(tree.query(p, distance_upper_bound=NEAR_VOXELS * voxel)[0])
            lacking[idx[~far]] = False
            if cut_tree is not None:  # lacking on purpose: neither seen nor missed
                cut = far & np.isfinite(cut_tree.query(p, distance_upper_bound=NEAR_VOXELS * voxel)[0])
                on_cut += int(cut.sum())
                seen[idx[cut]] = lacking[idx[cut]] = False
        hit = np.isfinite(t_mesh)
        empty = ~crossed & (crossings.opacity[rows] < EMPTY_OPACITY)
        field_surface += int(seen.sum())
        missed += int(lacking.sum())
        hits += int(hit.sum())
        extra += int((hit & (empty | (crossed & (t_mesh < t_field - tol)))).sum())
    return Agreement(
        field_surface=field_surface,
        missed=missed,
        mesh_surface=hits,
        extra=extra,
        views=views,
        tol=tol0,
        cut_away=on_cut,
    )
