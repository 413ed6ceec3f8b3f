"""Stage `render`: a trained run, or splats made from one, -> an H.264 mp4 along a camera path (and PNG frames).

    nerfpipe render RUN_DIR|SPLATS.ply OUT.mp4 [--path auto|turntable|arc|trajectory|spiral|test|train|FILE.json]
        [--frames 120] [--fps 30] [--downscale 1] [--max-seconds S] [--elevation DEG] [--radius R]
        [--outputs rgb,depth,accumulation] [--frames-dir DIR]

Paths (`model.camera_path`, maths in `radiance.paths`): `turntable` orbits the point the training cameras look
at (least-squares intersection of their optical axes) around the scene's +z (or the mean camera up when that
disagrees, see `radiance.paths.up_axis`), radius/elevation = the training cameras' medians unless given; `arc`
is the part of that orbit the training cameras cover; `trajectory` follows the training cameras (capture order,
smoothed, splined, resampled at equal arc length) looking at that point; `spiral` is LLFF's forward-facing path;
`test` / `train` replay that split's cameras (their own intrinsics, distortion included, and a PSNR against the
photo per frame in the metrics log). `auto`: spiral for a forward-facing capture, turntable when the training
cameras go round the object (no gap over 90 degrees between their azimuths), trajectory otherwise; the manifest
says which and why (coverage in degrees, largest gap). Synthetic paths use the first training camera's
intrinsics without distortion, scaled by 1/downscale. A `FILE.json` camera path (`data.camera_path`: recorded by
`nerfpipe view` or nerfstudio's camera_path.json) plays every camera in it at the file's size and field of view
(scaled by 1/downscale); --frames, --elevation and --radius do not apply to it.

Time budget (`max_seconds`): rays/s is measured on a small preview (`PREVIEW_VIEWS` path cameras at about
`PREVIEW_RAYS` pixels each; a video with no more pixels than that is rendered as asked, unmeasured); when the
requested frames at the requested size would take longer than what is left of the budget, frames are rendered
smaller (down to `MIN_SHORT_SIDE` pixels on the short side), then fewer (down to `MIN_FRAMES`; a test/train
replay keeps every camera). The manifest's `used.budget` records the measurement, what was asked, what was
chosen and why.

Outputs stack side by side: rgb | depth (z-depth, turbo over one range for the whole video, from a 1/8-resolution
preview pass: 1st-99th percentile over pixels with opacity >= 0.5) | accumulation (grey).
Next to OUT.mp4: `OUT.metrics.csv` (frame, seconds, rays/s, psnr) and `OUT.manifest.json`. The video is encoded
under a hidden temporary name and renamed into place after the manifest (`make`'s target is OUT.mp4); on any
failure (a full disk at the manifest, Ctrl-C, SIGTERM) the temporary and the files this render wrote are deleted
(metrics, manifest, frames), and an earlier OUT.mp4 stays as it was. Frames: at most `MAX_SIDE` px a side and
`MAX_PIXELS` pixels. Cameras and rendering come from the trained-run library (`model`); a splat .ply from `nerfpipe
splat` renders on its run's cameras, rasterised (`model.splat_run`: pinhole); the manifest's `used.input` says which.

Self-check (`OUT.manifest.json` `check`: ok | suspect, `checks`: `data.checks`), from what every frame's render
already returns (opacity per ray), gathered while the video is written:
- `empty_frames`: share of the median frame's pixels with accumulated opacity < `EMPTY_ACC`, at most `MAX_EMPTY`.
  An object on a plain background leaves much of each frame empty, so the limit is high: only a video of (almost)
  nothing fails it (the camera path misses the object, or the field is empty).
- `still_frames` (two frames or more): share of consecutive frame pairs whose mean absolute RGB difference is under
  `STILL_DIFF` (half a grey level of the 8-bit video), at most `MAX_STILL`: a path that does not move, or nothing to
  see.
- `non_finite`: NaN / inf values in the colour, the opacity or (when shown) the depth of opaque pixels: 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.camera_path import MAX_PIXELS, MAX_SIDE
from nerfpipe.data.checks import verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import MetricsLog, Stopwatch, config_to_json, sidecar, write_manifest
from nerfpipe.data.transforms import Scene, load_image
from nerfpipe.data.video import check_output, colorize, grey, removed_on_failure, to_uint8, video_writer, write_png
from nerfpipe.model import OPAQUE, PATHS, CameraPath, Run, camera_path, load_trained, render_view, resolve_device
from nerfpipe.model.cameras import is_path_file
from nerfpipe.model.field_model import inference, inference_record
from nerfpipe.model.splat_run import open_input
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr
from nerfpipe.stages.render.budget import (
    MIN_FPS,
    MIN_FRAMES,
    MIN_SHORT_SIDE,
    PREVIEW_RAYS,
    PREVIEW_VIEWS,
    depth_range,
    fit_budget,
    rays_per_second,
)
from nerfpipe.stages.render.checks import EMPTY_ACC, MAX_EMPTY, MAX_STILL, STILL_DIFF, FrameWatch

__all__ = [
    "Config",
    "Outputs",
    "OUTPUT_KINDS",
    "parse_outputs",
    "parse_path",
    "fit_budget",
    "run",
    "MIN_SHORT_SIDE",
    "MIN_FRAMES",
    "MIN_FPS",
    "PREVIEW_RAYS",
    "PREVIEW_VIEWS",
    "EMPTY_ACC",
    "MAX_EMPTY",
    "STILL_DIFF",
    "MAX_STILL",
]

OUTPUT_KINDS = ("rgb", "depth", "accumulation")


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json, checkpoint.pt, ...), or a splat .ply made from one by `nerfpipe splat`."""
    out: Path
    """Output video, `.mp4`."""
    path: str = "auto"
    """Camera path: auto | turntable | arc | trajectory | spiral | test | train, or a camera-path FILE.json
    (recorded by `nerfpipe view`, or nerfstudio's camera_path.json; docs/camera_path.md). turntable goes all
    the way round, arc covers the part of the orbit the photos cover, trajectory follows the training cameras
    (smoothed); auto: spiral for a forward-facing scene, turntable when the photos go round the object (no
    azimuth gap over 90 degrees), trajectory otherwise."""
    frames: int = 120
    """Number of frames of a synthetic path (test / train replay every camera of the split)."""
    fps: float = 30.0
    """Frames per second of the video."""
    downscale: float = 1.0
    """Render at 1/downscale of the training camera's resolution."""
    max_seconds: float | None = None
    """Time budget in seconds (about): if the frames at this size would take longer, by rays/s measured on a
    small preview render, render them smaller (down to 240 px on the short side), then fewer (down to 24);
    the manifest says what was chosen and why. None: no limit. `make` passes the training run's time."""
    elevation: float | None = None
    """Turntable / arc elevation in degrees above the horizontal plane through the centre (default: training
    median)."""
    radius: float | None = None
    """Turntable / arc radius in the user's (source) units (default: the training cameras' median distance)."""
    outputs: tuple[str, ...] = ("rgb",)
    """What to show, side by side: any of rgb, depth, accumulation."""
    frames_dir: Path | None = None
    """Also write each frame as PNG here (frame_00000.png, ...)."""
    device: str = "auto"
    """torch device: auto (cuda if available, else cpu), cpu, cuda, cuda:1, ..."""
    exact: bool = False
    """Render with rays stopped at float32's epsilon of light and every sample coloured (`model.field_model.EXACT`);
    default: `FAST` (faster, a few hundredths of a dB apart: docs/TRAINING.md "Inference")."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    video: Path
    """The mp4."""
    frames: tuple[Path, ...]
    """PNG frames (empty without frames_dir)."""
    metrics: Path
    """Per-frame timing (and PSNR for test/train) log."""
    manifest: Path
    """Provenance record, written last."""
    n_frames: int
    size: tuple[int, int]
    """(height, width) of one stacked frame before any even-size padding."""


def parse_outputs(text: str | tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """'rgb,depth' -> ('rgb', 'depth'); unknown or empty -> UserError naming the choices."""
    items = [s.strip() for s in text.split(",")] if isinstance(text, str) else [str(s).strip() for s in text]
    items = [s for s in items if s]
    bad = [s for s in items if s not in OUTPUT_KINDS]
    if bad or not items:
        raise UserError(f"--outputs: expected a comma-separated subset of {','.join(OUTPUT_KINDS)}, got {text!r}")
    if len(set(items)) != len(items):
        raise UserError(f"--outputs: {text!r} names an output twice")
    return tuple(items)


def parse_path(text: str) -> str:
    """A built-in path name or a `.json` camera-path file (for the CLI; ValueError lists the choices)."""
    text = text.strip()
    if text in PATHS or is_path_file(text):
        return text
    raise ValueError(f"unknown path {text!r}; expected one of {', '.join(PATHS)} or a FILE.json")


def _photo(scene: Scene, i: int, background: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    """The dataset image composited on `background`, or None when its size differs from the render's."""
    img = load_image(scene.image_path(i))
    if img.shape[:2] != size:
        return None
    if img.shape[2] == 4:
        img = over_background(img[..., :3], img[..., 3:], background)
    return img


