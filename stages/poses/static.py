"""The poses stage's refusal of a static camera: a turntable (the object turns, the camera and the room stay) or a
tripod gives matches that stay at the same pixel in every view; the mapper then fails, or models the room and puts
every camera at one place. `check_static_matches` (after the first attempt's matching) and
`check_static_cameras` (on the kept model) turn that into one-line UserErrors that ask for --masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from nerfpipe.data.errors import UserError
from nerfpipe.stages.poses.report import MIN_REGISTERED, RunState

__all__ = [
    "STATIC_FRACTION",
    "STATIC_PIXELS",
    "STATIC_SPREAD",
    "stationary_matches",
    "check_static_matches",
    "check_static_cameras",
]

STATIC_FRACTION = 0.3
"""More than this fraction of the verified inlier matches staying at the same pixel (`stationary_matches`)
means the camera did not move relative to much of what it saw: a turntable (object turns, camera and
background fixed) or a tripod. The mapper then either fails or triangulates the background and puts every
camera at one place. A normal capture has ~0 (synthetic orbit: 0.0; turntable without masks: see
tests/test_turntable.py)."""
STATIC_PIXELS = 1.5
"""A match 'stays at the same pixel' when it moves less than this many pixels, or 0.2 % of the image's long
side when that is more (SIFT's localisation error is well under a pixel)."""
STATIC_SPREAD = 0.01
"""Registered camera centres whose spread (RMS distance from their mean) is under this fraction of their
median distance to the model's points are 'all at one place' (`check_static_cameras`)."""


def stationary_matches(db_path: Path) -> tuple[float, int]:
    """(fraction of the verified inlier matches whose keypoint is at the same pixel in both images (within
    STATIC_PIXELS), number of inlier matches) over the verified pairs of a COLMAP database whose images are at
    least an eighth of the set (and 2) apart in extraction order: a turntable's background stays put between
    any two views, while the neighbours of a slowly moving video may still share pixels."""
    db = pycolmap.Database.open(db_path)
    try:
        keypoints, sizes = {}, {}
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        rank = {im.image_id: k for k, im in enumerate(images)}
        gap = max(2, len(images) // 8)
        for im in images:
            keypoints[im.image_id] = db.read_keypoints(im.image_id)[:, :2]
            cam = db.read_camera(im.camera_id)
            sizes[im.image_id] = max(cam.width, cam.height)
        still = total = 0
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            m = np.asarray(geometry.inlier_matches)
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if m.size == 0 or abs(rank[a] - rank[b]) < gap:
                continue
            moved = np.linalg.norm(keypoints[a][m[:, 0]] - keypoints[b][m[:, 1]], axis=1)
            still += int((moved < max(STATIC_PIXELS, 0.002 * sizes[a])).sum())
            total += len(m)
    finally:
        db.close()
    return (still / total if total else 0.0), total


def check_static_matches(db_path: Path, masked: bool, state: RunState) -> None:
    """UserError when most verified matches stay at the same pixel (STATIC_FRACTION): the background of a
    static camera dominates. Records the fraction in the report either way."""
    fraction, total = stationary_matches(db_path)
    state.stationary = {"fraction": round(fraction, 4), "inlier_matches": total, "limit": STATIC_FRACTION}
    if fraction > STATIC_FRACTION:
        fix = (
            "the masks leave too much of the static background white; mask it black"
            if masked
            else "give --masks DIR (one mask per photo, the object white, the rest black)"
        )
        raise UserError(
            f"static camera: {fraction:.0%} of the {total} verified feature matches stay at the same pixel "
            f"across views, so the background does not move (a turntable or tripod capture): the poses would be "
            f"those of the room, not of the object; {fix}"
        )


def check_static_cameras(rec: pycolmap.Reconstruction, masked: bool) -> None:
    """UserError when the registered cameras all sit at one place (STATIC_SPREAD of their distance to the
    points): a model of a static camera's background, whatever the matches said."""
    images = [im for im in rec.images.values() if im.has_pose]
    if len(images) < MIN_REGISTERED or rec.num_points3D() == 0:
        return
    centres = np.stack([im.projection_center() for im in images])
    points = np.stack([p.xyz for p in rec.points3D.values()])
    spread = float(np.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean()))
    dist = float(np.median(np.linalg.norm(points - centres.mean(0), axis=1)))
    if spread < STATIC_SPREAD * dist:
        fix = "the masks leave the static background in" if masked else "give --masks DIR (the object white)"
        raise UserError(
            f"static camera: the {len(images)} registered cameras all sit at one place (spread {spread:.3g}, "
            f"{spread / max(dist, 1e-12):.2%} of the distance to the scene): the model is of what did not move; {fix}"
        )
