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

Departures from COLMAP:
- FocalPlaneXResolution describes the sensor's full-size image (EXIF PixelXDimension x PixelYDimension); when
  those tags say the photo was saved smaller, the prior is scaled by the ratio of the long sides (COLMAP would keep
  the full-size figure).
- Cropped photos (issue 53). A 35 mm equivalent describes the camera's whole frame, whose aspect is a sensor's
  (3:2, or 4:3 for phones and small sensors), not the photo's: applied to the diagonal of a square crop it is wrong
  (the shared head: 4000 x 4000 px cut from a 6000 x 4000 px APS-C frame, FocalLengthIn35mmFilm 46 mm, gives
  6,014 px by the diagonal where its own cameras say ~7,540). When the photo's aspect is not within
  ASPECT_TOLERANCE of 3:2 or 4:3, the photo is taken as the largest crop of that aspect from the frame (it keeps
  the frame's short side when it is narrower than the frame, the long side when wider), the frame being 3:2 unless
  FocalLengthIn35mmFilm / FocalLength (the crop factor) is at least SMALL_SENSOR_CROP (4:3 sensors: phones, Four
  Thirds, compacts): the head gives 7,666 px (its own cameras: ~7,540, +1.7 %). That rule is a guess about how
  the photo was cut, so the prior is WEAK (`FocalPrior.weak` says why).
- When both FocalLengthIn35mmFilm and FocalLength x FocalPlaneXResolution give a focal and they differ by over
  FIELDS_DISAGREE, the prior is weak too, and the second is used (the pixel pitch survives a crop).
A weak prior starts COLMAP's cameras at its value without `has_prior_focal_length` (COLMAP then calibrates the
focal as it would without EXIF), and the model is compared with it by a check that never decides which attempt is
kept (`quality`: focal_vs_weak_exif): a self-consistent model is never thrown away against a guess.
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

__all__ = [
    "FocalPrior",
    "FILM_DIAGONAL_MM",
    "exif_focal",
    "apply_focal_priors",
    "ZOOM_SPREAD",
    "SENSOR_ASPECTS",
    "ASPECT_TOLERANCE",
    "SMALL_SENSOR_CROP",
    "FIELDS_DISAGREE",
    "crop_frame",
]

FILM_DIAGONAL_MM = 43.27
"""Diagonal of the 36 x 24 mm frame that FocalLengthIn35mmFilm refers to (CIPA DC-008; COLMAP's constant)."""
ZOOM_SPREAD = 0.05
"""Photos sharing one camera whose EXIF priors differ by more than this fraction (a zoom lens moved) get a
warning: one shared focal length cannot fit them all (single_camera=False gives each photo its own camera)."""
SENSOR_ASPECTS = (3 / 2, 4 / 3)
"""Aspects (long / short side) of camera frames: DSLR and mirrorless 3:2; phones, Four Thirds and compacts 4:3."""
ASPECT_TOLERANCE = 0.02
"""A photo within this fraction of a sensor aspect is taken as the whole frame (the 35 mm equivalent applies)."""
SMALL_SENSOR_CROP = 1.8
"""A crop factor (FocalLengthIn35mmFilm / FocalLength) from this up means a 4:3 frame (Four Thirds: 2.0, phones
4-7); under it a 3:2 one (full frame 1.0, APS-C 1.5-1.6)."""
FIELDS_DISAGREE = 0.10
"""FocalLengthIn35mmFilm and FocalLength x FocalPlaneXResolution further apart than this: the prior is weak."""

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
    weak: str | None = None
    """Why the prior is only a guess (a crop whose frame is assumed, EXIF fields that disagree); None: it is what
    the EXIF says of this photo (see the module docstring)."""


def exif_focal(path: Path) -> FocalPrior | None:
    """The photo's focal-length prior from its EXIF, or None when its EXIF has none (see the module docstring)."""
    with Image.open(path) as im:
        width, height = im.size
        try:
            exif = im.getexif().get_ifd(_EXIF_IFD)
        except Exception:  # a malformed EXIF block (Pillow raises several types): no prior, as without EXIF
            return None
    f35, f_mm = _number(exif.get(_FOCAL_35MM)), _number(exif.get(_FOCAL_LENGTH))
    plane = _plane_focal(exif, f_mm, max(width, height))
    if f35 <= 0:
        return plane
    frame, why = crop_frame(width, height, f35 / f_mm if f_mm > 0 else None)
    focal = f35 / FILM_DIAGONAL_MM * math.hypot(*frame)
    source = f"FocalLengthIn35mmFilm {f35:g} mm" + (
        f" on an assumed {frame[0]:.0f} x {frame[1]:.0f} px frame" if why else ""
    )
    if plane is not None and abs(plane.focal_px / focal - 1) > FIELDS_DISAGREE:
        why = (
            f"FocalLengthIn35mmFilm gives {focal:.0f} px, FocalLength x FocalPlaneXResolution {plane.focal_px:.0f} "
            "px: the EXIF fields disagree; the second is used (a crop keeps the pixel pitch)"
        )
        return FocalPrior(focal_px=plane.focal_px, source=plane.source, weak=why)
    return FocalPrior(focal_px=focal, source=source, weak=why)


