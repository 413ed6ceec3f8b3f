"""Point-cloud geometry for `stages.export_points`: normals from the density field, statistical outliers, the
output frame.

Normals (decision): n = -grad sigma / |grad sigma| at the point, the gradient taken by central differences of
the run's density (`Trained.density`, scene frame) with a step h: grad_k = (sigma(x + h e_k) - sigma(x - h e_k)) / 2h.
Density grows into an object, so -grad sigma points out of it, whichever camera saw the point. Why the field and
not the depth maps: the points come from sparse rays (a sub-grid of pixels, not whole depth maps), a depth-map
gradient needs each pixel's neighbours and is undefined along silhouettes and depth edges, exactly where rays hit
two surfaces; the density gradient is a property of the point, the same for every view. Why central differences
and not autograd: `Trained.density` is the public, no-grad query that already maps scene points into every run's
space (box, contracted, NDC); and the analytic gradient of a trilinear hash grid is piecewise constant per cell of
its finest level and noisy, while a step of a few cells averages over them (nerfstudio's nerfacto adds a normal
head for that noise). Cost: six density queries per point, small next to the rendering (a ray is many samples).
Where the gradient is zero or not finite (empty space around the point) the normal is the reverse of the ray that
gave the point (facing its camera), and counted.

Outliers: open3d's statistical rule, `remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)` as nerfstudio's
`ns-export pointcloud` calls it: for each point the mean distance to its `k` nearest other points
(`scipy.spatial.cKDTree`); a point goes when that mean exceeds the mean over all points by more than `std_ratio`
sample standard deviations. A similarity transform scales every distance alike, so the rule keeps the same points in
the scene and the user frame.

Frames: points map by out_from_scene [4, 4]; normals by the inverse transpose of its 3x3 (a gradient is a
covector: this keeps them perpendicular to the surface and outward under a mirror too), renormalised.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

__all__ = ["density_normals", "statistical_outliers", "to_frame", "facing_share"]

DensityFn = Callable[[torch.Tensor], torch.Tensor]
"""x [N, 3] float32 scene frame on the field's device -> sigma [N] (`Trained.density`)."""

_AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


def density_normals(
    density: DensityFn, points: np.ndarray, dirs: np.ndarray, step: float, device: torch.device, chunk: int = 1 << 16
) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals [N, 3] float64: -grad sigma normalised (module doc), mask [N]: from the gradient; the others
    are -dirs).

    points [N, 3] scene frame; dirs [N, 3] unit ray directions; step h in scene units (> 0)."""
    if not step > 0:
        raise ValueError(f"expected a step > 0, got {step}")
    normals = np.empty((len(points), 3), np.float64)
    offsets = step * _AXES  # [6, 3]
    with torch.no_grad():
        for a in range(0, len(points), chunk):
            x = points[a : a + chunk]
            q = (x[:, None, :] + offsets[None]).reshape(-1, 3)
            sigma = density(torch.as_tensor(q, dtype=torch.float32, device=device))
            s = sigma.detach().double().cpu().numpy().reshape(-1, 6)
            normals[a : a + chunk] = -(s[:, 0::2] - s[:, 1::2]) / (2.0 * step)  # -grad sigma
    norm = np.linalg.norm(normals, axis=1)
    good = np.isfinite(norm) & (norm > 0)
    normals[good] /= norm[good, None]
    normals[~good] = -np.asarray(dirs, np.float64)[~good]
    return normals, good


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
    info = {"applied": True, "neighbors": neighbors, "std_ratio": std_ratio, "mean_neighbor_distance_scene": mu,
            "std_scene": sd, "limit_scene": limit, "removed": int((~keep).sum())}  # fmt: skip
    return keep, info


def to_frame(out_from_scene: np.ndarray, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scene-frame points and unit normals [N, 3] -> the output frame's (module doc)."""
    m = np.asarray(out_from_scene, np.float64)
    p = points @ m[:3, :3].T + m[:3, 3]
    n = normals @ np.linalg.inv(m[:3, :3])  # rows: (A^-T n)^T = n^T A^-1
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.finfo(np.float64).tiny)
    return p, n


def facing_share(normals: np.ndarray, dirs: np.ndarray) -> float:
    """Share of normals that face the camera whose ray gave the point (n . -d > 0); NaN without points."""
    if len(normals) == 0:
        return float("nan")
    return float((np.einsum("ij,ij->i", normals, -np.asarray(dirs, np.float64)) > 0).mean())
