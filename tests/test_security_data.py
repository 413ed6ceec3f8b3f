"""Untrusted datasets (issue 32): paths confined to the dataset folder, images checked before decoding, cameras
sane, hostile JSON and symlinks as one line, one convert per folder. Every case is the attack itself, built in
tmp_path; each test fails on the code before the fix (outside files copied, a bomb decoded, rc 1 tracebacks)."""

from __future__ import annotations

import json
import re
import struct
import zlib
from pathlib import Path

import cv2
import fixtures_convert as fx
import numpy as np
import pytest

from nerfpipe import cli
from nerfpipe.data.confine import inside
from nerfpipe.data.errors import UserError
from nerfpipe.data.ground_truth import read_ground_truth
from nerfpipe.data.images import MAX_PIXELS, read_image
from nerfpipe.data.lock import FolderBusy, folder_lock
from nerfpipe.data.masks import read_mask
from nerfpipe.data.transforms import load_image, read_scene
from nerfpipe.stages.convert import Config, run


def _cli(capsys, *args) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in args])
    return e.value.code, capsys.readouterr().err


def _one_line(code: int, err: str, *parts: str) -> None:
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, (code, err)
    for p in parts:
        assert p in err, err


def _png(h: int, w: int, channels: int = 3, i: int = 0) -> bytes:
    return cv2.imencode(".png", fx._image(h, w, channels, i))[1].tobytes()


def _edit(path: Path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def _nothing_from(outside: Path, scene: Path) -> None:
    """No file of `outside` was copied anywhere under `scene`."""
    secrets = {p.read_bytes() for p in outside.rglob("*") if p.is_file()}
    copied = [p for p in scene.rglob("*") if p.is_file() and p.read_bytes() in secrets] if scene.exists() else []
    assert not copied, copied


# ---------------------------------------------------------------------------------------------- paths
def test_blender_file_path_outside_is_refused(tmp_path, capsys):
    src, outside = tmp_path / "src", tmp_path / "outside"
    fx.make_blender(src, counts=(2, 1, 1), size=16)
    outside.mkdir()
    (outside / "secret").write_bytes(_png(16, 16, 4, 7))
    _edit(src / "transforms_train.json", lambda d: d["frames"][0].__setitem__("file_path", "../outside/secret"))
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, "transforms_train.json: frames[0].file_path '../outside/secret' resolves outside")
    _nothing_from(outside, tmp_path / "scene")
    assert not (tmp_path / "scene").exists()  # created by the lock, removed again: it stayed empty


@pytest.mark.parametrize("how", ["name", "symlink", "mask"])
def test_colmap_image_outside_is_refused(tmp_path, capsys, how):
    src, outside = tmp_path / "src", tmp_path / "outside"
    fx.make_colmap(src / "sparse" / "0", src / "images", 4, text=True)
    outside.mkdir()
    (outside / "x.png").write_bytes(_png(36, 48, 3, 9))
    if how == "name":
        txt = src / "sparse" / "0" / "images.txt"
        txt.write_text(txt.read_text().replace("frame_000.png", "../../outside/x.png"))
        expected = "image 1 name '../../outside/x.png' resolves outside the dataset folder"
    elif how == "symlink":
        (src / "images" / "frame_001.png").unlink()
        (src / "images" / "frame_001.png").symlink_to(outside / "x.png")
        expected = "image 2 name 'frame_001.png' resolves outside the dataset folder"
    else:
        for i in range(4):
            (src / "masks").mkdir(exist_ok=True)
            (src / "masks" / f"frame_00{i}.png.png").write_bytes(
                cv2.imencode(".png", np.full((36, 48), 255, np.uint8))[1]
            )
        (src / "masks" / "frame_002.png.png").unlink()
        (src / "masks" / "frame_002.png.png").symlink_to(outside / "x.png")
        expected = "mask of image 3 name 'frame_002.png.png' resolves outside the dataset folder"
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, expected)
    _nothing_from(outside, tmp_path / "scene")


