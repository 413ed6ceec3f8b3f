"""Browser cameras <-> nerfpipe cameras (no viser import: plain numbers in, plain numbers out).

viser's cameras follow OpenCV axes (x right, y down, looking down +z): a pose is `wxyz` (quaternion, w first)
and `position` of the camera in the world, `fov` the vertical field of view in radians, `aspect` = width /
height. nerfpipe's are `world_from_cam` [4, 4] in OpenGL axes (x right, y up, looking down -z); the viewer's
world is the run's scene frame (transforms.json's normalised frame, up +z), so no other change is made.
"""

from __future__ import annotations

import math

import numpy as np

from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.keyframes import matrix_from_quat, quat_from_matrix

__all__ = ["world_from_cam_gl", "viser_pose", "browser_intrinsics", "vertical_fov"]

_FLIP = np.diag([1.0, -1.0, -1.0])  # OpenCV <-> OpenGL camera axes (its own inverse)


def world_from_cam_gl(wxyz, position) -> np.ndarray:
    """A viser camera pose (OpenCV axes) -> world_from_cam [4, 4] in OpenGL axes."""
    out = np.eye(4)
    out[:3, :3] = matrix_from_quat(np.asarray(wxyz, dtype=np.float64)) @ _FLIP
    out[:3, 3] = np.asarray(position, dtype=np.float64)
    return out


def viser_pose(world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """world_from_cam [4, 4] (OpenGL axes) -> (wxyz [4], position [3]) for viser (OpenCV axes)."""
    m = np.asarray(world_from_cam, dtype=np.float64)
    return quat_from_matrix(m[:3, :3] @ _FLIP), m[:3, 3].copy()


def browser_intrinsics(fov: float, aspect: float, long_side: int) -> Intrinsics:
    """A centred pinhole camera with vertical field of view `fov` (radians) and `long_side` pixels on its longer
    side (the browser window's shape, `aspect` = width / height)."""
    if not (0 < fov < math.pi and aspect > 0 and long_side >= 1):
        raise ValueError(f"expected fov in (0, pi), aspect > 0, long_side >= 1, got {fov}, {aspect}, {long_side}")
    w, h = (
        (long_side, max(1, round(long_side / aspect)))
        if aspect >= 1
        else (max(1, round(long_side * aspect)), long_side)
    )
    f = 0.5 * h / math.tan(0.5 * fov)
    return Intrinsics(w=w, h=h, fx=f, fy=f, cx=w / 2, cy=h / 2)


def vertical_fov(intr: Intrinsics) -> float:
    """Vertical field of view (radians) of a pinhole camera."""
    return 2.0 * math.atan(0.5 * intr.h / intr.fy)
