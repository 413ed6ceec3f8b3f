"""The poses stage's interface: its `Config` (with the validation of a config and its input) and its `Outputs`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from nerfpipe.data.errors import UserError
from nerfpipe.stages.poses import colmap as sfm
from nerfpipe.stages.poses.images import IMAGE_SUFFIXES
from nerfpipe.stages.poses.report import MIN_REGISTERED

__all__ = ["CameraModel", "CAMERA_MODELS", "Config", "Outputs", "check"]

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
    max_attempts: int = 5
    """Settings to try while under 80 % of the images register or a camera check fails: 1 = no retry, 2 = also
    pycolmap's 3200 px and 8192 features, 3 = also relaxed mapper thresholds, 4 = also wide-baseline features, 5 =
    also guided matching (see stages.poses.attempts; a time budget may stop it earlier once a usable model
    exists)."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Image pairs to match: 'auto' = exhaustive for photo folders, sequential for video."""
    single_camera: bool = True
    """Images of the same size share one camera (one phone, one zoom). Mixed sizes get one camera per size
    (with a warning) instead of refusing. False: one camera per image."""
    camera_model: CameraModel = "SIMPLE_RADIAL"
    """COLMAP camera model, one `convert` reads: SIMPLE_RADIAL (f, k1; robust, COLMAP's default), RADIAL,
    OPENCV (fx fy k1 k2 p1 p2; for large sharp images: on small ones its extra parameters can derail the
    mapper), PINHOLE, SIMPLE_PINHOLE."""
    second_radial_term: bool = True
    """With a camera shared by 10+ images and the mapper's SIMPLE_RADIAL model, a last bundle adjustment tries
    RADIAL (k1, k2) and keeps it where the reprojection error drops significantly and the lens stays plausible
    (stages.poses.lens; fox: median / largest rotation error 0.20 / 0.35 -> 0.12 / 0.20 deg)."""
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
    time_budget: float | None = None
    """Seconds the stage aims to finish in, wall clock (stages.poses.budget); unset: 5 s a photo, at least 60 s (22
    photos: 110 s), whatever their resolution; 0: unbounded. It caps the first attempt's SIFT working size where
    extracting every photo at it would take over a third of the budget (timed on the probe photos), and starts a
    retry, once a usable model is in hand, only where its predicted cost fits what is left (an extraction retry is
    shrunk first). Without a usable model every retry runs."""
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


def check(config: Config) -> str:
    """Validate the config and input; return the input kind ('photos' | 'video')."""
    if config.matcher not in ("auto", "exhaustive", "sequential"):
        raise UserError(f"matcher must be auto, exhaustive or sequential, got {config.matcher!r}")
    if config.camera_model not in CAMERA_MODELS:
        raise UserError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}; got {config.camera_model!r}")
    if config.drop_blurry < 0:
        raise UserError(f"drop_blurry must be a fraction in [0, 1) or a count >= 1, got {config.drop_blurry}")
    if (config.max_image_size is not None and config.max_image_size < 100) or config.max_num_features < 100:
        raise UserError("max_image_size and max_num_features must be at least 100")
    if config.time_budget is not None and not config.time_budget >= 0:
        raise UserError(f"time_budget must be >= 0 seconds (0: unbounded), got {config.time_budget}")
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
