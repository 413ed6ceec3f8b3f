"""Stage `poses`: a folder of photos or a video -> a COLMAP sparse model, in-process with pycolmap.

Steps: upright copies of the photos (EXIF orientation applied; COLMAP ignores it) and each photo's EXIF focal
length, or the sharpest frame per window of a video -> screening (blur, exposure, near-duplicates;
`drop_blurry` removes the blurriest) -> the SIFT working size (`max_image_size`, or the smallest of 1000 / 1600
/ 3200 px where SIFT finds enough features) -> SIFT, the cameras given the EXIF focal prior (`exif`) ->
exhaustive or sequential matching -> incremental mapping -> the LARGEST model (most registered images), never
blindly model 0 -> its cameras and structure checked (`quality`: focal against EXIF or a plausible field of
view, distortion, principal point, reprojection error, track length) -> under 80 % registered or a camera
check failed, retries with pycolmap's size and feature cap, then a relaxed mapper, then guided matching,
within a time budget (`attempts`, `choice`), keeping the attempt that registered most among those whose
cameras pass the checks (a failing one only when all fail, marked suspect) -> with a shared camera, one last
bundle adjustment that also refines the principal point -> the written model's checks: `check` ("ok" |
"suspect") and `checks` in poses_report.json and colmap/manifest.json, a warning line per failed check.

Outputs (COLMAP conventions: OpenCV camera axes, `cam_from_world` poses, binary model):
  SCENE_DIR/colmap/images/          upright copies / video frames: the image folder of the model
  SCENE_DIR/colmap/masks/           with --masks: COLMAP's masks, <image name>.png, 0 / 255 (black: no features);
                                    `convert` finds them there and carries them to training
  SCENE_DIR/colmap/names.json       {copy name: original path} (video frames: {name: "video.mp4#frame=N"})
  SCENE_DIR/colmap/database.db      features and matches of the attempt kept
  SCENE_DIR/colmap/sparse/          the chosen model (cameras.bin, images.bin, points3D.bin, ...)
  SCENE_DIR/colmap/metrics.csv      step, seconds, phase ("mapping (attempt 2)" when retrying), images,
                                    registered
  SCENE_DIR/colmap/manifest.json    provenance (also the working size and the attempts); the folder is built
                                    under a temporary name and renamed into place complete, so colmap/
                                    exists only after a success
  SCENE_DIR/poses_report.json       also on failure (status "failed" and the error): counts, per-image
                                    features / matches / observations / screening / EXIF focal, why images
                                    were left out, the focal prior ("absent" when no EXIF gives one), how the
                                    working size was chosen, each attempt's settings, result and checks, the
                                    `choice` (why the kept attempt won), why the ladder stopped, and the
                                    written model's `check` / `checks` (`status` stays "ok" | "failed")

A rerun first moves an earlier colmap/ (with its poses_report.json inside) to SCENE_DIR/colmap.previous/: a
failed rerun leaves no colmap/ that looks current, yet loses nothing (the error says where the old model is);
a successful one deletes colmap.previous/.

Static camera: a turntable (the object turns, the camera and background stay) gives matches that stay at the
same pixel in every view. After the first attempt's matching, over 30 % of the verified matches doing so stops
the stage with a one-line error that asks for --masks (the mapper would otherwise fail, after every retry, or
model the background); a model whose registered cameras all sit at one place is refused the same way
(`report.check_static_matches`, `report.check_static_cameras`). With --masks the background has no features.

Modules: `images` (upright copies, screening), `exif` (the EXIF focal prior, given to COLMAP's cameras), `video`
(frame picking), `colmap` (the pycolmap steps, the working size and the principal-point refinement), `attempts`
(the retry ladder), `quality` (the checks of a model), `choice` (which attempt to keep, when to stop), `report`
(run state, registration checks, poses_report.json, phase timer).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import pycolmap
from rich.console import Console
from rich.progress import Progress

from data.atomic import write_json
from data.checks import verdict
from data.errors import UserError
from data.masks import match_masks, read_mask, write_binary_mask
from data.rundir import MetricsLog, config_to_json, write_manifest
from stages.poses import colmap as sfm
from stages.poses import quality
from stages.poses.attempts import ladder, prior_focals, run_attempts
from stages.poses.exif import ZOOM_SPREAD, exif_focal
from stages.poses.images import (
    IMAGE_SUFFIXES,
    blurriest,
    list_images,
    near_duplicates,
    screen_image,
    write_upright,
)
from stages.poses.report import (
    FAIL_FRACTION,
    MIN_REGISTERED,
    WARN_FRACTION,
    PhaseTimer,
    RunState,
    build_report,
    check_features,
    check_registered,
    check_static_cameras,
    check_static_matches,
    print_summary,
)
from stages.poses.video import extract_frames

__all__ = ["Config", "Outputs", "run", "MIN_REGISTERED", "FAIL_FRACTION", "WARN_FRACTION"]

VERSION = "2"
CameraModel = Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE"]
CAMERA_MODELS = get_args(CameraModel)
"""The models `convert` (data.importers.colmap) reads."""


@dataclass(frozen=True, kw_only=True)
class Config:
    """Where the stage departs from pycolmap's defaults (pycolmap 4.x), and why:

    - SIFT working size: pycolmap downscales to 3200 px. Here the smallest of 1000 / 1600 / 3200 px (never
      above the photos' size) at which SIFT finds ENOUGH_FEATURES (1000) per image on probe photos; with too
      few registered, the first retry uses 3200. fox (50 photos, 1080x1920, 2 cores, 2048-feature cap):
      1000 px: 50/50 registered, 0.20 deg median rotation error, 65-75 CPU-s (~35-45 s wall); 1280 px:
      0.23 deg, 95 CPU-s; 1600 px: 0.20 deg, 137 CPU-s; 1920 (its full size, what 3200 gives): 0.22 deg,
      136 CPU-s. More pixels buy fox no accuracy and break its 60 s budget: matching and mapping time
      follow the number of features, which grows with the working size.
    - first_octave: pycolmap -1 (SIFT upsamples 2x). Here 0 at working sizes >= 1000 px (~3x faster; under
      a feature cap the upsampled octave is the finest and is dropped first anyway) and -2 with affine
      shape under 500 px (colmap.TINY_IMAGE).
    - min_model_size: pycolmap 10, here 3 (colmap.MIN_MODEL_SIZE): small separate models are reported.
    - Random seeds (RANSAC, mapper) are set from `seed`, so runs repeat.
    - Retries (`max_attempts`): pycolmap has none; see stages.poses.attempts.
    - Focal prior: pycolmap reads it from the EXIF of the file it extracts, which a photo converted to PNG
      (TIFF, BMP, WebP) has lost; here each original photo's EXIF prior is written into the cameras before
      matching (stages.poses.exif), and every model's cameras are checked against it (stages.poses.quality).
    Feature cap, matcher and verification options, and mapper thresholds are pycolmap's in the first two
    attempts; bundle adjustment options are pycolmap's throughout.
    """

    input: Path
    """A folder of photos (.jpg .png .tif .bmp .webp; not recursive) or a video file."""
    scene_dir: Path
    """Output folder: colmap/ (images, database.db, sparse/), poses_report.json."""
    max_image_size: int | None = None
    """SIFT working size, the long side in pixels that images are downscaled to; unset: the smallest of 1000,
    1600 and 3200 px (pycolmap's size) at which SIFT finds 1000 features per image on 3 probe photos. The
    model keeps full-resolution intrinsics."""
    max_num_features: int = sfm.PYCOLMAP_MAX_NUM_FEATURES
    """SIFT features kept per image, the coarsest scales first (pycolmap's 8192; matching time grows with its
    square; fox at 1000 px finds 942-1812, so the cap only binds on larger working sizes)."""
    max_attempts: int = 4
    """Settings to try while under 80 % of the images register or a camera check fails: 1 = no retry, 2 = also
    pycolmap's 3200 px and 8192 features, 3 = also relaxed mapper thresholds, 4 = also guided matching (see
    stages.poses.attempts; a time budget may stop it earlier once a usable model exists)."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Image pairs to match: 'auto' = exhaustive for photo folders, sequential for video."""
    single_camera: bool = True
    """Images of the same size share one camera (one phone, one zoom). Mixed sizes get one camera per size
    (with a warning) instead of refusing. False: one camera per image."""
    camera_model: CameraModel = "SIMPLE_RADIAL"
    """COLMAP camera model, one `convert` reads: SIMPLE_RADIAL (f, k1; robust, COLMAP's default), RADIAL,
    OPENCV (fx fy k1 k2 p1 p2; for large sharp images: on small ones its extra parameters can derail the
    mapper), PINHOLE, SIMPLE_PINHOLE."""
    video_frames: int = 150
    """For a video: about this many frames, the sharpest of each equal window of the video."""
    drop_blurry: float = 0.0
    """Remove the blurriest images before matching: a fraction (< 1) or a count (>= 1) of the images."""
    sequential_overlap: int = 10
    """Sequential matcher: each image is matched with this many following ones (plus quadratic jumps)."""
    seed: int = 0
    """Seeds COLMAP's RANSAC and mapper (results still vary a little with num_threads > 1)."""
    num_threads: int = -1
    """CPU threads for COLMAP; -1 = all cores."""
    masks: Path | None = None
    """A folder with one mask per photo (found by the photo's name: IMG_1.jpg.png, IMG_1.png or IMG_1.jpg; the
    photo's size; white = keep, black = masked out). SIFT keeps no feature on black pixels, and `convert` carries
    the masks to training, where masked-out pixels are transparent (data.masks). Needed when the camera stood
    still and the object turned (a turntable): without masks the static background would dominate, which the
    stage detects and refuses."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    colmap_dir: Path
    """SCENE_DIR/colmap."""
    sparse: Path
    """SCENE_DIR/colmap/sparse: the chosen model."""
    images: Path
    """SCENE_DIR/colmap/images: the model's image folder."""
    database: Path
    report: Path
    """SCENE_DIR/poses_report.json."""
    registered: int
    total: int
    mean_reprojection_error: float
    working_size: int
    """SIFT working size of the first attempt (long side, px)."""
    attempts: tuple[str, ...]
    """One line per attempt: name, registered, settings; the kept one is marked."""
    check: str
    """"ok" or "suspect": the kept model's verdict (stages.poses.quality; the failed checks are in the report)."""


def _check(config: Config) -> str:
    """Validate the config and input; return the input kind ('photos' | 'video')."""
    if config.matcher not in ("auto", "exhaustive", "sequential"):
        raise UserError(f"matcher must be auto, exhaustive or sequential, got {config.matcher!r}")
    if config.camera_model not in CAMERA_MODELS:
        raise UserError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}; got {config.camera_model!r}")
    if config.drop_blurry < 0:
        raise UserError(f"drop_blurry must be a fraction in [0, 1) or a count >= 1, got {config.drop_blurry}")
    if (config.max_image_size is not None and config.max_image_size < 100) or config.max_num_features < 100:
        raise UserError("max_image_size and max_num_features must be at least 100")
    if config.max_attempts < 1:
        raise UserError(f"max_attempts must be at least 1, got {config.max_attempts}")
    src = Path(config.input)
    if not src.exists():
        raise UserError(f"input {src} does not exist (expected a folder of photos or a video file)")
    colmap_dir = Path(config.scene_dir).resolve() / "colmap"
    if src.resolve() == colmap_dir or colmap_dir in src.resolve().parents:
        raise UserError(f"input {src} is inside the output folder {colmap_dir}; copy the photos elsewhere")
    if config.masks is not None and not Path(config.masks).is_dir():
        raise UserError(f"masks {config.masks}: no such folder (expected one mask image per photo, white = keep)")
    if src.is_dir():
        return "photos"
    if config.masks is not None:
        raise UserError(f"masks are for a folder of photos, not a video ({src}); extract the frames first")
    if src.suffix.lower() in IMAGE_SUFFIXES:
        raise UserError(f"input {src} is a single image; give a folder of at least {MIN_REGISTERED} photos")
    return "video"


