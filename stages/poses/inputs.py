"""What the poses stage's attempts start from: the images in the build folder (upright copies of the photos with
their EXIF focal prior, or a video's sharpest frames), their screening, COLMAP's masks, the camera groups and the
SIFT working size of the first attempt; and the zoom warning read from the EXIF focal prior."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.masks import match_masks, read_mask, write_binary_mask
from nerfpipe.stages.poses import colmap as sfm
from nerfpipe.stages.poses.budget import cap_working_size
from nerfpipe.stages.poses.exif import ZOOM_SPREAD, exif_focal
from nerfpipe.stages.poses.images import blurriest, list_images, near_duplicates, screen_image, write_upright
from nerfpipe.stages.poses.report import MIN_REGISTERED, RunState
from nerfpipe.stages.poses.video import extract_frames

if TYPE_CHECKING:
    from nerfpipe.stages.poses.config import Config

__all__ = ["prepare_photos", "prepare_video", "screen", "camera_groups", "write_masks", "working_size", "warn_zoom"]


def prepare_photos(folder: Path, images: Path, state: RunState) -> None:
    entries = [p for p in folder.iterdir() if not p.name.startswith(".")]
    if not entries:
        raise UserError(f"input folder {folder} is empty; put the photos (.jpg, .png, ...) directly in it")
    files = list_images(folder)
    if not files:
        raise UserError(f"no image files (.jpg .png .tif .bmp .webp) directly in {folder}")
    taken: set[str] = set()
    for src in files:
        try:
            name, grey = write_upright(src, images, taken)
        except Exception as e:  # PIL raises many types for bad files; skip the file, say why
            state.skipped[src.name] = f"undecodable: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
            continue
        state.names[name] = str(src)
        state.screens[name] = screen_image(grey)
        prior = exif_focal(src)  # the original's EXIF: a copy converted to PNG has none
        if prior is not None:
            state.exif_focal[name] = prior
    if state.skipped:
        state.warnings.append(f"skipped {len(state.skipped)} undecodable file(s): {', '.join(state.skipped)}")


def prepare_video(video: Path, images: Path, target: int, state: RunState) -> None:
    frames = extract_frames(video, images, target)
    for name, index in zip(frames.names, frames.source_index, strict=True):
        state.names[name] = f"{video}#frame={index}"
        state.screens[name] = screen_image(_grey_thumb(images / name))
    state.video = {
        "frames_decoded": frames.total_frames,
        "frames_kept": len(frames.names),
        "fps": frames.fps,
        "size": list(frames.size),
        "source_index": dict(zip(frames.names, frames.source_index, strict=True)),
    }


def _grey_thumb(path: Path) -> np.ndarray:
    from PIL import Image

    from nerfpipe.stages.poses.images import SCREEN_SIZE

    with Image.open(path) as im:
        grey = im.convert("L")
        grey.thumbnail((SCREEN_SIZE, SCREEN_SIZE), Image.Resampling.BILINEAR)
        return np.asarray(grey)


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def screen(config: Config, images: Path, state: RunState) -> list[str]:
    """Screening in the report; drop the blurriest; return the names to reconstruct."""
    names = list(state.names)
    if len(names) < MIN_REGISTERED:
        raise UserError(
            f"only {len(names)} readable image(s) in {config.input}; need at least {MIN_REGISTERED} "
            "overlapping photos (20+ recommended)"
        )
    screens = [state.screens[n] for n in names]
    state.duplicates = near_duplicates(names, screens)
    dropped = blurriest(names, screens, config.drop_blurry)
    if len(names) - len(dropped) < MIN_REGISTERED:
        raise UserError(
            f"drop_blurry={config.drop_blurry} would leave {len(names) - len(dropped)} of {len(names)} images; "
            f"at least {MIN_REGISTERED} must remain"
        )
    for n in dropped:
        state.skipped[n] = f"dropped as blurry (drop_blurry={config.drop_blurry}, blur {state.screens[n].blur:.1f})"
        (images / n).unlink()
    keep = [n for n in names if n not in set(dropped)]
    for n in keep:
        state.sizes[n] = _image_size(images / n)
    return keep


def warn_zoom(state: RunState) -> None:
    """A warning per camera whose photos' EXIF focal lengths differ (a zoom moved): one focal cannot fit all."""
    for camera_id, info in state.focal_prior.items():
        if info.get("spread", 0.0) > ZOOM_SPREAD:
            state.warnings.append(
                f"the photos sharing camera {camera_id} have EXIF focal lengths up to {info['spread']:.0%} apart "
                "(a zoom lens moved?): one shared focal length cannot fit them all; try single_camera=False"
            )


def write_masks(mask_dir: Path, names: list[str], out: Path, state: RunState) -> None:
    """COLMAP's masks for the copies `names` (out/<copy name>.png, binary), from the user's folder, where each
    is found by its original photo's name; UserError naming the file when one is missing or of another size."""
    originals = {n: Path(state.names[n]).name for n in names}
    found = match_masks(mask_dir, originals.values())
    out.mkdir(parents=True, exist_ok=True)
    for n in names:
        src = found[originals[n]]
        write_binary_mask(read_mask(src, state.sizes[n], image=originals[n]), out / f"{n}.png")
        state.masks[n] = str(src)


def camera_groups(config: Config, names: list[str], state: RunState) -> list[list[str]]:
    if not config.single_camera:
        return [names]
    by_size: dict[tuple[int, int], list[str]] = {}
    for n in names:
        by_size.setdefault(state.sizes[n], []).append(n)
    if len(by_size) > 1:
        sizes = ", ".join(f"{w}x{h} ({len(v)})" for (w, h), v in by_size.items())
        state.warnings.append(f"images have {len(by_size)} different sizes ({sizes}): one shared camera per size")
    return list(by_size.values())


def working_size(
    config: Config,
    settings: sfm.SfmSettings,
    probe_db: Path,
    images: Path,
    names: list[str],
    long_side: int,
    state: RunState,
    budget: float,
) -> sfm.SfmSettings:
    """`settings` with the first attempt's SIFT working size: the Config's, or `sfm.choose_working_size`'s, capped
    by the time budget (`budget.cap_working_size`: the probe's extraction is timed)."""
    if config.max_image_size is not None:
        state.working_size = {"size": min(config.max_image_size, long_side), "rule": "max_image_size"}
        return replace(settings, max_image_size=config.max_image_size)
    timed: dict[int, float] = {}

    def median_features_at(size: int) -> float:
        t0 = time.perf_counter()
        median = sfm.count_features(probe_db, images, names, size, settings, long_side, probe_db.parent / "working")
        timed[size] = (time.perf_counter() - t0) / min(sfm.PROBE_IMAGES, len(names))
        return median

    size, counted = sfm.choose_working_size(long_side, median_features_at)
    capped, why = cap_working_size(size, timed, len(names), budget, long_side)
    state.working_size = {
        "size": capped,
        "rule": f"smallest of {list(sfm.WORKING_SIZES)} px (at most the photos' {long_side}) where the probe "
        f"photos' median SIFT features reach {sfm.ENOUGH_FEATURES}, unless extracting every photo there would take "
        "over a third of the time budget",
        "median_features": {str(k): v for k, v in counted.items()},
        "probe_seconds_per_photo": {str(k): round(v, 2) for k, v in timed.items()},
        **({"capped": why} if why else {}),
    }
    return replace(settings, max_image_size=capped)
