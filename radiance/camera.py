"""Pinhole camera with OpenCV radial-tangential distortion, conventions, and ray generation.

Conventions (see docs/DESIGN.md):
- OpenGL camera: x right, y up, looking down -z (what transforms.json stores, `world_from_cam`).
- OpenCV camera: x right, y down, +z forward (what K and distortion act on, COLMAP's convention).
- Pixel (col i, row j) has its centre at (i + 0.5, j + 0.5); cx, cy are in the same coordinates.
- Distortion acts on normalised OpenCV coordinates (x/z, y/z): k1, k2, k3 radial, p1, p2 tangential.
- Rays: unit directions in the world frame; t is Euclidean distance along the ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "OPENGL_FROM_OPENCV",
    "Intrinsics",
    "distort",
    "undistort",
    "opencv_from_opengl",
    "opengl_from_opencv",
    "project",
    "pixel_centers",
    "generate_rays",
    "z_depth_from_t",
]

# diag(1, -1, -1, 1): flips y and z. Its own inverse.
OPENGL_FROM_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass(frozen=True, kw_only=True)
class Intrinsics:
    """One camera's intrinsics (OpenCV model), in pixels."""

    w: int
    """Image width in pixels."""
    h: int
    """Image height in pixels."""
    fx: float
    """Focal length along x, pixels."""
    fy: float
    """Focal length along y, pixels."""
    cx: float
    """Principal point x, pixels (centred: w / 2)."""
    cy: float
    """Principal point y, pixels (centred: h / 2)."""
    k1: float = 0.0
    """First radial distortion coefficient."""
    k2: float = 0.0
    """Second radial distortion coefficient."""
    k3: float = 0.0
    """Third radial distortion coefficient."""
    p1: float = 0.0
    """First tangential distortion coefficient."""
    p2: float = 0.0
    """Second tangential distortion coefficient."""

    def __post_init__(self) -> None:
        if self.w <= 0 or self.h <= 0:
            raise ValueError(f"expected positive image size, got w={self.w}, h={self.h}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"expected positive focal lengths, got fx={self.fx}, fy={self.fy}")

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in (self.k1, self.k2, self.k3, self.p1, self.p2))

    @property
    def K(self) -> Tensor:  # [3, 3] float64
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the image resized by `factor` (e.g. 0.5 for images_2)."""
        w, h = max(1, round(self.w * factor)), max(1, round(self.h * factor))
        sx, sy = w / self.w, h / self.h
        return Intrinsics(
            w=w,
            h=h,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
            k1=self.k1,
            k2=self.k2,
            k3=self.k3,
            p1=self.p1,
            p2=self.p2,
        )


def distort(xy: Tensor, intr: Intrinsics) -> Tensor:
    """Apply OpenCV radial-tangential distortion to normalised coordinates. xy: [..., 2] -> [..., 2]."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (intr.k1 + r2 * (intr.k2 + r2 * intr.k3))
    dx = 2 * intr.p1 * x * y + intr.p2 * (r2 + 2 * x * x)
    dy = intr.p1 * (r2 + 2 * y * y) + 2 * intr.p2 * x * y
    return torch.stack([x * radial + dx, y * radial + dy], dim=-1)


def undistort(xy_distorted: Tensor, intr: Intrinsics, iterations: int = 10) -> Tensor:
    """Invert `distort` by Newton's method (2x2 Jacobian per point). [..., 2] -> [..., 2].

    Converges to float precision in a few steps for the distortions cameras have; 10 steps is generous.
    """
    if not intr.has_distortion:
        return xy_distorted
    xy = xy_distorted.clone()
    k1, k2, k3, p1, p2 = intr.k1, intr.k2, intr.k3, intr.p1, intr.p2
    for _ in range(iterations):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d(radial)/d(r2)
        fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xy_distorted[..., 0]
        fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - xy_distorted[..., 1]
        j00 = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
        j01 = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
        j10 = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
        j11 = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x
        det = j00 * j11 - j01 * j10
        xy = xy - torch.stack([(j11 * fx - j01 * fy) / det, (j00 * fy - j10 * fx) / det], dim=-1)
    return xy


