"""Checks of a COLMAP model's cameras and structure, so that the poses stage never keeps a bad model silently.

Each check is a `data.checks.Check` (a figure against a limit); `model_checks` gives them for a reconstruction and
`data.checks.verdict` turns them into the {"check": "ok" | "suspect", "checks": [...]} of poses_report.json and
colmap/manifest.json. The CAMERA checks (`CAMERA_CHECKS`, one set per camera that a registered image uses) decide
which retry attempt is kept (`choice.choose`); the MODEL checks only mark the result suspect.

Camera checks and their limits:
  focal_vs_exif    |f / f_EXIF - 1| <= FOCAL_TOLERANCE (25 %), when the photos' EXIF gives a prior (`exif`).
                   The EXIF figure is the lens's focal length: focus breathing, in-camera crops and the 35 mm
                   equivalent's rounding move the true one by a few %, a wrong self-calibration by tens of %
                   (the case that motivated this: f = 10,450 px against EXIF 7,540 px, +39 %).
  focal_vs_weak_exif  |f / f_EXIF - 1| <= WEAK_FOCAL_TOLERANCE (50 %) when the prior is only a guess (`exif`: a
                   cropped photo whose camera frame is assumed, or EXIF focal fields that disagree). NOT a camera
                   check: it marks the result suspect but never decides which attempt is kept (a self-consistent
                   model is not thrown away against a guess; issue 53's 4000 px head lost 8 of 22 photos so). The
                   field_of_view check runs beside it as the camera check.
  field_of_view    FOV_RANGE_DEG (10-140 deg) across the long side, 2 atan(L / 2f), when there is no prior or a
                   weak one: 10 deg is a ~200 mm lens on a 35 mm camera, beyond which SfM's geometry is poorly
                   conditioned anyway; 140 deg is beyond any rectilinear lens (a 12 mm full-frame lens gives 113
                   deg), and these camera models cannot describe a fisheye.
  focal_aspect     |fx / fy - 1| <= ASPECT_TOLERANCE (5 %) for models with two focal lengths (PINHOLE, OPENCV):
                   every current sensor has square pixels, so a larger ratio is a degenerate fit.
  distortion       the largest radial displacement the distortion parameters cause inside the image, as a fraction
                   of the distance from the principal point, <= MAX_DISTORTION (15 %). Measured along the rays
                   through the image corners and edge midpoints from the centre (an ideal lens images them at
                   the corners), so one bound serves SIMPLE_RADIAL, RADIAL and OPENCV (tangential terms
                   included) and scales with the field of view: a bound on k1 itself would not (in normalised
                   coordinates a 200 mm lens sees r <= 0.1, so its k1 can be large while the image barely
                   bends). Rectilinear lenses stay under ~10 % at the corner (a strong 14-16 mm wide angle has
                   ~5-6 % "TV distortion", ~1.4x that at a 3:2 frame's corner); SIMPLE_RADIAL at f = long side
                   on a 3:2 frame reaches 15 % at |k1| = 0.42. The motivating case (k1 = -2.56, f = 10,450 px,
                   4000 x 4000 px) bends its corners by 19 %. 15 % also keeps SIMPLE_RADIAL from folding the
                   image back on itself, which needs a displacement of 33 % (1 + 3 k1 r^2 = 0).
  principal_point  distance of the principal point from the image centre <= PP_TOLERANCE (10 %) of the long
                   side: lenses are centred to a percent or two; the stage's own refinement
                   (`lens.PP_MAX_SHIFT`) rejects larger moves for the same reason.
Model checks:
  reprojection_error  mean reprojection error <= MAX_REPROJECTION_PX (2 px, the model's pixels): the mapper drops
                   observations over 4 px, so a mean at half that cap says most kept observations sit near it
                   (synthetic 256 px set: ~0.5 px).
  track_length     mean observations per 3D point >= MIN_TRACK_LENGTH (2.5): a point needs 2; a model whose
                   points are mostly seen twice rests on pairwise links only (synthetic 24-view set: ~6).
  registered_fraction  registered / total >= WARN_FRACTION (80 %), the stage's own warning level.
A check that does not apply (no prior, one focal length, no 3D points) is left out, never recorded as passed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

import numpy as np
import pycolmap

from nerfpipe.data.checks import Check
from nerfpipe.stages.poses.report import WARN_FRACTION

__all__ = [
    "CAMERA_CHECKS",
    "FOCAL_TOLERANCE",
    "WEAK_FOCAL_TOLERANCE",
    "FOV_RANGE_DEG",
    "ASPECT_TOLERANCE",
    "MAX_DISTORTION",
    "PP_TOLERANCE",
    "MAX_REPROJECTION_PX",
    "MIN_TRACK_LENGTH",
    "camera_checks",
    "model_checks",
    "distortion_at_edges",
    "cameras_pass",
    "failed",
]

FOCAL_TOLERANCE = 0.25
WEAK_FOCAL_TOLERANCE = 0.5
FOV_RANGE_DEG = (10.0, 140.0)
ASPECT_TOLERANCE = 0.05
MAX_DISTORTION = 0.15
PP_TOLERANCE = 0.10
MAX_REPROJECTION_PX = 2.0
MIN_TRACK_LENGTH = 2.5
CAMERA_CHECKS = ("focal_vs_exif", "field_of_view", "focal_aspect", "distortion", "principal_point")
"""The checks of a camera's intrinsics: an attempt that fails one is kept only when no attempt passes them all."""


