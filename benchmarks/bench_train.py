"""Training benchmark: fast vs vanilla field on lego_100 (and lego_400), PSNR against wall-clock.

lego_100 (../shared/data/lego_100): train views 0-99, test views 100-105. The npz images are premultiplied
(composited on black); with the matching alpha we write straight RGBA PNGs, so training composites random
backgrounds and evaluation uses white (the NeRF Blender convention). Both fields get the same time budget
through `stages.train.run`; the report gives final test PSNR, the time each needed to reach the vanilla
run's best PSNR (ratio = speed-up), peak memory, and one PNG of PSNR vs time for both.

Threads: torch's default (2 here). On an idle 2-core machine two threads beat one (84 vs 62 steps in 30 s);
on an oversubscribed one, `--threads 1` is far faster (two threads thrash).
Vanilla renders 2 of the 6 test views in full at the end (each costs minutes on CPU).

Run (2 CPU cores, 120 s each):  make bench-train   (= .venv/bin/python -m benchmarks.bench_train --out DIR)
  .venv/bin/python -m benchmarks.bench_train --dataset lego_400 --seconds 900 --fields fast
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np

from data.transforms import Frame, Scene, write_scene
from radiance.camera import Intrinsics
from stages import train

__all__ = ["lego_100_scene", "lego_400_scene", "main"]

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
AABB = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])


def _write_png(path: Path, rgba: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    bgra = cv2.cvtColor(np.round(np.clip(rgba, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGBA2BGRA)
    cv2.imwrite(str(path), bgra)


def lego_100_scene(out: Path) -> Path:
    """Write lego_100 as a scene folder (RGBA PNGs + transforms.json). Returns the folder."""
    if (out / "transforms.json").is_file():
        return out
    d = np.load(DATA / "lego_100" / "tiny_lego_100px.npz")
    alpha = np.load(DATA / "lego_100" / "tiny_lego_100px_alpha.npz")["alpha"]
    images, poses, focal = d["images"], d["poses"].astype(np.float64), float(d["focal"])
    frames = []
    for i in range(images.shape[0]):
        a = alpha[i][..., None]
        rgb = np.where(a > 0, images[i] / np.maximum(a, 1e-6), 0.0)  # un-premultiply
        _write_png(out / "images" / f"{i:03d}.png", np.concatenate([rgb, a], axis=-1))
        frames.append(Frame(file_path=f"images/{i:03d}.png", world_from_cam=poses[i]))
    h, w = images.shape[1:3]
    scene = Scene(root=out, frames=tuple(frames), intrinsics=Intrinsics(w=w, h=h, fx=focal, fy=focal, cx=w / 2,
                  cy=h / 2), aabb=AABB, near=2.0, far=6.0, has_alpha=True,
                  splits={"train": tuple(range(100)), "test": tuple(range(100, 106))})  # fmt: skip
    write_scene(scene, out / "transforms.json")
    return out


def lego_400_scene(out: Path) -> Path:
    """lego_400 (Blender layout) through `stages.convert`: its train / val / test splits; the benchmark renders
    25 evenly spaced test views (of 200) in full at the end."""
    if (out / "transforms.json").is_file():
        return out
    from stages import convert

    convert.run(convert.Config(source=DATA / "lego_400", scene_dir=out, kind="blender", downscales=()))
    return out


def _curve(metrics: Path) -> list[tuple[float, float]]:
    with open(metrics, newline="") as f:
        return [(float(r["seconds"]), float(r["test_psnr"])) for r in csv.DictReader(f) if r["test_psnr"]]


def _time_to(curve: list[tuple[float, float]], psnr: float) -> float | None:
    return next((s for s, p in curve if p >= psnr), None)


def main(seconds: float = 120.0, dataset: str = "lego_100", out: Path = Path("runs/bench_train"),
         fields: tuple[str, ...] = ("fast", "vanilla"), threads: int | None = None) -> dict:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene_dir = (lego_100_scene if dataset == "lego_100" else lego_400_scene)(out / dataset / "scene")
    results, curves = {}, {}
    for field in fields:
        # CPU-sized settings: small batches so that many steps fit the budget; periodic evaluation is excluded
        # from the training time (stages.train) so it does not bias the curve.
        fast = field == "fast"
        cfg = train.Config(scene_dir=scene_dir, run_dir=out / dataset / field, field=field, max_seconds=seconds,
                           max_steps=10**9, batch_rays=1024 if fast else 256, eval_every=50 if fast else 5,
                           eval_pixels=2048, step_ratio=2.0 if dataset == "lego_100" else 1.0,
                           resolution=(64, 160) if dataset == "lego_100" else (96, 300), threads=threads,
                           final_eval_views=(None if dataset == "lego_100" else 25) if fast else 2)  # fmt: skip
        res = train.run(cfg)
        manifest = json.loads(res.manifest.read_text())
        curves[field] = _curve(res.metrics)
        results[field] = {"steps": res.steps, "seconds": round(res.seconds, 1), "test_psnr": res.test_psnr,
                          "peak_rss_mb": manifest["used"]["peak_rss_mb"]}  # fmt: skip
        print(field, results[field], flush=True)
    if "fast" in curves and "vanilla" in curves and curves["vanilla"]:
        target = max(p for _, p in curves["vanilla"])
        t_fast, t_van = _time_to(curves["fast"], target), _time_to(curves["vanilla"], target)
        results["speedup"] = {"psnr": round(target, 2), "fast_s": t_fast, "vanilla_s": t_van,
                              "ratio": round(t_van / t_fast, 1) if t_fast and t_van else None}  # fmt: skip
    fig, ax = plt.subplots(figsize=(6, 4))
    for field, pts in curves.items():
        if pts:
            ax.plot(*zip(*pts, strict=True), "o-", markersize=3, label=field)
    ax.set_xlabel("wall-clock seconds")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(f"{dataset}: test PSNR vs time")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(out / dataset / "psnr_vs_time.png", dpi=100)
    (out / dataset / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    return results


def cli(argv: list[str] | None = None) -> None:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench_train"))
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--dataset", choices=("lego_100", "lego_400"), default="lego_100")
    p.add_argument("--fields", default="fast,vanilla", help="comma-separated: fast,vanilla")
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    main(seconds=a.seconds, dataset=a.dataset, out=a.out, fields=tuple(a.fields.split(",")), threads=a.threads)


if __name__ == "__main__":
    cli()
