"""eval's depth error against a synthetic scene's ground truth: the similarity that maps the run's frame onto the ground
truth's (align_to), per-view absolute errors and their summary."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.ground_truth import GroundTruth
from nerfpipe.data.transforms import Scene
from nerfpipe.model import OPAQUE, render_view
from nerfpipe.radiance.align import umeyama

__all__ = ["SAME_FRAME_TOL", "align_to", "depth_errors", "depth_summary"]


SAME_FRAME_TOL = 1e-4
"""Camera centres within this fraction of the ground-truth extent: the run is already in the GT frame."""


def align_to(scene: Scene, gt: GroundTruth) -> dict[str, Any]:
    """How the run's source frame maps onto the ground-truth frame, from camera centres matched by file name.

    Returns {method: none | similarity, scale (GT units per user unit), matched, rms_centre_error, ...}.
    """
    src, dst = [], []
    for f in scene.frames:
        name = Path(f.file_path).stem
        if name in gt.world_from_cam:
            src.append(scene.source_world_from_cam(f.world_from_cam)[:3, 3])
            dst.append(gt.world_from_cam[name][:3, 3])
    if not src:
        raise UserError(f"--ground-truth: no image name of the run's scene appears in {gt.folder / 'cameras.json'}")
    src_a, dst_a = np.array(src), np.array(dst)
    extent = float(np.linalg.norm(dst_a.max(0) - dst_a.min(0))) or 1.0
    err = np.linalg.norm(src_a - dst_a, axis=1)
    if err.max() <= SAME_FRAME_TOL * extent:
        return {
            "method": "none",
            "reason": "the run's cameras (source frame) coincide with the ground truth",
            "scale": 1.0,
            "matched": len(src),
            "rms_centre_error": float(np.sqrt((err**2).mean())),
        }
    if len(src) < 3:
        raise UserError(f"--ground-truth: frames differ and only {len(src)} camera(s) match by name (need 3)")
    s, rot, t = umeyama(src_a, dst_a)
    res = np.linalg.norm(s * src_a @ rot.T + t - dst_a, axis=1)
    return {
        "method": "similarity",
        "reason": "the run's source frame is not the ground-truth frame: Umeyama fit of camera centres by name",
        "scale": float(s),
        "rotation": rot.tolist(),
        "translation": t.tolist(),
        "matched": len(src),
        "rms_centre_error": float(np.sqrt((res**2).mean())),
    }


def depth_errors(trained, view, intr, pose, name, gt, alignment, scale, device):
    """|pred - gt| [n] in GT units on the pixels where the GT has depth; (None, 0, 0) when no GT depth file."""
    path = gt.folder / "depth" / f"{Path(name).stem}.npy"
    if not path.is_file():
        return None, 0, 0
    gt_depth = np.load(path, allow_pickle=False).astype(np.float64)
    if gt_depth.shape != view["depth"].shape:  # ground truth at another resolution: render at its size
        view = render_view(trained, intr.scaled(gt_depth.shape[1] / intr.w), pose, device)
    pred = view["depth"].astype(np.float64) / scale * alignment["scale"]
    has_gt = np.isfinite(gt_depth) & (gt_depth > 0)
    ok = has_gt & np.isfinite(pred)
    covered = int((has_gt & (view["acc"] >= OPAQUE)).sum())
    return np.abs(pred[ok] - gt_depth[ok]), covered, int(has_gt.sum())


def depth_summary(gt, alignment, abs_errors, covered, gt_pixels) -> dict[str, Any]:
    if gt is None:
        return {
            "depth_mae": None,
            "depth_median_abs_error": None,
            "depth_coverage": None,
            "depth_alignment": None,
            "depth_unavailable": "no --ground-truth given",
            "ground_truth": None,
        }
    err = np.concatenate(abs_errors) if abs_errors else np.zeros(0)
    return {
        "depth_mae": float(err.mean()) if err.size else None,
        "depth_median_abs_error": float(np.median(err)) if err.size else None,
        "depth_coverage": covered / gt_pixels if gt_pixels else None,
        "depth_units": "ground-truth units (metres): run depth / applied_scale x alignment scale",
        "depth_pixels": int(err.size),
        "depth_alignment": alignment,
        "depth_unavailable": None if err.size else "no ground-truth depth file matched a test view",
        "ground_truth": str(gt.folder),
    }
