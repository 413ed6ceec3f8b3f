"""Camera-path files: keyframe interpolation, the nerfpipe writer/reader, nerfstudio's camera_path.json, and
`render --path FILE.json` playing both (on the analytic sphere stand-in of test_render_stage)."""

from __future__ import annotations

import json

import imageio.v2 as iio
import numpy as np
import pytest

import nerfpipe.stages.render as render_stage
from nerfpipe import cli
from nerfpipe.data.camera_path import read_camera_path, write_camera_path
from nerfpipe.data.errors import UserError
from nerfpipe.model.cameras import path_from_file
from nerfpipe.radiance import paths
from nerfpipe.radiance.keyframes import interpolate_keyframes, matrix_from_quat, quat_from_matrix, slerp

try:  # the analytic stand-in lives with the render tests
    from test_render_stage import sphere_run  # noqa: F401  (fixture)
except ImportError:  # tests/ imported as a package
    from tests.test_render_stage import sphere_run  # noqa: F401


def _orbit(n: int, radius: float = 3.0) -> np.ndarray:
    orbit = paths.Orbit(
        centre=np.zeros(3), up=np.array([0.0, 0, 1]), radius=radius, elevation_deg=20.0, start_azimuth_deg=0.0
    )
    return paths.turntable(orbit, n, sweep_deg=270.0)


def test_quaternions_round_trip_and_slerp_ends():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        r = matrix_from_quat(q)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.allclose(matrix_from_quat(quat_from_matrix(r)), r, atol=1e-10)
    q0, q1 = quat_from_matrix(np.eye(3)), quat_from_matrix(_orbit(2)[1][:3, :3])
    assert np.allclose(slerp(q0, q1, 0.0), q0) and np.allclose(slerp(q0, q1, 1.0), q1)
    assert np.isclose(np.linalg.norm(slerp(q0, q1, 0.37)), 1.0)


def test_interpolation_passes_through_keyframes_at_their_times():
    keys = _orbit(4)
    times = np.array([0.0, 1.0, 2.0, 3.0])
    poses, fovs = interpolate_keyframes(keys, np.array([40.0, 50.0, 50.0, 60.0]), times, fps=10)
    assert poses.shape == (31, 4, 4) and fovs.shape == (31,)
    for k in range(4):
        assert np.allclose(poses[10 * k], keys[k], atol=1e-9), k
    assert np.isclose(fovs[5], 45.0)
    for p in poses:  # rotations stay rotations
        assert np.allclose(p[:3, :3] @ p[:3, :3].T, np.eye(3), atol=1e-9)
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert step.max() < 3 * step.mean()  # smooth, no jumps
    with pytest.raises(ValueError, match="increasing"):
        interpolate_keyframes(keys, np.full(4, 50.0), np.array([0.0, 1.0, 1.0, 2.0]), fps=10)


def test_written_path_reads_back(tmp_path):
    keys = _orbit(3)
    out = write_camera_path(
        tmp_path / "p.json",
        keyframes=keys,
        fovs_deg=np.full(3, 50.0),
        times=np.array([0.0, 0.5, 1.0]),
        width=40,
        height=30,
        fps=8,
    )
    doc = json.loads(out.read_text())
    assert doc["format"] == "nerfpipe-camera-path" and len(doc["keyframes"]) == 3
    got = read_camera_path(out)
    assert got.source == "nerfpipe" and (got.width, got.height, got.fps) == (40, 30, 8.0)
    assert got.world_from_cams.shape == (9, 4, 4)
    assert np.allclose(got.world_from_cams[0], keys[0]) and np.allclose(got.world_from_cams[-1], keys[-1])
    cams = path_from_file(out, downscale=2)
    assert (cams.intrinsics[0].w, cams.intrinsics[0].h) == (20, 15)
    fy = cams.intrinsics[0].fy
    assert np.isclose(2 * np.degrees(np.arctan(0.5 * 15 / fy)), 50.0, atol=1e-6)


def nerfstudio_camera_path(path, poses: np.ndarray, *, w: int = 33, h: int = 25, fov: float = 45.0) -> None:
    """A camera_path.json as nerfstudio's viewer writes it (keyframes of its own, flattened row-major
    camera_to_world, vertical fov in degrees)."""
    doc = {
        "keyframes": [
            {
                "matrix": json.dumps(p.T.reshape(-1).tolist()),
                "fov": fov,
                "aspect": w / h,
                "properties": json.dumps([["FOV", fov], ["NAME", f"Camera {i}"], ["TIME", i / 24]]),
            }
            for i, p in enumerate(poses)
        ],
        "camera_type": "perspective",
        "render_height": h,
        "render_width": w,
        "camera_path": [{"camera_to_world": p.reshape(-1).tolist(), "fov": fov, "aspect": w / h} for p in poses],
        "fps": 24,
        "seconds": len(poses) / 24,
        "smoothness_value": 0.5,
        "is_cycle": False,
        "crop": None,
    }
    path.write_text(json.dumps(doc))


def test_render_plays_a_nerfstudio_camera_path(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    f = tmp_path / "camera_path.json"
    nerfstudio_camera_path(f, _orbit(4))
    config = cli.config_from_args("render", [str(run_dir), str(tmp_path / "ns.mp4"), "--path", str(f)])
    res = render_stage.run(config)
    assert res.n_frames == 4 and res.size == (25, 33)
    manifest = json.loads(res.manifest.read_text())["used"]
    assert manifest["path"] == "file" and manifest["format"] == "nerfstudio"


def test_render_plays_a_recorded_path_with_the_sphere_in_view(sphere_run, tmp_path):
    run_dir, _ = sphere_run
    f = write_camera_path(
        tmp_path / "rec.json",
        keyframes=_orbit(2),
        fovs_deg=np.array([40.0, 40.0]),
        times=np.array([0.0, 1.0]),
        width=32,
        height=24,
        fps=4,
    )
    res = render_stage.run(
        render_stage.Config(
            run_dir=run_dir, out=tmp_path / "rec.mp4", path=str(f), frames_dir=tmp_path / "frames", max_seconds=30.0
        )
    )
    assert res.n_frames == 5 and res.size == (24, 32)
    frame = iio.imread(res.frames[2]).astype(float) / 255
    centre = frame[8:16, 12:20]
    assert np.abs(centre - 1.0).max() > 0.2  # the sphere (normal colours), not the white background


def test_bad_path_files_are_one_line_errors(tmp_path, sphere_run):
    f = tmp_path / "bad.json"
    f.write_text(
        json.dumps(
            {
                "camera_path": [{"camera_to_world": [1, 0, 0], "fov": 50}],
                "render_width": 4,
                "render_height": 4,
                "fps": 1,
            }
        )
    )
    with pytest.raises(UserError, match=r"camera_path\[0\].camera_to_world"):
        read_camera_path(f)
    f.write_text(
        json.dumps(
            {
                "camera_path": [{"camera_to_world": np.eye(4).tolist(), "fov": 50}],
                "render_width": 4,
                "render_height": 4,
                "fps": 1,
                "camera_type": "fisheye",
            }
        )
    )
    with pytest.raises(UserError, match="camera_type"):
        read_camera_path(f)
    with pytest.raises(UserError, match="not found"):
        read_camera_path(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="FILE.json"):
        render_stage.parse_path("bogus")
