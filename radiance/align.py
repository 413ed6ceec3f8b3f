"""Similarity alignment of two sets of cameras, and the pose error left after it (maths only, no file I/O).

Conventions:
- Poses are `world_from_cam` 4x4 camera-to-world matrices; both sets must use the same camera axes (both
  OpenGL: x right, y up, looking down -z, or both OpenCV; `radiance.camera.opengl_from_opencv` converts).
- An estimate's world frame is arbitrary up to a similarity (COLMAP: any rotation, translation and scale), so
  `umeyama` fits `dst ≈ scale * R @ src + t` to the camera centres by least squares (Umeyama 1991, with the
  reflection guard: R is always a proper rotation).
- `pose_errors` then compares, per camera, centres in the reference's units (metres for a synthetic scene)
  and rotations as the angle (degrees) of `R_ref^T R R_est`, the rotation left after alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PoseErrors", "umeyama", "pose_errors"]


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity with `dst ≈ scale * R @ src + t`.

    src, dst: [N, 3], N >= 3 not all collinear. Returns (scale, R [3, 3] proper rotation, t [3]).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"expected two [N>=3, 3] arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)  # [3, 3]
    u, d, vt = np.linalg.svd(cov)
    s = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2] = -1.0
    rot = u @ np.diag(s) @ vt
    var_s = (xs**2).sum() / len(src)
    scale = float((d * s).sum() / var_s) if var_s > 0 else 1.0
    t = mu_d - scale * rot @ mu_s
    return scale, rot, t


@dataclass(frozen=True, kw_only=True)
class PoseErrors:
    """Per-camera errors of an estimate against a reference, after `umeyama` on the camera centres."""

    rotation_deg: np.ndarray  # [N] angle between aligned estimate and reference rotations
    centre_error: np.ndarray  # [N] centre distance after alignment, reference units
    scene_size: float  # diagonal of the reference camera centres' bounding box
    scale: float  # alignment: ref = scale * R @ est + t
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]

    @property
    def median_rotation_deg(self) -> float:
        return float(np.median(self.rotation_deg))

    @property
    def median_centre_error_rel(self) -> float:
        """Median centre error as a fraction of `scene_size`."""
        return float(np.median(self.centre_error) / self.scene_size)


def pose_errors(est_world_from_cam: np.ndarray, ref_world_from_cam: np.ndarray) -> PoseErrors:
    """Errors of estimated poses [N, 4, 4] against reference poses [N, 4, 4] (same camera axes)."""
    est = np.asarray(est_world_from_cam, dtype=np.float64)
    ref = np.asarray(ref_world_from_cam, dtype=np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"expected two [N, 4, 4] arrays, got {est.shape} and {ref.shape}")
    scale, rot, t = umeyama(est[:, :3, 3], ref[:, :3, 3])
    centres = scale * est[:, :3, 3] @ rot.T + t
    centre_error = np.linalg.norm(centres - ref[:, :3, 3], axis=1)
    rel = np.einsum("nji,jk,nkl->nil", ref[:, :3, :3], rot, est[:, :3, :3])  # R_ref^T R R_est
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    extent = ref[:, :3, 3].max(0) - ref[:, :3, 3].min(0)
    return PoseErrors(
        rotation_deg=np.degrees(np.arccos(cos)),
        centre_error=centre_error,
        scene_size=float(np.linalg.norm(extent)),
        scale=scale,
        rotation=rot,
        translation=t,
    )
