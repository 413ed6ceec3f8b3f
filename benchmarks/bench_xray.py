"""X-ray benchmark: the TIGRE thorax phantom (128^3) -> cone-beam views -> attenuation field vs FDK.

`make bench-xray` (about 35 minutes: 10 minutes of training at each of 50, 25 and 10 views):
1. `xray-simulate` the phantom (`../shared/data/ct/tigre_thorax_img128.mat`, 2 mm voxels, so a 256 mm field)
   with NAF's chest geometry: cone beam, source 1000 mm and detector 1500 mm from the axis, 50 views over 180
   degrees, a detector of one voxel per pixel at the isocentre, 10 noise-free held-out views over 360 degrees.
2. For each view count (50, 25, 10: every view, every 2nd, every 5th of the same 50):
   - FDK (radiance.fdk, Ram-Lak; the classical baseline) on exactly those views: 3-D PSNR / SSIM, seconds;
   - `xray-train` (the CLI, in its own process, `--threads 1`, `--max-seconds 600`): 3-D PSNR / SSIM against
     training seconds (its metrics.csv), final figures, peak memory (the process's max RSS).
3. results.json and summary.md in --out. The goal (issue 15): 3-D PSNR >= FDK + 5 dB at 50 views within 10
   minutes on 2 CPU cores, and well above FDK at 10 views.

    .venv/bin/python -m benchmarks.bench_xray --out runs/bench/xray
    .venv/bin/python -m benchmarks.bench_xray --views 50 --seconds 120          # a quick look
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.projections import read_projection_scene, write_projection_scene
from nerfpipe.radiance.ct_metrics import psnr_3d, ssim_3d
from nerfpipe.radiance.fdk import fdk
from nerfpipe.stages import xray_simulate

__all__ = ["main"]

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT.parent / "shared" / "data" / "ct" / "tigre_thorax_img128.mat"


def _subset_scene(src: Path, dst: Path, views: int, total: int) -> Path:
    """The same scan keeping every (total // views)-th training view (the held-out views stay)."""
    if (dst / "projections.json").is_file():
        return dst
    scene = read_projection_scene(src)
    step = total // views
    train = tuple(scene.split("train")[::step][:views])
    write_projection_scene(replace(scene, splits={**scene.splits, "train": train}), dst)
    return dst


def _fdk(scene_dir: Path, threads: int) -> dict:
    torch.set_num_threads(threads)
    scene = read_projection_scene(scene_dir)
    train = list(scene.split("train"))
    t0 = time.perf_counter()
    rec = fdk(torch.from_numpy(scene.projections[train]), scene.geometry.subset(train), scene.grid).numpy()
    seconds = time.perf_counter() - t0
    return {
        "psnr_3d": round(psnr_3d(rec, scene.volume), 2),
        "ssim_3d": round(ssim_3d(rec, scene.volume), 4),
        "psnr_3d_clipped": round(psnr_3d(np.clip(rec, 0, None), scene.volume), 2),
        "seconds": round(seconds, 2),
    }


def _train(scene_dir: Path, run_dir: Path, seconds: float, threads: int, extra: list[str]) -> dict:
    cmd = [
        sys.executable,
        str(ROOT / "cli.py"),
        "xray-train",
        str(scene_dir),
        str(run_dir),
        "--max-seconds",
        str(seconds),
        "--threads",
        str(threads),
        "--device",
        "cpu",
        "--overwrite",
        *extra,
    ]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    used = json.loads((run_dir / "manifest.json").read_text())["used"]
    with open(run_dir / "metrics.csv", newline="") as f:
        curve = [
            {
                "seconds": float(r["seconds"]),
                "step": int(r["step"]),
                "psnr_3d": float(r["psnr_3d"]),
                "ssim_3d": float(r["ssim_3d"]),
            }
            for r in csv.DictReader(f)
            if r.get("psnr_3d")
        ]
    final = used["final"]
    return {
        "psnr_3d": round(final["psnr_3d"], 2),
        "ssim_3d": round(final["ssim_3d"], 4),
        "test_proj_psnr": round(final.get("test_proj_psnr", float("nan")), 2),
        "steps": used["steps"],
        "seconds": used["seconds"],
        "peak_rss_mb": used["peak_rss_mb"],
        "curve": curve,
    }


def _summary(results: dict, meta: dict) -> str:
    lines = [
        "# bench-xray: TIGRE thorax 128^3, cone beam over 180 degrees, attenuation field vs FDK",
        "",
        f"{meta['seconds']:.0f} s of training per run, {meta['threads']} CPU threads, load average at the start "
        f"{meta['load_start']}, at the end {meta['load_end']}.",
        "",
        "| views | FDK PSNR | FDK SSIM | field PSNR | field SSIM | gain (dB) | steps | train s | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for views, r in results.items():
        f, n = r["fdk"], r["field"]
        lines.append(
            f"| {views} | {f['psnr_3d']} | {f['ssim_3d']} | {n['psnr_3d']} | {n['ssim_3d']} | "
            f"{n['psnr_3d'] - f['psnr_3d']:+.2f} | {n['steps']} | {n['seconds']:.0f} | {n['peak_rss_mb']} |"
        )
    lines += ["", "3-D PSNR (dB) / SSIM against training seconds:", ""]
    for views, r in results.items():
        pts = ", ".join(f"{p['seconds']:.0f} s: {p['psnr_3d']:.2f}/{p['ssim_3d']:.3f}" for p in r["field"]["curve"])
        lines.append(f"- {views} views: {pts}")
    return "\n".join(lines) + "\n"


def main(out: Path, views: list[int], seconds: float, threads: int, train_args: list[str]) -> dict:
    import os

    load_start = round(os.getloadavg()[0], 2)
    base = out / "scene_50"
    if not (base / "manifest.json").is_file():
        xray_simulate.run(
            xray_simulate.Config(
                volume=PHANTOM, out_dir=base, views=50, arc=180.0, test_views=10, voxel_size=2.0, threads=threads
            )
        )
    results = {}
    for n in views:
        scene_dir = base if n == 50 else _subset_scene(base, out / f"scene_{n}", n, 50)
        fdk_res = _fdk(scene_dir, threads)
        print(f"{n} views FDK: {fdk_res}", flush=True)
        field = _train(scene_dir, out / f"run_{n}", seconds, threads, train_args)
        print(f"{n} views field: { {k: v for k, v in field.items() if k != 'curve'} }", flush=True)
        results[n] = {"fdk": fdk_res, "field": field}
    meta = {
        "seconds": seconds,
        "threads": threads,
        "load_start": load_start,
        "load_end": round(os.getloadavg()[0], 2),
        "train_args": train_args,
    }
    (out / "results.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2) + "\n")
    (out / "summary.md").write_text(_summary(results, meta))
    print(_summary(results, meta))
    return results


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench/xray"))
    p.add_argument("--views", default="50,25,10", help="comma-separated view counts (each divides 50)")
    p.add_argument("--seconds", type=float, default=600.0)
    p.add_argument(
        "--threads", type=int, default=1, help="torch threads (1: on a busy 2-core machine, 2 ran several times slower)"
    )
    p.add_argument("--train-args", default="", help="extra xray-train options, e.g. '--tv 1e-4'")
    a = p.parse_args(argv)
    main(a.out, [int(v) for v in a.views.split(",")], a.seconds, a.threads, a.train_args.split())


if __name__ == "__main__":
    cli()
