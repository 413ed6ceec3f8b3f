"""A mesh file as the scene stage's subject: rays cast against its triangles (trimesh's ray query through Embree),
smooth shading normals interpolated from the vertex normals of the triangle a point lies on, and the solid texture
of the analytic primitives (`data.synthetic.objects`).

The mesh is turned, moved and scaled into the rig's frame (`fit`: its up axis to +z, its bounding box's centre to a
given point, its half-diagonal to a given radius); the 4x4 `scene_from_source` says how, so the scene's ground truth
maps back to the file's coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from nerfpipe.data.errors import UserError
from nerfpipe.data.synthetic.objects import Material, Primitive

__all__ = ["MeshSurface", "read_mesh", "fit"]

CANDIDATES = 8
"""Triangles (nearest by centroid) searched for the one a surface point lies on."""


def read_mesh(path: Path) -> trimesh.Trimesh:
    """A mesh file (any format trimesh reads: obj, ply, stl, off, glb ...) as one triangle mesh; UserError when it
    cannot be read or holds no triangles."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such mesh file")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many kinds for files it cannot parse
        raise UserError(f"{path}: not a mesh trimesh reads ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"{path}: expected a mesh with triangles, found none")
    if not np.isfinite(mesh.vertices).all() or float(mesh.scale) <= 0:
        raise UserError(f"{path}: expected finite vertices spanning a non-empty box")
    return mesh


UP_TURN = {"z": np.eye(3), "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}
"""The rotation that takes a file's up axis to +z (y: +y -> +z, +z -> -y, x kept; a proper rotation)."""


def fit(mesh: trimesh.Trimesh, centre: np.ndarray, radius: float, up: str = "z") -> tuple[trimesh.Trimesh, np.ndarray]:
    """The mesh turned so that its `up` axis is +z, then moved and scaled so that its bounding box's centre is
    `centre` [3] and its half-diagonal is `radius`; and that 4x4 scene_from_source (a rotation, a uniform scale and a
    translation)."""
    if up not in UP_TURN:
        raise ValueError(f"expected up in {list(UP_TURN)}, got {up!r}")
    turn = np.eye(4)
    turn[:3, :3] = UP_TURN[up]
    corners = trimesh.bounds.corners(mesh.bounds) @ UP_TURN[up].T  # [8, 3] the box turned (a quarter turn: a box)
    lo, hi = corners.min(0), corners.max(0)
    scale = radius / (0.5 * float(np.linalg.norm(hi - lo)))
    place = np.eye(4)
    place[:3, :3] *= scale
    place[:3, 3] = np.asarray(centre, dtype=np.float64) - scale * (lo + hi) / 2
    tf = place @ turn
    moved = mesh.copy()
    moved.apply_transform(tf)
    return moved, tf


@dataclass(frozen=True, kw_only=True, eq=False)
class MeshSurface(Primitive):
    """A triangle mesh in the scene frame (module doc) with a solid texture."""

    surface: trimesh.Trimesh
    material: Material
    _centroids: cKDTree = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not trimesh.ray.has_embree:
            raise UserError("a mesh subject needs trimesh's Embree ray queries: install embreex (pyproject.toml)")
        object.__setattr__(self, "_centroids", cKDTree(self.surface.triangles_center))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t = np.full(len(o), np.inf)
        if len(o) == 0:
            return t
        _, ray, loc = self.surface.ray.intersects_id(o, d, multiple_hits=False, return_locations=True)
        t[ray] = np.einsum("ij,ij->i", loc - o[ray], d[ray])
        return t

    def normal(self, p: np.ndarray) -> np.ndarray:
        """Points on the surface [N, 3] -> unit normals [N, 3]: the vertex normals of the triangle the point lies
        on (the closest of its nearest triangles by centroid), interpolated barycentrically."""
        mesh, k = self.surface, min(CANDIDATES, len(self.surface.faces))
        _, near = self._centroids.query(p, k=k)  # [N, k]
        near = near.reshape(len(p), k)
        tris = mesh.triangles[near.reshape(-1)]  # [N k, 3, 3]
        closest = trimesh.triangles.closest_point(tris, np.repeat(p, k, axis=0)).reshape(len(p), k, 3)
        best = near[np.arange(len(p)), np.linalg.norm(closest - p[:, None], axis=-1).argmin(-1)]  # [N]
        bary = trimesh.triangles.points_to_barycentric(mesh.triangles[best], p)  # [N, 3]
        n = (mesh.vertex_normals[mesh.faces[best]] * bary[..., None]).sum(1)
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)

    def mesh(self) -> trimesh.Trimesh:
        return self.surface.copy()

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        lo, hi = self.surface.bounds
        return (lo + hi) / 2, 0.5 * float(np.linalg.norm(hi - lo)) * 1.001