def test_llff_image_symlink_outside_is_refused(tmp_path, capsys):
    src, outside = tmp_path / "src", tmp_path / "outside"
    fx.make_llff(src, n=5)
    outside.mkdir()
    (outside / "x.png").write_bytes(_png(24, 32, 3, 3))
    (src / "images" / "img_000.png").unlink()
    (src / "images" / "img_000.png").symlink_to(outside / "x.png")
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, "image 'img_000.png' resolves outside the dataset folder")
    _nothing_from(outside, tmp_path / "scene")


def test_transforms_image_found_by_added_suffix_outside_is_refused(tmp_path, capsys):
    """`images/0000` names no file; the reader tries `images/0000.png`, a symlink leading out."""
    src, outside = tmp_path / "src", tmp_path / "outside"
    fx.make_transforms(src, missing=())
    outside.mkdir()
    (outside / "x.png").write_bytes(_png(32, 24, 3, 5))
    (src / "images" / "0000.png").symlink_to(outside / "x.png")
    _edit(src / "transforms.json", lambda d: d["frames"][0].__setitem__("file_path", "images/0000"))
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, "frames[0].file_path 'images/0000.png' resolves outside the dataset folder")
    _nothing_from(outside, tmp_path / "scene")


@pytest.mark.parametrize("key", ["sparse_points_path", "sparse_depth_path"])
def test_top_level_file_keys_outside_are_refused(tmp_path, key):
    """view reads sparse_points_path and sends the points to the browser; train reads sparse_depth_path."""
    fx.make_transforms(tmp_path / "ds", missing=())
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "secret.ply").write_text("ply\n")
    _edit(tmp_path / "ds" / "transforms.json", lambda d: d.__setitem__(key, "../outside/secret.ply"))
    with pytest.raises(UserError, match=rf"transforms.json: {key} '../outside/secret.ply' resolves outside"):
        read_scene(tmp_path / "ds")
    _edit(tmp_path / "ds" / "transforms.json", lambda d: d.__setitem__(key, "pts.ply"))
    scene = read_scene(tmp_path / "ds")
    assert scene.named_file(key) == (tmp_path / "ds" / "pts.ply").resolve()


def test_converted_scene_does_not_carry_the_sources_file_keys(tmp_path):
    """The source's sparse_points_path names a file of the source's folder, not of the output's."""
    fx.make_transforms(tmp_path / "ds", missing=(), doc_extra={"sparse_points_path": "pts.ply", "note": 1})
    run(Config(source=tmp_path / "ds", scene_dir=tmp_path / "scene"))
    scene = read_scene(tmp_path / "scene")
    assert "sparse_points_path" not in scene.extra and scene.extra["note"] == 1
    manifest = json.loads((tmp_path / "scene" / "convert_manifest.json").read_text())
    assert "sparse_points_path" in manifest["left_out"]


