"""Analytic primitives and solid textures of the synthetic scene (the `scene` stage and other generators).

Conventions:
- World frame = scene frame: metres, right-handed, up +z. The ground slab's top face is the plane z = 0.
- Rays: origins `o [R, 3]` and unit directions `d [R, 3]` (float64); `t` is the Euclidean distance along the
  ray; `intersect` returns `t [R]` of the first hit in front of the origin, `inf` for a miss.
- Textures are *solid* (functions of the 3-D world point only), so every view sees the same colour at a surface
  point; shading is Lambertian with lights fixed in the world (`Lights`; no specular), hence view-consistent.
- Each primitive's `mesh()` is the same surface as a triangle mesh, tessellated finely enough that it deviates
  from the analytic surface by well under 0.1 mm (flat faces exactly).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

__all__ = [
    "Primitive",
    "Sphere",
    "Box",
    "Cylinder",
    "Material",
    "material",
    "solid_texture",
    "Lights",
    "DEFAULT_LIGHTS",
    "shade",
    "default_primitives",
    "backdrop",
    "room",
    "rot_z",
]


def rot_z(angle: float) -> np.ndarray:
    """[4, 4] rotation by `angle` radians about +z."""
    c, s = math.cos(angle), math.sin(angle)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


_MASK32 = np.uint64(0xFFFFFFFF)


@dataclass(frozen=True, kw_only=True)
class Material:
    """Parameters of one primitive's solid texture (deterministic from the scene seed)."""

    key: int
    """Hash key of this primitive's lattices."""
    rotation: np.ndarray
    """[3, 3] rotation of the texture lattices (so cells do not line up with box faces)."""
    offset: np.ndarray
    """[3] offset of the texture lattices, metres."""
    cell_big: float
    """Edge of the coloured cells, metres."""
    cell_small: float
    """Edge of the light/dark cells, metres."""


class Primitive:
    """A closed analytic surface with a solid texture."""

    material: Material

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:  # [R, 3], [R, 3] -> t [R]
        raise NotImplementedError

    def normal(self, p: np.ndarray) -> np.ndarray:  # points on the surface [N, 3] -> unit normals [N, 3]
        raise NotImplementedError

    def mesh(self) -> trimesh.Trimesh:
        raise NotImplementedError

    def albedo(self, p: np.ndarray) -> np.ndarray:  # points on the surface [N, 3] -> albedo [N, 3] in [0, 1]
        """The surface colour before shading: the primitive's solid texture (`prints.PrintedBox`: its prints)."""
        return solid_texture(p, self.material)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:  # centre [3], radius: encloses the primitive
        raise NotImplementedError

    def candidates(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Rays [R] that may hit the primitive (they meet its bounding sphere in front of the origin)."""
        c, r = self.bounding_sphere()
        oc = o - c
        b = oc[:, 0] * d[:, 0] + oc[:, 1] * d[:, 1] + oc[:, 2] * d[:, 2]
        cc = oc[:, 0] ** 2 + oc[:, 1] ** 2 + oc[:, 2] ** 2 - r * r
        return (b * b - cc >= 0) & ((b <= 0) | (cc <= 0))


def _apply(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """x @ m.T for x [N, 3], m [3, 3], as plain elementwise ops (BLAS threads gain nothing at K = 3)."""
    return x[:, :1] * m[:, 0] + x[:, 1:2] * m[:, 1] + x[:, 2:3] * m[:, 2]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _first_positive(*ts: np.ndarray) -> np.ndarray:
    """Smallest candidate t > 0 per ray (inf where none); candidates may hold nan/inf for a miss."""
    best = np.full_like(ts[0], np.inf)
    for t in ts:
        ok = np.isfinite(t) & (t > 1e-9)
        best = np.where(ok & (t < best), t, best)
    return best


@dataclass(frozen=True, kw_only=True)
class Sphere(Primitive):
    center: np.ndarray
    """[3] centre, metres."""
    radius: float
    """Radius, metres."""
    material: Material

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        oc = o - self.center
        b = _dot(oc, d)
        c = _dot(oc, oc) - self.radius**2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.sqrt(disc)
        return _first_positive(-b - s, -b + s)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.center, self.radius * 1.001

    def normal(self, p: np.ndarray) -> np.ndarray:
        n = p - self.center
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def mesh(self) -> trimesh.Trimesh:
        # subdivisions=5: 20480 faces; sagitta ~ r * 2e-4 (0.04 mm at r = 0.2 m).
        m = trimesh.creation.icosphere(subdivisions=5, radius=self.radius)
        m.apply_translation(self.center)
        return m


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, kw_only=True)
class Box(Primitive):
    center: np.ndarray
    """[3] centre, metres."""
    half: np.ndarray
    """[3] half extents along the box's own axes, metres."""
    yaw: float
    """Rotation about world z, radians."""
    material: Material

    def _local(self, x: np.ndarray, is_dir: bool) -> np.ndarray:
        return _apply(x if is_dir else x - self.center, _rot_z(self.yaw).T)  # box_from_world

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.center, float(np.linalg.norm(self.half)) * 1.001

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol, dl = self._local(o, False), self._local(d, True)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-self.half - ol) / dl
            t2 = (self.half - ol) / dl
        lo, hi = np.fmin(t1, t2), np.fmax(t1, t2)  # fmin/fmax skip nan (0 / 0 on a slab face)
        tmin = np.fmax(np.fmax(lo[:, 0], lo[:, 1]), lo[:, 2])
        tmax = np.fmin(np.fmin(hi[:, 0], hi[:, 1]), hi[:, 2])
        hit = tmax >= np.maximum(tmin, 0.0)
        t = np.where(tmin > 1e-9, tmin, tmax)
        return np.where(hit & (t > 1e-9), t, np.inf)

    def normal(self, p: np.ndarray) -> np.ndarray:
        pl = self._local(p, False) / self.half  # on the surface: max |component| == 1
        axis = np.argmax(np.abs(pl), axis=-1)
        nl = np.zeros_like(pl)
        nl[np.arange(len(pl)), axis] = np.sign(pl[np.arange(len(pl)), axis])
        return _apply(nl, _rot_z(self.yaw))

    def mesh(self) -> trimesh.Trimesh:
        tf = np.eye(4)
        tf[:3, :3] = _rot_z(self.yaw)
        tf[:3, 3] = self.center
        return trimesh.creation.box(extents=2 * self.half, transform=tf)


