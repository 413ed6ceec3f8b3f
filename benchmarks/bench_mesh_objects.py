"""Does a run's mesh keep every object of the synthetic scene (issue 52)? Against the scene's ground-truth mesh.

Run: .venv/bin/python -m benchmarks.bench_mesh_objects RUN_DIR MESH.ply GROUND_TRUTH_DIR [--tol 0.02]

MESH is a mesh of RUN_DIR written with `--frame normalized` (the scene frame); GROUND_TRUTH_DIR is the `scene`
stage's `ground_truth/` (cameras.json, mesh.ply: closed primitives, up +z, a ground slab under the objects). The
ground truth is mapped into the scene frame by the similarity that takes its camera centres onto the run's
(Umeyama, least squares over the frames both hold: the run's poses are COLMAP's, up to a similarity). Then, per
ground-truth primitive above the ground (its top over the slab's top by more than `tol`), the share of its surface
samples higher than the slab's top by `tol` that lie within `tol` (ground-truth units, metres) of the mesh:
`recall` (1.0: all of it meshed; an object the mesh lacks scores ~0). Also the share of the mesh's area above the
slab's top by `tol`, beside the ground truth's (the issue's "4.6 % of the surface area lies above the disk").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

__all__ = ["main", "scene_from_ground_truth", "umeyama"]


def umeyama(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The similarity [4, 4] taking points src [N, 3] onto dst [N, 3] in least squares (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    rot = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s) / a.var(0).sum())
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = mu_d - scale * rot @ mu_s
    return m


def scene_from_ground_truth(run_dir: Path, ground_truth: Path) -> tuple[np.ndarray, np.ndarray]:
    """The similarity [4, 4] taking the `scene` stage's ground-truth frame (GROUND_TRUTH/cameras.json) into the
    run's scene frame, fitted on the camera centres both hold, and each centre's residual [N] (scene units)."""
    cfg = json.loads((run_dir / "config.json").read_text())
    transforms = json.loads((Path(cfg["scene_dir"]) / "transforms.json").read_text())  # the scene frame's cameras
    gt = json.loads((ground_truth / "cameras.json").read_text())
    ours = {
        Path(f["file_path"]).stem: np.asarray(f["transform_matrix"], np.float64)[:3, 3] for f in transforms["frames"]
    }
    stems = sorted(set(ours) & set(gt["frames"]))
    src = np.stack([np.asarray(gt["frames"][k]["world_from_cam"], np.float64)[:3, 3] for k in stems])
    dst = np.stack([ours[k] for k in stems])
    scene_from_gt = umeyama(src, dst)
    return scene_from_gt, np.linalg.norm(src @ scene_from_gt[:3, :3].T + scene_from_gt[:3, 3] - dst, axis=1)


def _area_above(verts: np.ndarray, faces: np.ndarray, height: np.ndarray, level: float) -> float:
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return float(area[height[faces].mean(axis=1) > level].sum() / area.sum())


def main(argv: list[str] | None = None) -> dict:
    import trimesh
    from scipy.spatial import cKDTree

    from benchmarks.mesh_metrics import surface_points

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("mesh", type=Path)
    p.add_argument("ground_truth", type=Path)
    p.add_argument("--tol", type=float, default=0.02, help="metres (ground-truth units)")
    args = p.parse_args(argv)

    scene_from_gt, residual = scene_from_ground_truth(args.run_dir, args.ground_truth)
    scale = float(np.cbrt(np.linalg.det(scene_from_gt[:3, :3])))

    truth = trimesh.load(args.ground_truth / "mesh.ply", force="mesh", process=False)
    parts = truth.split(only_watertight=False)
    ground = max(parts, key=lambda m: m.area)  # the slab
    top = float(np.asarray(ground.vertices)[:, 2].max())
    mesh = trimesh.load(args.mesh, force="mesh", process=False)
    gt_from_scene = np.linalg.inv(scene_from_gt)
    v = np.asarray(mesh.vertices, np.float64) @ gt_from_scene[:3, :3].T + gt_from_scene[:3, 3]  # ours, GT frame
    tree = cKDTree(surface_points(v, np.asarray(mesh.faces), 400_000))
    objects = []
    for k, part in enumerate(parts):
        pv = np.asarray(part.vertices)
        if part is ground or pv[:, 2].max() <= top + args.tol:
            continue
        pts = surface_points(pv, np.asarray(part.faces), 20_000, seed=k)
        pts = pts[pts[:, 2] > top + args.tol]  # the part the cameras can see above the slab
        near = tree.query(pts, distance_upper_bound=args.tol)[0] < args.tol
        centre = pv.mean(axis=0).round(3).tolist()
        objects.append(
            {"centre_gt": centre, "height": round(float(pv[:, 2].max() - top), 3), "recall": float(near.mean())}
        )
    result = {
        "run": str(args.run_dir),
        "mesh": str(args.mesh),
        "tol_m": args.tol,
        "alignment": {"frames": len(residual), "camera_residual_m_max": float(residual.max() / scale)},
        "objects": objects,
        "min_object_recall": min(o["recall"] for o in objects) if objects else None,
        "area_above_ground": {
            "mesh": _area_above(v, np.asarray(mesh.faces), v[:, 2], top + args.tol),
            "ground_truth": _area_above(
                np.asarray(truth.vertices), np.asarray(truth.faces), np.asarray(truth.vertices)[:, 2], top + args.tol
            ),
        },
    }
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
