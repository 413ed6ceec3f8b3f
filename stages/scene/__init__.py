"""`scene` stage: a synthetic, analytically rendered scene with exact cameras, depth and mesh.

The project's fixture for every later stage and its built-in demo. A textured ground slab and five
high-texture objects (spheres, boxes, a cylinder; `data.synthetic.objects`) are ray cast exactly from cameras on
a hemisphere around them. Other subjects (`Config.subject`): a printed box on white (carton, cube), or a scene
the seed draws (random: 1-8 objects of random shape, size, pose and texture, random lights and surroundings;
`data.synthetic.random_scene`, manifest.json's `used.random_subject` says what was drawn).

Conventions (docs/DESIGN.md):
- World frame = scene frame: metres times `scale` (every length: objects, cameras, depth, mesh, aabb, near,
  far), right-handed, up +z, ground top at z = 0; `applied_transform` is the identity and `applied_scale` 1.
  The images do not depend on `scale` (a similarity changes no pixel): they are rendered at scale 1 and only
  the lengths written are multiplied, so they are byte-identical at any scale.
- Cameras: `world_from_cam` 4x4 in OpenGL axes (x right, y up, looking down -z); pinhole, no distortion,
  principal point at the image centre (w / 2, h / 2; pixel centres at +0.5).
- Colour: each pixel averages `SUPERSAMPLE x SUPERSAMPLE` stratified rays (box filter). Opaque kinds composite
  the background colour `BACKGROUND`; `rgba` and `blender` store straight (unpremultiplied) colour and alpha =
  the fraction of the pixel's rays that hit the scene, so compositing it on `BACKGROUND` gives the `posed` image.
- Depth (`ground_truth/depth/*.npy`, float32 [H, W]): z-depth along the optical axis (metres x `scale`) of the
  ray through the pixel centre; 0 where that ray hits nothing (background).

Outputs under `out_dir`:
  images/frame_0000.png ...              RGB (photos, posed) or RGBA (rgba)
  transforms.json                        posed and rgba only (data.transforms format)
  transforms_{train,val,test}.json       blender only: the NeRF-synthetic layout (see below)
  {train,val,test}/r_0.png ...           blender only: RGBA images
  ground_truth/cameras.json              exact intrinsics, world_from_cam (OpenGL) per image stem, background
  ground_truth/depth/frame_0000.npy ...  z-depth, metres x scale, 0 = background
  ground_truth/mesh.ply                  the rendered surface (concatenated closed primitives), metres x scale
  manifest.json                          written last

kind=blender writes what the NeRF synthetic datasets hold (and `data.importers.blender` reads): per split a
`transforms_<split>.json` = {"camera_angle_x": horizontal field of view in radians, "frames": [{"file_path":
"./<split>/r_<j>" (no extension), "transform_matrix": world_from_cam 4x4}]} and RGBA PNGs <split>/r_<j>.png.
No scene bounds are stated (as in NeRF synthetic). Views i % 8 == 0 are test, i % 8 == 4 val, the rest train; a
split without views gets no file. Ground truth is keyed by the name `convert` gives each image (`train_r_0`),
so `eval --ground-truth` finds it after conversion.

Modules: `config` (the Config, its validation, the Outputs), `subject` (what is photographed, what surrounds it in
the layout, the lights), `rig` (the cameras per layout), `turntable` (the turntable's cameras and angles), `files`
(PNG, depth, mesh, transforms.json and Blender-layout writers); the primitives and the exact renderer are
`data.synthetic`'s.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from nerfpipe.data.atomic import write_bytes, write_json
from nerfpipe.data.rundir import config_to_json, output_folder, write_manifest
from nerfpipe.data.synthetic.raycast import SUPERSAMPLE, render_turntable_view, render_view, scene_mesh
from nerfpipe.stages.scene.config import Config, Outputs, check
from nerfpipe.stages.scene.files import (
    TEST_EVERY,
    blender_split,
    grey_png,
    png,
    write_blender,
    write_mesh,
    write_npy,
    write_transforms,
)
from nerfpipe.stages.scene.files import (
    views as view_files,
)
from nerfpipe.stages.scene.rig import (
    CAMERA_RADIUS,
    ELEVATION_DEG,
    FORWARD_ELEVATION_DEG,
    FORWARD_SPREAD,
    FOV_X_DEG,
    LOOK_AT,
    UP,
    cameras,
    intrinsics,
)
from nerfpipe.stages.scene.subject import subject
from nerfpipe.stages.scene.turntable import angles as turntable_angles
from nerfpipe.stages.scene.turntable import room_from_cam

__all__ = [
    "Config",
    "Outputs",
    "run",
    "cameras",
    "intrinsics",
    "render_view",
    "scene_mesh",
    "blender_split",
    "SUPERSAMPLE",
    "BACKGROUND",
    "FOV_X_DEG",
]

VERSION = "1"
BACKGROUND = (1.0, 1.0, 1.0)
"""Background colour of the opaque kinds (RGB in [0, 1])."""


def run(config: Config) -> Outputs:
    """Render the scene described by `config` into `config.out_dir`; see the module docstring for the files."""
    check(config)
    with output_folder(config.out_dir, overwrite=config.overwrite):
        return _run(config) if config.count == 1 else _run_many(config)


def _run_many(config: Config) -> Outputs:
    """count > 1: one scene a seed in out_dir/<seed>, then the dataset's manifest (written last)."""
    started, out = time.time(), Path(config.out_dir)
    seeds = range(config.seed, config.seed + config.count)
    scenes = [_run(replace(config, out_dir=out / f"{s:06d}", seed=s, count=1)) for s in seeds]
    manifest = write_manifest(
        out,
        stage="scene",
        started=started,
        outputs=[s.manifest.relative_to(out) for s in scenes],
        used={"count": config.count, "seeds": [seeds[0], seeds[-1]], "scene_folders": "<seed>, six digits"},
        config=config_to_json(config),
    )
    return replace(scenes[0], out_dir=out, manifest=manifest, scenes=tuple(s.out_dir for s in scenes))


