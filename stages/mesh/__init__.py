"""Stage `mesh`: a trained radiance field -> a triangle mesh (PLY / OBJ / GLB), upright in the user's frame.

`nerfpipe mesh RUN_DIR OUT.ply|.obj|.glb [--method density|poisson] [--resolution 256]
[--threshold auto|global|VALUE] [--bbox x0,...,z1] [--crop auto|looked-at|occupied|field]
[--frame upright|user|normalized] [--up x,y,z] [--target-faces 300000] [--no-cleanup] [--no-colors] [--texture]`

Steps:
1. Box: `--bbox` (in the chosen frame), else `--crop` (`stages.mesh.crop`): for an object scene (alpha or a
   plain background) the occupied cells of the run's occupancy grid (one cell of margin; the run's aabb without
   a grid); for a real capture (contracted or forward-facing: the photos see walls and floors) the box of what
   the training views' central rays hit, with a support plane (the wall or table every camera faces) cut away.
   Never beyond the field's box (the inner box of a contracted scene). Voxels are cubes with `resolution` cells
   along the box's longest side.
2. Iso-level (`stages.mesh.threshold`): `threshold_rays` training-view rays on a pixel lattice are marched through
   the field; on each ray the density where the accumulated opacity 1 - exp(-integral sigma dt) first reaches 0.5
   (the ray's median depth: where the rendered surface is) is that ray's level, at its crossing point. `auto`:
   levels by region, the geometric mean of the levels of the crossings near each point (so a faint object keeps
   its own level instead of the disk's it stands on); `global`: one level, their median. Either way the mesh sits
   where depth maps put the surface, and the level does not depend on the grid resolution.
3. Density on the grid (`stages.mesh.grid`: coarse-to-fine, cells of the run's occupancy grid marked empty
   are zero without querying the field), zero-padded so the surface is closed where it meets the box; with levels
   by region, the density over the local level (`stages.mesh.surface`).
4. Marching cubes (scikit-image, Lewiner) at the level; faces wind counter-clockwise seen from outside
   (the side of lower density).
   `--method poisson` replaces steps 3-4 (`stages.mesh.poisson`): screened Poisson through the points where training
   rays become half opaque, with density-gradient normals, its unsupported hull trimmed, cut to the box.
5. Cleanup (`stages.mesh.cleanup`, pymeshlab) and quadric decimation to `--target-faces` (300k by default, a
   size a web viewer opens quickly; 0 keeps every face).
6. Vertex colours: `trained.color(x, -n)`, the colour a camera looking straight at the surface along the
   inward normal sees (a view-independent field ignores the direction). With `--texture`, texels take the mean of
   the training photos that see them (`--texture-source photos`, the default) or of the field's renders of those
   cameras (`field`; `stages.mesh.texture_views`), the rest the colour along the normal.
7. Export in the output frame (`data.export_frame`): `upright` (default) the user's frame turned so the scene's up
   is the format's (+Y for glTF and OBJ, +Z for PLY); `user` the source frame as it came in; `normalized` the scene
   frame. Winding reversed where the map mirrors. Written atomically, then `OUT.report.json` next to it (`mesh.ply`
   -> `mesh.report.json`, so several meshes in one folder keep their own reports) with `out_from_scene` and
   `out_from_source`.
8. Self-check (`stages.mesh.checks`; the report's `check`: ok | suspect and `checks`): the mesh against the field
   seen from the training cameras (`stages.mesh.agreement`: the share of the field's surface the mesh misses, and
   of the mesh where the field shows none), against the scene's box (a mesh that spans it on every axis is the
   surroundings cut out by the box, a slab, not an object) and its count of sizeable connected components.

Frames: the scene (normalized, training) frame is where the field lives; the user (source) frame is the one
`convert` started from: `p_scene = applied_scale * (applied_transform @ [p_src; 1])` (docs/DESIGN.md).

Modules: `config` (Config, Outputs, parsers, validation), `threshold` (the level's rays and rules), `surface`
(density -> marching cubes), `grid`, `crop`, `poisson`, `cleanup`, `field_access` (what the stage asks of a run),
`texture`, `texture_views`, `texture_files`, `agreement` and `checks` (the self-check).
"""