def _within_budget(trained: Run, cams: CameraPath, config: Config, device: torch.device, started: float):
    """The path re-made to fit what is left of `config.max_seconds` (see `fit_budget`) -> (cams, budget record)."""
    total = sum(i.w * i.h for i in cams.intrinsics)
    if total <= PREVIEW_VIEWS * PREVIEW_RAYS:
        reason = "rendered as asked: the whole video has no more pixels than the speed preview would"
        return cams, {"max_seconds": config.max_seconds, "rays": total, "reason": reason}
    rate, rays, seconds = rays_per_second(trained, cams, device, inference(config.exact))
    left = config.max_seconds - (time.time() - started)
    per_frame = sum(i.w * i.h for i in cams.intrinsics) / len(cams.intrinsics)
    replay = cams.frame_indices is not None or is_path_file(config.path)  # every camera kept
    scale, frames, reason = fit_budget(
        seconds=max(left, 1e-3),
        rays_per_s=rate,
        rays_per_frame=per_frame,
        frames=len(cams.names),
        short_side=min(min(i.w, i.h) for i in cams.intrinsics),
        drop_frames=not replay,
    )
    asked = {
        "frames": len(cams.names),
        "size_hw": [cams.intrinsics[0].h, cams.intrinsics[0].w],
        "downscale": config.downscale,
    }
    if scale < 1 or frames < len(cams.names):
        cams = camera_path(
            trained.scene,
            config.path,
            frames=frames,
            downscale=config.downscale / scale,
            elevation=config.elevation,
            radius=config.radius,
        )
    chosen = {
        "frames": len(cams.names),
        "size_hw": [cams.intrinsics[0].h, cams.intrinsics[0].w],
        "downscale": round(config.downscale / scale, 4),
    }
    estimate = sum(i.w * i.h for i in cams.intrinsics) / rate
    return cams, {
        "max_seconds": config.max_seconds,
        "seconds_left_after_preview": round(left, 2),
        "preview": {
            "rays_per_s": round(rate),
            "rays": rays,
            "seconds": round(seconds, 3),
            "views": min(PREVIEW_VIEWS, asked["frames"]),
        },
        "asked": asked,
        "chosen": chosen,
        "estimated_render_seconds": round(estimate, 1),
        "reason": reason,
    }


