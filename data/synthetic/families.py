"""Shape families: furniture-like objects built from boxes, upright cylinders and spheres, with exact occupancy.

What the single-view voxel network (`nerfpipe voxels`) is pretrained on: 3D-R2N2 and Pix2Vox train on ShapeNet's
chairs, tables, lamps...; here a seed draws one object of a family (`FAMILIES`) from its parts, the same parts
render it (`data.synthetic.raycast`, through `primitives`) and give its occupancy (`inside`), so the ground truth
is exact, not a voxelised mesh.

Conventions:
- Object frame: right-handed, up +z; the object stands on z = 0 before `normalise`; its front (a chair's seat
  edge, a sofa's seat) faces -y. Boxes are axis-aligned in the object frame (no yaw: the camera's azimuth turns
  the object).
- `normalise` puts the object in the unit frame: centred on the vertical axis through the middle of its bounding
  box and at half its height, scaled by `1 / max(2 * reach, height)` (`reach`: the farthest point from that axis),
  so the object fits the vertical cylinder of radius 0.5 and height 1 about the origin whatever it is turned by:
  the voxel grid's cube [-0.5, 0.5]^3 holds it seen from any azimuth.
- Parts: `Part(kind, a, b)`: "box" (a = centre [3], b = half extents [3]), "cyl" (a = (x, y, z0), b = (radius,
  z1, 0)), "sphere" (a = centre [3], b = (radius, 0, 0)).
- Thin parts are drawn at least `THIN` thick relative to the object's size, so that a 32^3 grid (cell 1/32)
  sees them: a leg thinner than half a cell would be in no voxel's majority.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from nerfpipe.data.synthetic.objects import Box, Cylinder, Primitive, Sphere
from nerfpipe.data.synthetic.random_scene import textured

__all__ = [
    "FAMILIES",
    "HELD_OUT",
    "TRAINED",
    "THIN",
    "Part",
    "Shape",
    "shape",
    "normalise",
    "inside",
    "primitives",
]

THIN = 0.05
"""Least thickness of a part, as a fraction of the object's largest extent (1.6 cells of a 32^3 grid)."""


@dataclass(frozen=True)
class Part:
    kind: str  # box, cyl, sphere
    a: tuple[float, float, float]
    b: tuple[float, float, float]


