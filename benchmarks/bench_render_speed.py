"""Inference render speed of trained runs (issue 28): rays/s of `load_trained(run).render_rays` (what render and
eval use), occupied samples whose density was evaluated per ray, and how far the result is from the plain
differentiable twin (the same march, every step at once, no early termination).

    .venv/bin/python -m benchmarks.bench_render_speed RUN_DIR [RUN_DIR ...] [--views 2] [--size 120]
        [--repeats 5] [--threads 1] [--no-check] [--save out.npz] [--compare before.npz] [--profile]
        [--json figures.jsonl --tag after]
    .venv/bin/python -m benchmarks.bench_render_speed --summarize figures.jsonl

For each run, `views` evenly spaced test cameras at `size` px on the short side; one repetition renders all of
them, timed as a whole (rays/s at the fastest and the median repetition, wall clock, and per CPU second of this
process, which a machine shared with other jobs disturbs less). Then, unless --no-check, untimed: samples per ray
(the marcher's `samples` output), the plain twin's render (`model.render(..., infer=None)`) and the largest
differences to it (rgb, acc, depths; early termination's bound is float32's epsilon) with the PSNR of the fast
render against it. `--save` writes the renders to an npz; `--compare` reads one that another checkout wrote and
prints the largest differences to it (0 when a change alters nothing but time). `--profile` prints a cProfile of
one repetition. It runs the checkout it is started from: measure a change A/B by running it from a copy of the
tree before the change and from this one in turn, each appending to one --json file with its --tag, then
`--summarize` pools every repetition per tag and run.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from nerfpipe.model import camera_path, load_trained, resolve_device
from nerfpipe.model.trained import Trained
from nerfpipe.radiance.camera import generate_rays

KEYS = ("rgb", "acc", "depth", "depth_median")


def _views(trained: Trained, n: int, size: int, device) -> list[tuple[Tensor, Tensor]]:
    """Rays (o, d) [R, 3] float32 of n evenly spaced test cameras at `size` px on the short side."""
    cams = camera_path(trained.scene, "test")
    picks = np.unique(np.linspace(0, len(cams.names) - 1, n).round().astype(int)).tolist()
    out = []
    for k in picks:
        intr = cams.intrinsics[k]
        intr = intr.scaled(size / min(intr.w, intr.h))
        o, d = generate_rays(intr, torch.as_tensor(np.asarray(cams.world_from_cams[k], dtype=np.float64)))
        out.append((o.to(device, torch.float32), d.to(device, torch.float32)))
    return out


def _render_all(trained: Trained, views) -> list[dict]:
    return [trained.render_rays(o, d) for o, d in views]


def _model_render(trained: Trained, o, d, **infer) -> dict:
    """`trained.render_rays`'s chunks through `model.render` directly, keeping `samples` (infer: its `infer=`)."""
    parts: dict[str, list] = {k: [] for k in (*KEYS, "samples")}
    with torch.no_grad():
        for i in range(0, o.shape[0], trained.chunk):
            out = trained.model.render(
                o[i : i + trained.chunk],
                d[i : i + trained.chunk],
                trained.background,
                train=False,
                median=True,
                **infer,
            )
            for k in KEYS:
                parts[k].append(out[k])
            parts["samples"].append(float(out["samples"]))
    return {**{k: torch.cat(parts[k]) for k in KEYS}, "samples": sum(parts["samples"])}