def _prepare_photos(folder: Path, images: Path, state: RunState) -> None:
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


def _prepare_video(video: Path, images: Path, target: int, state: RunState) -> None:
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

    from stages.poses.images import SCREEN_SIZE

    with Image.open(path) as im:
        grey = im.convert("L")
        grey.thumbnail((SCREEN_SIZE, SCREEN_SIZE), Image.Resampling.BILINEAR)
        return np.asarray(grey)


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def _screen(config: Config, images: Path, state: RunState) -> list[str]:
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


def _warn_zoom(state: RunState) -> None:
    """A warning per camera whose photos' EXIF focal lengths differ (a zoom moved): one focal cannot fit all."""
    for camera_id, info in state.focal_prior.items():
        if info.get("spread", 0.0) > ZOOM_SPREAD:
            state.warnings.append(
                f"the photos sharing camera {camera_id} have EXIF focal lengths up to {info['spread']:.0%} apart "
                "(a zoom lens moved?): one shared focal length cannot fit them all; try single_camera=False"
            )


def _write_masks(mask_dir: Path, names: list[str], out: Path, state: RunState) -> None:
    """COLMAP's masks for the copies `names` (out/<copy name>.png, binary), from the user's folder, where each
    is found by its original photo's name; UserError naming the file when one is missing or of another size."""
    originals = {n: Path(state.names[n]).name for n in names}
    found = match_masks(mask_dir, originals.values())
    out.mkdir(parents=True, exist_ok=True)
    for n in names:
        src = found[originals[n]]
        write_binary_mask(read_mask(src, state.sizes[n], image=originals[n]), out / f"{n}.png")
        state.masks[n] = str(src)


