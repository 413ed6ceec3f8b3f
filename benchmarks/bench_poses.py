"""Benchmark of the poses stage: registered images, pose error after a similarity alignment, seconds.

    .venv/bin/python -m benchmarks.bench_poses                 # fox (../shared/data/fox) and synthetic
    .venv/bin/python -m benchmarks.bench_poses --only fox --max-image-size 3200 --num-threads 2

The stage runs with exactly the Config that `nerfpipe poses IMAGES OUT` builds (`cli.config_from_args`):
its defaults, plus any `nerfpipe poses` options given here (they are passed to the CLI's parser as they are).

fox: 50 real 1080x1920 photos; the reference is instant-ngp's COLMAP transforms.json (OpenGL world_from_cam
in a transformed world frame, 67 frames listed, 50 images present). Goal: 50/50 registered, median rotation
difference <= 0.3 deg, <= 60 s wall on 2 cores. synthetic: `stages.scene` photos (size 256, 40 views) with
exact cameras. Goal: all registered, median rotation error <= 0.1 deg, median centre error <= 0.5 % of the
camera rig's size. Prints one line per scene: registered, errors, SIFT working size, attempts, wall and
process CPU seconds (a loaded machine inflates wall; `uptime` says how loaded).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nerfpipe.cli import config_from_args  # noqa: E402
from nerfpipe.data.ground_truth import read_ground_truth  # noqa: E402
from nerfpipe.data.importers.colmap import read_world_from_cam  # noqa: E402
from nerfpipe.data.transforms import read_scene  # noqa: E402
from nerfpipe.radiance.align import pose_errors  # noqa: E402
from nerfpipe.stages import poses  # noqa: E402

FOX = ROOT.parent / "shared" / "data" / "fox"


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def bench(name: str, images: Path, reference: dict[str, np.ndarray], out: Path, cli_options: list[str]) -> dict:
    config = config_from_args("poses", [str(images), str(out), *cli_options])
    cpu0, t0 = _cpu_seconds(), time.perf_counter()
    result = poses.run(config)
    wall, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
    est = read_world_from_cam(result.sparse)  # OpenGL axes, like both references
    common = sorted(set(est) & set(reference))
    err = pose_errors(np.stack([est[n] for n in common]), np.stack([reference[n] for n in common]))
    line = {
        "scene": name,
        "registered": f"{result.registered}/{result.total}",
        "rot_median_deg": round(err.median_rotation_deg, 3),
        "rot_max_deg": round(float(err.rotation_deg.max()), 3),
        "centre_median_pct": round(100 * err.median_centre_error_rel, 3),
        "reproj_px": round(result.mean_reprojection_error, 3),
        "working_size": result.working_size,
        "attempts": len(result.attempts),
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "load": " ".join(f"{v:.2f}" for v in os.getloadavg()),
    }
    print("  ".join(f"{k}={v}" for k, v in line.items()), flush=True)
    return line


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog="Other options are `nerfpipe poses` options, passed as they are."
    )
    p.add_argument("--only", choices=["fox", "synthetic"], default=None)
    p.add_argument("--seed", type=int, default=0, help="synthetic scene's seed (textures and camera jitter)")
    p.add_argument("--out", type=Path, default=None, help="keep outputs here (default: a temporary folder)")
    args, cli_options = p.parse_known_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_poses_") as tmp:
        out = args.out or Path(tmp)
        if args.only in (None, "fox"):
            if not (FOX / "images").is_dir():
                print(f"fox: skipped, {FOX} not found")
            else:
                frames = read_scene(FOX / "transforms.json").frames  # OpenGL, instant-ngp's world frame
                ref = {Path(f.file_path).name: f.world_from_cam for f in frames}
                bench("fox", FOX / "images", ref, out / "fox", cli_options)
        if args.only in (None, "synthetic"):
            from nerfpipe.stages import scene

            scene_dir = out / "synthetic_scene"
            scene.run(scene.Config(out_dir=scene_dir, kind="photos", size=256, views=40, seed=args.seed))
            ref = read_ground_truth(scene_dir).by_file_name()
            bench("synthetic", scene_dir / "images", ref, out / "synthetic", cli_options)


if __name__ == "__main__":
    main()
