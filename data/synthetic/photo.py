"""Photo textures: scikit-image's bundled photographs wrapped round a primitive by triplanar projection.

Conventions (`objects`' module doc): metres, up +z. A `PhotoTexture` is *solid*: its colour at a surface point is
a function of that point alone (the primitive's normal there is too), so every view sees the same colour.
Triplanar projection: the point, in the texture's own frame (`rotation`, `origin`), is projected along each of
the frame's three axes onto the image plane of the other two; the three samples are blended with weights
|n_axis|^4 of the surface normal in that frame, so a face sees mostly the projection square to it. The image
repeats mirrored (no seams), `scale` metres per image width.

Images come with scikit-image (files inside the package: no download; `PHOTOS`, `GREYS`), loaded once per
process.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import trimesh

from nerfpipe.data.synthetic.objects import Material, Primitive, _apply

__all__ = ["PHOTOS", "GREYS", "photo", "PhotoTexture", "PhotoTextured"]

PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry")
"""Colour photographs in `skimage.data` whose files ship with scikit-image (no pooch fetch)."""
GREYS = ("brick", "grass", "gravel")
"""Greyscale surface photographs in `skimage.data` (shipped files), coloured by a `PhotoTexture.tint`."""


@cache
def photo(name: str) -> np.ndarray:
    """The image `name` of `PHOTOS` or `GREYS`: [H, W, 3] float32 in [0, 1] (a grey image repeated thrice)."""
    if name not in PHOTOS + GREYS:
        raise ValueError(f"expected a photo of {PHOTOS + GREYS}, got {name!r}")
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    out = (img[..., :3].astype(np.float32) / 255.0).copy()
    out.flags.writeable = False  # shared by every texture of the process
    return out


def _mirror(x: np.ndarray, n: int) -> np.ndarray:
    """Pixel coordinate x [N] (continuous, pixel centres at integers) folded into [0, n - 1] by mirrored repeat."""
    t = np.mod(x, 2 * n)
    return np.clip(np.where(t < n, t, 2 * n - t), 0.0, n - 1)


def _bilinear(img: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """img [H, W, 3] at continuous pixel coordinates col, row [N] (mirrored repeat) -> [N, 3] float64."""
    h, w = img.shape[:2]
    x, y = _mirror(col, w), _mirror(row, h)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


@dataclass(frozen=True, kw_only=True)
class PhotoTexture:
    """One photograph projected triplanarly (module doc), tinted; deterministic from its fields."""

    name: str
    """The image: one of `PHOTOS` or `GREYS`."""
    tint: np.ndarray
    """[3] RGB multiplier of the image's colour (ones for a colour photo)."""
    rotation: np.ndarray
    """[3, 3] texture_from_world rotation (so the image's axes do not line up with box faces)."""
    origin: np.ndarray
    """[3] world point at the image's corner, metres."""
    scale: float
    """Metres per image width."""

    def __post_init__(self) -> None:
        if self.name not in PHOTOS + GREYS:
            raise ValueError(f"expected a photo of {PHOTOS + GREYS}, got {self.name!r}")
        if np.shape(self.rotation) != (3, 3) or np.shape(self.origin) != (3,) or np.shape(self.tint) != (3,):
            raise ValueError(
                f"expected rotation [3, 3], origin [3], tint [3], got {np.shape(self.rotation)}, "
                f"{np.shape(self.origin)}, {np.shape(self.tint)}"
            )
        if not self.scale > 0:
            raise ValueError(f"expected scale > 0 metres, got {self.scale}")

    def albedo(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Albedo [N, 3] in [0, 1] at surface points p [N, 3] with unit normals n [N, 3]."""
        img = photo(self.name)
        px = _apply(p - self.origin, self.rotation) * (img.shape[1] / self.scale)  # [N, 3] texture frame, pixels
        w = np.abs(_apply(n, self.rotation)) ** 4  # [N, 3] triplanar weights
        w /= w.sum(-1, keepdims=True)
        out = np.zeros((len(p), 3))
        for axis, (u, v) in enumerate(((1, 2), (0, 2), (0, 1))):  # project along `axis` onto (u, v)
            out += w[:, axis, None] * _bilinear(img, px[:, u], -px[:, v])  # image rows run down: v up
        return np.clip(out * self.tint, 0.0, 1.0)


@dataclass(frozen=True, kw_only=True)
class PhotoTextured(Primitive):
    """`shape` (any primitive: its surface, normals, mesh) wearing `photo` instead of its solid noise texture."""

    shape: Primitive
    """The surface."""
    photo: PhotoTexture
    """Its colour."""

    @property
    def material(self) -> Material:  # the shape's (unused by `albedo`); kept for code that reads it
        return self.shape.material

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:  # [R, 3], [R, 3] -> t [R]
        return self.shape.intersect(o, d)

    def normal(self, p: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 3]
        return self.shape.normal(p)

    def mesh(self) -> trimesh.Trimesh:
        return self.shape.mesh()

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.shape.bounding_sphere()

    def albedo(self, p: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 3]
        return self.photo.albedo(p, self.shape.normal(p))
