"""tiny-NeRF `.npz` (`images` [N, H, W, 3|4], `poses` [N, 4, 4] OpenGL camera-to-world, `focal`) -> `Source`.

Optional `alpha` [N, H, W] makes RGBA images. Images are re-encoded as PNG by `convert`. Poses keep their z-up
world. Splits: with N == 106 the tiny_nerf convention (views 0..99 train, 100..105 test); otherwise none (the
hold-out rule applies). A folder holding exactly one .npz may be given instead of the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.importers import Source, SourceFrame
from nerfpipe.radiance.camera import Intrinsics

__all__ = ["load", "TINY_NERF_VIEWS"]

TINY_NERF_VIEWS = 106


def _to_uint8(images: np.ndarray) -> np.ndarray:
    if images.dtype == np.uint8:
        return images
    return np.round(np.clip(images.astype(np.float64), 0.0, 1.0) * 255).astype(np.uint8)


def load(source: Path) -> Source:
    if source.is_dir():
        found = sorted(source.glob("*.npz"))
        if len(found) != 1:
            raise UserError(f"{source}: expected exactly one .npz, found {len(found)}")
        source = found[0]
    try:
        data = np.load(source, allow_pickle=False)
        keys = set(data.files)
    except (OSError, ValueError) as e:
        raise UserError(f"{source}: cannot read as .npz ({e})") from None
    missing = [k for k in ("images", "poses", "focal") if k not in keys]
    if missing:
        raise UserError(f"{source}: missing {', '.join(missing)} (has {', '.join(sorted(keys))})")
    images, poses, focal = data["images"], data["poses"].astype(np.float64), np.asarray(data["focal"], np.float64)
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise UserError(f"{source}: images: expected [N, H, W, 3|4], got {images.shape}")
    n, h, w = images.shape[:3]
    if poses.shape not in ((n, 4, 4), (n, 3, 4)):
        raise UserError(f"{source}: poses: expected [{n}, 4, 4], got {poses.shape}")
    if poses.shape[1] == 3:
        poses = np.concatenate([poses, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (n, 1, 1))], axis=1)
    if not np.isfinite(poses).all() or not np.isfinite(focal).all() or (focal <= 0).any():
        raise UserError(f"{source}: poses or focal contain NaN, infinity or a non-positive focal")
    if focal.size not in (1, n):
        raise UserError(f"{source}: focal: expected a scalar or [{n}], got shape {focal.shape}")
    focals = np.broadcast_to(focal.reshape(-1), (n,))
    pixels = _to_uint8(images)
    if "alpha" in keys:
        alpha = data["alpha"]
        if alpha.shape != (n, h, w):
            raise UserError(f"{source}: alpha: expected [{n}, {h}, {w}], got {alpha.shape}")
        pixels = np.concatenate([pixels[..., :3], _to_uint8(alpha)[..., None]], axis=-1)
    digits = len(str(n - 1))
    frames = tuple(
        SourceFrame(
            name=f"{i:0{digits}d}.png",
            world_from_cam=poses[i],
            intrinsics=Intrinsics(w=w, h=h, fx=float(focals[i]), fy=float(focals[i]), cx=w / 2, cy=h / 2),
        )
        for i in range(n)
    )
    splits = None
    if n == TINY_NERF_VIEWS:
        splits = {"train": tuple(range(100)), "test": tuple(range(100, n))}
    return Source(
        kind="npz",
        frames=frames,
        splits=splits,
        has_alpha=pixels.shape[-1] == 4,
        up="keep",
        scene_type="object",
        pixels=lambda i: pixels[i],
        inputs=(source,),
        used={"keys": sorted(keys), "split": "tiny_nerf 0-99 train / 100-105 test" if splits else "hold-out"},
    )
