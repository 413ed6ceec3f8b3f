"""GNT (issue 49): zero-shot on held-out generated scenes with few source views against the density method trained
on the same views, zero-shot on real data, and per-scene training as in the source document.

Run: .venv/bin/python -m benchmarks.bench_gnt --out runs/bench/gnt [--only fewview,real,perscene]
     [--weights pretrained|FILE] [--density-seconds 30] [--per-scene-seconds 900] [--threads 1]

- fewview: scenes the model never saw (`scene --subject random`, seeds 900000 and up; training used 100000-399999),
  two per layout (objects with alpha seen all round, forward-facing, inside a room), 80 px, 16 photos: 4 held out
  (every 4th), and N = 3, 6, 10 of the other 12 (evenly spread) as the only photos a method gets. GNT: `train
  --method gnt --init WEIGHTS --max-steps 0` (weights plus the scene); density: `train --max-seconds
  DENSITY_SECONDS` on the same N photos. Both scored by `eval` on the 4 held-out photos.
- real: zero-shot on lego_400 at 128 px (downscale 3.125; 25 of its 200 test views) and on the fern at 126x94
  (images_8 at downscale 4; its 3 test views), every training photo a source.
- perscene: `train --method gnt` from random weights on each of them for PER_SCENE_SECONDS, and the density method
  for the same seconds, scored on the same views (the source document: 10k steps of 1,024 rays, fern 22.87 dB,
  lego 26.06 dB).
Prints a markdown table per part and writes OUT/bench_gnt.json with the commit.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.provenance import commit

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
LAYOUTS = (("orbit", "rgba", 900000), ("forward", "posed", 910000), ("room", "posed", 920000))
SOURCES = (3, 6, 10)


def _eval(run_dir: Path, views: int | None = None) -> dict:
    from nerfpipe.stages import eval as eval_stage

    res = eval_stage.run(eval_stage.Config(run_dir=run_dir, out=run_dir / "eval.json", views=views)).result
    return {"psnr": round(res["psnr"], 2), "ssim": round(res["ssim"], 3), "views": res["n_views"]}


def _train(scene: Path, run_dir: Path, **kw) -> tuple[object, float]:
    from nerfpipe.stages import train

    t0 = time.perf_counter()
    out = train.run(train.Config(scene_dir=scene, run_dir=run_dir, overwrite=True, eval_every=0, **kw))
    return out, time.perf_counter() - t0


def _subset(scene_dir: Path, n: int) -> Path:
    """transforms_nN.json beside the scene's: N evenly spread training photos, every 4th photo held out."""
    doc = json.loads((scene_dir / "transforms.json").read_text())
    paths = [f["file_path"] for f in doc["frames"]]
    test = paths[::4]
    rest = [p for p in paths if p not in test]
    train = [rest[int(i)] for i in np.linspace(0, len(rest) - 1, n).round()]
    doc.update(train_filenames=train, test_filenames=test, val_filenames=test)
    path = scene_dir / f"transforms_n{n}.json"
    path.write_text(json.dumps(doc, indent=1))
    return path


def fewview(out: Path, weights: str, density_seconds: float, threads: int | None) -> list[dict]:
    from nerfpipe.model.methods.gnt.options import GntOptions
    from nerfpipe.stages import scene as scene_stage

    rows = []
    for layout, kind, seed in LAYOUTS:
        data = scene_stage.run(
            scene_stage.Config(
                out_dir=out / "scenes" / layout,
                subject="random",
                kind=kind,
                layout=layout,
                seed=seed,
                count=2,
                size=80,
                views=16,
                overwrite=True,
            )
        )
        for scene_dir in data.scenes:
            for n in SOURCES:
                subset = _subset(scene_dir, n)
                tag = f"{layout}_{scene_dir.name}_n{n}"
                opts = GntOptions(init=weights)
                _, gnt_s = _train(
                    subset, out / "runs" / f"{tag}_gnt", method="gnt", max_steps=0, options=opts, threads=threads
                )
                t0 = time.perf_counter()
                g = _eval(out / "runs" / f"{tag}_gnt")
                gnt_s += time.perf_counter() - t0
                d_out, _ = _train(subset, out / "runs" / f"{tag}_density", max_seconds=density_seconds, threads=threads)
                d = _eval(out / "runs" / f"{tag}_density")
                row = {
                    "layout": layout,
                    "scene": scene_dir.name,
                    "sources": n,
                    "gnt": g,
                    "gnt_seconds": round(gnt_s, 1),
                    "density": d,
                    "density_steps": d_out.steps,
                }
                print(json.dumps(row), flush=True)
                rows.append(row)
    return rows


