"""Working copies: SIFT on photos much larger than the working size reads small copies the stage makes itself.

COLMAP's extractor decodes every photo at full size and then shrinks it to the working size: for 4000 x 4000 px
JPEGs at a 1000 px working size that decoding and resampling, not SIFT, is most of the extraction (issue 53: ~3 s
a photo of 22, with masks read at full size too, on 2 shared cores; SIFT at 1000 px is a fraction of it). Photos at
least WORKING_COPY_FACTOR times the working size are therefore copied at the working size first (`copies`): JPEGs
decoded at a reduced scale in the DCT (Pillow's draft mode, a fraction of a full decode), then resized with an area
filter (Pillow's reducing_gap), saved as JPEG (quality 95, with the photo's EXIF so COLMAP reads what it would from
the original); masks resized the same way and thresholded at half. COLMAP extracts from the copies without
resizing them, and `to_full_resolution` then does to the database what COLMAP does after its own resize
(`FeatureKeypoint::Rescale`): every keypoint's x, y (and its affine shape a11, a21 by the x scale, a12, a22 by the
y scale) scaled to the full photo, each camera given the full size (`Camera.rescale`: focal length and principal
point with it). Matching, mapping and the model are then in the photos' own pixels, as before. The copies differ
from COLMAP's own (bilinear) resize by their filter, so the features are not bit-identical; smaller photos (the
fox: 1920 px at 1000) keep COLMAP's own path.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

__all__ = ["WORKING_COPY_FACTOR", "worth_copying", "copies", "to_full_resolution"]

WORKING_COPY_FACTOR = 2.0
"""Photos whose long side is at least this many times the working size get working copies."""


def worth_copying(long_side: int, size: int) -> bool:
    """Whether photos of `long_side` px are read from working copies at working size `size`."""
    return long_side >= WORKING_COPY_FACTOR * size


def _target(w: int, h: int, size: int) -> tuple[int, int]:
    """The copy's size: long side `size`, as COLMAP shrinks (each side x size / long side, truncated)."""
    scale = size / max(w, h)
    return max(1, int(w * scale)), max(1, int(h * scale))


def copies(
    image_dir: Path, names: list[str], size: int, out: Path, mask_dir: str | None
) -> tuple[Path, str | None, dict[str, tuple[int, int]]]:
    """Working copies of `names` at long side `size` in out/images (and of their COLMAP masks in out/masks when
    `mask_dir` is set); copies already there are kept. Returns (the copies' folder, their masks' folder or None,
    {name: the full photo's (width, height)})."""
    images, masks = out / "images", (out / "masks" if mask_dir is not None else None)
    images.mkdir(parents=True, exist_ok=True)
    if masks is not None:
        masks.mkdir(parents=True, exist_ok=True)
    full: dict[str, tuple[int, int]] = {}
    for name in names:
        dst = images / name
        with Image.open(image_dir / name) as im:
            full[name] = im.size
            target = _target(*im.size, size)
            if not dst.exists():
                exif = im.info.get("exif")
                im.draft("RGB", target)  # JPEG: decode at 1/2, 1/4 or 1/8 scale, at least `target`
                small = im.convert("RGB").resize(target, Image.Resampling.LANCZOS, reducing_gap=2.0)
                small.save(dst, format="JPEG", quality=95, **({"exif": exif} if exif else {}))
        if masks is not None and not (masks / f"{name}.png").exists():
            with Image.open(Path(mask_dir) / f"{name}.png") as m:
                grey = np.asarray(m.convert("L").resize(target, Image.Resampling.BOX), dtype=np.uint8)
            Image.fromarray(np.where(grey >= 128, 255, 0).astype(np.uint8)).save(masks / f"{name}.png")
    return images, (str(masks) if masks is not None else None), full


def to_full_resolution(db_path: Path, full: dict[str, tuple[int, int]]) -> None:
    """The database of an extraction from working copies, as if COLMAP had extracted from the full photos (`full`:
    name -> (width, height)): keypoints and cameras scaled (module doc)."""
    db = pycolmap.Database.open(db_path)
    try:
        cameras: dict[int, tuple[int, int]] = {}
        for image in db.read_all_images():
            if image.name not in full:
                continue
            w, h = full[image.name]
            cam = db.read_camera(image.camera_id)
            sx, sy = w / cam.width, h / cam.height
            if math.isclose(sx, 1.0) and math.isclose(sy, 1.0):
                continue
            keypoints = db.read_keypoints(image.image_id).astype(np.float64)
            if keypoints.shape[1] == 6:  # x, y, a11, a12, a21, a22
                keypoints[:, [0, 2, 4]] *= sx
                keypoints[:, [1, 3, 5]] *= sy
            else:  # x, y (, scale, orientation)
                keypoints[:, 0] *= sx
                keypoints[:, 1] *= sy
                if keypoints.shape[1] == 4:
                    keypoints[:, 2] *= (sx + sy) / 2
            db.update_keypoints(image.image_id, keypoints.astype(np.float32))
            cameras[image.camera_id] = (w, h)
        for camera_id, (w, h) in cameras.items():
            cam = db.read_camera(camera_id)
            cam.rescale(w, h)
            db.update_camera(cam)
    finally:
        db.close()
