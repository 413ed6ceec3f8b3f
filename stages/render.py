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
This module also holds what `depth` and `eval` share: `load_run`, `resolve_device`, `render_view`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from data.errors import UserError
from data.rundir import MetricsLog, Stopwatch, config_to_json, write_manifest
from data.transforms import Scene, is_forward_facing, load_image
from data.video import colorize, grey, to_uint8, video_writer, write_png
from radiance import paths
from radiance.camera import Intrinsics, generate_rays

__all__ = [
    "Config",
    "Outputs",
    "PATHS",
    "OUTPUT_KINDS",
    "parse_outputs",
    "run",
    "Renderable",
    "load_run",
    "resolve_device",
    "render_view",
    "CameraPath",
    "camera_path",
    "training_intrinsics",
    "sidecar",
]

PATHS = ("auto", "turntable", "spiral", "test", "train")
OUTPUT_KINDS = ("rgb", "depth", "accumulation")
OPAQUE = 0.5
"""Pixels with accumulated opacity below this count as background for depth ranges and depth exports."""


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json, checkpoint.pt, ...)."""
    out: Path
    """Output video, `.mp4`."""
    path: str = "auto"
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


class Renderable(Protocol):
    """What these stages need of `stages.train.load_trained(...)` (see docs/DESIGN.md)."""

    scene: Scene
    background: torch.Tensor

    def render_rays(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> dict[str, torch.Tensor]: ...


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


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise UserError(f"--device: unknown device {name!r} (expected auto, cpu, cuda, cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device: {name} requested but torch sees no CUDA device")
    return dev


def load_run(run_dir: Path, device: torch.device) -> Renderable:
    """`stages.train.load_trained` after checking the run directory exists (UserError otherwise)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: run directory not found")
    if not (run_dir / "checkpoint.pt").is_file():
        raise UserError(f"{run_dir}: no checkpoint.pt (not a finished training run?)")
    from stages.train import load_trained  # local: keeps `render --help` light

    return load_trained(run_dir, device)


@torch.no_grad()
def render_view(trained: Renderable, intr: Intrinsics, world_from_cam: np.ndarray, device: torch.device):
    """Render one camera (scene frame, OpenGL axes). Returns numpy float32 arrays:
    rgb [H, W, 3], depth [H, W] (z-depth of the expected t, scene units), depth_median [H, W] (z-depth of the
    median t), acc [H, W]. Memory: `trained.render_rays` works through the rays in chunks."""
    pose = torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64))
    rays_o, rays_d = generate_rays(intr, pose)  # float64 [R, 3]
    forward = -pose[:3, 2]
    cos = (rays_d @ forward).to(torch.float32)  # t -> z-depth factor
    out = trained.render_rays(rays_o.to(device, torch.float32), rays_d.to(device, torch.float32))
    h, w = intr.h, intr.w

    def grab(key: str, shape: tuple[int, ...]) -> np.ndarray:
        return out[key].detach().float().cpu().reshape(shape).numpy()

    cos_np = cos.reshape(h, w).numpy()
    return {
        "rgb": grab("rgb", (h, w, 3)),
        "depth": grab("depth", (h, w)) * cos_np,
        "depth_median": grab("depth_median", (h, w)) * cos_np,
        "acc": grab("acc", (h, w)),
    }


def training_intrinsics(scene: Scene) -> Intrinsics:
    """The first training camera's intrinsics (what synthetic paths render with, before downscale)."""
    train = scene.split("train") or tuple(range(len(scene.frames)))
    return scene.frame_intrinsics(train[0])


def _scaled(intr: Intrinsics, downscale: float, keep_distortion: bool) -> Intrinsics:
    out = intr.scaled(1.0 / downscale) if downscale != 1 else intr
    if not keep_distortion and out.has_distortion:
        out = Intrinsics(w=out.w, h=out.h, fx=out.fx, fy=out.fy, cx=out.cx, cy=out.cy)
    return out


@dataclass(frozen=True, kw_only=True)
class CameraPath:
    world_from_cams: np.ndarray
    """[N, 4, 4] scene frame, OpenGL axes."""
    intrinsics: tuple[Intrinsics, ...]
    """One per camera."""
    names: tuple[str, ...]
    """A file-name stem per camera."""
    frame_indices: tuple[int, ...] | None
    """Dataset frame index per camera for test/train replays (None for synthetic paths)."""
    used: dict[str, Any]
    """How the path was derived (for the manifest)."""


