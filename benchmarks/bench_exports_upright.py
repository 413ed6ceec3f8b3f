"""Does a run's GLB and splat PLY open upright in clients nobody here wrote (issue 52)? Screenshots and angles.

Run: .venv/bin/python -m benchmarks.bench_exports_upright RUN_DIR OUT_DIR [--ground-truth DIR] [--splat-seconds 60]

Makes the exports with the commands a user types and their defaults (`nerfpipe mesh RUN OUT/mesh.glb`, `nerfpipe
splat RUN OUT/splats.ply --max-seconds S`), opens each in Debian's headless Chromium: the GLB in a default three.js
scene (tests/js/three_glb.html: GLTFLoader, a PerspectiveCamera with three.js' default up, +Y), the splats in
gsplat.js with its default orbit camera (tests/js/gsplat_ply.html: its "above" is -Y, the 3DGS files'
convention). Writes the screenshots to OUT_DIR and prints one JSON document:

- `roll_deg`: the angle on the screen between the client camera's up and the scene's true up projected into the
  picture (0: the object stands upright on the screen; 180: upside down), and `axis_error_deg`: the angle between
  the true up and the client's up axis (+Y for three.js, -Y for gsplat.js), both in the file's frame (the true up
  mapped by the file's recorded `out_from_scene`). The true up: with --ground-truth (the `scene`
  stage's ground_truth/, +z up), its +z carried into the run's scene frame by the similarity fitted on the camera
  centres (`bench_mesh_objects.scene_from_ground_truth`); without it, the mean up of the training photos (the
  photographer's up: what a phone held upright records). That is the rule `convert` chose the scene's up by, so
  without a ground truth the figures check the chain (the file's frame, the client's reading of it), not the choice
  of up: the screenshots are the evidence for a person to look at.
- for the GLB, the screenshot against our own render of the field from the page's camera (mapped back into the
  scene frame): the PSNR over the pixels three.js draws the mesh on where the field is opaque, which says three.js
  drew the file in the frame the report records, and the silhouettes' IoU (meaningful for object scenes only: a
  real capture's field is opaque everywhere, its mesh is the object); `field_render.png` beside `three_glb.png`.

The scene's up the exports found is recorded in their reports (`up.source_up`). Needs node, `make js` and
chromium (as tests/test_export_clients.py).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import imageio.v2 as iio
import numpy as np
import torch

__all__ = ["main", "orbit_camera_axes", "angle_deg", "roll_deg"]

W, H, FOV = 480, 360, 40.0


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two directions [3], degrees."""
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def orbit_camera_axes(position: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The axes [3, 3] (columns: screen right, screen up, backwards; OpenGL's) of a camera at `position` looking at
    the origin with the up hint `up`."""
    back = position / np.linalg.norm(position)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(back, right), back], axis=1)


def roll_deg(axes: np.ndarray, up: np.ndarray) -> float:
    """The signed angle on the screen of a camera with `axes` [3, 3] (columns: right, up, back) from its up to the
    direction `up` [3] projected into the picture, degrees (0: up is straight up on the screen)."""
    u = axes.T @ up
    return math.degrees(math.atan2(u[0], u[1]))


def _nerfpipe(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "nerfpipe.cli", *args], check=True)


def _true_up(run_dir: Path, ground_truth: Path | None, trained) -> tuple[np.ndarray, str]:
    if ground_truth is not None:
        from benchmarks.bench_mesh_objects import scene_from_ground_truth

        scene_from_gt, _ = scene_from_ground_truth(run_dir, ground_truth)
        up = scene_from_gt[:3, :3] @ np.array([0.0, 0.0, 1.0])
        return up / np.linalg.norm(up), "the ground truth's +z, by the camera centres' similarity"
    ups = np.stack([np.asarray(f.world_from_cam)[:3, 1] for f in trained.scene.frames])  # OpenGL camera +Y
    up = ups.mean(axis=0)
    return up / np.linalg.norm(up), f"the mean up of the {len(ups)} photos"


def _direction(out_from_scene: np.ndarray, v: np.ndarray) -> np.ndarray:
    d = out_from_scene[:3, :3] @ v
    return d / np.linalg.norm(d)


def _field_render(trained, scene_from_out: np.ndarray, c2w_out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our render (rgb [H, W, 3], opacity [H, W]) from a camera given in the file's frame."""
    from nerfpipe.radiance.camera import Intrinsics, generate_rays

    scale = float(np.cbrt(np.linalg.det(scene_from_out[:3, :3])))
    c2w = np.eye(4)
    c2w[:3, :3] = scene_from_out[:3, :3] @ c2w_out[:3, :3] / scale
    c2w[:3, 3] = scene_from_out[:3, :3] @ c2w_out[:3, 3] + scene_from_out[:3, 3]
    f = (H / 2) / math.tan(math.radians(FOV) / 2)
    o, d = generate_rays(Intrinsics(w=W, h=H, fx=f, fy=f, cx=W / 2, cy=H / 2), torch.as_tensor(c2w))
    rgb, acc = [], []
    with torch.no_grad():
        for k in range(0, len(o), 8192):
            out = trained.render_rays(o[k : k + 8192].float(), d[k : k + 8192].float(), median=False)
            rgb.append(out["rgb"].cpu())
            acc.append(out["acc"].cpu())
    return torch.cat(rgb).numpy().reshape(H, W, 3), torch.cat(acc).numpy().reshape(H, W)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--ground-truth", type=Path, default=None)
    p.add_argument("--splat-seconds", type=float, default=60.0)
    args = p.parse_args(argv)
    from nerfpipe.model import load_trained
    from tests.test_export_clients import _page_result, _serve

    args.out.mkdir(parents=True, exist_ok=True)
    glb, splats = args.out / "mesh.glb", args.out / "splats.ply"
    if not glb.is_file():
        _nerfpipe("mesh", str(args.run_dir), str(glb))
    if not splats.is_file():
        _nerfpipe("splat", str(args.run_dir), str(splats), "--max-seconds", str(args.splat_seconds))
    trained = load_trained(args.run_dir, "cpu")
    true_up, rule = _true_up(args.run_dir, args.ground_truth, trained)
    result: dict = {"run": str(args.run_dir), "true_up_scene": true_up.round(4).tolist(), "true_up_rule": rule}
    server, base = _serve(args.out)
    try:
        with tempfile.TemporaryDirectory() as profiles:  # Chromium's profiles, fresh each run
            page = _page_result(f"{base}/page/three_glb.html?file=mesh.glb&fov={FOV}&w={W}&h={H}", Path(profiles, "g"))
            shot = _page_result(f"{base}/page/gsplat_ply.html?file=splats.ply&w={W}&h={H}", Path(profiles, "s"))
    finally:
        server.shutdown()

    report = json.loads((args.out / "mesh.report.json").read_text())
    out_from_scene = np.asarray(report["out_from_scene"], np.float64)
    c2w = np.asarray(page["world_from_cam"], np.float64).reshape(4, 4).T  # three.js: column-major
    iio.imwrite(args.out / "three_glb.png", page["image"])
    rgb, acc = _field_render(trained, np.linalg.inv(out_from_scene), c2w)
    iio.imwrite(args.out / "field_render.png", (np.dstack([rgb, acc]) * 255).clip(0, 255).astype(np.uint8))
    mask, want = page["image"][..., 3] > 127, acc > 0.5
    both = mask & want
    mse = float(np.mean((page["image"][..., :3][both] / 255.0 - rgb[both]) ** 2)) if both.any() else math.nan
    result["glb"] = {
        "source_up": report["up"]["source_up"],
        "roll_deg": round(roll_deg(c2w[:3, :3], _direction(out_from_scene, true_up)), 2),
        "axis_error_deg": round(angle_deg(np.array([0.0, 1.0, 0.0]), _direction(out_from_scene, true_up)), 2),
        "silhouette_iou_vs_field": round(float(both.sum() / max((mask | want).sum(), 1)), 3),
        "psnr_vs_field_db": round(10 * math.log10(1 / mse), 2) if mse > 0 else None,
    }

    splat_report = json.loads((args.out / "splats.report.json").read_text())
    splat_from_scene = np.asarray(splat_report["out_from_scene"], np.float64)
    iio.imwrite(args.out / "gsplat.png", shot["image"])
    position = np.asarray(shot["position"], np.float64)
    axes = orbit_camera_axes(position, np.array([0.0, -1.0, 0.0]))
    up_file = _direction(splat_from_scene, true_up)
    result["splat"] = {
        "camera_position": position.round(3).tolist(),
        "roll_deg": round(roll_deg(axes, up_file), 2),
        "axis_error_deg": round(angle_deg(np.array([0.0, -1.0, 0.0]), up_file), 2),
        "drawn_share": round(float((shot["image"][..., 3] > 127).mean()), 3),
    }
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