from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

from nerfpipe.data.atomic import atomic_path
from nerfpipe.data.checks import verdict
from nerfpipe.data.errors import UserError
from nerfpipe.data.export_frame import export_frame
from nerfpipe.data.rundir import config_to_json, write_manifest
from nerfpipe.model.run import can
from nerfpipe.stages.mesh.agreement import mesh_agreement
from nerfpipe.stages.mesh.checks import agreement_checks, mesh_checks
from nerfpipe.stages.mesh.cleanup import Cleanup, cleanup_mesh, mesh_stats, transform_mesh
from nerfpipe.stages.mesh.config import FORMAT_NAMES, FORMATS, Config, Outputs, parse_bbox, parse_threshold, validate
from nerfpipe.stages.mesh.crop import SUPPORT_CLEARANCE, Plane, default_box, drop_box_cut_pieces
from nerfpipe.stages.mesh.field_access import (
    as_np,
    density_function,
    field_device,
    has_color,
    occupancy_binary,
    surface_function,
    vertex_colors,
)
from nerfpipe.stages.mesh.grid import Grid, make_grid
from nerfpipe.stages.mesh.surface import Level, Region, choose_level, density_surface
from nerfpipe.stages.mesh.texture import bake_texture
from nerfpipe.stages.mesh.texture_files import glb_vertex_coloured, write_glb_textured, write_obj_textured
from nerfpipe.stages.mesh.texture_views import training_photos, training_views
from nerfpipe.stages.mesh.threshold import auto_threshold, march_crossings

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

VERSION = "2"


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


def _export(path: Path, tmp: Path, verts: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> None:
    """Write the mesh to `tmp` in the format `path`'s extension names (a coloured GLB: `glb_vertex_coloured`)."""
    import trimesh

    kind = path.suffix.lower().lstrip(".")
    if kind == "glb" and colors is not None:
        tmp.write_bytes(glb_vertex_coloured(verts, faces, colors))
        return
    trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False).export(tmp, file_type=kind)


