"""Source frame -> normalised scene frame, for `convert` (maths only, no file I/O).

Conventions: `world_from_cam` are 4x4 camera-to-world matrices in OpenGL camera axes (x right, y up, looking
down -z) in the *source* frame; the camera's up is its +y column, its forward the -z column. The result maps a
source point to the scene frame as `p_scene = scale * (A @ [p_src; 1])` with `A = [R | t]` (DESIGN.md).

The normalisation, deterministic in every branch:
1. **Up** (`R`): `"keep"` leaves the source axes (Blender, tiny-NeRF npz and transforms.json files are z-up by
   convention); `"cameras"` rotates the normalised mean of the cameras' up vectors onto +z by the smallest
   rotation (COLMAP and LLFF worlds have arbitrary axes; people hold cameras upright). A mean up of (near) zero
   length keeps the source axes.
2. **Region of interest** (a box in the rotated source frame; it becomes `aabb`, the box the field lives in).
   It comes from the data, never from a dataset convention; the first that applies:
   `box`: bounds stated for this scene: `convert --aabb`, or the `aabb` key of an input transforms.json. Used
   as given (its corners' box after the up rotation), no margin.
   `points`: the per-axis `percentile`..`100 - percentile` range of the sparse points (COLMAP), padded on
   every side by `margin` (default 0.1) times half its longest side.
   `frusta`: per-image depth bounds the dataset states (LLFF's near/far): the box of every camera's frustum
   between its near and far z-depth. No margin: the bounds already enclose what each image sees.
   `look_at` (Blender layout, tiny-NeRF npz, transforms.json without `aabb`): a cube centred on the
   least-squares intersection of the optical axes, half side = d tan(theta), d the median camera distance to
   that point and theta the narrower half field of view (the largest over the cameras): what the median camera
   sees across its narrower side at the target's distance. (The wider side of a phone photo held upright, 70
   degrees, made the posed fox's box 3.4 source units where instant-ngp's unit cube is 1.5: the fox a small part
   of it, 12.9 dB held-out after 800 steps against 15.9 with the narrower side; docs/GPU.md.)
   Its margin is built in: a ring of cameras at distance d sees whole only the ball of radius d sin(theta)
   about the target, which the cube contains with a margin of 1 / cos(theta) - 1 along the axes (6 % at
   NeRF-synthetic's 40 degrees, 8 % at the `scene` stage's 45) and more towards its corners; no `margin` is
   added on top. (NeRF-synthetic lego, cameras at d = 4.03: [-1.45, 1.45]^3; its object's visual hull is
   about [-0.64, 0.64] x [-1.15, 1.15] x [-0.53, 1.0].) Near-parallel axes (forward-facing rigs) use the
   mean centre pushed along the mean forward direction by the cameras' RMS spread (1 if they coincide)
   instead of the ill-conditioned intersection.
   Every rule moves with the data: scaling a source (cameras, points, bounds) by s scales the box by s, so
   after step 3 the scene is the same at any scale (constants enter only the degenerate fallbacks).
3. **Centre and scale**: the box centre goes to the origin and its longest half side to 1, so the box (= `aabb`)
   fits [-1, 1]^3 with its longest axis filling it.
4. **near / far** (scene units, distances along rays): from the points when there are any (per camera the 1st
   percentile of z-depth and the 99th of distance over points in front, then 0.9 x min / 1.1 x max); from
   LLFF bounds (0.9 x min near depth, 1.1 x the far depth at the frustum corner); else the aabb as seen from the
   cameras: near = the nearest camera's distance to the box (at least 1% of far: a camera may sit inside it),
   far = the largest camera-to-box-corner distance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from nerfpipe.radiance.camera import Intrinsics

__all__ = ["Normalization", "normalize", "rotation_onto_z", "look_at_point"]

UpMethod = Literal["keep", "cameras"]
_MAX_POINTS = 20000  # points used for near/far (deterministic stride subsample)


@dataclass(frozen=True, kw_only=True)
class Normalization:
    applied_transform: np.ndarray
    """[3, 4] source -> scene before scaling: [R | t]."""
    applied_scale: float
    """Scale applied after `applied_transform`."""
    aabb: np.ndarray
    """[2, 3] region of interest, scene frame (inside [-1, 1]^3 when rescaled)."""
    near: float
    """Near distance along rays, scene units."""
    far: float
    """Far distance along rays, scene units."""
    up_method: str
    """How R was chosen: 'keep', 'cameras', or 'keep (degenerate camera up)'."""
    roi_method: str
    """Which region of interest was used: 'box', 'points', 'frusta' or 'look_at'."""

    def scene_from_source(self) -> np.ndarray:  # [4, 4]
        m = np.eye(4)
        m[:3] = self.applied_transform * self.applied_scale
        return m


def rotation_onto_z(up: np.ndarray) -> np.ndarray:
    """Smallest rotation [3, 3] taking the unit vector `up` onto +z (pi about x when up = -z)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def look_at_point(centres: np.ndarray, forwards: np.ndarray) -> np.ndarray:
    """Least-squares closest point to the optical axes (centres [N, 3], unit forwards [N, 3]) -> [3].

    Ill-conditioned (near-parallel axes, or one camera): mean centre + mean forward * RMS spread (or 1).
    """
    eye = np.eye(3)
    proj = eye[None] - forwards[:, :, None] * forwards[:, None, :]  # [N, 3, 3]
    a = proj.sum(0)
    b = (proj @ centres[:, :, None]).sum(0)[:, 0]
    evals = np.linalg.eigvalsh(a)
    if len(centres) >= 2 and evals[0] > 0.02 * evals[-1]:
        return np.linalg.solve(a, b)
    mean_c = centres.mean(0)
    spread = float(np.sqrt(((centres - mean_c) ** 2).sum(1).mean()))
    fwd = forwards.mean(0)
    n = np.linalg.norm(fwd)
    fwd = fwd / n if n > 1e-9 else forwards[0]
    return mean_c + fwd * (spread if spread > 0 else 1.0)


