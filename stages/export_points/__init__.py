"""Stage `export-points`: a trained run -> a coloured point cloud with normals (binary PLY), by default upright in
the user's frame; what nerfstudio's `ns-export pointcloud` gives.

`nerfpipe export-points RUN_DIR OUT.ply [--num-points 1000000] [--acc-threshold 0.5]
[--frame upright|user|normalized] [--up x,y,z] [--bbox x0,y0,z0,x1,y1,z1] [--outlier-neighbors 20]
[--outlier-std-ratio 2] [--normal-step 0.002] [--no-reorient-normals] [--double] [--downscale F] [--seed 0]`

Steps:
1. Rays (`model.surface_points`): the training cameras at the size the run trained at, rendered in passes of
   interleaved pixel sub-grids until `num_points` rays gave a point. A ray gives one when its accumulated opacity
   is at least `acc_threshold` (0.5, as nerfstudio): the point at its expected depth, with its rendered colour, the
   background taken out. With `bbox`, points outside it (in the chosen frame) are dropped and do not count.
2. Cap: an even random subset (seeded) of `num_points` when the last pass overshot.
3. Outliers (`stages.export_points.geometry`): open3d's statistical rule (20 neighbours, 2 standard deviations, as
   nerfstudio calls it), with scipy's cKDTree. So the cloud holds at most `num_points` points.
4. Normals: -grad sigma normalised, by central differences of the density with a step of `normal_step` of the
   scene box's diagonal (why: the geometry module's doc); a run with a signed distance (the sdf method's) gives
   +grad f normalised instead, the same differences of its distance (`model.surface_points.sdf_normals`), and a
   point outside the distance's box (a real capture's surroundings) the reverse of its ray, counted; with
   `reorient_normals` (default, as nerfstudio) a normal that faces away from the camera whose ray gave the point
   is flipped.
5. Output frame (`data.export_frame`): "upright" (default) the user's frame (the one `convert` started from, e.g.
   COLMAP's; `p_scene = applied_scale * (applied_transform @ [p_src; 1])`, docs/DESIGN.md) turned so that the
   scene's up is +Z, the point-cloud tools' up; "user" that frame as it came in; "normalized" the scene frame the
   field was trained in; normals by the inverse transpose. The matrices are the report's `out_from_scene` and
   `out_from_source`. As `stages.mesh`'s `frame`, `up` and `bbox`.
6. Written atomically (`stages.export_points.ply`: binary PLY, x y z float (double with `double`), nx ny nz float,
   red green blue uchar); the PLY takes its name only after `OUT.report.json` next to it (`cloud.ply` ->
   `cloud.report.json`) is written.

Self-check (the report's `check`: ok | suspect, `checks`: `data.checks`):
- `ray_hit_fraction`: share of the rendered rays that gave a point (opaque enough), at least `MIN_HIT_FRACTION`:
  almost none means the views miss the object or the field is (nearly) empty.
- `outlier_fraction`: share of the points the statistical rule removed, at most `MAX_OUTLIER_FRACTION`: the rule
  takes a few % of a clean surface; far more means fog or floaters scattered through the volume.
- `normals_facing_camera`: share of the gradient normals that face the camera that saw their point (before they
  are reoriented), at least `MIN_FACING`: a surface seen from outside faces its cameras; a lower share means the
  gradient is noise at the points (an untrained or foggy field, or points inside semi-transparent volume).
- `non_finite`: rays whose opacity, or an opaque ray's depth or colour, is NaN / inf: 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.checks import Check, verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.export_frame import check_frame_options, export_frame
from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.data.rundir import config_to_json, write_manifest
from nerfpipe.model import camera_path, can, load_trained, require, require_any
from nerfpipe.model.surface_points import NORMAL_RULES, Gathered, facing_share, gather_points, surface_normals
from nerfpipe.stages.export_points.geometry import statistical_outliers, to_frame
from nerfpipe.stages.export_points.ply import ply_properties, write_ply

__all__ = ["Config", "Outputs", "run", "export", "MIN_HIT_FRACTION", "MAX_OUTLIER_FRACTION", "MIN_FACING"]

MIN_HIT_FRACTION = 0.01
"""Self-check: at least this share of the rendered rays gives a point."""
MAX_OUTLIER_FRACTION = 0.2
"""Self-check: the statistical rule removes at most this share of the points."""
MIN_FACING = 0.7
"""Self-check: at least this share of the gradient normals face the camera that saw their point."""
TRANSFORM = "p_out = out_from_scene @ [p_scene; 1]; normals by the inverse transpose of its 3x3, renormalised"


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json + checkpoint.pt from `train`)."""
    out: Path
    """Output point cloud (.ply); OUT.report.json goes next to it."""
    num_points: int = 1_000_000
    """Points to gather (nerfstudio's default); outlier removal then takes a few % off."""
    acc_threshold: float = 0.5
    """A ray gives a point when its accumulated opacity is at least this (0 < value <= 1)."""
    frame: Literal["upright", "user", "normalized"] = "upright"
    """Output (and bbox) frame: "upright" = the user's frame turned so that the scene's up is +Z, the scene's centre at
    the origin (`data.export_frame`); "user" = the source frame before convert, as it came in (e.g. COLMAP's);
    "normalized" = the scene frame the field was trained in."""
    up: tuple[float, float, float] | None = None
    """With frame "upright": the scene's up as a direction x,y,z in the user's frame; None: the scene frame's +z
    (convert's choice: the cameras' mean up for COLMAP and LLFF worlds)."""
    bbox: tuple[float, float, float, float, float, float] | None = None
    """Keep only points inside this box, (x0, y0, z0, x1, y1, z1) in the frame chosen by `frame`; None: all."""
    outlier_neighbors: int = 20
    """Statistical outlier removal: neighbours compared per point (0: no outlier removal)."""
    outlier_std_ratio: float = 2.0
    """Statistical outlier removal: a point goes when its mean neighbour distance exceeds the mean over all
    points by more than this many standard deviations."""
    normal_step: float = 0.002
    """Central-difference step of the density's (or signed distance's) gradient, the normals, as a fraction of the
    scene box's diagonal."""
    reorient_normals: bool = True
    """Flip normals that face away from the camera whose ray gave the point."""
    double: bool = False
    """Write coordinates as 64-bit doubles (a geo-referenced user frame with large coordinates); the default 32-bit
    floats are what web clients read (three.js refuses 64-bit buffers)."""
    downscale: float | None = None
    """Render the training cameras at 1/downscale of their size (None: the factor the run trained at)."""
    seed: int = 0
    """Seed of the pass order and of the subset taken when more than num_points were gathered."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:N."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out: Path
    """The PLY file."""
    report: Path
    """OUT.report.json next to it (written last)."""
    points: int
    """Points written."""
    rays: int
    """Rays rendered."""
    outliers: int
    """Points the statistical rule removed."""
    seconds: float


def _validate(config: Config) -> None:
    if Path(config.out).suffix.lower() != ".ply":
        raise UserError(f"{config.out}: expected a .ply output file")
    if config.num_points < 1:
        raise UserError(f"num_points: expected at least 1, got {config.num_points}")
    if not 0 < config.acc_threshold <= 1:
        raise UserError(f"acc_threshold: expected a value in (0, 1], got {config.acc_threshold}")
    check_frame_options(config.frame, config.up)
    if config.bbox is not None:
        b = np.asarray(config.bbox, np.float64)
        if b.shape != (6,) or not np.isfinite(b).all() or not (b[3:] > b[:3]).all():
            raise UserError(f"bbox: expected x0,y0,z0,x1,y1,z1 with x1 > x0, y1 > y0, z1 > z0, got {config.bbox}")
    if config.outlier_neighbors < 0:
        raise UserError(f"outlier_neighbors: expected 0 (no removal) or more, got {config.outlier_neighbors}")
    if not config.outlier_std_ratio > 0:
        raise UserError(f"outlier_std_ratio: expected > 0, got {config.outlier_std_ratio}")
    if not 0 < config.normal_step < 1:
        raise UserError(f"normal_step: expected a fraction of the box diagonal in (0, 1), got {config.normal_step}")
    if config.downscale is not None and not config.downscale > 0:
        raise UserError(f"downscale: expected > 0, got {config.downscale}")


def _inside(config: Config, out_from_scene: np.ndarray):
    """keep(points_scene) for `gather_points`: inside config.bbox in the output frame; None without a bbox."""
    if config.bbox is None:
        return None
    b = np.asarray(config.bbox, np.float64)
    m = out_from_scene

    def keep(points: np.ndarray) -> np.ndarray:
        p = points @ m[:3, :3].T + m[:3, 3]
        return ((p >= b[:3]) & (p <= b[3:])).all(axis=1)

    return keep


def _checks(g: Gathered, outlier_share: float, facing: float) -> list[Check]:
    return [
        Check.lower(
            "ray_hit_fraction",
            (len(g.points) + g.outside) / max(1, g.rays),
            MIN_HIT_FRACTION,
            "almost no ray is opaque enough to give a point: the views miss the object or the field is empty",
        ),
        Check.upper(
            "outlier_fraction",
            outlier_share,
            MAX_OUTLIER_FRACTION,
            "the statistical rule removed many points: fog or floaters scattered through the volume",
        ),
        Check.lower(
            "normals_facing_camera",
            facing,
            MIN_FACING,
            "the gradient at the points is noise (normals face away from the cameras that saw them): an "
            "untrained or foggy field",
        ),
        Check.upper(
            "non_finite",
            g.non_finite,
            0,
            "NaN or inf opacity, depth or colour: the field's output is broken there (those rays were dropped)",
        ),
    ]


def export(trained: Any, config: Config, *, inputs: tuple[Path, ...] = (), progress: Progress | None = None) -> Outputs:
    """Export the points of an already loaded run (`model.run.Run` with the capabilities rays and density or sdf
    (the normals), and colour for coloured points). `run` loads and calls this."""
    started, t0 = time.time(), time.perf_counter()
    _validate(config)
    require(trained, "rays", stage="export-points")
    require_any(trained, tuple(NORMAL_RULES), stage="export-points")  # the normals' (before any ray is rendered)
    out, scene = Path(config.out), trained.scene
    timing: dict[str, float] = {}
    out_from_scene, frame_info = export_frame(scene.source_from_scene(), config.frame, "points", config.up)
    downscale = config.downscale or trained.downscale
    cams = camera_path(scene, "train", downscale=downscale)
    g = gather_points(
        trained,
        cams,
        target=config.num_points,
        acc_threshold=config.acc_threshold,
        keep=_inside(config, out_from_scene),
        seed=config.seed,
        progress=progress,
    )
    timing["render"] = round(time.perf_counter() - t0, 3)
    if len(g.points) == 0:
        where = (
            f" inside bbox {[float(v) for v in config.bbox]} ({config.frame} frame)" if config.bbox is not None else ""
        )
        raise UserError(
            f"{config.run_dir}: none of the {g.rays} rays rendered gave a point{where} (accumulated "
            f"opacity >= {config.acc_threshold}, acc_threshold); nothing to export"
        )
    points, rgb, dirs = g.points, g.rgb, g.dirs
    over = max(0, len(points) - config.num_points)
    if over:
        pick = np.sort(np.random.default_rng(config.seed).choice(len(points), config.num_points, replace=False))
        points, rgb, dirs = points[pick], rgb[pick], dirs[pick]

    t = time.perf_counter()
    keep, outliers = statistical_outliers(points, config.outlier_neighbors, config.outlier_std_ratio)
    gathered = len(points)
    points, rgb, dirs = points[keep], rgb[keep], dirs[keep]
    timing["outliers"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    box = np.asarray(trained.aabb.tolist(), np.float64).reshape(2, 3)  # a tensor or an array
    step = config.normal_step * float(np.linalg.norm(box[1] - box[0]))
    normals, from_gradient, rule = surface_normals(trained, points, dirs, step, trained.device, stage="export-points")
    facing = facing_share(normals[from_gradient], dirs[from_gradient])
    flipped = np.einsum("ij,ij->i", normals, dirs.astype(np.float64)) > 0  # facing away from its camera
    flipped &= config.reorient_normals
    normals[flipped] *= -1
    timing["normals"] = round(time.perf_counter() - t, 3)

    p_out, n_out = to_frame(out_from_scene, points, normals)
    colors = np.rint(rgb.astype(np.float64) * 255).astype(np.uint8)
    record = {
        "used": {
            "config": config_to_json(config),
            "downscale": downscale,
            "device": str(trained.device),
            "cameras": {**cams.used, "count": len(cams.names)},
        },
        "left_out": _left_out(trained, config, outliers),
        "points": len(p_out),
        **frame_info,
        "out_from_scene": out_from_scene.tolist(),
        "transform": TRANSFORM,
        "rays": {
            "pixels": g.pixels,
            "stride": g.stride,
            "passes": g.passes,
            "of_passes": g.stride**2,
            "rendered": g.rays,
            "opaque": g.opaque,
            "gave_points": len(g.points),
        },
        "removed": _removed(config, g, over, outliers),
        "normals": {
            "rule": rule.words,
            "step_scene": step,
            "from_view_direction": int((~from_gradient).sum()),
            "reoriented": int(flipped.sum()),
            "facing_camera_before_reorienting": facing,
        },
        "colors": "rendered colour with the background taken out: (rgb - (1 - acc) * background) / acc, uint8",
        "ply": {
            "format": "binary_little_endian 1.0",
            "properties": [f"{k} {n}" for n, _, k in ply_properties(config.double)],
        },
        **verdict(_checks(g, outliers.get("removed", 0) / max(1, gathered), facing)),
    }
    t = time.perf_counter()
    with atomic_path(out) as tmp:  # OUT takes its name only after its report: no OUT that looks complete before
        comments = (f"nerfpipe export-points, frame {config.frame}",)
        write_ply(tmp, p_out, n_out, colors, comments=comments, double=config.double)
        timing["write"] = round(time.perf_counter() - t, 3)
        timing["total"] = round(time.perf_counter() - t0, 3)
        report = write_manifest(
            out.parent,
            name=f"{out.stem}.report.json",
            stage="export-points",
            started=started,
            inputs=inputs,
            outputs=[out],
            timing_seconds=timing,
            **record,
        )
    return Outputs(
        out=out, report=report, points=len(p_out), rays=g.rays, outliers=gathered - len(points), seconds=timing["total"]
    )


def _left_out(trained: Any, config: Config, outliers: dict[str, Any]) -> dict[str, str]:
    left_out = {}
    if not can(trained, "color"):
        left_out["colors"] = "the run's field is density-only: every colour is the evaluation background"
    if config.bbox is None:
        left_out["bbox"] = "no bbox given: every point kept"
    if not outliers["applied"]:
        left_out["outliers"] = outliers["why"]
    return left_out


def _removed(config: Config, g: Gathered, over: int, outliers: dict[str, Any]) -> list[dict[str, Any]]:
    """The report's `removed`: each step that dropped rays or points, how many, and why."""
    cap = (
        f"an even random subset (seed {config.seed}) of {config.num_points} of the {len(g.points)} gathered"
        if over
        else f"{len(g.points)} gathered, not over {config.num_points}"
    )
    return [
        {
            "what": "rays below acc_threshold",
            "count": g.rays - g.opaque,
            "why": f"accumulated opacity < {config.acc_threshold}: background (the ray more likely misses than hits)",
        },
        {"what": "non-finite", "count": g.non_finite, "why": "NaN / inf opacity, or depth or colour of an opaque ray"},
        {
            "what": "outside bbox",
            "count": g.outside,
            "why": f"bbox {list(config.bbox)} ({config.frame} frame)" if config.bbox is not None else "no bbox",
        },
        {"what": "over num_points", "count": over, "why": cap},
        {
            "what": "statistical outliers",
            "count": outliers.get("removed", 0),
            "why": "mean distance to the k nearest points > mean + std_ratio * std (open3d's rule)",
            **outliers,
        },
    ]


def run(config: Config, progress: Progress | None = None) -> Outputs:
    """Load RUN_DIR with `model.load_trained` and export its points (see the module doc)."""
    _validate(config)
    run_dir = Path(config.run_dir)
    trained = load_trained(run_dir, config.device)
    inputs = tuple(p for p in (run_dir / "config.json", run_dir / "checkpoint.pt") if p.is_file())
    return export(trained, config, inputs=inputs, progress=progress or NO_PROGRESS)