@dataclass(frozen=True, kw_only=True)
class Cylinder(Primitive):
    """Upright cylinder (axis along world z) with flat caps."""

    center: np.ndarray
    """[2] axis position (x, y), metres."""
    radius: float
    """Radius, metres."""
    z0: float
    """Bottom cap height, metres."""
    z1: float
    """Top cap height, metres."""
    material: Material
    sections: int = 1024
    """Mesh segments around the axis (sagitta r * (pi / sections)^2 / 2: 3.5 um at r = 0.75 m)."""

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ox, oy = o[:, 0] - self.center[0], o[:, 1] - self.center[1]
        dx, dy, oz, dz = d[:, 0], d[:, 1], o[:, 2], d[:, 2]
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.radius**2
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.sqrt(b * b - a * c)
            sides = [(-b - s) / a, (-b + s) / a]
            sides = [np.where((oz + t * dz >= self.z0) & (oz + t * dz <= self.z1), t, np.nan) for t in sides]
            caps = []
            for zc in (self.z0, self.z1):
                t = (zc - oz) / dz
                x, y = ox + t * dx, oy + t * dy
                caps.append(np.where(x * x + y * y <= self.radius**2, t, np.nan))
        return _first_positive(*sides, *caps)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        half_h = 0.5 * (self.z1 - self.z0)
        c = np.array([self.center[0], self.center[1], self.z0 + half_h])
        return c, float(np.hypot(self.radius, half_h)) * 1.001

    def normal(self, p: np.ndarray) -> np.ndarray:
        rel = p[:, :2] - self.center
        rad = np.linalg.norm(rel, axis=-1)
        mid, half_h = 0.5 * (self.z0 + self.z1), 0.5 * (self.z1 - self.z0)
        dz = p[:, 2] - mid
        # On the surface, whichever of the radial / axial fractions is closer to 1 names the face.
        side = np.abs(rad / self.radius - 1.0) < np.abs(np.abs(dz) / half_h - 1.0)
        n = np.zeros_like(p)
        n[:, :2] = np.where(side[:, None], rel / np.maximum(rad, 1e-12)[:, None], 0.0)
        n[:, 2] = np.where(side, 0.0, np.sign(dz))
        return n

    def mesh(self) -> trimesh.Trimesh:
        tf = np.eye(4)
        tf[:3, 3] = [self.center[0], self.center[1], 0.5 * (self.z0 + self.z1)]
        return trimesh.creation.cylinder(
            radius=self.radius, height=self.z1 - self.z0, sections=self.sections, transform=tf
        )


# ---------------------------------------------------------------- solid textures


