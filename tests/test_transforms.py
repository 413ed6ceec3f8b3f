"""transforms.json: round trip, validation errors naming file/frame/field, path escapes refused."""

import json
import math

import numpy as np
import pytest

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Frame, Scene, read_scene, write_scene
from nerfpipe.radiance.camera import Intrinsics


def _rot(axis_angle):
    import cv2

    r, _ = cv2.Rodrigues(np.asarray(axis_angle, dtype=np.float64))
    return r


def _scene(root, n=4, per_frame=False):
    intr = Intrinsics(w=64, h=48, fx=50.0, fy=51.0, cx=31.5, cy=24.5, k1=-0.1, p2=0.001)
    frames = []
    for i in range(n):
        m = np.eye(4)
        m[:3, :3] = _rot([0.1 * i, 0.2, -0.3])
        m[:3, 3] = [i, 2.0 * i, -1.0]
        fi = Intrinsics(w=32 + i, h=32, fx=40.0 + i, fy=40.0, cx=16.0, cy=16.0) if per_frame else None
        frames.append(Frame(file_path=f"images/f{i}.png", world_from_cam=m, intrinsics=fi))
    a = np.eye(4)[:3].copy()
    a[:3, :3] = _rot([0.0, 0.0, 0.5])
    a[:, 3] = [1.0, -2.0, 0.5]
    return Scene(
        root=root,
        frames=tuple(frames),
        intrinsics=None if per_frame else intr,
        applied_transform=a,
        applied_scale=0.25,
        aabb=np.array([[-1, -1, -0.5], [1, 1, 0.5]]),
        near=0.1,
        far=math.inf,
        splits={"train": (0, 1, 2), "test": (3,)},
        has_alpha=True,
        extra={"custom_key": [1, 2]},
    )


@pytest.mark.parametrize("per_frame", [False, True])
def test_round_trip(tmp_path, per_frame):
    s = _scene(tmp_path, per_frame=per_frame)
    write_scene(s)
    r = read_scene(tmp_path)
    assert r.intrinsics == s.intrinsics
    assert [f.intrinsics for f in r.frames] == [f.intrinsics for f in s.frames]
    for a, b in zip(r.frames, s.frames, strict=True):
        assert a.file_path == b.file_path
        np.testing.assert_allclose(a.world_from_cam, b.world_from_cam, atol=0, rtol=0)
    np.testing.assert_allclose(r.applied_transform, s.applied_transform)
    assert r.applied_scale == s.applied_scale and r.near == s.near and math.isinf(r.far)
    np.testing.assert_allclose(r.aabb, s.aabb)
    assert r.splits == s.splits and r.has_alpha and r.extra == {"custom_key": [1, 2]}
    # source <-> scene mapping: inverse pair, scale folded in
    np.testing.assert_allclose(r.scene_from_source() @ r.source_from_scene(), np.eye(4), atol=1e-12)
    assert np.isclose(np.linalg.det(r.scene_from_source()[:3, :3]), 0.25**3)


def test_written_file_has_nerfstudio_and_instant_ngp_keys(tmp_path):
    write_scene(_scene(tmp_path))
    doc = json.loads((tmp_path / "transforms.json").read_text())
    for key in (
        "w",
        "h",
        "fl_x",
        "fl_y",
        "cx",
        "cy",
        "k1",
        "k2",
        "p1",
        "p2",
        "camera_model",
        "frames",
        "applied_transform",
        "camera_angle_x",
        "camera_angle_y",
        "aabb_scale",
        "aabb",
        "near",
        "far",
        "applied_scale",
        "train_filenames",
        "test_filenames",
    ):
        assert key in doc, key
    assert doc["camera_model"] == "OPENCV"
    assert doc["far"] is None  # infinite far plane: strict JSON has no inf
    assert np.isclose(doc["camera_angle_x"], 2 * math.atan(32 / 50.0))
    assert set(doc["frames"][0]) >= {"file_path", "transform_matrix"}


def _write_doc(tmp_path, mutate):
    write_scene(_scene(tmp_path))
    p = tmp_path / "transforms.json"
    doc = json.loads(p.read_text())
    mutate(doc)
    p.write_text(json.dumps(doc))
    return p


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d["frames"][2].pop("transform_matrix"), "frames[2].transform_matrix"),
        (lambda d: d["frames"][1].__setitem__("transform_matrix", [[0] * 4] * 3), "frames[1].transform_matrix"),
        (lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")), "frames[1].transform_matrix"),
        (lambda d: d["frames"][0].pop("file_path"), "frames[0].file_path"),
        (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, 5.0), "frames[0].transform_matrix"),
        (lambda d: [d.pop(k) for k in ("fl_x", "camera_angle_x")], "frames[0].fl_x"),
        (lambda d: d.__setitem__("fl_y", -3), "fl_y"),
        (lambda d: d.__setitem__("w", "wide"), "w"),
        (lambda d: d.__setitem__("frames", []), "frames"),
        (lambda d: d.__setitem__("aabb", [[1, 1, 1], [0, 0, 0]]), "aabb"),
        (lambda d: d.__setitem__("near", 5.0) or d.__setitem__("far", 1.0), "near/far"),
        (lambda d: d.__setitem__("test_filenames", ["nope.png"]), "test_filenames"),
        (lambda d: d.__setitem__("applied_transform", [[1, 0, 0]]), "applied_transform"),
    ],
)
def test_validation_errors_name_file_and_field(tmp_path, mutate, field):
    p = _write_doc(tmp_path, mutate)
    with pytest.raises(UserError) as e:
        read_scene(p)
    msg = str(e.value)
    assert str(p) in msg and field in msg, msg
    assert "\n" not in msg


@pytest.mark.parametrize("bad", ["../outside.png", "/etc/passwd", "images/../../x.png"])
def test_path_escape_refused(tmp_path, bad):
    root = tmp_path / "ds"
    p = _write_doc(root, lambda d: d["frames"][1].__setitem__("file_path", bad))
    with pytest.raises(UserError, match=r"frames\[1\]\.file_path .* outside the dataset folder"):
        read_scene(p)


def test_symlink_escape_refused(tmp_path):
    root = tmp_path / "ds"
    root.mkdir()
    (tmp_path / "secret").mkdir()
    (root / "images").symlink_to(tmp_path / "secret")
    p = _write_doc(root, lambda d: None)
    with pytest.raises(UserError, match="outside the dataset folder"):
        read_scene(p)


def test_missing_and_invalid_json(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        read_scene(tmp_path / "nope")
    (tmp_path / "transforms.json").write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        read_scene(tmp_path)


def test_instant_ngp_camera_angle_only(tmp_path):
    doc = {
        "camera_angle_x": 0.69,
        "w": 100,
        "h": 80,
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    s = read_scene(tmp_path)
    assert np.isclose(s.intrinsics.fx, 50 / math.tan(0.345)) and s.intrinsics.fy == s.intrinsics.fx
    assert (s.intrinsics.cx, s.intrinsics.cy) == (50, 40)
    assert s.split("train") == (0,) and s.split("test") == ()
