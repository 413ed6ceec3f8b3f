"""The SDF method against the density method on the same photos and the same seconds (issue 48): one table.

Run: .venv/bin/python -m benchmarks.bench_sdf --out runs/bench/sdf [--seconds 300]   (make bench-sdf)
     .venv/bin/python -m benchmarks.bench_sdf --out runs/bench/sdf_scenes --scenes [--seconds 180]
         [--only slab,demo,bunny,cow,airplane]                                    (make bench-sdf-scenes)

The scene is `make bench-mesh`'s synthetic posed one (`stages.scene` kind posed, 128 px, 48 views, five objects on a
disk on white: a box scene), made once in OUT. Rows: the density method and the sdf method, each `train
--max-seconds SECONDS`; the sdf method stopped at 300 steps (the under-trained case: its mesh within 1 % of the
diagonal, or its self-check says suspect). Each run is meshed at 256 by `stages.mesh` in the ground truth's frame
and scored as `bench_mesh` scores it (Chamfer over the surface a training camera sees, % of the diagonal). Steps
depend on the machine: each row gives its own.

With --scenes the scenes are instead the five objects on their slab photographed on a transparent background (`scene
--kind rgba`, 128 px, 60 views), `make demo`'s scene (the same objects on white, 256 px, 40 views, here with exact
poses) and the scanned meshes pymeshlab's wheel ships (`pymeshlab/tests/sample_meshes`:
bunny, cow, airplane), each photographed by `scene --kind rgba --subject mesh` (128 px, 60 views); both methods
trained the same seconds (180 by default), meshed and scored the same way; the table adds the mesh's connected
pieces and whether it is watertight.

Where the scene is the five objects (every row but the scans'), a row also says how many objects its mesh kept: an
object is kept when at least half of its visible surface (200k points by area, those a training camera sees) lies
within 1 % of the scene's diagonal of the mesh.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from benchmarks.bench_mesh import _in_subprocess, trained_run
from benchmarks.mesh_metrics import scanned_mesh_file

__all__ = ["main"]

RESOLUTION = 256
UNDER_TRAINED_STEPS = 300
SCANS = ("bunny", "cow", "airplane")
SCENE_VIEWS, SCENE_SIZE = 60, 128
DEMO_VIEWS, DEMO_SIZE = 40, 256
"""`make demo`'s scene (pipelines/demo.mk: 256 px, 40 views, seed 0), here with its exact poses (the demo's come
from COLMAP) and a white background."""
KEPT_SHARE, KEPT_TOL = 0.5, 0.01
"""An object is kept when this share of its visible surface lies within this fraction of the diagonal of the mesh."""


def _row(out: Path, name: str, method: str, seconds: float, steps: int | None, scene_args: dict | None = None) -> dict:
    run_dir, src = trained_run(out, seconds, method, name=name, max_steps=steps, scene_args=scene_args)
    used = json.loads((run_dir / "manifest.json").read_text())
    spec = {
        "kind": name,
        "resolution": RESOLUTION,
        "run_dir": str(run_dir),
        "scene_src": str(src),
        "out": str(out / f"{name}_mesh" / "mesh.ply"),
    }
    mesh = _in_subprocess(spec)
    kept = objects_kept(Path(spec["out"]), src)
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
        "bodies": mesh["bodies"],
        "faces": mesh["faces"],
        "objects_kept": kept,
    }


def _table(rows: list[dict]) -> str:
    lines = [
        "| run | limit | steps | held-out PSNR | train self-check | Chamfer % diag | objects kept | mesh faces |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['row']} | {r['limit']} | {r['steps']} | {r['test_psnr']:.2f} dB | {r['train_check']} | "
            f"{r['chamfer_pct_diag']:.3f} | {_kept(r)} | {r['faces']} |"
        )
    return "\n".join(lines)


def objects_kept(mesh_path: Path, src: Path) -> list[float] | None:
    """The share of each object's visible surface within KEPT_TOL of the diagonal of the mesh (module doc), for a
    scene of the five objects (`stages.scene` subject objects, scale 1); None for another subject."""
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree

    from benchmarks.bench_mesh import _mesh_points
    from benchmarks.mesh_metrics import surface_points
    from benchmarks.standin import visible_points
    from nerfpipe.data.synthetic.objects import default_primitives

    config = json.loads((src / "manifest.json").read_text())["config"]
    if config["subject"] != "objects" or config["scale"] != 1.0:
        return None
    truth = trimesh.load(src / "ground_truth" / "mesh.ply", force="mesh", process=False)
    tol = KEPT_TOL * float(np.linalg.norm(truth.extents))
    tree = cKDTree(_mesh_points(mesh_path, 400_000))
    shares = []
    for prim in default_primitives(config["seed"])[1:]:  # the slab first, then the five objects
        m = prim.mesh()
        points = surface_points(np.asarray(m.vertices), np.asarray(m.faces), 200_000, seed=3)
        points = points[visible_points(points, src)]
        shares.append(float((tree.query(points)[0] < tol).mean()))
    return shares


def _cases() -> dict[str, dict]:
    """--scenes' cases: name -> the `stages.scene.Config` arguments of its scene (module doc)."""
    photos = {"kind": "rgba", "size": SCENE_SIZE, "views": SCENE_VIEWS}
    demo = {"kind": "posed", "size": DEMO_SIZE, "views": DEMO_VIEWS}
    scans = {scan: {**photos, "subject": "mesh", "mesh": scanned_mesh_file(scan)} for scan in SCANS}
    return {"slab": photos, "demo": demo} | scans


