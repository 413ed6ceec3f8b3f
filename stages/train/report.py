"""What `train` writes about a finished run: the PSNR-vs-time plot, the manifest's used / left_out records, and
the per-image report (`per_view_report`): every training view's PSNR, the worst listed, and a contact sheet.

Per-image report (`per_view.json`, `per_view_worst.png`): after training, each training view is rendered at a
low resolution (the run's images shrunk further so that all of them cost about PER_VIEW_FRACTION of the training
time at the measured render speed; long side between PER_VIEW_MIN_SIDE and PER_VIEW_MAX_SIDE px; where even the
smallest renders of every view would take over max(that, PER_VIEW_FLOOR_SECONDS), evenly spaced views that fit,
`views_rendered` of `views_total`) and compared with
its photo shrunk the same way (area filter; masks and alpha composited on the evaluation colour, like the test
PSNR). A view far below the others (SUSPECT_DB under the median) is one the field could not explain: blurred,
occluded, badly exposed or mis-posed. The sheet shows the worst views: photo | render | error (x4), one per row.
"""

from __future__ import annotations

import math
import os
import resource
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from nerfpipe.data.atomic import atomic_path, write_bytes, write_json
from nerfpipe.data.masks import load_masked_image
from nerfpipe.data.transforms import Scene, is_forward_facing
from nerfpipe.model.methods import TrainModel
from nerfpipe.radiance.camera import generate_rays
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr_from_mse
from nerfpipe.stages.train.fog import ViewDepth

if TYPE_CHECKING:
    from nerfpipe.stages.train.loop import Loop

__all__ = ["plot_psnr", "used_and_left_out", "per_view_report", "PER_VIEW_FRACTION"]

PER_VIEW_FRACTION = 0.03
"""The per-image report's render budget, as a fraction of the training seconds."""
PER_VIEW_MIN_SIDE, PER_VIEW_MAX_SIDE = 24, 128
"""Long side (px) of the per-image report's renders: at least, at most."""
PER_VIEW_FLOOR_SECONDS = 10.0
"""Seconds the report may take whatever the budget; where every view at the smallest side would take longer (a
slow method: the paper's NeRF renders a 24-px view in seconds), evenly spaced views that fit are rendered."""
SUSPECT_DB = 3.0
"""A view this many dB under the median PSNR is listed as suspect."""
WORST = 6
"""Views on the contact sheet."""


def plot_psnr(path: Path, rows: list[dict], title: str) -> None:
    """train and test PSNR against wall-clock seconds, from metrics.csv rows, as a PNG (atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for key, style in (("train_psnr", "-"), ("test_psnr", "o-")):
        pts = [(float(r["seconds"]), float(r[key])) for r in rows if r.get(key) not in (None, "")]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=key.replace("_", " "), markersize=3)
    ax.set_xlabel("wall-clock seconds")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def used_and_left_out(
    *,
    scene: Scene,
    loop: Loop,
    seconds: float,
    train_idx: tuple[int, ...],
    test_idx: tuple[int, ...],
    chosen: list[int],
    stride: int,
    test_psnr: float | None,
) -> tuple[dict[str, Any], dict[str, str]]:
    """The manifest's record of what the finished `loop` used and what it left out (and why)."""
    model, device, batch_rays, steps = loop.model, loop.device, loop.config.batch_rays, loop.step
    samples_per_ray = loop.samples_per_ray
    peak = torch.cuda.max_memory_allocated() if device.type == "cuda" else None
    described = model.describe()
    used: dict[str, Any] = {
        "method": loop.method.name,
        "batch_rays": batch_rays,
        **{k: v for k, v in described.items() if k not in ("scene_model", "space")},
        "device": str(device),
        "cpu_threads": torch.get_num_threads() if device.type == "cpu" else None,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),  # data.cpu_load: PASSIVE when the CPU was busy
        "steps": steps,
        "train_seconds": round(seconds, 3),
        "train_views": len(train_idx),
        "test_views": len(test_idx),
        "test_psnr": test_psnr,
        "test_views_scored": [test_idx[v] for v in chosen],
        "background": model.background.describe(),
        "scene_type": "forward-facing" if is_forward_facing(scene) else "bounded / 360",
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_cuda_mb": round(peak / 2**20, 1) if peak is not None else None,
        "samples_per_ray": round(samples_per_ray, 2),
    }
    left_out: dict[str, str] = {}
    if model.space is not None:
        used["scene_model"] = model.space.name
        used["space"] = model.space.describe()
        left_out |= model.space.left_out(is_forward_facing(scene))
    used["world_size"] = 1 if loop.parallel is None else loop.parallel.world.size
    if loop.parallel is not None:
        used["data_parallel"] = loop.parallel.describe()
    else:
        left_out["data_parallel"] = "one process (torchrun --nproc-per-node N ... shares each step's rays among N)"
    if not test_idx:
        left_out["test_psnr"] = "scene has no test or val split"
    else:
        pixels = "whole images" if stride == 1 else f"every {_ordinal(stride)} pixel"
        used["test_psnr_scored"] = {
            "views": len(chosen),
            "of": len(test_idx),
            "pixel_stride": stride,
            "words": f"{len(chosen)} of {len(test_idx)} test views, {pixels}",
        }
        if len(chosen) < len(test_idx):
            left_out["test_views"] = (
                f"test PSNR on {len(chosen)} of {len(test_idx)} views (final_eval_views): `eval` scores them all"
            )
    if "occupancy_skip_fraction" not in described:
        left_out["occupancy_grid"] = f"the {loop.method.name} method does not march an occupancy grid"
    return used, left_out