def camera_checks(
    cam: pycolmap.Camera, prior_px: float | None, label: str = "the camera", weak: str | None = None
) -> list[Check]:
    """The intrinsics checks of one camera (see the module docstring); `prior_px` is its EXIF focal or None,
    `weak` why that prior is only a guess (None: it is not)."""
    w, h = cam.width, cam.height
    long_side = max(w, h)
    fx, fy = float(cam.focal_length_x), float(cam.focal_length_y)
    f = (fx + fy) / 2
    checks = []
    if prior_px is not None and weak is None:
        off = f / prior_px - 1
        checks.append(
            _said(
                Check.upper("focal_vs_exif", abs(off) * 100, FOCAL_TOLERANCE * 100, unit=" %", says=""),
                f"{label}: f = {f:.0f} px against the EXIF prior {prior_px:.0f} px ({off:+.0%})",
                "the self-calibration drifted, so the poses are likely off too",
            )
        )
    else:
        if prior_px is not None:
            off = f / prior_px - 1
            checks.append(
                _said(
                    Check.upper("focal_vs_weak_exif", abs(off) * 100, WEAK_FOCAL_TOLERANCE * 100, unit=" %", says=""),
                    f"{label}: f = {f:.0f} px against a weak EXIF prior {prior_px:.0f} px ({off:+.0%}; {weak})",
                    "far even from a guess: check the intrinsics (this check never decides which attempt is kept)",
                )
            )
        fov = math.degrees(2 * math.atan(long_side / (2 * f))) if f > 0 else math.nan
        lo, hi = FOV_RANGE_DEG
        checks.append(
            _said(
                Check(
                    name="field_of_view",
                    ok=bool(lo <= fov <= hi),
                    value=_round(fov),
                    limit=f"{lo:g}-{hi:g} deg",
                    says="",
                ),
                f"{label}: f = {f:.0f} px gives a {fov:.0f} deg field of view across {long_side} px ("
                + ("no EXIF focal length to compare with)" if prior_px is None else "the EXIF prior is weak)"),
                "no rectilinear lens has that: a degenerate self-calibration",
            )
        )
    if len(cam.focal_length_idxs()) == 2:
        checks.append(
            _said(
                Check.upper("focal_aspect", abs(fx / fy - 1) * 100, ASPECT_TOLERANCE * 100, unit=" %", says=""),
                f"{label}: fx = {fx:.0f} px, fy = {fy:.0f} px",
                "pixels are square, so this is a degenerate fit",
            )
        )
    bend = distortion_at_edges(cam)
    params = ", ".join(f"{n.strip()} = {v:.3g}" for n, v in _extra_params(cam))
    checks.append(
        _said(
            Check.upper("distortion", bend * 100, MAX_DISTORTION * 100, unit=" %", says=""),
            f"{label}: the distortion ({params or 'none'}) moves points at the image edge by up to {bend:.1%} of their "
            "distance from the centre",
            "more than a rectilinear lens does: a degenerate self-calibration",
        )
    )
    shift = math.hypot(cam.principal_point_x - w / 2, cam.principal_point_y - h / 2) / long_side
    checks.append(
        _said(
            Check.upper("principal_point", shift * 100, PP_TOLERANCE * 100, unit=" %", says=""),
            f"{label}: the principal point ({cam.principal_point_x:.0f}, {cam.principal_point_y:.0f}) is {shift:.1%} "
            "of the image size off its centre",
            "lenses are centred, so this is a degenerate fit",
        )
    )
    return checks


