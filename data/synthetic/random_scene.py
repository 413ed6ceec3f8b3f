"""Random scenes: the seed draws how many objects stand on the ground slab, their shapes, sizes, poses and
textures, the ground's texture, what surrounds them and the lights. Many scenes whose geometry differs, not only
their textures: what a cross-scene model (a generalizable NeRF) is pretrained on.

Conventions (`objects`' module doc): metres, right-handed, up +z; the slab (radius `SLAB_RADIUS`) has its top at
z = 0, the cameras of the `scene` stage look at (0, 0, 0.12).
- Objects: `COUNT` of them; shapes `SHAPES` (`objects.Sphere`, `Box`, upright `Cylinder`; a box turns about z
  only: `Box` has a yaw, no tilt); size = the largest extent, in `SIZE`. Each stands on the slab, sunk `SINK`
  into it (no coplanar faces), or one in five floats `FLOAT` above it; footprints lie on the slab, tops below `TOP`.
- No two objects meet: their bounding spheres (`Primitive.bounding_sphere`) stay `GAP` apart, by rejection
  sampling (deterministic from the seed). An object that finds no room is drawn smaller at each try (size bound
  x 0.98 per try) and is left out after `TRIES` (`RandomScene.objects` holds those placed).
- Textures (each object and the ground): the solid noise texture (`objects.solid_texture`, random cell sizes) or
  a photograph (`photo.PhotoTexture`, random image, tint, scale, rotation and offset), half and half.
- Surround: none, a wall 4 m behind (`objects.backdrop`) or a room (`objects.room`), one in three each.
- Lights (`objects.Lights`): 1-3 directional lights 20-80 deg above the horizon, a key light first, total
  intensity 0.5-0.9, ambient 0.15-0.35, a tint with each channel in 0.8-1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from nerfpipe.data.synthetic.objects import (
    Box,
    Cylinder,
    Lights,
    Material,
    Primitive,
    Sphere,
    backdrop,
    material,
    room,
)
from nerfpipe.data.synthetic.photo import GREYS, PHOTOS, PhotoTexture, PhotoTextured

__all__ = [
    "COUNT",
    "SIZE",
    "SHAPES",
    "SURROUNDS",
    "SLAB_RADIUS",
    "Placed",
    "RandomScene",
    "random_scene",
    "random_primitives",
    "random_lights",
    "textured",
    "draw_lights",
]

COUNT = (1, 8)
"""Fewest and most objects (inclusive), uniform."""
SIZE = (0.1, 0.6)
"""Largest extent of an object, metres (uniform)."""
SHAPES = ("sphere", "box", "cylinder")
SURROUNDS = ("none", "wall", "room")
SLAB_RADIUS = 0.75
"""The ground slab's radius, metres (top at z = 0, 5 cm thick)."""
SINK = 0.01
"""How far a standing object sinks into the slab, metres."""
FLOAT = (0.05, 0.25)
"""Height of a floating object's bottom above the slab, metres."""
TOP = 0.7
"""Highest top of an object, metres (the cameras' view, at 2.4 m, holds a sphere of ~0.9 m round (0, 0, 0.12))."""
GAP = 0.01
"""Least distance between two objects' bounding spheres, metres."""
TRIES = 200
"""Placements tried per object before it is left out."""


@dataclass(frozen=True, kw_only=True)
class Placed:
    """One object of a random scene, as drawn."""

    shape: str
    """One of `SHAPES`."""
    size: float
    """Largest extent, metres."""
    yaw: float
    """Rotation about z, radians (boxes; 0 for spheres and cylinders, round about z)."""
    floating: bool
    """True: it hangs above the slab; False: it stands on it."""
    texture: str
    """'noise' (the solid noise texture) or 'photo:<image name>'."""
    primitive: Primitive
    """The surface and texture that is rendered."""


