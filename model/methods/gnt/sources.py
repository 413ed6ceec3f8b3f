"""Source photos for GNT: the posed images a ray borrows features from, their choice per ray, and the bilinear
gather of feature maps at projected points.

Conventions:
- Cameras as `model.views.Views` holds them: `world_from_cam` [V, 4, 4] in OpenGL axes (x right, y up, looking down
  -z), intrinsics (fx, fy, cx, cy, k1, k2, k3, p1, p2) of the source images as stored here (shrunk to at most
  `max_side` pixels, intrinsics scaled with them); pixel (col i, row j) has its centre at (i + 0.5, j + 0.5).
- Projection goes through OpenCV axes (y down, +z forward, `radiance.camera`); a point is *seen* by a source when
  it is in front of the camera (z > 0) and projects inside the image.
- A source image is 4 channels: colour premultiplied by alpha, and alpha (1 for opaque photos).

`gather` is the fast op (one flat index over every map's texels, 4 corners a sample); `gather_plain` its plain twin
(`torch.nn.functional.grid_sample`, one call a view): tests compare outputs and gradients.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.model.views import Views
from nerfpipe.radiance.camera import OPENGL_FROM_OPENCV

__all__ = ["Sources", "sources_from_views", "texels", "gather", "gather_texels", "gather_plain"]


@dataclass
class Sources:
    """Posed source images (module doc)."""

    images: Tensor  # [V, 4, H, W] float32: premultiplied rgb, alpha
    world_from_cams: Tensor  # [V, 4, 4] float32, OpenGL axes
    intrinsics: Tensor  # [V, 9] float32 of images' size: fx, fy, cx, cy, k1, k2, k3, p1, p2

    def __post_init__(self) -> None:
        v = self.images.shape[0]
        if self.images.ndim != 4 or self.images.shape[1] != 4:
            raise ValueError(f"expected images [V, 4, H, W], got {tuple(self.images.shape)}")
        if self.world_from_cams.shape != (v, 4, 4) or self.intrinsics.shape != (v, 9):
            raise ValueError(
                f"expected world_from_cams [{v}, 4, 4] and intrinsics [{v}, 9], got "
                f"{tuple(self.world_from_cams.shape)}, {tuple(self.intrinsics.shape)}"
            )
        cv = self.world_from_cams @ OPENGL_FROM_OPENCV.to(self.world_from_cams)
        self.cam_from_world = torch.linalg.inv(cv)[:, :3, :]  # [V, 3, 4] OpenCV axes
        self.centres = self.world_from_cams[:, :3, 3]  # [V, 3]
        self.pixels = texels(self.images)  # [V H W, 4] what a sample reads of the photos (`gather_texels`)
        self.distorted = bool((self.intrinsics[:, 4:] != 0).any())

    @property
    def n(self) -> int:
        return self.images.shape[0]

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) of the source images."""
        return int(self.images.shape[2]), int(self.images.shape[3])

    def to(self, device: torch.device) -> Sources:
        return Sources(self.images.to(device), self.world_from_cams.to(device), self.intrinsics.to(device))

    def select(self, point: Tensor, d: Tensor, k: int, exclude: Tensor | None = None) -> Tensor:
        """The k sources [R, k] (long) whose view of `point` [R, 3] (a point on each ray, its middle) is closest in
        angle to the ray's direction d [R, 3] (unit): IBRNet's and GNT's choice, per ray. `exclude` [R] (long, -1
        for none): a source each ray may not use (its own photo while training)."""
        to_point = point[:, None, :] - self.centres[None]  # [R, V, 3]
        cos = (to_point * d[:, None, :]).sum(-1) / torch.linalg.vector_norm(to_point, dim=-1).clamp_min(1e-12)
        if exclude is not None:
            mine = exclude[:, None] == torch.arange(self.n, device=d.device)[None]  # [R, V]
            cos = cos.masked_fill(mine, -3.0)
        return cos.topk(min(k, self.n), dim=1).indices  # [R, k]

    def project(self, x: Tensor, chosen: Tensor) -> tuple[Tensor, Tensor]:
        """Points x [R, S, 3] into each ray's chosen sources [R, K] -> uv [R, S, K, 2] (pixels of the source images)
        and seen [R, S, K] (bool: in front and inside)."""
        m = self.cam_from_world[chosen]  # [R, K, 3, 4]
        p = torch.einsum("rkij,rsj->rski", m[..., :3], x) + m[:, None, :, :, 3]  # [R, S, K, 3] OpenCV camera
        z = p[..., 2]
        front = z > 1e-6
        xy = p[..., :2] / torch.where(front, z, torch.ones_like(z))[..., None]
        k = self.intrinsics[chosen][:, None]  # [R, 1, K, 9]
        if self.distorted:
            x_, y_ = xy[..., 0], xy[..., 1]
            r2 = x_ * x_ + y_ * y_
            radial = 1 + r2 * (k[..., 4] + r2 * (k[..., 5] + r2 * k[..., 6]))
            dx = 2 * k[..., 7] * x_ * y_ + k[..., 8] * (r2 + 2 * x_ * x_)
            dy = k[..., 7] * (r2 + 2 * y_ * y_) + 2 * k[..., 8] * x_ * y_
            xy = torch.stack([x_ * radial + dx, y_ * radial + dy], dim=-1)
        uv = torch.stack([k[..., 0] * xy[..., 0] + k[..., 2], k[..., 1] * xy[..., 1] + k[..., 3]], dim=-1)
        h, w = self.size
        inside = (uv[..., 0] >= 0) & (uv[..., 0] <= w) & (uv[..., 1] >= 0) & (uv[..., 1] <= h)
        return uv, front & inside

    def directions(self, x: Tensor, chosen: Tensor) -> Tensor:
        """Unit directions [R, S, K, 3] from each chosen source's centre to the points x [R, S, 3]."""
        v = x[:, :, None, :] - self.centres[chosen][:, None]  # [R, S, K, 3]
        return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)