def test_inside_refuses_absolute_nul_and_allows_dotdot_within(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    assert inside(tmp_path, "a/b/../x.png", "f") == (tmp_path / "a" / "x.png").resolve()
    with pytest.raises(UserError, match="is an absolute path"):
        inside(tmp_path, str(tmp_path / "a" / "x.png"), "f")
    with pytest.raises(UserError, match="cannot be resolved"):
        inside(tmp_path, "a/\0x", "f")
    (tmp_path / "a" / "loop1").symlink_to(tmp_path / "a" / "loop2")
    (tmp_path / "a" / "loop2").symlink_to(tmp_path / "a" / "loop1")
    with pytest.raises(UserError, match="'a/loop1' cannot be resolved: symlink loop"):
        inside(tmp_path, "a/loop1", "frames[0].file_path")


def test_ground_truth_depth_symlink_outside_is_refused(tmp_path):
    gt = tmp_path / "ground_truth"
    (gt / "depth").mkdir(parents=True)
    (gt / "cameras.json").write_text(json.dumps({"frames": {"a": np.eye(4).tolist()}}))
    (tmp_path / "secret.npy").write_bytes(b"x")
    (gt / "depth" / "a.npy").symlink_to(tmp_path / "secret.npy")
    with pytest.raises(UserError, match="depth/a.npy' resolves outside"):
        read_ground_truth(tmp_path).depth_path("a.png")


# ---------------------------------------------------------------------------------------------- images
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _bomb_png(w: int, h: int, rows: int = 100) -> bytes:
    """A valid grey PNG of w x h black pixels in a few MB: one deflate block of `rows` zero rows, flushed so that
    it repeats byte for byte, repeated h / rows times."""
    c = zlib.compressobj(1)
    raw = b"\0" * ((w + 1) * rows)  # filter byte 0 + w pixels per row
    first, again = (c.compress(raw) + c.flush(zlib.Z_FULL_FLUSH) for _ in range(2))
    total = (w + 1) * h  # adler32 of `total` zero bytes: a = 1, b = total
    stream = first + again * (h // rows - 1) + b"\x03\x00" + struct.pack(">I", ((total % 65521) << 16) | 1)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", stream) + _chunk(b"IEND", b"")


def test_bomb_png_is_a_real_image():
    assert cv2.imdecode(np.frombuffer(_bomb_png(300, 200), np.uint8), cv2.IMREAD_UNCHANGED).shape == (200, 300)


def test_image_declaring_too_many_pixels_is_refused_before_decoding(tmp_path, capsys):
    src = tmp_path / "src"
    fx.make_transforms(src, missing=())
    bomb = _bomb_png(30000, 30000)
    assert len(bomb) < 5e6 and 30000**2 > MAX_PIXELS
    (src / "images" / "0002.jpg").write_bytes(bomb)
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, f"{src / 'images' / '0002.jpg'}: image declares 30000x30000 pixels")
    for reader in (load_image, read_image, read_mask):
        with pytest.raises(UserError, match="declares 30000x30000 pixels"):
            reader(src / "images" / "0002.jpg")


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_truncated_image_is_refused(tmp_path, capsys, suffix):
    src = tmp_path / "src"
    fx.make_transforms(src, missing=())
    h, w = 32, 24
    img = cv2.resize(cv2.imread(str(src / "images" / "0001.jpg")), (w * 8, h * 8))  # large enough to cut mid-scan
    data = cv2.imencode(suffix, img)[1].tobytes()
    (src / "images" / "0001.jpg").unlink()
    (src / "images" / f"0001{suffix}").write_bytes(data[: int(0.6 * len(data))])
    big = {"w": w * 8, "h": h * 8, "fl_x": 240.0, "fl_y": 244.0, "cx": 96.0, "cy": 128.0}
    _edit(src / "transforms.json", lambda d: d["frames"][1].update(file_path=f"images/0001{suffix}", **big))
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, f"images/0001{suffix}: image file is truncated")
    with pytest.raises(UserError, match="mask file is truncated"):
        read_mask(src / "images" / f"0001{suffix}")


# ---------------------------------------------------------------------------------------------- cameras
def test_mirrored_pose_and_absurd_focal_are_refused(tmp_path):
    fx.make_transforms(tmp_path / "ds", missing=())
    path = tmp_path / "ds" / "transforms.json"
    good = path.read_text()

    def mirror(d):
        m = np.array(d["frames"][2]["transform_matrix"])
        m[:3, 0] *= -1
        d["frames"][2]["transform_matrix"] = m.tolist()

    _edit(path, mirror)
    with pytest.raises(UserError, match=r"frames\[2\]\.transform_matrix: rotation part is a reflection \(det -1"):
        read_scene(path)
    for value in (1e308, 1e-9):
        path.write_text(good)
        _edit(path, lambda d, v=value: d.update(fl_x=v))
        with pytest.raises(UserError, match=re.escape(f"transforms.json: fl_x: {value:g} px is outside")):
            read_scene(path)
    path.write_text(good)
    _edit(path, lambda d: d["frames"][3].update(fl_x=1e308))  # a per-frame camera
    with pytest.raises(UserError, match=r"frames\[3\]\.fl_x: 1e\+308 px is outside"):
        read_scene(path)


