"""The scene stage's files: PNG images and masks, depth .npy, mesh .ply, transforms.json, and the NeRF-synthetic
(Blender) layout."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import trimesh

from nerfpipe.data.atomic import atomic_path, write_json
from nerfpipe.data.transforms import Frame, Scene, write_scene
from nerfpipe.radiance.camera import Intrinsics

__all__ = [
    "TEST_EVERY",
    "BLENDER_SPLITS",
    "png",
    "grey_png",
    "write_npy",
    "write_mesh",
    "write_transforms",
    "views",
    "blender_split",
    "write_blender",
]

TEST_EVERY = 8
BLENDER_SPLITS = ("train", "val", "test")


def write_npy(path: Path, arr: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        np.save(tmp, arr)


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> None:
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type="ply", encoding="binary")


def write_transforms(
    out_dir: Path,
    names: list[str],
    world_from_cam: np.ndarray,
    intr: Intrinsics,
    aabb,
    near,
    far,
    rgba: bool,
    masks: list[str] | None = None,
) -> Path:
    """transforms.json in the scene frame (= this generator's world: identity applied_transform, scale 1);
    `masks`: each frame's mask_path (relative to out_dir), or None."""
    test = tuple(range(0, len(names), TEST_EVERY))
    train = tuple(i for i in range(len(names)) if i % TEST_EVERY)
    frames = tuple(
        Frame(file_path=f"images/{n}", world_from_cam=w, intrinsics=None, mask_path=m)
        for n, w, m in zip(names, world_from_cam, masks or [None] * len(names), strict=True)
    )
    scene = Scene(
        root=out_dir,
        frames=frames,
        intrinsics=intr,
        applied_transform=np.eye(4)[:3],
        applied_scale=1.0,
        aabb=aabb,
        near=near,
        far=far,
        splits={"train": train, "val": test, "test": test},
        has_alpha=rgba,
    )
    return Path(write_scene(scene, out_dir / "transforms.json"))


def views(kind: str, views: int) -> list[tuple[str, str]]:
    """Per view: (image path relative to out_dir, ground-truth stem). blender: <split>/r_<j>.png, stem
    <split>_r_<j> (the name `convert` gives it); else images/frame_0000.png, stem frame_0000."""
    if kind != "blender":
        return [(f"images/frame_{i:04d}.png", f"frame_{i:04d}") for i in range(views)]
    count = dict.fromkeys(BLENDER_SPLITS, 0)
    out = []
    for i in range(views):
        split = blender_split(i)
        out.append((f"{split}/r_{count[split]}.png", f"{split}_r_{count[split]}"))
        count[split] += 1
    return out


def blender_split(i: int) -> str:
    """kind=blender: view i is test when i % 8 == 0, val when i % 8 == 4, else train."""
    return "test" if i % TEST_EVERY == 0 else "val" if i % TEST_EVERY == TEST_EVERY // 2 else "train"


def write_blender(out_dir: Path, rel: list[str], world_from_cam: np.ndarray, fov_x_deg: float) -> tuple[Path, ...]:
    """transforms_<split>.json in the NeRF-synthetic layout (see the module docstring), for non-empty splits."""
    frames: dict[str, list] = {s: [] for s in BLENDER_SPLITS}
    for r, w in zip(rel, world_from_cam, strict=True):
        split = r.split("/")[0]
        frames[split].append({"file_path": f"./{Path(r).with_suffix('').as_posix()}", "transform_matrix": w.tolist()})
    fov_x = math.radians(fov_x_deg)  # what `intrinsics` uses: the importer recovers the same focal length
    return tuple(
        write_json(out_dir / f"transforms_{s}.json", {"camera_angle_x": fov_x, "frames": f})
        for s, f in frames.items()
        if f
    )


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def png(rgb: np.ndarray, alpha: np.ndarray | None) -> bytes:
    img = _to_u8(rgb)[..., ::-1]  # RGB -> BGR for OpenCV
    if alpha is not None:
        img = np.concatenate([img, _to_u8(alpha)[..., None]], axis=-1)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def grey_png(x: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", _to_u8(x))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()
