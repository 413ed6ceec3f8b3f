"""`scene` stage: a synthetic, analytically rendered scene with exact cameras, depth and mesh.

The project's fixture for every later stage and its built-in demo. A textured ground slab and five
high-texture objects (spheres, boxes, a cylinder; `stages.scene.objects`) are ray cast exactly from cameras on
a hemisphere around them.

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
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
import trimesh

from data.atomic import write_bytes, write_json
from data.errors import UserError
from data.rundir import config_to_json, output_folder, write_manifest
from radiance.camera import Intrinsics, generate_rays, pixel_centers
from radiance.paths import look_at
from stages.scene.files import (
    TEST_EVERY,
    blender_split,
    write_blender,
    write_mesh,
    write_npy,
    write_transforms,
)
from stages.scene.files import (
    views as view_files,
)
from stages.scene.objects import Primitive, backdrop, default_primitives, room, shade, solid_texture
from stages.scene.turntable import angles as turntable_angles
from stages.scene.turntable import object_cameras, room_from_cam, rot_z

__all__ = [
    "Config", "Outputs", "run", "cameras", "render_view", "scene_mesh", "blender_split", "SUPERSAMPLE", "BACKGROUND",
]  # fmt: skip

VERSION = "1"
SUPERSAMPLE = 2
"""Rays per pixel along each axis (2 -> 4 stratified rays per pixel)."""
BACKGROUND = (1.0, 1.0, 1.0)
"""Background colour of the opaque kinds (RGB in [0, 1])."""
FOV_X_DEG = 45.0
CAMERA_RADIUS = 2.4
"""Distance from the look-at point, metres (the scene's bounding sphere, r ~ 0.8 m, subtends ~20 deg)."""
UP = np.array([0.0, 0.0, 1.0])  # world up: camera image up is as close to +z as can be
LOOK_AT = np.array([0.0, 0.0, 0.12])
ELEVATION_DEG = (15.0, 50.0)
FORWARD_SPREAD = (0.9, 0.5)
"""layout=forward: camera centres spread over this width x height (metres) of a plane facing the scene."""
FORWARD_ELEVATION_DEG = 20.0


@dataclass(frozen=True, kw_only=True)
class Config:
    out_dir: Path
    """Folder to write the scene into (created; one that holds an earlier scene needs --overwrite)."""
    kind: Literal["photos", "posed", "rgba", "blender"] = "posed"
    """photos: bare images for COLMAP; posed: images + transforms.json; rgba: transparent background + alpha;
    blender: the NeRF-synthetic layout (transforms_{train,val,test}.json, RGBA PNGs in train/ val/ test/)."""
    size: int = 64
    """Image width = height, pixels."""
    views: int = 24
    """Number of cameras."""
    seed: int = 0
    """Picks the textures and the camera jitter; same seed, byte-identical output."""
    layout: Literal["orbit", "forward", "room", "turntable"] = "orbit"
    """orbit, forward, room or turntable. orbit: cameras all round the scene on a hemisphere (a 360-degree capture).
    turntable: the objects turn on their slab in front of a fixed camera and a fixed room (one full turn over the
    views); truth poses are object-relative and masks/ holds each view's object mask (white = object;
    stages.scene.turntable); kinds photos, posed (mask_path per frame) and rgba (the object alone).
    room: the orbit inside a textured room (floor and walls 4 m away; transforms.json's aabb is the objects'
    box, so the room lies beyond it: an unbounded capture). forward: cameras on a
    jittered grid in one plane, all looking the same way at the scene, with a textured wall 4 m behind it (an
    LLFF-style forward-facing capture: content from ~1.5 m to ~7 m)."""
    scale: float = 1.0
    """Multiply every length (objects, cameras, depth, mesh) by this; the images do not change."""
    overwrite: bool = False
    """Replace an earlier scene in out_dir (set aside in OUT_DIR.previous/ until this one is written)."""


@dataclass(frozen=True, kw_only=True)
class Outputs:
    out_dir: Path
    """The scene folder."""
    images: tuple[Path, ...]
    """The rendered images, in view order."""
    transforms: Path | None
    """transforms.json (None for kind=photos and blender)."""
    masks: tuple[Path, ...] = ()
    """layout=turntable: masks/<stem>.png per view (white = object), in view order; empty otherwise."""
    split_files: tuple[Path, ...]
    """kind=blender: the transforms_<split>.json written; empty otherwise."""
    cameras: Path
    """ground_truth/cameras.json."""
    depths: tuple[Path, ...]
    """ground_truth/depth/*.npy, in view order."""
    mesh: Path
    """ground_truth/mesh.ply."""
    manifest: Path
    """manifest.json (written last)."""


# ---------------------------------------------------------------- cameras


def intrinsics(size: int) -> Intrinsics:
    f = 0.5 * size / math.tan(math.radians(FOV_X_DEG) / 2)
    return Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2)


