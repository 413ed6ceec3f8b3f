"""X-ray geometry and the exact voxel projector (Siddon): cone- and parallel-beam rays, line integrals, Beer-Lambert.

Conventions (docs/DESIGN.md "Projection scenes"):
- Lengths in the scene's `length_unit` (mm by default); attenuation mu in 1 / length_unit; a line integral
  p = integral mu dl = -log(I / I0) is dimensionless.
- World frame: right-handed, the rotation axis is +z through the isocentre (the origin).
- View at angle theta (radians): `e_s = (cos, sin, 0)` points from the isocentre to the source,
  `e_u = (-sin, cos, 0)` is the detector's column direction, `e_v = (0, 0, 1)` its up direction.
  Cone beam: source at `dso * e_s`, detector plane through `-(dsd - dso) * e_s`, rays from the source to each
  pixel centre. Parallel beam: rays along `-e_s`, starting `dso` from the axis (dsd only places the detector).
- Detector image [n_v, n_u] (rows, columns), seen from the source: column i grows along e_u (to the right),
  row j grows downwards, so pixel (j, i) has its centre at
  u = (i + 0.5 - n_u / 2) du + off_u,  v = (n_v / 2 - j - 0.5) dv + off_v.
- Volume [nx, ny, nz]: index (i, j, k) is the voxel whose centre is
  `center + ((i, j, k) + 0.5 - n / 2) * spacing`; mu is constant over each voxel (box-shaped voxels).
- Rays: `rays_o [R, 3]`, `rays_d [R, 3]` unit; `t` is distance along the ray.

`siddon_project` is exact for that piecewise-constant volume: every ray is cut at each voxel plane it crosses
and mu times the chord length is summed (Siddon 1985, sort-based so that it is vectorised); `siddon_reference`
is its plain per-ray loop twin.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from nerfpipe.radiance.aabb import ray_aabb_intersect

__all__ = [
    "XrayGeometry",
    "VoxelGrid",
    "view_axes",
    "detector_coordinates",
    "detector_rays",
    "rays_for_pixels",
    "volume_box",
    "voxel_centers",
    "siddon_project",
    "siddon_reference",
    "project_views",
    "line_integral_from_counts",
    "counts_from_line_integral",
    "poisson_counts",
    "shadow_detector",
]


@dataclass(frozen=True, kw_only=True)
class XrayGeometry:
    """A circular scan: cone or parallel beam, one angle per view (see the module docstring for the frame)."""

    mode: Literal["cone", "parallel"]
    """Beam shape."""
    dso: float
    """Distance source -> rotation axis (parallel beam: where the rays start)."""
    dsd: float
    """Distance source -> detector plane (> dso)."""
    detector_shape: tuple[int, int]
    """(n_v rows, n_u columns)."""
    detector_pitch: tuple[float, float]
    """(dv, du): pixel size on the detector, length units."""
    detector_offset: tuple[float, float] = (0.0, 0.0)
    """(off_v, off_u): shift of the detector centre within its plane, length units."""
    angles: tuple[float, ...] = field(default=())
    """Per view: rotation angle of the gantry, radians."""
    length_unit: str = "mm"
    """Unit of every length here (and 1 / unit for attenuation)."""

    @property
    def n_views(self) -> int:
        return len(self.angles)

    @property
    def magnification(self) -> float:
        """Detector size / size at the isocentre (1 for parallel beam)."""
        return self.dsd / self.dso if self.mode == "cone" else 1.0

    def with_angles(self, angles: Sequence[float]) -> XrayGeometry:
        return replace(self, angles=tuple(float(a) for a in angles))

    def subset(self, views: Sequence[int]) -> XrayGeometry:
        return self.with_angles([self.angles[i] for i in views])


@dataclass(frozen=True, kw_only=True)
class VoxelGrid:
    """A box-voxel grid: `shape` (nx, ny, nz), `spacing` (sx, sy, sz) and the world position of its centre."""

    shape: tuple[int, int, int]
    spacing: tuple[float, float, float]
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def box(self) -> np.ndarray:
        """[2, 3] min and max corner."""
        return volume_box(self.shape, self.spacing, self.center)

    def centers(self, dtype=torch.float32, device=None) -> Tensor:
        """Voxel centres [nx, ny, nz, 3]."""
        return voxel_centers(self.shape, self.spacing, self.center, dtype=dtype, device=device)


def view_axes(angle: float, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor, Tensor]:
    """(e_s, e_u, e_v), each [3], for one gantry angle in radians."""
    c, s = math.cos(angle), math.sin(angle)
    like = dict(dtype=dtype, device=device)
    return (
        torch.tensor([c, s, 0.0], **like),
        torch.tensor([-s, c, 0.0], **like),
        torch.tensor([0.0, 0.0, 1.0], **like),
    )


def detector_coordinates(geometry: XrayGeometry, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor]:
    """(v [n_v], u [n_u]): pixel-centre coordinates in the detector plane, rows top to bottom."""
    (nv, nu), (dv, du), (ov, ou) = geometry.detector_shape, geometry.detector_pitch, geometry.detector_offset
    like = dict(dtype=dtype, device=device)
    u = (torch.arange(nu, **like) + 0.5 - nu / 2) * du + ou
    v = (nv / 2 - torch.arange(nv, **like) - 0.5) * dv + ov
    return v, u


def detector_rays(
    geometry: XrayGeometry, view: int, dtype=torch.float32, device=None, pixels: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Rays of one view: (rays_o [R, 3], rays_d [R, 3] unit), row-major over the detector (R = n_v * n_u),
    or only the flat pixel indices `pixels [R]` (j * n_u + i). Built in float64, returned in `dtype`."""
    e_s, e_u, e_v = view_axes(geometry.angles[view], device=device)
    v, u = detector_coordinates(geometry, device=device)
    nu = geometry.detector_shape[1]
    if pixels is None:
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        vv, uu = vv.reshape(-1), uu.reshape(-1)
    else:
        pixels = pixels.to(device=device, dtype=torch.long)
        vv, uu = v[pixels // nu], u[pixels % nu]
    plane = uu[:, None] * e_u + vv[:, None] * e_v  # [R, 3] in-plane offsets
    if geometry.mode == "cone":
        pos = -(geometry.dsd - geometry.dso) * e_s + plane  # pixel centres
        src = geometry.dso * e_s
        d = pos - src
        d = d / d.norm(dim=-1, keepdim=True)
        o = src.expand_as(d)
    else:
        o = geometry.dso * e_s + plane
        d = (-e_s).expand_as(o)
    return o.to(dtype).contiguous(), d.to(dtype).contiguous()


def rays_for_pixels(
    geometry: XrayGeometry, views: Tensor, pixels: Tensor, dtype=torch.float32
) -> tuple[Tensor, Tensor]:
    """Rays through flat pixels `pixels [R]` (j * n_u + i) of views `views [R]` (mixed views, vectorised):
    (rays_o [R, 3], rays_d [R, 3] unit), built in float64 and returned in `dtype`, on `pixels`' device."""
    device = pixels.device
    angles = torch.as_tensor(geometry.angles, dtype=torch.float64, device=device)[views.long()]  # [R]
    c, s = torch.cos(angles), torch.sin(angles)
    zero = torch.zeros_like(c)
    e_s, e_u = torch.stack([c, s, zero], -1), torch.stack([-s, c, zero], -1)  # [R, 3]
    e_v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=device)
    v, u = detector_coordinates(geometry, device=device)
    nu = geometry.detector_shape[1]
    pixels = pixels.long()
    plane = u[pixels % nu][:, None] * e_u + v[pixels // nu][:, None] * e_v  # [R, 3]
    if geometry.mode == "cone":
        src = geometry.dso * e_s
        d = -(geometry.dsd - geometry.dso) * e_s + plane - src
        d = d / d.norm(dim=-1, keepdim=True)
        o = src
    else:
        o, d = geometry.dso * e_s + plane, -e_s
    return o.to(dtype).contiguous(), d.to(dtype).contiguous()


def volume_box(shape: Sequence[int], spacing: Sequence[float], center: Sequence[float] = (0, 0, 0)) -> np.ndarray:
    """[2, 3] (min corner, max corner) of a volume grid, length units."""
    n, s, c = (np.asarray(x, dtype=np.float64) for x in (shape, spacing, center))
    return np.stack([c - n * s / 2, c + n * s / 2])


def voxel_centers(shape, spacing, center=(0, 0, 0), dtype=torch.float32, device=None) -> Tensor:
    """Voxel centres [nx, ny, nz, 3] in the world frame."""
    axes = [
        (torch.arange(n, dtype=torch.float64, device=device) + 0.5 - n / 2) * s + c
        for n, s, c in zip(shape, spacing, center, strict=True)
    ]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).to(dtype)