def opengl_from_opencv(world_from_cam_cv: Tensor) -> Tensor:
    """Camera-to-world in OpenCV axes [..., 4, 4] -> the same camera in OpenGL axes [..., 4, 4]."""
    return world_from_cam_cv @ OPENGL_FROM_OPENCV.to(world_from_cam_cv)


def opencv_from_opengl(world_from_cam_gl: Tensor) -> Tensor:
    """Camera-to-world in OpenGL axes [..., 4, 4] -> OpenCV axes [..., 4, 4] (the same flip)."""
    return world_from_cam_gl @ OPENGL_FROM_OPENCV.to(world_from_cam_gl)


def project(points_world: Tensor, world_from_cam_gl: Tensor, intr: Intrinsics) -> tuple[Tensor, Tensor]:
    """Project world points into pixel coordinates.

    points_world: [N, 3]; world_from_cam_gl: [4, 4] (OpenGL axes).
    Returns (uv [N, 2] in pixels, pixel centres at +0.5; z [N] depth along the optical axis, > 0 in front).
    """
    if points_world.shape[-1] != 3:
        raise ValueError(f"expected points [N, 3], got {tuple(points_world.shape)}")
    cam_from_world_cv = torch.linalg.inv(opencv_from_opengl(world_from_cam_gl.to(points_world)))
    p = points_world @ cam_from_world_cv[:3, :3].T + cam_from_world_cv[:3, 3]  # [N, 3] OpenCV camera
    z = p[:, 2]
    xy = distort(p[:, :2] / z[:, None], intr)
    uv = torch.stack([intr.fx * xy[:, 0] + intr.cx, intr.fy * xy[:, 1] + intr.cy], dim=-1)
    return uv, z


def pixel_centers(intr: Intrinsics, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """All pixel centres, row-major: [H * W, 2] as (u, v) = (col + 0.5, row + 0.5)."""
    v, u = torch.meshgrid(
        torch.arange(intr.h, dtype=dtype, device=device),
        torch.arange(intr.w, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1) + 0.5


def generate_rays(intr: Intrinsics, world_from_cam_gl: Tensor, uv: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Rays through pixel coordinates (default: every pixel centre, row-major).

    world_from_cam_gl: [4, 4] (OpenGL axes); uv: [R, 2] pixels.
    Returns rays_o [R, 3], rays_d [R, 3] (unit length), in world_from_cam's dtype/device.
    """
    if world_from_cam_gl.shape != (4, 4):
        raise ValueError(f"expected world_from_cam [4, 4], got {tuple(world_from_cam_gl.shape)}")
    if uv is None:
        uv = pixel_centers(intr, world_from_cam_gl.dtype, world_from_cam_gl.device)
    uv = uv.to(world_from_cam_gl)
    xy_distorted = torch.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy], dim=-1)
    xy = undistort(xy_distorted, intr)  # [R, 2] normalised OpenCV
    # OpenCV (x, y, 1) -> OpenGL (x, -y, -1)
    dirs_cam = torch.stack([xy[:, 0], -xy[:, 1], -torch.ones_like(xy[:, 0])], dim=-1)  # [R, 3]
    rays_d = dirs_cam @ world_from_cam_gl[:3, :3].T
    rays_d = rays_d / torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    rays_o = world_from_cam_gl[:3, 3].expand_as(rays_d)
    return rays_o, rays_d


def z_depth_from_t(t: Tensor, rays_d: Tensor, world_from_cam_gl: Tensor) -> Tensor:
    """Distance along the ray t [R] -> depth along the camera's optical axis [R]."""
    forward = -world_from_cam_gl[:3, 2].to(rays_d)  # OpenGL looks down -z
    return t * (rays_d @ forward)
