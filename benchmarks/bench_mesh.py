"""Mesh accuracy and speed: resolution -> Chamfer distance -> time -> peak memory.

Run: .venv/bin/python -m benchmarks.bench_mesh --out runs/bench/mesh [--resolutions 128,256,512]
     [--train-seconds 780] [--method density|sdf] [--run RUN_DIR --scene-src SRC_DIR] [--skip-trained]
     [--skip-standin]

Two fields, each meshed by `stages.mesh` at every resolution in a fresh process (so the peak RSS is that
resolution's), Chamfer measured in the source (user) frame without any re-alignment:
- the analytic stand-in (`benchmarks.standin`: sphere U box, applied_scale 0.25 and a rotation), against its
  exact surface; with the auto threshold and with the exact level sigma_max / 2;
- a field trained on the synthetic `posed` scene (`stages.scene` -> `stages.convert` -> `stages.train`),
  against `ground_truth/mesh.ply` (metres). Only surface a training camera can see counts, on both sides:
  a point counts when, from some training camera, it lies in the image and the exact scene's first hit along
  the ray to it is not nearer than the point minus 1 cm (hidden faces: the slab's underside, the parts of
  objects sunk into the slab, the inside of the predicted slab are dropped; floaters in free space count).
Chamfer = symmetric mean of nearest-neighbour distances (`benchmarks.mesh_metrics.chamfer_distance`), 200k points per
side sampled uniformly by area; reported absolutely and as % of the ground truth's bounding-box diagonal.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["main", "measure", "trained_run"]

POINTS = 200_000


def _mesh_points(path: Path, n: int) -> np.ndarray:
    import trimesh

    from benchmarks.mesh_metrics import surface_points

    m = trimesh.load(path, force="mesh", process=False)
    return surface_points(np.asarray(m.vertices), np.asarray(m.faces), n, seed=1)


def measure(spec: dict) -> dict:
    """One meshing run (called in a fresh process): returns figures as a dict."""
    import trimesh

    from benchmarks.mesh_metrics import chamfer_distance
    from benchmarks.standin import visible_points
    from nerfpipe.stages import mesh

    out = Path(spec["out"])
    cfg = mesh.Config(
        run_dir=Path(spec.get("run_dir", out.parent)),
        out=out,
        resolution=spec["resolution"],
        threshold=spec.get("threshold", "auto"),
        frame="user",  # the ground truth's frame, exactly (the default, upright, turns and centres it)
    )
    t0 = time.perf_counter()
    if spec["kind"] == "standin":
        from benchmarks.standin import StandIn

        standin = StandIn(out.parent)
        result = mesh.extract(standin, cfg)
        seconds = time.perf_counter() - t0
        gt = standin.scene_to_source(standin.surface_points(POINTS))
        pred = _mesh_points(result.mesh, POINTS)
    else:
        result = mesh.run(cfg)
        seconds = time.perf_counter() - t0
        src = Path(spec["scene_src"])
        gt_mesh = trimesh.load(src / "ground_truth" / "mesh.ply", force="mesh", process=False)
        from benchmarks.mesh_metrics import surface_points

        gt = surface_points(np.asarray(gt_mesh.vertices), np.asarray(gt_mesh.faces), 2 * POINTS, seed=2)
        gt = gt[visible_points(gt, src)]
        pred = _mesh_points(result.mesh, 2 * POINTS)
        pred = pred[visible_points(pred, src)]
    report = json.loads(result.report.read_text())
    diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    chamfer = chamfer_distance(pred, gt)
    return {
        "kind": spec["kind"],
        "resolution": spec["resolution"],
        "threshold": result.threshold,
        "threshold_rule": spec.get("threshold", "auto"),
        "chamfer": chamfer,
        "chamfer_pct_diag": 100 * chamfer / diag,
        "seconds": round(seconds, 2),
        "peak_rss_mb": report["peak_rss_mb"],
        "faces": result.faces,
        "evaluated": report["grid"]["evaluated"],
        "samples": report["grid"]["samples"],
        "timing": report["timing_seconds"],
        "watertight": result.watertight,
        "bodies": report["final"]["components"],
    }


def _in_subprocess(spec: dict) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_mesh", "--measure", json.dumps(spec)], capture_output=True, text=True
    )
    if proc.returncode != 0:
        raise RuntimeError(f"measure {spec} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def trained_run(
    out: Path,
    seconds: float,
    method: str = "density",
    *,
    name: str | None = None,
    max_steps: int | None = None,
    scene_args: dict | None = None,
) -> tuple[Path, Path]:
    """The synthetic scene in OUT (made once: `scene_args` for `stages.scene.Config`, by default kind posed, 128 px,
    48 views, seed 0) and a run of `method` on it in OUT/name (default: run, or run_METHOD), trained for `seconds`
    (and at most `max_steps`) unless it is there: (run_dir, the scene's source)."""
    from nerfpipe.stages import convert, scene, train

    src, scene_dir = out / "scene_src", out / "scene"
    run_dir = out / (name or ("run" if method == "density" else f"run_{method}"))
    if not (src / "manifest.json").is_file():
        args = scene_args or {"kind": "posed", "size": 128, "views": 48, "seed": 0}
        scene.run(scene.Config(out_dir=src, **args))
    if not (scene_dir / "transforms.json").is_file():
        convert.run(convert.Config(source=src, scene_dir=scene_dir))
    if not (run_dir / "manifest.json").is_file():
        limit = {"max_steps": max_steps} if max_steps is not None else {}
        train.run(train.Config(scene_dir=scene_dir, run_dir=run_dir, max_seconds=seconds, method=method, **limit))
    return run_dir, src


def _table(rows: list[dict]) -> None:
    print(
        f"{'field':10s} {'level':>14s} {'res':>5s} {'Chamfer':>10s} {'% diag':>7s} {'time s':>7s} "
        f"{'peak MB':>8s} {'faces':>8s} {'queried':>8s}"
    )
    for r in rows:
        level = f"{r['threshold']:.3g} ({'auto' if r['threshold_rule'] == 'auto' else 'given'})"
        print(
            f"{r['kind']:10s} {level:>14s} {r['resolution']:5d} {r['chamfer']:10.5f} {r['chamfer_pct_diag']:7.3f} "
            f"{r['seconds']:7.2f} {r['peak_rss_mb']:8.0f} {r['faces']:8d} "
            f"{100 * r['evaluated'] / r['samples']:7.1f}%"
        )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one)")
    p.add_argument("--resolutions", default="128,256,512")
    p.add_argument("--train-seconds", type=float, default=780.0)
    p.add_argument("--method", default="density", help="train --method for the trained field (density, sdf, ...)")
    p.add_argument("--run", type=Path, default=None, help="use this trained run (with --scene-src)")
    p.add_argument("--scene-src", type=Path, default=None, help="the synthetic scene the run was trained on")
    p.add_argument("--skip-trained", action="store_true")
    p.add_argument("--skip-standin", action="store_true")
    p.add_argument("--measure", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.measure is not None:
        print(json.dumps(measure(json.loads(args.measure))))
        return
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_mesh_"))
    out.mkdir(parents=True, exist_ok=True)
    resolutions = [int(r) for r in args.resolutions.split(",")]
    rows = []
    if not args.skip_standin:
        for res in resolutions:
            for threshold in ("auto", 50.0):
                spec = {
                    "kind": "standin",
                    "resolution": res,
                    "threshold": threshold,
                    "out": str(out / f"standin_{res}_{threshold}" / "mesh.ply"),
                }
                rows.append(_in_subprocess(spec))
                print(json.dumps(rows[-1]), flush=True)
    if not args.skip_trained:
        if args.run is not None:
            run_dir, src = args.run, args.scene_src
            if src is None:
                p.error("--run needs --scene-src")
        else:
            t0 = time.perf_counter()
            run_dir, src = trained_run(out, args.train_seconds, args.method)
            print(f"scene + convert + train: {time.perf_counter() - t0:.0f} s", flush=True)
        for res in resolutions:
            spec = {
                "kind": "trained" if args.method == "density" else f"trained-{args.method}",
                "resolution": res,
                "run_dir": str(run_dir),
                "scene_src": str(src),
                "out": str(out / f"trained_{args.method}_{res}" / "mesh.ply"),
            }
            rows.append(_in_subprocess(spec))
            print(json.dumps(rows[-1]), flush=True)
    _table(rows)


if __name__ == "__main__":
    main()
