"""Stage `convert`: a posed source (COLMAP, NeRF Blender, LLFF, tiny-NeRF npz, transforms.json) -> SCENE_DIR.

Writes, in this order:
- `images/<name>` (copied byte for byte; npz arrays encoded as PNG) and `images_<F>/<name>` downscaled by
  F (cv2.INTER_AREA, same name and format, size `Intrinsics.scaled(1 / F)`) for each F in `downscales` whose
  result keeps at least `min_downscaled_size` pixels on the short side;
- `masks/<image stem>.<suffix>` when the source has masks (a transforms.json's `mask_path`, COLMAP's
  `masks/<image name>.png` beside its images, which `poses --masks` writes), each checked to decode at its
  image's size, copied byte for byte, named by `frames[].mask_path` (white = keep; `data.masks`);
- `sparse_points.ply` (COLMAP sources): the sparse points with colours **in the scene frame**; it is named by
  the top-level key `sparse_points_path`, not nerfstudio's `ply_file_path` (which nerfstudio reads as being in
  the source frame);
- `transforms.json` (atomic, `data.transforms.write_scene`): OpenGL camera-to-world in the scene frame,
  intrinsics with their distortion kept (rays are undistorted, images are not resampled), `applied_transform`
  + `applied_scale` (source -> scene, see `radiance.normalize` for how they are chosen), `aabb`, `near`, `far`,
  `has_alpha`, `train/val/test_filenames`, and `scene_type` ('object', 'forward' or '360');
- `convert_manifest.json` last; `used.roi` / `used.roi_from` say where the box came from (`--aabb`, a box the
  source states, or the data by `radiance.normalize`'s rule) and `used.aabb_source_frame` gives it back in
  source units.

Splits: the dataset's own where it has them (Blender files, the tiny-NeRF npz convention, a transforms.json's
`*_filenames`), else every `holdout_every`-th frame (indices 0, 8, 16, ... as in LLFF's `llffhold`) is test;
val = test when the source has no val. Frames whose image file is missing are skipped and counted.

Untrusted sources: every path a source names stays inside its folder (`data.confine`, in the importers); each
image is read once (`data.images.read_image_file`: size checked from its header before decoding, truncated
files refused) and the bytes that decoded are the bytes written to images/. SCENE_DIR's lock (`data.lock`) is
held while convert runs: a second writer into the folder is refused.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.importers import Source, SourceFrame, load_source
from nerfpipe.data.lock import folder_lock
from nerfpipe.data.rundir import config_to_json, write_manifest
from nerfpipe.data.sparse_depth import FILE as SPARSE_FILE
from nerfpipe.data.sparse_depth import KEY as SPARSE_KEY
from nerfpipe.data.sparse_depth import write_sparse_depth
from nerfpipe.data.transforms import Frame, Scene, cameras_face_forward, read_scene, write_scene
from nerfpipe.radiance.normalize import Normalization, normalize
from nerfpipe.stages.convert.files import check_names, copy_aux, copy_mask, mask_names, write_image, write_ply

__all__ = ["Config", "Outputs", "run", "holdout_splits"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Config:
    source: Path
    """COLMAP folder/model, Blender folder, LLFF folder, .npz file, or a transforms.json (or its folder)."""
    scene_dir: Path
    """Output folder: transforms.json, images/, images_F/, sparse_points.ply, convert_manifest.json."""
    kind: Literal["auto", "colmap", "blender", "llff", "npz", "transforms"] = "auto"
    """Source kind; 'auto' looks at the files (Blender, LLFF, COLMAP, then transforms.json)."""
    images: Path | None = None
    """Image folder for COLMAP / LLFF sources (default: found next to the model / images/)."""
    downscales: tuple[int, ...] = (2, 4, 8)
    """Factors F for the downscaled copies images_F/."""
    min_downscaled_size: int = 32
    """Make images_F only if the short image side divided by F is at least this many pixels."""
    holdout_every: int = 8
    """Without the dataset's own split, every N-th frame (0, N, 2N, ...) is test; 0 = no test frames."""
    up: Literal["auto", "keep", "cameras"] = "auto"
    """Up axis: 'keep' the source's z, 'cameras' = mean camera up; 'auto': keep for Blender/npz/transforms."""
    normalize: bool = True
    """Re-centre and scale into [-1, 1]^3; False keeps the source frame (identity transform, scale 1)."""
    roi_percentile: float = 1.0
    """Sparse points outside the [p, 100 - p] percentile range per axis are left out of the region of interest."""
    roi_margin: float = 0.1
    """Padding of the points' box on each side, as a fraction of its longest half side."""
    aabb: tuple[float, float, float, float, float, float] | None = None
    """x0,y0,z0,x1,y1,z1 in the source frame and units: the scene box, replacing the one derived from the data
    (and any the source states). For a transforms.json source: that file's frame."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    transforms: Path
    """SCENE_DIR/transforms.json."""
    manifest: Path
    """SCENE_DIR/convert_manifest.json."""
    kind: str
    """The source kind read."""
    num_frames: int
    """Frames written."""
    splits: dict[str, int]
    """Frames per split."""
    downscales: tuple[int, ...]
    """The images_F folders made."""
    applied_transform: np.ndarray
    """[3, 4] source -> scene (before the scale)."""
    applied_scale: float
    """Source -> scene scale."""


def holdout_splits(n: int, every: int) -> dict[str, tuple[int, ...]]:
    """Every `every`-th index (0, every, ...) is test; all frames train when n < 2 or every <= 0."""
    if every <= 0 or n < 2:
        return {"train": tuple(range(n)), "test": ()}
    test = tuple(range(0, n, every))
    return {"train": tuple(i for i in range(n) if i % every), "test": test}


def _existing(source: Source) -> tuple[list[int], dict[str, tuple[int, ...]] | None]:
    """Indices of the frames whose image exists, and the splits remapped to them."""
    keep = [i for i, f in enumerate(source.frames) if f.image is None or f.image.is_file()]
    new_index = {old: new for new, old in enumerate(keep)}
    splits = None
    if source.splits is not None:
        splits = {s: tuple(new_index[i] for i in idx if i in new_index) for s, idx in source.splits.items()}
    return keep, splits


def _scene_type(source: Source, frames: list[SourceFrame]) -> str:
    """The importer's, else 'forward' when every camera looks within 45 degrees of the mean view, else '360'."""
    if source.scene_type is not None:
        return source.scene_type
    return "forward" if cameras_face_forward(np.stack([f.world_from_cam for f in frames])) else "360"