def _check_volume(volume: Tensor, spacing, center) -> None:
    if volume.ndim != 3:
        raise ValueError(f"expected volume [nx, ny, nz], got {tuple(volume.shape)}")
    if len(spacing) != 3 or len(center) != 3 or not all(s > 0 for s in spacing):
        raise ValueError(f"expected 3 positive spacings and 3 centre coordinates, got {spacing}, {center}")


def siddon_project(
    volume: Tensor,  # [nx, ny, nz] mu per length unit
    spacing: Sequence[float],  # (sx, sy, sz)
    center: Sequence[float],  # (cx, cy, cz) world position of the volume's centre
    rays_o: Tensor,  # [R, 3]
    rays_d: Tensor,  # [R, 3] unit
    *,
    reduce: Literal["sum", "max"] = "sum",
    chunk: int = 4096,
) -> Tensor:
    """Exact line integrals sum_voxels mu * chord [R] ("max": the largest mu on the ray, a MIP), in the
    volume's dtype (float32 or float64: positions are taken relative to each ray's entry point, so a source
    1000 units away costs no precision). Differentiable in `volume` (gathers). Rays that miss give 0."""
    _check_volume(volume, spacing, center)
    if rays_o.shape != rays_d.shape or rays_o.ndim != 2 or rays_o.shape[-1] != 3:
        raise ValueError(f"expected rays_o, rays_d [R, 3], got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")
    out = [
        _siddon_chunk(volume, spacing, center, rays_o[i : i + chunk], rays_d[i : i + chunk], reduce)
        for i in range(0, rays_o.shape[0], chunk)
    ]
    return torch.cat(out) if out else volume.new_zeros(0)


