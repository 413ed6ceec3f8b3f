"""An existing nerfstudio / instant-ngp / nerfpipe `transforms.json` -> `Source`.

Validation is `data.transforms.read_scene`'s (errors name the file, frame and field; every path stays inside
the file's folder). Frames whose image is missing are skipped later by `convert` (counted in its manifest). When
the file carries `applied_transform` / `applied_scale` (it was itself converted from, e.g., COLMAP),
`source_from_original` keeps that mapping so the output's `applied_transform` maps all the way back to the
original frame. An explicit `aabb` key is taken as the region of interest. Poses keep the file's up axis (these
files are z-up by convention). Unknown top-level keys are carried over unchanged, except those naming a file
in the source's folder (`data.transforms.PATH_KEYS`, nerfstudio's `ply_file_path`): they would name another
file, or none, in the output's.
"""

from __future__ import annotations

from pathlib import Path

from nerfpipe.data.confine import inside, read_json
from nerfpipe.data.importers import Source, SourceFrame, flat_name, image_shape
from nerfpipe.data.transforms import PATH_KEYS, read_scene

__all__ = ["load"]

_NOT_CARRIED = (*PATH_KEYS, "ply_file_path")


def _resolve(root: Path, rel: str, what: str, file: Path) -> tuple[str, Path]:
    """The image `rel` names, `.png` added when the bare path does not exist: (that relative path, the file
    resolved inside `root`)."""
    p = root / rel
    rel = rel if p.suffix or p.is_file() else rel + ".png"
    return rel, inside(root, rel, what, file=file)


def load(source: Path) -> Source:
    path = source / "transforms.json" if source.is_dir() else source
    scene = read_scene(path)
    doc = read_json(path)
    root = scene.root
    frames = []
    has_alpha = bool(doc["has_alpha"]) if "has_alpha" in doc else None
    for i, fr in enumerate(scene.frames):
        rel, img = _resolve(root, fr.file_path, f"frames[{i}].file_path", path)
        if has_alpha is None and img.is_file():
            has_alpha = image_shape(img)[2] == 4
        frames.append(
            SourceFrame(
                name=flat_name(fr.file_path, Path(rel).suffix),
                world_from_cam=fr.world_from_cam,
                intrinsics=scene.frame_intrinsics(i),
                image=img,
                mask=inside(root, fr.mask_path, f"frames[{i}].mask_path", file=path) if fr.mask_path else None,
                depth=inside(root, fr.depth_file_path, f"frames[{i}].depth_file_path", file=path)
                if fr.depth_file_path
                else None,
            )
        )
    applied = "applied_transform" in doc or "applied_scale" in doc
    extra = {k: v for k, v in scene.extra.items() if k not in _NOT_CARRIED}
    left_out = {k: f"{scene.extra[k]!r}: names a file in the source's folder" for k in scene.extra if k not in extra}
    return Source(
        kind="transforms",
        frames=tuple(frames),
        splits=dict(scene.splits) or None,
        has_alpha=bool(has_alpha),
        up="keep",
        box=scene.aabb if "aabb" in doc else None,
        source_from_original=scene.scene_from_source() if applied else None,
        inputs=(path,),
        extra=extra,
        left_out=left_out,
        used={"file": str(path), "composed_applied_transform": applied},
    )
