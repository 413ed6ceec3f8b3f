"""An existing nerfstudio / instant-ngp / nerfpipe `transforms.json` -> `Source`.

Validation is `data.transforms.read_scene`'s (errors name the file, frame and field). Frames whose image is
missing are skipped later by `convert` (counted in its manifest). When the file carries `applied_transform` /
`applied_scale` (it was itself converted from, e.g., COLMAP), `source_from_original` keeps that mapping so the
output's `applied_transform` maps all the way back to the original frame. An explicit `aabb` key is taken as
the region of interest. Poses keep the file's up axis (these files are z-up by convention).
Unknown top-level keys are carried over unchanged.
"""

from __future__ import annotations

import json
from pathlib import Path

from nerfpipe.data.importers import Source, SourceFrame, flat_name, image_shape
from nerfpipe.data.transforms import read_scene

__all__ = ["load"]


def _resolve(root: Path, rel: str) -> Path:
    p = root / rel
    return p if p.suffix or p.is_file() else p.with_name(p.name + ".png")


def load(source: Path) -> Source:
    path = source / "transforms.json" if source.is_dir() else source
    scene = read_scene(path)
    doc = json.loads(path.read_text(encoding="utf-8"))
    frames = []
    has_alpha = bool(doc["has_alpha"]) if "has_alpha" in doc else None
    for i, fr in enumerate(scene.frames):
        img = _resolve(scene.root, fr.file_path)
        if has_alpha is None and img.is_file():
            has_alpha = image_shape(img)[2] == 4
        frames.append(
            SourceFrame(
                name=flat_name(fr.file_path, img.suffix),
                world_from_cam=fr.world_from_cam,
                intrinsics=scene.frame_intrinsics(i),
                image=img,
                mask=scene.root / fr.mask_path if fr.mask_path else None,
                depth=scene.root / fr.depth_file_path if fr.depth_file_path else None,
            )  # fmt: skip
        )
    applied = "applied_transform" in doc or "applied_scale" in doc
    return Source(
        kind="transforms", frames=tuple(frames), splits=dict(scene.splits) or None, has_alpha=bool(has_alpha),
        up="keep", box=scene.aabb if "aabb" in doc else None,
        source_from_original=scene.scene_from_source() if applied else None,
        inputs=(path,), extra=dict(scene.extra),
        used={"file": str(path), "composed_applied_transform": applied},
    )  # fmt: skip
