"""Mesh accuracy metrics for the tests and benchmark of `stages.mesh` (not used by the stage itself).

Conventions: points and vertices are [N, 3] in any one frame; distances come out in that frame's units. Faces
wind counter-clockwise seen from outside, so face normals point outward; a signed distance is positive outside.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["chamfer_distance", "surface_points", "surface_samples", "signed_offsets", "scanned_mesh_file"]


def chamfer_distance(a_points: np.ndarray, b_points: np.ndarray) -> float:
    """Symmetric mean Chamfer distance: (mean_a min_b |a - b| + mean_b min_a |b - a|) / 2 (not squared),
    in the points' units. a_points [N, 3], b_points [M, 3]."""
    from scipy.spatial import cKDTree

    a = np.asarray(a_points, np.float64).reshape(-1, 3)
    b = np.asarray(b_points, np.float64).reshape(-1, 3)
    if len(a) == 0 or len(b) == 0:
        raise ValueError(f"expected two non-empty point sets, got {len(a)} and {len(b)} points")
    d_ab = cKDTree(b).query(a, workers=-1)[0]
    d_ba = cKDTree(a).query(b, workers=-1)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def surface_samples(verts: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n points uniformly distributed by area on a triangle mesh, and their faces' unit normals (outward for
    counter-clockwise faces); deterministic for a seed. ([n, 3], [n, 3])."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(verts, np.float64)[np.asarray(faces)]  # [F, 3, 3]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # [F, 3], length = 2 * area
    area = 0.5 * np.linalg.norm(cross, axis=1)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)  # barycentric, uniform on the triangle
    normals = cross[f] / (2 * area[f, None])
    return np.einsum("nk,nkd->nd", w, tri[f]), normals


def surface_points(verts: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """n points uniformly distributed by area on a triangle mesh (deterministic for a seed). [n, 3]."""
    return surface_samples(verts, faces, n, seed)[0]


def signed_offsets(points: np.ndarray, surface: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Signed distance [N] of each point [N, 3] to a surface given by dense samples `surface` [M, 3] with unit
    `normals` [M, 3]: the offset from the nearest sample along that sample's normal (positive on the side the
    normal points to: outside). The tangential part of the offset is dropped, so the sample spacing enters only
    through the surface's curvature over it."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64).reshape(-1, 3)
    s = np.asarray(surface, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    if len(s) == 0 or n.shape != s.shape:
        raise ValueError(f"expected a non-empty surface [M, 3] and normals of the same shape, got {s.shape}, {n.shape}")
    idx = cKDTree(s).query(p, workers=-1)[1]
    return np.einsum("nd,nd->n", p - s[idx], n[idx])


def scanned_mesh_file(name: str) -> Path:
    """A scanned mesh pymeshlab's wheel ships, `pymeshlab/tests/sample_meshes/<name>.obj` (bunny, cow, airplane ...),
    found without importing pymeshlab; SystemExit in one line when it is not there."""
    import importlib.util

    spec = importlib.util.find_spec("pymeshlab")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("pymeshlab is not installed (make install): its sample meshes are the scans")
    path = Path(spec.submodule_search_locations[0]) / "tests" / "sample_meshes" / f"{name}.obj"
    if not path.is_file():
        raise SystemExit(f"{path} is not in this pymeshlab wheel")
    return path
