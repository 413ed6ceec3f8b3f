"""Stage `mesh`: a trained radiance field -> a triangle mesh (PLY / OBJ / GLB), in the user's frame by default.

`nerfpipe mesh RUN_DIR OUT.ply|.obj|.glb [--method density|poisson] [--resolution 256] [--threshold auto|VALUE]
[--bbox x0,...,z1] [--crop auto|looked-at|occupied|field] [--frame user|normalized] [--target-faces 300000]
[--no-cleanup] [--no-colors]`

Steps:
1. Box: `--bbox` (in the chosen frame), else `--crop` (`stages.mesh.crop`): for an object scene (alpha or a
   plain background) the occupied cells of the run's occupancy grid (one cell of margin; the run's aabb without
   a grid); for a real capture (contracted or forward-facing: the photos see walls and floors) the box of what
   the training views' central rays hit, with a support plane (the wall or table every camera faces) cut away.
   Never beyond the field's box (the inner box of a contracted scene). Voxels are cubes with `resolution` cells
   along the box's longest side.
2. Iso-level (`--threshold auto`, `stages.mesh.threshold`): march training-view rays through the field; on
   each ray take the density where the accumulated opacity 1 - exp(-integral sigma dt) first reaches 0.5 (the
   ray's median depth, `radiance.compositing.median_depth`: where the rendered surface is); the level is the
   median over the rays that reach 0.5 inside the box. So the mesh sits where depth maps put the surface, and
   the level does not depend on the grid resolution. Fewer than max(16, 1 %) of the rays reaching 0.5: the
   level falls back to ln 2 / (1 % of the aabb diagonal), the density at which 1 % of the box diagonal is half
   opaque.
3. Density on the grid (`stages.mesh.grid`: coarse-to-fine, cells of the run's occupancy grid marked empty
   are zero without querying the field), zero-padded so the surface is closed where it meets the box.
4. Marching cubes (scikit-image, Lewiner) at the level; faces wind counter-clockwise seen from outside
   (the side of lower density).
   `--method poisson` replaces steps 2-4 (`stages.mesh.poisson`): screened Poisson through the points where training
   rays become half opaque, with density-gradient normals, its unsupported hull trimmed, cut to the box.
5. Cleanup (`stages.mesh.cleanup`, pymeshlab) and quadric decimation to `--target-faces` (300k by default, a
   size a web viewer opens quickly; 0 keeps every face).
6. Vertex colours: `trained.color(x, -n)`, the colour a camera looking straight at the surface along the
   inward normal sees (a view-independent field ignores the direction). With `--texture`, texels take the mean of
   the field's renders of the training cameras that see them (`stages.mesh.texture_views`), the rest that colour.
7. Export in the output frame: `scene.source_from_scene()` for `--frame user` (winding reversed if it
   mirrors), identity for `--frame normalized`; written atomically, then `OUT.report.json` next to it
   (`mesh.ply` -> `mesh.report.json`, so several meshes in one folder keep their own reports).
8. Self-check (`stages.mesh.checks`; the report's `check`: ok | suspect and `checks`): the mesh against the scene's
   box (a mesh that spans it on every axis is the surroundings cut out by the box, a slab, not an object) and its
   count of sizeable connected components.

Frames: the scene (normalized, training) frame is where the field lives; the user (source) frame is the one
`convert` started from: `p_scene = applied_scale * (applied_transform @ [p_src; 1])` (docs/DESIGN.md).
"""

from __future__ import annotations

import math
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.checks import verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import config_to_json, write_manifest
from nerfpipe.stages.mesh.checks import mesh_checks
from nerfpipe.stages.mesh.cleanup import Cleanup, cleanup_mesh, mesh_stats, transform_mesh
from nerfpipe.stages.mesh.crop import SUPPORT_CLEARANCE, Plane, cut_density, default_box, drop_box_cut_pieces
from nerfpipe.stages.mesh.field_access import (
    as_np,
    density_function,
    field_device,
    has_color,
    occupancy_binary,
    surface_function,
    vertex_colors,
)
from nerfpipe.stages.mesh.grid import Grid, make_grid, sample_volume
from nerfpipe.stages.mesh.texture import bake_texture
from nerfpipe.stages.mesh.texture_files import write_glb_textured, write_obj_textured
from nerfpipe.stages.mesh.texture_views import TEXTURE_VIEWS, training_views
from nerfpipe.stages.mesh.threshold import auto_threshold

