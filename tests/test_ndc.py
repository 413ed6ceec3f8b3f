"""radiance.ndc: the NDC map of forward-facing scenes (points, rays, depths, directions, densities)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.ndc import NDC, fit_ndc, mean_pose
from nerfpipe.radiance.paths import look_at

INTR = Intrinsics(w=40, h=30, fx=35.0, fy=36.0, cx=20.0, cy=15.0)


def _rig(n: int = 9) -> np.ndarray:
    """Forward-facing rig: centres on a small grid at y = -3, all looking at the origin."""
    g = np.linspace(-0.4, 0.4, 3)
    eyes = [np.array([x, -3.0, z]) for x in g for z in g][:n]
    return np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])


def _ndc() -> NDC:
    return fit_ndc(_rig(), INTR, near=1.5)


def test_mean_pose_of_a_symmetric_rig_looks_at_the_centre():
    ref = mean_pose(_rig())
    np.testing.assert_allclose(ref[:3, 3], [0.0, -3.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(-ref[:3, 2], [0.0, 1.0, 0.0], atol=1e-3)  # looks along +y
    np.testing.assert_allclose(ref[:3, :3] @ ref[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(ref[:3, :3]) == pytest.approx(1.0)
    up = np.array([0.0, 0.0, 1.0])
    opposite = [look_at(np.array([0, y, 0.0]), np.zeros(3), up) for y in (-3.0, 3.0)]
    with pytest.raises(ValueError, match="opposite"):
        mean_pose(np.stack(opposite))


def test_points_round_trip_and_the_frustum_maps_to_the_unit_box():
    ndc = _ndc()
    g = torch.Generator().manual_seed(0)
    ref = torch.as_tensor(ndc.world_from_ref)
    q = torch.rand(500, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 4.0, -1e4]) - torch.tensor(
        [2.0, 2.0, 1.6]
    )  # reference frame, z in (-1e4, -1.6)
    x = q @ ref[:3, :3].T + ref[:3, 3]
    assert bool(ndc.in_front(x).all())
    np.testing.assert_allclose(ndc.points_from_ndc(ndc.points_to_ndc(x)), x, rtol=1e-9, atol=1e-9)
    # near plane -> z' = -1; the reference image's corners -> x', y' = -+1; far -> z' -> 1
    corner = torch.tensor([[-INTR.cx / INTR.fx * 1.5, INTR.cy / INTR.fy * 1.5, -1.5]], dtype=torch.float64)
    p = ndc.points_to_ndc(corner @ ref[:3, :3].T + ref[:3, 3])
    np.testing.assert_allclose(p, [[-1.0, 1.0, -1.0]], atol=1e-12)
    far = torch.tensor([[0.0, 0.0, -1e12]], dtype=torch.float64) @ ref[:3, :3].T + ref[:3, 3]
    assert 1.0 - 1e-9 < float(ndc.points_to_ndc(far)[0, 2]) < 1.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_world_rays_stay_straight_and_depths_map_back(dtype):
    ndc = _ndc()
    poses = _rig()
    o = torch.as_tensor(poses[:, :3, 3], dtype=dtype)
    target = torch.tensor([[0.3, 1.0, -0.2]], dtype=dtype).expand_as(o)
    d = target - o
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    o_n, d_n, valid = ndc.rays_to_ndc(o, d)
    assert bool(valid.all()) and o_n.dtype == dtype
    np.testing.assert_allclose(o_n[:, 2].numpy(), -1.0, atol=1e-6)  # origins on the near plane
    np.testing.assert_allclose(torch.linalg.vector_norm(d_n, dim=-1).numpy(), 1.0, atol=1e-6)
    for t_world in (2.0, 4.0, 50.0, 1e5):
        p = ndc.points_to_ndc(o + t_world * d)
        t_n = ((p - o_n) * d_n).sum(-1)
        off_ray = torch.linalg.vector_norm(p - (o_n + t_n[:, None] * d_n), dim=-1)
        assert float(off_ray.max()) < (1e-5 if dtype == torch.float32 else 1e-12)
        back = ndc.world_t(o, d, o_n, d_n, t_n)
        rtol = 1e-4 if dtype == torch.float64 else (1e-3 if t_world < 100 else 0.5)  # far away: z' ~ 1 - 3e-5
        np.testing.assert_allclose(back.numpy(), t_world, rtol=rtol)
    inf = ndc.world_t(o, d, o_n, d_n, torch.full((len(o),), math.inf, dtype=dtype))
    assert bool(torch.isinf(inf).all())


def test_rays_facing_away_are_flagged_and_miss():
    ndc = _ndc()
    o = torch.tensor([[0.0, -3.0, 0.0], [0.0, -3.0, 0.0], [0.0, -3.0, 0.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    o_n, d_n, valid = ndc.rays_to_ndc(o, d)
    assert valid.tolist() == [True, False, False]
    assert bool(torch.isfinite(o_n).all() and torch.isfinite(d_n).all())
    assert bool((o_n[~valid, 0] > 5).all())  # the dummy ray starts outside any NDC box


def test_directions_and_density_scale_match_finite_differences():
    ndc = _ndc()
    ref = torch.as_tensor(ndc.world_from_ref)
    x = torch.tensor([[0.2, -0.1, -2.5], [-0.5, 0.3, -7.0]], dtype=torch.float64) @ ref[:3, :3].T + ref[:3, 3]
    d = torch.tensor([[0.3, 0.9, 0.1], [-0.2, 0.95, -0.1]], dtype=torch.float64)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    h = 1e-6
    fd = (ndc.points_to_ndc(x + h * d) - ndc.points_to_ndc(x - h * d)) / (2 * h)
    np.testing.assert_allclose(
        ndc.directions_to_ndc(x, d), fd / torch.linalg.vector_norm(fd, dim=-1, keepdim=True), atol=1e-8
    )
    u = x - ref[:3, 3]
    u = u / torch.linalg.vector_norm(u, dim=-1, keepdim=True)
    fd_u = (ndc.points_to_ndc(x + h * u) - ndc.points_to_ndc(x - h * u)) / (2 * h)
    np.testing.assert_allclose(ndc.world_density_scale(x), torch.linalg.vector_norm(fd_u, dim=-1), rtol=1e-6)


def test_box_holds_every_camera_frustum_and_bad_input_raises():
    ndc = _ndc()
    poses = _rig()
    box = ndc.box(poses, [INTR] * len(poses))
    assert box[0, 2] == -1.0 and box[1, 2] == 1.0 and (box[0, :2] < -1).all() and (box[1, :2] > 1).all()
    rng = np.random.default_rng(0)
    for w in poses:  # random pixels' rays at random depths land inside the box
        uv = rng.uniform([0, 0], [INTR.w, INTR.h], size=(50, 2))
        dirs = np.stack([(uv[:, 0] - INTR.cx) / INTR.fx, -(uv[:, 1] - INTR.cy) / INTR.fy, -np.ones(50)], -1)
        dirs = dirs @ w[:3, :3].T
        pts = w[:3, 3] + rng.uniform(1.6, 1e3, (50, 1)) * dirs
        p = ndc.points_to_ndc(torch.as_tensor(pts)).numpy()
        assert ((p >= box[0] - 1e-9) & (p <= box[1] + 1e-9)).all()
    with pytest.raises(ValueError, match="near"):
        fit_ndc(poses, INTR, near=0.0)
    with pytest.raises(ValueError, match="near"):
        fit_ndc(poses, INTR, near=math.inf)
    again = NDC.from_dict(ndc.to_dict())
    assert (again.a, again.b, again.near) == (ndc.a, ndc.b, ndc.near)
    np.testing.assert_array_equal(again.world_from_ref, ndc.world_from_ref)


def test_density_query_matches_its_parts_and_zeroes_points_before_the_near_plane():
    ndc = _ndc()
    ref = torch.as_tensor(ndc.world_from_ref)
    q = torch.tensor(
        [[0.2, -0.1, -2.5], [-0.5, 0.3, -7.0], [0.1, 0.1, -1.0], [0.0, 0.0, 0.0], [0.3, 0.0, 2.0]], dtype=torch.float64
    )
    x = q @ ref[:3, :3].T + ref[:3, 3]
    p, scale, front = ndc.density_query(x)
    assert front.tolist() == [True, True, False, False, False]  # near = 1.5
    np.testing.assert_allclose(p[:2], ndc.points_to_ndc(x[:2]), rtol=1e-12)
    np.testing.assert_allclose(scale[:2], ndc.world_density_scale(x[:2]), rtol=1e-12)
    assert bool(torch.isfinite(p).all()) and scale[2:].tolist() == [0.0, 0.0, 0.0]