def test_importers_refuse_mirrored_poses_and_absurd_focal(tmp_path):
    fx.make_blender(tmp_path / "bl", counts=(2, 1, 1), size=16)

    def mirror(d):
        m = np.array(d["frames"][1]["transform_matrix"])
        m[:3, 1] *= -1
        d["frames"][1]["transform_matrix"] = m.tolist()

    _edit(tmp_path / "bl" / "transforms_train.json", mirror)
    with pytest.raises(UserError, match=r"frames\[1\]\.transform_matrix: rotation part is a reflection"):
        run(Config(source=tmp_path / "bl", scene_dir=tmp_path / "s1"))
    _edit(tmp_path / "bl" / "transforms_train.json", mirror)  # mirrored twice: proper again
    _edit(tmp_path / "bl" / "transforms_train.json", lambda d: d.update(camera_angle_x=1e-300))
    with pytest.raises(UserError, match=r"frame 0 \(train_r_0.png\): fl_x: .* px is outside"):
        run(Config(source=tmp_path / "bl", scene_dir=tmp_path / "s1"))

    fx.make_npz(tmp_path / "a.npz", 4)
    data = dict(np.load(tmp_path / "a.npz"))
    data["poses"][3, :3, 2] *= -1
    np.savez(tmp_path / "a.npz", **data)
    with pytest.raises(UserError, match=r"a.npz: frame 3 \(3.png\): rotation part is a reflection"):
        run(Config(source=tmp_path / "a.npz", scene_dir=tmp_path / "s2"))

    fx.make_llff(tmp_path / "llff", n=5)
    pb = np.load(tmp_path / "llff" / "poses_bounds.npy")
    pb[2, 14] = 1e300  # the focal length of row 2
    np.save(tmp_path / "llff" / "poses_bounds.npy", pb)
    with pytest.raises(UserError, match=r"llff: frame 2 \(img_002.png\): fl_x: .*e\+299 px is outside"):
        run(Config(source=tmp_path / "llff", scene_dir=tmp_path / "s3"))


# ---------------------------------------------------------------------------------------------- hostile files
def test_image_symlink_loop_is_one_line(tmp_path, capsys):
    src = tmp_path / "src"
    fx.make_transforms(src, missing=())
    (src / "images" / "0003.jpg").unlink()
    (src / "images" / "0003.jpg").symlink_to(src / "images" / "loop")
    (src / "images" / "loop").symlink_to(src / "images" / "0003.jpg")
    code, err = _cli(capsys, "convert", src, tmp_path / "scene")
    _one_line(code, err, "frames[3].file_path 'images/0003.jpg' cannot be resolved: symlink loop")


def test_deeply_nested_json_is_one_line(tmp_path, capsys):
    deep = "[" * 200_000 + "]" * 200_000
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "transforms.json").write_text(deep)
    code, err = _cli(capsys, "convert", tmp_path / "ds", tmp_path / "scene")
    _one_line(code, err, "transforms.json: not valid JSON (nested too deeply)")
    fx.make_blender(tmp_path / "bl", counts=(1, 0, 0), size=16)
    (tmp_path / "bl" / "transforms_train.json").write_text(deep)
    code, err = _cli(capsys, "convert", tmp_path / "bl", tmp_path / "scene")
    _one_line(code, err, "transforms_train.json: not valid JSON (nested too deeply)")
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "cameras.json").write_text(deep)
    with pytest.raises(UserError, match="cameras.json: not valid JSON"):
        read_ground_truth(tmp_path / "gt")


# ---------------------------------------------------------------------------------------------- one writer
def test_second_convert_into_one_folder_is_refused(tmp_path, capsys):
    fx.make_transforms(tmp_path / "ds", missing=())
    scene = tmp_path / "scene"
    with folder_lock(scene):  # the first convert, still writing
        with pytest.raises(FolderBusy):
            run(Config(source=tmp_path / "ds", scene_dir=scene))
        code, err = _cli(capsys, "convert", tmp_path / "ds", scene)
        _one_line(code, err, f"{scene} is being written by another nerfpipe process (pid ")
        assert not (scene / "transforms.json").exists() and not (scene / "images").exists()
    out = run(Config(source=tmp_path / "ds", scene_dir=scene))  # released
    assert out.transforms.is_file() and not (scene / ".nerfpipe.lock").exists()