__all__ = [
    "Config",
    "Outputs",
    "Cleanup",
    "run",
    "extract",
    "auto_threshold",
    "density_function",
    "parse_threshold",
    "parse_bbox",
    "FORMATS",
]

VERSION = "1"
FORMATS = (".ply", ".obj", ".glb")


@dataclass(frozen=True, kw_only=True)
class Config:
    run_dir: Path
    """Trained run directory (config.json + checkpoint.pt from `train`)."""
    out: Path
    """Output mesh; the format follows the extension: .ply, .obj or .glb. OUT.report.json goes next to it."""
    method: Literal["density", "poisson"] = "density"
    """Surface extraction: "density" marching cubes on the density at the iso-level (steps 2-4); "poisson" screened
    Poisson on the points where training rays end, with density normals (`stages.mesh.poisson`, its defaults)."""
    resolution: int = 256
    """Voxels along the longest side of the box (cubic voxels)."""
    threshold: float | Literal["auto"] = "auto"
    """Iso-level on density (per scene-frame unit), or "auto" (median density at 50 % accumulated opacity
    along training rays; see the module doc)."""
    bbox: tuple[float, float, float, float, float, float] | None = None
    """Box to mesh, (x0, y0, z0, x1, y1, z1) in the frame chosen by `frame`; None: the box `crop` finds."""
    crop: Literal["auto", "looked-at", "occupied", "field"] = "auto"
    """Without a bbox, what to mesh: "looked-at" the box of what the training views' central rays hit, the
    support plane (a wall, floor, table) cut away (`stages.mesh.crop`); "occupied" the occupancy grid's occupied
    cells; "field" the field's whole (inner) box; "auto": occupied for object scenes (alpha or plain background),
    looked-at for real captures."""
    frame: Literal["user", "normalized"] = "user"
    """Output (and --bbox) frame: "user" = the source frame before convert (e.g. COLMAP's, metres for the
    synthetic scene); "normalized" = the scene frame the field was trained in."""
    target_faces: int = 300_000
    """Decimate to at most this many faces (quadric edge collapse); 0: keep all."""
    cleanup: Cleanup | None = field(default_factory=Cleanup)
    """Cleanup steps (None: the raw marching-cubes mesh, `--no-cleanup`)."""
    colors: bool = True
    """Write per-vertex colours from the field (ignored for density-only fields)."""
    texture: bool = False
    """Bake a texture from the field instead of vertex colours (`stages.mesh.texture`): OUT.obj writes OUT.obj,
    OUT.mtl and OUT.png; OUT.glb embeds the PNG. Not for .ply."""
    texture_size: int | None = None
    """Texture width = height in texels (a power of two); None: from the face count (256..2048)."""
    texture_views: int = TEXTURE_VIEWS
    """Training cameras whose renders colour the texels they see (`stages.mesh.texture_views`); 0: every texel
    coloured along its normal only."""
    coarse_resolution: int = 128
    """Coarse pass: the fine grid is evaluated only in blocks near the surface of a grid about this fine
    (>= resolution: every voxel is evaluated)."""
    threshold_rays: int = 2048
    """Training-view rays marched for `threshold="auto"`."""
    device: str = "auto"
    """Torch device for the field ("auto": CUDA when available)."""
    chunk: int = 1 << 18
    """Points per field query (memory vs speed)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    mesh: Path
    """The mesh file."""
    report: Path
    """OUT.report.json next to the mesh (written last)."""
    vertices: int
    faces: int
    threshold: float | None
    """The iso-level used (density per scene-frame unit); None for method poisson."""
    watertight: bool
    seconds: float


# ---------------------------------------------------------------------------------------------- CLI helpers


def parse_threshold(text: str) -> float | Literal["auto"]:
    """'auto' or a finite number (for the CLI)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise UserError(f"--threshold: expected 'auto' or a number, got {text!r}") from None
    if not math.isfinite(value):
        raise UserError(f"--threshold: expected a finite number, got {text!r}")
    return value


