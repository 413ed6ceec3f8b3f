"""Stage `poses`: a folder of photos or a video -> a COLMAP sparse model, in-process with pycolmap.

Steps: upright copies of the photos (EXIF orientation applied; COLMAP ignores it) and each photo's EXIF focal
length, or the sharpest frame per window of a video -> screening (blur, exposure, near-duplicates;
`drop_blurry` removes the blurriest) -> the SIFT working size (`max_image_size`, or the smallest of 1000 / 1600
/ 3200 px where SIFT finds enough features) -> SIFT, the cameras given the EXIF focal prior (`exif`) ->
exhaustive or sequential matching -> incremental mapping -> the LARGEST model (most registered images), never
blindly model 0 -> its cameras and structure checked (`quality`: focal against EXIF or a plausible field of
view, distortion, principal point, reprojection error, track length) and its poses against the photos
(`consistency`: a model that folded onto itself where faces look alike reprojects well; the capture order
catches it) -> a fold is retried at once with the matches restricted to neighbours in capture order, then
without the features matched far across that order (a turntable's room, `far_matched`); under 80 %
registered or a camera check failed, retries with pycolmap's size and feature cap, then a relaxed mapper, then
wide-baseline features (for photos taken far apart), then guided matching, within the stage's time budget
(`budget`: 5 s a photo by default, whatever their resolution; `attempts`, `choice`), keeping the attempt that
registered most among those whose cameras pass the checks and whose poses agree with the photos (a failing one only
when all fail, marked suspect) -> with a shared camera, the last bundle adjustments refine the principal point,
then try a second radial term (`lens`: each kept where it pays) -> the written model's checks: `check` ("ok" |
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
(`static.check_static_matches`, `static.check_static_cameras`). With --masks the background has no features.

Modules: `config` (the Config, its validation, the Outputs), `inputs` (the images, screening, masks, camera groups
and working size the attempts start from), `images` (upright copies, screening), `exif` (the EXIF focal prior,
given to COLMAP's cameras; weak for cropped photos), `video` (frame picking), `colmap` (the pycolmap steps and the
working size), `lens` (the last bundle adjustments: principal point, second radial term), `attempts` (the retry
ladder), `budget` (the time budget: the first working size, which retries fit), `quality` (the checks of a
model's cameras and structure), `consistency` (the checks of its poses against the photos' matches), `choice`
(which attempt to keep, when to stop), `report` (run state, registration checks, poses_report.json, phase timer),
`output` (setting aside an earlier colmap/, writing the kept model, report and manifest into place).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import pycolmap
from rich.console import Console
from rich.progress import Progress

from nerfpipe.data.errors import UserError
from nerfpipe.data.lock import folder_lock
from nerfpipe.data.rundir import MetricsLog
from nerfpipe.stages.poses import colmap as sfm
from nerfpipe.stages.poses import inputs, lens, output, quality
from nerfpipe.stages.poses.attempts import ladder, prior_focals, run_attempts, weak_priors
from nerfpipe.stages.poses.budget import stage_budget
from nerfpipe.stages.poses.colmap import interrupted_by_sigterm
from nerfpipe.stages.poses.config import CAMERA_MODELS, CameraModel, Config, Outputs, check
from nerfpipe.stages.poses.inputs import camera_groups as _camera_groups  # tests/test_poses.py reaches it by this name
from nerfpipe.stages.poses.report import (
    FAIL_FRACTION,
    MIN_REGISTERED,
    WARN_FRACTION,
    PhaseTimer,
    RunState,
    check_features,
    check_registered,
    print_summary,
)
from nerfpipe.stages.poses.static import check_static_cameras, check_static_matches

__all__ = [
    "Config",
    "Outputs",
    "run",
    "MIN_REGISTERED",
    "FAIL_FRACTION",
    "WARN_FRACTION",
    "CameraModel",
    "CAMERA_MODELS",
]


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Photos or video -> SCENE_DIR/colmap (see the module docstring). UserError on bad input or a failed model.
    Holds SCENE_DIR's lock (`data.lock`: one writer; it sweeps a killed run's `.colmap.tmp-*`); SIGTERM stops it
    with one line (`interrupted_by_sigterm`)."""
    kind = check(config)
    with folder_lock(config.scene_dir), interrupted_by_sigterm():
        return _run(config, kind, progress)


