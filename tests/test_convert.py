"""Stage `convert`: every source kind round-trips its poses through source_from_scene; splits; bad input."""

from __future__ import annotations

import json
from pathlib import Path

import fixtures_convert as fx
import numpy as np
import pytest
import trimesh

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import load_image, read_scene
from nerfpipe.stages.convert import Config, holdout_splits, run


def _back_in_source(scene, frame) -> np.ndarray:
    m = scene.source_from_scene() @ frame.world_from_cam
    m[:3, :3] *= scene.applied_scale
    return m


def assert_round_trip(scene_dir: Path, expected: dict[str, np.ndarray], tol: float = 1e-6):
    scene = read_scene(scene_dir)
    assert sorted(Path(f.file_path).name for f in scene.frames) == sorted(expected)
    for f in scene.frames:
        np.testing.assert_allclose(_back_in_source(scene, f), expected[Path(f.file_path).name], atol=tol)
        assert scene.image_path(scene.frames.index(f)).is_file()
    assert (np.abs(scene.aabb) <= 1 + 1e-9).all()
    assert (scene_dir / "convert_manifest.json").is_file()
    return scene


def _manifest(scene_dir: Path) -> dict:
    return json.loads((scene_dir / "convert_manifest.json").read_text())


def _split_names(scene, name):
    return [Path(scene.frames[i].file_path).name for i in scene.splits[name]]


def test_blender_round_trip_splits_alpha(tmp_path):
    expected = fx.make_blender(tmp_path / "src")
    out = run(Config(source=tmp_path / "src", scene_dir=tmp_path / "scene"))
    scene = assert_round_trip(tmp_path / "scene", expected)
    assert out.kind == "blender" and scene.has_alpha and scene.extra["scene_type"] == "object"
    assert {s: len(i) for s, i in scene.splits.items()} == {"train": 4, "val": 2, "test": 3}
    assert _split_names(scene, "val") == ["val_r_0.png", "val_r_1.png"]
    # no stated bounds: the cube the cameras (~4 units away, 0.69 rad field of view) see at their target
    assert 1 / scene.applied_scale == pytest.approx(4 * np.tan(0.69 / 2), rel=0.03)
    np.testing.assert_allclose(scene.aabb, [[-1] * 3, [1] * 3])
    assert _manifest(tmp_path / "scene")["used"]["roi"] == "look_at"
    assert out.downscales == ()  # 40 px / 2 < 32 px
    assert load_image(scene.image_path(0)).shape == (40, 40, 4)
    assert 0 < scene.near < scene.far


def test_blender_box_follows_the_cameras_at_any_scale(tmp_path):
    """The same Blender scene 100x smaller or larger normalises to the same scene: the box scales with it."""
    scenes = {}
    for s in (0.01, 1.0, 100.0):
        expected = fx.make_blender(tmp_path / f"src{s}", counts=(3, 1, 1), size=16, scale=s)
        run(Config(source=tmp_path / f"src{s}", scene_dir=tmp_path / f"scene{s}"))
        scenes[s] = assert_round_trip(tmp_path / f"scene{s}", expected, tol=1e-6 * s)
        box = np.array(_manifest(tmp_path / f"scene{s}")["used"]["aabb_source_frame"])
        assert np.ptp(box, axis=0).max() == pytest.approx(2 * 4 * s * np.tan(0.69 / 2), rel=0.03)
    ref = scenes[1.0]
    for s, scene in scenes.items():
        np.testing.assert_allclose(scene.aabb, ref.aabb, rtol=1e-6, atol=1e-12)
        assert scene.applied_scale * s == pytest.approx(ref.applied_scale, rel=1e-6)
        assert (scene.near, scene.far) == pytest.approx((ref.near, ref.far), rel=1e-6)
        for f, g in zip(scene.frames, ref.frames, strict=True):
            np.testing.assert_allclose(f.world_from_cam, g.world_from_cam, rtol=1e-6, atol=1e-9)


