"""A binary PLY point cloud (numpy only): x y z (double), nx ny nz (float), red green blue (uchar).

Coordinates are doubles: the user frame may be a COLMAP or geo-referenced frame whose coordinates are large, where
float32 keeps only ~7 digits (6 cm at 1000 km); normals and colours need no more than float32 and 8 bits. Open3D
writes the same layout; trimesh, MeshLab (pymeshlab), CloudCompare and Blender read it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import numpy as np

__all__ = ["PLY_PROPERTIES", "write_ply"]

PLY_PROPERTIES = (
    ("x", "<f8", "double"),
    ("y", "<f8", "double"),
    ("z", "<f8", "double"),
    ("nx", "<f4", "float"),
    ("ny", "<f4", "float"),
    ("nz", "<f4", "float"),
    ("red", "u1", "uchar"),
    ("green", "u1", "uchar"),
    ("blue", "u1", "uchar"),
)


def write_ply(
    path: str | os.PathLike, points: np.ndarray, normals: np.ndarray, colors: np.ndarray, comments: Iterable[str] = ()
) -> None:
    """Write points [N, 3], unit normals [N, 3] and colours [N, 3] uint8 to `path` (binary little-endian PLY).

    `path` is written as is: callers wanting an atomic file pass `data.atomic.atomic_path`'s temporary."""
    n = len(points)
    for name, arr in (("points", points), ("normals", normals), ("colors", colors)):
        if np.shape(arr) != (n, 3):
            raise ValueError(f"expected {name} [{n}, 3], got {np.shape(arr)}")
    rows = np.empty(n, dtype=np.dtype([(name, dtype) for name, dtype, _ in PLY_PROPERTIES]))
    for k, axis in enumerate("xyz"):
        rows[axis] = points[:, k]
        rows["n" + axis] = normals[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        rows[channel] = colors[:, k]
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {' '.join(str(c).split())}" for c in comments]  # one line each
    lines += [f"element vertex {n}"] + [f"property {kind} {name}" for name, _, kind in PLY_PROPERTIES]
    lines.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(lines) + "\n").encode("ascii", errors="replace"))
        f.write(rows.tobytes())
