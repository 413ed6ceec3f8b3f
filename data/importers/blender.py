"""NeRF Blender layout (`transforms_{train,val,test}.json`, `camera_angle_x`, RGBA PNGs) -> `Source`.

Poses are already OpenGL camera-to-world in Blender's z-up world, so the up axis is kept. `file_path` is
written without extension (`./train/r_0`): `.png` is added when the bare path does not exist. Splits come from
the files. The layout states no scene bounds, so no box is returned: `radiance.normalize` takes the region of
interest from the cameras (its `look_at` rule), which follows the scene at any scale (the NeRF synthetic
scenes, cameras ~4 units away, get about [-1.45, 1.45]^3; the same scene 10x smaller, cameras included, gets
a box 10x smaller). A fixed box would leave a small object a few voxels wide.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nerfpipe.data.confine import inside, read_json
from nerfpipe.data.errors import UserError
from nerfpipe.data.importers import Source, SourceFrame, flat_name, image_shape
from nerfpipe.data.transforms import rotation_problem
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["load"]


def _resolve(root: Path, rel: str, what: str, file: Path) -> tuple[str, Path]:
    """The image `rel` names, `.png` added when the bare path does not exist: (that relative path, the file
    resolved inside `root`)."""
    p = root / rel
    rel = rel if p.suffix or p.is_file() else rel + ".png"
    return rel, inside(root, rel, what, file=file)


def _matrix(value, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: expected a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise UserError(f"{where}: expected a 4x4 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise UserError(f"{where}: contains NaN or infinity")
    problem = rotation_problem(m)
    if problem is not None:
        raise UserError(f"{where}: {problem}")
    return m


def load(source: Path) -> Source:
    root = source.parent if source.is_file() else source
    files = {s: root / f"transforms_{s}.json" for s in ("train", "val", "test")}
    files = {s: f for s, f in files.items() if f.is_file()}
    if not files:
        raise UserError(f"{root}: no transforms_{{train,val,test}}.json")
    frames, splits = [], {}
    first_shape = None
    for split, path in files.items():
        doc = read_json(path)
        ang = doc.get("camera_angle_x") if isinstance(doc, dict) else None
        if isinstance(ang, bool) or not isinstance(ang, int | float) or not (0 < ang < math.pi):
            raise UserError(f"{path}: camera_angle_x: missing or not an angle in (0, pi) radians, got {ang!r}")
        raw = doc.get("frames")
        if not isinstance(raw, list) or not raw:
            raise UserError(f"{path}: frames: missing or empty")
        start = len(frames)
        for i, fr in enumerate(raw):
            fp = fr.get("file_path") if isinstance(fr, dict) else None
            if not isinstance(fp, str) or not fp:
                raise UserError(f"{path}: frames[{i}].file_path: missing or not a string")
            if "transform_matrix" not in fr:
                raise UserError(f"{path}: frames[{i}].transform_matrix: missing")
            m = _matrix(fr["transform_matrix"], f"{path}: frames[{i}].transform_matrix")
            rel, img = _resolve(root, fp, f"frames[{i}].file_path", path)
            if first_shape is None and img.is_file():
                first_shape = image_shape(img)
            frames.append((flat_name(fp, Path(rel).suffix), m, float(ang), img))
        splits[split] = tuple(range(start, len(frames)))
    if first_shape is None:
        raise UserError(f"{root}: none of the images listed in {', '.join(f.name for f in files.values())} exist")
    h, w, channels = first_shape
    out = []
    for name, m, ang, img in frames:
        f = 0.5 * w / math.tan(0.5 * ang)
        intr = Intrinsics(w=w, h=h, fx=f, fy=f, cx=w / 2, cy=h / 2)
        out.append(SourceFrame(name=name, world_from_cam=m, intrinsics=intr, image=img))
    return Source(
        kind="blender",
        frames=tuple(out),
        splits=splits,
        has_alpha=channels == 4,
        up="keep",
        scene_type="object",
        inputs=tuple(files.values()),
        used={"splits": {s: len(i) for s, i in splits.items()}},
    )
