"""The frame an export is written in: the user's frame turned upright for the file's format, kept, or the scene's.

Shared by the stages that write geometry (`mesh`, `export-points`, `splat`). Three choices (`FRAMES`):

- `upright` (the default): the user's frame (the one `convert` started from: its units) turned by the smallest
  rotation that puts the scene's up on the format's up axis (`FORMAT_UP`), so that a client opens the file the
  right way up, and moved so that the scene's centre (the scene frame's origin: the middle of the region of
  interest) is the file's origin. Viewers orbit the origin: gsplat.js' default camera looks at it from 5 units,
  three.js' OrbitControls and Blender's view turn about it; `make demo`'s splats, at their COLMAP origin, lay 2.6
  units from it, under the default camera's view (issue 52). The scene's up is the scene frame's +z: `convert`'s
  choice (the cameras' mean up vector for COLMAP and LLFF worlds, the source's z for Blender, tiny-NeRF and
  transforms.json inputs; `radiance.normalize`); or an up direction the user gives in their own frame (`up`).
- `user`: the user's frame exactly as it came in (e.g. COLMAP's, whose axes are wherever the first camera pointed).
- `normalized`: the scene frame the field was trained in (z up, the region of interest in [-1, 1]^3).

The format's up (`FORMAT_UP`, each with a 3x3 rotation from a z-up frame):
- glTF (.glb): +Y, the glTF 2.0 specification's ("glTF uses a right-handed coordinate system ... +Y is up"); its
  front is +Z, so z-up x, y, z become x, -z, y (what Blender's glTF exporter does).
- OBJ: +Y, as Blender's OBJ importer (forward -Z, up Y by default), Maya and three.js' OBJLoader read it; the same
  rotation as glTF's.
- PLY meshes and point clouds: +Z, as Blender's PLY importer (up Z by default), CloudCompare, PDAL and Potree read
  them, and as nerfstudio's point-cloud and mesh exports are written; no rotation from the z-up frame.
- Gaussian splats (INRIA PLY, .splat): -Y. The 3DGS files are written in COLMAP's frame, whose y points down in
  the first camera; viewers are built for that: SuperSplat / PlayCanvas turn every file 180 degrees about z when
  loading, gsplat.js' camera and orbit controls take -y as up (its projection flips y, OpenCV-like), as
  antimatter15's viewer does. The rotation takes z-up x, y, z to x, z, -y.

Every matrix is recorded in the outputs' reports: `out_from_scene` (4x4; scene -> file) as before, and with it
`out_from_source` (4x4; the user's frame -> file: a rotation and a shift for `upright`, the identity for `user`), so
every export maps back to the user's frame: `p_source = inv(out_from_source) @ p_file`.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

__all__ = ["FRAMES", "FORMAT_UP", "Frame", "check_frame_options", "export_frame", "rotation_onto"]

Frame = Literal["upright", "user", "normalized"]
FRAMES: tuple[str, ...] = ("upright", "user", "normalized")

_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z-up -> y-up: x, y, z -> x, -z, y
_MINUS_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # z-up -> -y-up: x, y, z -> x, z, -y

FORMAT_UP: dict[str, tuple[str, np.ndarray]] = {
    "gltf": ("+Y", _Y_UP),
    "obj": ("+Y", _Y_UP),
    "ply": ("+Z", np.eye(3)),
    "points": ("+Z", np.eye(3)),
    "splat": ("-Y", _MINUS_Y_UP),
}
"""Format -> (its up axis, the rotation [3, 3] from a z-up frame to the format's axes). Module doc: why each."""


def check_frame_options(frame: str, up: Any, *, flag: str = "") -> None:
    """UserError in one line unless `frame` is one of FRAMES and `up` is None or three finite numbers, not all 0;
    `flag` prefixes the option names as the caller's users type them ("--" on the command line)."""
    from nerfpipe.data.errors import UserError

    if frame not in FRAMES:
        raise UserError(f"{flag}frame: expected one of {', '.join(FRAMES)}, got {frame!r}")
    if up is not None:
        u = np.asarray(up, np.float64)
        if u.shape != (3,) or not np.isfinite(u).all() or not np.linalg.norm(u) > 0:
            raise UserError(f"{flag}up: expected three numbers x,y,z, not all 0, got {up}")


def rotation_onto(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking the direction `u` onto the direction `v` (a half turn about an axis
    perpendicular to both when they are opposite)."""
    u = np.asarray(u, np.float64) / np.linalg.norm(u)
    v = np.asarray(v, np.float64) / np.linalg.norm(v)
    c = float(u @ v)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        axis = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    w = np.cross(u, v)
    wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    return np.eye(3) + wx + wx @ wx / (1 + c)


def export_frame(
    source_from_scene: np.ndarray, frame: str, fmt: str, up: tuple[float, float, float] | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """(out_from_scene [4, 4], the report's entry) for an export in format `fmt` (a `FORMAT_UP` key) in `frame`
    (`FRAMES`); `up`: the up direction in the user's frame (None: the scene's, module doc). `source_from_scene` is
    the scene's `source_from_scene()` (a similarity)."""
    if frame not in FRAMES:
        raise ValueError(f"frame: expected one of {', '.join(FRAMES)}, got {frame!r}")
    if fmt not in FORMAT_UP:
        raise ValueError(f"format: expected one of {', '.join(FORMAT_UP)}, got {fmt!r}")
    m = np.asarray(source_from_scene, np.float64)
    if frame == "normalized":
        return np.eye(4), {"frame": "normalized", "out_from_source": np.linalg.inv(m).tolist()}
    if frame == "user":
        return m.copy(), {"frame": "user", "out_from_source": np.eye(4).tolist()}
    axis_name, to_format = FORMAT_UP[fmt]
    if up is None:
        source_up = m[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the scene's +z in the user's frame
        rule = "the scene's up (+z of the scene frame: convert's choice, the cameras' mean up for COLMAP and LLFF)"
    else:
        source_up = np.asarray(up, np.float64)
        rule = "given (up)"
    source_up = source_up / np.linalg.norm(source_up)
    out_from_source = np.eye(4)
    out_from_source[:3, :3] = to_format @ rotation_onto(source_up, np.array([0.0, 0.0, 1.0]))
    out_from_source[:3, 3] = -out_from_source[:3, :3] @ m[:3, 3]  # the scene's centre (its origin) to the origin
    info = {
        "frame": "upright",
        "up": {"rule": rule, "source_up": source_up.round(6).tolist(), "format_up": axis_name, "format": fmt},
        "out_from_source": out_from_source.tolist(),
    }
    return out_from_source @ m, info
