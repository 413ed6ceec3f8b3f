"""`transforms.json`: read, validate, write.

One file serves nerfpipe, nerfstudio and instant-ngp. Keys written:
- nerfstudio: `w h fl_x fl_y cx cy k1 k2 k3 p1 p2 camera_model frames[].file_path frames[].transform_matrix
  applied_transform`, per-frame intrinsics when cameras differ, `frames[].mask_path`,
  `frames[].depth_file_path`, `train_filenames / val_filenames / test_filenames`;
- instant-ngp: `camera_angle_x camera_angle_y aabb_scale`;
- nerfpipe: `aabb` ([[x0,y0,z0],[x1,y1,z1]]), `near`, `far` (null = infinite), `applied_scale`, `has_alpha`.

Frames are camera-to-world (`world_from_cam`) 4x4 in the OpenGL camera convention, in the scene frame.
The scene frame relates to the source (COLMAP, Blender, ...) world as
`p_scene = applied_scale * (applied_transform @ [p_src; 1])` (see docs/DESIGN.md).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.atomic import write_json
from nerfpipe.data.confine import inside, read_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.images import MAX_PIXELS, as_float_rgb, read_image
from nerfpipe.radiance.camera import Intrinsics

__all__ = [
    "Frame",
    "Scene",
    "read_scene",
    "write_scene",
    "intrinsics_dict",
    "load_image",
    "is_forward_facing",
    "cameras_face_forward",
    "rotation_problem",
    "camera_problem",
    "SPLITS",
    "PATH_KEYS",
    "ROTATION_TOL",
    "FOCAL_RANGE",
]

SPLITS = ("train", "val", "test")
PATH_KEYS = ("sparse_points_path", "sparse_depth_path")
"""Top-level keys naming a file in the dataset folder (read by view and train): confined like frames' paths."""
ROTATION_TOL = 1000 * float(np.finfo(np.float32).eps)
"""|R^T R - I| and |det R - 1| allowed in a camera's rotation (1.2e-4): a thousand float32 roundings. A rotation
stored as float32 or printed to 7 digits is within ~1e-6 (the NeRF synthetic and instant-ngp fox files: 1.3e-6)."""
FOCAL_RANGE = (1e-3, 1e3)
"""A focal length (px) must lie in this range times the image's larger side: fields of view 0.06 to 179.9 deg."""
_INTRINSIC_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
_DISTORTION_KEYS = ("k1", "k2", "k3", "p1", "p2")


@dataclass(frozen=True, kw_only=True)
class Frame:
    """One image and its camera."""

    file_path: str
    """Image path as written in the file, relative to the scene root."""
    world_from_cam: np.ndarray
    """[4, 4] float64 camera-to-world, OpenGL axes, scene frame."""
    intrinsics: Intrinsics | None = None
    """Per-frame camera; None means the scene's shared one."""
    mask_path: str | None = None
    """Optional mask image, relative to the scene root: grey, the image's size, white = keep, black = masked
    out (nerfstudio's convention; `train` makes masked-out pixels transparent, see `data.masks`)."""
    depth_file_path: str | None = None
    """Optional depth map, relative to the scene root."""


