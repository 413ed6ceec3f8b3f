"""Masks (data.masks): the convention, one-line errors naming the file, convert carrying mask_path, training
with masks = transparent masked-out pixels, and nothing changed without masks."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from nerfpipe.data.errors import UserError
from nerfpipe.data.masks import (
    apply_mask,
    load_masked_image,
    mask_candidates,
    match_masks,
    read_mask,
    write_binary_mask,
)
from nerfpipe.data.transforms import Frame, Scene, read_scene, write_scene
from nerfpipe.radiance.camera import Intrinsics
from nerfpipe.radiance.paths import look_at
from nerfpipe.stages import convert

W, H = 12, 8


def _one_line(excinfo) -> str:
    msg = str(excinfo.value)
    assert msg and "\n" not in msg
    return msg


def _png(path: Path, img: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)
    return path


def _scene(root: Path, views: int = 3, masks: bool = True, mask_size: tuple[int, int] = (W, H)) -> Path:
    """A tiny posed scene: grey images, masks keeping the left half (white = keep)."""
    rng = np.random.default_rng(0)
    frames = []
    for k in range(views):
        name = f"v{k}.png"
        _png(root / "images" / name, rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        if masks:
            m = np.zeros((mask_size[1], mask_size[0]), np.uint8)
            m[:, : mask_size[0] // 2] = 255
            _png(root / "masks" / name, m)
        eye = np.array([3.0 * np.cos(k), 3.0 * np.sin(k), 1.0])
        frames.append(
            Frame(
                file_path=f"images/{name}",
                world_from_cam=look_at(eye, np.zeros(3), np.array([0, 0, 1.0])),
                mask_path=f"masks/{name}" if masks else None,
            )
        )
    scene = Scene(root=root, frames=tuple(frames), intrinsics=Intrinsics(w=W, h=H, fx=10.0, fy=10.0, cx=6.0, cy=4.0))
    return write_scene(scene, root / "transforms.json")


def test_convention_white_keeps_black_masks_out(tmp_path):
    m = np.array([[0, 128, 255]], np.uint8)
    mask = read_mask(_png(tmp_path / "m.png", m))
    assert mask.dtype == np.float32 and np.allclose(mask, [[0, 128 / 255, 1]])
    rgb = np.full((1, 3, 3), 0.5, np.float32)
    out = apply_mask(rgb, mask)
    assert out.shape == (1, 3, 4) and np.allclose(out[..., 3], mask) and np.allclose(out[..., :3], 0.5)
    rgba = np.concatenate([rgb, np.full((1, 3, 1), 0.5, np.float32)], -1)
    assert np.allclose(apply_mask(rgba, mask)[..., 3], 0.5 * mask)  # alpha x mask
    assert apply_mask(rgb, None) is rgb
    write_binary_mask(mask, tmp_path / "b.png")
    assert cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_UNCHANGED).tolist() == [[0, 255, 255]]  # >= 50 % kept
    colour = _png(tmp_path / "c.png", np.full((2, 2, 3), 255, np.uint8))
    assert np.allclose(read_mask(colour), 1.0)


def test_match_masks_names_and_missing_mask(tmp_path):
    (tmp_path / "m").mkdir()
    for n in ("a.jpg.png", "b.png", "c.jpg"):
        (tmp_path / "m" / n).write_bytes(b"")
    found = match_masks(tmp_path / "m", ["a.jpg", "b.jpg", "c.jpg"])
    assert {k: v.name for k, v in found.items()} == {"a.jpg": "a.jpg.png", "b.jpg": "b.png", "c.jpg": "c.jpg"}
    assert mask_candidates("x.jpg")[:2] == ["x.jpg.png", "x.png"]
    with pytest.raises(UserError) as e:
        match_masks(tmp_path / "m", ["a.jpg", "d.jpg"])
    assert "d.jpg" in _one_line(e)
    with pytest.raises(UserError) as e:
        match_masks(tmp_path / "nope", ["a.jpg"])
    assert "nope" in _one_line(e)


def test_wrong_size_and_missing_mask_are_one_line_errors(tmp_path):
    scene = read_scene(_scene(tmp_path / "s", mask_size=(W + 2, H)))
    with pytest.raises(UserError) as e:
        load_masked_image(scene, 0)
    msg = _one_line(e)
    assert "masks/v0.png" in msg and f"{W + 2}x{H}" in msg and f"{W}x{H}" in msg
    scene = read_scene(_scene(tmp_path / "t"))
    (tmp_path / "t" / "masks" / "v1.png").unlink()
    with pytest.raises(UserError) as e:
        load_masked_image(scene, 1)
    assert "masks/v1.png" in _one_line(e)
    with pytest.raises(UserError) as e:  # convert refuses it too, naming the file
        convert.run(convert.Config(source=tmp_path / "t", scene_dir=tmp_path / "out", normalize=False))
    assert "v1.png" in _one_line(e)


def test_masked_image_is_transparent_where_masked(tmp_path):
    scene = read_scene(_scene(tmp_path / "s"))
    img = load_masked_image(scene, 0)
    assert img.shape == (H, W, 4)
    assert (img[:, : W // 2, 3] == 1).all() and (img[:, W // 2 :, 3] == 0).all()
    plain = read_scene(_scene(tmp_path / "p", masks=False))
    assert not plain.has_masks and load_masked_image(plain, 0).shape == (H, W, 3)  # no mask: unchanged


def test_convert_carries_masks(tmp_path):
    _scene(tmp_path / "s")
    out = convert.run(convert.Config(source=tmp_path / "s", scene_dir=tmp_path / "out", normalize=False))
    scene = read_scene(out.transforms)
    assert [f.mask_path for f in scene.frames] == [f"masks/v{k}.png" for k in range(3)]
    for k in range(3):
        copied = (tmp_path / "out" / "masks" / f"v{k}.png").read_bytes()
        assert copied == (tmp_path / "s" / "masks" / f"v{k}.png").read_bytes()
    assert "3 of 3" in json.loads(out.manifest.read_text())["used"]["masks"]
    plain = convert.run(convert.Config(source=tmp_path / "s", scene_dir=tmp_path / "out2", normalize=False))
    assert plain.num_frames == 3
    _scene(tmp_path / "n", masks=False)
    none = convert.run(convert.Config(source=tmp_path / "n", scene_dir=tmp_path / "out3", normalize=False))
    assert not read_scene(none.transforms).has_masks and not (tmp_path / "out3" / "masks").exists()
    assert json.loads(none.manifest.read_text())["used"]["masks"] is None


def test_colmap_importer_finds_poses_masks(tmp_path):
    """convert of a COLMAP model looks for masks/<image name>.png beside its image folder (poses --masks' layout;
    end to end in tests/test_turntable.py)."""
    from nerfpipe.data.importers.colmap import _mask_dir

    root = tmp_path / "colmap"
    _png(root / "images" / "f0.jpg", np.zeros((H, W, 3), np.uint8))
    assert _mask_dir(root / "images", ["f0.jpg"]) is None
    _png(root / "masks" / "f0.jpg.png", np.full((H, W), 255, np.uint8))
    assert _mask_dir(root / "images", ["f0.jpg", "f1.jpg"]) == root / "masks"
    assert _mask_dir(root / "images", ["other.jpg"]) is None