def _hash(ijk: np.ndarray, key: int) -> np.ndarray:
    """Integer lattice points [N, 3] (int64) -> uint32 hashes [N] (murmur3 finaliser; platform-independent)."""
    u = (ijk.astype(np.int64).view(np.uint64)) & _MASK32
    h = (u[:, 0] * np.uint64(73856093)) ^ (u[:, 1] * np.uint64(19349663)) ^ (u[:, 2] * np.uint64(83492791))
    h = (h ^ np.uint64(key & 0xFFFFFFFF) * np.uint64(2654435761)) & _MASK32
    h ^= h >> np.uint64(16)
    h = (h * np.uint64(0x85EBCA6B)) & _MASK32
    h ^= h >> np.uint64(13)
    h = (h * np.uint64(0xC2B2AE35)) & _MASK32
    h ^= h >> np.uint64(16)
    return h


def _unit(h: np.ndarray) -> np.ndarray:
    return h.astype(np.float64) / 4294967296.0


def _cells(q: np.ndarray, size: float, key: int) -> np.ndarray:
    """One uniform random value in [0, 1) per cubic cell of edge `size`. q: [N, 3] -> [N]."""
    return _unit(_hash(np.floor(q / size), key))


def _value_noise(q: np.ndarray, size: float, key: int) -> np.ndarray:
    """Smooth (trilinear, smoothstep-weighted) value noise in [0, 1]. q: [N, 3] -> [N]."""
    g = q / size
    i = np.floor(g)
    f = g - i
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(q))
    for corner in range(8):
        c = [(corner >> k) & 1 for k in range(3)]
        w = (f[:, 0] if c[0] else 1 - f[:, 0]) * (f[:, 1] if c[1] else 1 - f[:, 1]) * (f[:, 2] if c[2] else 1 - f[:, 2])
        out += w * _unit(_hash(i + np.array(c, dtype=np.float64), key))
    return out


def solid_texture(p: np.ndarray, mat: Material) -> np.ndarray:
    """Albedo [N, 3] in [0, 1] at world points p [N, 3].

    Coloured cells (~10 cm), light/dark cells (~3 cm) and two octaves of value noise: strong contrast at
    several scales, so SIFT finds blobs and corners at every image size from 64 to 512 px.
    """
    q = _apply(p, mat.rotation) + mat.offset
    k = mat.key
    big = np.stack([_cells(q, mat.cell_big, k + 11 * c) for c in range(3)], axis=-1)
    colour = 0.08 + 0.87 * big
    small = _cells(q + 0.37 * mat.cell_small, mat.cell_small, k + 101)
    level = np.where(small < 0.5, 0.3, 1.0) + 0.25 * (_cells(q, 0.5 * mat.cell_small, k + 202) - 0.5)
    noise = 0.75 + 0.5 * _value_noise(q, 2.2 * mat.cell_big, k + 303) * _value_noise(q, 0.6 * mat.cell_small, k + 404)
    return np.clip(colour * level[:, None] * noise[:, None], 0.0, 1.0)


@dataclass(frozen=True, kw_only=True)
class Lights:
    """What `shade` lights a surface with: directional lights (fixed in the world, no shadows) plus ambient, all
    of one colour. `DEFAULT_LIGHTS` lights every fixed scene; `random_scene` draws others per seed."""

    directions: np.ndarray
    """[L, 3] unit vectors from a surface towards each light, world frame."""
    intensities: np.ndarray
    """[L] intensity of each light: a surface facing it gets this much light on top of `ambient`."""
    ambient: float
    """Light that reaches every surface whatever its normal."""
    tint: np.ndarray = field(default_factory=lambda: np.ones(3))
    """[3] RGB colour of all the light, multiplying the shaded colour ((1, 1, 1): white, today's scenes)."""

    def __post_init__(self) -> None:
        d, i, t = np.asarray(self.directions), np.asarray(self.intensities), np.asarray(self.tint)
        if d.ndim != 2 or d.shape[1] != 3 or i.shape != (len(d),):
            raise ValueError(f"expected directions [L, 3] and intensities [L], got {d.shape} and {i.shape}")
        if not np.allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-9):
            raise ValueError(f"expected unit light directions, got norms {np.linalg.norm(d, axis=-1).tolist()}")
        if (i < 0).any() or self.ambient < 0 or t.shape != (3,) or (t < 0).any():
            raise ValueError(
                f"expected intensities >= 0, ambient >= 0 and tint [3] >= 0, got {i.tolist()}, {self.ambient}, "
                f"{t.tolist()}"
            )


DEFAULT_LIGHTS = Lights(
    directions=np.stack(
        [
            np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84]),
            np.array([-0.6, -0.5, 0.62]) / np.linalg.norm([-0.6, -0.5, 0.62]),
        ]
    ),
    intensities=np.array([0.62, 0.25]),
    ambient=0.3,
)
"""The lights of every fixed scene (the objects, the printed boxes, the room and wall): a key light, a fill."""