def camera_path(
    scene: Scene, kind: str, *, frames: int = 120, downscale: float = 1.0, elevation: float | None = None,
    radius: float | None = None,
) -> CameraPath:  # fmt: skip
    """Cameras of a path over a trained run's scene. radius in the user's units (scaled into the scene frame)."""
    if kind not in PATHS:
        raise UserError(f"--path: unknown path {kind!r}; expected one of {', '.join(PATHS)}")
    if kind == "auto":
        kind = "spiral" if is_forward_facing(scene) else "turntable"
    if not downscale > 0:
        raise UserError(f"--downscale: expected > 0, got {downscale}")
    if kind in ("test", "train"):
        idx = scene.split(kind) or (scene.split("val") if kind == "test" else ())
        if not idx:
            raise UserError(f"--path {kind}: the run's scene ({scene.root}) has no {kind} split")
        poses = np.stack([scene.frames[i].world_from_cam for i in idx])
        intr = tuple(_scaled(scene.frame_intrinsics(i), downscale, keep_distortion=True) for i in idx)
        names = tuple(Path(scene.frames[i].file_path).stem for i in idx)
        split = kind if scene.split(kind) else "val"
        return CameraPath(world_from_cams=poses, intrinsics=intr, names=names, frame_indices=tuple(idx),
                          used={"path": kind, "split": split})  # fmt: skip
    if frames < 1:
        raise UserError(f"--frames: expected >= 1, got {frames}")
    train_idx = scene.split("train") or tuple(range(len(scene.frames)))
    train_poses = np.stack([scene.frames[i].world_from_cam for i in train_idx])
    intr = _scaled(training_intrinsics(scene), downscale, keep_distortion=False)
    used: dict[str, Any] = {"path": kind, "intrinsics": "first training camera, no distortion"}
    if kind == "turntable":
        orbit = paths.orbit_from_cameras(train_poses)
        if radius is not None:
            if not radius > 0:
                raise UserError(f"--radius: expected > 0, got {radius}")
            orbit = dataclasses.replace(orbit, radius=radius * scene.applied_scale)
        if elevation is not None:
            if not -90 < elevation < 90:
                raise UserError(f"--elevation: expected degrees in (-90, 90), got {elevation}")
            orbit = dataclasses.replace(orbit, elevation_deg=float(elevation))
        poses = paths.turntable(orbit, frames)
        defaults = [name for name, value in (("radius", radius), ("elevation", elevation)) if value is None]
        used.update(
            centre_scene=orbit.centre.tolist(), up=orbit.up.tolist(), up_reason=paths.up_axis(train_poses)[1],
            radius_scene=orbit.radius, radius_user=orbit.radius / scene.applied_scale,
            elevation_deg=orbit.elevation_deg, from_training_cameras=defaults,
        )  # fmt: skip
    else:
        try:
            poses = paths.spiral(train_poses, frames)
        except ValueError as exc:
            raise UserError(f"--path spiral: {exc}; use --path turntable") from None
        used.update(focus_scene=paths.focus_point(train_poses).tolist(), rotations=2, radii_percentile=90)
    names = tuple(f"frame_{k:05d}" for k in range(len(poses)))
    return CameraPath(world_from_cams=poses, intrinsics=(intr,) * len(poses), names=names, frame_indices=None,
                      used=used)  # fmt: skip


def sidecar(out: Path, what: str) -> Path:
    """`dir/name.mp4` -> `dir/name.<what>` (the manifest / metrics files written next to a file output)."""
    return out.with_name(f"{out.stem}.{what}")


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
        img = img[..., :3] * img[..., 3:] + background * (1 - img[..., 3:])
    return img


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB for images in [0, 1]; capped at 100 dB (identical images)."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


def run(config: Config, progress: Any | None = None) -> Outputs:
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
    trained = load_run(config.run_dir, device)
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
    owns_progress = progress is None
    if owns_progress:
        from rich.progress import Progress

        progress = Progress(transient=True)
        progress.start()
    try:
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
    finally:
        if owns_progress:
            progress.stop()
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
