"""Where a trained run's rays end: coloured surface points with density (or signed-distance) normals.

Shared by the stages that turn a field into a point set: `export-points` (the cloud itself) and `mesh --method
poisson` (the cloud Poisson meshes). Only the `Trained` attributes are used: `render_rays`, `background`,
`density` (or `sdf` and `aabb`: `surface_normals`), `device`.

Sampling: each camera's pixels (at the render size) are split into `stride` x `stride` interleaved sub-grids:
pixel (row, col) belongs to offset (row % stride, col % stride). A pass renders one sub-grid of every camera (rays
through the pixel centres); the offsets are taken in a seeded random order, so passes never repeat a ray and each
pass covers every camera and the whole of each image evenly. `stride` makes one pass about `PASS_SHARE` of the
points asked for; passes go on until that many points are kept (or every pixel is used), then the caller takes an
even random subset. Rays of several cameras are rendered together (`batch` rays per `render_rays` call, which
chunks them further).

A ray gives a point when its accumulated opacity is at least `acc_threshold` and its depth and colour are finite:
the point is `o + t d` (scene frame, world distances) at the ray's expected depth t = sum(w t) / acc
(`depth="expected"`) or its median depth, where the accumulated opacity reaches 0.5 (`depth="median"`: where the
surface is, without the blend of a foreground and a background that the expected depth takes at silhouettes). Its
colour is the rendered colour with the evaluation background taken out, (rgb - (1 - acc) background) / acc: the
colour of what the ray hit, not of the background that shows through a ray that is not fully opaque (acc >=
acc_threshold > 0, and the division clamps acc at float32's epsilon).

Normals (`density_normals`): n = -grad sigma / |grad sigma| at the point, by central differences of the density
with a step h: grad_k = (sigma(x + h e_k) - sigma(x - h e_k)) / 2h. Density grows into an object, so -grad sigma
points out of it, whichever camera saw the point. A run with a signed distance f (negative inside: the sdf
method's) has `sdf_normals`, +grad f / |grad f| by the same differences: f grows out of the object. Central
differences rather than autograd: `Trained.density` (and `Trained.sdf`) is the public no-grad query that maps scene
points into every run's space (box, contracted, NDC), and the analytic gradient of a trilinear hash grid is
piecewise constant per cell of its finest level and noisy, while a step of a few cells averages over them. Where
the gradient is zero or not finite (empty space around the point) the normal is the reverse of the ray that gave
the point (facing its camera), and counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from nerfpipe.data.progress import NO_PROGRESS, Progress
from nerfpipe.model.cameras import CameraPath
from nerfpipe.model.run import require_any
from nerfpipe.radiance.camera import generate_rays

__all__ = [
    "PASS_SHARE",
    "Gathered",
    "gather_points",
    "pass_stride",
    "density_normals",
    "sdf_normals",
    "NormalRule",
    "NORMAL_RULES",
    "surface_normals",
    "facing_share",
]

PASS_SHARE = 0.25
"""One pass renders about this share of the points asked for (so the last pass overshoots by at most that)."""

DensityFn = Callable[[torch.Tensor], torch.Tensor]
"""x [N, 3] float32 scene frame on the field's device -> sigma [N] (`Trained.density`)."""

_AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


@dataclass(frozen=True, kw_only=True)
class Gathered:
    """The points of the rays rendered, and what the rays gave."""

    points: np.ndarray  # [N, 3] float64, scene frame
    rgb: np.ndarray  # [N, 3] float32 in [0, 1], background taken out
    dirs: np.ndarray  # [N, 3] float32 unit: the direction of the ray that gave each point
    pixels: int
    """Pixels of every camera at the render size."""
    stride: int
    passes: int
    """Passes rendered (of stride * stride)."""
    rays: int
    """Rays rendered."""
    opaque: int
    """Rays with accumulated opacity >= acc_threshold."""
    non_finite: int
    """Rays whose opacity, or an opaque ray's depth or colour, is NaN / inf (dropped)."""
    outside: int
    """Finite points dropped by `keep`."""


def pass_stride(pixels: int, target: int) -> int:
    """The sub-grid stride that makes one pass about `PASS_SHARE * target` rays (1: one pass renders every pixel)."""
    return max(1, math.floor(math.sqrt(pixels / max(1.0, PASS_SHARE * target))))


def _pass_rays(cams: CameraPath, stride: int, offset: tuple[int, int]) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """(rays_o, rays_d) [R, 3] float64 of one sub-grid of each camera, camera by camera."""
    dr, dc = offset
    for intr, pose in zip(cams.intrinsics, cams.world_from_cams, strict=True):
        rows = torch.arange(dr, intr.h, stride, dtype=torch.float64)
        cols = torch.arange(dc, intr.w, stride, dtype=torch.float64)
        if rows.numel() == 0 or cols.numel() == 0:
            continue
        v, u = torch.meshgrid(rows, cols, indexing="ij")
        uv = torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1) + 0.5  # pixel centres
        yield generate_rays(intr, torch.as_tensor(np.asarray(pose, np.float64)), uv)


