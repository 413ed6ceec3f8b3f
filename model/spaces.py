"""A run's scene space from its scene (`radiance.space`: box, NDC, contracted): the rule `train --scene-model auto`
applies (`choose_space`), and the space of a given kind made for a scene (`make_space`)."""

from __future__ import annotations

import math

import numpy as np

from nerfpipe.data.errors import UserError
from nerfpipe.data.transforms import Scene, is_forward_facing
from nerfpipe.radiance.contraction import Contraction
from nerfpipe.radiance.ndc import NDC, fit_ndc
from nerfpipe.radiance.space import FAR, SPACES, Box, Contracted, NDCSpace, Space

__all__ = ["choose_space", "make_space", "scene_ndc"]


def choose_space(scene_model: str, scene: Scene, *, plain_background: bool) -> tuple[type[Space], str]:
    """(the space's class, why) for `train --scene-model`. "auto": NDC when the cameras are forward-facing (all
    within 45 degrees of their mean direction); the box when the photos have alpha or a plain background colour
    (nothing to model outside the object's box); contracted otherwise (real photos see a background beyond the
    box)."""
    if scene_model != "auto":
        if scene_model not in SPACES:
            raise UserError(f"unknown scene model {scene_model!r}: expected auto, {', '.join(SPACES)}")
        return SPACES[scene_model], f"asked for (scene_model={scene_model})"
    if is_forward_facing(scene):
        return NDCSpace, "forward-facing cameras (all within 45 degrees of their mean direction)"
    if plain_background:
        return Box, "images with alpha or a plain background colour: nothing to model outside the box"
    return Contracted, "opaque photos whose background is not a plain colour: space beyond the box is contracted"


def scene_ndc(scene: Scene) -> NDC:
    """NDC of the scene's mean camera; its near plane is the scene's near bound."""
    if not (scene.near > 0 and math.isfinite(scene.near)):
        raise UserError(f"{scene.root}: NDC needs a near bound > 0 in transforms.json, got near={scene.near}")
    return fit_ndc(np.stack([f.world_from_cam for f in scene.frames]), scene.frame_intrinsics(0), scene.near)


def _box(rows) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    lo, hi = np.asarray(rows, dtype=np.float64).reshape(2, 3).tolist()
    return tuple(lo), tuple(hi)  # type: ignore[return-value]


def make_space(kind: type[Space], scene: Scene) -> Space:
    """The space of class `kind` for `scene`: its box and near/far bounds (Box), the NDC of its mean camera and
    the box of every training camera's frustum (NDCSpace), the contraction around its box (Contracted)."""
    if kind is NDCSpace:
        ndc = scene_ndc(scene)
        poses = np.stack([f.world_from_cam for f in scene.frames])
        intr = [scene.frame_intrinsics(i) for i in range(len(scene.frames))]
        return NDCSpace(ndc=ndc, box=_box(ndc.box(poses, intr)))
    if kind is Contracted:
        return Contracted(contraction=Contraction(scene.aabb), near=float(scene.near))
    return Box(aabb=_box(scene.aabb), near=float(scene.near), far=float(scene.far if math.isfinite(scene.far) else FAR))
