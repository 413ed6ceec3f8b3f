"""The scene stage's exact renderer: rays cast against the primitives (`data.synthetic.objects`), `SUPERSAMPLE` x
`SUPERSAMPLE` stratified rays per pixel averaged with a box filter, shaded colour, coverage alpha and the z-depth of
the pixel-centre ray; a turntable view (the objects turned, camera and room fixed); the scene's mesh."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from nerfpipe.data.synthetic.objects import DEFAULT_LIGHTS, Lights, Primitive, rot_z, shade
from nerfpipe.radiance.camera import Intrinsics, generate_rays, pixel_centers

__all__ = ["SUPERSAMPLE", "render_view", "render_turntable_view", "scene_mesh"]

SUPERSAMPLE = 2
"""Rays per pixel along each axis (2 -> 4 stratified rays per pixel)."""


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
    prims: tuple[Primitive, ...], intr: Intrinsics, world_from_cam: np.ndarray, lights: Lights = DEFAULT_LIGHTS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view: straight colour [H, W, 3] (mean over covered rays; 0 where none), coverage alpha [H, W]
    and z-depth [H, W] of the pixel-centre ray (0 = background), all float64; shaded under `lights`."""
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
            rgb[m] = shade(prim.albedo(p), prim.normal(p), lights)
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
    objects: tuple[Primitive, ...],
    background: tuple[Primitive, ...],
    intr: Intrinsics,
    fixed: np.ndarray,
    theta: float,
    lights: Lights = DEFAULT_LIGHTS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One turntable view (the `scene` stage's turntable layout): the camera `fixed` (room frame), the objects turned by
    `theta`; `lights` turn with the objects (and light the room fixed in it). Returns straight colour of everything
    [H, W, 3], its coverage [H, W], the object's straight colour [H, W, 3] and coverage (the mask) [H, W], and the
    object's z-depth [H, W] (0 = not the object), float64."""
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
        (objects, oo, do, t_obj, w_obj, on_obj),
        (background, o, d, t_bg, w_bg, ~on_obj & (w_bg >= 0)),
    ):
        for k, prim in enumerate(prims):
            m = use & (which == k)
            if m.any():
                p = origin[m] + t[m, None] * direction[m]
                rgb[m] = shade(prim.albedo(p), prim.normal(p), lights)
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