def _scene_rows(out: Path, seconds: float, only: list[str] | None) -> list[dict]:
    cases = _cases()
    if only is not None and (unknown := set(only) - set(cases)):
        raise SystemExit(f"bench_sdf --only: unknown {sorted(unknown)}; expected some of {list(cases)}")
    rows = []
    for case, args in cases.items():
        if only is not None and case not in only:
            continue
        for method in ("density", "sdf"):
            rows.append(
                {**_row(out / case, method, method, seconds, None, args), "row": f"{case} {method}", "scene": case}
            )
    return rows


def _kept(row: dict) -> str:
    shares = row.get("objects_kept")
    if shares is None:
        return ""
    kept = sum(s >= KEPT_SHARE for s in shares)
    return f"{kept}/{len(shares)} (least {min(shares):.2f})"


def _scene_table(rows: list[dict]) -> str:
    lines = [
        "| scene, method | steps | held-out PSNR | train self-check | Chamfer % diag | sdf / density | objects kept | "
        "pieces | watertight |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    density = {r["scene"]: r["chamfer_pct_diag"] for r in rows if r["method"] == "density"}
    for r in rows:
        ratio = r["chamfer_pct_diag"] / density[r["scene"]] if r["method"] == "sdf" else None
        lines.append(
            f"| {r['row']} | {r['steps']} | {r['test_psnr']:.2f} dB | {r['train_check']} | "
            f"{r['chamfer_pct_diag']:.3f} | {'' if ratio is None else f'{ratio:.2f}'} | {_kept(r)} | {r['bodies']} | "
            f"{'yes' if r['watertight'] else 'no'} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/bench/sdf"))
    p.add_argument("--seconds", type=float, default=None, help="train seconds (300; with --scenes 180)")
    p.add_argument(
        "--scenes", action="store_true", help="the slab, the demo's scene and the scanned meshes instead (module doc)"
    )
    p.add_argument(
        "--only", type=lambda v: v.split(","), default=None, help="with --scenes: these cases, comma-separated"
    )
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if args.scenes:
        rows = _scene_rows(args.out, args.seconds or 180.0, args.only)
        (args.out / "results.json").write_text(json.dumps(rows, indent=1))
        print(_scene_table(rows))
        print(f"{time.perf_counter() - t0:.0f} s in all")
        return
    args.seconds = args.seconds or 300.0
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
