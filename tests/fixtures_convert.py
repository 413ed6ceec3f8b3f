"""Tiny generated sources for `convert` tests: Blender, LLFF, npz, COLMAP (binary/text), transforms.json.

Each maker returns {output image name: expected world_from_cam} with the pose in the SOURCE frame, OpenGL
camera axes (what `scene.source_from_scene() @ frame.world_from_cam`, rotation re-scaled, must give back).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nerfpipe.radiance.paths import look_at

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def rotation(axis_angle) -> np.ndarray:
    import cv2

    r, _ = cv2.Rodrigues(np.asarray(axis_angle, dtype=np.float64))
    return r


def orbit(n: int, seed: int, radius: float = 4.0) -> list[np.ndarray]:
    """n z-up cameras on the upper hemisphere looking near the origin."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(n):
        az = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
        el = rng.uniform(0.2, 0.9)
        c = radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        poses.append(look_at(c, rng.uniform(-0.1, 0.1, 3), np.array([0.0, 0.0, 1.0])))
    return poses


def similarity(pose: np.ndarray, rot: np.ndarray, t, scale: float) -> np.ndarray:
    """The camera moved by p -> scale * rot @ p + t (rotation stays orthonormal)."""
    out = np.eye(4)
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] = scale * rot @ pose[:3, 3] + np.asarray(t)
    return out


def _image(h: int, w: int, channels: int, i: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([(xx * 7 + i * 13) % 256, (yy * 5 + i * 29) % 256, ((xx + yy) * 3) % 256], -1).astype(np.uint8)
    if channels == 4:
        img = np.concatenate([img, np.full((h, w, 1), 255 if i % 2 else 128, np.uint8)], -1)
    return img


def write_png(path: Path, h: int, w: int, channels: int = 3, i: int = 0) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), _image(h, w, channels, i))


def make_blender(root: Path, counts=(4, 2, 3), size=40, scale: float = 1.0) -> dict[str, np.ndarray]:
    """NeRF-synthetic layout; cameras ~4 units from the origin times `scale` (the same scene, resized)."""
    poses = [similarity(p, np.eye(3), np.zeros(3), scale) for p in orbit(sum(counts), seed=1)]
    expected, k = {}, 0
    for split, n in zip(("train", "val", "test"), counts, strict=True):
        frames = []
        for j in range(n):
            write_png(root / split / f"r_{j}.png", size, size, 4, k)
            frames.append({"file_path": f"./{split}/r_{j}", "rotation": 0.1, "transform_matrix": poses[k].tolist()})
            expected[f"{split}_r_{j}.png"] = poses[k]
            k += 1
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    return expected


def make_llff(root: Path, n: int = 9, size=(24, 32)) -> dict[str, np.ndarray]:
    """Forward-facing rig in a tilted world; poses_bounds hwf at twice the image size (focal factor 0.5)."""
    h, w = size
    world = rotation([0.3, -0.2, 0.4])
    rows, expected = [], {}
    for i in range(n):
        c = np.array([0.3 * (i % 3), 0.2 * (i // 3), 0.0])
        pose = similarity(
            look_at(c + [0, 0, 5.0], [0.1 * i, 0.0, 0.0], np.array([0.0, 1.0, 0.0])), world, [1.0, 2.0, 3.0], 1.0
        )
        m = np.zeros((3, 5))
        m[:, 0], m[:, 1], m[:, 2], m[:, 3] = -pose[:3, 1], pose[:3, 0], pose[:3, 2], pose[:3, 3]  # down right back
        m[:, 4] = [2 * h, 2 * w, 60.0]
        rows.append(np.concatenate([m.ravel(), [3.0 + 0.1 * i, 8.0]]))
        write_png(root / "images" / f"img_{i:03d}.png", h, w, 3, i)
        expected[f"img_{i:03d}.png"] = pose
    np.save(root / "poses_bounds.npy", np.array(rows))
    return expected


def make_npz(path: Path, n: int, size: int = 8, alpha: bool = False) -> dict[str, np.ndarray]:
    poses = np.stack(orbit(n, seed=3))
    rng = np.random.default_rng(0)
    data = {"images": rng.random((n, size, size, 3), dtype=np.float32), "poses": poses.astype(np.float32)}
    data["focal"] = np.float64(10.0)
    if alpha:
        data["alpha"] = rng.random((n, size, size), dtype=np.float32)
    np.savez(path, **data)
    digits = len(str(n - 1))
    return {f"{i:0{digits}d}.png": poses[i].astype(np.float32).astype(np.float64) for i in range(n)}


def make_colmap(
    model_dir: Path,
    image_dir: Path | None,
    n_images: int,
    n_points: int = 60,
    *,
    text: bool = False,
    model: str = "OPENCV",
    seed: int = 5,
    size=(36, 48),
) -> dict[str, np.ndarray]:
    """A COLMAP model whose world is a rotated, shifted, scaled z-up orbit; points uniform in the object box."""
    import pycolmap

    h, w = size
    rng = np.random.default_rng(seed)
    world_rot, world_t, world_s = rotation([1.2, -0.4, 0.7]), np.array([3.0, -1.0, 2.0]), 2.5
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, 40.0, w, h)
    if model == "OPENCV":
        cam.params = [40.0, 41.0, w / 2 + 0.3, h / 2 - 0.2, -0.05, 0.01, 0.001, -0.002]
    rec.add_camera_with_trivial_rig(cam)
    expected = {}
    for i, pose in enumerate(orbit(n_images, seed=seed)):
        pose = similarity(pose, world_rot, world_t, world_s)
        cam_from_world = np.linalg.inv(pose @ OPENGL_FROM_OPENCV)
        rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world[:3, :3]), cam_from_world[:3, 3])
        name = f"frame_{i:03d}.png"
        image = pycolmap.Image(name=name, keypoints=np.zeros((n_points, 2)), camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, rigid)
        expected[name] = pose
        if image_dir is not None:
            write_png(image_dir / name, h, w, 3, i)
    for j in range(n_points):
        p = world_s * world_rot @ rng.uniform(-0.8, 0.8, 3) + world_t
        track = pycolmap.Track()
        track.add_element(1, j)
        track.add_element(2, j)
        rec.add_point3D(p, track, rng.integers(0, 256, 3).astype(np.uint8))
    model_dir.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(model_dir))
    return expected


def make_transforms(root: Path, n: int = 6, missing=(1, 4), doc_extra: dict | None = None) -> dict[str, np.ndarray]:
    """instant-ngp style transforms.json (shared camera, distortion); frames in `missing` have no image."""
    poses = orbit(n, seed=7)
    frames, expected = [], {}
    for i, pose in enumerate(poses):
        frames.append({"file_path": f"images/{i:04d}.jpg", "sharpness": 30.0, "transform_matrix": pose.tolist()})
        if i not in missing:
            write_png(root / "images" / f"{i:04d}.jpg", 32, 24, 3, i)
            expected[f"{i:04d}.jpg"] = pose
    doc = {"camera_angle_x": 0.75, "fl_x": 30.0, "fl_y": 30.5, "cx": 12.2, "cy": 16.1, "w": 24.0, "h": 32.0}
    doc.update({"k1": 0.05, "k2": -0.08, "p1": -0.001, "p2": 0.0002, "aabb_scale": 4, "frames": frames})
    doc.update(doc_extra or {})
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps(doc))
    return expected
