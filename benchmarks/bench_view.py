"""Viewer render speed: rays/s of `render`'s path (`model.render_view`) against the viewer's preview
(`model.preview.render_preview`, refined and coarse) on evenly spaced test cameras of a trained run, at 256 px.

    .venv/bin/python -m benchmarks.bench_view RUN_DIR [--size 256] [--threads 2] [--views 8] [--repeats 2] [--rounds 2]
        [--device auto|cpu|cuda]      (issue 16's GPU goal: --device cuda --size 800, >= 30 frames/s coarse)

Each kind renders every chosen view `repeats` times in a row, as the viewer does (a stream of coarse frames while
the camera moves); the kinds take turns `rounds` times, so that a machine whose speed drifts slows them alike.
Prints per kind the median and largest seconds per frame and rays/s at the median; then how far the previews are
from `render_view` (largest rgb difference of the refined preview: early ray termination, at most about 1e-3) and
the coarse preview's PSNR against the refined one. Goal (issue 16): the coarse 256 px preview in <= 0.5 s on 2 CPU
cores.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from nerfpipe.model import load_trained, render_view, resolve_device
from nerfpipe.model.cameras import camera_path
from nerfpipe.model.preview import render_preview


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="auto, cpu, cuda, cuda:N")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    dev = resolve_device(args.device)
    trained = load_trained(args.run_dir, dev)
    cams = camera_path(trained.scene, "test")
    intr = cams.intrinsics[0].scaled(args.size / max(cams.intrinsics[0].w, cams.intrinsics[0].h))
    views = np.unique(np.linspace(0, len(cams.names) - 1, args.views).round().astype(int)).tolist()
    render_view(trained, intr.scaled(0.1), cams.world_from_cams[0], dev)  # warm-up (caches, allocator)
    rays = intr.w * intr.h
    kinds = {
        "render_view (render stage)": lambda k: render_view(trained, intr, cams.world_from_cams[k], dev)["rgb"],
        "preview, refined": lambda k: render_preview(trained, intr, cams.world_from_cams[k])["rgb"],
        "preview, coarse": lambda k: render_preview(trained, intr, cams.world_from_cams[k], coarse=True)["rgb"],
    }
    times: dict[str, list[float]] = {name: [] for name in kinds}
    images: dict[str, dict[int, np.ndarray]] = {name: {} for name in kinds}
    for _ in range(args.rounds):
        for name, fn in kinds.items():
            for k in views:
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    images[name][k] = fn(k)
                    times[name].append(time.perf_counter() - t0)
    res: dict = {"size": [intr.w, intr.h], "views": views, "threads": args.threads, "device": str(dev)}
    for name, ts in times.items():
        med = statistics.median(ts)
        res[name] = {"median_s": round(med, 3), "max_s": round(max(ts), 3), "rays_per_s": round(rays / med)}
        print(
            f"{name} on {dev}: {intr.w}x{intr.h}, {len(ts)} frames: median {med:.3f} s (largest {max(ts):.3f} s), "
            f"{rays / med:.0f} rays/s, {1 / med:.1f} frames/s",
            flush=True,
        )
    ref, fine, coarse = (images[name] for name in kinds)
    diff = max(float(np.abs(fine[k] - ref[k]).max()) for k in views)
    mse = [float(((coarse[k] - fine[k]) ** 2).mean()) for k in views]
    psnr = [float(-10 * np.log10(max(m, 1e-20))) for m in mse]
    res["largest_rgb_difference_refined_vs_render_view"] = diff
    res["coarse_vs_refined_psnr_db"] = {"mean": round(float(np.mean(psnr)), 2), "min": round(min(psnr), 2)}
    print(f"largest |rgb(preview refined) - rgb(render_view)|: {diff:.2e}")
    print(f"coarse preview against the refined one: mean {np.mean(psnr):.2f} dB, lowest {min(psnr):.2f} dB")
    return res


if __name__ == "__main__":
    main()