def _batches(
    cams: CameraPath, stride: int, order: np.ndarray, batch: int
) -> Iterator[tuple[int, torch.Tensor, torch.Tensor]]:
    """(pass index, rays_o, rays_d) of about `batch` rays each; a batch never spans two passes."""
    for k, flat in enumerate(order):
        offset = (int(flat) // stride, int(flat) % stride)
        buf_o, buf_d, n = [], [], 0
        for o, d in _pass_rays(cams, stride, offset):
            buf_o.append(o)
            buf_d.append(d)
            n += o.shape[0]
            if n >= batch:
                yield k, torch.cat(buf_o), torch.cat(buf_d)
                buf_o, buf_d, n = [], [], 0
        if buf_o:
            yield k, torch.cat(buf_o), torch.cat(buf_d)


def _points_of(
    trained: Any, out: dict[str, torch.Tensor], o: torch.Tensor, d: torch.Tensor, acc_threshold: float, key: str
):
    """(opaque rays, NaN / inf rays (opacity, or depth or colour of an opaque ray), points [K, 3] f64,
    rgb [K, 3] f32, dirs [K, 3] f32); `key` the depth to place points at (depth or depth_median)."""
    acc = out["acc"].detach().float().cpu()
    opaque = acc >= acc_threshold  # a NaN opacity is never opaque
    t = out[key].detach().double().cpu()[opaque]
    rgb = out["rgb"].detach().float().cpu()[opaque]
    a = acc[opaque][:, None]
    background = torch.as_tensor(trained.background, dtype=torch.float32).cpu().reshape(1, 3)
    rgb = (rgb - (1 - a) * background) / a.clamp_min(torch.finfo(torch.float32).eps)
    finite = torch.isfinite(t) & torch.isfinite(rgb).all(dim=-1)
    o, d = o[opaque][finite], d[opaque][finite]
    points = (o + t[finite, None] * d).numpy()
    bad = int((~torch.isfinite(acc)).sum()) + int((~finite).sum())
    return int(opaque.sum()), bad, points, rgb[finite].clamp(0, 1).numpy(), d.float().numpy()


def gather_points(
    trained: Any,
    cams: CameraPath,
    *,
    target: int,
    acc_threshold: float,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    seed: int = 0,
    batch: int = 1 << 18,
    progress: Progress | None = None,
    depth: Literal["expected", "median"] = "expected",
) -> Gathered:
    """Render passes of the cameras' rays (module doc) until at least `target` points are kept or every pixel is
    rendered. `keep(points_scene [K, 3]) -> mask [K]` drops points (a box); `depth` where a ray's point lies."""
    if depth not in ("expected", "median"):
        raise ValueError(f"depth: expected 'expected' or 'median', got {depth!r}")
    key = "depth" if depth == "expected" else "depth_median"
    pixels = sum(intr.w * intr.h for intr in cams.intrinsics)
    stride = pass_stride(pixels, target)
    order = np.random.default_rng(seed).permutation(stride * stride)
    progress = progress or NO_PROGRESS
    task = progress.add_task("surface points: rendering", total=target)
    parts: dict[str, list[np.ndarray]] = {"points": [], "rgb": [], "dirs": []}
    rays = opaque = non_finite = outside = kept = 0
    passes, done_pass = 0, -1
    with torch.no_grad():
        for k, o, d in _batches(cams, stride, order, batch):
            if k != done_pass and kept >= target:  # a new pass, and the last one finished with enough points
                break
            if k != done_pass:
                passes, done_pass = passes + 1, k
            out = trained.render_rays(
                o.to(trained.device, torch.float32), d.to(trained.device, torch.float32), median=depth == "median"
            )
            n_opaque, n_bad, points, rgb, dirs = _points_of(trained, out, o, d, acc_threshold, key)
            rays, opaque, non_finite = rays + o.shape[0], opaque + n_opaque, non_finite + n_bad
            if keep is not None:
                inside = np.asarray(keep(points), bool)
                outside += int((~inside).sum())
                points, rgb, dirs = points[inside], rgb[inside], dirs[inside]
            for name, value in (("points", points), ("rgb", rgb), ("dirs", dirs)):
                parts[name].append(value)
            progress.advance(task, min(len(points), max(0, target - kept)))
            kept += len(points)
    joined = {name: np.concatenate(v) if v else np.zeros((0, 3)) for name, v in parts.items()}
    return Gathered(
        points=joined["points"].astype(np.float64),
        rgb=joined["rgb"].astype(np.float32),
        dirs=joined["dirs"].astype(np.float32),
        pixels=pixels,
        stride=stride,
        passes=passes,
        rays=rays,
        opaque=opaque,
        non_finite=non_finite,
        outside=outside,
    )


def density_normals(
    density: DensityFn, points: np.ndarray, dirs: np.ndarray, step: float, device: torch.device, chunk: int = 1 << 16
) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals [N, 3] float64: -grad sigma normalised (module doc), mask [N]: from the gradient; the others
    are -dirs).

    points [N, 3] scene frame; dirs [N, 3] unit ray directions; step h in scene units (> 0)."""
    return _gradient_normals(density, -1.0, points, dirs, step, device, chunk)


def sdf_normals(
    sdf: DensityFn, points: np.ndarray, dirs: np.ndarray, step: float, device: torch.device, chunk: int = 1 << 16
) -> tuple[np.ndarray, np.ndarray]:
    """`density_normals` for a signed distance `sdf` (scene points [M, 3] -> [M], negative inside): +grad f
    normalised (module doc)."""
    return _gradient_normals(sdf, 1.0, points, dirs, step, device, chunk)


def _gradient_normals(
    fn: DensityFn,
    sign: float,
    points: np.ndarray,
    dirs: np.ndarray,
    step: float,
    device: torch.device,
    chunk: int,
) -> tuple[np.ndarray, np.ndarray]:
    """sign x grad fn / |grad fn| by central differences (module doc), [N, 3] float64, and the mask [N] of those
    from the gradient (the others: -dirs)."""
    if not step > 0:
        raise ValueError(f"expected a step > 0, got {step}")
    normals = np.empty((len(points), 3), np.float64)
    offsets = step * _AXES  # [6, 3]
    with torch.no_grad():
        for a in range(0, len(points), chunk):
            x = points[a : a + chunk]
            q = (x[:, None, :] + offsets[None]).reshape(-1, 3)
            value = fn(torch.as_tensor(q, dtype=torch.float32, device=device))
            v = value.detach().double().cpu().numpy().reshape(-1, 6)
            normals[a : a + chunk] = sign * (v[:, 0::2] - v[:, 1::2]) / (2.0 * step)
    norm = np.linalg.norm(normals, axis=1)
    good = np.isfinite(norm) & (norm > 0)
    normals[good] /= norm[good, None]
    normals[~good] = -np.asarray(dirs, np.float64)[~good]
    return normals, good


@dataclass(frozen=True)
class NormalRule:
    """How the normals come from what a run gives at points (a capability of `model.run`, read as `run.<name>`)."""

    normals: Callable[..., tuple[np.ndarray, np.ndarray]]  # `density_normals` or `sdf_normals`
    words: str  # the reports' rule
    in_box_only: bool  # a surface's gradient only inside the run's aabb (beyond: the point faces its camera)


NORMAL_RULES = {
    "sdf": NormalRule(sdf_normals, "+grad f / |grad f|, central differences of the signed distance", True),
    "density": NormalRule(density_normals, "-grad sigma / |grad sigma|, central differences of the density", False),
}
"""By what the run gives at points, in the order asked (a signed distance's when a run has both)."""


def surface_normals(
    trained: Any, points: np.ndarray, dirs: np.ndarray, step: float, device: torch.device, *, stage: str
) -> tuple[np.ndarray, np.ndarray, NormalRule]:
    """(unit normals [N, 3] float64, mask [N] of those from the gradient, the rule used) of a run's points (scene
    frame) by the first of NORMAL_RULES it can give; a signed distance's only inside the run's aabb, a point beyond
    it (a real capture's surroundings, from the density outside) facing its camera as one without a gradient does.
    UserError in one line (naming `stage`) when the run gives neither."""
    name = require_any(trained, tuple(NORMAL_RULES), stage=stage)
    rule = NORMAL_RULES[name]
    normals, good = rule.normals(getattr(trained, name), points, dirs, step, device)
    if rule.in_box_only:
        box = np.asarray(trained.aabb.tolist(), np.float64).reshape(2, 3)  # a tensor or an array
        outside = ~((points >= box[0]) & (points <= box[1])).all(axis=1)
        normals[outside], good[outside] = -np.asarray(dirs, np.float64)[outside], False
    return normals, good, rule


def facing_share(normals: np.ndarray, dirs: np.ndarray) -> float:
    """Share of normals that face the camera whose ray gave the point (n . -d > 0); NaN without points."""
    if len(normals) == 0:
        return float("nan")
    return float((np.einsum("ij,ij->i", normals, -np.asarray(dirs, np.float64)) > 0).mean())