def _run(config: Config) -> Outputs:
    scale = float(config.scale)
    started = time.time()
    out = Path(config.out_dir)
    subj = subject(config)
    objects = subj.objects
    turntable = config.layout == "turntable"
    prims = objects if turntable else (*objects, *subj.surroundings)
    intr = intrinsics(config.size)
    world_from_cam = cameras(config.views, config.seed, config.layout)  # rendered at scale 1
    scaled_from_cam = world_from_cam.copy()
    scaled_from_cam[:, :3, 3] *= scale  # the scene at `scale`: rotations unchanged, centres scaled
    views = view_files(config.kind, config.views)
    rgba = config.kind in ("rgba", "blender")
    bg = np.array(BACKGROUND)

    images, depths, masks, z_min = [], [], [], np.inf
    fixed = room_from_cam(LOOK_AT, CAMERA_RADIUS, UP)
    for k, ((rel, stem), w) in enumerate(zip(views, world_from_cam, strict=True)):
        if turntable:
            colour, alpha, obj_colour, mask, z = render_turntable_view(
                objects, subj.surroundings, intr, fixed, float(turntable_angles(config.views)[k]), subj.lights
            )
            if rgba:
                colour, alpha = obj_colour, mask
            masks.append(write_bytes(out / "masks" / f"{stem}.png", grey_png(mask)))
        else:
            colour, alpha, z = render_view(prims, intr, w, subj.lights)
        z_min = min(z_min, float(z[z > 0].min(initial=np.inf)))
        if not rgba:
            colour = alpha[..., None] * colour + (1 - alpha[..., None]) * bg
        images.append(write_bytes(out / rel, png(colour, alpha if rgba else None)))
        depth_path = out / "ground_truth" / "depth" / f"{stem}.npy"
        write_npy(depth_path, (z * scale).astype(np.float32))
        depths.append(depth_path)

    mesh = scene_mesh(prims)
    # Surroundings lie beyond the aabb (an unbounded capture), except a forward rig's (its far content, for NDC).
    aabb_of_all = config.layout == "forward" or len(prims) == len(objects)
    aabb = (mesh if aabb_of_all else scene_mesh(objects)).bounds + np.array([[-0.05], [0.05]])
    dist = np.linalg.norm(world_from_cam[:, :3, 3] - LOOK_AT, axis=-1)
    r_bound = float(np.max(np.linalg.norm(mesh.vertices - LOOK_AT, axis=-1)))
    near, far = float(max(0.05, 0.9 * (dist.min() - r_bound))), float(1.1 * (dist.max() + r_bound))
    if config.layout == "forward" and np.isfinite(z_min):
        # The wall makes the bounding-sphere bound useless (0.05 m); a forward-facing near bound is the closest
        # content actually seen (as LLFF's poses_bounds.npy has it), and NDC puts its near plane there.
        near = 0.9 * z_min
    aabb, near, far = aabb * scale, near * scale, far * scale
    if scale != 1.0:
        mesh.apply_scale(scale)
    mesh_path = out / "ground_truth" / "mesh.ply"
    write_mesh(mesh_path, mesh)

    intr_doc = {"w": intr.w, "h": intr.h, "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy}
    cams_doc = {
        "convention": "world_from_cam 4x4, OpenGL camera axes (x right, y up, looking down -z); metres x scale; "
        "up +z; frames keyed by image stem",
        "depth": "depth/<stem>.npy: float32 [H, W] z-depth along the optical axis, metres x scale, of the ray "
        "through the pixel centre; 0 = background",
        "mesh": "mesh.ply: the rendered surface, closed primitives concatenated (hidden faces where objects sink "
        "into the ground slab), metres x scale",
        "scale": scale,
        "camera_model": "PINHOLE",
        **intr_doc,
        "background": list(BACKGROUND) if not rgba else None,
        "aabb": aabb.tolist(),
        "near": near,
        "far": far,
        "frames": {
            stem: {"file_path": rel, "world_from_cam": w.tolist(), **intr_doc}
            for (rel, stem), w in zip(views, scaled_from_cam, strict=True)
        },
    }
    cams_path = write_json(out / "ground_truth" / "cameras.json", cams_doc)
    transforms, split_files = None, ()
    rel = [r for r, _ in views]
    if config.kind == "blender":
        split_files = write_blender(out, rel, scaled_from_cam, FOV_X_DEG)
    elif config.kind != "photos":
        names = [Path(r).name for r in rel]
        mask_rel = [str(p.relative_to(out).as_posix()) for p in masks] if masks and not rgba else None
        transforms = write_transforms(out, names, scaled_from_cam, intr, aabb, near, far, rgba, mask_rel)

    outputs = [*images, *masks, *depths, mesh_path, cams_path, *([transforms] if transforms else []), *split_files]
    manifest_path = write_manifest(
        out,
        stage="scene",
        started=started,
        outputs=[p.relative_to(out) for p in outputs],
        used={
            "supersample": f"{SUPERSAMPLE}x{SUPERSAMPLE} rays per pixel, box filter",
            "fov_x_deg": FOV_X_DEG,
            "background": "transparent" if rgba else list(BACKGROUND),
            "camera_radius_m": CAMERA_RADIUS,
            "scale": scale,
            "layout": config.layout,
            "test_split": f"every {TEST_EVERY}th view"
            + (f", val every {TEST_EVERY}th from {TEST_EVERY // 2}" if config.kind == "blender" else ""),
            **({"random_subject": subj.drawn} if subj.drawn is not None else {}),
            **({"mesh_subject": _placed_at_scale(subj.placed, scale)} if subj.placed is not None else {}),
            **(
                {"turntable": "the objects turn, camera and room fixed; poses object-relative; masks/ = object"}
                if turntable
                else {}
            ),
            **(
                {"elevation_deg": list(ELEVATION_DEG)}
                if config.layout == "orbit"
                else {"forward_spread_m": list(FORWARD_SPREAD), "elevation_deg": FORWARD_ELEVATION_DEG}
            ),
        },
        config=config_to_json(config),
    )
    return Outputs(
        out_dir=out,
        images=tuple(images),
        masks=tuple(masks),
        transforms=transforms,
        split_files=split_files,
        cameras=cams_path,
        depths=tuple(depths),
        mesh=mesh_path,
        manifest=manifest_path,
    )


def _placed_at_scale(placed: dict, scale: float) -> dict:
    """The mesh subject's record with scene_from_source taking the file to the written (scaled) scene frame."""
    tf = np.array(placed["scene_from_source"])
    tf[:3] *= scale
    return {**placed, "scene_from_source": tf.tolist()}