def extract(trained: Any, config: Config, *, inputs: tuple[Path, ...] = (), progress: Any | None = None) -> Outputs:
    """Mesh an already loaded field (anything with the `Trained` attributes: density, color, aabb,
    occupancy, scene). `run` loads the run and calls this. `progress`: an optional rich Progress."""
    started = time.time()
    t_start = time.perf_counter()
    validate(config)
    out = Path(config.out)
    timing: dict[str, float] = {}
    task = progress.add_task(f"mesh {out.name}", total=8) if progress is not None else None

    def lap(name: str, t: float) -> float:
        now = time.perf_counter()
        timing[name] = round(now - t, 3)
        if task is not None:
            progress.advance(task)
        return now

    scene = trained.scene
    fmt = FORMAT_NAMES[out.suffix.lower()]
    out_from_scene, frame_info = export_frame(scene.source_from_scene(), config.frame, fmt, config.up)
    device = field_device(trained)
    surface = surface_function(trained)
    density = surface.values
    aabb = as_np(trained.aabb).reshape(2, 3)
    t = time.perf_counter()
    grid, how, crop_info, plane = _grid_for(config, trained, out_from_scene)
    t = lap("crop", t)
    # the level's rays, marched through the field as it is (before any cut): also the self-check's
    crossings = None  # a run without a density (a signed distance only) has no opacity along rays to compare with
    if can(trained, "density"):
        rays_density = density if surface.level is None else density_function(trained)
        crossings = march_crossings(
            rays_density, scene, aabb, n_rays=config.threshold_rays, device=device, chunk=config.chunk
        )
    t = lap("training_rays", t)

    keep_beyond = SUPPORT_CLEARANCE * crop_info["support_plane"]["tolerance"] if plane is not None else 0.0
    region = Region(grid=grid, plane=plane, keep_beyond=keep_beyond, how=how)
    level, method_info, sample_stats = None, {"name": "density"}, {}
    if config.method == "poisson":
        from nerfpipe.stages.mesh.poisson import Poisson, poisson_surface

        verts_g, faces_g, steps, method_info = poisson_surface(
            trained, grid, plane, keep_beyond, device=device, resolution=config.resolution, params=Poisson(), lap=lap
        )
        t = time.perf_counter()
    else:
        if surface.level is not None:  # a signed distance: its zero, no level rule
            method_info = {"name": surface.what}
            rule = {"rule": f"the zero level set of the run's {surface.what}"}
            level = Level(density, surface.level, surface.level, rule, by_region=False)
        else:
            level = choose_level(config.threshold, density, crossings, aabb)
        verts_g, faces_g, sample_stats = density_surface(
            level,
            region,
            crossings=crossings,
            aabb=aabb,
            run_dir=config.run_dir,
            given=surface.level is None and config.threshold not in ("auto", "global"),
            device=device,
            chunk=config.chunk,
            close=config.close_gaps,
        )
        steps = [{"step": "marching_cubes", "vertices": len(verts_g), "faces": len(faces_g)}]
        t = lap("sampling_and_marching_cubes", t)
    cut_away = None  # the box-cut pieces in the scene frame (the self-check does not count their surface missed)
    if crop_info["rule"] == "looked-at":
        verts_cut = verts_g
        verts_g, faces_g, step, faces_cut = drop_box_cut_pieces(verts_g, faces_g, grid.lo, grid.hi, 1.5 * grid.h)
        steps.append(step)
        cut_away = transform_mesh(verts_cut, faces_cut, grid.scene_from_grid)
    t = lap("box_cut_pieces", t)

    out_from_grid = out_from_scene @ grid.scene_from_grid
    verts, faces = transform_mesh(verts_g, faces_g, out_from_grid)
    verts, faces, clean_steps = cleanup_mesh(verts, faces, config.cleanup, config.target_faces or None)
    steps += clean_steps
    if len(faces) == 0:
        at = f"at threshold {level.value:g}" if level is not None else "(method poisson)"
        raise UserError(f"{config.run_dir}: no surface left after cleanup {at}; try --no-cleanup")
    t = lap("cleanup", t)

    colors, tex = None, None
    left_out: dict[str, str] = {}
    v_scene, f_scene = transform_mesh(verts, faces, np.linalg.inv(out_from_scene))
    if config.texture and has_color(trained):  # the training views' renders where they see a texel, else the normal
        views, why = training_photos(trained, config.texture_views) if config.texture_source == "photos" else (None, "")
        if views is None:
            views = training_views(trained, config.texture_views)
            if why and views is not None:
                views.info["why"] = f"the field's renders instead of the photos: {why}"
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

    agreement = None
    if crossings is not None:
        agreement = mesh_agreement(v_scene, f_scene, crossings, scene, region.inside, grid.voxel, cut_away=cut_away)
    else:
        left_out["agreement"] = "the run has no density to render the training views' surface with (signed distance)"
    t = lap("check", t)

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
            threshold={"value": level.value, **level.info} if level is not None else None,
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
            **frame_info,
            out_from_scene=out_from_scene.tolist(),
            winding_reversed=bool(np.linalg.det(out_from_grid[:3, :3]) < 0),
            agreement=agreement.report() if agreement is not None else None,
            timing_seconds=timing,
            peak_rss_mb=round(_peak_rss_mb(), 1),
            device=str(device),
            **verdict((agreement_checks(agreement) if agreement else []) + mesh_checks(v_scene, f_scene, aabb)),
        )
    return Outputs(
        mesh=out,
        report=report,
        vertices=len(verts),
        faces=len(faces),
        threshold=level.value if level is not None else None,
        watertight=stats["watertight"],
        seconds=timing["total"],
    )


def run(config: Config, progress: Any | None = None) -> Outputs:
    """Load RUN_DIR with `model.load_trained` and mesh it (see the module doc)."""
    validate(config)
    run_dir = Path(config.run_dir)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: no such run directory (expected the output folder of `nerfpipe train`)")
    from nerfpipe.model import load_trained

    trained = load_trained(run_dir, config.device)
    inputs = tuple(p for p in (run_dir / "config.json", run_dir / "checkpoint.pt") if p.is_file())
    return extract(trained, config, inputs=inputs, progress=progress)