@dataclass(frozen=True)
class Shape:
    family: str
    seed: int
    parts: tuple[Part, ...]
    """In the unit frame (module doc) once `normalise`d."""
    scale: float = 1.0
    """Unit frame from object frame: p_unit = (p_object - centre) * scale."""
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The object frame's point at the unit frame's origin, metres."""


def _box(x: float, y: float, z: float, hx: float, hy: float, hz: float) -> Part:
    return Part("box", (x, y, z), (hx, hy, hz))


def _post(x: float, y: float, z0: float, z1: float, r: float) -> Part:
    return Part("cyl", (x, y, z0), (r, z1, 0.0))


def _legs(rng: np.random.Generator, hx: float, hy: float, top: float, t: float, round_: bool) -> list[Part]:
    """Four legs under a top of half extents (hx, hy) at height `top`, thickness t, inset a little."""
    inset = rng.uniform(0.0, 0.15)
    xs, ys = (hx - t) * (1 - inset), (hy - t) * (1 - inset)
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            if round_:
                out.append(_post(sx * xs, sy * ys, 0.0, top, t))
            else:
                out.append(_box(sx * xs, sy * ys, top / 2, t, t, top / 2))
    return out


def _chair(rng: np.random.Generator) -> list[Part]:
    w, d = rng.uniform(0.4, 0.6, 2) / 2
    seat_h, seat_t = rng.uniform(0.38, 0.5), rng.uniform(0.04, 0.08)
    t = rng.uniform(0.025, 0.045)
    parts = [_box(0, 0, seat_h - seat_t / 2, w, d, seat_t / 2)]
    parts += _legs(rng, w, d, seat_h - seat_t, t, rng.uniform() < 0.4)
    back_h, back_t = rng.uniform(0.3, 0.6), rng.uniform(0.03, 0.06)
    if rng.uniform() < 0.6:  # a solid back
        parts.append(_box(0, d - back_t / 2, seat_h + back_h / 2, w, back_t / 2, back_h / 2))
    else:  # two posts and a top rail
        rail = rng.uniform(0.06, 0.15)
        for sx in (-1, 1):
            parts.append(_box(sx * (w - t), d - back_t / 2, seat_h + back_h / 2, t, back_t / 2, back_h / 2))
        parts.append(_box(0, d - back_t / 2, seat_h + back_h - rail / 2, w, back_t / 2, rail / 2))
    if rng.uniform() < 0.3:  # arms
        arm_h = rng.uniform(0.18, 0.28)
        for sx in (-1, 1):
            parts.append(_box(sx * (w - t), 0, seat_h + arm_h, t, d * 0.9, t))
            parts.append(_box(sx * (w - t), -d * 0.7, seat_h + arm_h / 2, t, t, arm_h / 2))
    return parts


def _table(rng: np.random.Generator) -> list[Part]:
    h, top_t = rng.uniform(0.6, 0.8), rng.uniform(0.03, 0.07)
    if rng.uniform() < 0.35:  # round, one pedestal
        r = rng.uniform(0.35, 0.6)
        post = rng.uniform(0.04, 0.08)
        return [
            Part("cyl", (0, 0, h - top_t), (r, h, 0)),
            _post(0, 0, 0.0, h - top_t, post),
            Part("cyl", (0, 0, 0.0), (rng.uniform(0.5, 0.8) * r, rng.uniform(0.03, 0.06), 0)),
        ]
    w, d = rng.uniform(0.8, 1.6) / 2, rng.uniform(0.5, 1.0) / 2
    t = rng.uniform(0.03, 0.06)
    parts = [_box(0, 0, h - top_t / 2, w, d, top_t / 2)]
    parts += _legs(rng, w, d, h - top_t, t, rng.uniform() < 0.3)
    if rng.uniform() < 0.3:  # a shelf between the legs
        parts.append(_box(0, 0, rng.uniform(0.1, 0.25), w * 0.85, d * 0.85, top_t / 2))
    return parts


def _stool(rng: np.random.Generator) -> list[Part]:
    h, r = rng.uniform(0.45, 0.8), rng.uniform(0.15, 0.22)
    seat_t = rng.uniform(0.04, 0.08)
    t = rng.uniform(0.02, 0.035)
    n = int(rng.integers(3, 5))
    parts = [Part("cyl", (0, 0, h - seat_t), (r, h, 0))]
    spread = r * rng.uniform(0.6, 0.85)
    turn = rng.uniform(0, 2 * math.pi)
    for k in range(n):
        a = turn + 2 * math.pi * k / n
        parts.append(_post(spread * math.cos(a), spread * math.sin(a), 0.0, h - seat_t, t))
    if rng.uniform() < 0.5:  # a foot ring, as a thin disk
        z = rng.uniform(0.15, 0.3) * h
        parts.append(Part("cyl", (0, 0, z), (spread + t, z + 0.03, 0)))
    return parts


def _lamp(rng: np.random.Generator) -> list[Part]:
    h = rng.uniform(0.4, 1.6)
    base_t = rng.uniform(0.02, 0.05) * h
    parts = []
    if rng.uniform() < 0.6:
        parts.append(Part("cyl", (0, 0, 0.0), (rng.uniform(0.1, 0.2) * h, base_t, 0)))
    else:
        b = rng.uniform(0.08, 0.18) * h
        parts.append(_box(0, 0, base_t / 2, b, b, base_t / 2))
    shade_h = rng.uniform(0.15, 0.3) * h
    parts.append(_post(0, 0, base_t, h - shade_h * 0.5, rng.uniform(0.03, 0.05) * h))
    if rng.uniform() < 0.65:  # a cylinder shade, wider than its base
        parts.append(Part("cyl", (0, 0, h - shade_h), (rng.uniform(0.12, 0.25) * h, h, 0)))
    else:  # a globe
        r = rng.uniform(0.1, 0.18) * h
        parts.append(Part("sphere", (0, 0, h - r), (r, 0, 0)))
    return parts


def _shelf(rng: np.random.Generator) -> list[Part]:
    w, d, h = rng.uniform(0.5, 1.2) / 2, rng.uniform(0.2, 0.4) / 2, rng.uniform(0.6, 1.8)
    t = rng.uniform(0.02, 0.04)
    n = int(rng.integers(3, 7))
    parts = [_box(sx * (w - t / 2), 0, h / 2, t / 2, d, h / 2) for sx in (-1, 1)]
    for k in range(n):
        z = t / 2 + (h - t) * k / (n - 1)
        parts.append(_box(0, 0, z, w, d, t / 2))
    if rng.uniform() < 0.5:  # a back panel
        parts.append(_box(0, d - t / 2, h / 2, w, t / 2, h / 2))
    return parts


def _mug(rng: np.random.Generator) -> list[Part]:
    r, h = rng.uniform(0.035, 0.06), rng.uniform(0.08, 0.14)
    t = rng.uniform(0.1, 0.15) * h
    reach = rng.uniform(0.03, 0.05)
    lo, hi = h * rng.uniform(0.15, 0.3), h * rng.uniform(0.7, 0.85)
    x = r + reach
    return [
        Part("cyl", (0, 0, 0.0), (r, h, 0)),
        _box(x - t / 2, 0, (lo + hi) / 2, t / 2, t / 2, (hi - lo) / 2 + t / 2),
        _box(r + reach / 2, 0, hi, reach / 2 + t / 2, t / 2, t / 2),
        _box(r + reach / 2, 0, lo, reach / 2 + t / 2, t / 2, t / 2),
    ]


def _bed(rng: np.random.Generator) -> list[Part]:
    w, d = rng.uniform(0.9, 1.8) / 2, rng.uniform(1.9, 2.2) / 2
    base_h, mat_h = rng.uniform(0.2, 0.4), rng.uniform(0.12, 0.25)
    head_h = rng.uniform(0.3, 0.7)
    t = rng.uniform(0.04, 0.08)
    parts = [
        _box(0, 0, base_h / 2 + 0.05, w, d, base_h / 2),
        _box(0, -0.02, base_h + 0.05 + mat_h / 2, w * 0.97, d * 0.95, mat_h / 2),
        _box(0, d + t / 2, (base_h + head_h + 0.05) / 2, w, t / 2, (base_h + head_h + 0.05) / 2),
    ]
    parts += _legs(rng, w, d, 0.05, 0.05, False)
    if rng.uniform() < 0.4:  # a footboard
        foot = base_h + 0.05 + rng.uniform(0.0, 0.2)
        parts.append(_box(0, -d - t / 2, foot / 2, w, t / 2, foot / 2))
    return parts


def _sofa(rng: np.random.Generator) -> list[Part]:
    w, d = rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.5)
    seat_h, back_h = rng.uniform(0.35, 0.45), rng.uniform(0.3, 0.5)
    arm_w, arm_h, back_t = rng.uniform(0.08, 0.2), rng.uniform(0.15, 0.3), rng.uniform(0.12, 0.22)
    legs = rng.uniform() < 0.5
    lift = 0.08 if legs else 0.0
    parts = [
        _box(0, 0, lift + (seat_h - lift) / 2, w, d, (seat_h - lift) / 2),
        _box(0, d - back_t / 2, lift + (seat_h + back_h - lift) / 2, w, back_t / 2, (seat_h + back_h - lift) / 2),
    ]
    for sx in (-1, 1):
        parts.append(
            _box(sx * (w - arm_w / 2), 0, lift + (seat_h + arm_h - lift) / 2, arm_w / 2, d, (seat_h + arm_h - lift) / 2)
        )
    if legs:
        parts += _legs(rng, w, d, lift, 0.04, rng.uniform() < 0.5)
    return parts


FAMILIES: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "chair": _chair,
    "table": _table,
    "stool": _stool,
    "lamp": _lamp,
    "shelf": _shelf,
    "mug": _mug,
    "bed": _bed,
    "sofa": _sofa,
}
HELD_OUT = "sofa"
"""The family left out of pretraining entirely (`make pretrain-voxels`): what the network makes of a kind of
object it never saw."""
TRAINED = tuple(f for f in FAMILIES if f != HELD_OUT)


def _bounds(part: Part) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo [3], hi [3]) of one part, object frame."""
    a, b = np.asarray(part.a, float), np.asarray(part.b, float)
    if part.kind == "box":
        return a - b, a + b
    if part.kind == "cyl":
        r = b[0]
        return np.array([a[0] - r, a[1] - r, a[2]]), np.array([a[0] + r, a[1] + r, b[1]])
    return a - b[0], a + b[0]