def _run(config: Config, kind: str, progress: Progress | None) -> Outputs:
    pycolmap.logging.minloglevel = 1  # COLMAP's INFO lines would drown the summary; warnings and errors stay
    console = Console(stderr=True)
    scene_dir = Path(config.scene_dir)
    colmap_dir = scene_dir / "colmap"
    report_path = scene_dir / "poses_report.json"
    previous = output.set_aside(colmap_dir, report_path)
    build = Path(tempfile.mkdtemp(prefix=".colmap.tmp-", dir=scene_dir))
    images = build / "images"
    images.mkdir()
    state = RunState(started=time.time())
    metrics = MetricsLog(build / "metrics.csv", ["step", "seconds", "phase", "images", "registered"])
    phase = PhaseTimer(state, metrics, progress)
    matcher = config.matcher if config.matcher != "auto" else ("sequential" if kind == "video" else "exhaustive")
    settings = sfm.SfmSettings(  # max_image_size: a placeholder until inputs.working_size, after screening
        max_image_size=sfm.PYCOLMAP_MAX_IMAGE_SIZE,
        max_num_features=config.max_num_features,
        camera_model=config.camera_model,
        single_camera=config.single_camera,
        matcher=matcher,
        sequential_overlap=config.sequential_overlap,
        num_threads=config.num_threads,
        seed=config.seed,
    )
    pycolmap.set_random_seed(config.seed)
    try:
        with phase("images"):
            if kind == "photos":
                inputs.prepare_photos(Path(config.input), images, state)
            else:
                inputs.prepare_video(Path(config.input), images, config.video_frames, state)
        with phase("screening"):
            names = inputs.screen(config, images, state)
            groups = _camera_groups(config, names, state)
        masked = config.masks is not None
        if masked:
            with phase("masks"):
                inputs.write_masks(Path(config.masks), names, build / "masks", state)
            settings = replace(settings, mask_path=str(build / "masks"))
        long_sides = [max(max(state.sizes[n]) for n in g) for g in groups]
        budget = stage_budget(config.time_budget, len(names))
        with phase("working_size"):
            settings = inputs.working_size(
                config, settings, build / "probe.db", images, names, max(long_sides), state, budget
            )
        plan = ladder(settings, config.max_attempts, max(long_sides))
        run_attempts(
            plan,
            build,
            images,
            groups,
            long_sides,
            state,
            phase,
            after_matching=lambda db: check_static_matches(db, masked, state),
            budget=budget,
        )
        check_features(state.stats)
        check_registered(state, matcher)
        check_static_cameras(state.model, masked)
        inputs.warn_zoom(state)
        if config.single_camera:
            with phase("principal_point"):
                mapped = state.model
                state.model, state.principal_point = lens.refine_principal_point(mapped, config.num_threads)
            if config.second_radial_term:
                with phase("radial_term"):
                    state.model, state.radial_term = lens.add_radial_term(
                        state.model, state.model is not mapped, config.num_threads
                    )
        state.checks = [
            *quality.model_checks(
                state.model, prior_focals(state.focal_prior), len(state.stats.features), weak_priors(state.focal_prior)
            ),
            *state.consistency[0],
        ]
        report = output.write_model(config, state, build, colmap_dir, report_path, metrics, matcher, groups)
    except BaseException as e:
        shutil.rmtree(build, ignore_errors=True)
        if isinstance(e, Exception):
            output.write_failed_report(config, state, report_path, e)
        if isinstance(e, UserError) and previous is not None:
            e.args = (f"{e} (the earlier model is kept in {previous})",)  # the same error: Interrupted keeps 143
            raise e from None
        raise
    if previous is not None:
        shutil.rmtree(previous, ignore_errors=True)
    print_summary(console, report)
    return output.outputs(colmap_dir, report_path, report, state)