def _siddon_chunk(volume, spacing, center, rays_o, rays_d, reduce) -> Tensor:
    dtype, device = volume.dtype, volume.device
    shape = torch.tensor(volume.shape, device=device)
    box = torch.as_tensor(volume_box(volume.shape, spacing, center), dtype=dtype, device=device)  # [2, 3]
    s = torch.as_tensor(spacing, dtype=dtype, device=device)
    o, d = rays_o.to(dtype), rays_d.to(dtype)
    t_in, t_out, hit = ray_aabb_intersect(o, d, box)
    length = torch.where(hit, t_out - t_in, torch.zeros_like(t_in))  # [R] chord through the box
    entry = o + d * t_in[:, None]  # [R, 3]: t is measured from here on
    grid_in = (entry - box[0]) / s  # [R, 3] entry point in voxel units, in [0, n]
    step = d / s  # [R, 3] voxels per unit length
    cuts = [torch.zeros_like(length)[:, None], length[:, None]]
    for a in range(3):
        # Planes k strictly between entry and exit along axis a (a contiguous range per ray).
        g0, g1 = grid_in[:, a], grid_in[:, a] + step[:, a] * length
        first = torch.floor(torch.minimum(g0, g1)) + 1
        count = (torch.ceil(torch.maximum(g0, g1)) - first).clamp(min=0)  # [R]
        count = torch.where(step[:, a] == 0, torch.zeros_like(count), count)
        width = int(count.max()) if count.numel() else 0
        if width == 0:
            continue
        k = torch.arange(width, dtype=dtype, device=device)
        planes = first[:, None] + k  # [R, W]
        step_safe = torch.where(step[:, a] == 0, torch.ones_like(g0), step[:, a])
        t = (planes - g0[:, None]) / step_safe[:, None]
        valid = k[None, :] < count[:, None]
        cuts.append(torch.where(valid, t.clamp(0, None), length[:, None]).minimum(length[:, None]))
    t_sorted = torch.cat(cuts, dim=1).sort(dim=1).values  # [R, M]
    seg = t_sorted[:, 1:] - t_sorted[:, :-1]  # [R, M - 1] chord per voxel (0 for repeated cuts)
    mid = 0.5 * (t_sorted[:, 1:] + t_sorted[:, :-1])
    idx = torch.floor(grid_in[:, None, :] + step[:, None, :] * mid[..., None]).long()  # [R, M - 1, 3] voxel
    idx = torch.minimum(idx.clamp(min=0), shape - 1)
    flat = (idx[..., 0] * volume.shape[1] + idx[..., 1]) * volume.shape[2] + idx[..., 2]
    mu = volume.reshape(-1)[flat]  # [R, M - 1]
    if reduce == "sum":
        return (mu * seg).sum(dim=1)
    if reduce == "max":
        return torch.where(seg > 0, mu, torch.zeros_like(mu)).amax(dim=1)
    raise ValueError(f"expected reduce 'sum' or 'max', got {reduce!r}")


