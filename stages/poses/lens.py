"""The last bundle adjustment of the poses stage: lens terms the mapper keeps fixed, each kept only where it pays.

The mapper calibrates SIMPLE_RADIAL (f, k1) with the principal point at the image centre: robust on any capture,
but a real phone lens is off centre by a percent and bends with more than one radial term, and the pose of every
camera absorbs what the camera model cannot say. A camera shared by LENS_MIN_IMAGES+ registered images constrains
more, so two nested steps follow the mapper, each a full bundle adjustment judged by the F statistic of the
reprojection improvement it buys per added parameter (`improvement_f`; pure noise gives ~1):

1. `refine_principal_point`: (cx, cy) free. Kept if F >= LENS_MIN_F and the point moved under PP_MAX_SHIFT of the
   image size (lenses are centred to a percent or two).
2. `add_radial_term`: a shared SIMPLE_RADIAL camera becomes RADIAL (f, cx, cy, k1, k2), the principal point free
   again where step 1 kept it. Kept if F >= LENS_MIN_F and the lens stays plausible (`quality.distortion_at_edges`
   under `quality.MAX_DISTORTION`); else SIMPLE_RADIAL stays. The user's `--camera-model` otherwise is left as asked.

Fox (50 phone photos, 1080x1920, against instant-ngp's COLMAP poses, which used OPENCV; `benchmarks/bench_poses.py
--only fox`), median / largest rotation error after a similarity:
| final model                                        | F        | rotation error      | reprojection |
| + principal point (step 1)                         | 512      | 0.199 / 0.354 deg   | 1.126 px     |
| + k2, principal point fixed                        | 5,319    | 0.171 / 0.271 deg   | 1.088 px     |
| + k2, principal point free (step 2)                | 5,377    | 0.120 / 0.203 deg   | 1.087 px     |
| OPENCV (fx, fy, k1, k2, p1, p2) from that          | 26 (< 100: not kept) | 0.074 / 0.211 deg | 1.087 px |
The tangential terms and a second focal length buy too little here to pass the same test, so they are not tried.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pycolmap

from nerfpipe.stages.poses.quality import MAX_DISTORTION, distortion_at_edges

__all__ = [
    "LENS_MIN_IMAGES",
    "LENS_MIN_F",
    "PP_MAX_SHIFT",
    "refine_principal_point",
    "add_radial_term",
    "improvement_f",
]

LENS_MIN_IMAGES = 10
"""A camera's lens is refined past the mapper only if this many registered images share it."""
PP_MAX_SHIFT = 0.1
"""The principal point is kept only if it moved less than this fraction of the image size."""
LENS_MIN_F = 100.0
"""A lens term is kept only where the reprojection error dropped significantly: F statistic of the improvement
per added parameter (pure noise gives ~1; fox 1080x1920, where both terms are real, 512 and 5,377; the 256 px
synthetic scene, a centred pinhole, ~30)."""


def _shared(rec: pycolmap.Reconstruction) -> list[int]:
    users = Counter(im.camera_id for im in rec.images.values() if im.has_pose)
    return sorted(c for c, k in users.items() if k >= LENS_MIN_IMAGES)


def _adjust(rec: pycolmap.Reconstruction, free: list[int], principal_point: bool, num_threads: int) -> None:
    """Bundle adjustment in place: every registered pose and point, the intrinsics of the `free` cameras only."""
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_principal_point = principal_point
    opts.print_summary = False
    opts.ceres.solver_options.num_threads = num_threads
    ba = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        ba.add_image(image_id)
    for cam_id in rec.cameras:
        if cam_id not in free:
            ba.set_constant_cam_intrinsics(cam_id)
    ba.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    pycolmap.create_default_bundle_adjuster(opts, ba, rec).solve()
    rec.update_point_3d_errors()


