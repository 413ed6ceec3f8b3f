"""`scene --layout turntable`: the object turns on a turntable in front of a fixed camera and a fixed room.

Frames (docs/DESIGN.md conventions; metres, up +z):
- the **room frame**: the camera and the background (the textured room of `objects.room`) never move in it;
- the **object frame** (= the scene frame written to transforms.json and ground_truth/): the slab and its five
  objects (`objects.default_primitives`), turning about the room's z axis through the origin. View k shows the
  object turned by `theta_k = 2 pi k / views`: `p_room = Rz(theta_k) p_object`. Its camera, object-relative as a
  photogrammetry tool must find it, is `object_from_cam_k = Rz(-theta_k) @ room_from_cam` (OpenGL axes).
- Camera: one fixed pose, `CAMERA_RADIUS` from `LOOK_AT`, `ELEVATION_DEG` up, looking along +y.
- Shading: the object's lights turn with it (shaded in the object frame), so each surface point keeps one colour
  in every view, as the other layouts promise; the room is shaded in the room frame. (A real turntable's fixed
  lights would change the object's shading as it turns: a simplification.)
- Mask (`masks/<image stem>.png`): the fraction of each pixel's rays that hit the object before the room, white =
  object (`data.masks` convention). Depth: z-depth of the object only (0 where the room is seen): the room is not
  a rigid part of the object-frame scene.
"""

from __future__ import annotations

import math

import numpy as np

from nerfpipe.data.synthetic.objects import rot_z
from nerfpipe.radiance.paths import look_at

__all__ = ["ELEVATION_DEG", "angles", "room_from_cam", "object_cameras", "rot_z"]

ELEVATION_DEG = 30.0
"""The fixed camera's elevation above the turntable's centre (degrees)."""


def angles(views: int) -> np.ndarray:
    """Turntable angle of each view, radians [V]: one full turn in equal steps."""
    return 2 * np.pi * np.arange(views) / views


def room_from_cam(look_at_point: np.ndarray, radius: float, up: np.ndarray) -> np.ndarray:
    """The fixed camera [4, 4] (OpenGL axes): `radius` from the look-at point, ELEVATION_DEG up, looking along +y."""
    el = math.radians(ELEVATION_DEG)
    eye = look_at_point + radius * np.array([0.0, -math.cos(el), math.sin(el)])
    return look_at(eye, look_at_point, up)


def object_cameras(fixed: np.ndarray, views: int) -> np.ndarray:
    """object_from_cam [V, 4, 4]: the fixed camera seen from the object, which has turned by `angles(views)`."""
    return np.stack([rot_z(-a) @ fixed for a in angles(views)])
