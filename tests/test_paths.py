"""Camera paths (radiance.paths): look-at frames, focus point, turntable and spiral geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from radiance import paths


def _orbit_cameras(n=12, radius=3.0, elevation=25.0, centre=(0.2, -0.1, 0.3)):
    orbit = paths.Orbit(centre=np.array(centre), up=np.array([0.0, 0, 1]), radius=radius,
                        elevation_deg=elevation, start_azimuth_deg=10.0)  # fmt: skip
    return paths.turntable(orbit, n), orbit


def _assert_rigid(poses):
    rot = poses[:, :3, :3]
    assert np.allclose(rot.transpose(0, 2, 1) @ rot, np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    assert np.allclose(poses[:, 3], [0, 0, 0, 1])


def test_look_at_points_minus_z_at_target_with_up():
    m = paths.look_at(np.array([0.0, -2, 1]), np.zeros(3), np.array([0.0, 0, 1]))
    _assert_rigid(m[None])
    forward = -m[:3, 2]
    assert np.allclose(forward, -m[:3, 3] / np.linalg.norm(m[:3, 3]))
    assert m[2, 1] > 0  # image up has a positive world-z component
    assert abs(m[2, 0]) < 1e-12  # no roll: right is horizontal


def test_look_at_straight_down_is_deterministic_and_rigid():
    a = paths.look_at(np.array([0.0, 0, 2]), np.zeros(3), np.array([0.0, 0, 1]))
    b = paths.look_at(np.array([0.0, 0, 2]), np.zeros(3), np.array([0.0, 0, 1]))
    _assert_rigid(a[None])
    assert np.array_equal(a, b)
    assert np.allclose(-a[:3, 2], [0, 0, -1])


def test_turntable_looks_at_centre_and_keeps_radius_and_elevation():
    poses, orbit = _orbit_cameras()
    _assert_rigid(poses)
    rel = poses[:, :3, 3] - orbit.centre
    dist = np.linalg.norm(rel, axis=1)
    assert np.allclose(dist, orbit.radius)
    assert np.allclose(np.degrees(np.arcsin(rel[:, 2] / dist)), orbit.elevation_deg)
    assert np.allclose(-poses[:, :3, 2], -rel / dist[:, None])  # forward points at the centre
    az = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
    steps = np.diff(np.unwrap(np.radians(az)))
    assert np.allclose(steps, 2 * math.pi / len(poses))  # evenly spaced, one full turn


def test_orbit_from_cameras_recovers_the_orbit():
    poses, orbit = _orbit_cameras(n=9, radius=2.5, elevation=-10.0)
    found = paths.orbit_from_cameras(poses)
    assert np.allclose(found.centre, orbit.centre, atol=1e-9)
    assert np.allclose(found.up, [0, 0, 1])
    assert found.radius == pytest.approx(2.5)
    assert found.elevation_deg == pytest.approx(-10.0)
    again = paths.turntable(found, 9)
    assert np.allclose(again[0, :3, 3], poses[0, :3, 3], atol=1e-9)  # starts at the first camera


def test_focus_point_is_the_axes_intersection():
    rng = np.random.default_rng(0)
    target = np.array([0.5, 1.0, -0.2])
    eyes = target + rng.normal(size=(6, 3)) * 3
    poses = np.stack([paths.look_at(e, target, np.array([0.0, 0, 1])) for e in eyes])
    assert np.allclose(paths.focus_point(poses), target, atol=1e-9)


def test_up_axis_falls_back_to_mean_camera_up_when_scene_is_not_z_up():
    poses, _ = _orbit_cameras()
    y_up = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # z-up -> y-up world
    up, reason = paths.up_axis(y_up @ poses)
    assert np.allclose(up, [0, 1, 0], atol=0.2) and "mean" in reason
    assert np.allclose(paths.up_axis(poses)[0], [0, 0, 1])


def test_spiral_for_forward_facing_capture_is_sane():
    rng = np.random.default_rng(1)
    target = np.array([0.0, 0.0, -4.0])  # cameras near the origin looking down -z
    eyes = rng.uniform(-0.3, 0.3, size=(10, 3)) * [1, 1, 0.2]
    poses = np.stack([paths.look_at(e, target, np.array([0.0, 1, 0])) for e in eyes])
    path = paths.spiral(poses, 30)
    assert path.shape == (30, 4, 4) and np.isfinite(path).all()
    _assert_rigid(path)
    centres = path[:, :3, 3]
    assert np.abs(centres[:, :2]).max() < 0.5  # stays within the capture's spread (plus margin)
    assert centres[:, :2].std(0).min() > 0.02  # but moves
    forwards = -path[:, :3, 2]
    assert (forwards[:, 2] < -0.9).all()  # still looking into the scene
    assert (path[:, 1, 1] > 0.9).all()  # image up stays up
    focus = paths.focus_point(poses)
    assert np.allclose(focus, target, atol=0.05)


def test_bad_inputs_raise_value_errors():
    with pytest.raises(ValueError, match="expected world_from_cams"):
        paths.focus_point(np.eye(4))
    poses, orbit = _orbit_cameras()
    with pytest.raises(ValueError, match="n_frames"):
        paths.turntable(orbit, 0)
    level, _ = _orbit_cameras(n=8, elevation=0.0)  # cameras facing every way: no mean pose to spiral around
    with pytest.raises(ValueError, match="forward-facing"):
        paths.spiral(level, 10)