def refine_principal_point(rec: pycolmap.Reconstruction, num_threads: int) -> tuple[pycolmap.Reconstruction, str]:
    """Step 1 (module doc): the principal point of cameras shared by LENS_MIN_IMAGES+ images.

    The mapper keeps it at the image centre, which shows up as a constant rotation offset of every camera (fox:
    ~0.65 deg against instant-ngp's COLMAP poses, which refined it the same way). Returns (the model to keep, what
    was done, for the report).
    """
    shared = _shared(rec)
    if not shared:
        return rec, "kept at the image centre (no camera shared by enough images)"
    refined = pycolmap.Reconstruction(rec)
    _adjust(refined, shared, True, num_threads)
    f_stat = improvement_f(rec, refined, extra_params=2 * len(shared))
    moved = 0.0
    for cam_id in shared:
        a, b = rec.cameras[cam_id], refined.cameras[cam_id]
        shift = np.hypot(b.principal_point_x - a.principal_point_x, b.principal_point_y - a.principal_point_y)
        moved = max(moved, float(shift) / max(a.width, a.height))
    what = f"moved up to {moved:.2%} of the image size, F = {f_stat:.0f}"
    if moved > PP_MAX_SHIFT or not np.isfinite(moved) or f_stat < LENS_MIN_F:
        return rec, f"refinement rejected ({what}); kept at the image centre"
    return refined, f"refined for {len(shared)} shared camera(s) ({what})"


def add_radial_term(
    rec: pycolmap.Reconstruction, principal_point: bool, num_threads: int
) -> tuple[pycolmap.Reconstruction, str]:
    """Step 2 (module doc): shared SIMPLE_RADIAL cameras -> RADIAL, the principal point free if `principal_point`
    (step 1 kept it). Returns (the model to keep, what was done, for the report)."""
    shared = [c for c in _shared(rec) if rec.cameras[c].model == pycolmap.CameraModelId.SIMPLE_RADIAL]
    if not shared:
        return rec, "not tried (no SIMPLE_RADIAL camera shared by enough images)"
    refined = pycolmap.Reconstruction(rec)
    for cam_id in shared:
        cam = refined.cameras[cam_id]
        f, cx, cy, k1 = (float(v) for v in cam.params)
        refined.cameras[cam_id] = pycolmap.Camera(
            model="RADIAL", width=cam.width, height=cam.height, params=[f, cx, cy, k1, 0.0], camera_id=cam_id
        )
    _adjust(refined, shared, principal_point, num_threads)
    f_stat = improvement_f(rec, refined, extra_params=len(shared))
    k2 = max((float(refined.cameras[c].params[4]) for c in shared), key=abs)
    bend = max(distortion_at_edges(refined.cameras[c]) for c in shared)
    what = f"k2 = {k2:.4g}, F = {f_stat:.0f}, the image edge bent by up to {bend:.1%}"
    if not np.isfinite(f_stat) or f_stat < LENS_MIN_F:
        return rec, f"rejected ({what}: too little gain); SIMPLE_RADIAL kept"
    if not bend <= MAX_DISTORTION:
        return rec, f"rejected ({what}: over {MAX_DISTORTION:.0%}); SIMPLE_RADIAL kept"
    return refined, f"RADIAL (k1, k2) for {len(shared)} shared camera(s) ({what})"


def _sse(rec: pycolmap.Reconstruction) -> tuple[float, int]:
    """Sum of squared reprojection errors (from each point's mean error) and the number of residuals."""
    sse, n = 0.0, 0
    for point in rec.points3D.values():
        k = point.track.length()
        sse += k * point.error**2
        n += 2 * k
    return sse, n


def improvement_f(before: pycolmap.Reconstruction, after: pycolmap.Reconstruction, extra_params: int) -> float:
    """F statistic of the reprojection improvement bought by `extra_params` more parameters (~1 if noise)."""
    sse0, _ = _sse(before)
    sse1, n = _sse(after)
    if sse1 <= 0 or n <= extra_params:
        return 0.0
    return float((sse0 - sse1) / extra_params / (sse1 / (n - extra_params)))