def _real_scenes(out: Path) -> dict[str, tuple[Path, float, int | None]]:
    from nerfpipe.stages import convert

    scenes = {}
    lego, fern = out / "lego_400", out / "fern"
    if not (lego / "transforms.json").is_file():
        convert.run(convert.Config(source=DATA / "lego_400", scene_dir=lego))
    if not (fern / "transforms.json").is_file():
        convert.run(convert.Config(source=DATA / "fern", scene_dir=fern, images=Path("images_8")))
    scenes["lego_400 at 128 px"] = (lego, 3.125, 25)
    scenes["fern at 126x94"] = (fern, 4.0, None)
    return scenes


def real(out: Path, weights: str, threads: int | None) -> list[dict]:
    from nerfpipe.model.methods.gnt.options import GntOptions

    rows = []
    for name, (scene, downscale, views) in _real_scenes(out).items():
        run = out / "runs" / f"zero_{scene.name}"
        _, seconds = _train(
            scene,
            run,
            method="gnt",
            max_steps=0,
            downscale=downscale,
            final_eval_views=1,
            options=GntOptions(init=weights),
            threads=threads,
        )
        t0 = time.perf_counter()
        res = _eval(run, views)
        row = {"scene": name, "zero_shot": res, "seconds": round(seconds + time.perf_counter() - t0, 1)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def perscene(out: Path, seconds: float, threads: int | None) -> list[dict]:
    rows = []
    for name, (scene, downscale, views) in _real_scenes(out).items():
        row: dict = {"scene": name, "seconds": seconds}
        for method in ("gnt", "density"):
            run = out / "runs" / f"perscene_{scene.name}_{method}"
            res, _ = _train(
                scene, run, method=method, max_seconds=seconds, downscale=downscale, final_eval_views=1, threads=threads
            )
            row[method] = {**_eval(run, views), "steps": res.steps}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def _tables(doc: dict) -> str:
    lines = []
    if doc.get("fewview"):
        lines += [
            "| layout | scene | sources | gnt zero-shot dB / SSIM (s) | density dB / SSIM (steps) |",
            "|---|---|---|---|---|",
        ]
        for r in doc["fewview"]:
            g, d = r["gnt"], r["density"]
            lines.append(
                f"| {r['layout']} | {r['scene']} | {r['sources']} | {g['psnr']} / {g['ssim']} ({r['gnt_seconds']}) | "
                f"{d['psnr']} / {d['ssim']} ({r['density_steps']}) |"
            )
    if doc.get("real"):
        lines += ["", "| scene | gnt zero-shot dB / SSIM | views | seconds |", "|---|---|---|---|"]
        for r in doc["real"]:
            z = r["zero_shot"]
            lines.append(f"| {r['scene']} | {z['psnr']} / {z['ssim']} | {z['views']} | {r['seconds']} |")
    if doc.get("perscene"):
        lines += ["", "| scene | seconds | gnt dB / SSIM (steps) | density dB / SSIM (steps) |", "|---|---|---|---|"]
        for r in doc["perscene"]:
            g, d = r["gnt"], r["density"]
            lines.append(
                f"| {r['scene']} | {r['seconds']} | {g['psnr']} / {g['ssim']} ({g['steps']}) | "
                f"{d['psnr']} / {d['ssim']} ({d['steps']}) |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("runs/bench/gnt"))
    ap.add_argument("--only", default="fewview,real,perscene")
    ap.add_argument("--weights", default="pretrained")
    ap.add_argument("--density-seconds", type=float, default=30.0)
    ap.add_argument("--per-scene-seconds", type=float, default=900.0)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    parts = set(args.only.split(","))
    args.out.mkdir(parents=True, exist_ok=True)
    doc: dict = {"commit": commit(), "weights": args.weights}
    if "fewview" in parts:
        doc["fewview"] = fewview(args.out, args.weights, args.density_seconds, args.threads)
    if "real" in parts:
        doc["real"] = real(args.out, args.weights, args.threads)
    if "perscene" in parts:
        doc["perscene"] = perscene(args.out, args.per_scene_seconds, args.threads)
    (args.out / "bench_gnt.json").write_text(json.dumps(doc, indent=1))
    print(_tables(doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
