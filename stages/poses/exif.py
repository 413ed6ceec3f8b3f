"""The focal-length prior of the poses stage: read from the photos' EXIF with Pillow, handed to COLMAP's cameras.

How COLMAP gets a prior by itself (pycolmap 4.2, `Bitmap::ExifFocalLength`, read by `extract_features` from the
image file it is given): FocalLengthIn35mmFilm -> f = f35 / 43.27 mm * image diagonal (px), the CIPA definition of
the 35 mm equivalent (the 36 x 24 mm frame's diagonal is 43.27 mm; for a 3:2 photo this is f35 / 36 mm * long
side); else FocalLength (mm) x FocalPlaneXResolution (pixels per FocalPlaneResolutionUnit); else FocalLength and
the sensor width from COLMAP's camera database (by EXIF Make / Model). The camera then gets that focal length and
`has_prior_focal_length = True`; without any, f = 1.2 x long side and no prior.

`colmap/images/` holds copies (`images.write_upright`): JPEG and PNG files that need no rotation are copied byte
for byte and keep their EXIF; rotated JPEGs are re-encoded with it; other formats (TIFF, BMP, WebP) become PNG
WITHOUT their EXIF. So this module reads the prior from each ORIGINAL photo (`exif_focal`, the same rules as
COLMAP but the camera database, which Pillow does not have) and writes it into the database's cameras after
extraction and before matching (`apply_focal_priors`), as COLMAP does: the focal parameter(s) set to the prior and
`has_prior_focal_length = True` (two-view verification and the mapper's initial pair then use it). pycolmap's
`ImageReaderOptions` has no per-photo prior to pass instead: only `camera_params` (one parameter string for every
camera) and `default_focal_length_factor`. A camera shared by several photos gets the median of their priors.
Rotation changes neither the diagonal nor the long side, so an upright copy has the same prior in pixels as the
photo stored sideways.

One departure: FocalPlaneXResolution describes the sensor's full-size image (EXIF PixelXDimension x
PixelYDimension); when those tags say the photo was saved smaller, the prior is scaled by the ratio of the long
sides (COLMAP would keep the full-size figure).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from PIL import Image

__all__ = ["FocalPrior", "FILM_DIAGONAL_MM", "exif_focal", "apply_focal_priors", "ZOOM_SPREAD"]

FILM_DIAGONAL_MM = 43.27
"""Diagonal of the 36 x 24 mm frame that FocalLengthIn35mmFilm refers to (CIPA DC-008; COLMAP's constant)."""
ZOOM_SPREAD = 0.05
"""Photos sharing one camera whose EXIF priors differ by more than this fraction (a zoom lens moved) get a
warning: one shared focal length cannot fit them all (single_camera=False gives each photo its own camera)."""

_EXIF_IFD = 0x8769
_FOCAL_LENGTH, _FOCAL_35MM = 0x920A, 0xA405
_PLANE_X_RES, _PLANE_UNIT = 0xA20E, 0xA210
_PIXEL_X, _PIXEL_Y = 0xA002, 0xA003
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit: inch, cm, mm, um


@dataclass(frozen=True, kw_only=True)
class FocalPrior:
    focal_px: float
    """Focal length in pixels of the photo as stored (the same for its upright copy)."""
    source: str
    """Which EXIF tags gave it, with their values, e.g. "FocalLengthIn35mmFilm 50 mm"."""


def exif_focal(path: Path) -> FocalPrior | None:
    """The photo's focal-length prior from its EXIF, or None when its EXIF has none (see the module docstring)."""
    with Image.open(path) as im:
        width, height = im.size
        try:
            exif = im.getexif().get_ifd(_EXIF_IFD)
        except Exception:  # a malformed EXIF block (Pillow raises several types): no prior, as without EXIF
            return None
    f35 = _number(exif.get(_FOCAL_35MM))
    if f35 > 0:
        focal = f35 / FILM_DIAGONAL_MM * math.hypot(width, height)
        return FocalPrior(focal_px=focal, source=f"FocalLengthIn35mmFilm {f35:g} mm")
    f_mm, resolution = _number(exif.get(_FOCAL_LENGTH)), _number(exif.get(_PLANE_X_RES))
    unit = _UNIT_MM.get(int(_number(exif.get(_PLANE_UNIT))))
    if f_mm > 0 and resolution > 0 and unit is not None:
        focal = f_mm * resolution / unit
        full = max(_number(exif.get(_PIXEL_X)), _number(exif.get(_PIXEL_Y)))
        scale = max(width, height) / full if full > 0 else 1.0
        return FocalPrior(
            focal_px=focal * scale,
            source=f"FocalLength {f_mm:g} mm x FocalPlaneXResolution {resolution:g}"
            + (f" (scaled x{scale:.3g} from the sensor's {full:g} px)" if scale != 1.0 else ""),
        )
    return None


def _number(value: Any) -> float:
    """An EXIF rational / int as a float; 0 for a missing or unreadable tag."""
    try:
        number = float(value) if value is not None else 0.0
    except (TypeError, ValueError, ZeroDivisionError):
        return 0.0
    return number if math.isfinite(number) else 0.0


def apply_focal_priors(db_path: Path, priors: Mapping[str, float]) -> dict[int, dict[str, Any]]:
    """Give each camera of a COLMAP database the EXIF prior of its photos (`priors`: image name -> focal px).

    Returns {camera_id: {"images", "prior_px", "source", "colmap_read" (the prior COLMAP had read from the copy
    itself, or None), "spread" (max / min - 1 of its photos' priors)}}. A camera none of whose photos has an
    EXIF prior keeps COLMAP's (from its camera database, "source" says so) or has none ("absent").
    """
    db = pycolmap.Database.open(db_path)
    try:
        names: dict[int, list[str]] = {}
        for im in db.read_all_images():
            names.setdefault(im.camera_id, []).append(im.name)
        out: dict[int, dict[str, Any]] = {}
        for camera_id, members in sorted(names.items()):
            cam = db.read_camera(camera_id)
            colmap_read = float(cam.mean_focal_length()) if cam.has_prior_focal_length else None
            ours = [priors[n] for n in members if n in priors]
            info: dict[str, Any] = {"images": len(members), "colmap_read": _round(colmap_read)}
            if ours:
                focal = float(np.median(ours))
                params = np.array(cam.params)
                params[list(cam.focal_length_idxs())] = focal
                cam.params = params
                cam.has_prior_focal_length = True
                db.update_camera(cam)
                info.update(
                    prior_px=_round(focal),
                    source=f"EXIF of {len(ours)} of {len(members)} photos",
                    spread=round(max(ours) / min(ours) - 1, 4),
                )
            elif colmap_read is not None:
                info.update(prior_px=_round(colmap_read), source="COLMAP (EXIF focal length, its sensor database)")
            else:
                info.update(prior_px=None, source="absent")
            out[camera_id] = info
    finally:
        db.close()
    return out


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 2)
