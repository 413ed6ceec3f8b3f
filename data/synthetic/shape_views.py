"""Photos of one family shape (`families`) and its occupancy in the frame of each photo's camera.

The view frame (what `nerfpipe voxels` predicts in; viewer-centred, gravity-aligned): the unit frame
(`families`, up +z) turned about +z so that
- x: the camera's right, horizontal;
- y: horizontal, away from the camera (the camera looks along +y, tilted down by its elevation);
- z: up.
A point p_view maps to the unit frame as p_unit = view_rotation(azimuth) @ p_view. The voxel grid covers the cube
[-0.5, 0.5]^3 of the view frame, `RES` cells a side, occupancy[i, j, k] at cell centre (x_i, y_j, z_k).

The camera (OpenGL axes, `radiance.camera`) sits at azimuth phi (radians, counter-clockwise seen from above, 0 on
+x), elevation el above the horizon and distance `distance` from the origin, looking at the origin; its field of
view (`FOV_DEG`) holds the unit sphere of radius 0.71 from 1.8 units away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from nerfpipe.data.synthetic.families import FAMILIES, Shape, inside, primitives, shape
from nerfpipe.data.synthetic.objects import Lights, Primitive
from nerfpipe.data.synthetic.photo import PHOTOS
from nerfpipe.data.synthetic.photo import photo as skimage_photo
from nerfpipe.data.synthetic.random_scene import draw_lights
from nerfpipe.data.synthetic.raycast import render_view
from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.paths import look_at

__all__ = [
    "RES",
    "FOV_DEG",
    "ELEVATION_DEG",
    "DISTANCE",
    "view_rotation",
    "camera",
    "grid_points",
    "view_occupancy",
    "photo",
    "ShapePhoto",
    "shape_photos",
]

RES = 32
"""Cells a side of the voxel grid."""
FOV_DEG = 50.0
ELEVATION_DEG = (5.0, 50.0)
"""Range of the cameras' elevations (uniform); 3D-R2N2's renders span 25-30 deg."""
DISTANCE = (1.7, 2.5)
"""Range of the cameras' distances from the origin, unit-frame units (uniform)."""


def view_rotation(azimuth: float) -> np.ndarray:
    """[3, 3] unit_from_view for a camera at `azimuth` (module doc): columns = the view axes in the unit frame."""
    c, s = math.cos(azimuth), math.sin(azimuth)
    return np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 1.0]])


def camera(azimuth: float, elevation: float, distance: float, size: int) -> tuple[Intrinsics, np.ndarray]:
    """Pinhole intrinsics (square, `size` pixels) and world_from_cam [4, 4] (OpenGL axes) looking at the origin."""
    f = 0.5 * size / math.tan(math.radians(FOV_DEG) / 2)
    eye = distance * np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )
    return Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2), look_at(
        eye, np.zeros(3), np.array([0.0, 0.0, 1.0])
    )


def grid_points(res: int = RES, sub: int = 1) -> np.ndarray:
    """Points [res^3 * sub^3, 3] of the view-frame cube: `sub`^3 stratified points in each cell, ordered (i, j, k,
    sub-point) with i along x, j along y, k along z."""
    cell = (np.arange(res * sub) + 0.5) / (res * sub) - 0.5
    x, y, z = np.meshgrid(cell, cell, cell, indexing="ij")
    p = np.stack([x, y, z], axis=-1).reshape(res, sub, res, sub, res, sub, 3)
    return p.transpose(0, 2, 4, 1, 3, 5, 6).reshape(-1, 3)


def view_occupancy(s: Shape, azimuth: float, res: int = RES, sub: int = 2) -> np.ndarray:
    """Occupied fraction of each cell in the view frame of a camera at `azimuth`: float32 [res, res, res] in
    [0, 1], from `sub`^3 points a cell tested exactly against the parts (`families.inside`)."""
    p = grid_points(res, sub) @ view_rotation(azimuth).T
    return inside(s.parts, p).reshape(res**3, sub**3).mean(-1).reshape(res, res, res).astype(np.float32)


def photo(
    prims: tuple[Primitive, ...], lights: Lights, azimuth: float, elevation: float, distance: float, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """A photo of the shape: straight colour [size, size, 3] and coverage alpha [size, size], float64 in [0, 1]."""
    intr, world_from_cam = camera(azimuth, elevation, distance, size)
    rgb, alpha, _ = render_view(prims, intr, world_from_cam, lights)
    return rgb, alpha


@dataclass(frozen=True)
class ShapePhoto:
    """One photo of one family shape, as a user would give it, and the exact answer."""

    rgb: np.ndarray  # [S, S, 3] float32: the object over a background
    mask: np.ndarray  # [S, S] float32: the object's mask, edges as a user's mask tool leaves them
    occupancy: np.ndarray  # [RES, RES, RES] bool: cells at least half inside the shape, view frame
    azimuth: float
    elevation: float
    distance: float


def _background(rng: np.random.Generator, size: int) -> np.ndarray:
    """A plain colour, or a crop of a scikit-image photograph: [size, size, 3] float32."""
    if rng.uniform() < 0.5:
        return np.broadcast_to(rng.uniform(0.0, 1.0, 3).astype(np.float32), (size, size, 3)).copy()
    img = skimage_photo(PHOTOS[int(rng.integers(len(PHOTOS)))])
    h, w = img.shape[:2]
    side = int(rng.integers(size // 2, min(h, w)))
    r, c = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    idx = (np.arange(size) * side / size).astype(int)
    return img[r + idx[:, None], c + idx[None, :]].astype(np.float32)


def _user_mask(rng: np.random.Generator, alpha: np.ndarray) -> np.ndarray:
    """The coverage as a mask tool returns it: kept soft (an alpha matte), made hard, or grown or shrunk by a
    pixel (a hand-made or automatic mask), one in four each."""
    kind = int(rng.integers(4))
    if kind == 0:
        return alpha
    hard = (alpha >= 0.5).astype(np.float32)
    if kind == 1:
        return hard
    return (ndimage.binary_dilation if kind == 2 else ndimage.binary_erosion)(hard).astype(np.float32)


def shape_photos(family: str, seed: int, views: int, size: int) -> tuple[Shape, list[ShapePhoto]]:
    """`views` photos of the shape of (`family`, `seed`) from random cameras (`ELEVATION_DEG`, `DISTANCE`, any
    azimuth), textured and lit at random (the same texture and lights in every view), each over its own random
    background with a user's mask, and the shape's occupancy in each photo's view frame."""
    s = shape(family, seed)
    rng = np.random.default_rng([seed, sorted(FAMILIES).index(family), 51])
    prims = primitives(s, rng)
    lights = draw_lights(rng)
    out = []
    for _ in range(views):
        az = float(rng.uniform(0.0, 2 * math.pi))
        el = math.radians(float(rng.uniform(*ELEVATION_DEG)))
        dist = float(rng.uniform(*DISTANCE))
        rgb, alpha = photo(prims, lights, az, el, dist, size)
        a = alpha.astype(np.float32)[..., None]
        composite = rgb.astype(np.float32) * a + _background(rng, size) * (1 - a)
        out.append(
            ShapePhoto(
                rgb=composite,
                mask=_user_mask(rng, alpha.astype(np.float32)),
                occupancy=view_occupancy(s, az) >= 0.5,
                azimuth=az,
                elevation=el,
                distance=dist,
            )
        )
    return s, out