def _said(check: Check, figure: str, meaning: str) -> Check:
    """`check` saying its figure, and what that means when it failed."""
    return replace(check, says=figure if check.ok else f"{figure}: {meaning}")


def distortion_at_edges(cam: pycolmap.Camera, samples: int = 32) -> float:
    """Largest |distorted - ideal| / |ideal - principal point| (pixels) over points an ideal pinhole with this
    camera's focal length and principal point images along the rays to the 4 corners and 4 edge midpoints."""
    fx, fy = float(cam.focal_length_x), float(cam.focal_length_y)
    cx, cy, w, h = cam.principal_point_x, cam.principal_point_y, cam.width, cam.height
    ends = np.array([[0, 0], [w, 0], [0, h], [w, h], [w / 2, 0], [w / 2, h], [0, h / 2], [w, h / 2]], float)
    t = np.linspace(1 / samples, 1, samples)[:, None, None]  # [S, 1, 1]
    ideal = np.array([cx, cy]) + t * (ends - [cx, cy])  # [S, 8, 2] pixels
    ideal = ideal.reshape(-1, 2)  # [S*8, 2]
    radius = np.linalg.norm(ideal - [cx, cy], axis=1)  # [S*8]
    keep = radius > 1e-6 * max(w, h)
    ideal, radius = ideal[keep], radius[keep]
    cam_points = np.column_stack([(ideal[:, 0] - cx) / fx, (ideal[:, 1] - cy) / fy, np.ones(len(ideal))])  # [N, 3]
    imaged = cam.img_from_cam(cam_points)  # [N, 2]
    bend = np.linalg.norm(imaged - ideal, axis=1) / radius
    return float(bend.max()) if np.all(np.isfinite(bend)) else math.inf


def _extra_params(cam: pycolmap.Camera) -> list[tuple[str, float]]:
    names = cam.params_info.split(",")
    return [(names[i], float(cam.params[i])) for i in cam.extra_params_idxs()]


def model_checks(
    rec: pycolmap.Reconstruction,
    priors: Mapping[int, float | None],
    total: int,
    weak: Mapping[int, str | None] | None = None,
) -> list[Check]:
    """Camera checks of every camera a registered image uses (`priors`: camera id -> EXIF focal px; `weak`: camera
    id -> why its prior is only a guess), then the model checks (reprojection error, track length, registered
    fraction of `total` images)."""
    weak = weak or {}
    used = sorted({im.camera_id for im in rec.images.values() if im.has_pose})
    checks: list[Check] = []
    for camera_id in used:
        cam = rec.cameras[camera_id]
        label = f"camera {camera_id} ({cam.width}x{cam.height})" if len(used) > 1 else "the camera"
        checks += camera_checks(cam, priors.get(camera_id), label, weak.get(camera_id))
    if rec.num_points3D() > 0:
        err = float(rec.compute_mean_reprojection_error())
        checks.append(
            _said(
                Check.upper("reprojection_error", err, MAX_REPROJECTION_PX, unit=" px", says=""),
                f"mean reprojection error {err:.2f} px",
                "the model fits its own observations poorly",
            )
        )
        track = float(rec.compute_mean_track_length())
        checks.append(
            _said(
                Check.lower("track_length", track, MIN_TRACK_LENGTH, says=""),
                f"3D points are seen in {track:.1f} images on average",
                "the views are linked only pairwise",
            )
        )
    reg = rec.num_reg_images()
    checks.append(
        _said(
            Check.lower(
                "registered_fraction", reg / total * 100 if total else math.nan, WARN_FRACTION * 100, unit=" %", says=""
            ),
            f"{reg} of {total} images registered",
            "poses_report.json says why each other one did not",
        )
    )
    return checks


def cameras_pass(checks: list[Check]) -> bool:
    """All camera checks pass (model checks are not looked at)."""
    return all(c.ok for c in checks if c.name in CAMERA_CHECKS)


def failed(checks: list[Check], camera_only: bool = False) -> str:
    """'focal_vs_exif = 38.6 (expected <= 25 %), distortion = ...': the failed checks with their figures."""
    bad = [c for c in checks if not c.ok and (not camera_only or c.name in CAMERA_CHECKS)]
    return ", ".join(f"{c.name} = {_text(c.value)} (expected {c.limit})" for c in bad)


def _text(value: float | int | str) -> str:
    return f"{value:g}" if isinstance(value, (int, float)) else value


def _round(value: float) -> float | str:
    if math.isnan(value) or math.isinf(value):
        return str(value)
    return float(f"{value:.4g}")
