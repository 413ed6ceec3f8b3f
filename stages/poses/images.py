"""Input photos for the poses stage: listing, upright copies (EXIF orientation applied) and screening.

COLMAP ignores EXIF orientation, so every photo is copied upright into `colmap/images/`; a copy keeps
its original file name where it can (same extension), and `names` maps copy name -> original path.
Screening scores each image on a grey thumbnail (long side `SCREEN_SIZE` px) so scores compare across
resolutions: blur = variance of the Laplacian (low = blurry), exposure = fraction of clipped pixels,
near-duplicates = a 64-bit difference hash within `DUPLICATE_BITS` bits of another image's.
"""

from __future__ import annotations

import re
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps

from nerfpipe.data.images import declared_size

__all__ = [
    "IMAGE_SUFFIXES",
    "Screen",
    "list_images",
    "natural_key",
    "write_upright",
    "screen_image",
    "near_duplicates",
    "blurriest",
]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
SCREEN_SIZE = 512
DUPLICATE_BITS = 2
OVER, UNDER = 250, 5  # grey levels counted as clipped
CLIPPED_FRACTION = 0.25  # an image with more clipped pixels than this is flagged


def natural_key(name: str) -> list:
    """Sort key so `img2` comes before `img10`."""
    return [int(s) if s.isdigit() else s.lower() for s in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder` (not hidden), in natural name order."""
    files = [p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")]
    return sorted((p for p in files if p.suffix.lower() in IMAGE_SUFFIXES), key=lambda p: natural_key(p.name))


def write_upright(src: Path, out_dir: Path, taken: set[str]) -> tuple[str, np.ndarray]:
    """Copy `src` upright into `out_dir`; return (copy name, grey thumbnail uint8 [h, w]).

    JPEG/PNG files that need no rotation are copied byte for byte (lossless, keeps EXIF focal length);
    rotated JPEGs are re-encoded at quality 95 with their EXIF (orientation reset); other formats become PNG.
    Raises OSError / PIL errors for undecodable files (the caller skips them).
    """
    declared_size(src.read_bytes(), src)  # the header's size (MAX_PIXELS) and truncation, before decoding
    with warnings.catch_warnings():
        warnings.simplefilter("error", Image.DecompressionBombWarning)
        with Image.open(src) as im:
            im.load()  # decodes everything: truncated or corrupt files fail here
            orientation = im.getexif().get(0x0112, 1)
            upright = ImageOps.exif_transpose(im) if orientation != 1 else im
            suffix = src.suffix.lower()
            keep = suffix in (".jpg", ".jpeg", ".png")
            name = _free_name(src.stem + (src.suffix if keep else ".png"), taken)
            dst = out_dir / name
            if keep and orientation == 1:
                shutil.copyfile(src, dst)
            elif keep and suffix != ".png":
                exif = upright.getexif()
                exif[0x0112] = 1
                upright.convert("RGB").save(dst, quality=95, exif=exif.tobytes())
            else:
                rgb = upright.convert("RGBA" if "A" in upright.getbands() else "RGB")
                rgb.save(dst, compress_level=1)
            grey = upright.convert("L")
            grey.thumbnail((SCREEN_SIZE, SCREEN_SIZE), Image.Resampling.BILINEAR)
            return name, np.asarray(grey)


def _free_name(name: str, taken: set[str]) -> str:
    stem, suffix = Path(name).stem, Path(name).suffix
    candidate, i = name, 1
    while candidate.lower() in taken:
        candidate, i = f"{stem}_{i}{suffix}", i + 1
    taken.add(candidate.lower())
    return candidate


@dataclass(frozen=True, kw_only=True)
class Screen:
    """Per-image screening scores (see module docstring)."""

    blur: float  # variance of the Laplacian on the grey thumbnail; low = blurry
    overexposed: float  # fraction of pixels >= OVER
    underexposed: float  # fraction of pixels <= UNDER
    dhash: int  # 64-bit difference hash

    def flags(self) -> list[str]:
        out = []
        if self.overexposed > CLIPPED_FRACTION:
            out.append(f"overexposed ({self.overexposed:.0%} clipped white)")
        if self.underexposed > CLIPPED_FRACTION:
            out.append(f"underexposed ({self.underexposed:.0%} clipped black)")
        return out


def screen_image(grey: np.ndarray) -> Screen:
    """Scores of a grey uint8 [h, w] thumbnail."""
    lap = cv2.Laplacian(grey, cv2.CV_64F)
    small = cv2.resize(grey, (9, 8), interpolation=cv2.INTER_AREA).astype(np.int16)
    bits = (small[:, 1:] > small[:, :-1]).ravel()
    return Screen(
        blur=float(lap.var()),
        overexposed=float((grey >= OVER).mean()),
        underexposed=float((grey <= UNDER).mean()),
        dhash=int(np.packbits(bits).view(">u8")[0]),
    )


def near_duplicates(names: list[str], screens: list[Screen]) -> dict[str, str]:
    """name -> an earlier name whose hash differs by at most DUPLICATE_BITS bits."""
    out: dict[str, str] = {}
    hashes = np.array([s.dhash for s in screens], dtype=np.uint64)
    for i in range(1, len(names)):
        x = np.bitwise_xor(hashes[:i], hashes[i])
        bits = np.unpackbits(x.view(np.uint8).reshape(-1, 8), axis=1).sum(1)
        j = int(np.argmin(bits))
        if bits[j] <= DUPLICATE_BITS:
            out[names[i]] = names[j]
    return out


def blurriest(names: list[str], screens: list[Screen], drop: float) -> list[str]:
    """The names to drop: `drop` < 1 is a fraction of the images, `drop` >= 1 a count (lowest blur first)."""
    if drop < 0:
        raise ValueError(f"drop_blurry must be >= 0, got {drop}")
    count = int(round(drop * len(names))) if drop < 1 else int(drop)
    order = sorted(range(len(names)), key=lambda i: (screens[i].blur, i))
    return [names[i] for i in order[:count]]
