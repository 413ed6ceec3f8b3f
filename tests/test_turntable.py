"""Turntable captures (scene --layout turntable) through poses: with masks every view registers with the
object-relative poses; without, poses refuses in one line (static camera) instead of a wrong model."""

from __future__ import annotations

import json
from pathlib import Path

import cv2  # before pycolmap (imported by stages.poses): the other order crashes cv2's PNG writer
import numpy as np
import pytest

from nerfpipe.data.errors import UserError
from nerfpipe.data.ground_truth import read_ground_truth
from nerfpipe.data.importers.colmap import read_world_from_cam
from nerfpipe.data.transforms import read_scene
from nerfpipe.radiance.align import pose_errors
from nerfpipe.stages import convert, poses
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages.poses.static import check_static_cameras
from nerfpipe.stages.scene.turntable import angles, rot_z

SIZE, VIEWS = 128, 16


@pytest.fixture(scope="module")
def turntable(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("turntable")
    scene_stage.run(
        scene_stage.Config(out_dir=root / "scene", kind="posed", layout="turntable", size=SIZE, views=VIEWS, seed=0)
    )
    return root


def test_scene_writes_object_relative_poses_and_masks(turntable):
    scene = read_scene(turntable / "scene")
    poses_ = np.stack([f.world_from_cam for f in scene.frames])
    # the camera is fixed in the room: object_from_cam_k = Rz(-theta_k) @ room_from_cam
    room = np.stack([rot_z(a) @ p for a, p in zip(angles(VIEWS), poses_, strict=True)])
    assert np.allclose(room, room[0], atol=1e-9)
    centres = poses_[:, :3, 3]
    assert np.ptp(centres[:, 2]) < 1e-9 and np.ptp(np.linalg.norm(centres[:, :2], axis=1)) < 1e-9
    assert [f.mask_path for f in scene.frames] == [f"masks/frame_{k:04d}.png" for k in range(VIEWS)]
    mask = cv2.imread(str(turntable / "scene" / "masks" / "frame_0000.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (SIZE, SIZE) and 0.15 < (mask > 127).mean() < 0.7  # the object, not the room
    assert mask[0, 0] == 0 and mask[SIZE // 2, SIZE // 2] == 255
    gt = read_ground_truth(turntable / "scene").by_file_name()
    assert np.allclose(gt["frame_0003.png"], poses_[3])
    # the room does not turn with the object: its pixels (top rows: the far wall) are the same in every view
    a = cv2.imread(str(turntable / "scene/images/frame_0000.png"))
    b = cv2.imread(str(turntable / "scene/images/frame_0005.png"))
    assert np.array_equal(a[:10], b[:10]) and not np.array_equal(a, b)


def test_poses_with_masks_registers_every_view(turntable):
    """Masks -> every view registers; poses match the object-relative truth; convert carries the masks."""
    out = poses.run(
        poses.Config(
            input=turntable / "scene" / "images",
            scene_dir=turntable / "masked",
            masks=turntable / "scene" / "masks",
            num_threads=2,
        )
    )
    assert (out.registered, out.total) == (VIEWS, VIEWS)
    est = read_world_from_cam(out.sparse)
    gt = read_ground_truth(turntable / "scene").by_file_name()
    names = sorted(gt)
    err = pose_errors(np.stack([est[n] for n in names]), np.stack([gt[n] for n in names]))
    # 128 px, 16 views: measured 1.10 deg median (2.2 max), the relaxed mapper's attempt; the 0.5 deg goal is
    # benchmarks/bench_turntable.py's (256 px, 24 views)
    assert err.median_rotation_deg < 2.0 and err.median_centre_error_rel < 0.02
    report = json.loads(out.report.read_text())
    assert report["stationary_matches"]["fraction"] < 0.05 and len(report["masks"]) == VIEWS
    assert sorted(p.name for p in (out.colmap_dir / "masks").iterdir()) == [f"{n}.png" for n in names]
    conv = convert.run(convert.Config(source=turntable / "masked", scene_dir=turntable / "converted"))
    scene = read_scene(conv.transforms)
    assert all(f.mask_path is not None for f in scene.frames)
    assert (turntable / "converted" / scene.frames[0].mask_path).is_file()


def test_poses_without_masks_says_static_camera(turntable):
    with pytest.raises(UserError) as e:
        poses.run(poses.Config(input=turntable / "scene" / "images", scene_dir=turntable / "unmasked", num_threads=2))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("static camera") and "--masks" in msg
    report = json.loads((turntable / "unmasked" / "poses_report.json").read_text())
    assert report["status"] == "failed" and report["stationary_matches"]["fraction"] > 0.3
    assert len(report["attempts"]) == 0  # refused after the first matching, before any mapping


def test_static_cameras_check():
    """All registered cameras at one place -> one-line UserError (the model-side twin of the matches check)."""
    pycolmap = pytest.importorskip("pycolmap")

    class _Image:
        has_pose = True

        def __init__(self, c):
            self.c = c

        def projection_center(self):
            return self.c

    class _Point:
        def __init__(self, xyz):
            self.xyz = xyz

    class _Rec:
        def __init__(self, centres, points):
            self.images = {k: _Image(np.asarray(c, float)) for k, c in enumerate(centres)}
            self.points3D = {k: _Point(np.asarray(p, float)) for k, p in enumerate(points)}

        def num_points3D(self):
            return len(self.points3D)

    assert pycolmap is not None
    points = np.random.default_rng(0).normal(size=(50, 3)) + [0, 0, 5]
    with pytest.raises(UserError) as e:
        check_static_cameras(_Rec([[0, 0, 0], [1e-4, 0, 0], [0, 1e-4, 0]], points), masked=False)
    assert str(e.value).startswith("static camera") and "--masks" in str(e.value) and "\n" not in str(e.value)
    check_static_cameras(_Rec([[0, 0, 0], [1, 0, 0], [0, 1, 0]], points), masked=False)  # moved: fine