def _reach(part: Part, axis: np.ndarray) -> float:
    """Farthest horizontal distance of the part from the vertical line through `axis` (x, y)."""
    a, b = np.asarray(part.a, float), np.asarray(part.b, float)
    if part.kind == "box":
        corners = np.array([[a[0] + sx * b[0], a[1] + sy * b[1]] for sx in (-1, 1) for sy in (-1, 1)])
        return float(np.max(np.linalg.norm(corners - axis, axis=-1)))
    return float(np.linalg.norm(a[:2] - axis) + b[0])


def _thicken(part: Part, least: float) -> Part:
    a, b = part.a, part.b
    if part.kind == "box":
        return Part("box", a, tuple(max(h, least / 2) for h in b))
    if part.kind == "cyl":
        return Part("cyl", a, (max(b[0], least / 2), max(b[1], a[2] + least), 0.0))
    return Part("sphere", a, (max(b[0], least / 2), 0.0, 0.0))


def normalise(family: str, seed: int, parts: list[Part]) -> Shape:
    """The unit-frame shape (module doc) of parts drawn in the object frame; parts thinner than `THIN` of the
    object's largest extent are thickened first."""
    lo = np.min([_bounds(p)[0] for p in parts], axis=0)
    hi = np.max([_bounds(p)[1] for p in parts], axis=0)
    parts = [_thicken(p, THIN * float(np.max(hi - lo))) for p in parts]
    lo = np.min([_bounds(p)[0] for p in parts], axis=0)
    hi = np.max([_bounds(p)[1] for p in parts], axis=0)
    axis = 0.5 * (lo[:2] + hi[:2])
    reach = max(_reach(p, axis) for p in parts)
    scale = 1.0 / max(2 * reach, float(hi[2] - lo[2]))
    centre = np.array([axis[0], axis[1], 0.5 * (lo[2] + hi[2])])
    out = []
    for p in parts:
        a, b = (np.asarray(p.a, float) - centre) * scale, np.asarray(p.b, float) * scale
        if p.kind == "cyl":  # b[1] is the top height: a position, not a length
            b[1] = (p.b[1] - centre[2]) * scale
        out.append(Part(p.kind, tuple(map(float, a)), tuple(map(float, b))))
    return Shape(family=family, seed=seed, parts=tuple(out), scale=scale, centre=tuple(map(float, centre)))