def shade(albedo: np.ndarray, n: np.ndarray, lights: Lights = DEFAULT_LIGHTS) -> np.ndarray:
    """Lambertian shading: albedo [N, 3] at unit normals n [N, 3] -> colour [N, 3] in [0, 1] (no specular, no
    shadows)."""
    light = np.full(len(n), lights.ambient)
    for direction, intensity in zip(lights.directions, lights.intensities, strict=True):
        light += intensity * np.clip(
            n[:, 0] * direction[0] + n[:, 1] * direction[1] + n[:, 2] * direction[2], 0.0, None
        )
    return np.clip(albedo * light[:, None] * lights.tint, 0.0, 1.0)  # a tint of 1.0 changes no bit


# ---------------------------------------------------------------- the scene


def material(rng: np.random.Generator, key: int, cell_big: float, cell_small: float) -> Material:
    """A solid texture of coloured cells `cell_big` and light/dark cells `cell_small` (metres), its lattices turned
    and offset at random by `rng`, hashed with `key`."""
    a = rng.normal(size=(3, 3))
    q, r = np.linalg.qr(a)
    q = q * np.sign(np.diag(r))  # a proper random orthonormal matrix
    return Material(key=key, rotation=q, offset=rng.uniform(-1.0, 1.0, 3), cell_big=cell_big, cell_small=cell_small)


def default_primitives(seed: int) -> tuple[Primitive, ...]:
    """The demo scene: a textured ground slab (radius 0.75 m, top at z = 0) and five objects on it.

    The layout is fixed (objects 0.2-0.5 m, none touching another; each rests slightly sunk, 1 cm, into the
    slab so no faces are coplanar); the seed picks the textures.
    """
    rng = np.random.default_rng([seed, 20240611])
    keys = rng.integers(0, 2**31, size=6)
    sink = 0.01
    return (
        Cylinder(
            center=np.array([0.0, 0.0]),
            radius=0.75,
            z0=-0.05,
            z1=0.0,
            material=material(rng, int(keys[0]), 0.12, 0.035),
        ),
        Sphere(
            center=np.array([-0.28, 0.22, 0.2 - sink]), radius=0.2, material=material(rng, int(keys[1]), 0.08, 0.025)
        ),
        Box(
            center=np.array([0.27, 0.22, 0.16 - sink]),
            half=np.array([0.16, 0.1, 0.16]),
            yaw=0.5,
            material=material(rng, int(keys[2]), 0.08, 0.025),
        ),
        Cylinder(
            center=np.array([0.05, -0.3]),
            radius=0.12,
            z0=-sink,
            z1=0.45,
            sections=512,
            material=material(rng, int(keys[3]), 0.08, 0.025),
        ),
        Box(
            center=np.array([-0.38, -0.22, 0.09 - sink]),
            half=np.array([0.09, 0.09, 0.09]),
            yaw=-0.35,
            material=material(rng, int(keys[4]), 0.06, 0.02),
        ),
        Sphere(
            center=np.array([0.4, -0.2, 0.12 - sink]), radius=0.12, material=material(rng, int(keys[5]), 0.06, 0.02)
        ),
    )


def room(seed: int) -> tuple[Primitive, ...]:
    """A textured room round the objects: a floor 0.25 m below the slab's top and four walls 4 m from the
    centre, 3.25 m tall (8 m x 8 m): the unbounded background a phone capture of an object in a room sees."""
    rng = np.random.default_rng([seed, 20261123])
    keys = [int(k) for k in rng.integers(0, 2**31, size=5)]
    floor = Box(
        center=np.array([0.0, 0.0, -0.3]),
        half=np.array([4.0, 4.0, 0.05]),
        yaw=0.0,
        material=material(rng, keys[0], 0.45, 0.2),
    )
    walls = [
        Box(center=np.array(c), half=np.array(h), yaw=0.0, material=material(rng, k, 0.55, 0.2))
        for c, h, k in (
            ((0.0, 4.05, 1.375), (4.1, 0.05, 1.625), keys[1]),
            ((0.0, -4.05, 1.375), (4.1, 0.05, 1.625), keys[2]),
            ((4.05, 0.0, 1.375), (0.05, 4.1, 1.625), keys[3]),
            ((-4.05, 0.0, 1.375), (0.05, 4.1, 1.625), keys[4]),
        )
    ]
    return (floor, *walls)


def backdrop(seed: int) -> Primitive:
    """A textured wall 4 m behind the objects (seen from azimuth -90 deg: the plane y = 4), 8 m wide and 6 m
    tall: the far content of a forward-facing capture, beyond any box drawn round the objects."""
    rng = np.random.default_rng([seed, 20261122])
    key = int(rng.integers(0, 2**31))
    return Box(
        center=np.array([0.0, 4.05, 0.0]),
        half=np.array([4.0, 0.05, 3.0]),
        yaw=0.0,
        material=material(rng, key, 0.5, 0.15),
    )