def test_aabb_override_applied_and_recorded(tmp_path):
    given = (-0.5, -1.0, -0.25, 0.5, 1.0, 0.75)
    expected = fx.make_blender(tmp_path / "src", counts=(3, 1, 1), size=16)
    run(Config(source=tmp_path / "src", scene_dir=tmp_path / "scene", aabb=given))
    scene = assert_round_trip(tmp_path / "scene", expected)
    corners = np.concatenate([scene.aabb, np.ones((2, 1))], axis=1) @ scene.source_from_scene().T
    np.testing.assert_allclose(corners[:, :3], np.reshape(given, (2, 3)), atol=1e-12)  # Blender: up kept
    assert np.abs(scene.aabb).max() == pytest.approx(1.0)  # rescaled: the longest side fills [-1, 1]
    used = _manifest(tmp_path / "scene")["used"]
    assert used["roi"] == "box" and used["roi_from"].startswith("--aabb")
    np.testing.assert_allclose(used["aabb_source_frame"], np.reshape(given, (2, 3)), atol=1e-12)

    # a transforms.json's own aabb is used as stated, and --aabb replaces it (recorded as left out)
    stated = [[-2.0, -2.0, -1.0], [2.0, 2.0, 3.0]]
    fx.make_transforms(tmp_path / "tf", missing=(), doc_extra={"aabb": stated})
    run(Config(source=tmp_path / "tf", scene_dir=tmp_path / "tf_stated"))
    used = _manifest(tmp_path / "tf_stated")["used"]
    assert used["roi_from"] == "the aabb the source states"
    np.testing.assert_allclose(used["aabb_source_frame"], stated, atol=1e-12)
    run(Config(source=tmp_path / "tf", scene_dir=tmp_path / "tf_given", aabb=given))
    manifest = _manifest(tmp_path / "tf_given")
    np.testing.assert_allclose(manifest["used"]["aabb_source_frame"], np.reshape(given, (2, 3)), atol=1e-12)
    assert "replaced by --aabb" in manifest["left_out"]["source aabb"]


def test_aabb_option_parsed_from_comma_text():
    from nerfpipe import cli

    config = cli.config_from_args("convert", ["src", "s", "--aabb", "-0.5,-1,-0.25,0.5,1,0.75"])
    assert config.aabb == (-0.5, -1.0, -0.25, 0.5, 1.0, 0.75)
    assert cli.config_from_args("convert", ["src", "s"]).aabb is None


def test_llff_round_trip_forward(tmp_path):
    expected = fx.make_llff(tmp_path / "src")
    run(Config(source=tmp_path / "src", scene_dir=tmp_path / "scene"))
    scene = assert_round_trip(tmp_path / "scene", expected)
    assert scene.extra["scene_type"] == "forward"
    assert scene.frame_intrinsics(0).fx == pytest.approx(30.0)  # hwf at twice the image size
    assert _split_names(scene, "test") == ["img_000.png", "img_008.png"]  # every 8th from 0, LLFF's llffhold
    assert scene.splits["val"] == scene.splits["test"]
    ups = np.stack([f.world_from_cam[:3, 1] for f in scene.frames]).mean(0)
    np.testing.assert_allclose(ups / np.linalg.norm(ups), [0, 0, 1], atol=1e-9)
    # near/far from the bounds: every bound depth, scaled, lies inside [near, far]
    assert scene.near <= 0.9 * 3.0 * scene.applied_scale + 1e-9 and scene.far >= 8.0 * scene.applied_scale


@pytest.mark.parametrize("n", [106, 10])
def test_npz_round_trip_and_split_convention(tmp_path, n):
    expected = fx.make_npz(tmp_path / "tiny.npz", n, alpha=n == 10)
    run(Config(source=tmp_path / "tiny.npz", scene_dir=tmp_path / "scene"))
    scene = assert_round_trip(tmp_path / "scene", expected)
    assert scene.has_alpha == (n == 10)
    if n == 106:
        assert scene.splits["train"] == tuple(range(100)) and scene.splits["test"] == tuple(range(100, 106))
    else:
        assert scene.splits["test"] == (0, 8)
    img = load_image(scene.image_path(3))
    src = np.load(tmp_path / "tiny.npz")["images"][3]
    np.testing.assert_allclose(img[..., :3], src, atol=0.5 / 255 + 1e-6)


