"""pycolmap steps of the poses stage: SIFT extraction, matching, incremental mapping, database statistics
(the last bundle adjustment, which refines the lens, is `lens`).

Every pycolmap option is COLMAP's default unless set here, and each one set here says why (the stage's Config
docstring lists them). Speed figures are from `benchmarks/bench_poses.py` (fox: 50 photos of 1080x1920 on 2
CPU cores). COLMAP logs go to glog (stderr).

How the SIFT feature cap works (COLMAP's CPU extractor, VLFeat): every scale level of the image is detected
and described, then the COARSEST levels are kept until their count passes `max_num_features` (the level
that crosses the cap is kept whole, and a keypoint can have 2 orientations, so up to ~1.4x the cap come
out). A larger working size under a cap that binds therefore costs more extraction time but adds no finer
features: only a larger cap does.
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import threading
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap

from nerfpipe.data.errors import Interrupted
from nerfpipe.stages.poses.working import copies, to_full_resolution, worth_copying

__all__ = [
    "SfmSettings",
    "MapperThresholds",
    "RELAXED_MAPPER",
    "PYCOLMAP_MAX_IMAGE_SIZE",
    "PYCOLMAP_MAX_NUM_FEATURES",
    "WORKING_SIZES",
    "ENOUGH_FEATURES",
    "choose_working_size",
    "count_features",
    "extract",
    "match",
    "verification_options",
    "copy_features",
    "reconstruct",
    "database_stats",
    "DatabaseStats",
    "interrupted_by_sigterm",
]


@contextlib.contextmanager
def interrupted_by_sigterm() -> Iterator[None]:
    """Within the block SIGTERM raises `data.errors.Interrupted` (one line, exit 143) where Python next runs.

    Importing pycolmap installs glog's failure-signal handler (C++, invisible to `signal.getsignal`), which
    answers SIGTERM with a 35-line stack trace before dying; a Python handler replaces it. pycolmap's long
    steps (extraction, matching, mapping) poll Python's signals while they run, so the stop is prompt (about 1 s
    on the test photos). The handler left afterwards is the default (a plain SIGTERM death, no trace). Off the
    main thread: nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        pycolmap.logging.minloglevel = 3  # pycolmap logs "Stopping thread..." as it unwinds: the line below says it
        raise Interrupted(f"interrupted ({signal.Signals(signum).name})", signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


PYCOLMAP_MAX_IMAGE_SIZE = 3200
"""pycolmap's SIFT working size (`FeatureExtractionOptions().eff_max_image_size()`; tested)."""
PYCOLMAP_MAX_NUM_FEATURES = 8192
"""pycolmap's SIFT feature cap (`SiftExtractionOptions().max_num_features`; tested)."""
PYCOLMAP_MIN_VERIFIED_INLIERS = 15
"""pycolmap's two-view verification threshold (`TwoViewGeometryOptions().min_num_inliers`; tested)."""
WORKING_SIZES = (1000, 1600, PYCOLMAP_MAX_IMAGE_SIZE)
"""Candidate SIFT working sizes (long side, px), smallest first; see `choose_working_size`."""
ENOUGH_FEATURES = 1000
"""SIFT features per image that make a working size large enough: the mapper's initial pair needs 100
inlier matches (init_min_num_inliers) and neighbouring views typically turn 10-30 % of their features into
inliers. fox at 1000 px: 942-1812 features per image (median 1446), 50/50 registered."""
PROBE_IMAGES = 3
"""Photos (evenly spread over the set) on which `choose_working_size` counts features."""
MIN_MODEL_SIZE = 3
"""Keep models of 3+ images (pycolmap: 10): the report names every model found, and a set of 6-20 photos
that splits still shows where (the stage fails under 40 % registered in any case)."""
SMALL_IMAGE = 1000
"""Images whose working long side is below this are upsampled 2x inside SIFT (first_octave -1, COLMAP's
default); larger ones start at full resolution (first_octave 0: ~3x faster, enough features)."""
TINY_IMAGE = 500
"""Below this working long side, SIFT upsamples 4x (first_octave -2) and estimates affine shape: on the
256 px synthetic scene (3 seeds) this doubles the 3D points and cuts the median rotation error from
0.12-0.16 deg to 0.077-0.083 deg, for ~10 s more on 40 images (`benchmarks/bench_poses.py --only synthetic`)."""


def sift_octave_and_affine(long_side: int) -> tuple[int, bool]:
    """(first_octave, estimate_affine_shape) for images whose working long side is `long_side` pixels."""
    if long_side < TINY_IMAGE:
        return -2, True
    return (-1 if long_side < SMALL_IMAGE else 0), False


@dataclass(frozen=True, kw_only=True)
class MapperThresholds:
    """Incremental-mapper thresholds; the defaults are pycolmap's (tested against
    `IncrementalPipelineOptions()`), `RELAXED_MAPPER` is the last retry's."""

    min_num_matches: int = 15
    """Verified inlier matches for an image pair to be used at all."""
    init_min_num_inliers: int = 100
    """Inliers of the initial image pair."""
    init_min_tri_angle: float = 16.0
    """Median triangulation angle (deg) of the initial pair."""
    abs_pose_min_num_inliers: int = 30
    """2D-3D inliers to register an image."""
    abs_pose_min_inlier_ratio: float = 0.25
    """... and their fraction of the image's 2D-3D correspondences."""
    max_reg_trials: int = 3
    """Times the mapper tries to register an image before giving up on it."""
    structure_less_fallback: bool = True
    """An image that 2D-3D registration fails may be registered from its 2D-2D correspondences alone."""


RELAXED_MAPPER = MapperThresholds(
    min_num_matches=8,
    init_min_num_inliers=50,
    init_min_tri_angle=8.0,
    abs_pose_min_num_inliers=15,
    abs_pose_min_inlier_ratio=0.15,
    max_reg_trials=6,
    structure_less_fallback=False,
)
"""About half of each default (twice the registration trials): less evidence to start a model and to register
an image. The reprojection-error filters (4 px) that every registered image and point must pass are unchanged.
Without the structure-less fallback: an image that fails even these thresholds is not registered from 2D-2D
correspondences alone (two relaxations at once; 22 photos all round a masked head, the wide-baseline matches
restricted to neighbours: 22 registered 6.2 deg off with it, 21 within 0.5 deg median without)."""


@dataclass(frozen=True, kw_only=True)
class SfmSettings:
    """The pycolmap knobs one attempt of the poses stage uses (see `stages.poses.Config` for the meaning)."""

    max_image_size: int
    """SIFT working size (long side, px; images are never upsampled)."""
    max_num_features: int
    camera_model: str
    single_camera: bool
    matcher: str  # "exhaustive" | "sequential"
    sequential_overlap: int
    num_threads: int
    seed: int
    guided_matching: bool = False
    """Re-match each verified pair under its estimated geometry (more inliers; pycolmap's default: off)."""
    min_verified_inliers: int = PYCOLMAP_MIN_VERIFIED_INLIERS
    """Two-view verification keeps pairs with this many inliers (the mapper then uses min_num_matches)."""
    mapper: MapperThresholds = field(default_factory=MapperThresholds)
    wide_baseline: bool = False
    """Features that survive larger changes of viewpoint (COLMAP's advice for wide baselines): SIFT upsamples 2x
    (first_octave at most -1), pools descriptors over domain sizes (DSP-SIFT) and estimates affine shapes; about
    8 x the extraction time of first_octave 0 (`attempts`: the ladder's last retry)."""
    mask_path: str | None = None
    """Folder of COLMAP masks (`<image name>.png`, black = no features there), or None (poses --masks)."""


def choose_working_size(long_side: int, median_features_at: Callable[[int], float]) -> tuple[int, dict[int, float]]:
    """The smallest of WORKING_SIZES (never above `long_side`: COLMAP does not upsample) at which
    `median_features_at(size)` reaches ENOUGH_FEATURES; the largest candidate needs no count.

    Returns (size, {size: median features} for each size counted).
    """
    candidates = sorted({min(s, long_side) for s in WORKING_SIZES})
    counted: dict[int, float] = {}
    for size in candidates[:-1]:
        counted[size] = median_features_at(size)
        if counted[size] >= ENOUGH_FEATURES:
            return size, counted
    return candidates[-1], counted


def count_features(
    db: Path,
    image_dir: Path,
    names: Sequence[str],
    size: int,
    s: SfmSettings,
    long_side: int | None = None,
    work: Path | None = None,
) -> float:
    """Median SIFT features of `names` at working size `size` (a scratch database `db`, deleted after); `long_side`
    and `work` as `extract`'s (the probe's working copies are kept there for the attempts)."""
    probe_names = [names[round(i * (len(names) - 1) / max(PROBE_IMAGES - 1, 1))] for i in range(PROBE_IMAGES)]
    probe_names = list(dict.fromkeys(probe_names))
    try:
        extract(db, image_dir, [probe_names], [long_side or size], replace(s, max_image_size=size), work)
        counts = database_stats(db).features
    finally:
        db.unlink(missing_ok=True)
    return float(np.median(list(counts.values())))


def extract(
    db: Path,
    image_dir: Path,
    groups: list[list[str]],
    long_sides: list[int],
    s: SfmSettings,
    work: Path | None = None,
) -> None:
    """SIFT features for the images; with `single_camera`, each group (one image size) shares a camera.

    long_sides: the largest image long side of each group (picks first_octave, see SMALL_IMAGE). `work`: a folder
    for working copies (`working`): a group of photos at least WORKING_COPY_FACTOR x the working size is read
    from copies made there at the working size, and the database scaled to the photos' size after.
    """
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = s.camera_model
    mode = pycolmap.CameraMode.SINGLE if s.single_camera else pycolmap.CameraMode.PER_IMAGE
    for names, long_side in zip(groups, long_sides, strict=True):
        source, mask_path, full = image_dir, s.mask_path, None
        if work is not None and worth_copying(long_side, s.max_image_size):
            source, mask_path, full = copies(
                image_dir, names, s.max_image_size, work / str(s.max_image_size), s.mask_path
            )
        if mask_path is not None:
            reader.mask_path = mask_path  # COLMAP: <mask_path>/<image name>.png; no keypoint where it is 0
        opts = pycolmap.FeatureExtractionOptions()
        opts.max_image_size = s.max_image_size
        opts.num_threads = s.num_threads
        opts.sift.max_num_features = s.max_num_features
        opts.sift.first_octave, opts.sift.estimate_affine_shape = sift_octave_and_affine(
            min(long_side, s.max_image_size)
        )
        if s.wide_baseline:
            opts.sift.first_octave = min(opts.sift.first_octave, -1)
            opts.sift.estimate_affine_shape = opts.sift.domain_size_pooling = True
        pycolmap.extract_features(
            db,
            source,
            image_names=names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=opts,
            device=pycolmap.Device.cpu,
        )
        if full is not None:
            to_full_resolution(db, full)


def verification_options(s: SfmSettings) -> pycolmap.TwoViewGeometryOptions:
    """The two-view geometric verification of `s`'s matching (its inlier minimum and seed)."""
    verify = pycolmap.TwoViewGeometryOptions()
    verify.min_num_inliers = s.min_verified_inliers
    verify.ransac.random_seed = s.seed
    return verify


def match(db: Path, s: SfmSettings) -> None:
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = s.num_threads
    opts.guided_matching = s.guided_matching
    verify = verification_options(s)
    if s.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = s.sequential_overlap
        pairing.num_threads = s.num_threads
        pycolmap.match_sequential(
            db, matching_options=opts, pairing_options=pairing, verification_options=verify, device=pycolmap.Device.cpu
        )
    elif s.matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=opts, verification_options=verify, device=pycolmap.Device.cpu)
    else:
        raise ValueError(f"expected matcher 'exhaustive' or 'sequential', got {s.matcher!r}")