@dataclass(frozen=True, kw_only=True)
class Scene:
    """A parsed transforms.json."""

    root: Path
    """Folder holding transforms.json; frame paths are relative to it."""
    frames: tuple[Frame, ...]
    """The images, in file order."""
    intrinsics: Intrinsics | None
    """Shared camera; None when every frame carries its own."""
    applied_transform: np.ndarray = field(default_factory=lambda: np.eye(4)[:3])
    """[3, 4] source world -> scene frame, applied before `applied_scale`."""
    applied_scale: float = 1.0
    """Scale applied after `applied_transform`."""
    aabb: np.ndarray = field(default_factory=lambda: np.array([[-1.0] * 3, [1.0] * 3]))
    """[2, 3] box holding the region of interest, scene frame."""
    near: float = 0.0
    """Near plane distance along rays, scene units."""
    far: float = math.inf
    """Far plane distance along rays, scene units (inf allowed)."""
    splits: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """'train' / 'val' / 'test' -> frame indices."""
    has_alpha: bool = False
    """Images carry an alpha channel (an object on a transparent background)."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Top-level keys nerfpipe does not interpret, preserved on write."""

    def frame_intrinsics(self, i: int) -> Intrinsics:
        intr = self.frames[i].intrinsics or self.intrinsics
        if intr is None:  # read_scene guarantees this cannot happen
            raise UserError(f"frame {i} ({self.frames[i].file_path}) has no intrinsics")
        return intr

    def image_path(self, i: int) -> Path:
        return _inside_root(self.root, self.frames[i].file_path, f"frames[{i}].file_path")

    def mask_path(self, i: int) -> Path | None:
        """Frame i's mask file, resolved (None without one; white = keep, `data.masks`)."""
        rel = self.frames[i].mask_path
        return None if rel is None else _inside_root(self.root, rel, f"frames[{i}].mask_path")

    def named_file(self, key: str) -> Path | None:
        """The file a top-level key names (`sparse_points_path`, `sparse_depth_path`), resolved inside the
        dataset folder (UserError otherwise); None without the key."""
        rel = self.extra.get(key)
        return None if rel is None else _inside_root(self.root, rel, key)

    @property
    def has_masks(self) -> bool:
        """Some frame has a mask_path."""
        return any(f.mask_path is not None for f in self.frames)

    def split(self, name: str) -> tuple[int, ...]:
        """Frame indices of a split; 'train' defaults to every frame when the file names none."""
        if name in self.splits:
            return self.splits[name]
        if name == "train":
            return tuple(range(len(self.frames)))
        return ()

    def scene_from_source(self) -> np.ndarray:  # [4, 4]
        m = np.eye(4)
        m[:3] = self.applied_transform
        m[:3] *= self.applied_scale
        return m

    def source_from_scene(self) -> np.ndarray:  # [4, 4]
        return np.linalg.inv(self.scene_from_source())

    def source_world_from_cam(self, world_from_cam: np.ndarray) -> np.ndarray:  # [4, 4] -> [4, 4]
        """A scene-frame camera in the source frame (rigid: the scale goes into the centre only)."""
        m = self.source_from_scene() @ np.asarray(world_from_cam, dtype=np.float64)
        m[:3, :3] /= np.linalg.norm(m[:3, :3], axis=0, keepdims=True)
        return m

    def replace(self, **changes: Any) -> Scene:
        return dataclasses.replace(self, **changes)


def _inside_root(root: Path, rel: str, what: str) -> Path:
    """Resolve `rel` under `root`; refuse paths that escape it (absolute paths, `..`, symlinks out)."""
    return inside(root, rel, what, file=root / "transforms.json")


def rotation_problem(world_from_cam: np.ndarray) -> str | None:
    """What is wrong with a camera-to-world matrix's rotation part (None when it is a proper rotation within
    ROTATION_TOL): not orthonormal, or a reflection (det -1, a mirrored camera)."""
    rot = np.asarray(world_from_cam, dtype=np.float64)[:3, :3]
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if not err <= ROTATION_TOL:
        return f"rotation part is not orthonormal (max |R^T R - I| = {err:.2g}, allowed {ROTATION_TOL:.2g})"
    det = float(np.linalg.det(rot))
    if not abs(det - 1) <= ROTATION_TOL:
        return f"rotation part is a reflection (det {det:.3g}, expected +1): a mirrored camera"
    return None


def camera_problem(intr: Intrinsics) -> str | None:
    """What is wrong with a camera's size or focal lengths (None when sane): more than MAX_PIXELS pixels, or a
    focal length outside FOCAL_RANGE times the larger image side. Names the transforms.json key."""
    if intr.w * intr.h > MAX_PIXELS:
        return f"w x h: {intr.w}x{intr.h} is more than the {MAX_PIXELS} pixels an image may have"
    lo, hi = (r * max(intr.w, intr.h) for r in FOCAL_RANGE)
    for key, f in (("fl_x", intr.fx), ("fl_y", intr.fy)):
        if not lo <= f <= hi:
            return (
                f"{key}: {f:g} px is outside [{FOCAL_RANGE[0]:g}, {FOCAL_RANGE[1]:g}] x the larger image "
                f"side ({lo:g} to {hi:g} px)"
            )
    return None