def sources_from_views(views: Views, max_side: int) -> Sources:
    """The views' photos as sources, shrunk (area filter) so the long side is at most `max_side` pixels."""
    sizes = set(views.shapes)
    if len(sizes) != 1:
        raise UserError(f"gnt: every source photo must have one size, got {len(sizes)} sizes ({sorted(sizes)[:3]} ...)")
    (h, w), n = views.shapes[0], len(views.shapes)
    rgba = views.rgba.reshape(n, h, w, 4).permute(0, 3, 1, 2).float() / 255.0  # [V, 4, h, w]
    rgba = torch.cat([rgba[:, :3] * rgba[:, 3:], rgba[:, 3:]], dim=1)  # premultiplied
    scale = min(1.0, max_side / max(h, w))
    intr = views.intrinsics.clone().float()
    if scale < 1.0:
        hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
        rgba = F.interpolate(rgba, size=(hs, ws), mode="area")
        intr[:, [0, 2]] *= ws / w
        intr[:, [1, 3]] *= hs / h
    return Sources(rgba.contiguous(), views.world_from_cams.float(), intr)


def texels(maps: Tensor) -> Tensor:
    """maps [U, C, h, w] -> their texels [U h w, C], channels last (what `gather_texels` reads; a copy: keep it
    where the maps are read many times)."""
    u_, c, h, w = maps.shape
    return maps.permute(0, 2, 3, 1).reshape(u_ * h * w, c)


def gather(maps: Tensor, view: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples of maps [U, C, h, w] at uv [N, 2] (pixels of the maps, centres at +0.5, clamped to the
    border) in map view [N] (long) -> [N, C]: one flat index over every texel, four corners a sample."""
    return gather_texels(texels(maps), maps.shape[-2:], view, uv)


def gather_texels(flat: Tensor, size: tuple[int, int], view: Tensor, uv: Tensor) -> Tensor:
    """`gather` from texels [U h w, C] (`texels`) of maps of size (h, w)."""
    h, w = int(size[0]), int(size[1])
    x = (uv[:, 0] - 0.5).clamp(0, w - 1)
    y = (uv[:, 1] - 0.5).clamp(0, h - 1)
    x0, y0 = x.floor().clamp(max=w - 2 if w > 1 else 0), y.floor().clamp(max=h - 2 if h > 1 else 0)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.long(), y0.long()
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    base = view.long() * (h * w)
    top = flat[base + y0 * w + x0] * (1 - fx) + flat[base + y0 * w + x1] * fx
    bottom = flat[base + y1 * w + x0] * (1 - fx) + flat[base + y1 * w + x1] * fx
    return top * (1 - fy) + bottom * fy


def gather_plain(maps: Tensor, view: Tensor, uv: Tensor) -> Tensor:
    """`gather`'s plain twin: `grid_sample` (bilinear, border, align_corners=False), one call per map."""
    _, c, h, w = maps.shape
    out = uv.new_zeros(uv.shape[0], c)
    grid = torch.stack([uv[:, 0] / w * 2 - 1, uv[:, 1] / h * 2 - 1], dim=-1)  # [N, 2] in [-1, 1]
    for v in view.unique().tolist():
        rows = (view == v).nonzero()[:, 0]
        s = F.grid_sample(maps[v : v + 1], grid[rows][None, :, None], "bilinear", "border", align_corners=False)
        out = out.index_put((rows,), s[0, :, :, 0].T)
    return out
