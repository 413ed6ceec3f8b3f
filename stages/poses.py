"""Stage `poses`: a folder of photos or a video -> a COLMAP sparse model, in-process with pycolmap.

Steps: upright copies of the photos (EXIF orientation applied; COLMAP ignores it) or the sharpest frame per
window of a video -> screening (blur, exposure, near-duplicates; `drop_blurry` removes the blurriest) ->
SIFT on images downscaled to `max_image_size` -> exhaustive or sequential matching -> incremental mapping ->
the LARGEST model (most registered images), never blindly model 0 -> with a shared camera, one last bundle
adjustment that also refines the principal point.

Outputs (COLMAP conventions: OpenCV camera axes, `cam_from_world` poses, binary model):
  SCENE_DIR/colmap/images/          upright copies / video frames: the image folder of the model
  SCENE_DIR/colmap/names.json       {copy name: original path} (video frames: {name: "video.mp4#frame=N"})
  SCENE_DIR/colmap/database.db      features and matches
  SCENE_DIR/colmap/sparse/          the chosen model (cameras.bin, images.bin, points3D.bin, ...)
  SCENE_DIR/colmap/metrics.csv      step, seconds, phase, images, registered
  SCENE_DIR/colmap/manifest.json    provenance; the folder is built under a temporary name and renamed
                                    into place complete, so colmap/ exists only after a success
  SCENE_DIR/poses_report.json       also on failure (status "failed" and the error): counts, per-image
                                    features / matches / observations / screening, why images were left out

A rerun first moves an earlier colmap/ (with its poses_report.json inside) to SCENE_DIR/colmap.previous/: a
failed rerun leaves no colmap/ that looks current, yet loses nothing (the error says where the old model is);
a successful one deletes colmap.previous/.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pycolmap
from rich.console import Console
from rich.progress import Progress

from data.atomic import write_json
from data.errors import UserError
from data.rundir import MetricsLog, config_to_json, write_manifest
from stages import poses_colmap as sfm
from stages.poses_images import (
    IMAGE_SUFFIXES,
    Screen,
    blurriest,
    list_images,
    near_duplicates,
    screen_image,
    write_upright,
)
from stages.poses_video import extract_frames

__all__ = ["Config", "Outputs", "run", "MIN_REGISTERED", "FAIL_FRACTION", "WARN_FRACTION"]

VERSION = "1"
MIN_REGISTERED = 3
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
"""The models `convert` (data.importers.colmap) reads."""
FAIL_FRACTION = 0.4
"""Fewer registered images than this fraction is an error (no model is written)."""
WARN_FRACTION = 0.8
"""Fewer registered images than this fraction prints a warning."""
MIN_FEATURES = 100
"""An image with fewer SIFT features than this is reported as texture-less."""
PP_REFINE_MIN_IMAGES = 10
"""The final bundle adjustment refines a camera's principal point only if it is shared by this many images."""
PP_MAX_SHIFT = 0.1
"""... and keeps the result only if the principal point moved less than this fraction of the image size"""
PP_MIN_F = 100.0
"""... and the reprojection error dropped significantly: F statistic of the improvement per added parameter
(pure noise gives ~1; fox 1080x1920, where it is real, ~260; the 256 px synthetic scene, centred, ~30)."""


@dataclass(frozen=True, kw_only=True)
class Config:
    input: Path
    """A folder of photos (.jpg .png .tif .bmp .webp; not recursive) or a video file."""
    scene_dir: Path
    """Output folder: colmap/ (images, database.db, sparse/), poses_report.json."""
    max_image_size: int = 1000
    """SIFT runs on images downscaled so that the long side is at most this many pixels (the model keeps
    full-resolution intrinsics)."""
    max_num_features: int = 2048
    """SIFT features kept per image (matching time grows with its square)."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Image pairs to match: 'auto' = exhaustive for photo folders, sequential for video."""
    single_camera: bool = True
    """Images of the same size share one camera (one phone, one zoom). Mixed sizes get one camera per size
    (with a warning) instead of refusing. False: one camera per image."""
    camera_model: str = "SIMPLE_RADIAL"
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


