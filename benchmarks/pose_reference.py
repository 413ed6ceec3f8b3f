"""Poses from `nerfpipe poses` against a capture's own: the figures the benchmarks report.

Two measures: the rotation error of each camera after a similarity alignment of the centres (`radiance.align`), and
the difference of the rotation between every two cameras, model against reference, which needs no alignment
(issue 53's measure of a folded carton: 27 deg at the median, up to 149). References: a `transforms.json` (fox,
instant-ngp's COLMAP run), an LLFF `poses_bounds.npy` whose rows follow the sorted image names (the head), or a
scene stage's ground truth (exact).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from nerfpipe.data.ground_truth import read_ground_truth
from nerfpipe.data.importers.colmap import read_world_from_cam
from nerfpipe.data.importers.llff import world_from_cam_from_llff
from nerfpipe.data.transforms import read_scene
from nerfpipe.radiance.align import pose_errors

__all__ = ["from_transforms", "from_llff", "from_ground_truth", "compare"]


def from_transforms(path: Path) -> dict[str, np.ndarray]:
    """{image file name: world_from_cam 4x4 (OpenGL)} of a transforms.json."""
    return {Path(f.file_path).name: f.world_from_cam for f in read_scene(path).frames}


def from_llff(folder: Path) -> dict[str, np.ndarray]:
    """{image file name: world_from_cam} of folder/poses_bounds.npy, rows in sorted folder/images/ name order."""
    names = sorted(p.name for p in (folder / "images").iterdir() if p.is_file())
    poses = world_from_cam_from_llff(np.load(folder / "poses_bounds.npy"))
    if len(names) != len(poses):
        raise ValueError(f"{folder}: {len(names)} images but {len(poses)} rows in poses_bounds.npy")
    return dict(zip(names, poses, strict=True))


def from_ground_truth(scene_dir: Path) -> dict[str, np.ndarray]:
    """{image file name: world_from_cam} of a `nerfpipe scene` folder's ground truth."""
    return read_ground_truth(scene_dir).by_file_name()


def _angle(r: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def compare(sparse: Path, reference: dict[str, np.ndarray], by_stem: bool = False) -> dict:
    """Registered images in common, rotation error after alignment (median / largest, deg) and the difference of
    the rotation between two cameras (median / largest over all pairs, deg) of the model in `sparse` against
    `reference`. `by_stem`: match names without their extension (a reference of .JPG photos, a model of copies)."""
    est = read_world_from_cam(sparse)
    key = (lambda n: Path(n).stem) if by_stem else (lambda n: n)
    ref = {key(n): w for n, w in reference.items()}
    est = {key(n): w for n, w in est.items()}
    common = sorted(set(est) & set(ref))
    if len(common) < 3:
        return {"common": len(common), "reference": len(ref)}
    err = pose_errors(np.stack([est[n] for n in common]), np.stack([ref[n] for n in common]))
    pairs = [
        _angle((est[a][:3, :3].T @ est[b][:3, :3]).T @ (ref[a][:3, :3].T @ ref[b][:3, :3]))
        for a, b in itertools.combinations(common, 2)
    ]
    return {
        "common": len(common),
        "reference": len(ref),
        "rotation_deg": [round(err.median_rotation_deg, 3), round(float(err.rotation_deg.max()), 3)],
        "within_1deg": int((err.rotation_deg <= 1.0).sum()),
        "pairwise_deg": [round(float(np.median(pairs)), 3), round(float(np.max(pairs)), 3)],
    }
