"""Benchmark of the poses stage: registered images, pose error after a similarity alignment, seconds.

    .venv/bin/python benchmarks/bench_poses.py                 # fox (../shared/data/fox) and synthetic
    .venv/bin/python benchmarks/bench_poses.py --only fox --max-image-size 1000 --max-num-features 2048

fox: 50 real 1080x1920 photos; the reference is instant-ngp's COLMAP transforms.json (OpenGL world_from_cam
in a transformed world frame, 67 frames listed, 50 images present). Goal: 50/50 registered, median rotation
difference <= 0.6 deg, <= 60 s wall on 2 cores. synthetic: `stages.scene` photos (size 256, 40 views) with
exact cameras. Goal: all registered, median rotation error <= 0.1 deg, median centre error <= 0.5 % of the
camera rig's size. Prints one line per scene; also the process CPU seconds (a loaded machine inflates wall).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data.ground_truth import read_ground_truth  # noqa: E402
from data.importers.colmap import read_world_from_cam  # noqa: E402
from data.transforms import read_scene  # noqa: E402
from radiance.align import pose_errors  # noqa: E402
from stages import poses  # noqa: E402

FOX = ROOT.parent / "shared" / "data" / "fox"


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def bench(name: str, images: Path, reference: dict[str, np.ndarray], out: Path, args) -> dict:
    config = poses.Config(
        input=images,
        scene_dir=out,
        max_image_size=args.max_image_size,
        max_num_features=args.max_num_features,
        camera_model=args.camera_model,
        num_threads=args.num_threads,
    )
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
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
    }
    print("  ".join(f"{k}={v}" for k, v in line.items()), flush=True)
    return line


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=["fox", "synthetic"], default=None)
    p.add_argument("--max-image-size", type=int, default=poses.Config.max_image_size)
    p.add_argument("--max-num-features", type=int, default=poses.Config.max_num_features)
    p.add_argument("--camera-model", default=poses.Config.camera_model)
    p.add_argument("--num-threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0, help="synthetic scene's seed (textures and camera jitter)")
    p.add_argument("--out", type=Path, default=None, help="keep outputs here (default: a temporary folder)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_poses_") as tmp:
        out = args.out or Path(tmp)
        if args.only in (None, "fox"):
            if not (FOX / "images").is_dir():
                print(f"fox: skipped, {FOX} not found")
            else:
                frames = read_scene(FOX / "transforms.json").frames  # OpenGL, instant-ngp's world frame
                ref = {Path(f.file_path).name: f.world_from_cam for f in frames}
                bench("fox", FOX / "images", ref, out / "fox", args)
        if args.only in (None, "synthetic"):
            from stages import scene

            scene_dir = out / "synthetic_scene"
            scene.run(scene.Config(out_dir=scene_dir, kind="photos", size=256, views=40, seed=args.seed))
            ref = read_ground_truth(scene_dir).by_file_name()
            bench("synthetic", scene_dir / "images", ref, out / "synthetic", args)


if __name__ == "__main__":
    main()
