"""Camera paths for rendering: a turntable orbit and an LLFF-style spiral, derived from the training cameras.

Conventions (see docs/DESIGN.md):
- Poses are `world_from_cam` [4, 4] float64 in the OpenGL camera convention (x right, y up, looking down -z),
  in the scene frame (up axis +z by contract). No file I/O here.
- The *focus* of a capture is the point closest, in the least-squares sense, to every camera's optical axis.
- Turntable: the camera orbits the focus around an `up` axis at a fixed `radius` (distance to the focus) and
  `elevation` (degrees above the plane through the focus perpendicular to `up`), always looking at the focus,
  its image up as close to `up` as the view allows.
- Spiral (forward-facing captures, as LLFF's `render_path_spiral`): the camera circles the mean training pose
  in its image plane (radii from camera-position percentiles) while looking at a point ahead of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Orbit",
    "look_at",
    "camera_centres",
    "camera_forwards",
    "focus_point",
    "up_axis",
    "orbit_from_cameras",
    "turntable",
    "mean_pose",
    "spiral",
]

_SCENE_UP = np.array([0.0, 0.0, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-300)


def _check_poses(world_from_cams: np.ndarray) -> np.ndarray:
    m = np.asarray(world_from_cams, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] != (4, 4) or len(m) == 0:
        raise ValueError(f"expected world_from_cams [N>=1, 4, 4], got {m.shape}")
    return m


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL `world_from_cam` [4, 4] at `eye` looking at `target`, image up towards `up` (all [3]).

    When the view direction is parallel to `up`, a deterministic perpendicular replaces it.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = _unit(eye - target)  # camera +z points away from what it looks at
    if np.linalg.norm(back) == 0:
        raise ValueError("look_at: eye and target coincide")
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(up), 1e-300):
        # looking straight along up: use the world axis least aligned with the view
        right = np.cross(np.eye(3)[np.argmin(np.abs(back))], back)
    right = _unit(right)
    cam_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, cam_up, back, eye
    return m


def camera_centres(world_from_cams: np.ndarray) -> np.ndarray:  # [N, 4, 4] -> [N, 3]
    return _check_poses(world_from_cams)[:, :3, 3]


def camera_forwards(world_from_cams: np.ndarray) -> np.ndarray:  # [N, 4, 4] -> [N, 3] unit
    return _unit(-_check_poses(world_from_cams)[:, :3, 2])  # OpenGL looks down -z


def focus_point(world_from_cams: np.ndarray) -> np.ndarray:
    """Least-squares intersection of the optical axes: argmin_p sum_i |(I - d_i d_i^T)(p - c_i)|^2 -> [3].

    Nearly parallel axes (forward-facing captures) make the system ill-conditioned; then the point on the mean
    axis (through the mean centre along the mean forward direction) closest to the axes is returned instead,
    found by 1-D least squares on the distance along that axis (deterministic; never random).
    """
    c = camera_centres(world_from_cams)
    d = camera_forwards(world_from_cams)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [N, 3, 3]
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, c)
    eig = np.linalg.eigvalsh(a)
    if eig[0] > 1e-3 * len(c):
        return np.linalg.solve(a, b)
    # degenerate: p = c0 + s * f with c0, f the mean centre and forward; minimise over s
    c0, f = c.mean(0), _unit(d.mean(0))
    pf = np.einsum("nij,j->ni", proj, f)  # [N, 3]
    r = np.einsum("nij,nj->ni", proj, c0[None] - c)  # [N, 3]
    denom = float((pf * pf).sum())
    s = -float((pf * r).sum()) / denom if denom > 1e-12 else 1.0
    if not math.isfinite(s) or s <= 0:
        s = float(np.median(np.linalg.norm(c - c0, axis=1))) or 1.0
    return c0 + s * f


def up_axis(world_from_cams: np.ndarray) -> tuple[np.ndarray, str]:
    """The orbit axis: the scene frame's +z (DESIGN: the scene frame is up +z) when the training cameras' mean
    image-up agrees with it within 60 degrees, otherwise the mean camera up. Returns (unit [3], reason)."""
    ups = _check_poses(world_from_cams)[:, :3, 1]
    mean_up = ups.mean(0)
    if np.linalg.norm(mean_up) < 1e-9:
        return _SCENE_UP.copy(), "scene +z (camera ups cancel out)"
    mean_up = _unit(mean_up)
    if float(mean_up @ _SCENE_UP) >= 0.5:
        return _SCENE_UP.copy(), "scene +z"
    return mean_up, "mean training camera up (differs from scene +z by more than 60 degrees)"


@dataclass(frozen=True, kw_only=True)
class Orbit:
    """A turntable orbit in the scene frame."""

    centre: np.ndarray
    """[3] the point looked at."""
    up: np.ndarray
    """[3] unit orbit axis."""
    radius: float
    """Distance from the camera to `centre`, scene units."""
    elevation_deg: float
    """Angle of the camera above the plane through `centre` perpendicular to `up`."""
    start_azimuth_deg: float
    """Azimuth of the first frame, measured in the basis of `_horizontal_basis(up)`."""


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to `up` (x-ish first; deterministic)."""
    up = _unit(np.asarray(up, dtype=np.float64))
    seed = np.eye(3)[0] if abs(up[0]) < 0.9 else np.eye(3)[1]
    e1 = _unit(seed - (seed @ up) * up)
    return e1, np.cross(up, e1)


