"""Peak memory of `nerfpipe train` against the number of views: big captures in bounded memory (issue 19).

A capture of N views at 1920x1080 (default 300) is written as transforms.json over a few distinct generated
photos (every frame points at one of them: memory is per view all the same, and writing 1000 PNGs would
measure the disk), cameras on a circle round the origin. `nerfpipe train` then runs a few steps in a
subprocess per view count, through the CLI exactly as a user types it; the figure is the child's peak resident
set (ru_maxrss from wait4), next to the images' own size (4 bytes a pixel, RGBA uint8).

`--downscale 1` trains on the full 1920x1080 images (the hard case); `--downscale auto` passes nothing, so train
picks its CPU default (1080p -> 480x270). `--code DIR` runs another checkout's cli.py (the code before this
change, for comparison). Goal: 300 views at 1920x1080, full size, in <= 4 GB.

Run:  make bench-memory  (= .venv/bin/python -m benchmarks.bench_memory --out runs/bench/memory)
      .venv/bin/python -m benchmarks.bench_memory --views 100,300,1000 --downscale auto
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
W, H, DISTINCT = 1920, 1080, 4

__all__ = ["make_capture", "measure", "main"]


def make_capture(out: Path, views: int) -> Path:
    """transforms.json with `views` frames at 1920x1080 over DISTINCT generated photos; returns the folder."""
    import cv2

    from nerfpipe.data.transforms import Frame, Scene, write_scene
    from nerfpipe.radiance.camera import Intrinsics

    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for k in range(DISTINCT):
        path = out / f"photo{k}.jpg"
        if not path.exists():  # smooth colour noise: a photo-like image that compresses like one
            small = rng.integers(0, 256, (H // 40, W // 40, 3), dtype=np.uint8)
            cv2.imwrite(str(path), cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC))
    frames = []
    for i in range(views):
        a = 2 * math.pi * i / views
        eye = np.array([3 * math.cos(a), 3 * math.sin(a), 1.0])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, up, -forward], axis=1)  # OpenGL: looking down -z
        pose[:3, 3] = eye
        frames.append(Frame(file_path=f"photo{i % DISTINCT}.jpg", world_from_cam=pose))
    intr = Intrinsics(w=W, h=H, fx=1500.0, fy=1500.0, cx=W / 2, cy=H / 2)
    scene = Scene(
        root=out,
        frames=tuple(frames),
        intrinsics=intr,
        applied_transform=np.eye(4)[:3],
        applied_scale=1.0,
        aabb=np.array([[-1.0] * 3, [1.0] * 3]),
        near=0.5,
        far=6.0,
        splits={"train": tuple(range(views))},
        has_alpha=False,
        extra={},
    )
    write_scene(scene, out / "transforms.json")
    return out


def measure(scene: Path, run: Path, downscale: str, steps: int, code: Path) -> dict:
    """Train `steps` steps in a child process; its peak RSS (MB), wall seconds and exit status."""
    args = [
        sys.executable,
        str(code / "cli.py"),
        "train",
        str(scene),
        str(run),
        "--max-steps",
        str(steps),
        "--device",
        "cpu",
        "--threads",
        "1",
        "--eval-every",
        "0",
        "--resolution",
        "16,32",
        "--overwrite",
    ]
    if downscale != "auto":
        args += ["--downscale", downscale]
    if code != ROOT:
        args.remove("--overwrite")  # older code has no such option
        subprocess.run(["rm", "-rf", str(run)], check=True)
    print("$", " ".join(args), flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, cwd=code, env={**os.environ, "PYTHONPATH": str(code)})
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {
        "peak_rss_mb": round(usage.ru_maxrss / 1024),
        "seconds": round(time.perf_counter() - t0, 1),
        "exit": proc.returncode,
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "memory")
    p.add_argument("--views", default="100,300", help="comma-separated view counts")
    p.add_argument("--downscale", default="1", help="1 (full 1920x1080), 2, 4, ... or auto (train's default)")
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--code", type=Path, default=ROOT, help="checkout whose cli.py runs (default: this one)")
    a = p.parse_args(argv)
    rows = []
    for n in [int(v) for v in a.views.split(",")]:
        scene = make_capture(a.out / f"scene_{n}", n)
        factor = 4 if a.downscale == "auto" else float(a.downscale)  # auto on CPU: long side <= 800 -> 4
        pixels = n * round(W / factor) * round(H / factor)
        row = {
            "views": n,
            "downscale": a.downscale,
            "code": str(a.code),
            "pixels": pixels,
            "images_mb": round(4 * pixels / 2**20),
        }
        row.update(measure(scene, a.out / f"run_{n}_{a.downscale}", a.downscale, a.steps, a.code.resolve()))
        print(json.dumps(row), flush=True)
        rows.append(row)
    a.out.mkdir(parents=True, exist_ok=True)
    with open(a.out / "results.jsonl", "a") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")
    return {"rows": rows}


if __name__ == "__main__":
    main()