class _Reader:
    """Validation with error messages that name the file, the frame and the field."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, msg: str) -> UserError:
        return UserError(f"{self.path}: {where}: {msg}")

    def number(self, obj: dict, key: str, where: str, *, positive: bool = False, required: bool = True):
        if key not in obj:
            if required:
                raise self.fail(f"{where}{key}", "missing")
            return None
        v = obj[key]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self.fail(f"{where}{key}", f"expected a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.fail(f"{where}{key}", f"expected > 0, got {v!r}")
        return float(v)

    def matrix(self, value: Any, rows: int, where: str) -> np.ndarray:
        try:
            m = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(where, f"expected a {rows}x4 matrix of numbers") from None
        if m.shape != (rows, 4):
            raise self.fail(where, f"expected a {rows}x4 matrix, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise self.fail(where, "contains NaN or infinity")
        return m

    def intrinsics(self, obj: dict, where: str, fallback: dict | None = None) -> Intrinsics:
        """Intrinsics from `obj`, with missing keys taken from `fallback` (the top level)."""
        merged = {**(fallback or {}), **obj}
        vals = {}
        for key in ("w", "h"):
            v = self.number(merged, key, where, positive=True)
            if v != int(v):
                raise self.fail(f"{where}{key}", f"expected an integer, got {merged[key]!r}")
            vals[key] = int(v)
        # instant-ngp files may give only camera_angle_x
        if "fl_x" not in merged and "camera_angle_x" in merged:
            ang = self.number(merged, "camera_angle_x", where, positive=True)
            merged["fl_x"] = 0.5 * vals["w"] / math.tan(0.5 * ang)
        if "fl_y" not in merged:
            if "camera_angle_y" in merged:
                ang = self.number(merged, "camera_angle_y", where, positive=True)
                merged["fl_y"] = 0.5 * vals["h"] / math.tan(0.5 * ang)
            elif "fl_x" in merged:
                merged["fl_y"] = merged["fl_x"]
        fx = self.number(merged, "fl_x", where, positive=True)
        fy = self.number(merged, "fl_y", where, positive=True)
        cx = self.number(merged, "cx", where, required=False)
        cy = self.number(merged, "cy", where, required=False)
        dist = {k: self.number(merged, k, where, required=False) or 0.0 for k in _DISTORTION_KEYS}
        intr = Intrinsics(
            w=vals["w"],
            h=vals["h"],
            fx=fx,
            fy=fy,
            cx=vals["w"] / 2 if cx is None else cx,
            cy=vals["h"] / 2 if cy is None else cy,
            **dist,
        )
        problem = camera_problem(intr)
        if problem is not None:
            raise UserError(f"{self.path}: {where}{problem}")
        return intr


def read_scene(path: str | os.PathLike) -> Scene:
    """Parse and validate a transforms.json (or the folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    if not path.is_file():
        raise UserError(f"{path}: no such file (expected a transforms.json or a folder holding one)")
    doc = read_json(path)
    r = _Reader(path)
    if not isinstance(doc, dict):
        raise r.fail("top level", "expected a JSON object")
    raw_frames = doc.get("frames")
    if not isinstance(raw_frames, list) or not raw_frames:
        raise r.fail("frames", "missing or empty (expected a list of frames)")

    top_has_camera = any(k in doc for k in ("fl_x", "camera_angle_x"))
    shared = r.intrinsics(doc, "") if top_has_camera else None
    top_camera = {k: doc[k] for k in (*_INTRINSIC_KEYS, *_DISTORTION_KEYS, "camera_angle_x") if k in doc}
    root = path.parent
    frames = []
    for i, fr in enumerate(raw_frames):
        where = f"frames[{i}]."
        if not isinstance(fr, dict):
            raise r.fail(f"frames[{i}]", "expected an object")
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise r.fail(f"{where}file_path", "missing or not a string")
        inside(root, fp, f"frames[{i}].file_path", file=path)
        if "transform_matrix" not in fr:
            raise r.fail(f"{where}transform_matrix", "missing")
        m = r.matrix(fr["transform_matrix"], 4, f"{where}transform_matrix")
        if not np.allclose(m[3], [0, 0, 0, 1]):
            raise r.fail(f"{where}transform_matrix", f"last row must be [0, 0, 0, 1], got {m[3].tolist()}")
        problem = rotation_problem(m)
        if problem is not None:
            raise r.fail(f"{where}transform_matrix", problem)
        per_frame = any(k in fr for k in ("fl_x", "w", "h", "camera_angle_x"))
        if per_frame:
            intr = r.intrinsics(fr, where, top_camera)
        elif shared is None:
            raise r.fail(f"{where}fl_x", "missing (no shared camera at the top level either)")
        else:
            intr = None
        for key in ("mask_path", "depth_file_path"):
            if fr.get(key) is not None:
                if not isinstance(fr[key], str):
                    raise r.fail(f"{where}{key}", "expected a string")
                inside(root, fr[key], f"frames[{i}].{key}", file=path)
        frames.append(
            Frame(
                file_path=fp,
                world_from_cam=m,
                intrinsics=intr,
                mask_path=fr.get("mask_path"),
                depth_file_path=fr.get("depth_file_path"),
            )
        )

    for key in PATH_KEYS:
        if doc.get(key) is not None:
            if not isinstance(doc[key], str):
                raise r.fail(key, "expected a string")
            inside(root, doc[key], key, file=path)

    applied = np.eye(4)[:3]
    if "applied_transform" in doc:
        a = np.asarray(doc["applied_transform"], dtype=np.float64) if _is_numeric(doc["applied_transform"]) else None
        if a is not None and a.shape == (4, 4):
            a = a[:3]
        applied = r.matrix(a if a is not None else doc["applied_transform"], 3, "applied_transform")
    scale = r.number(doc, "applied_scale", "", positive=True, required=False) or 1.0

    if "aabb" in doc:
        try:
            aabb = np.asarray(doc["aabb"], dtype=np.float64)
        except (TypeError, ValueError):
            raise r.fail("aabb", "expected [[x0, y0, z0], [x1, y1, z1]]") from None
        if aabb.shape != (2, 3) or not np.isfinite(aabb).all() or not (aabb[1] > aabb[0]).all():
            raise r.fail("aabb", f"expected [[x0, y0, z0], [x1, y1, z1]] with x1 > x0 etc., got {doc['aabb']!r}")
    else:
        aabb = _default_aabb(doc, frames)
    near = r.number(doc, "near", "", required=False)
    near = 0.0 if near is None else near
    far = math.inf if doc.get("far") is None else r.number(doc, "far", "")
    if near < 0 or far <= near:
        raise r.fail("near/far", f"expected 0 <= near < far, got near={near}, far={far}")

    by_path = {f.file_path: i for i, f in enumerate(frames)}
    splits = {}
    for name in SPLITS:
        key = f"{name}_filenames"
        if key in doc:
            names = doc[key]
            if not isinstance(names, list):
                raise r.fail(key, "expected a list of file paths")
            missing = [n for n in names if n not in by_path]
            if missing:
                raise r.fail(key, f"names {missing[0]!r} which is not a frame's file_path")
            splits[name] = tuple(by_path[n] for n in names)

    known = {
        *_INTRINSIC_KEYS,
        *_DISTORTION_KEYS,
        "camera_model",
        "camera_angle_x",
        "camera_angle_y",
        "frames",
        "applied_transform",
        "applied_scale",
        "aabb",
        "near",
        "far",
        "has_alpha",
        "aabb_scale",
        *(f"{s}_filenames" for s in SPLITS),
    }
    return Scene(
        root=root,
        frames=tuple(frames),
        intrinsics=shared,
        applied_transform=applied,
        applied_scale=scale,
        aabb=aabb,
        near=near,
        far=far,
        splits=splits,
        has_alpha=bool(doc.get("has_alpha", False)),
        extra={k: v for k, v in doc.items() if k not in known},
    )


def _is_numeric(value: Any) -> bool:
    try:
        np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return True


def _default_aabb(doc: dict, frames: list[Frame]) -> np.ndarray:
    """instant-ngp's convention when no aabb is given: a cube of side aabb_scale around the origin."""
    s = float(doc.get("aabb_scale", 1)) if isinstance(doc.get("aabb_scale", 1), int | float) else 1.0
    return np.array([[-s] * 3, [s] * 3], dtype=np.float64)


def intrinsics_dict(intr: Intrinsics, angles: bool = True) -> dict[str, Any]:
    """An Intrinsics as transforms.json spells it (nerfstudio's keys); `angles`: with camera_angle_x / _y."""
    d: dict[str, Any] = {
        "w": intr.w,
        "h": intr.h,
        "fl_x": intr.fx,
        "fl_y": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
        "k1": intr.k1,
        "k2": intr.k2,
        "k3": intr.k3,
        "p1": intr.p1,
        "p2": intr.p2,
    }
    if angles:
        d["camera_angle_x"] = 2 * math.atan(0.5 * intr.w / intr.fx)
        d["camera_angle_y"] = 2 * math.atan(0.5 * intr.h / intr.fy)
    return d


def write_scene(scene: Scene, path: str | os.PathLike | None = None) -> Path:
    """Write `scene` as transforms.json (atomically). Default path: scene.root / 'transforms.json'."""
    path = Path(path) if path is not None else scene.root / "transforms.json"
    doc: dict[str, Any] = dict(scene.extra)
    any_distortion = any(
        (f.intrinsics or scene.intrinsics).has_distortion  # type: ignore[union-attr]
        for f in scene.frames
    )
    doc["camera_model"] = "OPENCV" if any_distortion else "PINHOLE"
    if scene.intrinsics is not None:
        doc.update(intrinsics_dict(scene.intrinsics))
    frames = []
    for i, f in enumerate(scene.frames):
        if f.intrinsics is None and scene.intrinsics is None:
            raise ValueError(f"frame {i} has no intrinsics and the scene has no shared camera")
        if f.world_from_cam.shape != (4, 4) or not np.isfinite(f.world_from_cam).all():
            raise ValueError(f"frame {i}: expected a finite [4, 4] world_from_cam, got {f.world_from_cam.shape}")
        fr: dict[str, Any] = {"file_path": f.file_path, "transform_matrix": f.world_from_cam.tolist()}
        if f.intrinsics is not None:
            fr.update(intrinsics_dict(f.intrinsics))
        if f.mask_path is not None:
            fr["mask_path"] = f.mask_path
        if f.depth_file_path is not None:
            fr["depth_file_path"] = f.depth_file_path
        frames.append(fr)
    doc["frames"] = frames
    doc["applied_transform"] = np.asarray(scene.applied_transform, dtype=np.float64).tolist()
    doc["applied_scale"] = float(scene.applied_scale)
    doc["aabb"] = np.asarray(scene.aabb, dtype=np.float64).tolist()
    # instant-ngp: power of two >= the largest |coordinate| of the aabb, at most 128
    extent = float(np.abs(scene.aabb).max())
    doc["aabb_scale"] = int(min(128, 2 ** max(0, math.ceil(math.log2(max(extent, 1.0))))))
    doc["near"] = float(scene.near)
    doc["far"] = None if math.isinf(scene.far) else float(scene.far)
    doc["has_alpha"] = bool(scene.has_alpha)
    for name, idx in scene.splits.items():
        doc[f"{name}_filenames"] = [scene.frames[i].file_path for i in idx]
    return write_json(path, doc)


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image as float32 [H, W, C] in [0, 1], C = 3 (RGB) or 4 (RGBA). 16-bit PNGs keep precision.
    `data.images.read_image`'s checks: at most MAX_PIXELS declared, no truncated file."""
    return as_float_rgb(read_image(path))


def cameras_face_forward(world_from_cam: np.ndarray) -> bool:
    """True when every camera of world_from_cam [N, 4, 4] (OpenGL axes) looks within 45 degrees of their mean
    viewing direction (a forward-facing capture); False for a rig without a mean direction."""
    fwd = -np.asarray(world_from_cam, dtype=np.float64)[:, :3, 2]  # OpenGL looks down -z
    mean = fwd.mean(axis=0)
    if np.linalg.norm(mean) < 1e-6:
        return False
    mean /= np.linalg.norm(mean)
    return bool((fwd @ mean).min() > math.cos(math.radians(45.0)))


def is_forward_facing(scene: Scene) -> bool:
    """convert's `scene_type` when present, else `cameras_face_forward` on the scene's cameras."""
    if scene.extra.get("scene_type") in ("object", "360", "forward"):
        return scene.extra["scene_type"] == "forward"
    return cameras_face_forward(np.stack([f.world_from_cam for f in scene.frames]))
