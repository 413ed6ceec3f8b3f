"""The SDF method against the density method on the same photos and the same seconds (issue 48): one table.

Run: .venv/bin/python -m benchmarks.bench_sdf --out runs/bench/sdf [--seconds 300]   (make bench-sdf)

The scene is `make bench-mesh`'s synthetic posed one (`stages.scene` kind posed, 128 px, 48 views, five objects on a
disk on white: a box scene), made once in OUT. Rows: the density method and the sdf method, each `train
--max-seconds SECONDS`; the sdf method stopped at 300 steps (the under-trained case: its mesh within 1 % of the
diagonal, or its self-check says suspect). Each run is meshed at 256 by `stages.mesh` in the ground truth's frame
and scored as `bench_mesh` scores it (Chamfer over the surface a training camera sees, % of the diagonal). Steps
depend on the machine: each row gives its own.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from benchmarks.bench_mesh import _in_subprocess, trained_run

__all__ = ["main"]

RESOLUTION = 256
UNDER_TRAINED_STEPS = 300


def _row(out: Path, name: str, method: str, seconds: float, steps: int | None) -> dict:
    run_dir, src = trained_run(out, seconds, method, name=name, max_steps=steps)
    used = json.loads((run_dir / "manifest.json").read_text())
    spec = {
        "kind": name,
        "resolution": RESOLUTION,
        "run_dir": str(run_dir),
        "scene_src": str(src),
        "out": str(out / f"{name}_mesh" / "mesh.ply"),
    }
    mesh = _in_subprocess(spec)
    failed = [f"{c['name']} {c['value']}" for c in used["checks"] if not c["ok"]]
    return {
        "row": name,
        "method": method,
        "limit": f"{steps} steps" if steps is not None else f"{seconds:g} s",
        "steps": used["used"]["steps"],
        "train_seconds": used["used"]["train_seconds"],
        "test_psnr": used["used"]["test_psnr"],
        "train_check": used["check"] + (f" ({', '.join(failed)})" if failed else ""),
        "sdf": used["used"].get("sdf"),
        "chamfer_pct_diag": mesh["chamfer_pct_diag"],
        "watertight": mesh["watertight"],
        "faces": mesh["faces"],
    }


def _table(rows: list[dict]) -> str:
    lines = [
        "| run | limit | steps | held-out PSNR | train self-check | Chamfer % diag | mesh faces |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['row']} | {r['limit']} | {r['steps']} | {r['test_psnr']:.2f} dB | {r['train_check']} | "
            f"{r['chamfer_pct_diag']:.3f} | {r['faces']} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench/sdf"))
    p.add_argument("--seconds", type=float, default=300.0)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = [
        _row(args.out, "density", "density", args.seconds, None),
        _row(args.out, "sdf", "sdf", args.seconds, None),
        _row(args.out, f"sdf_{UNDER_TRAINED_STEPS}_steps", "sdf", args.seconds, UNDER_TRAINED_STEPS),
    ]
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    table = _table(rows)
    print(table)
    print(f"{time.perf_counter() - t0:.0f} s in all")


if __name__ == "__main__":
    main()
