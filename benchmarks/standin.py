"""Test and benchmark support for `stages.mesh` (tests/test_mesh.py, benchmarks/bench_mesh.py; never imported by
product code): an analytic stand-in for a trained run, and the visibility of points in the synthetic scene
(`stages.scene`) for fair Chamfer distances.

`StandIn` is a run (`model.run.Run`) with the capabilities rays, density and colour: `density`, `color`, `aabb`,
`occupancy` (None), `scene`, `device`, `space` (a box in the scene frame). The object is a union of a sphere
and a box (optionally plus a small floating ball) given by a signed distance `sdf` in the scene frame; the density
is
    sigma(x) = sigma_max * sigmoid(-sdf(x) / eps),   sigma_max = 1 / eps,
so a ray hitting the surface head-on accumulates optical depth ln 2 (opacity 0.5) exactly at sdf = 0, where
sigma = sigma_max / 2: the auto threshold should find ~sigma_max / 2 and the iso-surface is the exact surface.
Cameras look at the origin from a sphere of radius 3 (OpenGL axes); the scene's `applied_transform` /
`applied_scale` are non-trivial, so the user (source) frame differs from the scene frame.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.transforms import Frame, Scene
from nerfpipe.radiance.camera import Intrinsics, project
from nerfpipe.radiance.paths import look_at
from nerfpipe.radiance.space import Box

Z_UP = np.array([0.0, 0.0, 1.0])

__all__ = ["StandIn", "visible_points", "VISIBILITY_TOL"]

VISIBILITY_TOL = 0.01
"""Metres: a point counts as seen when the first hit towards it is at most this much nearer."""

SPHERE = (np.array([-0.25, 0.0, 0.0]), 0.35)  # centre, radius (scene frame)
BOX = (np.array([0.3, 0.05, 0.0]), np.array([0.2, 0.25, 0.3]))  # centre, half extents
FLOATER = (np.array([0.62, 0.62, 0.62]), 0.04)


def _rotation(axis, angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(angle_deg)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


class StandIn:
    """Analytic field + scene with the `Trained` attributes (see module doc)."""

    has_color = True
    method = "standin"
    capabilities = frozenset({"rays", "density", "color"})
    downscale = 1.0
    """Trained at full size."""
    far = math.inf
    pose_refinement = None
    appearance = None

    def __init__(
        self,
        root: str | Path = ".",
        *,
        eps: float = 0.01,
        floater: bool = False,
        mirror: bool = False,
        identity: bool = False,
        views: int = 24,
        size: int = 64,
        empty: bool = False,
    ):
        self.eps, self.floater, self.empty = eps, floater, empty
        self.aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
        self.occupancy = None
        self.device = torch.device("cpu")
        lo, hi = self.aabb.tolist()
        self.space = Box(aabb=(tuple(lo), tuple(hi)), near=0.0, far=math.inf)  # the analytic field is the scene's
        rot = _rotation([1.0, 2.0, 3.0], 40.0) @ (np.diag([1.0, 1.0, -1.0]) if mirror else np.eye(3))
        applied = np.concatenate([rot, np.array([[0.3], [-0.2], [0.5]])], axis=1)  # [3, 4]
        frames = []
        golden = math.pi * (3 - math.sqrt(5))
        for i in range(views):  # Fibonacci sphere, radius 3
            z = 1 - 2 * (i + 0.5) / views
            r = math.sqrt(1 - z * z)
            eye = 3.0 * np.array([r * math.cos(golden * i), r * math.sin(golden * i), z])
            frames.append(
                Frame(
                    file_path=f"images/{i:03d}.png", world_from_cam=look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
                )
            )
        focal = 0.5 * size / math.tan(math.radians(20.0))
        self.scene = Scene(
            root=Path(root),
            frames=tuple(frames),
            intrinsics=Intrinsics(w=size, h=size, fx=focal, fy=focal, cx=size / 2, cy=size / 2),
            applied_transform=np.eye(4)[:3] if identity else applied,
            applied_scale=1.0 if identity else 0.25,
            aabb=self.aabb.numpy().astype(np.float64),
            near=0.1,
            far=10.0,
        )

    # ------------------------------------------------------------------ field
    def sdf(self, x: Tensor) -> Tensor:
        """x [N, 3] scene frame -> signed distance [N] (negative inside)."""
        c, r = (torch.as_tensor(v, dtype=x.dtype) for v in SPHERE)
        d = torch.linalg.norm(x - c, dim=-1) - r
        bc, bh = (torch.as_tensor(v, dtype=x.dtype) for v in BOX)
        q = (x - bc).abs() - bh
        box = torch.linalg.norm(q.clamp(min=0), dim=-1) + q.amax(dim=-1).clamp(max=0)
        d = torch.minimum(d, box)
        if self.floater:
            fc, fr = (torch.as_tensor(v, dtype=x.dtype) for v in FLOATER)
            d = torch.minimum(d, torch.linalg.norm(x - fc, dim=-1) - fr)
        return d

    def density(self, x: Tensor) -> Tensor:
        """x [N, 3] -> sigma [N] >= 0."""
        if self.empty:
            return torch.zeros(x.shape[0], dtype=x.dtype)
        return torch.sigmoid(-self.sdf(x) / self.eps) / self.eps

    def density_function(self):
        """The density query meshing uses (`model.run`: capability density)."""
        return self.density

    def color(self, x: Tensor, d: Tensor | None) -> Tensor:
        """x [N, 3] -> rgb [N, 3], view independent (a smooth solid texture)."""
        phase = torch.tensor([0.0, 2.0, 4.0], dtype=x.dtype)
        return 0.5 + 0.4 * torch.sin(3.0 * x.sum(dim=-1, keepdim=True) + phase)

    def render_rays(self, rays_o: Tensor, rays_d: Tensor, *, infer=None, median: bool = True) -> dict[str, Tensor]:
        """The analytic field rendered along rays [R, 3] (scene frame, unit directions): 384 samples over the
        cameras' range of depths through the box (t in [1, 5]), emission-absorption over black."""
        from nerfpipe.radiance.render import StratifiedSampler, render_rays

        def rgb_sigma(x: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
            return self.color(x, d).to(x), self.density(x).to(x)

        out = render_rays(
            rays_o,
            rays_d,
            near=1.0,
            far=5.0,
            sampler=StratifiedSampler(n_samples=384),
            rgb_sigma_fn=rgb_sigma,
            background=torch.zeros(3, dtype=rays_o.dtype),
        )
        return {k: out[k] for k in ("rgb", "depth", "acc") + (("depth_median",) if median else ())}

    # ------------------------------------------------------------------ ground truth
    def surface_points(self, n: int = 200_000, seed: int = 0) -> np.ndarray:
        """About n points uniformly spread over the exact surface (union boundary), scene frame. [M, 3]."""
        rng = np.random.default_rng(seed)
        (sc, sr), (bc, bh) = SPHERE, BOX
        parts = [("sphere", sc, sr)] + ([("floater", *FLOATER)] if self.floater else [])
        areas = {name: 4 * math.pi * r * r for name, _, r in parts}
        faces = [(axis, sign) for axis in range(3) for sign in (-1.0, 1.0)]
        face_area = [4 * np.prod(np.delete(bh, axis)) for axis, _ in faces]
        total = sum(areas.values()) + sum(face_area)
        pts = []
        for name, c, r in parts:
            v = rng.normal(size=(int(n * areas[name] / total), 3))
            pts.append(c + r * v / np.linalg.norm(v, axis=1, keepdims=True))
        for (axis, sign), area in zip(faces, face_area, strict=True):
            p = rng.uniform(-1, 1, size=(int(n * area / total), 3)) * bh
            p[:, axis] = sign * bh[axis]
            pts.append(bc + p)
        p = np.concatenate(pts)
        keep = np.abs(self.sdf(torch.as_tensor(p)).numpy()) < 1e-9  # on the union's boundary, not buried
        return p[keep]

    def scene_to_source(self, p: np.ndarray) -> np.ndarray:
        m = self.scene.source_from_scene()
        return p @ m[:3, :3].T + m[:3, 3]


def visible_points(points: np.ndarray, scene_src: Path, tol: float = VISIBILITY_TOL) -> np.ndarray:
    """Mask [N]: the point (source frame, metres) is seen by a training camera of the synthetic scene in
    `scene_src` (the output folder of `stages.scene`): it projects into the image and the exact scene's
    first hit along the ray to it is not nearer than the point minus `tol`. Hidden ground-truth faces
    (the slab's underside, the parts of objects sunk into it) and the unseen inside of a predicted surface
    are dropped; floaters in free space are kept."""
    import json

    from nerfpipe.data.synthetic.objects import default_primitives
    from nerfpipe.data.transforms import read_scene

    scene = read_scene(scene_src)
    manifest = json.loads((Path(scene_src) / "manifest.json").read_text())
    seed = int(manifest.get("config", {}).get("seed", 0))
    prims = default_primitives(seed)
    seen = np.zeros(len(points), bool)
    for i in scene.split("train"):
        intr = scene.frame_intrinsics(i)
        pose = scene.frames[i].world_from_cam
        uv, z = project(torch.as_tensor(points), torch.as_tensor(pose), intr)
        uv, z = uv.numpy(), z.numpy()
        idx = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < intr.w) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.h))
        idx = idx[~seen[idx]]
        o = np.broadcast_to(pose[:3, 3], (len(idx), 3)).copy()
        v = points[idx] - o
        dist = np.linalg.norm(v, axis=1)
        d = v / dist[:, None]
        t = np.full(len(idx), np.inf)
        for prim in prims:
            t = np.minimum(t, prim.intersect(o, d))
        seen[idx[t >= dist - tol]] = True
    return seen