def _psnr(a: Tensor, b: Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else -10 * float(np.log10(mse))


def _largest(a: dict, b: dict) -> dict[str, float]:
    """Largest |a - b| of each output over the finite values (depth_median is inf where acc < 0.5)."""
    out = {}
    for k in KEYS:
        x, y = torch.as_tensor(a[k]), torch.as_tensor(b[k])
        both = torch.isfinite(x) & torch.isfinite(y)
        out[k] = float((x[both] - y[both]).abs().max()) if both.any() else 0.0
        out[f"{k}_finite_differs"] = int((torch.isfinite(x) != torch.isfinite(y)).sum())
    return out


def _profile(fn, top: int = 25) -> str:
    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    buf = io.StringIO()
    stats = pstats.Stats(prof, stream=buf)
    stats.sort_stats("cumulative").print_stats(top)
    stats.sort_stats("tottime").print_stats(top)
    return buf.getvalue()


def bench_run(
    run_dir: str, *, views: int, size: int, repeats: int, device, check: bool, profile: bool
) -> tuple[dict, dict]:
    """Speed, samples and the plain twin's differences of one run -> (figures, renders by 'view/key')."""
    trained = load_trained(run_dir, device)
    rays = _views(trained, views, size, device)
    n_rays = sum(o.shape[0] for o, _ in rays)
    trained.render_rays(rays[0][0][:4096], rays[0][1][:4096])  # warm-up (caches, allocator)
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fast = _render_all(trained, rays)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    res: dict = {
        "run": run_dir,
        "space": trained.space.name,
        "rays": n_rays,
        "views": len(rays),
        "seconds": [round(t, 3) for t in times],
        "cpu_seconds": [round(t, 3) for t in cpu],
        "rays_per_s_best": round(n_rays / min(times)),
        "rays_per_s_median": round(n_rays / statistics.median(times)),
        "rays_per_cpu_s_median": round(n_rays / statistics.median(cpu)),
    }
    if check:
        samples = sum(_model_render(trained, o, d)["samples"] for o, d in rays)
        res["samples_per_ray"] = round(samples / n_rays, 2)
        plain = [_model_render(trained, o, d, infer=None) for o, d in rays]
        diffs = [_largest(f, p) for f, p in zip(fast, plain, strict=True)]
        res["vs_plain_twin"] = {k: max(dd[k] for dd in diffs) for k in diffs[0]}
        res["vs_plain_twin"]["rgb_psnr_db"] = min(_psnr(f["rgb"], p["rgb"]) for f, p in zip(fast, plain, strict=True))
        res["plain_samples_per_ray"] = round(sum(p["samples"] for p in plain) / n_rays, 2)
    if profile:
        res["profile"] = _profile(lambda: _render_all(trained, rays))
    renders = {f"{i}/{k}": f[k].cpu().numpy() for i, f in enumerate(fast) for k in KEYS}
    return res, renders


def _print(res: dict) -> None:
    print(
        f"{res['run']} ({res['space']}): {res['views']} views, {res['rays']} rays; seconds {res['seconds']}; "
        f"rays/s best {res['rays_per_s_best']}, median {res['rays_per_s_median']} (per CPU second, median "
        f"{res['rays_per_cpu_s_median']})",
        flush=True,
    )
    if "vs_plain_twin" in res:
        print(
            f"  samples/ray {res['samples_per_ray']} (plain twin {res['plain_samples_per_ray']}); largest "
            f"difference to the plain twin: {res['vs_plain_twin']}",
            flush=True,
        )
    if "vs_saved" in res:
        print(f"  largest difference to the saved renders: {res['vs_saved']}", flush=True)
    if "profile" in res:
        print(res["profile"], flush=True)


def summarize(path: Path) -> list[dict]:
    """Lines of a --json file, pooled by (tag, run): every repetition's seconds -> rays/s at the fastest and the
    median repetition."""
    pooled: dict[tuple[str, str], dict] = {}
    for line in path.read_text().splitlines():
        res = json.loads(line)
        entry = pooled.setdefault((res["tag"], res["run"]), {"rays": res["rays"], "seconds": [], "cpu": []})
        entry["seconds"] += res["seconds"]
        entry["cpu"] += res["cpu_seconds"]
    out = []
    for (tag, run), e in sorted(pooled.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        best, med = e["rays"] / min(e["seconds"]), e["rays"] / statistics.median(e["seconds"])
        cpu_best, cpu_med = e["rays"] / min(e["cpu"]), e["rays"] / statistics.median(e["cpu"])
        print(
            f"{run} [{tag}]: {len(e['seconds'])} repetitions, rays/s best {best:.0f}, median {med:.0f}; per CPU "
            f"second best {cpu_best:.0f}, median {cpu_med:.0f}"
        )
        out.append(
            {
                "tag": tag,
                "run": run,
                "repetitions": len(e["seconds"]),
                "rays_per_s_best": round(best),
                "rays_per_s_median": round(med),
                "rays_per_cpu_s_best": round(cpu_best),
                "rays_per_cpu_s_median": round(cpu_med),
            }
        )
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dirs", nargs="*")
    ap.add_argument("--views", type=int, default=2, help="test cameras, evenly spaced")
    ap.add_argument("--size", type=int, default=120, help="pixels on the short side")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu", help="auto, cpu, cuda, cuda:N")
    ap.add_argument("--save", type=Path, default=None, help="write the renders to this npz")
    ap.add_argument("--compare", type=Path, default=None, help="an npz written by --save: print the differences")
    ap.add_argument("--no-check", dest="check", action="store_false", help="time only (no samples, no plain twin)")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--json", type=Path, default=None, help="append the figures to this file (one line a run)")
    ap.add_argument("--tag", default="", help="a label for --json (before, after)")
    ap.add_argument("--summarize", type=Path, default=None, help="a --json file: print each tag and run's figures")
    args = ap.parse_args(argv)
    if args.summarize is not None:
        return summarize(args.summarize)
    torch.set_num_threads(args.threads)
    dev = resolve_device(args.device)
    saved = dict(np.load(args.compare)) if args.compare is not None else None
    results, arrays = [], {}
    for i, run in enumerate(args.run_dirs):
        res, renders = bench_run(
            run,
            views=args.views,
            size=args.size,
            repeats=args.repeats,
            device=dev,
            check=args.check,
            profile=args.profile,
        )
        arrays.update({f"{i}/{k}": v for k, v in renders.items()})
        if saved is not None:
            views = sorted({k.split("/")[0] for k in renders})
            pairs = [({k: renders[f"{v}/{k}"] for k in KEYS}, {k: saved[f"{i}/{v}/{k}"] for k in KEYS}) for v in views]
            diffs = [_largest(a, b) for a, b in pairs]
            res["vs_saved"] = {k: max(dd[k] for dd in diffs) for k in diffs[0]}
        _print(res)
        results.append(res)
        if args.json is not None:
            with args.json.open("a") as f:
                f.write(json.dumps({"tag": args.tag, **{k: v for k, v in res.items() if k != "profile"}}) + "\n")
    if args.save is not None:
        np.savez(args.save, **arrays)
    return results


if __name__ == "__main__":
    main()
