"""pycolmap steps of the poses stage: SIFT extraction, matching, incremental mapping, database statistics.

Speed settings (2 CPU cores, 50 photos of 1080x1920 in well under a minute) are chosen in
`benchmarks/bench_poses.py`; the values here are the ones it found. COLMAP logs go to glog (stderr).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pycolmap

__all__ = ["SfmSettings", "extract", "match", "reconstruct", "database_stats", "DatabaseStats"]


BA_GLOBAL_MAX_ITERATIONS = 100
BA_LOCAL_MAX_ITERATIONS = 25
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
class SfmSettings:
    """The pycolmap knobs the poses stage exposes (see `stages.poses.Config` for the meaning)."""

    max_image_size: int
    max_num_features: int
    camera_model: str
    single_camera: bool
    matcher: str  # "exhaustive" | "sequential"
    sequential_overlap: int
    num_threads: int
    seed: int
    ba_global_max_num_iterations: int = BA_GLOBAL_MAX_ITERATIONS
    ba_local_max_num_iterations: int = BA_LOCAL_MAX_ITERATIONS


def extract(db: Path, image_dir: Path, groups: list[list[str]], long_sides: list[int], s: SfmSettings) -> None:
    """SIFT features for the images; with `single_camera`, each group (one image size) shares a camera.

    long_sides: the largest image long side of each group (picks first_octave, see SMALL_IMAGE).
    """
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = s.camera_model
    mode = pycolmap.CameraMode.SINGLE if s.single_camera else pycolmap.CameraMode.PER_IMAGE
    for names, long_side in zip(groups, long_sides, strict=True):
        opts = pycolmap.FeatureExtractionOptions()
        opts.max_image_size = s.max_image_size
        opts.num_threads = s.num_threads
        opts.sift.max_num_features = s.max_num_features
        opts.sift.first_octave, opts.sift.estimate_affine_shape = sift_octave_and_affine(
            min(long_side, s.max_image_size)
        )
        pycolmap.extract_features(
            db,
            image_dir,
            image_names=names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=opts,
            device=pycolmap.Device.cpu,
        )


def match(db: Path, s: SfmSettings) -> None:
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = s.num_threads
    opts.guided_matching = False
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = s.seed
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
    opts.extract_colors = True
    opts.min_model_size = 3
    opts.ba_global_max_num_iterations = s.ba_global_max_num_iterations
    opts.ba_local_max_num_iterations = s.ba_local_max_num_iterations
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
