"""Camera model and rays: projection/ray consistency with and without distortion, convention round trips."""

import pytest
import torch

from nerfpipe.radiance.camera import (
    Intrinsics,
    distort,
    generate_rays,
    opencv_from_opengl,
    opengl_from_opencv,
    pixel_centers,
    project,
    undistort,
    z_depth_from_t,
)

PINHOLE = Intrinsics(w=64, h=48, fx=50.0, fy=52.0, cx=31.0, cy=25.0)
DISTORTED = Intrinsics(w=64, h=48, fx=50.0, fy=52.0, cx=31.0, cy=25.0, k1=-0.25, k2=0.07, k3=-0.01, p1=1e-3, p2=-2e-3)


def _pose(seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(4, generator=g, dtype=torch.float64)
    q = q / q.norm()
    w, x, y, z = q
    rot = torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = rot
    m[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64)
    return m


@pytest.mark.parametrize("intr", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_projected_point_lies_on_its_pixel_ray(intr):
    world_from_cam = _pose(1)
    g = torch.Generator().manual_seed(2)
    # points in front of the camera (OpenGL: -z), spread over the field of view
    p_cam = torch.stack(
        [
            torch.rand(50, generator=g, dtype=torch.float64) - 0.5,
            torch.rand(50, generator=g, dtype=torch.float64) - 0.5,
            -(1 + 3 * torch.rand(50, generator=g, dtype=torch.float64)),
        ],
        dim=-1,
    )
    p_world = p_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    uv, z = project(p_world, world_from_cam, intr)
    assert (z > 0).all()
    rays_o, rays_d = generate_rays(intr, world_from_cam, uv)
    offset = p_world - rays_o
    dist_to_ray = torch.linalg.cross(offset, rays_d).norm(dim=-1)
    assert dist_to_ray.max() < 1e-9
    assert ((offset * rays_d).sum(-1) > 0).all()  # in front, not behind
    torch.testing.assert_close(rays_d.norm(dim=-1), torch.ones(50, dtype=torch.float64))
    # z-depth from the distance along the ray equals the projection's z
    t = offset.norm(dim=-1)
    torch.testing.assert_close(z_depth_from_t(t, rays_d, world_from_cam), z)


def test_centre_pixel_ray_is_optical_axis():
    intr = Intrinsics(w=65, h=49, fx=40.0, fy=40.0, cx=32.5, cy=24.5)
    world_from_cam = _pose(3)
    uv = torch.tensor([[32.5, 24.5]], dtype=torch.float64)  # centre of pixel (32, 24)
    _, d = generate_rays(intr, world_from_cam, uv)
    torch.testing.assert_close(d[0], -world_from_cam[:3, 2])
    centres = pixel_centers(intr, torch.float64)
    assert centres.shape == (65 * 49, 2)
    assert torch.equal(centres[0], torch.tensor([0.5, 0.5], dtype=torch.float64))
    assert torch.equal(centres[32 + 24 * 65], uv[0])


def test_image_y_points_down_in_opengl_camera():
    """A pixel below the centre must map to a ray with negative camera-y (OpenGL y up)."""
    world_from_cam = torch.eye(4, dtype=torch.float64)
    _, d = generate_rays(PINHOLE, world_from_cam, torch.tensor([[31.0, 40.0], [50.0, 25.0]], dtype=torch.float64))
    assert d[0, 1] < 0 and d[0, 2] < 0  # below centre, looking down -z
    assert d[1, 0] > 0  # right of centre


def test_undistort_inverts_distort():
    g = torch.Generator().manual_seed(0)
    xy = (torch.rand(1000, 2, generator=g, dtype=torch.float64) - 0.5) * 1.2
    torch.testing.assert_close(undistort(distort(xy, DISTORTED), DISTORTED), xy, atol=1e-12, rtol=0)


def test_opengl_opencv_round_trip():
    m = _pose(4)
    torch.testing.assert_close(opengl_from_opencv(opencv_from_opengl(m)), m)
    cv = opencv_from_opengl(m)
    torch.testing.assert_close(cv[:3, 2], -m[:3, 2])  # OpenCV +z is OpenGL -z
    torch.testing.assert_close(cv[:3, 3], m[:3, 3])  # same centre


def test_intrinsics_validation_and_scaling():
    with pytest.raises(ValueError, match="positive focal"):
        Intrinsics(w=10, h=10, fx=0.0, fy=1.0, cx=5, cy=5)
    with pytest.raises(ValueError, match="positive image size"):
        Intrinsics(w=0, h=10, fx=1.0, fy=1.0, cx=5, cy=5)
    half = PINHOLE.scaled(0.5)
    assert (half.w, half.h, half.fx, half.cx) == (32, 24, 25.0, 15.5)
    with pytest.raises(ValueError, match=r"expected world_from_cam \[4, 4\]"):
        generate_rays(PINHOLE, torch.eye(3))