@pytest.mark.parametrize("text", [False, True])
def test_colmap_round_trip_points_in_aabb(tmp_path, text):
    src = tmp_path / "src"
    expected = fx.make_colmap(src / "sparse" / "0", src / "images", 10, text=text)
    out = run(Config(source=src, scene_dir=tmp_path / "scene"))
    scene = assert_round_trip(tmp_path / "scene", expected)
    intr = scene.frame_intrinsics(0)
    assert (intr.k1, intr.k2, intr.p1, intr.p2) == pytest.approx((-0.05, 0.01, 0.001, -0.002))  # distortion kept
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx((40.0, 41.0, 24.3, 17.8))
    points = np.asarray(trimesh.load(tmp_path / "scene" / scene.extra["sparse_points_path"]).vertices)
    assert len(points) == 60
    assert ((points >= scene.aabb[0]) & (points <= scene.aabb[1])).all()
    ups = np.stack([f.world_from_cam[:3, 1] for f in scene.frames]).mean(0)
    assert ups[2] / np.linalg.norm(ups) > 1 - 1e-9  # mean camera up is +z
    assert out.splits == {"train": 8, "val": 2, "test": 2}
    assert scene.extra["scene_type"] == "360"
    # every point seen by a camera in front of it lies within [near, far]
    for f in scene.frames:
        d = points - f.world_from_cam[:3, 3]
        front = d @ -f.world_from_cam[:3, 2] > 0
        assert (np.linalg.norm(d[front], axis=1) <= scene.far).all()


def test_colmap_largest_model_chosen(tmp_path):
    src = tmp_path / "src"
    fx.make_colmap(src / "sparse" / "0", src / "images", 4, seed=8)
    expected = fx.make_colmap(src / "sparse" / "1", src / "images", 9, seed=5)
    run(Config(source=src, scene_dir=tmp_path / "scene"))
    assert_round_trip(tmp_path / "scene", expected)
    manifest = json.loads((tmp_path / "scene" / "convert_manifest.json").read_text())
    assert manifest["used"]["model"].endswith("sparse/1")
    assert any(k.endswith("sparse/0") for k in manifest["left_out"])


def test_colmap_poses_stage_layout_downscales(tmp_path):
    """The `poses` stage writes SCENE_DIR/colmap/sparse (files directly) + colmap/images; convert in place."""
    scene_dir = tmp_path / "scene"
    expected = fx.make_colmap(scene_dir / "colmap" / "sparse", scene_dir / "colmap" / "images", 6, size=(72, 96))
    out = run(Config(source=scene_dir, scene_dir=scene_dir))
    assert_round_trip(scene_dir, expected)
    assert out.downscales == (2,)
    assert load_image(scene_dir / "images_2" / "frame_000.png").shape == (36, 48, 3)


def test_transforms_skips_missing_and_composes_applied(tmp_path):
    # a nerfstudio-like file: poses already moved by applied_transform / applied_scale from an "original" frame
    a = np.concatenate([fx.rotation([0.2, 0.1, -0.3]), [[0.5], [-1.0], [2.0]]], axis=1)
    expected = fx.make_transforms(tmp_path / "src", doc_extra={"applied_transform": a.tolist(), "applied_scale": 0.5})
    out = run(Config(source=tmp_path / "src" / "transforms.json", scene_dir=tmp_path / "scene"))
    assert out.num_frames == 4
    scene = read_scene(tmp_path / "scene")
    file_from_original = np.eye(4)
    file_from_original[:3] = 0.5 * a
    for f in scene.frames:
        back = file_from_original @ _back_in_source(scene, f)  # scene -> original -> the file's frame
        back[:3, :3] /= 0.5
        np.testing.assert_allclose(back, expected[Path(f.file_path).name], atol=1e-6)
    assert scene.frame_intrinsics(0).k1 == pytest.approx(0.05)
    manifest = json.loads((tmp_path / "scene" / "convert_manifest.json").read_text())
    assert "2 of 6" in manifest["left_out"]["missing images"]


def test_transforms_plain_round_trip(tmp_path):
    expected = fx.make_transforms(tmp_path / "src", missing=())
    run(Config(source=tmp_path / "src", scene_dir=tmp_path / "scene"))
    assert_round_trip(tmp_path / "scene", expected)


def test_holdout_rule():
    assert holdout_splits(10, 8) == {"train": (1, 2, 3, 4, 5, 6, 7, 9), "test": (0, 8)}
    assert holdout_splits(1, 8) == {"train": (0,), "test": ()}


# ---- bad input: one-line UserError naming the problem