def parse_bbox(text: str) -> tuple[float, float, float, float, float, float] | None:
    """'auto' or 'x0,y0,z0,x1,y1,z1' (for the CLI)."""
    if text.strip().lower() == "auto":
        return None
    try:
        vals = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise UserError(f"--bbox: expected 'auto' or six numbers x0,y0,z0,x1,y1,z1, got {text!r}") from None
    if len(vals) != 6:
        raise UserError(f"--bbox: expected six numbers x0,y0,z0,x1,y1,z1, got {len(vals)} in {text!r}")
    return vals  # type: ignore[return-value]


def _validate(config: Config) -> None:
    if Path(config.out).suffix.lower() not in FORMATS:
        raise UserError(f"{config.out}: unknown mesh format; expected one of {', '.join(FORMATS)}")
    if config.texture and Path(config.out).suffix.lower() == ".ply":
        raise UserError(f"{config.out}: texture needs an .obj or .glb output (PLY holds no texture)")
    if config.texture_views < 0:
        raise UserError(f"texture_views: expected >= 0, got {config.texture_views}")
    if config.texture_size is not None and not (16 <= config.texture_size <= 8192):
        raise UserError(f"texture_size: expected 16..8192 texels, got {config.texture_size}")
    if not 8 <= config.resolution <= 2048:
        raise UserError(f"--resolution: expected 8..2048, got {config.resolution}")
    if config.threshold != "auto" and (isinstance(config.threshold, str) or not math.isfinite(float(config.threshold))):
        raise UserError(f"--threshold: expected 'auto' or a finite number, got {config.threshold!r}")
    if config.frame not in ("user", "normalized"):
        raise UserError(f"--frame: expected 'user' or 'normalized', got {config.frame!r}")
    if config.bbox is not None:
        b = np.asarray(config.bbox, np.float64)
        if b.shape != (6,) or not np.isfinite(b).all() or not (b[3:] > b[:3]).all():
            raise UserError(f"--bbox: expected x0,y0,z0,x1,y1,z1 with x1 > x0, y1 > y0, z1 > z0, got {config.bbox}")
    if config.target_faces != 0 and config.target_faces < 4:
        raise UserError(f"--target-faces: expected 0 (keep all) or at least 4, got {config.target_faces}")
    if config.method not in ("density", "poisson"):
        raise UserError(f"--method: expected 'density' or 'poisson', got {config.method!r}")
    if config.crop not in ("auto", "looked-at", "occupied", "field"):
        raise UserError(f"--crop: expected auto, looked-at, occupied or field, got {config.crop!r}")


# ---------------------------------------------------------------------------------------------- the stage


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _grid_for(config: Config, trained: Any, out_from_scene: np.ndarray) -> tuple[Grid, str, dict, Plane | None]:
    """(grid, the crop rule said in one phrase, the crop's report entry, the support plane to cut or None)."""
    stride = 1
    if config.coarse_resolution > 0 and config.resolution > config.coarse_resolution:
        stride = max(1, round(config.resolution / config.coarse_resolution))
    if config.bbox is not None:  # sample in the chosen frame, so the crop is exactly the user's box
        b = np.asarray(config.bbox, np.float64)
        scene_from_out = np.linalg.inv(out_from_scene)
        how = f"--bbox ({config.frame} frame)"
        return make_grid(b[:3], b[3:], config.resolution, stride, scene_from_out), how, {"rule": how}, None
    lo, hi, how, info, plane = default_box(config.crop, trained)
    return make_grid(lo, hi, config.resolution, stride), how, info, plane


