"""Training benchmark through the commands a user types, on the files as distributed.

Every figure comes from `nerfpipe convert`, `nerfpipe train` and `nerfpipe eval` with exactly the Config the CLI
builds from the arguments shown (cli.config_from_args): no hand-made scenes, boxes, backgrounds or near/far.

Datasets (../shared/data):
- `tiny`: lego_100/tiny_lego_100px.npz as is (RGB composited on black, no alpha; tiny-NeRF split: views 0-99
  train, 100-105 test). Goal: >= 31 dB in 120 s with no options (density); nerf reported for the record.
- `lego_400`: the NeRF-synthetic Blender folder as is (RGBA); eval on 25 evenly spaced test views.
  Goal: >= 31 dB in 900 s.
- `small`: a Blender-layout object scene made with `nerfpipe scene --kind blender`, at scale 0.1 and at 1;
  goal: within 1 dB of each other, and their meshes as accurate (Chamfer in % of the diagonal, `mesh` +
  benchmarks.mesh_metrics against the scene's ground-truth mesh).

Run:  make bench-train  (= .venv/bin/python -m benchmarks.bench_train --out runs/bench/train)
      .venv/bin/python -m benchmarks.bench_train --dataset lego_400 --seconds 900
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

__all__ = ["nerfpipe", "main"]


def nerfpipe(command: str, args: str):
    """Run one stage exactly as `nerfpipe COMMAND ARGS` would (the CLI's own Config), return its Outputs."""
    import importlib

    from nerfpipe.cli import STAGES, config_from_args

    print(f"$ nerfpipe {command} {args}", flush=True)
    config = config_from_args(command, shlex.split(args))
    return importlib.import_module(STAGES[command].module).run(config)


def _train_eval(scene: Path, run: Path, seconds: float, field: str, eval_views: int | None) -> dict:
    out = nerfpipe("train", f"{scene} {run} --max-seconds {seconds} --method {field} --overwrite")
    views = f" --views {eval_views}" if eval_views else ""
    ev = nerfpipe("eval", f"{run} {run}/eval.json{views}").result
    used = json.loads(out.manifest.read_text())["used"]
    return {
        "method": field,
        "steps": out.steps,
        "train_seconds": round(out.seconds, 1),
        "eval_psnr": round(ev["psnr"], 3),
        "eval_ssim": round(ev["ssim"], 4),
        "eval_views": ev["n_views"],
        "train_final_psnr": out.test_psnr,
        "peak_rss_mb": used["peak_rss_mb"],
        "defaults": used.get("defaults", {}).get("resolved"),
    }


def bench_tiny(out: Path, seconds: float, fields: tuple[str, ...]) -> dict:
    scene = out / "tiny" / "scene"
    nerfpipe("convert", f"{DATA / 'lego_100' / 'tiny_lego_100px.npz'} {scene}")
    return {f: _train_eval(scene, out / "tiny" / f, seconds, f, None) for f in fields}


def bench_lego_400(out: Path, seconds: float, fields: tuple[str, ...]) -> dict:
    scene = out / "lego_400" / "scene"
    nerfpipe("convert", f"{DATA / 'lego_400'} {scene}")
    return {f: _train_eval(scene, out / "lego_400" / f, seconds, f, 25) for f in fields}


def bench_small(out: Path, seconds: float) -> dict:
    import trimesh

    from benchmarks.mesh_metrics import chamfer_distance, surface_points

    res = {}
    for scale in (1.0, 0.1):
        root = out / f"small_{scale:g}"
        nerfpipe("scene", f"{root / 'src'} --kind blender --size 128 --views 48 --scale {scale} --overwrite")
        nerfpipe("convert", f"{root / 'src'} {root / 'scene'}")
        r = _train_eval(root / "scene", root / "run", seconds, "fast", None)
        nerfpipe("mesh", f"{root / 'run'} {root / 'mesh.ply'} --resolution 256")
        gt = trimesh.load(root / "src" / "ground_truth" / "mesh.ply")
        got = trimesh.load(root / "mesh.ply")
        diag = float(gt.bounding_box.primitive.extents.__pow__(2).sum() ** 0.5)
        a = surface_points(gt.vertices, gt.faces, 50_000)
        b = surface_points(got.vertices, got.faces, 50_000)
        r["chamfer_pct_of_diagonal"] = round(100 * chamfer_distance(a, b) / diag, 3)
        res[f"scale_{scale:g}"] = r
    return res


def main(*, dataset: str, seconds: float, out: Path, fields: tuple[str, ...]) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    if dataset == "tiny":
        results = bench_tiny(out, seconds, fields)
    elif dataset == "lego_400":
        results = bench_lego_400(out, seconds, fields)
    else:
        results = bench_small(out, seconds)
    (out / f"{dataset}_results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    return results


def cli(argv: list[str] | None = None) -> None:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench/train"))
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--dataset", choices=("tiny", "lego_400", "small"), default="tiny")
    p.add_argument("--methods", default="density", help="comma-separated: density,nerf")
    a = p.parse_args(argv)
    main(dataset=a.dataset, seconds=a.seconds, out=a.out, fields=tuple(a.methods.split(",")))


if __name__ == "__main__":
    cli()
