"""LLFF (`poses_bounds.npy` [N, 17] + `images/`) -> `Source`.

Each row is a 3x5 matrix (row-major) followed by the near/far z-depth bounds. Its first three columns are the
camera's axes in LLFF's [down, right, back] order, the fourth the camera centre, the fifth (height, width,
focal). As LLFF's own loader does, the OpenGL camera-to-world is [right, up, back, centre] =
[col1, -col0, col2, col3]. Images are the folder's JPG/jpg/png files in sorted order (LLFF's rule); when they
are smaller than (height, width) the focal length is scaled like LLFF's `factor` handling. An image may not be
a symlink leading out of its folder (`data.confine.inside`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfpipe.data.confine import inside
from nerfpipe.data.errors import UserError
from nerfpipe.data.importers import Source, SourceFrame, image_shape
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["load", "world_from_cam_from_llff"]

_EXTS = (".jpg", ".jpeg", ".png")


def world_from_cam_from_llff(poses_bounds: np.ndarray) -> np.ndarray:
    """[N, 17] -> [N, 4, 4] OpenGL camera-to-world."""
    m = poses_bounds[:, :15].reshape(-1, 3, 5)
    out = np.zeros((len(m), 4, 4))
    out[:, :3, 0] = m[:, :, 1]  # right
    out[:, :3, 1] = -m[:, :, 0]  # up = -down
    out[:, :3, 2] = m[:, :, 2]  # back
    out[:, :3, 3] = m[:, :, 3]
    out[:, 3, 3] = 1.0
    return out


def _image_dir(root: Path, images: Path | None) -> Path:
    """The image folder: `images` as given, else relative to the dataset (`--images images_8`, as LLFF names its
    downscaled copies); without it `images/`, else the largest of the `images_F/` copies the dataset ships
    (the NeRF data's fern ships images_4 and images_8 only)."""
    if images is not None:
        given = Path(images)
        for cand in (given, root / given):
            if cand.is_dir():
                return cand
        raise UserError(f"{given}: image folder not found (neither as given nor in {root})")
    if (root / "images").is_dir():
        return root / "images"
    copies = sorted((int(p.name[7:]), p) for p in root.glob("images_*") if p.is_dir() and p.name[7:].isdigit())
    if not copies:
        raise UserError(f"{root}: no images/ (nor images_F/) folder next to poses_bounds.npy")
    return copies[0][1]


def load(source: Path, *, images: Path | None = None) -> Source:
    root = source.parent if source.is_file() else source
    pb_path = root / "poses_bounds.npy"
    try:
        pb = np.load(pb_path, allow_pickle=False).astype(np.float64)
    except (OSError, ValueError) as e:
        raise UserError(f"{pb_path}: cannot read ({e})") from None
    if pb.ndim != 2 or pb.shape[1] != 17 or len(pb) == 0:
        raise UserError(f"{pb_path}: expected an [N, 17] array, got shape {pb.shape}")
    if not np.isfinite(pb).all():
        raise UserError(f"{pb_path}: contains NaN or infinity")
    image_dir = _image_dir(root, images)
    files = sorted(p for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in _EXTS)
    resolved = [inside(image_dir, p.name, "image", file=image_dir) for p in files]  # a symlink may not lead out
    if len(files) != len(pb):
        raise UserError(f"{image_dir}: {len(files)} images but {pb_path.name} has {len(pb)} poses")
    h0, w0, f0 = pb[0, :15].reshape(3, 5)[:, 4]
    h, w, channels = image_shape(resolved[0])
    if abs(w / w0 - h / h0) > 0.02 * w / w0:
        raise UserError(f"{files[0]}: image is {w}x{h} but {pb_path.name} says {w0:g}x{h0:g} (aspect differs)")
    factor = w / w0
    c2w = world_from_cam_from_llff(pb)
    frames = []
    for i, p in enumerate(files):
        f = float(pb[i, :15].reshape(3, 5)[2, 4]) * factor
        intr = Intrinsics(w=w, h=h, fx=f, fy=f, cx=w / 2, cy=h / 2)
        frames.append(SourceFrame(name=p.name, world_from_cam=c2w[i], intrinsics=intr, image=resolved[i]))
    return Source(
        kind="llff",
        frames=tuple(frames),
        has_alpha=channels == 4,
        up="cameras",
        scene_type="forward",
        depth_bounds=pb[:, 15:17].copy(),
        inputs=(pb_path,),
        used={"images": str(image_dir), "focal_factor": factor},
    )