def run(config: Config, progress: Progress | None = None) -> Outputs:
    started = time.time()
    outputs = parse_outputs(config.outputs)
    out = Path(config.out)
    if out.suffix.lower() != ".mp4":
        raise UserError(f"{out}: expected an .mp4 output path")
    if config.path not in PATHS and not is_path_file(config.path):
        raise UserError(f"--path: unknown path {config.path!r}; expected one of {', '.join(PATHS)} or a FILE.json")
    if not config.fps > 0:
        raise UserError(f"--fps: expected > 0, got {config.fps}")
    if config.max_seconds is not None and not config.max_seconds > 0:
        raise UserError(f"--max-seconds: expected > 0, got {config.max_seconds}")
    for path, what in (
        (out, "video"),
        (sidecar(out, "metrics.csv"), "metrics log"),
        (sidecar(out, "manifest.json"), "manifest"),
    ):
        check_output(path, what)
    if config.frames_dir is not None:
        check_output(config.frames_dir, "PNG frames", folder=True)
    device = resolve_device(config.device)
    source = open_input(config.run_dir)
    source.refuse_output(out, "video")
    trained = source.load(device, load_trained)
    scene = trained.scene
    cams = camera_path(
        scene,
        config.path,
        frames=config.frames,
        downscale=config.downscale,
        elevation=config.elevation,
        radius=config.radius,
    )
    w, h = max(i.w for i in cams.intrinsics) * len(outputs), max(i.h for i in cams.intrinsics)
    if max(w, h) > MAX_SIDE or w * h > MAX_PIXELS:
        raise UserError(
            f"downscale: {config.downscale:g} makes frames of {w}x{h} px ({'|'.join(outputs)}): more "
            f"than the {MAX_SIDE} px a side or {MAX_PIXELS} pixels nerfpipe renders; expected a larger "
            "downscale"
        )
    budget: dict = {"max_seconds": config.max_seconds}
    if config.max_seconds is not None:
        cams, budget = _within_budget(trained, cams, config, device, started)
    scale = float(scene.applied_scale)
    lo, hi = depth_range(trained, cams, device, scale) if "depth" in outputs else (0.0, 1.0)
    background = trained.background.detach().float().cpu().numpy().reshape(3)

    metrics = MetricsLog(sidecar(out, "metrics.csv"), ["step", "seconds", "rays_per_s", "psnr"])
    clock, size, progress = Stopwatch(), (0, 0), progress or NO_PROGRESS
    task = progress.add_task(f"render {config.path}", total=len(cams.names))
    fps = config.fps
    asked_frames = budget.get("asked", {}).get("frames")
    if asked_frames and len(cams.names) < asked_frames:
        fps = max(min(config.fps, MIN_FPS), config.fps * len(cams.names) / asked_frames)
        budget["fps"] = {
            "asked": config.fps,
            "chosen": round(fps, 3),
            "reason": f"{len(cams.names)} of {asked_frames} frames: slower, to keep the length asked for "
            f"(at least {min(config.fps, MIN_FPS):g} fps)",
        }
    watch, infer = FrameWatch(shows_depth="depth" in outputs), inference(config.exact)
    # the mp4 is renamed into place when this block ends, after the manifest; on failure the block's files go
    with removed_on_failure(out.parent, config.frames_dir) as written, video_writer(out, fps=fps) as video:
        for k in range(len(cams.names)):
            t0 = time.perf_counter()
            intr, pose = cams.intrinsics[k], cams.world_from_cams[k]
            view = render_view(trained, intr, pose, device, depth=watch.shows_depth, infer=infer)
            seconds = time.perf_counter() - t0
            watch.add(view)
            panels = []
            for kind in outputs:
                if kind == "rgb":
                    panels.append(view["rgb"])
                elif kind == "depth":
                    panels.append(colorize(view["depth"] / scale, lo, hi, valid=view["acc"] >= OPAQUE))
                else:
                    panels.append(grey(view["acc"]))
            frame = to_uint8(np.concatenate(panels, axis=1))
            size = frame.shape[:2]
            video.write(frame)
            if config.frames_dir is not None:
                written.append(write_png(Path(config.frames_dir) / f"frame_{k:05d}.png", frame))
            err = ""
            if cams.frame_indices is not None:
                photo = _photo(scene, cams.frame_indices[k], background, view["rgb"].shape[:2])
                err = "" if photo is None else round(psnr(view["rgb"], photo), 4)
            rays = cams.intrinsics[k].w * cams.intrinsics[k].h
            metrics.append(step=k, seconds=round(clock(), 4), rays_per_s=round(rays / max(seconds, 1e-9)), psnr=err)
            progress.advance(task)
        frame_paths = tuple(written)
        video.finish()
        written.append(metrics.save())
        written.append(
            write_manifest(
                out.parent,
                stage="render",
                started=started,
                name=sidecar(out, "manifest.json").name,
                inputs=source.inputs,
                outputs=[out, metrics.path, *frame_paths],
                used={
                    **cams.used,
                    "input": source.record(),
                    "budget": budget,
                    "inference": inference_record(infer),
                    "outputs": list(outputs),
                    "device": str(device),
                    "frames": len(cams.names),
                    "fps": fps,
                    "size_hw": list(size),
                    "codec": "h264 yuv420p crf 18 (odd sizes padded by edge)",
                    **(
                        {
                            "depth_range_user_units": [lo, hi],
                            "depth_colormap": "turbo",
                            "depth_background": f"black where accumulation < {OPAQUE}",
                        }
                        if "depth" in outputs
                        else {}
                    ),
                },
                config=config_to_json(config),
                **verdict(watch.checks()),
            )
        )
    return Outputs(
        video=out,
        frames=frame_paths,
        metrics=metrics.path,
        manifest=written[-1],
        n_frames=len(cams.names),
        size=(int(size[0]), int(size[1])),
    )