@dataclass(kw_only=True)
class _Run:
    """Mutable state of one run, turned into poses_report.json."""

    started: float
    source: str = ""
    names: dict[str, str] = field(default_factory=dict)  # copy name -> original
    skipped: dict[str, str] = field(default_factory=dict)  # original name -> why (undecodable, dropped)
    screens: dict[str, Screen] = field(default_factory=dict)
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)  # copy name -> (w, h)
    duplicates: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    video: dict[str, Any] | None = None
    stats: sfm.DatabaseStats | None = None
    models: list[int] = field(default_factory=list)  # registered images per model found
    model: pycolmap.Reconstruction | None = None
    all_models: dict[int, pycolmap.Reconstruction] = field(default_factory=dict)
    principal_point: str = ""


def _check(config: Config) -> str:
    """Validate the config and input; return the input kind ('photos' | 'video')."""
    if config.matcher not in ("auto", "exhaustive", "sequential"):
        raise UserError(f"matcher must be auto, exhaustive or sequential, got {config.matcher!r}")
    if config.camera_model not in CAMERA_MODELS:
        raise UserError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}; got {config.camera_model!r}")
    if config.drop_blurry < 0:
        raise UserError(f"drop_blurry must be a fraction in [0, 1) or a count >= 1, got {config.drop_blurry}")
    if config.max_image_size < 100 or config.max_num_features < 100:
        raise UserError("max_image_size and max_num_features must be at least 100")
    src = Path(config.input)
    if not src.exists():
        raise UserError(f"input {src} does not exist (expected a folder of photos or a video file)")
    colmap_dir = Path(config.scene_dir).resolve() / "colmap"
    if src.resolve() == colmap_dir or colmap_dir in src.resolve().parents:
        raise UserError(f"input {src} is inside the output folder {colmap_dir}; copy the photos elsewhere")
    if src.is_dir():
        return "photos"
    if src.suffix.lower() in IMAGE_SUFFIXES:
        raise UserError(f"input {src} is a single image; give a folder of at least {MIN_REGISTERED} photos")
    return "video"


def _prepare_photos(folder: Path, images: Path, state: _Run) -> None:
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
    if state.skipped:
        state.warnings.append(f"skipped {len(state.skipped)} undecodable file(s): {', '.join(state.skipped)}")


def _prepare_video(video: Path, images: Path, target: int, state: _Run) -> None:
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

    from stages.poses_images import SCREEN_SIZE

    with Image.open(path) as im:
        grey = im.convert("L")
        grey.thumbnail((SCREEN_SIZE, SCREEN_SIZE), Image.Resampling.BILINEAR)
        return np.asarray(grey)


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def _screen(config: Config, images: Path, state: _Run) -> list[str]:
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


def _camera_groups(config: Config, names: list[str], state: _Run) -> list[list[str]]:
    if not config.single_camera:
        return [names]
    by_size: dict[tuple[int, int], list[str]] = {}
    for n in names:
        by_size.setdefault(state.sizes[n], []).append(n)
    if len(by_size) > 1:
        sizes = ", ".join(f"{w}x{h} ({len(v)})" for (w, h), v in by_size.items())
        state.warnings.append(f"images have {len(by_size)} different sizes ({sizes}): one shared camera per size")
    return list(by_size.values())


def _check_features(stats: sfm.DatabaseStats) -> None:
    textured = [n for n, k in stats.features.items() if k >= MIN_FEATURES]
    if len(textured) < MIN_REGISTERED:
        raise UserError(
            f"only {len(textured)} of {len(stats.features)} images have {MIN_FEATURES}+ SIFT features: the images "
            "look blank or texture-less; photograph a scene with visible texture (not plain walls, sky or blur)"
        )


