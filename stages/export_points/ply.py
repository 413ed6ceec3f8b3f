"""A binary PLY point cloud (numpy only): x y z (float, or double), nx ny nz (float), red green blue (uchar).

Coordinates are 32-bit floats by default: web clients refuse 64-bit ones (three.js: "Unsupported buffer data format"
for a Float64Array attribute, issue 52), and a capture's coordinates in its own frame are small, where float32's ~7
digits are sub-micrometre. `double=True` writes doubles, for a user frame whose coordinates are large (geo-referenced:
float32 keeps ~6 cm at 1000 km), which trimesh, MeshLab (pymeshlab), CloudCompare and Blender read. Normals and
colours need no more than float32 and 8 bits. Open3D writes the same layouts.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import numpy as np

__all__ = ["PLY_PROPERTIES", "ply_properties", "write_ply"]

PLY_PROPERTIES = (
    ("x", "<f4", "float"),
    ("y", "<f4", "float"),
    ("z", "<f4", "float"),
    ("nx", "<f4", "float"),
    ("ny", "<f4", "float"),
    ("nz", "<f4", "float"),
    ("red", "u1", "uchar"),
    ("green", "u1", "uchar"),
    ("blue", "u1", "uchar"),
)


def ply_properties(double: bool = False) -> tuple[tuple[str, str, str], ...]:
    """(name, numpy type, PLY type) of each property: PLY_PROPERTIES, with double coordinates when `double`."""
    if not double:
        return PLY_PROPERTIES
    return tuple((n, "<f8", "double") if n in "xyz" else (n, t, k) for n, t, k in PLY_PROPERTIES)


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    normals: np.ndarray,
    colors: np.ndarray,
    comments: Iterable[str] = (),
    *,
    double: bool = False,
) -> None:
    """Write points [N, 3], unit normals [N, 3] and colours [N, 3] uint8 to `path` (binary little-endian PLY;
    coordinates as float32, or float64 with `double`).

    `path` is written as is: callers wanting an atomic file pass `data.atomic.atomic_path`'s temporary."""
    n = len(points)
    for name, arr in (("points", points), ("normals", normals), ("colors", colors)):
        if np.shape(arr) != (n, 3):
            raise ValueError(f"expected {name} [{n}, 3], got {np.shape(arr)}")
    props = ply_properties(double)
    rows = np.empty(n, dtype=np.dtype([(name, dtype) for name, dtype, _ in props]))
    for k, axis in enumerate("xyz"):
        rows[axis] = points[:, k]
        rows["n" + axis] = normals[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        rows[channel] = colors[:, k]
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {' '.join(str(c).split())}" for c in comments]  # one line each
    lines += [f"element vertex {n}"] + [f"property {kind} {name}" for name, _, kind in props]
    lines.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(lines) + "\n").encode("ascii", errors="replace"))
        f.write(rows.tobytes())