def shape(family: str, seed: int) -> Shape:
    """The object of `family` drawn by `seed`, in the unit frame."""
    if family not in FAMILIES:
        raise ValueError(f"expected a family in {sorted(FAMILIES)}, got {family!r}")
    rng = np.random.default_rng([seed, sorted(FAMILIES).index(family), 50])
    return normalise(family, seed, FAMILIES[family](rng))


def inside(parts: tuple[Part, ...], p: np.ndarray) -> np.ndarray:
    """Whether each point p [N, 3] lies inside any part: bool [N] (the exact occupancy)."""
    hit = np.zeros(len(p), bool)
    for part in parts:
        a, b = np.asarray(part.a), np.asarray(part.b)
        if part.kind == "box":
            hit |= np.all(np.abs(p - a) <= b, axis=-1)
        elif part.kind == "cyl":
            r2 = (p[:, 0] - a[0]) ** 2 + (p[:, 1] - a[1]) ** 2
            hit |= (r2 <= b[0] ** 2) & (p[:, 2] >= a[2]) & (p[:, 2] <= b[1])
        else:
            hit |= np.sum((p - a) ** 2, axis=-1) <= b[0] ** 2
    return hit


def primitives(s: Shape, rng: np.random.Generator) -> tuple[Primitive, ...]:
    """The shape's parts as renderable primitives (`data.synthetic.objects`), each textured by `rng` (solid noise
    or a photograph, as `random_scene` textures its objects; one texture for the whole object half the time)."""
    builds = []
    for part in s.parts:
        a, b = np.asarray(part.a), np.asarray(part.b)
        if part.kind == "box":
            builds.append(lambda m, a=a, b=b: Box(center=a, half=b, yaw=0.0, material=m))
        elif part.kind == "cyl":
            builds.append(
                lambda m, a=a, b=b: Cylinder(
                    center=a[:2], radius=float(b[0]), z0=float(a[2]), z1=float(b[1]), sections=256, material=m
                )
            )
        else:
            builds.append(lambda m, a=a, b=b: Sphere(center=a, radius=float(b[0]), material=m))
    if rng.uniform() < 0.5:  # one texture (drawn once) for every part
        state = rng.bit_generator.state
        out = []
        for build in builds:
            rng.bit_generator.state = state
            out.append(textured(rng, build, (0.05, 0.3), (0.3, 1.5))[1])
        return tuple(out)
    return tuple(textured(rng, build, (0.05, 0.3), (0.3, 1.5))[1] for build in builds)