def _refine_principal_point(rec: pycolmap.Reconstruction, state: _Run, num_threads: int) -> pycolmap.Reconstruction:
    """Final BA that also refines the principal point of cameras shared by PP_REFINE_MIN_IMAGES+ images.

    A shared camera constrains it well; the mapper keeps it at the image centre, which shows up as a
    constant rotation offset of every camera (fox: ~0.65 deg against instant-ngp's COLMAP poses, which
    refined it the same way). A result that moves it further than PP_MAX_SHIFT of the image size or does not
    improve the reprojection error significantly (PP_MIN_F) is rejected: the mapper's model is kept.
    """
    users = Counter(im.camera_id for im in rec.images.values() if im.has_pose)
    shared = sorted(c for c, k in users.items() if k >= PP_REFINE_MIN_IMAGES)
    if not shared:
        state.principal_point = "kept at the image centre (no camera shared by enough images)"
        return rec
    refined = pycolmap.Reconstruction(rec)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_principal_point = True
    opts.print_summary = False
    opts.ceres.solver_options.num_threads = num_threads
    ba = pycolmap.BundleAdjustmentConfig()
    for image_id in refined.reg_image_ids():
        ba.add_image(image_id)
    for cam_id in refined.cameras:
        if cam_id not in shared:
            ba.set_constant_cam_intrinsics(cam_id)
    ba.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    pycolmap.create_default_bundle_adjuster(opts, ba, refined).solve()
    refined.update_point_3d_errors()
    f_stat = _improvement_f(rec, refined, extra_params=2 * len(shared))
    moved = 0.0
    for cam_id in shared:
        a, b = rec.cameras[cam_id], refined.cameras[cam_id]
        shift = np.hypot(b.principal_point_x - a.principal_point_x, b.principal_point_y - a.principal_point_y)
        moved = max(moved, float(shift) / max(a.width, a.height))
    what = f"moved up to {moved:.2%} of the image size, F = {f_stat:.0f}"
    if moved > PP_MAX_SHIFT or not np.isfinite(moved) or f_stat < PP_MIN_F:
        state.principal_point = f"refinement rejected ({what}); kept at the image centre"
        return rec
    state.principal_point = f"refined for {len(shared)} shared camera(s) ({what})"
    return refined


def _sse(rec: pycolmap.Reconstruction) -> tuple[float, int]:
    """Sum of squared reprojection errors (from each point's mean error) and the number of residuals."""
    sse, n = 0.0, 0
    for point in rec.points3D.values():
        k = point.track.length()
        sse += k * point.error**2
        n += 2 * k
    return sse, n


def _improvement_f(before: pycolmap.Reconstruction, after: pycolmap.Reconstruction, extra_params: int) -> float:
    """F statistic of the reprojection improvement bought by `extra_params` more parameters (~1 if noise)."""
    sse0, _ = _sse(before)
    sse1, n = _sse(after)
    if sse1 <= 0 or n <= extra_params:
        return 0.0
    return float((sse0 - sse1) / extra_params / (sse1 / (n - extra_params)))


def _why_not_registered(name: str, stats: sfm.DatabaseStats, models: dict[int, pycolmap.Reconstruction]) -> str:
    if stats.features.get(name, 0) < MIN_FEATURES:
        return f"few features ({stats.features.get(name, 0)}): blank, blurry or texture-less"
    if stats.verified_pairs.get(name, 0) == 0:
        return "no verified matches with any other image (no overlap?)"
    for rec in models.values():
        if rec.find_image_with_name(name) is not None and rec.find_image_with_name(name).has_pose:
            return f"registered only in a smaller, separate model ({rec.num_reg_images()} images)"
    return f"matched ({stats.verified_pairs[name]} verified pairs) but the mapper could not register it"


