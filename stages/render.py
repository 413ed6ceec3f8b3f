"""Stage `render`: a trained run -> an H.264 mp4 along a camera path (and optionally the PNG frames).

    nerfpipe render RUN_DIR OUT.mp4 [--path auto|turntable|spiral|test|train] [--frames 120] [--fps 30]
        [--downscale 1] [--elevation DEG] [--radius R] [--outputs rgb,depth,accumulation] [--frames-dir DIR]

Paths (`radiance.paths`): `turntable` orbits the point the training cameras look at (least-squares intersection
of their optical axes) around the scene's +z (or the mean camera up when that disagrees, see
`radiance.paths.up_axis`), radius/elevation = the training cameras' medians unless given; `spiral` is LLFF's
forward-facing path; `test` / `train` replay that split's cameras (their own intrinsics, distortion included,
and a PSNR against the photo per frame in the metrics log). Synthetic paths use the first training camera's
intrinsics without distortion, scaled by 1/downscale.

Outputs stack side by side: rgb | depth (z-depth, turbo over one range for the whole video, from a 1/8-resolution
preview pass: 1st-99th percentile over pixels with opacity >= 0.5) | accumulation (grey).
Next to OUT.mp4: `OUT.metrics.csv` (frame, seconds, rays/s, psnr) and `OUT.manifest.json` (written last).
Cameras and rendering come from the trained-run library (`model`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from data.errors import UserError
from data.progress import NO_PROGRESS, Progress
from data.rundir import MetricsLog, Stopwatch, config_to_json, sidecar, write_manifest
from data.transforms import Scene, load_image
from data.video import colorize, grey, to_uint8, video_writer, write_png
from model import OPAQUE, PATHS, CameraPath, Renderable, camera_path, load_trained, render_view, resolve_device
from radiance.compositing import over_background
from radiance.metrics import psnr

__all__ = ["Config", "Outputs", "OUTPUT_KINDS", "parse_outputs", "run"]

OUTPUT_KINDS = ("rgb", "depth", "accumulation")


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json, checkpoint.pt, ...)."""
    out: Path
    """Output video, `.mp4`."""
    path: Literal["auto", "turntable", "spiral", "test", "train"] = "auto"
    """Camera path: turntable | spiral | test | train; auto: spiral for a forward-facing scene (the cameras
    only saw it from one side), turntable otherwise."""
    frames: int = 120
    """Number of frames of a turntable / spiral (test / train replay every camera of the split)."""
    fps: float = 30.0
    """Frames per second of the video."""
    downscale: float = 1.0
    """Render at 1/downscale of the training camera's resolution."""
    elevation: float | None = None
    """Turntable elevation in degrees above the horizontal plane through the centre (default: training median)."""
    radius: float | None = None
    """Turntable radius in the user's (source) units (default: the training cameras' median distance)."""
    outputs: tuple[str, ...] = ("rgb",)
    """What to show, side by side: any of rgb, depth, accumulation."""
    frames_dir: Path | None = None
    """Also write each frame as PNG here (frame_00000.png, ...)."""
    device: str = "auto"
    """torch device: auto (cuda if available, else cpu), cpu, cuda, cuda:1, ..."""


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


def _depth_range(trained: Renderable, cams: CameraPath, device: torch.device, scale: float) -> tuple[float, float]:
    """1st-99th percentile of opaque z-depth (user units) over a 1/8-resolution preview of up to 16 frames."""
    picks = np.unique(np.linspace(0, len(cams.names) - 1, min(16, len(cams.names))).round().astype(int))
    vals = []
    for k in picks:
        intr = cams.intrinsics[k]
        small = intr.scaled(max(8 / min(intr.w, intr.h), 1 / 8)) if min(intr.w, intr.h) > 8 else intr
        view = render_view(trained, small, cams.world_from_cams[k], device)
        vals.append(view["depth"][view["acc"] >= OPAQUE] / scale)
    v = np.concatenate(vals) if vals else np.zeros(0)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, [1, 99]))
    return (lo, hi) if hi > lo else (lo, lo + 1e-6 + abs(lo) * 1e-3)


def _photo(scene: Scene, i: int, background: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    """The dataset image composited on `background`, or None when its size differs from the render's."""
    img = load_image(scene.image_path(i))
    if img.shape[:2] != size:
        return None
    if img.shape[2] == 4:
        img = over_background(img[..., :3], img[..., 3:], background)
    return img


def run(config: Config, progress: Progress | None = None) -> Outputs:
    started = time.time()
    outputs = parse_outputs(config.outputs)
    out = Path(config.out)
    if out.suffix.lower() != ".mp4":
        raise UserError(f"{out}: expected an .mp4 output path")
    if config.path not in PATHS:
        raise UserError(f"--path: unknown path {config.path!r}; expected one of {', '.join(PATHS)}")
    if not config.fps > 0:
        raise UserError(f"--fps: expected > 0, got {config.fps}")
    device = resolve_device(config.device)
    trained = load_trained(config.run_dir, device)
    scene = trained.scene
    cams = camera_path(scene, config.path, frames=config.frames, downscale=config.downscale,
                       elevation=config.elevation, radius=config.radius)  # fmt: skip
    scale = float(scene.applied_scale)
    lo, hi = _depth_range(trained, cams, device, scale) if "depth" in outputs else (0.0, 1.0)
    background = trained.background.detach().float().cpu().numpy().reshape(3)

    metrics = MetricsLog(sidecar(out, "metrics.csv"), ["step", "seconds", "rays_per_s", "psnr"])
    clock = Stopwatch()
    frame_paths: list[Path] = []
    size = (0, 0)
    progress = progress or NO_PROGRESS
    task = progress.add_task(f"render {config.path}", total=len(cams.names))
    with video_writer(out, fps=config.fps) as video:
        for k in range(len(cams.names)):
            t0 = time.perf_counter()
            view = render_view(trained, cams.intrinsics[k], cams.world_from_cams[k], device)
            seconds = time.perf_counter() - t0
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
                frame_paths.append(write_png(Path(config.frames_dir) / f"frame_{k:05d}.png", frame))
            err = ""
            if cams.frame_indices is not None:
                photo = _photo(scene, cams.frame_indices[k], background, view["rgb"].shape[:2])
                err = "" if photo is None else round(psnr(view["rgb"], photo), 4)
            rays = cams.intrinsics[k].w * cams.intrinsics[k].h
            metrics.append(step=k, seconds=round(clock(), 4), rays_per_s=round(rays / max(seconds, 1e-9)),
                           psnr=err)  # fmt: skip
            progress.advance(task)
    metrics.save()
    manifest = write_manifest(
        out.parent, stage="render", started=started, name=sidecar(out, "manifest.json").name,
        inputs=[Path(config.run_dir) / "checkpoint.pt", Path(config.run_dir) / "config.json"],
        outputs=[out, metrics.path, *frame_paths],
        used={**cams.used, "outputs": list(outputs), "device": str(device), "frames": len(cams.names),
              "fps": config.fps, "size_hw": list(size), "codec": "h264 yuv420p crf 18 (odd sizes padded by edge)",
              **({"depth_range_user_units": [lo, hi], "depth_colormap": "turbo", "depth_background":
                  f"black where accumulation < {OPAQUE}"} if "depth" in outputs else {})},
        config=config_to_json(config),
    )  # fmt: skip
    return Outputs(video=out, frames=tuple(frame_paths), metrics=metrics.path, manifest=manifest,
                   n_frames=len(cams.names), size=(int(size[0]), int(size[1])))  # fmt: skip
