"""Mesh accuracy metrics for the tests and benchmark of `stages.mesh` (not used by the stage itself).

Conventions: points and vertices are [N, 3] in any one frame; distances come out in that frame's units.
"""

from __future__ import annotations

import numpy as np

__all__ = ["chamfer_distance", "surface_points"]


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


def surface_points(verts: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """n points uniformly distributed by area on a triangle mesh (deterministic for a seed). [n, 3]."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(verts, np.float64)[np.asarray(faces)]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)  # barycentric, uniform on the triangle
    return np.einsum("nk,nkd->nd", w, tri[f])