def _fails(match: str, **cfg):
    with pytest.raises(UserError, match=match) as e:
        run(Config(**cfg))
    assert "\n" not in str(e.value)


def test_bad_inputs(tmp_path):
    scene = tmp_path / "scene"
    (tmp_path / "empty").mkdir()
    _fails("unknown source kind", source=tmp_path / "empty", scene_dir=scene)
    _fails("no such file", source=tmp_path / "nope", scene_dir=scene)
    (tmp_path / "c" / "sparse" / "0").mkdir(parents=True)
    _fails("no COLMAP model", source=tmp_path / "c", scene_dir=scene, kind="colmap")
    _fails("unknown source kind 'bogus'", source=tmp_path / "empty", scene_dir=scene, kind="bogus")

    fx.make_transforms(tmp_path / "nan", missing=())
    doc = json.loads((tmp_path / "nan" / "transforms.json").read_text())
    doc["frames"][1]["transform_matrix"][0][3] = float("nan")
    (tmp_path / "nan" / "transforms.json").write_text(json.dumps(doc))
    _fails(r"frames\[1\]\.transform_matrix: contains NaN", source=tmp_path / "nan", scene_dir=scene)
    doc["frames"][1]["transform_matrix"][0][3] = 0.0
    del doc["frames"][2]["transform_matrix"]
    (tmp_path / "nan" / "transforms.json").write_text(json.dumps(doc))
    _fails(r"frames\[2\]\.transform_matrix: missing", source=tmp_path / "nan", scene_dir=scene)

    fx.make_transforms(tmp_path / "gone", missing=tuple(range(6)))
    _fails("none of the 6 images", source=tmp_path / "gone", scene_dir=scene)
    fx.make_transforms(tmp_path / "same", missing=())
    _fails("the source is the output itself", source=tmp_path / "same", scene_dir=tmp_path / "same")

    fx.make_colmap(tmp_path / "noimg" / "sparse" / "0", None, 4)
    _fails(r"give the image folder \(images=FOLDER\)", source=tmp_path / "noimg", scene_dir=scene)
    fx.make_colmap(tmp_path / "fish" / "sparse", tmp_path / "fish" / "images", 4, model="OPENCV_FISHEYE")
    _fails("OPENCV_FISHEYE model", source=tmp_path / "fish", scene_dir=scene)

    fx.make_llff(tmp_path / "llff", n=5)
    (tmp_path / "llff" / "images" / "img_004.png").unlink()
    _fails("4 images but poses_bounds.npy has 5 poses", source=tmp_path / "llff", scene_dir=scene)

    _fails(r"--aabb: expected x0,y0,z0,x1,y1,z1", source=tmp_path / "empty", scene_dir=scene, aabb=(0, 0, 0, 1, -1, 1))

    fx.make_blender(tmp_path / "bl", counts=(2, 0, 0))
    (tmp_path / "bl" / "transforms_train.json").write_text(json.dumps({"frames": []}))
    _fails("camera_angle_x", source=tmp_path / "bl", scene_dir=scene)
    assert not (scene / "transforms.json").exists()


def test_no_normalize_keeps_source_frame(tmp_path):
    src = tmp_path / "src"
    expected = fx.make_colmap(src / "sparse", src / "images", 5)
    run(Config(source=src, scene_dir=tmp_path / "scene", normalize=False))
    scene = read_scene(tmp_path / "scene")
    np.testing.assert_allclose(scene.applied_transform, np.eye(4)[:3])
    assert scene.applied_scale == 1.0
    for f in scene.frames:
        np.testing.assert_allclose(f.world_from_cam, expected[Path(f.file_path).name], atol=1e-9)


def test_look_at_point_converging_and_parallel():
    from nerfpipe.radiance.normalize import look_at_point

    centres = np.array([[4.0, 0, 0], [0, 4.0, 0], [-4.0, 0, 1]])
    target = np.array([0.5, -0.2, 0.3])
    fwd = (target - centres) / np.linalg.norm(target - centres, axis=1, keepdims=True)
    np.testing.assert_allclose(look_at_point(centres, fwd), target, atol=1e-9)
    parallel = np.tile([[0.0, 0.0, -1.0]], (3, 1))
    a, b = look_at_point(centres, parallel), look_at_point(centres, parallel)
    np.testing.assert_array_equal(a, b)  # deterministic fallback, in front of the rig
    assert a[2] < centres[:, 2].mean()


