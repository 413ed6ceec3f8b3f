"""Point-cloud geometry for `stages.export_points`: statistical outliers and the output frame.

Normals: `model.surface_points.density_normals` (shared with the mesh stage's Poisson method).

Outliers: open3d's statistical rule, `remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)` as nerfstudio's
`ns-export pointcloud` calls it: for each point the mean distance to its `k` nearest other points
(`scipy.spatial.cKDTree`); a point goes when that mean exceeds the mean over all points by more than `std_ratio`
sample standard deviations. A similarity transform scales every distance alike, so the rule keeps the same points in
the scene and the user frame.

Frames: points map by out_from_scene [4, 4]; normals by the inverse transpose of its 3x3 (a gradient is a
covector: this keeps them perpendicular to the surface and outward under a mirror too), renormalised.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["statistical_outliers", "to_frame"]


def statistical_outliers(points: np.ndarray, neighbors: int, std_ratio: float) -> tuple[np.ndarray, dict[str, Any]]:
    """(keep mask [N], the rule's figures) of the statistical rule (module doc); every point kept when there are
    no more points than `neighbors` (nothing to compare with)."""
    from scipy.spatial import cKDTree

    n = len(points)
    if neighbors < 1 or n <= neighbors:
        return np.ones(n, bool), {"applied": False, "why": f"{n} points, {neighbors} neighbours: nothing to compare"}
    dist, _ = cKDTree(points).query(points, k=neighbors + 1, workers=-1)  # the first neighbour is the point itself
    mean = dist[:, 1:].mean(axis=1)
    mu, sd = float(mean.mean()), float(mean.std(ddof=1))
    limit = mu + std_ratio * sd
    keep = mean <= limit
    info = {
        "applied": True,
        "neighbors": neighbors,
        "std_ratio": std_ratio,
        "mean_neighbor_distance_scene": mu,
        "std_scene": sd,
        "limit_scene": limit,
        "removed": int((~keep).sum()),
    }
    return keep, info


def to_frame(out_from_scene: np.ndarray, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scene-frame points and unit normals [N, 3] -> the output frame's (module doc)."""
    m = np.asarray(out_from_scene, np.float64)
    p = points @ m[:3, :3].T + m[:3, 3]
    n = normals @ np.linalg.inv(m[:3, :3])  # rows: (A^-T n)^T = n^T A^-1
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.finfo(np.float64).tiny)
    return p, n