def _report(config: Config, state: _Run, status: str, error: str | None) -> dict[str, Any]:
    rec, stats = state.model, state.stats
    per_image: dict[str, Any] = {}
    for name, original in state.names.items():
        entry: dict[str, Any] = {"original": original}
        if name in state.skipped:
            entry["left_out"] = state.skipped[name]
        if name in state.sizes:
            entry["size"] = list(state.sizes[name])
        sc = state.screens.get(name)
        if sc is not None:
            entry.update(blur=round(sc.blur, 2), overexposed=round(sc.overexposed, 4),
                         underexposed=round(sc.underexposed, 4), flags=sc.flags())  # fmt: skip
        if name in state.duplicates:
            entry["near_duplicate_of"] = state.duplicates[name]
        if stats is not None and name in stats.features:
            entry.update(features=stats.features[name], verified_pairs=stats.verified_pairs[name],
                         matches=stats.matches[name])  # fmt: skip
            image = rec.find_image_with_name(name) if rec is not None else None
            entry["registered"] = bool(image is not None and image.has_pose)
            entry["observations"] = int(image.num_points3D) if entry["registered"] else 0
            if not entry["registered"]:
                entry["why"] = _why_not_registered(name, stats, state.all_models)
        per_image[name] = entry
    registered = rec.num_reg_images() if rec is not None else 0
    total = len(stats.features) if stats is not None else len(state.sizes)
    blur = sorted(state.screens[n].blur for n in state.screens)
    return {
        "status": status,
        "error": error,
        "input": str(config.input),
        "registered": registered,
        "total": total,
        "registered_fraction": round(registered / total, 4) if total else 0.0,
        "not_registered": {n: e["why"] for n, e in per_image.items() if "why" in e},
        "left_out": {Path(n).name: why for n, why in state.skipped.items()},
        "models_found": state.models,
        "mean_reprojection_error_px": round(rec.compute_mean_reprojection_error(), 4) if rec is not None else None,
        "points3D": rec.num_points3D() if rec is not None else 0,
        "cameras": {
            str(c): {
                "model": cam.model.name,
                "width": cam.width,
                "height": cam.height,
                "params": [round(float(v), 6) for v in cam.params],
            }
            for c, cam in (rec.cameras.items() if rec is not None else [])
        },  # fmt: skip
        "principal_point": state.principal_point,
        "timings_s": {k: round(v, 3) for k, v in state.timings.items()},
        "warnings": state.warnings,
        "screening": {
            "blur_median": round(blur[len(blur) // 2], 2) if blur else None,
            "blur_min": round(blur[0], 2) if blur else None,
            "near_duplicates": state.duplicates,
            "exposure_flags": {n: f for n, sc in state.screens.items() if (f := sc.flags())},
        },
        "video": state.video,
        "images": per_image,
        "config": config_to_json(config),
    }


def _summary(console: Console, report: dict[str, Any]) -> None:
    reg, tot = report["registered"], report["total"]
    colour = "green" if tot and reg / tot >= WARN_FRACTION else "yellow"
    err = report["mean_reprojection_error_px"]
    t = sum(report["timings_s"].values())
    console.print(
        f"poses: [{colour}]{reg}/{tot} registered[/{colour}], {report['points3D']} points, "
        f"reprojection {err:.2f} px, {t:.1f} s"
        if err is not None
        else f"poses: {reg}/{tot} registered"
    )
    for w in report["warnings"]:
        console.print(f"[yellow]warning:[/yellow] {w}")


class _Timer:
    def __init__(self, state: _Run, metrics: MetricsLog, progress: Progress | None):
        self.state, self.metrics, self.progress = state, metrics, progress
        self.task = progress.add_task("poses", total=None) if progress is not None else None

    def __call__(self, phase: str):
        timer = self

        class _Phase:
            def __enter__(self):
                if timer.progress is not None:
                    timer.progress.update(timer.task, description=f"poses: {phase}")
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                state = timer.state
                state.timings[phase] = time.perf_counter() - self.t0
                if exc[0] is None:
                    registered = state.model.num_reg_images() if state.model is not None else ""
                    timer.metrics.append(step=len(timer.metrics.rows), seconds=round(time.time() - state.started, 3),
                                         phase=phase, images=len(state.sizes) or len(state.names),
                                         registered=registered)  # fmt: skip
                return False

        return _Phase()


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
    images, db = build / "images", build / "database.db"
    images.mkdir()
    state = _Run(started=time.time())
    metrics = MetricsLog(build / "metrics.csv", ["step", "seconds", "phase", "images", "registered"])
    phase = _Timer(state, metrics, progress)
    matcher = config.matcher if config.matcher != "auto" else ("sequential" if kind == "video" else "exhaustive")
    settings = sfm.SfmSettings(
        max_image_size=config.max_image_size, max_num_features=config.max_num_features,
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
        with phase("features"):
            long_sides = [max(max(state.sizes[n]) for n in g) for g in groups]
            sfm.extract(db, images, groups, long_sides, settings)
            state.stats = sfm.database_stats(db)
            _check_features(state.stats)
        with phase("matching"):
            sfm.match(db, settings)
            state.stats = sfm.database_stats(db)
        with phase("mapping"):
            models = state.all_models = sfm.reconstruct(db, images, build / "models", settings)
            state.models = sorted((m.num_reg_images() for m in models.values()), reverse=True)
            if models:
                state.model = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))
        _check_registered(state, matcher)
        if config.single_camera:
            with phase("principal_point"):
                state.model = _refine_principal_point(state.model, state, config.num_threads)
        (build / "sparse").mkdir()
        state.model.write_binary(str(build / "sparse"))
        shutil.rmtree(build / "models")
        report = _report(config, state, "ok", None)
        write_json(build / "names.json", state.names)
        metrics.save()
        write_json(report_path, report)
        write_manifest(
            build, stage="poses", started=state.started, inputs=[config.input],
            outputs=["images/", "names.json", "database.db", "sparse/", "metrics.csv", "../poses_report.json"],
            used={"matcher": matcher, "principal_point": state.principal_point,
                  "camera_groups": [len(g) for g in groups], "pycolmap": pycolmap.__version__},
            left_out={**state.skipped, **report["not_registered"]}, version=VERSION,
            config=config_to_json(config),
        )  # fmt: skip
        os.replace(build, colmap_dir)
    except BaseException as e:
        shutil.rmtree(build, ignore_errors=True)
        if isinstance(e, Exception):
            try:
                write_json(report_path, _report(config, state, "failed", str(e).splitlines()[0] if str(e) else ""))
            except Exception:  # the report must never hide the original error
                pass
        if isinstance(e, UserError) and previous is not None:
            raise UserError(f"{e} (the earlier model is kept in {previous})") from None
        raise
    if previous is not None:
        shutil.rmtree(previous, ignore_errors=True)
    _summary(console, report)
    return Outputs(
        colmap_dir=colmap_dir, sparse=colmap_dir / "sparse", images=colmap_dir / "images",
        database=colmap_dir / "database.db", report=report_path, registered=report["registered"],
        total=report["total"], mean_reprojection_error=float(report["mean_reprojection_error_px"]),
    )  # fmt: skip


def _check_registered(state: _Run, matcher: str) -> None:
    total = len(state.stats.features)
    reg = state.model.num_reg_images() if state.model is not None else 0
    if reg < MIN_REGISTERED or reg < FAIL_FRACTION * total:
        few = sum(k < MIN_FEATURES for k in state.stats.features.values())
        unmatched = sum(p == 0 for p in state.stats.verified_pairs.values())
        if few > total // 2:
            cause = f"{few} images have under {MIN_FEATURES} features (texture-less or blurry)"
        elif unmatched > total // 2:
            cause = f"{unmatched} images share no verified matches (too little overlap between views)"
        elif len(state.models) > 1:
            cause = f"the scene split into {len(state.models)} separate models {state.models}"
        else:
            cause = "the views could not be chained together"
        also = "matcher=exhaustive or " if matcher != "exhaustive" else ""
        raise UserError(
            f"only {reg} of {total} images registered: {cause}; take more overlapping photos (60-80% overlap, "
            f"small steps around the subject) or try {also}a larger max_image_size / max_num_features"
        )
    if reg < WARN_FRACTION * total:
        state.warnings.append(f"only {reg} of {total} images registered; see poses_report.json for why")
