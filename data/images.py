"""Reading image files a dataset names: the size from the header before any pixel is decoded, whole files only.

`read_image` reads the file once into memory and, before decoding:
- takes the size the header declares (PNG: IHDR; JPEG: the SOF segment; other formats: PIL's header parser)
  and refuses more than `MAX_PIXELS` pixels: a 2.6 MB PNG can declare 30000x30000 (900 M pixels, 2.7 GB
  decoded as RGB, 11 GB as float32), which decoding would allocate;
- refuses a file that ends before its data does: a JPEG whose scan has no end-of-image marker after it (libjpeg
  decodes a truncated JPEG and fills the missing rows with grey, with only a warning on stderr), a PNG that ends
  before its IEND chunk. Both checks walk the file's segments (no decoding), so they cost next to nothing;
then decodes with OpenCV as `cv2.IMREAD_UNCHANGED` does: [H, W] or [H, W, 3|4] BGR(A), uint8 or uint16, EXIF
orientation not applied. Every refusal is one UserError line naming the file.
"""

from __future__ import annotations

import os
import struct
import threading
import warnings
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

import numpy as np

from nerfpipe.data.errors import UserError

__all__ = [
    "MAX_PIXELS",
    "Decoded",
    "read_image",
    "read_image_file",
    "declared_size",
    "as_float_rgb",
    "srgb_to_linear",
    "exif_orientation",
    "upright",
]

MAX_PIXELS = 2**27
"""The most pixels an image may declare (134 M: a 108 MP phone photo, 11584x11584; 512 MB as RGBA uint8).
Below Pillow's own refusal (2 x `PIL.Image.MAX_IMAGE_PIXELS`, 179 M), so this budget is the one that decides."""

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD8)}  # TEM, RST0..7: markers without a length
_PIL_HEADER = threading.Lock()  # warnings.catch_warnings is process-wide: one header read at a time


@dataclass(frozen=True)
class Decoded:
    """An image file as read: its bytes (what a copy must write) and its pixels."""

    data: bytes
    pixels: np.ndarray  # [H, W] or [H, W, 3|4] BGR(A), uint8 or uint16


def _png(data: bytes) -> tuple[tuple[int, int] | None, bool]:
    """((w, h) from IHDR, whether the chunks reach IEND within the file)."""
    size = struct.unpack(">II", data[16:24]) if data[12:16] == b"IHDR" and len(data) >= 24 else None
    pos = len(_PNG_MAGIC)
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        pos += 12 + length
        if pos > len(data):
            return size, False
        if kind == b"IEND":
            return size, True
    return size, False


def _jpeg(data: bytes) -> tuple[tuple[int, int] | None, bool]:
    """((w, h) from the frame header, whether an end-of-image marker follows the first scan). The segments
    before the first scan (EXIF, which may hold a whole thumbnail JPEG) are skipped by their lengths; inside
    entropy-coded data every 0xFF byte is followed by 0x00 or a restart marker, so the first FFD9 after the
    scan starts is the image's end."""
    size, pos = None, 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return size, False
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _JPEG_STANDALONE:
            pos += 2
            continue
        length = int.from_bytes(data[pos + 2 : pos + 4], "big")
        if marker in _JPEG_SOF and pos + 9 <= len(data):
            h, w = struct.unpack(">HH", data[pos + 5 : pos + 9])
            size = (w, h)
        if marker == 0xDA:  # start of scan
            return size, data.find(b"\xff\xd9", pos + 2 + length) >= 0
        pos += 2 + length
    return size, False


def _pil_size(data: bytes, path: Path, what: str) -> tuple[int, int]:
    """(w, h) from PIL's header parser (formats other than PNG and JPEG); nothing is decoded."""
    from PIL import Image

    with _PIL_HEADER, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # DecompressionBombWarning: the budget is MAX_PIXELS, checked below
        try:
            with Image.open(BytesIO(data)) as im:
                return im.size
        except Image.DecompressionBombError:
            raise UserError(
                f"{path}: {what} declares more than {2 * Image.MAX_IMAGE_PIXELS} pixels; at most {MAX_PIXELS} "
                "are read (downscale it)"
            ) from None
        except Exception:  # PIL raises many types for what it cannot parse
            raise UserError(f"{path}: cannot decode {what} (an unknown format or a corrupt header)") from None