def _ordinal(k: int) -> str:
    return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def _view_image(scene: Scene, i: int, w: int, h: int) -> np.ndarray:
    """Frame i's photo (mask applied) shrunk to w x h (area filter): float32 [h, w, 4]."""
    import cv2

    img = load_masked_image(scene, i)
    if img.shape[-1] == 3:
        img = np.concatenate([img, np.ones_like(img[..., :1])], axis=-1)
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)


@torch.no_grad()
def _render(
    model: TrainModel, intr, world_from_cam: np.ndarray, bg: torch.Tensor, device
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The field's colour [h, w, 3], depth and opacity [h, w] (None where the method renders none) of every
    pixel of `intr` (rows first), float32."""
    o, d = generate_rays(intr, torch.as_tensor(world_from_cam, dtype=torch.float64))
    o, d = o.float().to(device), d.float().to(device)
    outs = [
        model.render(o[k : k + model.chunk], d[k : k + model.chunk], bg, train=False)
        for k in range(0, o.shape[0], model.chunk)
    ]
    rgb = torch.cat([out["rgb"] for out in outs]).clamp(0, 1).cpu().numpy().reshape(intr.h, intr.w, 3)
    per_pixel = [
        torch.cat([out[key] for out in outs]).float().cpu().numpy().reshape(intr.h, intr.w)
        if all(key in out for out in outs)
        else None
        for key in ("depth", "acc")
    ]
    return rgb, per_pixel[0], per_pixel[1]


def _shrink(scene: Scene, train_idx: tuple[int, ...], downscale: float, rays: float) -> float:
    """Factor (>= the run's downscale) at which the training views hold about `rays` pixels in all, the long
    side kept within [PER_VIEW_MIN_SIDE, PER_VIEW_MAX_SIDE]."""
    pixels = sum(scene.frame_intrinsics(i).w * scene.frame_intrinsics(i).h for i in train_idx)
    long_side = max(max(scene.frame_intrinsics(i).w, scene.frame_intrinsics(i).h) for i in train_idx)
    factor = max(downscale, math.sqrt(pixels / max(rays, 1.0)), long_side / PER_VIEW_MAX_SIDE)
    return min(factor, max(downscale, long_side / PER_VIEW_MIN_SIDE))


def _affordable(scene: Scene, train_idx: tuple[int, ...], factor: float, rays: float) -> tuple[int, ...]:
    """Every training view where all of them at downscale `factor` hold at most `rays` pixels; else as many
    evenly spaced ones as do (at least one)."""
    pixels = [scene.frame_intrinsics(i).scaled(1 / factor) for i in train_idx]
    per_view = sum(p.w * p.h for p in pixels) / len(pixels)
    count = max(1, min(len(train_idx), int(rays // max(per_view, 1.0))))
    if count == len(train_idx):
        return train_idx
    return tuple(train_idx[round(k)] for k in np.linspace(0, len(train_idx) - 1, count))


def _label(img: np.ndarray, text: str) -> np.ndarray:
    """uint8 [h, w, 3] RGB with a 14-px caption strip above it."""
    import cv2

    strip = np.full((14, img.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (2, 11), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


def _contact_sheet(rows: list[tuple[str, float, np.ndarray, np.ndarray]], height: int = 128) -> bytes:
    """PNG bytes: per row (name, psnr, photo, render) the photo | render | |error| x 4, scaled to `height` px."""
    import cv2

    lines = []
    for name, psnr, photo, render in rows:
        err = np.clip(np.abs(photo - render) * 4, 0, 1)
        scale = height / photo.shape[0]
        tiles = []
        for tile, what in ((photo, f"{name}  {psnr:.1f} dB"), (render, "render"), (err, "|error| x4")):
            u8 = np.round(np.clip(tile, 0, 1) * 255).astype(np.uint8)
            u8 = cv2.resize(u8, (round(tile.shape[1] * scale), height), interpolation=cv2.INTER_NEAREST)
            tiles.append(_label(u8, what))
        lines.append(np.concatenate(tiles, axis=1))
    width = max(line.shape[1] for line in lines)
    sheet = np.concatenate(
        [np.pad(line, ((0, 2), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    )
    ok, buf = cv2.imencode(".png", sheet[..., ::-1].copy())
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def per_view_report(
    run_dir: Path,
    model: TrainModel,
    scene: Scene,
    train_idx: tuple[int, ...],
    downscale: float,
    train_seconds: float,
    rays_per_second: float | None,
    device: torch.device,
    fraction: float = PER_VIEW_FRACTION,
) -> tuple[dict[str, Any], tuple[ViewDepth, ...]]:
    """Write run_dir/per_view.json and per_view_worst.png (module docstring); returns the manifest's summary
    (`files` lists the two files) and each rendered view's depth and opacity (`fog.ViewDepth`; none where the
    method renders no depth). `rays_per_second`: the render speed measured in training (None: measured on the
    first view)."""
    t0 = time.perf_counter()
    model.train_mode(False)
    bg = model.background.eval_colour().detach()
    budget = fraction * train_seconds
    first = scene.frame_intrinsics(train_idx[0]).scaled(1 / _shrink(scene, train_idx, downscale, 0))
    if rays_per_second is None:  # one small view, timed
        t = time.perf_counter()
        _render(model, first, scene.frames[train_idx[0]].world_from_cam, bg, device)
        rays_per_second = first.w * first.h / max(time.perf_counter() - t, 1e-6)
    factor = _shrink(scene, train_idx, downscale, budget * rays_per_second)
    picked = _affordable(scene, train_idx, factor, max(budget, PER_VIEW_FLOOR_SECONDS) * rays_per_second)
    views, sheet_rows, depths = [], {}, []
    bg_np = bg.cpu().numpy()
    for i in picked:
        intr = scene.frame_intrinsics(i).scaled(1 / factor)
        photo = _view_image(scene, i, intr.w, intr.h)
        target = over_background(photo[..., :3], photo[..., 3:], bg_np)
        render, depth, acc = _render(model, intr, scene.frames[i].world_from_cam, bg, device)
        if depth is not None and acc is not None:
            depths.append(ViewDepth(intr=intr, world_from_cam=scene.frames[i].world_from_cam, depth=depth, acc=acc))
        mse = float(np.mean((render - target) ** 2))
        name = Path(scene.frames[i].file_path).name
        views.append(
            {
                "frame": i,
                "file": scene.frames[i].file_path,
                "psnr": round(psnr_from_mse(mse), 3),
                "masked": scene.frames[i].mask_path is not None,
            }
        )
        sheet_rows[i] = (name, views[-1]["psnr"], target, render)
    worst = sorted(views, key=lambda v: v["psnr"])
    median = float(np.median([v["psnr"] for v in views]))
    suspect = [v["file"] for v in worst if v["psnr"] < median - SUSPECT_DB]
    shown = worst[:WORST]
    write_bytes(run_dir / "per_view_worst.png", _contact_sheet([sheet_rows[v["frame"]] for v in shown]))
    seconds = time.perf_counter() - t0
    doc = {
        "what": "PSNR of each training view (views_rendered of views_total: evenly spaced where a slow method "
        "cannot render them all in budget) rendered at low resolution against its photo (shrunk the same way, "
        "masks applied, composited on the evaluation colour); worst first",
        "resolution": {"downscale": round(factor, 3), "example_size": [intr.w, intr.h]},
        "budget_seconds": round(budget, 3),
        "seconds": round(seconds, 3),
        "median_psnr": round(median, 3),
        "views_rendered": len(picked),
        "views_total": len(train_idx),
        "suspect": suspect,
        "suspect_rule": f"PSNR more than {SUSPECT_DB:g} dB under the median: blurred, occluded, badly exposed or "
        "mis-posed photos; the sheet per_view_worst.png shows photo | render | error x4",
        "sheet": [v["file"] for v in shown],
        "views": worst,
    }
    write_json(run_dir / "per_view.json", doc)
    summary = {
        "files": ["per_view.json", "per_view_worst.png"],
        "median_psnr": doc["median_psnr"],
        "worst": [[v["file"], v["psnr"]] for v in shown[:3]],
        "suspect": suspect,
        "views_total": len(train_idx),
        "views_rendered": len(picked),
        "seconds": doc["seconds"],
        "budget_seconds": doc["budget_seconds"],
        "downscale": round(factor, 3),
    }
    return summary, tuple(depths)
