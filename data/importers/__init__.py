"""Readers for posed sources (COLMAP, NeRF Blender, LLFF, tiny-NeRF npz, transforms.json) -> `Source`.

Every importer returns poses in the **source** world frame as camera-to-world 4x4 in **OpenGL** camera axes
(x right, y up, looking down -z): COLMAP's OpenCV cameras are converted where they are read
(`radiance.camera.opengl_from_opencv`), LLFF's [down, right, back] columns where they are read. Intrinsics are
`radiance.camera.Intrinsics` (pixel centres at +0.5, OpenCV distortion kept, not resampled). `stages.convert`
then normalises, copies the images and writes `transforms.json`.

Every path a source names is resolved inside its folder (`data.confine.inside`: no absolute path, no `..` or
symlink leading out), every image is read through `data.images` (size from the header first, no truncated
file), and `load_source` checks every frame's camera (`data.transforms.rotation_problem`, `camera_problem`:
a proper rotation, a sane focal length) whatever the importer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.images import read_image
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["KINDS", "Source", "SourceFrame", "detect_kind", "load_source", "flat_name", "image_shape", "check_cameras"]

KINDS = ("colmap", "blender", "llff", "npz", "transforms")


@dataclass(frozen=True, kw_only=True)
class SourceFrame:
    """One posed image of a source."""

    name: str
    """Output file name under SCENE_DIR/images/ (flat: nerfstudio finds images_N/<name>)."""
    world_from_cam: np.ndarray
    """[4, 4] camera-to-world, OpenGL axes, source frame."""
    intrinsics: Intrinsics
    """This image's camera."""
    image: Path | None = None
    """Source image file (None: pixels come from `Source.pixels`)."""
    mask: Path | None = None
    """Optional source mask file."""
    depth: Path | None = None
    """Optional source depth file."""
    point_ids: np.ndarray | None = None
    """Indices into `Source.points` of the sparse points this image observed (COLMAP tracks), or None."""


@dataclass(frozen=True, kw_only=True)
class Source:
    """What an importer read; poses in the source frame."""

    kind: str
    """One of KINDS."""
    frames: tuple[SourceFrame, ...]
    """Images in a deterministic order."""
    splits: dict[str, tuple[int, ...]] | None = None
    """The dataset's own split (indices into frames), or None for the hold-out rule."""
    has_alpha: bool = False
    """Images are RGBA (object on a transparent background)."""
    up: str = "cameras"
    """Default up policy for `radiance.normalize`: 'keep' (z-up source) or 'cameras'."""
    scene_type: str | None = None
    """'object', 'forward' or None (let convert classify)."""
    points: np.ndarray | None = None
    """[M, 3] sparse points, source frame."""
    colors: np.ndarray | None = None
    """[M, 3] uint8 point colours."""
    box: np.ndarray | None = None
    """[2, 3] region of interest the dataset states (an input transforms.json's `aabb`), source frame; None:
    `radiance.normalize` derives it from the points, depth bounds or cameras. Never a dataset convention."""
    depth_bounds: np.ndarray | None = None
    """[N, 2] per-image near/far z-depth the dataset states, source units (LLFF)."""
    pixels: Callable[[int], np.ndarray] | None = None
    """Frame index -> uint8 [H, W, 3|4] RGB(A), for sources holding arrays (npz)."""
    source_from_original: np.ndarray | None = None
    """[4, 4] (scale folded in) when the source is itself a converted file: its frame from the user's original."""
    inputs: tuple[Path, ...] = ()
    """Files to hash into the manifest."""
    used: dict[str, Any] = field(default_factory=dict)
    """Choices made while reading (model chosen, image folder, ...)."""
    left_out: dict[str, str] = field(default_factory=dict)
    """What was ignored and why."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Top-level keys to carry into the output transforms.json."""


def flat_name(rel: str, suffix: str | None = None) -> str:
    """'./train/r_0' -> 'train_r_0' (+ suffix); a leading 'images/' folder is dropped."""
    parts = [p for p in PurePosixPath(rel.replace("\\", "/")).parts if p not in (".", "")]
    if len(parts) > 1 and parts[0] == "images":
        parts = parts[1:]
    name = "_".join(parts)
    return name + suffix if suffix and not PurePosixPath(name).suffix else name


def image_shape(path: Path) -> tuple[int, int, int]:
    """(h, w, channels) of an image file (`data.images.read_image`'s checks)."""
    img = read_image(path)
    return img.shape[0], img.shape[1], 1 if img.ndim == 2 else img.shape[2]


def check_cameras(source: Source, path: Path) -> Source:
    """`source` unchanged when every frame has a proper rotation and a sane camera; else UserError naming
    `path` and the frame."""
    from nerfpipe.data.transforms import camera_problem, rotation_problem

    for i, f in enumerate(source.frames):
        problem = rotation_problem(f.world_from_cam) or camera_problem(f.intrinsics)
        if problem is not None:
            raise UserError(f"{path}: frame {i} ({f.name}): {problem}")
    return source


def detect_kind(path: Path) -> str:
    """Guess the source kind from the files present (Blender, LLFF, COLMAP, then transforms.json)."""
    from nerfpipe.data.importers.colmap import find_models

    if path.is_file():
        if path.suffix == ".npz":
            return "npz"
        if path.name == "poses_bounds.npy":
            return "llff"
        if path.name.startswith("transforms_") and path.suffix == ".json":
            return "blender"
        if path.suffix == ".json":
            return "transforms"
        raise UserError(f"{path}: unknown source kind (expected a folder, a .npz or a transforms .json)")
    if not path.is_dir():
        raise UserError(f"{path}: no such file or folder")
    if any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        return "blender"
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    if find_models(path):
        return "colmap"
    if (path / "transforms.json").is_file():
        return "transforms"
    npz = sorted(path.glob("*.npz"))
    if len(npz) == 1:
        return "npz"
    raise UserError(
        f"{path}: unknown source kind (no COLMAP model, transforms_{{train,val,test}}.json, poses_bounds.npy, "
        "transforms.json or single .npz found)"
    )


def load_source(path: Path, kind: str, *, images: Path | None = None) -> Source:
    """Read `path` as `kind` ('auto' guesses). `images`: image folder override (COLMAP, LLFF)."""
    from nerfpipe.data.importers import blender, colmap, llff, nerfstudio, npz

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file or folder")
    if kind == "auto":
        kind = detect_kind(path)
    readers = {
        "colmap": lambda: colmap.load(path, images=images),
        "blender": lambda: blender.load(path),
        "llff": lambda: llff.load(path, images=images),
        "npz": lambda: npz.load(path),
        "transforms": lambda: nerfstudio.load(path),
    }
    if kind not in readers:
        raise UserError(f"unknown source kind {kind!r} (expected auto or one of {', '.join(KINDS)})")
    return check_cameras(readers[kind](), path)