def cameras(views: int, seed: int, layout: str = "orbit") -> np.ndarray:
    """world_from_cam [V, 4, 4] (OpenGL axes), all looking at `LOOK_AT`.

    orbit: azimuths evenly spread with jitter, elevations 15-50 deg stratified (golden-ratio sequence), radius
    2.4 m +- 3 %. forward: centres on a jittered grid of `FORWARD_SPREAD` in the plane 2.4 m from `LOOK_AT`,
    seen from azimuth -90 deg (looking along +y) and 20 deg elevation.
    """
    if layout == "forward":
        return _forward_cameras(views, seed)
    if layout == "turntable":
        return object_cameras(room_from_cam(LOOK_AT, CAMERA_RADIUS, UP), views)
    rng = np.random.default_rng([seed, 7])
    i = np.arange(views)
    azimuth = 2 * np.pi * (i + rng.uniform(-0.3, 0.3, views) + rng.uniform()) / views
    lo, hi = ELEVATION_DEG
    frac = (i * 0.6180339887 + rng.uniform()) % 1.0
    elevation = np.radians(lo + (hi - lo) * frac)
    radius = CAMERA_RADIUS * (1 + rng.uniform(-0.03, 0.03, views))
    eye = LOOK_AT + radius[:, None] * np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1
    )
    return np.stack([look_at(e, LOOK_AT, UP) for e in eye])


