"""`make bench-splat`: splats from bench-real's runs against their fields, on the same held-out views (issue 30).

For each run bench-real made (fox: a 300 s field; lego_400: a 900 s field), the commands a user types:

    nerfpipe splat RUN OUT/splats.ply --max-seconds 300
    nerfpipe eval OUT/splats.ply OUT/splats_eval.json [--views 25]
    nerfpipe eval RUN OUT/field_eval.json [--views 25]          # back to back, the same views

The table: held-out PSNR / SSIM of each, the gap (field - splats; the goal is <= 1.5 dB), the seconds a frame each
took to render in eval (CPU, same views), the splats' Gaussians, steps and training PSNR before / after, and the
splat report's self-check. Written as JSON and markdown to OUT/results.{json,md}.

    .venv/bin/python -m benchmarks.bench_splat                  # both (~20 min on 2 cores)
    .venv/bin/python -m benchmarks.bench_splat --only fox
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NERFPIPE = [sys.executable, "-m", "nerfpipe.cli"]
RUNS = {"fox": ([], "bench-real's fox run (300 s field)"), "lego_400": (["--views", "25"], "lego_400 (900 s field)")}
"""Run name -> (eval arguments, as bench-real scores it; what the run is)."""

__all__ = ["main"]


def _sh(cmd: list[str]) -> None:
    print("$ " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def measure(name: str, run: Path, out: Path, seconds: float) -> dict:
    eval_args, what = RUNS[name]
    out.mkdir(parents=True, exist_ok=True)
    ply = out / "splats.ply"
    _sh([*NERFPIPE, "splat", str(run), str(ply), "--max-seconds", str(seconds)])
    _sh([*NERFPIPE, "eval", str(ply), str(out / "splats_eval.json"), *eval_args])
    _sh([*NERFPIPE, "eval", str(run), str(out / "field_eval.json"), *eval_args])
    report, splats, field = (
        _json(p) for p in (out / "splats.report.json", out / "splats_eval.json", out / "field_eval.json")
    )
    return {
        "run": name,
        "what": what,
        "views": splats["n_views"],
        "field_psnr": field["psnr"],
        "field_ssim": field["ssim"],
        "splat_psnr": splats["psnr"],
        "splat_ssim": splats["ssim"],
        "gap_db": field["psnr"] - splats["psnr"],
        "field_s_per_frame": field["render_seconds"] / field["n_views"],
        "splat_s_per_frame": splats["render_seconds"] / splats["n_views"],
        "gaussians": report["gaussians"],
        "steps": report["steps"],
        "splat_seconds": report["seconds"],
        "kernel": report["used"].get("kernel"),
        "psnr_train_init": report["psnr_train_init"],
        "psnr_train_final": report["psnr_train_final"],
        "check": report["check"],
    }


def markdown(rows: list[dict]) -> str:
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    lines = [
        f"Measured at {head.strip()}, {time.strftime('%Y-%m-%d')}, 2-core CPU; load at the end "
        f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}. Command: `make bench-splat`.",
        "",
        "| run | views | field PSNR / SSIM | splats PSNR / SSIM | gap | s/frame field / splats | Gaussians | steps "
        "(s) | train PSNR init -> final | kernel | check |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['what']} | {r['views']} | {r['field_psnr']:.2f} dB / {r['field_ssim']:.3f} | "
            f"{r['splat_psnr']:.2f} dB / {r['splat_ssim']:.3f} | {r['gap_db']:.2f} dB | "
            f"{r['field_s_per_frame']:.2f} / {r['splat_s_per_frame']:.2f} | {r['gaussians']:,} | "
            f"{r['steps']} ({r['splat_seconds']:.0f}) | {r['psnr_train_init']:.2f} -> {r['psnr_train_final']:.2f} | "
            f"{r['kernel']} | {r['check']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=Path, default=ROOT / "runs" / "bench" / "real", help="bench-real's output folder")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "splat")
    p.add_argument("--only", default=",".join(RUNS))
    p.add_argument("--seconds", type=float, default=300.0, help="the splat stage's --max-seconds")
    args = p.parse_args(argv)
    rows = []
    for name in args.only.split(","):
        if name not in RUNS:
            p.error(f"unknown run {name!r}; expected some of {list(RUNS)}")
        run = args.runs / name / "run"
        if not (run / "checkpoint.pt").is_file():
            print(f"{name}: skipped, no trained run at {run} (make bench-real makes it)")
            continue
        rows.append(measure(name, run, args.out / name, args.seconds))
        print(json.dumps(rows[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    (args.out / "results.md").write_text(markdown(rows))
    print(markdown(rows))
    return rows


if __name__ == "__main__":
    main()