def declared_size(data: bytes, path: str | os.PathLike, what: str = "image") -> tuple[int, int]:
    """(w, h) an image file's header declares, checked: UserError naming `path` when the file is truncated
    (PNG, JPEG) or declares more than MAX_PIXELS pixels."""
    path = Path(path)
    if data.startswith(_PNG_MAGIC):
        size, whole, kind = *_png(data), "PNG"
    elif data.startswith(b"\xff\xd8"):
        size, whole, kind = *_jpeg(data), "JPEG"
    else:
        size, whole, kind = _pil_size(data, path, what), True, ""
    if size is None or min(size) <= 0:
        raise UserError(f"{path}: cannot decode {what} (no valid {kind} header)")
    w, h = size
    if w * h > MAX_PIXELS:
        raise UserError(
            f"{path}: {what} declares {w}x{h} pixels ({w * h / 1e6:.0f} M), more than the "
            f"{MAX_PIXELS / 1e6:.0f} M read; downscale it"
        )
    if not whole:
        end = "an IEND chunk" if kind == "PNG" else "an end-of-image marker after its data"
        raise UserError(f"{path}: {what} file is truncated ({kind} without {end})")
    return w, h


def read_image_file(path: str | os.PathLike, what: str = "image") -> Decoded:
    """The file's bytes and its pixels (module docstring); `what` names it in errors ('image', 'mask')."""
    import cv2  # heavy import kept local

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {what} not found")
    try:
        data = path.read_bytes()
    except OSError as e:
        reason = os.strerror(e.errno).lower() if e.errno else str(e)
        raise UserError(f"{path}: cannot read {what} ({reason})") from None
    declared_size(data, path, what)
    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise UserError(f"{path}: cannot decode {what}")
    return Decoded(data=data, pixels=pixels)


def read_image(path: str | os.PathLike, what: str = "image") -> np.ndarray:
    """Pixels of an image file, [H, W] or [H, W, 3|4] BGR(A) uint8/uint16 (cv2.IMREAD_UNCHANGED), after the
    checks of the module docstring."""
    return read_image_file(path, what).pixels


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (IEC 61966-2-1), as float32: what glTF's vertex colours hold."""
    v = np.clip(np.asarray(values, np.float64), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def as_float_rgb(pixels: np.ndarray) -> np.ndarray:
    """Decoded pixels (`read_image`: [H, W] or [H, W, 3|4] BGR(A), uint8 or uint16) -> float32 [H, W, C] in
    [0, 1], C = 3 (RGB) or 4 (RGBA); grey becomes three equal channels, 16-bit keeps its precision."""
    import cv2  # heavy import kept local

    scale = 65535.0 if pixels.dtype == np.uint16 else 255.0
    if pixels.ndim == 2:
        img = np.repeat(pixels[..., None], 3, axis=-1)
    elif pixels.shape[-1] == 4:
        img = cv2.cvtColor(pixels, cv2.COLOR_BGRA2RGBA)
    else:
        img = cv2.cvtColor(pixels[..., :3], cv2.COLOR_BGR2RGB)
    return (img.astype(np.float32) / scale).clip(0.0, 1.0)


def exif_orientation(data: bytes) -> int:
    """The EXIF orientation tag (1-8) of an image file's bytes; 1 when there is none or it cannot be read."""
    from PIL import Image

    try:
        with Image.open(BytesIO(data)) as im:
            value = int(im.getexif().get(0x0112, 1))
    except Exception:  # no EXIF, or a header PIL does not read: the pixels as stored
        return 1
    return value if 1 <= value <= 8 else 1


def upright(pixels: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels [H, W, ...] as stored -> as displayed under EXIF `orientation` (what PIL's `exif_transpose` does)."""
    if orientation == 2:
        out = pixels[:, ::-1]
    elif orientation == 3:
        out = pixels[::-1, ::-1]
    elif orientation == 4:
        out = pixels[::-1]
    elif orientation == 5:
        out = pixels.swapaxes(0, 1)
    elif orientation == 6:
        out = np.rot90(pixels, k=-1)
    elif orientation == 7:
        out = pixels[::-1, ::-1].swapaxes(0, 1)
    elif orientation == 8:
        out = np.rot90(pixels, k=1)
    else:
        out = pixels
    return np.ascontiguousarray(out)
