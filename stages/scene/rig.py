"""Where the scene stage's cameras are: the pinhole intrinsics and `world_from_cam` [V, 4, 4] (OpenGL axes) per
layout (orbit, room, forward, turntable), all looking at `LOOK_AT`; metres, world up +z."""

from __future__ import annotations

import math

import numpy as np

from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.paths import look_at
from nerfpipe.stages.scene.turntable import object_cameras, room_from_cam

__all__ = [
    "FOV_X_DEG",
    "CAMERA_RADIUS",
    "UP",
    "LOOK_AT",
    "ELEVATION_DEG",
    "FORWARD_SPREAD",
    "FORWARD_ELEVATION_DEG",
    "intrinsics",
    "cameras",
]

FOV_X_DEG = 45.0
CAMERA_RADIUS = 2.4
"""Distance from the look-at point, metres (the scene's bounding sphere, r ~ 0.8 m, subtends ~20 deg)."""
UP = np.array([0.0, 0.0, 1.0])  # world up: camera image up is as close to +z as can be
LOOK_AT = np.array([0.0, 0.0, 0.12])
ELEVATION_DEG = (15.0, 50.0)
FORWARD_SPREAD = (0.9, 0.5)
"""layout=forward: camera centres spread over this width x height (metres) of a plane facing the scene."""
FORWARD_ELEVATION_DEG = 20.0


def intrinsics(size: int) -> Intrinsics:
    f = 0.5 * size / math.tan(math.radians(FOV_X_DEG) / 2)
    return Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2)


def cameras(views: int, seed: int, layout: str = "orbit") -> np.ndarray:
    """world_from_cam [V, 4, 4] (OpenGL axes), all looking at `LOOK_AT`.

    orbit: azimuths evenly spread with jitter, elevations 15-50 deg stratified (golden-ratio sequence), radius
    2.4 m +- 3 %. forward: centres on a jittered grid of `FORWARD_SPREAD` in the plane 2.4 m from `LOOK_AT`,
    seen from azimuth -90 deg (looking along +y) and 20 deg elevation.
    """
    if layout == "forward":
        return _forward_cameras(views, seed)
    if layout == "turntable":
        return object_cameras(room_from_cam(LOOK_AT, CAMERA_RADIUS, UP), views)
    rng = np.random.default_rng([seed, 7])
    i = np.arange(views)
    azimuth = 2 * np.pi * (i + rng.uniform(-0.3, 0.3, views) + rng.uniform()) / views
    lo, hi = ELEVATION_DEG
    frac = (i * 0.6180339887 + rng.uniform()) % 1.0
    elevation = np.radians(lo + (hi - lo) * frac)
    radius = CAMERA_RADIUS * (1 + rng.uniform(-0.03, 0.03, views))
    eye = LOOK_AT + radius[:, None] * np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1
    )
    return np.stack([look_at(e, LOOK_AT, UP) for e in eye])


def _forward_cameras(views: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 11])
    cols = math.ceil(math.sqrt(views * FORWARD_SPREAD[0] / FORWARD_SPREAD[1]))
    rows = math.ceil(views / cols)
    k = np.arange(views)
    u = ((k % cols) + 0.5 + rng.uniform(-0.25, 0.25, views)) / cols - 0.5  # [-0.5, 0.5]
    v = ((k // cols) + 0.5 + rng.uniform(-0.25, 0.25, views)) / rows - 0.5
    el = math.radians(FORWARD_ELEVATION_DEG)
    back = np.array([0.0, -math.cos(el), math.sin(el)])  # from LOOK_AT towards the rig
    right = np.array([1.0, 0.0, 0.0])
    up = np.cross(back, right)
    eye = LOOK_AT + CAMERA_RADIUS * back + FORWARD_SPREAD[0] * u[:, None] * right + FORWARD_SPREAD[1] * v[:, None] * up
    return np.stack([look_at(e, LOOK_AT, UP) for e in eye])
