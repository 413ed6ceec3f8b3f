"""Viewer render speed: rays/s of `render`'s path (`model.render_view`) against the viewer's preview
(`model.preview.render_preview`, refined and coarse) on one test camera of a trained run, at 256 px.

    .venv/bin/python -m benchmarks.bench_view RUN_DIR [--size 256] [--threads 2] [--repeats 3]

Prints the best of `repeats` seconds per frame and rays/s for each, and the largest rgb difference between the
refined preview and `render_view` (early ray termination: at most about 1e-3).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from model import load_trained, render_view
from model.cameras import camera_path
from model.preview import render_preview


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cpu = torch.device("cpu")
    trained = load_trained(args.run_dir, cpu)
    cams = camera_path(trained.scene, "test")
    intr = cams.intrinsics[0].scaled(args.size / max(cams.intrinsics[0].w, cams.intrinsics[0].h))
    render_view(trained, intr.scaled(0.1), cams.world_from_cams[0], cpu)  # warm-up
    rays = intr.w * intr.h
    kinds = {
        "render_view (render stage)": lambda k: render_view(trained, intr, cams.world_from_cams[k], cpu),
        "preview, refined": lambda k: render_preview(trained, intr, cams.world_from_cams[k]),
        "preview, coarse": lambda k: render_preview(trained, intr, cams.world_from_cams[k], coarse=True),
    }
    for name, fn in kinds.items():
        times = []
        for k in range(args.repeats):
            t0 = time.perf_counter()
            fn(k % len(cams.names))
            times.append(time.perf_counter() - t0)
        best = min(times)
        print(f"{name}: {intr.w}x{intr.h}, best of {args.repeats}: {best:.3f} s, {rays / best:.0f} rays/s", flush=True)
    a = render_view(trained, intr, cams.world_from_cams[0], cpu)["rgb"]
    b = render_preview(trained, intr, cams.world_from_cams[0])["rgb"]
    print(f"largest |rgb(preview refined) - rgb(render_view)|: {float(np.abs(a - b).max()):.2e}")


if __name__ == "__main__":
    main()
