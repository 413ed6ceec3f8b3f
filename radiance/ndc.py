"""Normalised device coordinates (NDC) for forward-facing scenes (NeRF's LLFF mode, Mildenhall et al. 2020,
appendix C).

A forward-facing capture looks through one window at content from a near plane out to infinity. NDC maps the
frustum of a reference camera (the mean training pose) onto a box: in the reference camera's frame (OpenGL
axes: x right, y up, looking down -z), a point (x, y, z) with z < 0 maps to

    x' = a x / z,   y' = b y / z,   z' = 1 + 2 n / z,      a = -2 fx / W,  b = -2 fy / H,

so the near plane z = -n goes to z' = -1 and z -> -inf to z' = 1; x', y' in [-1, 1] is the reference image.
A straight world ray stays straight in NDC, and equal steps in z' are equal steps in disparity, which is
where a forward-facing scene's detail lies. The field, the occupancy grid and the sampler work in the NDC box
unchanged; only rays in and depths / densities out are mapped (see `stages.train`).

Densities: a field trained in NDC gives sigma per NDC length. A world-frame density along world direction u at
x is sigma_ndc * |J(x) u| (J = d ndc / d x); `world_density_scale` evaluates it along the reference camera's
ray through x (the direction from which the scene was seen).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from nerfpipe.radiance.camera import Intrinsics, generate_rays

__all__ = ["NDC", "mean_pose", "fit_ndc"]


def mean_pose(world_from_cam: np.ndarray) -> np.ndarray:
    """The mean of camera poses [N, 4, 4] (OpenGL axes): mean centre, mean viewing (back) axis, mean up
    orthogonalised against it (LLFF's `poses_avg`). Returns world_from_ref [4, 4] float64."""
    poses = np.asarray(world_from_cam, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise ValueError(f"expected world_from_cam [N>0, 4, 4], got {poses.shape}")
    back = poses[:, :3, 2].mean(0)
    up = poses[:, :3, 1].mean(0)
    if np.linalg.norm(back) < 1e-9:
        raise ValueError("cameras look in opposite directions on average: no mean viewing direction")
    z = back / np.linalg.norm(back)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("mean up is parallel to the mean viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    out = np.eye(4)
    out[:3, :3] = np.stack([x, y, z], axis=1)
    out[:3, 3] = poses[:, :3, 3].mean(0)
    return out


@dataclass(frozen=True, kw_only=True)
class NDC:
    """The NDC map of one reference camera."""

    world_from_ref: np.ndarray  # [4, 4] float64, OpenGL camera axes, rigid
    a: float  # -2 fx / W
    b: float  # -2 fy / H
    near: float  # n > 0, scene units: the plane z = -n of the reference frame maps to z' = -1
    ref_from_world: np.ndarray = field(init=False, repr=False, compare=False)  # [4, 4] inverse, derived once

    def __post_init__(self) -> None:
        w = np.asarray(self.world_from_ref, dtype=np.float64)
        if w.shape != (4, 4) or not np.isfinite(w).all():
            raise ValueError(f"expected a finite world_from_ref [4, 4], got {w.shape}")
        if not (self.near > 0 and math.isfinite(self.near)) or not (self.a < 0 and self.b < 0):
            raise ValueError(f"expected near > 0 and a, b < 0, got near={self.near}, a={self.a}, b={self.b}")
        object.__setattr__(self, "world_from_ref", w)
        object.__setattr__(self, "ref_from_world", np.linalg.inv(w))

    # ---------------------------------------------------------------- (de)serialisation

    def to_dict(self) -> dict:
        return {"world_from_ref": self.world_from_ref.tolist(), "a": self.a, "b": self.b, "near": self.near}

    @classmethod
    def from_dict(cls, d: dict) -> NDC:
        return cls(
            world_from_ref=np.asarray(d["world_from_ref"]), a=float(d["a"]), b=float(d["b"]), near=float(d["near"])
        )

    # ---------------------------------------------------------------- frames

    def _ref_from_world(self, like: Tensor) -> tuple[Tensor, Tensor]:
        r = torch.as_tensor(self.ref_from_world[:3, :3], dtype=like.dtype, device=like.device)
        t = torch.as_tensor(self.ref_from_world[:3, 3], dtype=like.dtype, device=like.device)
        return r, t

    def _to_ref(self, x: Tensor) -> Tensor:
        """World points [..., 3] -> reference-frame points [..., 3]."""
        r, t = self._ref_from_world(x)
        return x @ r.T + t

    def _ref_to_ndc(self, q: Tensor) -> Tensor:
        inv_z = 1.0 / q[..., 2]
        return torch.stack([self.a * q[..., 0] * inv_z, self.b * q[..., 1] * inv_z, 1.0 + 2.0 * self.near * inv_z], -1)

    def _world_from_ref(self, like: Tensor) -> tuple[Tensor, Tensor]:
        r = torch.as_tensor(self.world_from_ref[:3, :3], dtype=like.dtype, device=like.device)
        t = torch.as_tensor(self.world_from_ref[:3, 3], dtype=like.dtype, device=like.device)
        return r, t

    # ---------------------------------------------------------------- points

    def points_to_ndc(self, x: Tensor) -> Tensor:
        """World points [..., 3] -> NDC [..., 3]. Points on or behind the reference plane z >= 0 have no image
        (x' = y' = z' = inf there); callers mask them with `in_front`."""
        return self._ref_to_ndc(self._to_ref(x))

    def in_front(self, x: Tensor) -> Tensor:
        """World points [..., 3] -> bool [...]: beyond the near plane (z < -near in the reference frame)."""
        return self._to_ref(x)[..., 2] < -self.near

    def points_from_ndc(self, p: Tensor) -> Tensor:
        """NDC points [..., 3] with z' < 1 -> world points [..., 3] (z' -> 1 is infinitely far: inf)."""
        z = 2.0 * self.near / (p[..., 2] - 1.0)
        q = torch.stack([p[..., 0] * z / self.a, p[..., 1] * z / self.b, z], -1)
        r, t = self._world_from_ref(p)
        return q @ r.T + t

    # ---------------------------------------------------------------- rays

    def rays_to_ndc(self, rays_o: Tensor, rays_d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """World rays o, d [R, 3] -> NDC rays (o', d' unit [R, 3]) and valid [R] bool.

        The origin moves along the ray to the near plane first (content before the near plane is not
        modelled). A ray is valid when it heads into the frustum (d_z < 0 in the reference frame, by more than
        the dtype's resolution); invalid rays get a finite dummy ray that misses the NDC box (x' = 10).
        """
        r, t = self._ref_from_world(rays_o)
        o = rays_o @ r.T + t  # [R, 3] reference frame
        d = rays_d @ r.T
        tiny = torch.finfo(rays_d.dtype).eps * 16
        valid = d[:, 2] < -tiny
        dz = torch.where(valid, d[:, 2], torch.full_like(d[:, 2], -1.0))
        shift = -(self.near + o[:, 2]) / dz
        o = o + shift[:, None] * d
        oz = -self.near  # every valid origin now lies on z = -n
        o_n = torch.stack([self.a * o[:, 0] / oz, self.b * o[:, 1] / oz, torch.full_like(o[:, 0], -1.0)], -1)
        d_n = torch.stack(
            [
                self.a * (d[:, 0] / dz - o[:, 0] / oz),
                self.b * (d[:, 1] / dz - o[:, 1] / oz),
                torch.full_like(o[:, 0], -2.0 * self.near / oz),
            ],
            -1,
        )
        d_n = d_n / torch.linalg.vector_norm(d_n, dim=-1, keepdim=True)
        dummy_o = torch.tensor([10.0, 0.0, 0.0], dtype=o_n.dtype, device=o_n.device)
        dummy_d = torch.tensor([0.0, 0.0, 1.0], dtype=o_n.dtype, device=o_n.device)
        o_n = torch.where(valid[:, None], o_n, dummy_o)
        d_n = torch.where(valid[:, None], d_n, dummy_d)
        return o_n, d_n, valid

    def world_t(self, rays_o: Tensor, rays_d: Tensor, o_ndc: Tensor, d_ndc: Tensor, t_ndc: Tensor) -> Tensor:
        """Distances t_ndc [R] along NDC rays (o_ndc, d_ndc unit) -> distances [R] along the world rays
        (rays_o, rays_d unit). z' >= 1 (infinitely far) and non-finite t give inf."""
        finite = torch.isfinite(t_ndc)
        p = o_ndc + torch.where(finite, t_ndc.clamp(min=0.0), torch.zeros_like(t_ndc))[:, None] * d_ndc
        far = ~finite | (p[:, 2] >= 1.0 - torch.finfo(p.dtype).eps * 4)
        p = torch.where(far[:, None], torch.zeros_like(p), p)
        x = self.points_from_ndc(p)
        t = ((x - rays_o) * rays_d).sum(-1)
        return torch.where(far, torch.full_like(t, math.inf), t)

    # ---------------------------------------------------------------- directions and densities

    def _jacobian_times(self, q: Tensor, v: Tensor) -> Tensor:
        """J(q) v for reference-frame points q [..., 3] and vectors v [..., 3] (J = d ndc / d q)."""
        inv_z = 1.0 / q[..., 2]
        return torch.stack(
            [
                self.a * (v[..., 0] - q[..., 0] * inv_z * v[..., 2]) * inv_z,
                self.b * (v[..., 1] - q[..., 1] * inv_z * v[..., 2]) * inv_z,
                -2.0 * self.near * v[..., 2] * inv_z * inv_z,
            ],
            -1,
        )

    def directions_to_ndc(self, x: Tensor, d: Tensor) -> Tensor:
        """World directions d [..., 3] at world points x [..., 3] -> unit NDC directions [..., 3]."""
        r, t = self._ref_from_world(x)
        v = self._jacobian_times(x @ r.T + t, d @ r.T)
        return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)

    def _density_scale_ref(self, q: Tensor) -> Tensor:
        u = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        return torch.linalg.vector_norm(self._jacobian_times(q, u), dim=-1)

    def world_density_scale(self, x: Tensor) -> Tensor:
        """x [..., 3] world points in front of the near plane -> |J u| [...]: NDC length per world length
        along the reference camera's ray u through x (multiply an NDC density by it for a world density)."""
        return self._density_scale_ref(self._to_ref(x))

    def density_query(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """World points x [N, 3] -> (NDC points [N, 3], density scale [N], in front [N] bool), with one
        change of frame. Points on or before the near plane get the NDC point (0, 0, 0) and scale 0 (they
        are outside the modelled frustum: world density 0)."""
        q = self._to_ref(x)
        front = q[..., 2] < -self.near
        stand_in = torch.tensor([0.0, 0.0, -2.0 * self.near], dtype=q.dtype, device=q.device)  # maps to z' = 0
        q = torch.where(front[..., None], q, stand_in)
        scale = torch.where(front, self._density_scale_ref(q), torch.zeros_like(q[..., 0]))
        return self._ref_to_ndc(q), scale, front

    def box(self, world_from_cam: np.ndarray, intrinsics: list[Intrinsics], margin: float = 0.05) -> np.ndarray:
        """The NDC box [2, 3] that holds every training camera's frustum beyond the near plane: x', y' of the
        image corners at the near plane and at infinity, plus `margin`; z' in [-1, 1]."""
        o, d = [], []
        for w, intr in zip(world_from_cam, intrinsics, strict=True):
            corners = torch.tensor([[0, 0], [intr.w, 0], [0, intr.h], [intr.w, intr.h]], dtype=torch.float64)
            o_w, d_w = generate_rays(intr, torch.as_tensor(w, dtype=torch.float64), uv=corners)
            o.append(o_w)
            d.append(d_w)
        o_n, d_n, valid = self.rays_to_ndc(torch.cat(o), torch.cat(d))
        if not bool(valid.all()):
            raise ValueError("a training camera's image corner looks away from the NDC reference view")
        t_inf = (1.0 - o_n[:, 2]) / d_n[:, 2]  # where z' reaches 1
        pts = torch.cat([o_n, o_n + t_inf[:, None] * d_n])
        lo = pts[:, :2].min(0).values.numpy() - margin
        hi = pts[:, :2].max(0).values.numpy() + margin
        return np.array([[lo[0], lo[1], -1.0], [hi[0], hi[1], 1.0]])


def fit_ndc(world_from_cam: np.ndarray, intr: Intrinsics, near: float) -> NDC:
    """NDC of the mean training pose, with the first camera's focal lengths and size and the scene's near."""
    if not (near > 0 and math.isfinite(near)):
        raise ValueError(f"NDC needs a finite near bound > 0, got {near}")
    return NDC(
        world_from_ref=mean_pose(world_from_cam), a=-2.0 * intr.fx / intr.w, b=-2.0 * intr.fy / intr.h, near=float(near)
    )