def _forward_cameras(views: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 11])
    cols = math.ceil(math.sqrt(views * FORWARD_SPREAD[0] / FORWARD_SPREAD[1]))
    rows = math.ceil(views / cols)
    k = np.arange(views)
    u = ((k % cols) + 0.5 + rng.uniform(-0.25, 0.25, views)) / cols - 0.5  # [-0.5, 0.5]
    v = ((k // cols) + 0.5 + rng.uniform(-0.25, 0.25, views)) / rows - 0.5
    el = math.radians(FORWARD_ELEVATION_DEG)
    back = np.array([0.0, -math.cos(el), math.sin(el)])  # from LOOK_AT towards the rig
    right = np.array([1.0, 0.0, 0.0])
    up = np.cross(back, right)
    eye = LOOK_AT + CAMERA_RADIUS * back + FORWARD_SPREAD[0] * u[:, None] * right + FORWARD_SPREAD[1] * v[:, None] * up
    return np.stack([look_at(e, LOOK_AT, UP) for e in eye])


# ---------------------------------------------------------------- rendering


def _rays(intr: Intrinsics, world_from_cam: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through (col + ox, row + oy) for every pixel and each offset [S, 2] (`radiance.camera.generate_rays`):
    o, d [H * W * S, 3] float64, ordered (row, col, sample)."""
    corners = pixel_centers(intr, torch.float64) - 0.5  # [H * W, 2] (col, row), row-major
    uv = (corners[:, None, :] + torch.from_numpy(offsets)).reshape(-1, 2)  # [H * W * S, 2]
    o, d = generate_rays(intr, torch.from_numpy(world_from_cam), uv)
    return o.numpy(), d.numpy()


def _cast(prims: tuple[Primitive, ...], o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit: t [R] (inf = miss) and primitive index [R] (-1 = miss)."""
    t = np.full(len(o), np.inf)
    which = np.full(len(o), -1)
    for k, prim in enumerate(prims):
        idx = np.flatnonzero(prim.candidates(o, d))  # bounding-sphere culling
        tk = prim.intersect(o[idx], d[idx])
        closer = tk < t[idx]
        t[idx[closer]] = tk[closer]
        which[idx[closer]] = k
    return t, which


def render_view(
    prims: tuple[Primitive, ...], intr: Intrinsics, world_from_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view: straight colour [H, W, 3] (mean over covered rays; 0 where none), coverage alpha [H, W]
    and z-depth [H, W] of the pixel-centre ray (0 = background), all float64."""
    s = SUPERSAMPLE
    grid = (np.arange(s) + 0.5) / s
    offsets = np.stack(np.meshgrid(grid, grid, indexing="xy"), axis=-1).reshape(-1, 2)  # [S, 2]
    o, d = _rays(intr, world_from_cam, offsets)
    t, which = _cast(prims, o, d)
    rgb = np.zeros((len(o), 3))
    for k, prim in enumerate(prims):
        m = which == k
        if m.any():
            p = o[m] + t[m, None] * d[m]
            rgb[m] = shade(solid_texture(p, prim.material), prim.normal(p))
    hit = (which >= 0).reshape(intr.h, intr.w, s * s)
    alpha = hit.mean(-1)
    colour_sum = rgb.reshape(intr.h, intr.w, s * s, 3).sum(-2)
    colour = colour_sum / np.maximum(hit.sum(-1), 1)[..., None]

    oc, dc = _rays(intr, world_from_cam, np.array([[0.5, 0.5]]))
    tc, _ = _cast(prims, oc, dc)
    forward = -world_from_cam[:3, 2]
    z = np.where(
        np.isfinite(tc), tc * (dc[:, 0] * forward[0] + dc[:, 1] * forward[1] + dc[:, 2] * forward[2]), 0.0
    ).reshape(intr.h, intr.w)
    return colour, alpha, z


def render_turntable_view(
    objects: tuple[Primitive, ...], background: tuple[Primitive, ...], intr: Intrinsics, fixed: np.ndarray,
    theta: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """One turntable view (stages.scene.turntable): the camera `fixed` (room frame), the objects turned by
    `theta`. Returns straight colour of everything [H, W, 3], its coverage [H, W], the object's straight colour
    [H, W, 3] and coverage (the mask) [H, W], and the object's z-depth [H, W] (0 = not the object), float64."""
    s = SUPERSAMPLE
    grid = (np.arange(s) + 0.5) / s
    offsets = np.stack(np.meshgrid(grid, grid, indexing="xy"), axis=-1).reshape(-1, 2)  # [S, 2]
    object_from_room = rot_z(-theta)[:3, :3]

    def cast(offs: np.ndarray) -> tuple[np.ndarray, ...]:
        o, d = _rays(intr, fixed, offs)  # room frame
        oo, do = o @ object_from_room.T, d @ object_from_room.T  # object frame, same t
        t_obj, w_obj = _cast(objects, oo, do)
        t_bg, w_bg = _cast(background, o, d)
        on_obj = (w_obj >= 0) & (t_obj <= t_bg)
        return o, d, oo, do, t_obj, w_obj, t_bg, w_bg, on_obj

    o, d, oo, do, t_obj, w_obj, t_bg, w_bg, on_obj = cast(offsets)
    rgb = np.zeros((len(o), 3))
    for prims, origin, direction, t, which, use in (
        (objects, oo, do, t_obj, w_obj, on_obj), (background, o, d, t_bg, w_bg, ~on_obj & (w_bg >= 0)),
    ):  # fmt: skip
        for k, prim in enumerate(prims):
            m = use & (which == k)
            if m.any():
                p = origin[m] + t[m, None] * direction[m]
                rgb[m] = shade(solid_texture(p, prim.material), prim.normal(p))
    hw = (intr.h, intr.w, s * s)
    hit, obj = (on_obj | (w_bg >= 0)).reshape(hw), on_obj.reshape(hw)
    rgb = rgb.reshape(*hw, 3)
    colour = (rgb * hit[..., None]).sum(-2) / np.maximum(hit.sum(-1), 1)[..., None]
    obj_colour = (rgb * obj[..., None]).sum(-2) / np.maximum(obj.sum(-1), 1)[..., None]

    _, dc, _, _, tc, _, _, _, on_c = cast(np.array([[0.5, 0.5]]))
    forward = -fixed[:3, 2]
    z = np.where(on_c, tc * (dc @ forward), 0.0).reshape(intr.h, intr.w)
    return colour, hit.mean(-1), obj_colour, obj.mean(-1), z


def scene_mesh(prims: tuple[Primitive, ...]) -> trimesh.Trimesh:
    """The scene surface: the primitives' closed meshes concatenated (no boolean union: where an object is sunk
    into the ground slab, the hidden parts of both stay as interior faces)."""
    return trimesh.util.concatenate([p.mesh() for p in prims])


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def _png(rgb: np.ndarray, alpha: np.ndarray | None) -> bytes:
    img = _to_u8(rgb)[..., ::-1]  # RGB -> BGR for OpenCV
    if alpha is not None:
        img = np.concatenate([img, _to_u8(alpha)[..., None]], axis=-1)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _grey_png(x: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", _to_u8(x))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def run(config: Config) -> Outputs:
    """Render the scene described by `config` into `config.out_dir`; see the module docstring for the files."""
    _check(config)
    with output_folder(config.out_dir, overwrite=config.overwrite):
        return _run(config)


def _check(config: Config) -> None:
    if config.size < 8 or config.views < 1:
        raise UserError(f"scene: expected --size >= 8 and --views >= 1, got size={config.size}, views={config.views}")
    if config.kind not in ("photos", "posed", "rgba", "blender"):
        raise UserError(f"scene: expected --kind photos|posed|rgba|blender, got {config.kind!r}")
    if config.layout not in ("orbit", "forward", "room", "turntable"):
        raise UserError(f"scene: expected --layout orbit|forward|room|turntable, got {config.layout!r}")
    if config.layout == "turntable" and config.kind == "blender":
        raise UserError("scene: --layout turntable writes kinds photos, posed or rgba, not blender")
    scale = float(config.scale)
    if not (math.isfinite(scale) and scale > 0):
        raise UserError(f"scene: expected --scale > 0 (finite), got {config.scale!r}")


def _run(config: Config) -> Outputs:
    scale = float(config.scale)
    started = time.time()
    out = Path(config.out_dir)
    prims = default_primitives(config.seed)
    objects = prims
    if config.layout == "forward":
        prims = (*prims, backdrop(config.seed))
    elif config.layout == "room":
        prims = (*prims, *room(config.seed))
    turntable = config.layout == "turntable"
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
                objects, room(config.seed), intr, fixed, float(turntable_angles(config.views)[k])
            )
            if rgba:
                colour, alpha = obj_colour, mask
            masks.append(write_bytes(out / "masks" / f"{stem}.png", _grey_png(mask)))
        else:
            colour, alpha, z = render_view(prims, intr, w)
        z_min = min(z_min, float(z[z > 0].min(initial=np.inf)))
        if not rgba:
            colour = alpha[..., None] * colour + (1 - alpha[..., None]) * bg
        images.append(write_bytes(out / rel, _png(colour, alpha if rgba else None)))
        depth_path = out / "ground_truth" / "depth" / f"{stem}.npy"
        write_npy(depth_path, (z * scale).astype(np.float32))
        depths.append(depth_path)

    mesh = scene_mesh(prims)
    aabb = (mesh if config.layout != "room" else scene_mesh(objects)).bounds + np.array([[-0.05], [0.05]])
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
        "aabb": aabb.tolist(), "near": near, "far": far,
        "frames": {
            stem: {"file_path": rel, "world_from_cam": w.tolist(), **intr_doc}
            for (rel, stem), w in zip(views, scaled_from_cam, strict=True)
        },
    }  # fmt: skip
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
        out, stage="scene", started=started, outputs=[p.relative_to(out) for p in outputs],
        used={"supersample": f"{SUPERSAMPLE}x{SUPERSAMPLE} rays per pixel, box filter", "fov_x_deg": FOV_X_DEG,
              "background": "transparent" if rgba else list(BACKGROUND), "camera_radius_m": CAMERA_RADIUS,
              "scale": scale, "layout": config.layout,
              "test_split": f"every {TEST_EVERY}th view" + (f", val every {TEST_EVERY}th from {TEST_EVERY // 2}"
                                                            if config.kind == "blender" else ""),
              **({"turntable": "the objects turn, camera and room fixed; poses object-relative; masks/ = object"}
                 if turntable else {}),
              **({"elevation_deg": list(ELEVATION_DEG)} if config.layout == "orbit" else
                 {"forward_spread_m": list(FORWARD_SPREAD), "elevation_deg": FORWARD_ELEVATION_DEG})},
        config=config_to_json(config),
    )  # fmt: skip
    return Outputs(
        out_dir=out, images=tuple(images), masks=tuple(masks), transforms=transforms, split_files=split_files,
        cameras=cams_path, depths=tuple(depths), mesh=mesh_path, manifest=manifest_path,
    )  # fmt: skip