@dataclass(frozen=True, kw_only=True)
class RandomScene:
    """What `random_scene(seed)` drew."""

    seed: int
    """The seed it was drawn from."""
    ground: Primitive
    """The slab: radius `SLAB_RADIUS`, top at z = 0."""
    ground_texture: str
    """'noise' or 'photo:<image name>'."""
    objects: tuple[Placed, ...]
    """The objects on or above the slab (1 to 8)."""
    surround: str
    """One of `SURROUNDS`: what `surroundings()` holds."""
    lights: Lights
    """The lights to shade it with."""

    def primitives(self) -> tuple[Primitive, ...]:
        """The slab, then the objects: the bounded scene (what a turntable turns)."""
        return (self.ground, *(o.primitive for o in self.objects))

    def surroundings(self) -> tuple[Primitive, ...]:
        """What surrounds the slab: nothing, the wall (`objects.backdrop(seed)`) or the room (`objects.room`)."""
        if self.surround == "wall":
            return (backdrop(self.seed),)
        return room(self.seed) if self.surround == "room" else ()

    def describe(self) -> dict[str, Any]:
        """What was drawn, as plain JSON (the `scene` stage's manifest)."""

        def r(x: Any) -> Any:
            return np.round(np.asarray(x, dtype=np.float64), 4).tolist()

        return {
            "seed": self.seed,
            "count": len(self.objects),
            "objects": [
                {
                    "shape": o.shape,
                    "size_m": r(o.size),
                    "bounding_centre_m": r(o.primitive.bounding_sphere()[0]),
                    "bounding_radius_m": r(o.primitive.bounding_sphere()[1]),
                    "yaw_deg": r(math.degrees(o.yaw)),
                    "floating": o.floating,
                    "texture": o.texture,
                }
                for o in self.objects
            ],
            "ground_texture": self.ground_texture,
            "surround": self.surround,
            "lights": {
                "directions": r(self.lights.directions),
                "intensities": r(self.lights.intensities),
                "ambient": r(self.lights.ambient),
                "tint": r(self.lights.tint),
            },
        }


def random_scene(seed: int) -> RandomScene:
    """The random scene of `seed` (module doc); the same seed, the same scene."""
    if seed < 0:
        raise ValueError(f"expected a seed >= 0, got {seed}")
    layout = np.random.default_rng([seed, 20270301])
    paint = np.random.default_rng([seed, 20270302])
    ground_texture, ground = textured(
        paint,
        lambda m: Cylinder(center=np.zeros(2), radius=SLAB_RADIUS, z0=-0.05, z1=0.0, material=m),
        cells=(0.06, 0.2),
        scales=(0.3, 1.2),
    )
    count = int(layout.integers(COUNT[0], COUNT[1] + 1))
    placed: list[Placed] = []
    for _ in range(count):
        drawn = _place(layout, [o.primitive.bounding_sphere() for o in placed])
        if drawn is None:
            continue
        shape, size, yaw, floating, build = drawn
        texture, prim = textured(paint, build, cells=(0.04, 0.15), scales=(0.15, 0.6))
        placed.append(Placed(shape=shape, size=size, yaw=yaw, floating=floating, texture=texture, primitive=prim))
    surround = SURROUNDS[int(layout.integers(len(SURROUNDS)))]
    lights = draw_lights(np.random.default_rng([seed, 20270303]))
    return RandomScene(
        seed=seed, ground=ground, ground_texture=ground_texture, objects=tuple(placed), surround=surround, lights=lights
    )


def random_primitives(seed: int) -> tuple[Primitive, ...]:
    """The whole random scene of `seed`: slab, objects and surroundings (shade it with `random_lights(seed)`)."""
    drawn = random_scene(seed)
    return (*drawn.primitives(), *drawn.surroundings())


def random_lights(seed: int) -> Lights:
    """The lights of the random scene of `seed`."""
    return random_scene(seed).lights


# ---------------------------------------------------------------- drawing


Build = Callable[[Material], Primitive]
"""A drawn shape waiting for its texture: its noise material -> the primitive."""


