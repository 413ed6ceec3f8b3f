"""Stage `depth`: a trained run -> depth maps in the user's units for a set of views.

    nerfpipe depth RUN_DIR OUT_DIR [--views test|train|turntable] [--kind expected|median] [--video]

Depth is z-depth (along each camera's optical axis) in the user's (source) units: the scene-frame depth divided
by `applied_scale` (the rotation/translation of `applied_transform` do not change distances). `expected` is the
z-depth of the weight-averaged ray distance, `median` of the distance where accumulated weight reaches 1/2.
Background: pixels whose accumulated opacity is below `acc_threshold` (default 0.5: the ray is more likely to
miss than to hit) have no depth; they are 0 in every depth output (the nerfstudio / 16-bit PNG convention
"0 = no depth"); `accumulation/` keeps the opacity so another threshold can be applied later.

Outputs under OUT_DIR, per view NAME (image stem, or frame_00000... for the turntable):
  depth/NAME.npy          float32 [H, W] z-depth, user units, 0 = background
  depth_mm/NAME.png       uint16 millimetres (= user units x 1000, assuming metres), rounded, clipped to 65535
  depth_color/NAME.png    turbo over one range for every view (1st-99th percentile), colour bar in user units
  accumulation/NAME.png   uint8 grey opacity
  cameras.json            each view's camera in the source frame (OpenGL world_from_cam) + intrinsics
  depth.mp4               (--video) the coloured depth maps as a video
  metrics.csv, manifest.json (written last)

Self-check (manifest.json `check`: ok | suspect, `checks`: `data.checks`), from the renders the maps come from:
- `depth_coverage`: share of the median view's pixels with depth (accumulation >= `acc_threshold`, finite, > 0), at
  least `MIN_COVERAGE`: an object on a plain background leaves much of a view without depth, only (almost) none is
  suspect (views that miss the object, or an empty field).
- `depth_beyond_far`: share of the pixels with depth whose ray distance exceeds the scene's far bound
  (transforms.json `far`: the farthest sparse point, the dataset's bounds, or the box seen from the cameras), at
  most `MAX_BEYOND_FAR`: most of the depth lies where the capture says nothing is (background at infinity,
  fog). Only for runs whose rays march past that bound (contracted and NDC runs); a box run's rays stop there,
  so the check is left out (manifest `left_out`).
- `non_finite`: pixels whose opacity, or whose depth where it is opaque enough, is NaN / inf: 0.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from nerfpipe.data.atomic import atomic_path, write_json
from nerfpipe.data.checks import Check, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import (
    MetricsLog,
    Stopwatch,
    config_to_json,
    output_folder,
    refuse_output_inside,
    write_manifest,
)
from nerfpipe.data.transforms import intrinsics_dict
from nerfpipe.data.video import colorize, depth_legend_png, to_uint8, video_writer, write_png
from nerfpipe.model import camera_path, load_trained, render_view, resolve_device
from nerfpipe.model.field_model import inference, inference_record
from nerfpipe.model.view_cache import open_view_cache
from nerfpipe.radiance.camera import Intrinsics, generate_rays

__all__ = ["Config", "Outputs", "VIEWS", "KINDS", "run", "depth_mm"]

VIEWS = ("test", "train", "turntable")
KINDS = ("expected", "median")
MIN_COVERAGE = 0.05
"""Self-check: at least this share of the median view's pixels has depth (the test sphere: a tenth)."""
MAX_BEYOND_FAR = 0.5
"""Self-check: at most this share of the pixels with depth may lie beyond the scene's far bound."""


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory."""
    out_dir: Path
    """Folder for the depth maps (created)."""
    views: Literal["test", "train", "turntable"] = "test"
    """Which cameras: test (the held-out split; val if there is no test split) | train | turntable."""
    kind: Literal["expected", "median"] = "expected"
    """expected (weight-averaged distance) | median (distance at half the accumulated weight)."""
    frames: int = 120
    """Turntable frames (views=turntable only)."""
    downscale: float | None = None
    """Render at 1/downscale of each camera's resolution (None: the factor the run trained at, 1 for runs that
    kept full-size images; `--downscale 1` renders full size)."""
    acc_threshold: float = 0.5
    """Pixels with accumulated opacity below this are background: depth 0."""
    video: bool = False
    """Also write depth.mp4 of the coloured depth maps."""
    fps: float = 30.0
    """Frames per second of depth.mp4."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""
    exact: bool = False
    """Render with rays stopped at float32's epsilon of light (`model.field_model.EXACT`); default: `FAST`, as eval
    renders the test views (their depth then comes from eval's renders: the run's render cache)."""
    overwrite: bool = False
    """Replace an earlier output in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    names: tuple[str, ...]
    depth: tuple[Path, ...]
    """depth/NAME.npy per view."""
    depth_mm: tuple[Path, ...]
    depth_color: tuple[Path, ...]
    accumulation: tuple[Path, ...]
    cameras: Path
    video: Path | None
    depth_range: tuple[float, float]
    """Colour range of depth_color / depth.mp4, user units."""
    manifest: Path


def depth_mm(depth_user: np.ndarray) -> np.ndarray:
    """Depth in metres [H, W] -> uint16 millimetres (0 stays 0 = no depth; clipped to 65535)."""
    mm = np.rint(np.nan_to_num(np.asarray(depth_user, np.float64), nan=0.0, posinf=0.0, neginf=0.0) * 1000.0)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def _write_npy(path: Path, arr: np.ndarray) -> Path:
    with atomic_path(path, suffix=".npy") as tmp, open(tmp, "wb") as f:
        np.save(f, arr)
    return path


def _global_range(paths: list[Path], max_samples: int = 1_000_000) -> tuple[float, float]:
    """1st-99th percentile of the non-zero depth over every map (subsampled), without holding them all."""
    per_map = max(1, max_samples // max(1, len(paths)))
    vals = []
    for p in paths:
        d = np.load(p, mmap_mode="r", allow_pickle=False).reshape(-1)
        step = max(1, d.size // per_map)
        v = np.asarray(d[::step])
        vals.append(v[v > 0])
    v = np.concatenate(vals) if vals else np.zeros(0)
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, [1, 99]))
    return (lo, hi) if hi > lo else (lo, lo + max(1e-6, abs(lo) * 1e-3))


def _far_bound(trained: Any) -> float | None:
    """The scene's far bound (scene units) when the run's rays march past it (contracted, NDC), else None."""
    far = float(trained.scene.far)
    marched = float(trained.far)
    return far if math.isfinite(far) and marched > far * (1 + 1e-6) else None


def _ray_distance(z: np.ndarray, intr: Intrinsics, world_from_cam: np.ndarray) -> np.ndarray:
    """z-depth [H, W] (scene units) -> distance along each pixel's ray [H, W] (`render_view`'s cos factor undone)."""
    pose = torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64))
    _, rays_d = generate_rays(intr, pose)  # [H * W, 3] unit
    cos = (rays_d @ -pose[:3, 2]).reshape(z.shape).numpy()
    return z / np.maximum(cos, 1e-9)


class _DepthWatch:
    """The self-check's figures (module doc), gathered view by view."""

    def __init__(self, far: float | None) -> None:
        self.far = far
        self.coverage: list[float] = []  # per view: share of pixels with depth
        self.valid = self.beyond = self.non_finite = 0

    def add(
        self,
        view: dict[str, np.ndarray],
        z: np.ndarray,
        valid: np.ndarray,
        opaque: np.ndarray,
        intr: Intrinsics,
        world_from_cam: np.ndarray,
    ) -> None:
        """z: the exported kind's z-depth [H, W] (scene units); valid: pixels with depth; opaque: acc >= threshold."""
        self.non_finite += int((~np.isfinite(view["acc"]) | (opaque & ~np.isfinite(z))).sum())
        self.coverage.append(float(valid.mean()))
        self.valid += int(valid.sum())
        if self.far is not None and valid.any():
            self.beyond += int((_ray_distance(z, intr, world_from_cam)[valid] > self.far).sum())

    def checks(self) -> tuple[list[Check], dict[str, str]]:
        """(checks, left_out: the checks that do not apply and why)."""
        out = [
            Check.lower(
                "depth_coverage",
                float(np.median(self.coverage)) if self.coverage else math.nan,
                MIN_COVERAGE,
                "the median view has (almost) no depth: the views miss the object, or the field is empty",
            )
        ]
        left_out = {}
        if self.far is None:
            left_out["check depth_beyond_far"] = "the run's rays stop at the scene's far bound (box run) or it has none"
        elif not self.valid:
            left_out["check depth_beyond_far"] = "no pixel has depth"
        else:
            out.append(
                Check.upper(
                    "depth_beyond_far",
                    self.beyond / self.valid,
                    MAX_BEYOND_FAR,
                    "most of the depth lies beyond the scene's far bound, where the capture saw nothing: background or "
                    "fog at infinity, not the scene",
                )
            )
        out.append(
            Check.upper(
                "non_finite",
                self.non_finite,
                0,
                "NaN or inf opacity or depth: the field's output is broken there (written as 0 = no depth)",
            )
        )
        return out, left_out


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Hold out_dir (one writer; an earlier output needs --overwrite) and run the stage (`_run`)."""
    refuse_output_inside(config.out_dir, config.run_dir, "depth output")
    with output_folder(config.out_dir, overwrite=config.overwrite):
        return _run(config, progress)


def _run(config: Config, progress: Progress | None = None) -> Outputs:
    started = time.time()
    if config.views not in VIEWS:
        raise UserError(f"--views: expected one of {', '.join(VIEWS)}, got {config.views!r}")
    if config.kind not in KINDS:
        raise UserError(f"--kind: expected one of {', '.join(KINDS)}, got {config.kind!r}")
    if not 0 <= config.acc_threshold <= 1:
        raise UserError(f"--acc-threshold: expected a value in [0, 1], got {config.acc_threshold}")
    out_dir = Path(config.out_dir)
    device = resolve_device(config.device)
    trained = load_trained(config.run_dir, device)
    scene = trained.scene
    if config.downscale is not None and not config.downscale > 0:
        raise UserError(f"--downscale: expected > 0, got {config.downscale}")
    downscale = config.downscale or trained.downscale
    cams = camera_path(scene, config.views, frames=config.frames, downscale=downscale)
    scale = float(scene.applied_scale)
    key = "depth" if config.kind == "expected" else "depth_median"

    metrics = MetricsLog(out_dir / "metrics.csv", ["step", "seconds", "rays_per_s", "background_fraction"])
    clock = Stopwatch()
    files: dict[str, list[Path]] = {"depth": [], "depth_mm": [], "accumulation": []}
    cameras_doc: dict[str, Any] = {}
    progress = progress or NO_PROGRESS
    task = progress.add_task(f"depth {config.views}", total=2 * len(cams.names))
    watch = _DepthWatch(_far_bound(trained))
    cache = open_view_cache(Path(config.run_dir)) if Path(config.run_dir).is_dir() else None
    cached = 0  # views taken from the run's render cache (eval's renders of the test views)
    infer = inference(config.exact)
    for k, name in enumerate(cams.names):
        intr, pose = cams.intrinsics[k], cams.world_from_cams[k]
        t0 = time.perf_counter()
        view = cache.get(intr, pose, infer) if cache is not None else None
        cached += view is not None
        if view is None:
            view = render_view(trained, intr, pose, device, infer=infer)
        seconds = time.perf_counter() - t0
        opaque = view["acc"] >= config.acc_threshold
        valid = opaque & np.isfinite(view[key]) & (view[key] > 0)
        watch.add(view, view[key], valid, opaque, intr, pose)
        depth = np.where(valid, view[key] / scale, 0.0).astype(np.float32)
        files["depth"].append(_write_npy(out_dir / "depth" / f"{name}.npy", depth))
        files["depth_mm"].append(write_png(out_dir / "depth_mm" / f"{name}.png", depth_mm(depth)))
        files["accumulation"].append(write_png(out_dir / "accumulation" / f"{name}.png", to_uint8(view["acc"])))
        cameras_doc[name] = {
            "world_from_cam": scene.source_world_from_cam(pose).tolist(),
            **intrinsics_dict(intr, angles=False),
        }
        metrics.append(
            step=k,
            seconds=round(clock(), 4),
            rays_per_s=round(intr.w * intr.h / max(seconds, 1e-9)),
            background_fraction=round(float(1 - valid.mean()), 6),
        )
        progress.advance(task)

    lo, hi = _global_range(files["depth"])
    color_paths: list[Path] = []
    video_path = out_dir / "depth.mp4" if config.video else None
    with _maybe_video(video_path, config.fps) as video:
        for k, name in enumerate(cams.names):
            depth = np.load(files["depth"][k], allow_pickle=False)
            rgb = colorize(depth, lo, hi, valid=depth > 0)
            color_paths.append(
                depth_legend_png(out_dir / "depth_color" / f"{name}.png", rgb, lo, hi, "z-depth (user units)")
            )
            if video is not None:
                video.write(to_uint8(rgb))
            progress.advance(task)

    cameras_path = write_json(
        out_dir / "cameras.json",
        {
            "convention": "world_from_cam 4x4 in the source (user) frame, OpenGL camera axes (x right, y up, looking "
            "down -z); depth/NAME.npy is z-depth along -z in the same units; intrinsics in pixels",
            "frames": cameras_doc,
        },
    )
    metrics.save()
    checks, left_out = watch.checks()
    manifest = write_manifest(
        out_dir,
        stage="depth",
        started=started,
        left_out=left_out,
        inputs=[Path(config.run_dir) / "checkpoint.pt", Path(config.run_dir) / "config.json"],
        outputs=[
            *files["depth"],
            *files["depth_mm"],
            *color_paths,
            *files["accumulation"],
            cameras_path,
            metrics.path,
            *([video_path] if video_path else []),
        ],
        used={
            **cams.used,
            "kind": config.kind,
            "downscale": downscale,
            "device": str(device),
            "views": len(cams.names),
            "views_from_render_cache": cached,
            "inference": inference_record(infer),
            "render_cache": "the run's renders/ folder (model.view_cache): views `eval` rendered are not rendered "
            "again",
            "units": "user (source) units: scene depth / applied_scale",
            "applied_scale": scale,
            "background": f"accumulation < {config.acc_threshold} -> depth 0",
            "depth_mm": "round(depth * 1000), clipped to 65535 (assumes the user's units are metres)",
            "color_range_user_units": [lo, hi],
            "colormap": "turbo",
        },
        config=config_to_json(config),
        **verdict(checks),
    )
    return Outputs(
        out_dir=out_dir,
        names=cams.names,
        depth=tuple(files["depth"]),
        depth_mm=tuple(files["depth_mm"]),
        depth_color=tuple(color_paths),
        accumulation=tuple(files["accumulation"]),
        cameras=cameras_path,
        video=video_path,
        depth_range=(lo, hi),
        manifest=manifest,
    )


def _maybe_video(path: Path | None, fps: float):
    return video_writer(path, fps=fps) if path is not None else contextlib.nullcontext()