def reconstruct(db: Path, image_dir: Path, out_dir: Path, s: SfmSettings) -> dict[int, pycolmap.Reconstruction]:
    """Incremental mapping; every model found (COLMAP may split a scene into several)."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = s.num_threads
    opts.random_seed = s.seed
    opts.min_model_size = MIN_MODEL_SIZE
    t = s.mapper
    opts.min_num_matches = t.min_num_matches
    opts.mapper.init_min_num_inliers = t.init_min_num_inliers
    opts.mapper.init_min_tri_angle = t.init_min_tri_angle
    opts.mapper.abs_pose_min_num_inliers = t.abs_pose_min_num_inliers
    opts.mapper.abs_pose_min_inlier_ratio = t.abs_pose_min_inlier_ratio
    opts.mapper.max_reg_trials = t.max_reg_trials
    opts.structure_less_registration_fallback = t.structure_less_fallback
    out_dir.mkdir(parents=True, exist_ok=True)
    return pycolmap.incremental_mapping(db, image_dir, out_dir, options=opts)


@dataclass(frozen=True, kw_only=True)
class DatabaseStats:
    features: dict[str, int]  # image name -> keypoints
    matches: dict[str, int]  # image name -> verified inlier matches summed over its pairs
    verified_pairs: dict[str, int]  # image name -> pairs with a verified two-view geometry
    camera_of: dict[str, int]  # image name -> camera id


def database_stats(db_path: Path) -> DatabaseStats:
    db = pycolmap.Database.open(db_path)
    try:
        images = db.read_all_images()
        name_of = {im.image_id: im.name for im in images}
        features = {im.name: db.num_keypoints_for_image(im.image_id) for im in images}
        matches: dict[str, int] = defaultdict(int)
        pairs: dict[str, int] = defaultdict(int)
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        for pair_id, n in zip(pair_ids, inliers, strict=True):
            if n <= 0:
                continue
            for image_id in pycolmap.pair_id_to_image_pair(pair_id):
                matches[name_of[image_id]] += n
                pairs[name_of[image_id]] += 1
        camera_of = {im.name: im.camera_id for im in images}
    finally:
        db.close()
    return DatabaseStats(
        features=features,
        matches={n: matches.get(n, 0) for n in features},
        verified_pairs={n: pairs.get(n, 0) for n in features},
        camera_of=camera_of,
    )


def copy_features(src: Path, dst: Path) -> None:
    """A copy of database `src` with its features only (matches and two-view geometries cleared)."""
    shutil.copyfile(src, dst)
    db = pycolmap.Database.open(dst)
    try:
        db.clear_matches()
        db.clear_two_view_geometries()
    finally:
        db.close()
