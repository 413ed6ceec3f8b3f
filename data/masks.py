"""Masks: which pixels of a photo belong to the subject.

Convention (nerfstudio's, also COLMAP's): a mask is a grey image of the photo's size, **white (255) = keep,
black (0) = masked out**; grey levels in between are a fraction kept (anti-aliased edges). A colour mask is read
as its grey level (ITU-R 601 luma), an alpha channel in the mask file is ignored.

Where masks come from and go:
- `poses --masks DIR`: one mask per photo in DIR, found by the photo's file name (`match_masks`: `IMG_1.jpg`
  takes `IMG_1.jpg.png` (COLMAP's name), `IMG_1.png` or `IMG_1.jpg`); they are written binary (kept where
  >= 50 %) as `colmap/masks/<image name>.png`, COLMAP's layout, and SIFT keeps no feature on a black pixel.
- `convert` finds `masks/<image name>.png` next to a COLMAP model (the `poses` layout) and a transforms.json's
  `frames[].mask_path`, copies them to `SCENE_DIR/masks/` and writes `mask_path` per frame.
- `train` (and its per-image report) multiplies each image's alpha by its mask (`load_masked_image`): a
  masked-out pixel is **transparent**, like the empty background of an RGBA object capture. The rule, and why:
  masks here mark the subject of an object capture (a turntable's object, whose background does not turn with
  it and so cannot be explained by any one 3-D scene); transparent pixels train against a random background
  colour per ray, so the field learns empty space there, and evaluation composites them on the evaluation
  colour. (Masking pixels out of the loss instead would leave that space unconstrained: floaters in renders.)
  Transient occluders in a scene capture (a passer-by) would want "not in the loss" instead; that mode is not
  implemented.

Masks are optional everywhere: without `mask_path` / `--masks`, nothing changes.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from nerfpipe.data.confine import inside
from nerfpipe.data.errors import UserError
from nerfpipe.data.images import read_image

__all__ = [
    "MASK_SUFFIXES",
    "KEEP",
    "mask_candidates",
    "match_masks",
    "read_mask",
    "write_binary_mask",
    "load_masked_image",
    "apply_mask",
]

MASK_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
KEEP = 0.5
"""A binary use (COLMAP's features) keeps the pixels whose mask value is at least this fraction of white."""


def mask_candidates(image_name: str) -> list[str]:
    """File names that count as the mask of `image_name`, in order of preference: COLMAP's `<name>.png`, the
    same stem with a mask suffix (`.png` first), the same name."""
    stem = Path(image_name).stem
    names = [f"{image_name}.png", *(stem + s for s in MASK_SUFFIXES), image_name]
    return list(dict.fromkeys(names))


def match_masks(mask_dir: str | os.PathLike, image_names: Iterable[str]) -> dict[str, Path]:
    """image name -> its mask file in `mask_dir` (resolved; a symlink may not lead out of the folder); UserError
    (one line, naming the image) when the folder is missing or an image has no mask."""
    mask_dir = Path(mask_dir)
    if not mask_dir.is_dir():
        raise UserError(f"masks {mask_dir}: no such folder (expected one mask image per photo, white = keep)")
    present = {p.name for p in mask_dir.iterdir() if p.is_file()}
    out = {}
    for name in image_names:
        found = next((c for c in mask_candidates(name) if c in present), None)
        if found is None:
            raise UserError(
                f"masks {mask_dir}: no mask for image {name} (expected {name}.png or "
                f"{Path(name).stem}.png, white = keep)"
            )
        out[name] = inside(mask_dir, found, f"the mask of {name}")
    return out


def read_mask(path: str | os.PathLike, size: tuple[int, int] | None = None, image: str | None = None) -> np.ndarray:
    """A mask file as float32 [H, W] in [0, 1] (1 = keep). `size` (w, h): the size it must have (that of
    `image`, named in the error); UserError when it is not, or the file cannot be decoded (`data.images`'s
    checks: at most MAX_PIXELS declared, no truncated file)."""
    import cv2  # heavy import kept local

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: mask not found" + (f" (the mask of {image})" if image else ""))
    m = read_image(path, "mask")
    if m.ndim == 3:
        m = cv2.cvtColor(m[..., :3], cv2.COLOR_BGR2GRAY)
    scale = 65535.0 if m.dtype == np.uint16 else 255.0
    if size is not None and (m.shape[1], m.shape[0]) != tuple(size):
        of = f" but its image {image} is" if image else ", expected"
        raise UserError(f"{path}: mask is {m.shape[1]}x{m.shape[0]}{of} {size[0]}x{size[1]}")
    return (m.astype(np.float32) / scale).clip(0.0, 1.0)


def write_binary_mask(mask: np.ndarray, path: str | os.PathLike) -> Path:
    """mask [H, W] in [0, 1] -> a PNG of 0 / 255 (kept where >= KEEP), atomically."""
    import cv2

    from nerfpipe.data.atomic import write_bytes

    ok, buf = cv2.imencode(".png", np.where(mask >= KEEP, 255, 0).astype(np.uint8))
    if not ok:
        raise UserError(f"{path}: cannot encode the mask as PNG")
    return Path(write_bytes(Path(path), buf.tobytes()))


def apply_mask(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """image float32 [H, W, 3|4] -> RGBA [H, W, 4] with alpha multiplied by mask [H, W] (the image unchanged,
    whatever its channels, when mask is None)."""
    if mask is None:
        return image
    if mask.shape != image.shape[:2]:
        raise ValueError(f"expected a mask of shape {image.shape[:2]}, got {mask.shape}")
    alpha = image[..., 3] if image.shape[-1] == 4 else np.ones(image.shape[:2], np.float32)
    return np.concatenate([image[..., :3], (alpha * mask)[..., None]], axis=-1).astype(np.float32)


def load_masked_image(scene, i: int) -> np.ndarray:
    """Frame i of a `data.transforms.Scene` as float32 [H, W, C] in [0, 1]: `load_image`, then, when the frame
    has a `mask_path`, RGBA with alpha = image alpha x mask (module docstring). UserError naming the mask file
    when it is missing or not the image's size."""
    from nerfpipe.data.transforms import load_image

    path = scene.image_path(i)
    img = load_image(path)
    rel = scene.frames[i].mask_path
    if rel is None:
        return img
    mask = read_mask(scene.mask_path(i), (img.shape[1], img.shape[0]), image=path.name)
    return apply_mask(img, mask)
