"""Forward-facing benchmark: the fast field trained in the scene's box vs in NDC, same time budget.

Scene: `stages.scene` with layout=forward (objects 1.5-3.5 m from a rig of cameras spread 0.9 x 0.5 m, a wall
4 m behind them, so the scene's aabb is 8 x 8 x 6 m), posed, every 8th view held out. Both runs use the stage's
CPU defaults; the report gives test PSNR on the held-out views, the median relative z-depth error against the
ground truth (pixels that are opaque in both), steps and peak memory, and writes results.json.

    .venv/bin/python -m benchmarks.bench_ndc --out runs/bench/ndc                 # 120 s each, 128 px, 32 views
    .venv/bin/python -m benchmarks.bench_ndc --seconds 30 --size 64 --views 16    # quick look
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from nerfpipe.model import load_trained
from nerfpipe.radiance.camera import generate_rays, z_depth_from_t
from nerfpipe.stages import scene as scene_stage
from nerfpipe.stages import train

__all__ = ["main"]


def _depth_error(run_dir: Path, scene_dir: Path) -> float:
    """Median |z - z_gt| / z_gt over the test views' pixels that are opaque in the render and the truth."""
    trained = load_trained(run_dir, "cpu")
    errors = []
    for view in trained.scene.split("test"):
        frame = trained.scene.frames[view]
        intr = trained.scene.frame_intrinsics(view)
        w = torch.as_tensor(frame.world_from_cam, dtype=torch.float64)
        o, d = generate_rays(intr, w)
        out = trained.render_rays(o.float(), d.float())
        z = z_depth_from_t(out["depth_median"].double(), d, w).numpy().reshape(intr.h, intr.w)
        gt = np.load(scene_dir / "ground_truth" / "depth" / f"{Path(frame.file_path).stem}.npy")
        ok = (gt > 0) & (out["acc"].numpy().reshape(intr.h, intr.w) > 0.5) & np.isfinite(z)
        errors.append(np.abs(z[ok] - gt[ok]) / gt[ok])
    return float(np.median(np.concatenate(errors)))


def main(seconds: float, size: int, views: int, out: Path, threads: int | None) -> dict:
    scene_dir = out / "scene"
    if not (scene_dir / "transforms.json").is_file():
        scene_stage.run(
            scene_stage.Config(out_dir=scene_dir, kind="posed", size=size, views=views, seed=0, layout="forward")
        )
    results = {}
    for model in ("box", "ndc"):
        cfg = train.Config(
            scene_dir=scene_dir,
            run_dir=out / model,
            scene_model=model,
            max_seconds=seconds,
            max_steps=10**9,
            eval_every=100,
            threads=threads,
            overwrite=True,
        )
        res = train.run(cfg)
        used = json.loads(res.manifest.read_text())["used"]
        results[model] = {
            "steps": res.steps,
            "seconds": round(res.seconds, 1),
            "test_psnr": round(res.test_psnr, 2),
            "depth_median_rel_error": round(_depth_error(out / model, scene_dir), 4),
            "samples_per_ray": used.get("samples_per_ray"),
            "peak_rss_mb": used["peak_rss_mb"],
        }
        print(model, results[model], flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench/ndc"))
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--views", type=int, default=32)
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    main(a.seconds, a.size, a.views, a.out, a.threads)


if __name__ == "__main__":
    cli()