def crop_frame(width: int, height: int, crop_factor: float | None) -> tuple[tuple[float, float], str | None]:
    """((long, short) side in pixels of the camera frame the photo was cut from, why it is assumed) for a photo of
    `width` x `height` px: the photo itself (why None) when its aspect is a sensor's (SENSOR_ASPECTS), else the
    frame of 3:2 (4:3 when `crop_factor` >= SMALL_SENSOR_CROP) of which it is the largest crop."""
    long, short = max(width, height), min(width, height)
    aspect = long / short
    if any(abs(aspect / a - 1) <= ASPECT_TOLERANCE for a in SENSOR_ASPECTS):
        return (float(long), float(short)), None
    frame = 4 / 3 if crop_factor is not None and crop_factor >= SMALL_SENSOR_CROP else 3 / 2
    kept = "short" if aspect < frame else "long"
    size = (short * frame, float(short)) if kept == "short" else (float(long), long / frame)
    name = "4:3" if frame < 1.4 else "3:2"
    factor = f"crop factor {crop_factor:.2f}" if crop_factor is not None else "no FocalLength to tell the sensor"
    why = (
        f"the photo's aspect ({long}x{short}, {aspect:.3g}:1) is not a camera frame's: taken as a crop keeping the "
        f"{kept} side of a {name} frame ({factor}), a guess"
    )
    return size, why


def _plane_focal(exif: Any, f_mm: float, long_side: int) -> FocalPrior | None:
    """FocalLength x FocalPlaneXResolution, scaled to the photo as stored; None when a tag is missing."""
    resolution = _number(exif.get(_PLANE_X_RES))
    unit = _UNIT_MM.get(int(_number(exif.get(_PLANE_UNIT))))
    if not (f_mm > 0 and resolution > 0 and unit is not None):
        return None
    focal = f_mm * resolution / unit
    full = max(_number(exif.get(_PIXEL_X)), _number(exif.get(_PIXEL_Y)))
    scale = long_side / full if full > 0 else 1.0
    return FocalPrior(
        focal_px=focal * scale,
        source=f"FocalLength {f_mm:g} mm x FocalPlaneXResolution {resolution:g}"
        + (f" (scaled x{scale:.3g} from the sensor's {full:g} px)" if scale != 1.0 else ""),
    )


def _number(value: Any) -> float:
    """An EXIF rational / int as a float; 0 for a missing or unreadable tag."""
    try:
        number = float(value) if value is not None else 0.0
    except (TypeError, ValueError, ZeroDivisionError):
        return 0.0
    return number if math.isfinite(number) else 0.0


def apply_focal_priors(
    db_path: Path, priors: Mapping[str, float], weak: Mapping[str, str] | None = None
) -> dict[int, dict[str, Any]]:
    """Give each camera of a COLMAP database the EXIF prior of its photos (`priors`: image name -> focal px;
    `weak`: image name -> why its prior is only a guess, for the weak ones).

    Returns {camera_id: {"images", "prior_px", "source", "colmap_read" (the prior COLMAP had read from the copy
    itself, or None), "spread" (max / min - 1 of its photos' priors), "weak" (why, or None)}}. A camera one of
    whose photos has a weak prior gets the value as its starting focal WITHOUT has_prior_focal_length (COLMAP
    calibrates it as without EXIF). A camera none of whose photos has an EXIF prior keeps COLMAP's (from its
    camera database, "source" says so) or has none ("absent").
    """
    weak = weak or {}
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
            guesses = [weak[n] for n in members if n in priors and n in weak]
            info: dict[str, Any] = {"images": len(members), "colmap_read": _round(colmap_read), "weak": None}
            if ours:
                focal = float(np.median(ours))
                params = np.array(cam.params)
                params[list(cam.focal_length_idxs())] = focal
                cam.params = params
                cam.has_prior_focal_length = not guesses
                info["weak"] = guesses[0] if guesses else None
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
