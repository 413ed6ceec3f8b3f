"""What the scene stage photographs, decided once per run: the objects, what surrounds them in this layout, the
lights, and a record of what the seed drew (random subject) or how a mesh file was placed (mesh subject)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nerfpipe.data.synthetic.mesh_subject import MeshSurface, fit, read_mesh
from nerfpipe.data.synthetic.objects import (
    DEFAULT_LIGHTS,
    Lights,
    Primitive,
    backdrop,
    default_primitives,
    material,
    room,
)
from nerfpipe.data.synthetic.prints import subject_primitives
from nerfpipe.data.synthetic.random_scene import random_scene
from nerfpipe.stages.scene.config import Config
from nerfpipe.stages.scene.rig import LOOK_AT

MESH_RADIUS = 0.6
"""subject=mesh: the mesh's bounding box's half-diagonal in the scene, metres (the objects' scene spans ~0.8 m)."""

__all__ = ["Subject", "subject"]


@dataclass(frozen=True, kw_only=True)
class Subject:
    """What one run of the stage renders, and under which lights."""

    objects: tuple[Primitive, ...]
    """What is photographed: the bounded scene (aabb), what a turntable turns."""
    surroundings: tuple[Primitive, ...]
    """Around or behind it in this layout (a turntable: the fixed room); beyond the aabb except for `forward`."""
    lights: Lights
    """What everything is shaded with."""
    drawn: dict[str, Any] | None
    """subject=random: what the seed drew (`RandomScene.describe`) and the surroundings used; None otherwise."""
    placed: dict[str, Any] | None = None
    """subject=mesh: the file and the 4x4 scene_from_source it was placed with (`mesh_subject.fit`); None otherwise."""


def subject(config: Config) -> Subject:
    """The subject of `config` (its subject, layout and seed)."""
    seed, layout = config.seed, config.layout
    if config.subject == "random":
        drawn = random_scene(seed)
        around = _around(layout, drawn.surround, config.kind)
        surroundings = room(seed) if around == "room" else (backdrop(seed),) if around == "wall" else ()
        record = {**drawn.describe(), "surroundings": around}
        return Subject(objects=drawn.primitives(), surroundings=surroundings, lights=drawn.lights, drawn=record)
    product = config.subject != "objects"  # a printed box or a mesh alone: no slab, no room behind a turntable
    placed = None
    if config.subject == "mesh":
        surface, scene_from_source = fit(read_mesh(config.mesh), LOOK_AT, MESH_RADIUS, config.mesh_up)
        texture = material(np.random.default_rng([seed, 20261129]), seed, 0.08, 0.025)
        objects: tuple[Primitive, ...] = (MeshSurface(surface=surface, material=texture),)
        placed = {
            "file": str(config.mesh),
            "faces": len(surface.faces),
            "scene_from_source": scene_from_source.tolist(),
            "up": config.mesh_up,
            "rule": f"the file's +{config.mesh_up} turned to +z, its box centred at the look-at point "
            f"{LOOK_AT.tolist()}, half-diagonal {MESH_RADIUS} m",
        }
    else:
        objects = subject_primitives(config.subject, seed) if product else default_primitives(seed)
    if layout == "forward":
        surroundings = (backdrop(seed),)
    elif layout == "room" or (layout == "turntable" and not product):
        surroundings = room(seed)
    else:
        surroundings = ()
    return Subject(objects=objects, surroundings=surroundings, lights=DEFAULT_LIGHTS, drawn=None, placed=placed)


def _around(layout: str, drawn: str, kind: str) -> str:
    """subject=random: the surroundings used ('none', 'wall' or 'room'). The layout's own win (forward: a far
    wall; room and turntable: the room); an orbit shows what the seed `drawn` (none with alpha: an object on a
    transparent background, whose aabb is the whole scene; a drawn room there made opaque photos of a scene whose
    box left the room out), a forward rig the drawn room instead of its wall."""
    if layout == "orbit":
        return "none" if kind in ("rgba", "blender") else drawn
    if layout == "forward":
        return "room" if drawn == "room" else "wall"
    return "room"
