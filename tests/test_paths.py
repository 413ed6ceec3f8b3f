"""Camera paths (radiance.paths): look-at frames, focus point, turntable and spiral geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nerfpipe.radiance import paths


def _orbit_cameras(n=12, radius=3.0, elevation=25.0, centre=(0.2, -0.1, 0.3)):
    orbit = paths.Orbit(
        centre=np.array(centre),
        up=np.array([0.0, 0, 1]),
        radius=radius,
        elevation_deg=elevation,
        start_azimuth_deg=10.0,
    )
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


# --- coverage, ordering and the trajectory through the training cameras ----------------------------------------


def _arc_cameras(azimuths_deg, radius=2.0, elevation=15.0, centre=(0.1, 0.2, -0.1), noise=0.0, seed=0):
    """Cameras at the given azimuths (degrees, about +z through `centre`) looking at it; optional hand shake."""
    rng = np.random.default_rng(seed)
    az, el = np.radians(np.asarray(azimuths_deg, dtype=float)), math.radians(elevation)
    eyes = np.asarray(centre) + radius * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full_like(az, math.sin(el))], axis=1
    )
    eyes = eyes + rng.normal(scale=noise * radius, size=eyes.shape)
    return np.stack([paths.look_at(e, np.asarray(centre), np.array([0.0, 0, 1])) for e in eyes])


def test_azimuth_coverage_tells_a_full_circle_from_half_of_one():
    orbit = paths.Orbit(
        centre=np.array([0.1, 0.2, -0.1]),
        up=np.array([0.0, 0, 1]),
        radius=2.0,
        elevation_deg=15.0,
        start_azimuth_deg=0.0,
    )
    full = paths.azimuth_coverage(_arc_cameras(np.arange(0, 360, 30)), orbit)
    assert full.largest_gap_deg == pytest.approx(30.0) and full.covered_deg == pytest.approx(330.0)
    half = paths.azimuth_coverage(_arc_cameras(np.linspace(150, 330, 10)), orbit)  # crosses +-180
    assert half.largest_gap_deg == pytest.approx(180.0) and half.covered_deg == pytest.approx(180.0)
    assert half.start_deg == pytest.approx(150.0)
    one = paths.azimuth_coverage(_arc_cameras([40.0]), orbit)
    assert one.largest_gap_deg == 360.0 and one.covered_deg == 0.0


def test_azimuth_order_sorts_along_the_covered_arc_across_the_wrap():
    rng = np.random.default_rng(3)
    azimuths = np.linspace(150, 330, 10)  # 150 ... 180 | -180 ... -30
    shuffled = rng.permutation(10)
    orbit = paths.orbit_from_cameras(_arc_cameras(azimuths))
    cover = paths.azimuth_coverage(_arc_cameras(azimuths[shuffled]), orbit)
    assert np.array_equal(shuffled[paths.azimuth_order(cover)], np.arange(10))


def test_turntable_sweep_covers_an_arc_with_both_ends():
    orbit = paths.Orbit(
        centre=np.zeros(3), up=np.array([0.0, 0, 1]), radius=1.0, elevation_deg=0.0, start_azimuth_deg=30.0
    )
    poses = paths.turntable(orbit, 5, sweep_deg=120.0)
    _assert_rigid(poses)
    az = np.degrees(np.arctan2(poses[:, 1, 3], poses[:, 0, 3]))
    assert np.allclose(az, [30, 60, 90, 120, 150])
    with pytest.raises(ValueError, match="sweep_deg"):
        paths.turntable(orbit, 5, sweep_deg=400.0)


def test_smooth_polyline_keeps_straight_runs_and_ends():
    line = np.linspace([0.0, 0, 0], [1.0, 2, 3], 9)
    assert np.allclose(paths.smooth_polyline(line, 2.0), line)
    noisy = line + np.random.default_rng(0).normal(scale=0.05, size=line.shape)
    smooth = paths.smooth_polyline(noisy, 1.5)
    assert np.abs(smooth - line).mean() < np.abs(noisy - line).mean()
    assert np.array_equal(paths.smooth_polyline(noisy, 0.0), noisy)


def test_interpolation_passes_through_keyframes_without_smoothing():
    keys = _arc_cameras(np.linspace(0, 180, 7))[:, :3, 3]
    pts = paths.interpolate_polyline(keys, 301)
    assert np.allclose(pts[0], keys[0]) and np.allclose(pts[-1], keys[-1])
    step = np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()
    dist = np.linalg.norm(keys[:, None] - pts[None], axis=2).min(1)
    assert dist.max() <= 0.5 * step + 1e-9
    # a curve, not chords: well inside the chords' sag (r (1 - cos 15 deg)) from the keyframes' circle
    rel = pts - np.array([0.1, 0.2, -0.1])
    r = 2 * math.cos(math.radians(15))
    assert np.abs(np.linalg.norm(rel[:, :2], axis=1) - r).max() < 0.75 * r * (1 - math.cos(math.radians(15)))


def test_trajectory_is_smooth_near_the_cameras_and_made_of_rotations():
    azimuths = np.linspace(-20, 160, 25)
    clean = _arc_cameras(azimuths)
    shaky = _arc_cameras(azimuths, noise=0.02, seed=1)  # hand-held: 4 cm of shake at 2 m
    centre = np.array([0.1, 0.2, -0.1])
    poses = paths.trajectory(shaky, 90, centre=centre, up=np.array([0.0, 0, 1]), sigma=2.0)
    assert poses.shape == (90, 4, 4) and np.isfinite(poses).all()
    _assert_rigid(poses)
    eyes = poses[:, :3, 3]
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    assert steps.max() < 1.5 * steps.mean() and steps.min() > 0.5 * steps.mean()  # no jumps, no stalls
    turns = np.arccos(np.clip((-poses[1:, :3, 2] * -poses[:-1, :3, 2]).sum(1), -1, 1))
    assert turns.max() < 3 * turns.mean()  # the view turns smoothly too
    near = np.linalg.norm(clean[:, None, :3, 3] - eyes[None], axis=2).min(1)
    assert near.max() < 0.1  # passes near every (unshaken) keyframe: 5 % of the radius
    axis_dist = np.linalg.norm((eyes - centre)[:, :2], axis=1)
    assert np.abs(axis_dist - 2 * math.cos(math.radians(15))).max() < 0.05  # smoothing keeps the arc round
    assert np.allclose(-poses[:, :3, 2], _unit_rows(centre - eyes))  # looks at the centre
    assert (poses[:, 2, 1] > 0).all() and np.abs(poses[:, 2, 0]).max() < 1e-9  # image up is up, no roll


def _unit_rows(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_trajectory_of_one_camera_or_repeated_cameras_stands_still():
    one = _arc_cameras([45.0])
    poses = paths.trajectory(one, 4, centre=np.zeros(3), up=np.array([0.0, 0, 1]))
    assert np.allclose(poses[:, :3, 3], one[0, :3, 3])
    twice = np.concatenate([one, one, _arc_cameras([90.0])])
    pts = paths.interpolate_polyline(twice[:, :3, 3], 5)
    assert np.isfinite(pts).all() and np.allclose(pts[-1], twice[-1, :3, 3])