def orbit_from_cameras(world_from_cams: np.ndarray) -> Orbit:
    """Orbit through the training cameras: centre = focus point, radius and elevation = their medians,
    starting at the first camera's azimuth."""
    c = camera_centres(world_from_cams)
    centre = focus_point(world_from_cams)
    up, _ = up_axis(world_from_cams)
    e1, e2 = _horizontal_basis(up)
    rel = c - centre
    dist = np.linalg.norm(rel, axis=1)
    elev = np.degrees(np.arcsin(np.clip((rel @ up) / np.maximum(dist, 1e-300), -1.0, 1.0)))
    azim = np.degrees(np.arctan2(rel[0] @ e2, rel[0] @ e1))
    return Orbit(
        centre=centre, up=up, radius=float(np.median(dist)), elevation_deg=float(np.median(elev)),
        start_azimuth_deg=float(azim),
    )  # fmt: skip


def turntable(orbit: Orbit, n_frames: int) -> np.ndarray:
    """`n_frames` poses [N, 4, 4] evenly spaced over one full turn (the last frame stops short of the first)."""
    if n_frames < 1:
        raise ValueError(f"expected n_frames >= 1, got {n_frames}")
    if not orbit.radius > 0:
        raise ValueError(f"expected radius > 0, got {orbit.radius}")
    e1, e2 = _horizontal_basis(orbit.up)
    el = math.radians(orbit.elevation_deg)
    out = np.empty((n_frames, 4, 4))
    for k in range(n_frames):
        az = math.radians(orbit.start_azimuth_deg) + 2 * math.pi * k / n_frames
        direction = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * orbit.up
        out[k] = look_at(orbit.centre + orbit.radius * direction, orbit.centre, orbit.up)
    return out


def mean_pose(world_from_cams: np.ndarray) -> np.ndarray:
    """LLFF's `poses_avg`: mean centre, mean back (+z) axis, mean up re-orthogonalised -> [4, 4]."""
    m = _check_poses(world_from_cams)
    back_sum = m[:, :3, 2].sum(0)
    if np.linalg.norm(back_sum) < 1e-3 * len(m):
        raise ValueError("the cameras look in all directions (no mean viewing direction): not a forward-facing capture")
    back = _unit(back_sum)
    up = m[:, :3, 1].sum(0)
    right = _unit(np.cross(up, back))
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, np.cross(back, right), back, m[:, :3, 3].mean(0)
    return out


def spiral(
    world_from_cams: np.ndarray, n_frames: int, *, focus_distance: float | None = None, rotations: float = 2.0,
    percentile: float = 90.0, z_rate: float = 0.5,
) -> np.ndarray:  # fmt: skip
    """LLFF-style spiral around the mean pose -> [N, 4, 4].

    Radii along the mean pose's right/up/back axes are the `percentile` of the cameras' absolute offsets from
    the mean centre in that pose's frame (a small floor keeps a single camera moving); the camera looks at the
    point `focus_distance` ahead of the mean pose (default: the focus point's depth along the mean axis).
    """
    if n_frames < 1:
        raise ValueError(f"expected n_frames >= 1, got {n_frames}")
    m = _check_poses(world_from_cams)
    avg = mean_pose(m)
    if focus_distance is None:
        focus_distance = float((focus_point(m) - avg[:3, 3]) @ -avg[:3, 2])
        if not focus_distance > 0:
            focus_distance = float(np.median(np.linalg.norm(m[:, :3, 3] - avg[:3, 3], axis=1))) or 1.0
    offsets = (m[:, :3, 3] - avg[:3, 3]) @ avg[:3, :3]  # [N, 3] in the mean pose's axes
    radii = np.percentile(np.abs(offsets), percentile, axis=0)
    radii = np.maximum(radii, 0.05 * focus_distance * np.array([1.0, 1.0, 0.0]))
    target = avg[:3, 3] - focus_distance * avg[:3, 2]
    up = avg[:3, 1]
    out = np.empty((n_frames, 4, 4))
    for k in range(n_frames):
        theta = 2 * math.pi * rotations * k / n_frames
        local = np.array([math.cos(theta), -math.sin(theta), -math.sin(theta * z_rate)]) * radii
        eye = avg[:3, :3] @ local + avg[:3, 3]
        out[k] = look_at(eye, target, up)
    return out
