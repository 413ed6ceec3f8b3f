"""Benchmark of turntable captures (issue 17): masks through poses, convert and train, and the refusal without.

    .venv/bin/python -m benchmarks.bench_turntable --out runs/bench/turntable          # make bench-turntable
    .venv/bin/python -m benchmarks.bench_turntable --train-seconds 0                   # poses only

Every stage runs with the Config its `nerfpipe` command builds (`cli.config_from_args`):
1. `nerfpipe scene OUT --kind posed --layout turntable --size 256 --views 24`: the objects turn, camera and room
   fixed; exact object-relative poses and a mask per view;
2. `nerfpipe poses IMAGES OUT --masks MASKS`: goal every view registered, median rotation error < 0.5 deg after a
   similarity alignment to the truth;
3. `nerfpipe poses IMAGES OUT` (no masks): goal a one-line refusal ("static camera ... --masks"), not a model;
4. (--train-seconds > 0) `nerfpipe convert` of the masked model, `nerfpipe train --max-seconds S`: test PSNR on the
   masked (transparent) background, and the per-image report's cost against its budget.
Prints one line per step and writes summary.json in --out.
"""

from __future__ import annotations

import argparse
import json
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
from nerfpipe.data.errors import UserError  # noqa: E402
from nerfpipe.data.ground_truth import read_ground_truth  # noqa: E402
from nerfpipe.data.importers.colmap import read_world_from_cam  # noqa: E402
from nerfpipe.radiance.align import pose_errors  # noqa: E402
from nerfpipe.stages import convert, poses, train  # noqa: E402
from nerfpipe.stages import scene as scene_stage  # noqa: E402


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _timed(fn):
    cpu0, t0 = _cpu_seconds(), time.perf_counter()
    out = fn()
    return out, round(time.perf_counter() - t0, 1), round(_cpu_seconds() - cpu0, 1)


def _print(line: dict) -> dict:
    print("  ".join(f"{k}={v}" for k, v in line.items()), flush=True)
    return line


def run(out: Path, size: int, views: int, seed: int, train_seconds: float, threads: int) -> dict:
    scene_dir = out / "scene"
    _, wall, cpu = _timed(
        lambda: scene_stage.run(
            config_from_args(
                "scene",
                [
                    str(scene_dir),
                    "--kind",
                    "posed",
                    "--layout",
                    "turntable",
                    "--size",
                    str(size),
                    "--views",
                    str(views),
                    "--seed",
                    str(seed),
                ],
            )
        )
    )
    summary = {"scene": _print({"step": "scene", "size": size, "views": views, "wall_s": wall, "cpu_s": cpu})}
    truth = read_ground_truth(scene_dir).by_file_name()
    images, masks = scene_dir / "images", scene_dir / "masks"
    common = ["--num-threads", str(threads)]

    result, wall, cpu = _timed(
        lambda: poses.run(config_from_args("poses", [str(images), str(out / "masked"), "--masks", str(masks), *common]))
    )
    est = read_world_from_cam(result.sparse)
    names = sorted(set(est) & set(truth))
    err = pose_errors(np.stack([est[n] for n in names]), np.stack([truth[n] for n in names]))
    report = json.loads(result.report.read_text())
    summary["poses_masked"] = _print(
        {
            "step": "poses --masks",
            "registered": f"{result.registered}/{result.total}",
            "rot_median_deg": round(err.median_rotation_deg, 3),
            "rot_max_deg": round(float(err.rotation_deg.max()), 3),
            "centre_median_pct": round(100 * err.median_centre_error_rel, 3),
            "stationary_matches": report["stationary_matches"]["fraction"],
            "attempts": [a["name"] for a in report["attempts"]],
            "wall_s": wall,
            "cpu_s": cpu,
            "goal": "all registered, median rotation < 0.5 deg",
            "met": result.registered == result.total and err.median_rotation_deg < 0.5,
        }
    )

    def unmasked() -> str:
        try:
            r = poses.run(config_from_args("poses", [str(images), str(out / "unmasked"), *common]))
        except UserError as e:
            return f"error: {e}"
        return f"no error: {r.registered}/{r.total} registered"

    message, wall, cpu = _timed(unmasked)
    summary["poses_unmasked"] = _print(
        {
            "step": "poses (no masks)",
            "result": message,
            "wall_s": wall,
            "cpu_s": cpu,
            "goal": "one-line refusal naming --masks",
            "met": message.startswith("error: static camera") and "--masks" in message and "\n" not in message,
        }
    )

    if train_seconds > 0:
        conv = convert.run(config_from_args("convert", [str(out / "masked"), str(out / "converted")]))
        trained, wall, cpu = _timed(
            lambda: train.run(
                config_from_args(
                    "train",
                    [
                        str(conv.transforms.parent),
                        str(out / "run"),
                        "--max-seconds",
                        str(train_seconds),
                        "--threads",
                        "1",
                    ],
                )
            )
        )
        manifest = json.loads(trained.manifest.read_text())
        per_view = manifest["used"]["per_view"]
        summary["train"] = _print(
            {
                "step": "convert + train",
                "test_psnr": round(trained.test_psnr or float("nan"), 2),
                "steps": trained.steps,
                "train_s": round(trained.seconds, 1),
                "background": manifest["used"]["background"]["mode"],
                "scene_model": manifest["used"]["scene_model"],
                "per_view_s": per_view["seconds"],
                "per_view_budget_s": per_view["budget_seconds"],
                "per_view_median_psnr": per_view["median_psnr"],
                "worst": per_view["worst"][:2],
                "wall_s": wall,
                "cpu_s": cpu,
            }
        )
    summary["load"] = " ".join(f"{v:.2f}" for v in os.getloadavg())
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=None, help="keep outputs here (default: a temporary folder)")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--views", type=int, default=24)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train-seconds", type=float, default=120.0, help="0: skip convert + train")
    p.add_argument("--threads", type=int, default=2, help="COLMAP threads (train runs on one: see docs/BENCHMARKS.md)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_turntable_") as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        run(out, args.size, args.views, args.seed, args.train_seconds, args.threads)


if __name__ == "__main__":
    main()