def _place(
    rng: np.random.Generator, taken: list[tuple[np.ndarray, float]]
) -> tuple[str, float, float, bool, Build] | None:
    """Draw one object clear of the bounding spheres `taken` (centre [3], radius): (shape, size, yaw, floating,
    build), or None when `TRIES` tries found no room."""
    shape = SHAPES[int(rng.integers(len(SHAPES)))]  # once: a crowded slab does not favour the compact shapes
    for attempt in range(TRIES):
        size = float(rng.uniform(SIZE[0], max(SIZE[0], SIZE[1] * 0.98**attempt)))
        yaw = float(rng.uniform(-math.pi, math.pi)) if shape == "box" else 0.0
        footprint, height, make = _shape(rng, shape, size, yaw)
        floating = bool(rng.uniform() < 0.2) and TOP - height > FLOAT[0]
        bottom = float(rng.uniform(FLOAT[0], min(FLOAT[1], TOP - height))) if floating else -SINK
        reach = max(0.0, SLAB_RADIUS - footprint - GAP)
        rad, ang = reach * math.sqrt(rng.uniform()), rng.uniform(0.0, 2 * math.pi)
        xy = np.array([rad * math.cos(ang), rad * math.sin(ang)])
        build = make(xy, bottom)
        centre, radius = build(_NO_MATERIAL).bounding_sphere()
        if all(np.linalg.norm(centre - c) >= radius + r + GAP for c, r in taken):
            return shape, size, yaw, floating, build
    return None


def _shape(
    rng: np.random.Generator, shape: str, size: float, yaw: float
) -> tuple[float, float, Callable[[np.ndarray, float], Build]]:
    """A shape of largest extent `size`: (footprint radius, height, make(xy [2], bottom z) -> build)."""
    if shape == "sphere":
        r = 0.5 * size
        return r, size, lambda xy, z: lambda m: Sphere(center=np.array([*xy, z + r]), radius=r, material=m)
    if shape == "box":
        half = 0.5 * size * rng.permutation([1.0, rng.uniform(0.4, 1.0), rng.uniform(0.4, 1.0)])
        return (
            float(np.hypot(half[0], half[1])),
            2 * float(half[2]),
            lambda xy, z: lambda m: Box(center=np.array([*xy, z + half[2]]), half=half, yaw=yaw, material=m),
        )
    tall = rng.uniform() < 0.5  # the height is the largest extent, else the diameter is
    other = size * rng.uniform(0.3, 1.0)
    r, h = (0.5 * other, size) if tall else (0.5 * size, other)
    return r, h, lambda xy, z: lambda m: Cylinder(center=xy, radius=r, z0=z, z1=z + h, sections=512, material=m)


_NO_MATERIAL = Material(key=0, rotation=np.eye(3), offset=np.zeros(3), cell_big=1.0, cell_small=1.0)
"""Stands in for a texture while only the geometry is looked at."""


def _rotation(rng: np.random.Generator) -> np.ndarray:
    """A random proper rotation [3, 3] (uniform on SO(3))."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def textured(
    rng: np.random.Generator, build: Build, cells: tuple[float, float], scales: tuple[float, float]
) -> tuple[str, Primitive]:
    """Texture a drawn shape: ('noise', with coloured cells of `cells` metres) or ('photo:<name>', a photo of
    `scales` metres per image width): (the texture's name, the primitive)."""
    cell_big = float(rng.uniform(*cells))
    solid = material(rng, int(rng.integers(0, 2**31)), cell_big, cell_big * float(rng.uniform(0.2, 0.4)))
    prim = build(solid)
    if rng.uniform() < 0.5:
        return "noise", prim
    names = PHOTOS + GREYS
    name = names[int(rng.integers(len(names)))]
    tint = np.ones(3) if name in PHOTOS else 0.3 + 0.7 * rng.uniform(size=3)
    scale = float(rng.uniform(*scales))
    origin = prim.bounding_sphere()[0] + scale * rng.uniform(-1.0, 1.0, 3)
    texture = PhotoTexture(name=name, tint=tint, rotation=_rotation(rng), origin=origin, scale=scale)
    return f"photo:{name}", PhotoTextured(shape=prim, photo=texture)


def draw_lights(rng: np.random.Generator) -> Lights:
    n = int(rng.integers(1, 4))
    elevation = np.radians(rng.uniform(20.0, 80.0, n))
    azimuth = rng.uniform(0.0, 2 * math.pi, n)
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1
    )
    share = np.sort(rng.dirichlet(np.ones(n)))[::-1]  # the key light first
    tint = 1.0 - rng.uniform(0.0, 0.2, 3)
    return Lights(
        directions=directions,
        intensities=rng.uniform(0.5, 0.9) * share,
        ambient=float(rng.uniform(0.15, 0.35)),
        tint=tint / tint.max(),
    )