def _camera_groups(config: Config, names: list[str], state: RunState) -> list[list[str]]:
    if not config.single_camera:
        return [names]
    by_size: dict[tuple[int, int], list[str]] = {}
    for n in names:
        by_size.setdefault(state.sizes[n], []).append(n)
    if len(by_size) > 1:
        sizes = ", ".join(f"{w}x{h} ({len(v)})" for (w, h), v in by_size.items())
        state.warnings.append(f"images have {len(by_size)} different sizes ({sizes}): one shared camera per size")
    return list(by_size.values())


def _working_size(
    config: Config, settings: sfm.SfmSettings, probe_db: Path, images: Path, names: list[str], long_side: int,
    state: RunState,
) -> sfm.SfmSettings:  # fmt: skip
    """`settings` with the first attempt's SIFT working size: the Config's, or `sfm.choose_working_size`'s."""
    if config.max_image_size is not None:
        state.working_size = {"size": min(config.max_image_size, long_side), "rule": "max_image_size"}
        return replace(settings, max_image_size=config.max_image_size)
    size, counted = sfm.choose_working_size(
        long_side, lambda s: sfm.count_features(probe_db, images, names, s, settings)
    )
    state.working_size = {
        "size": size,
        "rule": f"smallest of {list(sfm.WORKING_SIZES)} px (at most the photos' {long_side}) where the probe "
        f"photos' median SIFT features reach {sfm.ENOUGH_FEATURES}",
        "median_features": {str(k): v for k, v in counted.items()},
    }
    return replace(settings, max_image_size=size)