def _marching_cubes(vol: np.ndarray, level: float, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    from skimage.measure import marching_cubes

    # "ascent": density grows into the object, so faces wind counter-clockwise seen from outside
    verts, faces, _, _ = marching_cubes(vol, level=level, gradient_direction="ascent", allow_degenerate=False)
    verts = grid.lo + (verts.astype(np.float64) - 1.0) * grid.h  # volume index -> grid frame (pad offset)
    return verts, faces.astype(np.int64)


def _export(path: Path, tmp: Path, verts: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> None:
    """Write the mesh to `tmp` in the format `path`'s extension names."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False)
    mesh.export(tmp, file_type=path.suffix.lower().lstrip("."))


def _level_checks(config: Config, level: float, stats: dict, grid: Grid, how: str) -> None:
    lo, hi = stats["min"], stats["max"]
    where = f"box {np.round(grid.lo, 4).tolist()}..{np.round(grid.hi, 4).tolist()} ({how})"
    if hi <= 0:
        raise UserError(f"{config.run_dir}: the field is empty (density 0 everywhere in the {where}); nothing to mesh")
    if config.threshold != "auto" and not lo < level < hi:
        raise UserError(
            f"--threshold {level:g} is outside the sampled density range [{lo:g}, {hi:g}] of the {where}; "
            "pick a value inside it or use --threshold auto"
        )
    if level >= hi:
        raise UserError(
            f"{config.run_dir}: the field is empty at the auto threshold {level:g} (max density {hi:g} in the "
            f"{where}); nothing to mesh"
        )
    if level <= lo:
        raise UserError(
            f"{config.run_dir}: the whole {where} is denser than the auto threshold {level:g} (min {lo:g}); "
            "give --bbox or --threshold"
        )


def extract(trained: Any, config: Config, *, inputs: tuple[Path, ...] = (), progress: Any | None = None) -> Outputs:
    """Mesh an already loaded field (anything with the `Trained` attributes: density, color, aabb,
    occupancy, scene). `run` loads the run and calls this. `progress`: an optional rich Progress."""
    started = time.time()
    t_start = time.perf_counter()
    _validate(config)
    out = Path(config.out)
    timing: dict[str, float] = {}
    task = progress.add_task(f"mesh {out.name}", total=7) if progress is not None else None

    def lap(name: str, t: float) -> float:
        now = time.perf_counter()
        timing[name] = round(now - t, 3)
        if task is not None:
            progress.advance(task)
        return now

    scene = trained.scene
    out_from_scene = scene.source_from_scene() if config.frame == "user" else np.eye(4)
    device = field_device(trained)
    surface = surface_function(trained)
    density = surface.values
    t = time.perf_counter()
    grid, how, crop_info, plane = _grid_for(config, trained, out_from_scene)
    t = lap("crop", t)

    keep_beyond = SUPPORT_CLEARANCE * crop_info["support_plane"]["tolerance"] if plane is not None else 0.0
    level, method_info, sample_stats, threshold_info = None, {"name": "density"}, {}, None
    if surface.level is not None and config.method != "poisson":  # a signed distance: its zero, no level rule
        method_info = {"name": surface.what}
        level, threshold_info = surface.level, {"rule": f"the zero level set of the run's {surface.what}"}
    elif config.method == "poisson":
        from nerfpipe.stages.mesh.poisson import Poisson, poisson_surface

        verts_g, faces_g, steps, method_info = poisson_surface(
            trained, grid, plane, keep_beyond, device=device, resolution=config.resolution, params=Poisson(), lap=lap
        )
        t = time.perf_counter()
    elif config.threshold == "auto":
        level, threshold_info = auto_threshold(
            density,
            scene,
            as_np(trained.aabb).reshape(2, 3),
            n_rays=config.threshold_rays,
            device=device,
            chunk=config.chunk,
        )
    else:
        level, threshold_info = float(config.threshold), {"rule": "given (--threshold)"}
    if level is not None:
        t = lap("threshold", t)
        if plane is not None:  # after the level: the level is the field's, measured on every training ray
            density = cut_density(density, plane, keep_beyond)
        vol, sample_stats = sample_volume(density, grid, level, device=device, chunk=config.chunk)
        t = lap("sampling", t)
        _level_checks(config, level, sample_stats, grid, how)
        verts_g, faces_g = _marching_cubes(vol, level, grid)
        del vol
        steps = [{"step": "marching_cubes", "vertices": len(verts_g), "faces": len(faces_g)}]
    if crop_info["rule"] == "looked-at":
        verts_g, faces_g, step = drop_box_cut_pieces(verts_g, faces_g, grid.lo, grid.hi, 1.5 * grid.h)
        steps.append(step)
    t = lap("marching_cubes" if level is not None else "box_cut_pieces", t)

    out_from_grid = out_from_scene @ grid.scene_from_grid
    verts, faces = transform_mesh(verts_g, faces_g, out_from_grid)
    verts, faces, clean_steps = cleanup_mesh(verts, faces, config.cleanup, config.target_faces or None)
    steps += clean_steps
    if len(faces) == 0:
        at = f"at threshold {level:g}" if level is not None else "(method poisson)"
        raise UserError(f"{config.run_dir}: no surface left after cleanup {at}; try --no-cleanup")
    t = lap("cleanup", t)

    colors, tex = None, None
    left_out: dict[str, str] = {}
    v_scene, f_scene = transform_mesh(verts, faces, np.linalg.inv(out_from_scene))
    if config.texture and has_color(trained):  # the training views' renders where they see a texel, else the normal
        views = training_views(trained, config.texture_views)
        tex = bake_texture(
            v_scene, f_scene, trained.color, texture_size=config.texture_size, views=views, device=device
        )
        timing.update({f"texture_{k}": v for k, v in tex.info["timing_seconds"].items()})
        tex = tex.transformed(out_from_scene)
        left_out["vertex_colors"] = "a texture is baked instead (texture)"
    elif config.texture:
        left_out["texture"] = "the field is density-only"
    elif config.colors and has_color(trained):
        colors = vertex_colors(trained, v_scene, f_scene, 1 << 16)
    elif config.colors:
        left_out["colors"] = "the field is density-only"
    else:
        left_out["colors"] = "--no-colors"
    if config.cleanup is None:
        left_out["cleanup"] = "--no-cleanup"
    t = lap("colors", t)

    # the mesh takes its name only after its report is written: a failure in between leaves no OUT that `make`
    # would take for done (the report alone is not a make target)
    with atomic_path(out) as tmp:
        extra: list[Path] = []
        if tex is not None and out.suffix.lower() == ".obj":
            extra = [p for k, p in write_obj_textured(out, tex, into=tmp).items() if k != "obj"]
        elif tex is not None:
            write_glb_textured(out, tex, into=tmp)
        else:
            _export(out, tmp, verts, faces, colors)
        lap("export", t)
        stats = mesh_stats(verts, faces)
        timing["total"] = round(time.perf_counter() - t_start, 3)
        seconds = timing["total"]
        report = write_manifest(
            out.parent,
            name=f"{out.stem}.report.json",
            stage="mesh",
            started=started,
            inputs=inputs,
            outputs=[out, *extra],
            used={"config": config_to_json(config)},
            left_out=left_out,
            version=VERSION,
            method=method_info,
            threshold={"value": level, **threshold_info} if threshold_info else None,
            crop=crop_info,
            texture=tex.info if tex is not None else None,
            grid={
                "crop": how,
                "frame": "scene" if np.allclose(grid.scene_from_grid, np.eye(4)) else config.frame,
                "lo": grid.lo.tolist(),
                "hi": grid.hi.tolist(),
                "voxel": grid.h,
                "samples_per_axis": list(grid.shape),
                "coarse_stride": grid.stride,
                "occupancy_skipping": occupancy_binary(trained) is not None,
                **{k: v for k, v in sample_stats.items()},
            },
            steps=steps,
            final={"vertices": len(verts), "faces": len(faces), **stats},
            frame=config.frame,
            out_from_scene=out_from_scene.tolist(),
            winding_reversed=bool(np.linalg.det(out_from_grid[:3, :3]) < 0),
            timing_seconds=timing,
            peak_rss_mb=round(_peak_rss_mb(), 1),
            device=str(device),
            **verdict(mesh_checks(v_scene, f_scene, as_np(trained.aabb))),
        )
    return Outputs(
        mesh=out,
        report=report,
        vertices=len(verts),
        faces=len(faces),
        threshold=level,
        watertight=stats["watertight"],
        seconds=seconds,
    )


def run(config: Config, progress: Any | None = None) -> Outputs:
    """Load RUN_DIR with `model.load_trained` and mesh it (see the module doc)."""
    _validate(config)
    run_dir = Path(config.run_dir)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: no such run directory (expected the output folder of `nerfpipe train`)")
    from nerfpipe.model import load_trained

    trained = load_trained(run_dir, config.device)
    inputs = tuple(p for p in (run_dir / "config.json", run_dir / "checkpoint.pt") if p.is_file())
    return extract(trained, config, inputs=inputs, progress=progress)