def _compose(norm: Normalization, source_from_original: np.ndarray | None) -> tuple[np.ndarray, float]:
    """applied_transform [3, 4] and scale of scene <- original (through the source file's own mapping)."""
    if source_from_original is None:
        return norm.applied_transform, norm.applied_scale
    total = norm.scene_from_source() @ source_from_original
    scale = float(np.cbrt(np.linalg.det(total[:3, :3])))
    return total[:3] / scale, scale


def _given_box(aabb) -> np.ndarray | None:
    """`--aabb` as [2, 3] (None when not given); UserError unless finite with x0 < x1, y0 < y1, z0 < z1."""
    if aabb is None:
        return None
    box = np.asarray(aabb, dtype=np.float64)
    if box.shape != (6,) or not np.isfinite(box).all() or not (box[3:] > box[:3]).all():
        raise UserError(f"--aabb: expected x0,y0,z0,x1,y1,z1 (finite, x0 < x1, y0 < y1, z0 < z1), got {aabb!r}")
    return box.reshape(2, 3)


def _source_box(norm: Normalization, scene_from_source: np.ndarray) -> list[list[float]]:
    """The axis-aligned box round `aabb`'s corners mapped back to the source frame (a rotated `up` tilts it)."""
    lo, hi = norm.aabb
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    src = (corners - scene_from_source[:3, 3]) @ np.linalg.inv(scene_from_source[:3, :3]).T
    return [src.min(0).tolist(), src.max(0).tolist()]


def run(config: Config) -> Outputs:
    """Source -> SCENE_DIR (module docstring), holding SCENE_DIR's lock; a SCENE_DIR this call created is removed
    again when it fails leaving it empty."""
    scene_dir = Path(config.scene_dir)
    created = not scene_dir.exists()
    try:
        with folder_lock(scene_dir):
            return _run(config, scene_dir)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                scene_dir.rmdir()  # only when empty
        raise


