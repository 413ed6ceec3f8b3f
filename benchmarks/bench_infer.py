"""Inference settings against the exact render (issue 54): for each preset of `model.field_model.Inference`, the
speed and the PSNR cost of rendering a run's test views as `eval` does (the run's downscale, whole views).

    .venv/bin/python -m benchmarks.bench_infer RUN_DIR [--views N] [--threads T] [--json out.jsonl]

Per preset: rays/s over the views (one warm-up view first), the mean PSNR against the photos (as `eval` scores
them: photos with alpha composited on the run's background) and against the exact render (`EXACT`), and the largest
colour difference to it. Presets: `exact` (rays stop below float32's epsilon of light), `t1e-4` / `t1e-3` (rays stop
below that transmittance: colour and opacity off by at most that), `keep1e-3` / `keep3e-3` (colour only samples of
at least that weight and each ray's largest, rescaled: the viewer's coarse rule, at the exact step), and their pairs.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.masks import load_masked_image
from nerfpipe.model import camera_path, load_trained, render_view, resolve_device
from nerfpipe.model.field_model import EXACT, Inference
from nerfpipe.radiance.compositing import over_background
from nerfpipe.radiance.metrics import psnr

PRESETS = {
    "exact": EXACT,
    "t1e-4": Inference(min_transmittance=1e-4),
    "t1e-3": Inference(min_transmittance=1e-3),
    "keep1e-3": Inference(color_keep=1e-3),
    "keep3e-3": Inference(color_keep=3e-3),
    "t1e-4+keep1e-3": Inference(min_transmittance=1e-4, color_keep=1e-3),
    "t1e-3+keep3e-3": Inference(min_transmittance=1e-3, color_keep=3e-3),
    "t1e-2+keep1e-2": Inference(min_transmittance=1e-2, color_keep=1e-2),
    "t1e-3+keep3e-3+step1.5": Inference(min_transmittance=1e-3, color_keep=3e-3, step_scale=1.5),
    "t1e-3+keep3e-3+step2": Inference(min_transmittance=1e-3, color_keep=3e-3, step_scale=2.0),
    "t1e-2+keep1e-2+step1.5": Inference(min_transmittance=1e-2, color_keep=1e-2, step_scale=1.5),
    "t1e-2+keep1e-2+step2": Inference(min_transmittance=1e-2, color_keep=1e-2, step_scale=2.0),
    "t3e-2+keep3e-2+step1.5": Inference(min_transmittance=3e-2, color_keep=3e-2, step_scale=1.5),
    "t1e-2+keep1e-2+step1.75": Inference(min_transmittance=1e-2, color_keep=1e-2, step_scale=1.75),
}


def bench(run_dir: Path, views: int | None, device, presets: list[str] | None = None) -> list[dict]:
    import cv2

    trained = load_trained(run_dir, device)
    scene = trained.scene
    cams = camera_path(scene, "test", downscale=trained.downscale)
    idx = scene.split("test") or scene.split("val")
    picks = range(len(cams.names)) if views is None else np.unique(np.linspace(0, len(idx) - 1, views).round())
    picks = [int(k) for k in picks]
    bg = trained.background.detach().float().cpu().numpy().reshape(3)
    photos = []
    for k in picks:
        intr, photo = cams.intrinsics[k], load_masked_image(scene, idx[k])
        photo = cv2.resize(photo, (intr.w, intr.h), interpolation=cv2.INTER_AREA)
        photos.append(over_background(photo[..., :3], photo[..., 3:], bg) if photo.shape[2] == 4 else photo)
    render_view(trained, cams.intrinsics[picks[0]].scaled(0.25), cams.world_from_cams[picks[0]], device)  # warm-up
    rows, exact = [], None
    for name in ["exact", *[p for p in (presets or PRESETS) if p != "exact"]]:  # exact first: the reference
        infer = PRESETS[name]
        renders, seconds, rays = [], 0.0, 0
        for k in picks:
            intr = cams.intrinsics[k]
            t0 = time.perf_counter()
            renders.append(
                np.clip(render_view(trained, intr, cams.world_from_cams[k], device, infer=infer)["rgb"], 0, 1)
            )
            seconds += time.perf_counter() - t0
            rays += intr.w * intr.h
        exact = renders if exact is None else exact
        pairs = list(zip(renders, exact, strict=True))
        row = {
            "run": str(run_dir),
            "preset": name,
            "views": len(picks),
            "rays_per_s": round(rays / seconds),
            "psnr_vs_photos": round(float(np.mean([psnr(r, p) for r, p in zip(renders, photos, strict=True)])), 3),
            "psnr_vs_exact": round(min(psnr(r, e) for r, e in pairs), 2),
            "largest_rgb_difference": round(max(float(np.abs(r - e).max()) for r, e in pairs), 4),
        }
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--views", type=int, default=None, help="evenly spaced test views (default: all)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--json", type=Path, default=None, help="append the rows to this file")
    ap.add_argument("--presets", nargs="*", choices=sorted(PRESETS), default=None, help="default: every preset")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = bench(args.run_dir, args.views, resolve_device(args.device), args.presets)
    if args.json:
        with args.json.open("a") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
    return rows


if __name__ == "__main__":
    main()