def siddon_reference(volume: np.ndarray, spacing, center, rays_o: np.ndarray, rays_d: np.ndarray) -> np.ndarray:
    """Plain float64 per-ray loop twin of `siddon_project` (reduce="sum"), for tests."""
    vol = np.asarray(volume, np.float64)
    box = volume_box(vol.shape, spacing, center)
    s = np.asarray(spacing, np.float64)
    out = []
    for o, d in zip(np.asarray(rays_o, np.float64), np.asarray(rays_d, np.float64), strict=True):
        t_lo, t_hi = 0.0, math.inf
        for a in range(3):
            if d[a] == 0:
                if not box[0, a] <= o[a] <= box[1, a]:
                    t_lo, t_hi = math.inf, -math.inf
                continue
            t0, t1 = sorted(((box[0, a] - o[a]) / d[a], (box[1, a] - o[a]) / d[a]))
            t_lo, t_hi = max(t_lo, t0), min(t_hi, t1)
        if t_hi <= t_lo:
            out.append(0.0)
            continue
        ts = {t_lo, t_hi}
        for a in range(3):
            if d[a] != 0:
                for k in range(vol.shape[a] + 1):
                    t = (box[0, a] + k * s[a] - o[a]) / d[a]
                    if t_lo < t < t_hi:
                        ts.add(t)
        ts = sorted(ts)
        total = 0.0
        for a, b in zip(ts[:-1], ts[1:], strict=True):
            p = o + d * (0.5 * (a + b))
            i, j, k = (min(max(int(math.floor((p[c] - box[0, c]) / s[c])), 0), vol.shape[c] - 1) for c in range(3))
            total += vol[i, j, k] * (b - a)
        out.append(total)
    return np.asarray(out)


def project_views(
    volume: Tensor,
    spacing: Sequence[float],
    center: Sequence[float],
    geometry: XrayGeometry,
    *,
    reduce: Literal["sum", "max"] = "sum",
    chunk: int = 4096,
) -> Tensor:
    """Every view of `geometry` through the volume: [V, n_v, n_u] in the volume's dtype (no grad needed)."""
    nv, nu = geometry.detector_shape
    out = []
    for view in range(geometry.n_views):
        o, d = detector_rays(geometry, view, dtype=volume.dtype, device=volume.device)
        out.append(siddon_project(volume, spacing, center, o, d, reduce=reduce, chunk=chunk).reshape(nv, nu))
    return torch.stack(out) if out else volume.new_zeros(0, nv, nu)


# ---------------------------------------------------------------------------------------------- intensities
def line_integral_from_counts(counts: Tensor, i0: float) -> Tensor:
    """Measured photon counts -> line integrals p = -log(I / I0), with both edge cases explicit:

    - I = 0 (photon starvation): the log is unbounded, so the count is taken as half a photon
      (p = log(2 I0), the largest value the measurement can support) instead of inf;
    - I > I0 (noise above the flat field): p < 0 is kept (clipping at 0 would bias air upwards).
    Finite values and gradients for every count >= 0.
    """
    if not i0 > 0:
        raise ValueError(f"expected i0 > 0, got {i0}")
    if bool((counts < 0).any()):
        raise ValueError("expected photon counts >= 0")
    starved = counts <= 0
    safe = torch.where(starved, torch.full_like(counts, 0.5), counts)
    return math.log(i0) - torch.log(safe)


def counts_from_line_integral(p: Tensor, i0: float) -> Tensor:
    """Expected counts I0 exp(-p) (p >= 0 underflows to 0 counts, never NaN)."""
    return i0 * torch.exp(-p)


def poisson_counts(p: Tensor, i0: float, generator: torch.Generator | None = None) -> Tensor:
    """Poisson photon counts for line integrals p and flat-field count i0 (float64 rates, counts as float)."""
    rates = counts_from_line_integral(p.to(torch.float64), i0)
    return torch.poisson(rates, generator=generator)


def shadow_detector(
    box: np.ndarray, mode: str, dso: float, dsd: float, pitch: float, margin: float = 1.05
) -> tuple[tuple[int, int], tuple[float, float]]:
    """A square-pixel detector that sees the whole box from every angle: ((n_v, n_u), (dv, du)).

    The box's corners are projected for a dense set of angles; the detector covers the largest |u| and |v|
    (times `margin`), with `pitch` the pixel size at the detector.
    """
    corners = np.array([[x, y, z] for x in box[:, 0] for y in box[:, 1] for z in box[:, 2]], np.float64)
    u_max = v_max = 0.0
    for angle in np.linspace(0, 2 * np.pi, 73):
        e_s = np.array([np.cos(angle), np.sin(angle), 0.0])
        e_u = np.array([-np.sin(angle), np.cos(angle), 0.0])
        s, u, v = corners @ e_s, corners @ e_u, corners[:, 2]
        if mode == "cone":
            if np.any(s >= dso):
                raise ValueError(f"dso: the source ({dso}) must lie outside the volume (corner at {s.max():.4g})")
            scale = dsd / (dso - s)
            u, v = u * scale, v * scale
        u_max, v_max = max(u_max, np.abs(u).max()), max(v_max, np.abs(v).max())
    n_u = int(math.ceil(2 * u_max * margin / pitch))
    n_v = int(math.ceil(2 * v_max * margin / pitch))
    return (n_v, n_u), (pitch, pitch)
