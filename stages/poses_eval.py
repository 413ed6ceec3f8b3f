"""Pose accuracy after a similarity alignment (used by tests and benchmarks).

Conventions: poses are `world_from_cam` 4x4 matrices; both sets must use the same camera axes
(both OpenCV or both OpenGL, see `radiance.camera.OPENGL_FROM_OPENCV`). The estimate's world frame is
arbitrary up to a similarity, so we fit `ref ≈ scale * R @ est + t` on the camera centres (Umeyama 1991),
then compare centres in the reference's units and rotations as the angle of `R_ref^T R R_est`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "OPENGL_FROM_OPENCV",
    "PoseErrors",
    "umeyama",
    "pose_errors",
    "read_colmap_world_from_cam",
    "read_transforms_world_from_cam",
    "read_scene_cameras",
]

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiply a `world_from_cam` to switch camera axes OpenCV <-> OpenGL (its own inverse)."""


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


def read_colmap_world_from_cam(sparse_dir: str | Path) -> dict[str, np.ndarray]:
    """Registered images of a COLMAP model: image name -> world_from_cam [4, 4] (OpenCV axes)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(sparse_dir))
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam_from_world = np.eye(4)
        cam_from_world[:3, :4] = image.cam_from_world().matrix()
        out[image.name] = np.linalg.inv(cam_from_world)
    return out


def read_transforms_world_from_cam(path: str | Path) -> dict[str, np.ndarray]:
    """A nerfstudio / instant-ngp transforms.json: image file name -> world_from_cam [4, 4] (OpenGL axes)."""
    import json

    data = json.loads(Path(path).read_text())
    return {
        Path(frame["file_path"]).name: np.asarray(frame["transform_matrix"], dtype=np.float64)
        for frame in data["frames"]
    }


def read_scene_cameras(path: str | Path) -> dict[str, np.ndarray]:
    """`stages.scene`'s ground_truth/cameras.json: image file name -> world_from_cam [4, 4] (OpenGL axes)."""
    import json

    data = json.loads(Path(path).read_text())
    return {
        Path(frame["file_path"]).name: np.asarray(frame["world_from_cam"], dtype=np.float64)
        for frame in data["frames"].values()
    }