def _box_of(points: np.ndarray) -> np.ndarray:
    return np.stack([points.min(0), points.max(0)])


def _half_fov_tan(intr: Intrinsics) -> float:
    """tan of the narrower half field of view (each axis' wider side of the principal point)."""
    return min(max(intr.cx, intr.w - intr.cx) / intr.fx, max(intr.cy, intr.h - intr.cy) / intr.fy)


def _frustum_corners(intr: Intrinsics) -> np.ndarray:
    """[4, 3] image-corner directions in OpenGL camera axes with z-depth 1 (z = -1)."""
    xs = (np.array([0.0, intr.w]) - intr.cx) / intr.fx
    ys = (np.array([0.0, intr.h]) - intr.cy) / intr.fy
    return np.array([[x, -y, -1.0] for x in xs for y in ys])


def normalize(
    world_from_cam: np.ndarray,  # [N, 4, 4] OpenGL, source frame
    intrinsics: Sequence[Intrinsics],  # [N]
    *,
    up: UpMethod = "cameras",
    points: np.ndarray | None = None,  # [M, 3] source frame
    box: np.ndarray | None = None,  # [2, 3] stated bounds, source frame
    depth_bounds: np.ndarray | None = None,  # [N, 2] z-depth near/far per camera, source units
    percentile: float = 1.0,
    margin: float = 0.1,
    rescale: bool = True,
) -> Normalization:
    """Choose the source -> scene similarity (see the module docstring)."""
    c2w = np.asarray(world_from_cam, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) != len(intrinsics) or len(c2w) == 0:
        raise ValueError(f"expected [N, 4, 4] poses and N intrinsics, got {c2w.shape} and {len(intrinsics)}")
    up_method = up
    rot = np.eye(3)
    if up == "cameras" and rescale:
        mean_up = c2w[:, :3, 1].mean(0)
        if np.linalg.norm(mean_up) > 1e-6:
            rot = rotation_onto_z(mean_up)
        else:
            up_method = "keep (degenerate camera up)"
    elif not rescale:
        up_method = "keep"
    centres = c2w[:, :3, 3] @ rot.T  # [N, 3] rotated source frame
    forwards = -c2w[:, :3, 2] @ rot.T

    pts = None if points is None or len(points) == 0 else np.asarray(points, dtype=np.float64) @ rot.T
    if box is not None:
        b = np.asarray(box, dtype=np.float64)
        corners = np.array([[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        roi, roi_method = _box_of(corners @ rot.T), "box"
    elif pts is not None:
        lo = np.percentile(pts, percentile, axis=0)
        hi = np.percentile(pts, 100 - percentile, axis=0)
        pad = margin * float((hi - lo).max()) / 2
        roi, roi_method = np.stack([lo - pad, hi + pad]), "points"
    elif depth_bounds is not None:
        corners = []
        for i, intr in enumerate(intrinsics):
            dirs = _frustum_corners(intr) @ c2w[i, :3, :3].T @ rot.T  # [4, 3], z-depth 1
            for depth in depth_bounds[i]:
                corners.append(centres[i] + depth * dirs)
        roi, roi_method = _box_of(np.concatenate(corners)), "frusta"
    else:
        target = look_at_point(centres, forwards)
        dist = float(np.median(np.linalg.norm(centres - target, axis=1)))
        half = dist * max(_half_fov_tan(i) for i in intrinsics)
        half = half if half > 0 else 1.0
        roi, roi_method = np.stack([target - half, target + half]), "look_at"

    if rescale:
        centre = roi.mean(0)
        longest = float((roi[1] - roi[0]).max()) / 2
        scale = 1.0 / longest if longest > 0 else 1.0
    else:
        centre, scale = np.zeros(3), 1.0
    applied = np.concatenate([rot, -centre[:, None] + 0.0], axis=1)  # p' = R p - centre (+0.0: no -0.0)
    aabb = (roi - centre) * scale
    cam_scene = (centres - centre) * scale
    near, far = _near_far(c2w, rot, cam_scene, intrinsics, aabb, pts, centre, scale, depth_bounds)
    return Normalization(
        applied_transform=applied,
        applied_scale=scale,
        aabb=aabb,
        near=near,
        far=far,
        up_method=up_method,
        roi_method=roi_method,
    )


def _near_far(c2w, rot, cam_scene, intrinsics, aabb, pts, centre, scale, depth_bounds) -> tuple[float, float]:
    near = far = None
    if pts is not None:
        p = (pts[:: max(1, math.ceil(len(pts) / _MAX_POINTS))] - centre) * scale  # [M, 3] scene
        nears, fars = [], []
        for i in range(len(c2w)):
            fwd = -(rot @ c2w[i, :3, 2])
            d = p - cam_scene[i]
            z = d @ fwd
            front = z > 0
            if front.any():
                nears.append(np.percentile(z[front], 1))
                fars.append(np.percentile(np.linalg.norm(d[front], axis=1), 99))
        if nears:
            near, far = 0.9 * float(min(nears)), 1.1 * float(max(fars))
    elif depth_bounds is not None:
        corner = np.array([float(np.linalg.norm(_frustum_corners(i), axis=1).max()) for i in intrinsics])
        near = 0.9 * scale * float(depth_bounds[:, 0].min())
        far = 1.1 * scale * float((depth_bounds[:, 1] * corner).max())
    if near is None or far is None:  # the aabb seen from the cameras
        outside = np.maximum(np.maximum(aabb[0] - cam_scene, cam_scene - aabb[1]), 0.0)  # [N, 3]
        far_corner = np.maximum(np.abs(cam_scene - aabb[0]), np.abs(cam_scene - aabb[1]))
        far = float(np.linalg.norm(far_corner, axis=1).max())
        near = max(float(np.linalg.norm(outside, axis=1).min()), 0.01 * far)
    near = max(0.0, near)
    return near, max(far, near * 1.01 + 1e-6)
