"""convert's writers: the images at each downscale (EXIF orientation applied, 16-bit and alpha kept), masks, auxiliary
files and sparse points, and the check that image names stay unique and inside the scene."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import atomic_path, write_bytes
from nerfpipe.data.errors import UserError
from nerfpipe.data.images import read_image_file
from nerfpipe.data.importers import SourceFrame
from nerfpipe.data.masks import read_mask

__all__ = ["write_image", "imwrite", "mask_names", "copy_mask", "copy_aux", "write_ply", "check_names"]


def write_image(frame: SourceFrame, pixels, dest: Path, factors: list[int]) -> None:
    """Copy / encode one image into images/ and its downscaled copies into images_F/."""
    import cv2

    intr = frame.intrinsics
    if pixels is not None:
        img = pixels
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[-1] == 4 else cv2.COLOR_RGB2BGR)
        imwrite(dest / "images" / frame.name, img)
    else:
        decoded = read_image_file(frame.image)
        img = decoded.pixels
        write_bytes(dest / "images" / frame.name, decoded.data)  # the bytes that decoded, byte for byte
    if img.shape[:2] != (intr.h, intr.w):
        raise UserError(
            f"{frame.image or frame.name}: image is {img.shape[1]}x{img.shape[0]} but its camera says {intr.w}x{intr.h}"
        )
    for f in factors:
        small = intr.scaled(1.0 / f)
        imwrite(dest / f"images_{f}" / frame.name, cv2.resize(img, (small.w, small.h), interpolation=cv2.INTER_AREA))


def imwrite(path: Path, img: np.ndarray) -> None:
    import cv2

    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix.lower() in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(path.suffix, img, params)
    if not ok:
        raise UserError(f"{path}: cannot encode image as {path.suffix}")
    write_bytes(path, buf.tobytes())


def mask_names(frames: list[SourceFrame]) -> list[str | None]:
    """Each frame's mask file name under SCENE_DIR/masks/: the image's stem with the mask's suffix
    (images/a.jpg -> masks/a.png, nerfstudio's layout), or the image's name plus it where stems repeat."""
    stems = [Path(f.name).stem for f in frames]
    unique = len(set(stems)) == len(stems)
    return [
        None if f.mask is None else (stem if unique else f.name) + (f.mask.suffix.lower() or ".png")
        for f, stem in zip(frames, stems, strict=True)
    ]


def copy_mask(frame: SourceFrame, dest: Path) -> None:
    """Copy a frame's mask byte for byte after checking it decodes and has the image's size (UserError naming
    the mask file otherwise)."""
    read_mask(frame.mask, (frame.intrinsics.w, frame.intrinsics.h), image=frame.name)
    with atomic_path(dest) as tmp:
        shutil.copyfile(frame.mask, tmp)


def copy_aux(src: Path | None, dest_dir: Path, name: str) -> str | None:
    if src is None or not src.is_file():
        return None
    with atomic_path(dest_dir / name) as tmp:
        shutil.copyfile(src, tmp)
    return f"{dest_dir.name}/{name}"


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray | None) -> None:
    import trimesh

    cloud = trimesh.PointCloud(points, colors=colors if colors is not None and len(colors) else None)
    write_bytes(path, cloud.export(file_type="ply"))


def check_names(source: Path, names: list[str]) -> None:
    """Output names are plain file names (an importer's `flat_name`), unique: nothing is written outside images/."""
    bad = next((n for n in names if not n or "/" in n or "\0" in n or n in (".", "..")), None)
    if bad is not None:
        raise UserError(f"{source}: image name {bad!r} is not a plain file name")
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise UserError(f"{source}: two images map to the same output name {dup!r}")
