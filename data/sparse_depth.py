"""Which sparse points each photo sees: the structure-from-motion tracks, for depth supervision (DS-NeRF).

COLMAP knows, for every registered image, which 3-D points it observed (its feature tracks). `convert` writes them
next to transforms.json as `sparse_depth.npz`, named by the top-level key `sparse_depth_path`:
    points [M, 3] float32   the sparse points in the **scene frame** (the frame of transforms.json's poses)
    names  [F] str          frame file paths as in transforms.json (`frames[].file_path`)
    frame  [V] int32        per observation, an index into names
    point  [V] int32        per observation, an index into points
A ray from a camera's centre through one of its observed points ends on a surface at that point's distance; train
uses that (`--depth-loss`). No pixel coordinates are stored: the ray is fixed by the two 3-D points, so lens
distortion and downscaling do not enter. Optional everywhere: scenes without the key train as before.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.errors import UserError

__all__ = ["SparseDepth", "write_sparse_depth", "read_sparse_depth", "KEY", "FILE"]

KEY = "sparse_depth_path"
FILE = "sparse_depth.npz"


class SparseDepth:
    """points [M, 3] (scene frame) and, per frame file path, the indices of the points it observed."""

    def __init__(self, points: np.ndarray, observed: dict[str, np.ndarray]) -> None:
        self.points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        self.observed = {k: np.asarray(v, dtype=np.int64).reshape(-1) for k, v in observed.items()}
        for name, ids in self.observed.items():
            if len(ids) and (ids.min() < 0 or ids.max() >= len(self.points)):
                raise ValueError(f"{name}: point indices outside [0, {len(self.points)})")

    def rays(self, name: str, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays from `centre` [3] through the points frame `name` observed -> (o [K, 3], unit d [K, 3], distance
        [K]); points closer than 1e-6 of the scene (degenerate) are left out."""
        pts = self.points[self.observed.get(name, np.zeros(0, dtype=np.int64))].astype(np.float64)
        v = pts - np.asarray(centre, dtype=np.float64).reshape(1, 3)
        dist = np.linalg.norm(v, axis=1)
        keep = dist > 1e-6
        d = v[keep] / dist[keep, None]
        return np.broadcast_to(centre, d.shape).astype(np.float32), d.astype(np.float32), dist[keep].astype(np.float32)


def write_sparse_depth(path: Path, points: np.ndarray, observed: dict[str, np.ndarray]) -> Path:
    """Atomic write of the layout above."""
    names = sorted(observed)
    frame = np.concatenate([np.full(len(observed[n]), i, dtype=np.int32) for i, n in enumerate(names)] or [[]])
    point = np.concatenate([np.asarray(observed[n], dtype=np.int32) for n in names] or [[]])
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(
            tmp,
            points=np.asarray(points, np.float32),
            names=np.array(names, dtype=str),
            frame=frame.astype(np.int32),
            point=point.astype(np.int32),
        )
    return Path(path)


def read_sparse_depth(path: Path) -> SparseDepth:
    """The file `write_sparse_depth` wrote; a missing or malformed file is a UserError naming it."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            points, names, frame, point = z["points"], z["names"], z["frame"], z["point"]
    except FileNotFoundError:
        raise UserError(f"{path}: sparse depth file not found (transforms.json's {KEY})") from None
    except (KeyError, ValueError, OSError) as e:
        raise UserError(f"{path}: expected an npz with points, names, frame, point ({e})") from None
    if frame.shape != point.shape or (len(frame) and (frame.min() < 0 or frame.max() >= len(names))):
        raise UserError(f"{path}: frame/point arrays do not match ({frame.shape} vs {point.shape}, {len(names)} names)")
    observed = {str(n): point[frame == i] for i, n in enumerate(names)}
    try:
        return SparseDepth(points, observed)
    except ValueError as e:
        raise UserError(f"{path}: {e}") from None
