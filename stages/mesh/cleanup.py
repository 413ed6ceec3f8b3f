"""Mesh cleanup for `stages.mesh` (pymeshlab 2023.12+ filter names), and mesh statistics.

Each step records the vertex / face counts after it, so the mesh's `OUT.report.json` shows what every step did.
Order: exact duplicates and degenerate faces -> small floating components (relative diameter, then face
count) -> non-manifold edges and vertices -> optional hole closing -> Taubin smoothing (shrink-free) ->
optional quadric edge-collapse decimation. All thresholds are relative to the mesh's own size, so the
cleanup does not depend on the frame or units the mesh is in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Cleanup", "cleanup_mesh", "mesh_stats", "vertex_components", "vertex_normals", "transform_mesh"]


@dataclass(frozen=True, kw_only=True)
class Cleanup:
    """What the cleanup does (the defaults suit a marching-cubes mesh of a radiance field)."""

    min_component_diameter: float = 0.1
    """Drop connected components whose bounding-box diagonal is below this fraction of the whole mesh's
    (MeshLab's default: 10 %)."""
    min_component_faces: int = 50
    """Drop connected components with fewer faces than this."""
    max_hole_edges: int = 0
    """Close holes bounded by at most this many edges (0: leave holes open)."""
    smooth_steps: int = 5
    """Taubin smoothing iterations (lambda 0.5, mu -0.53: removes marching-cubes terracing without shrinking)."""


def _counts(ms, step: str) -> dict:
    m = ms.current_mesh()
    return {"step": step, "vertices": int(m.vertex_number()), "faces": int(m.face_number())}


def cleanup_mesh(
    verts: np.ndarray,  # [V, 3]
    faces: np.ndarray,  # [F, 3] int
    cleanup: Cleanup | None,
    target_faces: int | None = None,
) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Clean (when `cleanup` is given) and decimate (when `target_faces` is given) a triangle mesh.

    Returns (verts [V', 3] float64, faces [F', 3] int64, steps: [{step, vertices, faces}, ...]).
    """
    steps: list[dict] = []
    if cleanup is None and target_faces is None:
        return verts, faces, steps
    import pymeshlab  # only here: `--no-cleanup` without decimation never loads it

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(verts, np.float64), face_matrix=np.asarray(faces, np.int32)))
    if cleanup is not None:
        ms.meshing_remove_duplicate_vertices()
        ms.meshing_remove_duplicate_faces()
        ms.meshing_remove_null_faces()
        ms.meshing_remove_unreferenced_vertices()
        steps.append(_counts(ms, "remove_duplicates"))
        if cleanup.min_component_diameter > 0:
            pct = pymeshlab.PercentageValue(100.0 * cleanup.min_component_diameter)
            ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=pct, removeunref=True)
            steps.append(_counts(ms, "remove_small_components_by_diameter"))
        if cleanup.min_component_faces > 0:
            ms.meshing_remove_connected_component_by_face_number(
                mincomponentsize=cleanup.min_component_faces, removeunref=True
            )
            steps.append(_counts(ms, "remove_small_components_by_faces"))
        ms.meshing_repair_non_manifold_edges(method="Remove Faces")
        ms.meshing_repair_non_manifold_vertices(vertdispratio=0.0)
        ms.meshing_remove_unreferenced_vertices()
        steps.append(_counts(ms, "repair_non_manifold"))
        if cleanup.max_hole_edges > 0 and ms.current_mesh().face_number() > 0:
            try:
                ms.meshing_close_holes(maxholesize=cleanup.max_hole_edges, selfintersection=False)
            except pymeshlab.PyMeshLabException as exc:  # refuses meshes it still finds non-manifold
                steps.append({**_counts(ms, "close_holes"), "skipped": str(exc).strip()})
            else:
                steps.append(_counts(ms, "close_holes"))
        if cleanup.smooth_steps > 0 and ms.current_mesh().face_number() > 0:
            ms.apply_coord_taubin_smoothing(lambda_=0.5, mu=-0.53, stepsmoothnum=cleanup.smooth_steps)
            steps.append(_counts(ms, "taubin_smoothing"))
    if target_faces is not None and ms.current_mesh().face_number() > target_faces:
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(target_faces),
            preservenormal=True,
            preservetopology=True,
            optimalplacement=True,
            planarquadric=True,
            qualitythr=0.3,
            autoclean=True,
        )
        ms.meshing_remove_unreferenced_vertices()
        steps.append(_counts(ms, "decimation"))
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64), steps


def transform_mesh(
    verts: np.ndarray, faces: np.ndarray, target_from_source: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Map vertices [V, 3] by a 4x4 affine; reverse face winding when it mirrors (det < 0) so normals stay outward."""
    m = np.asarray(target_from_source, np.float64)
    out = verts @ m[:3, :3].T + m[:3, 3]
    if np.linalg.det(m[:3, :3]) < 0:
        faces = faces[:, ::-1].copy()
    return out, faces


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V, 3] (outward for counter-clockwise faces); zero for isolated vertices."""
    tri = verts[faces]  # [F, 3, 3]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # [F, 3], length = 2 * area
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)


def mesh_stats(verts: np.ndarray, faces: np.ndarray) -> dict:
    """Connected components (vertices joined by faces), watertightness (every edge in exactly two faces, once
    in each direction), boundary / non-manifold edge counts, signed volume (> 0: faces wind outward)."""
    if len(faces) == 0:
        return {
            "components": 0,
            "watertight": False,
            "boundary_edges": 0,
            "non_manifold_edges": 0,
            "signed_volume": 0.0,
        }
    faces = np.asarray(faces, np.int64)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    n_v = int(faces.max()) + 1
    used = np.bincount(faces.reshape(-1), minlength=n_v) > 0  # (np.unique is slow on millions of ints)
    _, labels = vertex_components(faces, n_v)
    components = int((np.bincount(labels[used]) > 0).sum())
    src, dst = np.concatenate([a, b, c]), np.concatenate([b, c, a])  # directed edges
    keys = np.sort(src * n_v + dst)
    undirected = np.sort(np.minimum(src, dst) * n_v + np.maximum(src, dst))
    starts = np.flatnonzero(np.r_[True, undirected[1:] != undirected[:-1]])
    count = np.diff(np.r_[starts, len(undirected)])  # faces per undirected edge
    oriented = bool((keys[1:] != keys[:-1]).all()) and np.array_equal(keys, np.sort(dst * n_v + src))
    tri = np.asarray(verts, np.float64)[faces]
    volume = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)
    return {
        "components": int(components),
        "watertight": bool((count == 2).all() and oriented),
        "boundary_edges": int((count == 1).sum()),
        "non_manifold_edges": int((count > 2).sum()),
        "signed_volume": volume,
    }


def vertex_components(faces: np.ndarray, n_verts: int) -> tuple[int, np.ndarray]:
    """(number of components, label [n_verts]) of the graph of vertices joined by faces' edges (a vertex no face
    uses is a component of its own)."""
    import scipy.sparse
    import scipy.sparse.csgraph

    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    graph = scipy.sparse.coo_matrix(
        (np.ones(2 * len(faces), np.int8), (np.concatenate([a, b]), np.concatenate([b, c]))), shape=(n_verts, n_verts)
    )
    return scipy.sparse.csgraph.connected_components(graph, directed=False)