def _run(config: Config, scene_dir: Path) -> Outputs:
    started = time.time()
    given = _given_box(config.aabb)
    source = load_source(Path(config.source), config.kind, images=config.images)
    for inp in source.inputs:
        if inp.resolve() == (scene_dir / "transforms.json").resolve():
            raise UserError(f"{inp}: the source is the output itself; choose another --scene-dir")
    keep, splits = _existing(source)
    frames, missing = [source.frames[i] for i in keep], len(source.frames) - len(keep)
    if not frames:
        raise UserError(f"{config.source}: none of the {len(source.frames)} images listed exist")
    if missing:
        log.warning("convert: skipped %d of %d frames whose image is missing", missing, len(source.frames))
    check_names(config.source, [f.name for f in frames])

    left_out = dict(source.left_out)
    if given is not None:  # the region of interest: --aabb, else the source's stated box, else the data's
        box, roi_from = given, f"--aabb {given.tolist()} (given, source frame)"
        if source.box is not None:
            left_out["source aabb"] = f"{np.asarray(source.box).tolist()} (stated by the source): replaced by --aabb"
    elif source.box is not None:
        box, roi_from = source.box, "the aabb the source states"
    else:
        box, roi_from = None, "the data: sparse points, stated depth bounds or the cameras (radiance.normalize)"
    up = config.up if config.up != "auto" else source.up
    norm = normalize(
        np.stack([f.world_from_cam for f in frames]),
        [f.intrinsics for f in frames],
        up=up,
        points=source.points,
        box=box,  # type: ignore[arg-type]
        depth_bounds=source.depth_bounds[keep] if source.depth_bounds is not None else None,
        percentile=config.roi_percentile,
        margin=config.roi_margin,
        rescale=config.normalize,
    )
    scene_from_source = norm.scene_from_source()
    applied, scale = _compose(norm, source.source_from_original)

    if splits is None:
        splits = holdout_splits(len(frames), config.holdout_every)
    if "val" not in splits:
        splits["val"] = splits.get("test", ())
    splits = {s: splits[s] for s in ("train", "val", "test") if s in splits}

    short = min(min(f.intrinsics.w, f.intrinsics.h) for f in frames)
    factors = sorted(f for f in set(config.downscales) if f > 1 and short / f >= config.min_downscaled_size)
    px = source.pixels

    masks = mask_names(frames)

    def write_one(i: int) -> None:
        write_image(frames[i], px(i) if px is not None else None, scene_dir, factors)
        if masks[i] is not None:
            copy_mask(frames[i], scene_dir / "masks" / masks[i])

    with ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1))) as pool:
        list(pool.map(write_one, range(len(frames))))

    intrs = [f.intrinsics for f in frames]
    shared = intrs[0] if all(i == intrs[0] for i in intrs) else None
    out_frames = []
    for f, mask_name in zip(frames, masks, strict=True):
        world_from_cam = scene_from_source @ f.world_from_cam
        world_from_cam[:3, :3] /= norm.applied_scale  # rotation stays orthonormal; the scale moves the centre only
        out_frames.append(
            Frame(
                file_path=f"images/{f.name}",
                world_from_cam=world_from_cam,
                intrinsics=None if shared is not None else f.intrinsics,
                mask_path=f"masks/{mask_name}" if mask_name is not None else None,
                depth_file_path=copy_aux(f.depth, scene_dir / "depths", f.name),
            )
        )

    extra = dict(source.extra)
    extra["scene_type"] = _scene_type(source, frames)
    outputs = [scene_dir / "images", *(scene_dir / f"images_{f}" for f in factors)]
    if source.points is not None and len(source.points):
        pts = source.points @ scene_from_source[:3, :3].T + scene_from_source[:3, 3]
        write_ply(scene_dir / "sparse_points.ply", pts, source.colors)
        extra["sparse_points_path"] = "sparse_points.ply"
        outputs.append(scene_dir / "sparse_points.ply")
        observed = {
            fr.file_path: f.point_ids for f, fr in zip(frames, out_frames, strict=True) if f.point_ids is not None
        }
        if observed:
            write_sparse_depth(scene_dir / SPARSE_FILE, pts, observed)
            extra[SPARSE_KEY] = SPARSE_FILE
            outputs.append(scene_dir / SPARSE_FILE)

    scene = Scene(
        root=scene_dir,
        frames=tuple(out_frames),
        intrinsics=shared,
        applied_transform=applied,
        applied_scale=scale,
        aabb=norm.aabb,
        near=norm.near,
        far=norm.far,
        splits=splits,
        has_alpha=source.has_alpha,
        extra=extra,
    )
    transforms = write_scene(scene, scene_dir / "transforms.json")
    read_scene(transforms)  # what we wrote must parse
    outputs.insert(0, transforms)

    masked = sum(m is not None for m in masks)
    if masked:
        outputs.append(scene_dir / "masks")
    if missing:
        left_out["missing images"] = f"{missing} of {len(source.frames)} frames skipped: image file not found"
    skipped = sorted(set(config.downscales) - set(factors))
    if skipped:
        left_out[f"images_{skipped}"] = f"short image side {short} px / F < {config.min_downscaled_size} px"
    manifest = write_manifest(
        scene_dir,
        name="convert_manifest.json",
        stage="convert",
        started=started,
        inputs=source.inputs,
        outputs=outputs,
        used={
            **source.used,
            "kind": source.kind,
            "up": norm.up_method,
            "roi": norm.roi_method,
            "roi_from": roi_from,
            "aabb_source_frame": _source_box(norm, scene_from_source),
            "scene_type": extra["scene_type"],
            "frames": len(frames),
            "downscales": factors,
            "masks": f"{masked} of {len(frames)} frames: masks/ (white = keep; masked-out pixels train as "
            "transparent, data.masks)"
            if masked
            else None,
        },
        left_out=left_out,
        config=config_to_json(config),
    )
    log.info("convert: %d frames from %s (%s) -> %s", len(frames), config.source, source.kind, transforms)
    return Outputs(
        transforms=transforms,
        manifest=manifest,
        kind=source.kind,
        num_frames=len(frames),
        splits={s: len(i) for s, i in splits.items()},
        downscales=tuple(factors),
        applied_transform=applied,
        applied_scale=scale,
    )
