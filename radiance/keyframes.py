"""Camera keyframes -> a smooth camera path: positions on a Catmull-Rom spline, rotations by slerp.

Conventions (see docs/DESIGN.md):
- Poses are `world_from_cam` [4, 4] float64 (OpenGL camera axes: x right, y up, looking down -z); keyframe
  `times` [K] are seconds, strictly increasing; frames are sampled at `t = i / fps`, i = 0 .. round(T * fps)
  where T = times[-1] - times[0] (so the last keyframe is the last frame).
- Quaternions are (w, x, y, z), unit, w >= 0 after `quat_from_matrix`; `slerp` takes the short arc.
- Positions between keyframes follow a uniform Catmull-Rom spline (ends duplicated): it passes through every
  keyframe; two keyframes give a straight line. Vertical field of view (degrees) is interpolated linearly.
No file I/O here (`data.camera_path` reads and writes the files).
"""

from __future__ import annotations

import numpy as np

__all__ = ["quat_from_matrix", "matrix_from_quat", "slerp", "interpolate_keyframes"]


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] -> unit quaternion (w, x, y, z) [4] with w >= 0 (Shepperd's method, stable)."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"expected [3, 3], got {r.shape}")
    tr = np.trace(r)
    cands = np.array([tr, r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 1e-300))
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 1e-300))
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 1e-300))
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 1e-300))
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) [4] (normalised here) -> rotation [3, 3]."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical interpolation from q0 (u = 0) to q1 (u = 1) along the short arc; unit quaternion [4]."""
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 1 - 1e-9:  # nearly equal: linear is exact to rounding
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    return (np.sin((1 - u) * theta) * q0 + np.sin(u * theta) * q1) / np.sin(theta)


def _catmull_rom(p0, p1, p2, p3, u: float) -> np.ndarray:
    """Uniform Catmull-Rom between p1 (u = 0) and p2 (u = 1)."""
    u2, u3 = u * u, u * u * u
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u3)


def interpolate_keyframes(
    world_from_cams: np.ndarray,  # [K, 4, 4]
    fovs_deg: np.ndarray,  # [K] vertical
    times: np.ndarray,  # [K] seconds, increasing
    fps: float,
) -> tuple[np.ndarray, np.ndarray]:
    """-> (world_from_cams [F, 4, 4], fovs_deg [F]) sampled every 1/fps from the first keyframe to the last."""
    poses = np.asarray(world_from_cams, dtype=np.float64)
    fovs, times = np.asarray(fovs_deg, dtype=np.float64), np.asarray(times, dtype=np.float64)
    k = poses.shape[0]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or fovs.shape != (k,) or times.shape != (k,):
        raise ValueError(f"expected [K, 4, 4], [K], [K], got {poses.shape}, {fovs.shape}, {times.shape}")
    if k < 1 or not fps > 0:
        raise ValueError(f"expected at least one keyframe and fps > 0, got {k}, {fps}")
    if k > 1 and not np.all(np.diff(times) > 0):
        raise ValueError("expected strictly increasing keyframe times")
    n = 1 if k == 1 else int(round((times[-1] - times[0]) * fps)) + 1
    quats = [quat_from_matrix(p[:3, :3]) for p in poses]
    centres = poses[:, :3, 3]
    out = np.tile(np.eye(4), (n, 1, 1))
    fov_out = np.empty(n)
    for i in range(n):
        t = times[0] + (times[-1] - times[0]) * (i / max(n - 1, 1))
        j = 0 if k == 1 else min(int(np.searchsorted(times, t, side="right")) - 1, k - 2)
        u = 0.0 if k == 1 else float(np.clip((t - times[j]) / (times[j + 1] - times[j]), 0.0, 1.0))
        jn = min(j + 1, k - 1)
        p = [centres[max(j - 1, 0)], centres[j], centres[jn], centres[min(j + 2, k - 1)]]
        out[i, :3, 3] = _catmull_rom(*p, u)
        out[i, :3, :3] = matrix_from_quat(slerp(quats[j], quats[jn], u))
        fov_out[i] = (1 - u) * fovs[j] + u * fovs[jn]
    return out, fov_out