def _set_aside(colmap_dir: Path, report_path: Path) -> Path | None:
    """Move an earlier run's colmap/ (and its report, into it) to colmap.previous/; returns that folder, or
    None when there was no earlier colmap/ (an older colmap.previous/ is then left as it is)."""
    previous = colmap_dir.with_name("colmap.previous")
    if not colmap_dir.exists():
        report_path.unlink(missing_ok=True)  # a failed run's report: this run writes its own
        return previous if previous.exists() else None
    shutil.rmtree(previous, ignore_errors=True)
    os.replace(colmap_dir, previous)
    if report_path.exists():
        os.replace(report_path, previous / report_path.name)
    return previous


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Photos or video -> SCENE_DIR/colmap (see the module docstring). UserError on bad input or a failed model."""
    kind = _check(config)
    pycolmap.logging.minloglevel = 1  # COLMAP's INFO lines would drown the summary; warnings and errors stay
    console = Console(stderr=True)
    scene_dir = Path(config.scene_dir)
    colmap_dir = scene_dir / "colmap"
    report_path = scene_dir / "poses_report.json"
    scene_dir.mkdir(parents=True, exist_ok=True)
    previous = _set_aside(colmap_dir, report_path)
    build = Path(tempfile.mkdtemp(prefix=".colmap.tmp-", dir=scene_dir))
    images = build / "images"
    images.mkdir()
    state = RunState(started=time.time())
    metrics = MetricsLog(build / "metrics.csv", ["step", "seconds", "phase", "images", "registered"])
    phase = PhaseTimer(state, metrics, progress)
    matcher = config.matcher if config.matcher != "auto" else ("sequential" if kind == "video" else "exhaustive")
    settings = sfm.SfmSettings(  # max_image_size: a placeholder until _working_size, after screening
        max_image_size=sfm.PYCOLMAP_MAX_IMAGE_SIZE, max_num_features=config.max_num_features,
        camera_model=config.camera_model, single_camera=config.single_camera, matcher=matcher,
        sequential_overlap=config.sequential_overlap, num_threads=config.num_threads, seed=config.seed,
    )  # fmt: skip
    pycolmap.set_random_seed(config.seed)
    try:
        with phase("images"):
            if kind == "photos":
                _prepare_photos(Path(config.input), images, state)
            else:
                _prepare_video(Path(config.input), images, config.video_frames, state)
        with phase("screening"):
            names = _screen(config, images, state)
            groups = _camera_groups(config, names, state)
        masked = config.masks is not None
        if masked:
            with phase("masks"):
                _write_masks(Path(config.masks), names, build / "masks", state)
            settings = replace(settings, mask_path=str(build / "masks"))
        long_sides = [max(max(state.sizes[n]) for n in g) for g in groups]
        with phase("working_size"):
            settings = _working_size(config, settings, build / "probe.db", images, names, max(long_sides), state)
        plan = ladder(settings, config.max_attempts, max(long_sides))
        run_attempts(plan, build, images, groups, long_sides, state, phase,
                     after_matching=lambda db: check_static_matches(db, masked, state))  # fmt: skip
        check_features(state.stats)
        check_registered(state, matcher)
        check_static_cameras(state.model, masked)
        _warn_zoom(state)
        if config.single_camera:
            with phase("principal_point"):
                state.model, state.principal_point = sfm.refine_principal_point(state.model, config.num_threads)
        state.checks = quality.model_checks(state.model, prior_focals(state.focal_prior), len(state.stats.features))
        (build / "sparse").mkdir()
        state.model.write_binary(str(build / "sparse"))
        shutil.rmtree(build / "models")
        report = build_report(config, state, "ok", None)
        write_json(build / "names.json", state.names)
        metrics.save()
        write_json(report_path, report)
        write_manifest(
            build, stage="poses", started=state.started, inputs=[config.input],
            outputs=["images/", *(["masks/"] if masked else []), "names.json", "database.db", "sparse/",
                     "metrics.csv", "../poses_report.json"],
            used={"matcher": matcher, "principal_point": state.principal_point,
                  "camera_groups": [len(g) for g in groups], "pycolmap": pycolmap.__version__,
                  "working_size": state.working_size, "masks": str(config.masks) if masked else None,
                  "stationary_matches": state.stationary, "focal_prior": report["focal_prior"],
                  "attempts": [{k: a[k] for k in ("name", "registered", "total", "kept", "check", "settings")}
                               for a in state.attempts], "choice": state.choice, "ladder": state.ladder},
            left_out={**state.skipped, **report["not_registered"]}, version=VERSION,
            config=config_to_json(config), **verdict(state.checks),
        )  # fmt: skip
        os.replace(build, colmap_dir)
    except BaseException as e:
        shutil.rmtree(build, ignore_errors=True)
        if isinstance(e, Exception):
            try:
                write_json(report_path, build_report(config, state, "failed", str(e).splitlines()[0] if str(e) else ""))
            except Exception:  # the report must never hide the original error
                pass
        if isinstance(e, UserError) and previous is not None:
            raise UserError(f"{e} (the earlier model is kept in {previous})") from None
        raise
    if previous is not None:
        shutil.rmtree(previous, ignore_errors=True)
    print_summary(console, report)
    return Outputs(
        colmap_dir=colmap_dir, sparse=colmap_dir / "sparse", images=colmap_dir / "images",
        database=colmap_dir / "database.db", report=report_path, registered=report["registered"],
        total=report["total"], mean_reprojection_error=float(report["mean_reprojection_error_px"]),
        working_size=state.working_size["size"], check=report["check"],
        attempts=tuple(f"{a['name']}: {a['registered']}/{a['total']} registered{' (kept)' if a['kept'] else ''}; "
                       f"{a['settings']}" for a in state.attempts),
    )  # fmt: skip