def test_colmap_tracks_become_sparse_depth(tmp_path):
    """convert writes which points each photo observed (the fixture's tracks: photos 1 and 2 see all 60), in the
    scene frame, and the rays through them end at the points."""
    from nerfpipe.data.sparse_depth import KEY, read_sparse_depth

    src = tmp_path / "src"
    fx.make_colmap(src / "sparse" / "0", src / "images", 10)
    run(Config(source=src, scene_dir=tmp_path / "scene"))
    scene = read_scene(tmp_path / "scene")
    sparse = read_sparse_depth(scene.root / scene.extra[KEY])
    points = np.asarray(trimesh.load(tmp_path / "scene" / scene.extra["sparse_points_path"]).vertices)
    np.testing.assert_allclose(sparse.points, points, atol=1e-5)
    counts = sorted(len(v) for v in sparse.observed.values())
    assert counts == [0] * 8 + [60, 60]
    name = next(n for n, v in sparse.observed.items() if len(v))
    i = next(k for k, f in enumerate(scene.frames) if f.file_path == name)
    o, d, dist = sparse.rays(name, scene.frames[i].world_from_cam[:3, 3])
    np.testing.assert_allclose(o + d * dist[:, None], sparse.points[sparse.observed[name]], atol=1e-5)
    assert (d @ -scene.frames[i].world_from_cam[:3, 2] > 0).all()  # in front of the camera that saw them


def test_sparse_depth_file_errors_are_one_line(tmp_path):
    from nerfpipe.data.errors import UserError
    from nerfpipe.data.sparse_depth import read_sparse_depth, write_sparse_depth

    with pytest.raises(UserError, match="not found"):
        read_sparse_depth(tmp_path / "nope.npz")
    (tmp_path / "bad.npz").write_bytes(b"not an npz")
    with pytest.raises(UserError, match="expected an npz"):
        read_sparse_depth(tmp_path / "bad.npz")
    write_sparse_depth(tmp_path / "oob.npz", np.zeros((2, 3)), {"a.png": np.array([0, 5])})
    with pytest.raises(UserError, match="outside"):
        read_sparse_depth(tmp_path / "oob.npz")


def test_llff_image_folder_found_in_the_dataset(tmp_path):
    """`convert fern --images images_8` (LLFF's name for its small copies) finds the folder in the dataset, and a
    dataset without images/ uses its largest images_F copy."""
    fx.make_llff(tmp_path / "src", n=9)
    (tmp_path / "src" / "images").rename(tmp_path / "src" / "images_8")
    scene = tmp_path / "scene"
    run(Config(source=tmp_path / "src", scene_dir=scene, images=Path("images_8"), downscales=()))
    used = json.loads((scene / "convert_manifest.json").read_text())["used"]
    assert used["images"] == str(tmp_path / "src" / "images_8")
    run(Config(source=tmp_path / "src", scene_dir=tmp_path / "scene2", downscales=()))
    _fails(
        "no_such_folder: image folder not found",
        source=tmp_path / "src",
        scene_dir=tmp_path / "s3",
        images=Path("no_such_folder"),
    )


def test_look_at_box_follows_the_narrower_field_of_view():
    """A ring of upright phone photos (portrait: 53 degrees across, 90 up): the box is what each camera sees
    across its narrower side at the target's distance (half side d tan(theta_narrow)); the wider side made the
    posed fox's box 2.3x too large (docs/GPU.md)."""
    from nerfpipe.radiance.camera import Intrinsics
    from nerfpipe.radiance.normalize import normalize

    poses = []
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        c = np.array([4 * np.cos(a), 4 * np.sin(a), 0.5])
        back = c / np.linalg.norm(c)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        m[:3, 3] = c
        poses.append(m)
    portrait = Intrinsics(w=100, h=200, fx=100.0, fy=100.0, cx=50.0, cy=100.0)  # tan: 0.5 across, 1.0 up
    norm = normalize(np.stack(poses), [portrait] * 8, up="keep")
    d = float(np.linalg.norm(poses[0][:3, 3]))  # the axes meet at the origin
    assert norm.applied_scale == pytest.approx(1.0 / (d * 0.5), rel=1e-6)
