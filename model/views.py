"""Training and test views of a scene, held in memory as uint8 colours; rays are made per batch.

Memory grows with the images, not beyond them: each pixel is 4 bytes (uint8 RGBA, alpha 255 for RGB images) and
each view keeps its camera. A batch of ray indices (flat over the views' pixels, view-major then row-major, the
order `radiance.camera.pixel_centers` uses) becomes rays there and then: view and pixel from the index, the
direction from that view's camera (`radiance.camera.generate_rays`' arithmetic, float64, then float32), so the
rays are those the whole images would give and sampling is unchanged. (Before: directions float32 and a view
index per pixel, 20 bytes a pixel, 5x the images; 300 views of 1920x1080 needed 12 GB.)
Rays are in the scene frame with unit directions. `evenly_spaced` picks the test views `train` renders in full.
`sparse_depth_rays`: the rays from the training cameras through the sparse points they observed (DS-NeRF's depth
supervision; `data.sparse_depth`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nerfpipe.data.confine import inside
from nerfpipe.data.errors import UserError
from nerfpipe.data.masks import load_masked_image
from nerfpipe.data.sparse_depth import read_sparse_depth
from nerfpipe.data.transforms import Scene
from nerfpipe.radiance.camera import Intrinsics, undistort

__all__ = ["Views", "load_views", "evenly_spaced", "auto_downscale", "DepthRays", "sparse_depth_rays"]


class RayViews:
    """`views.view[idx]`: the view [B] (int32) of each flat ray index, from the views' pixel offsets."""

    def __init__(self, offsets: Tensor):
        self.offsets = offsets  # [V + 1] int64

    def __getitem__(self, idx: Tensor) -> Tensor:
        return (torch.searchsorted(self.offsets, idx.long().contiguous(), right=True) - 1).to(torch.int32)


@dataclass(frozen=True)
class _Cameras:
    """Per-ray intrinsics as [B] float64 tensors: what `radiance.camera.undistort` reads, elementwise."""

    fx: Tensor
    fy: Tensor
    cx: Tensor
    cy: Tensor
    k1: Tensor
    k2: Tensor
    k3: Tensor
    p1: Tensor
    p2: Tensor
    has_distortion: bool


@dataclass
class Views:
    """A set of views: uint8 colours per pixel (views concatenated) and one camera per view."""

    rgba: Tensor  # [M, 4] uint8, view-major then row-major
    offsets: Tensor  # [V + 1] int64: view v's pixels are offsets[v]:offsets[v + 1]
    world_from_cams: Tensor  # [V, 4, 4] float64, OpenGL axes
    intrinsics: Tensor  # [V, 9] float64: fx, fy, cx, cy, k1, k2, k3, p1, p2 (of the possibly shrunk images)
    shapes: list[tuple[int, int]]  # (h, w) per view
    plain_behind: Tensor | None = None
    """[M] bool after `mask_colour(..., opaque_object=True)`: the opaque pixels that train on the plain colour (those
    of that colour); None: every opaque pixel does."""

    def __post_init__(self) -> None:
        self.widths = torch.tensor([w for _, w in self.shapes], dtype=torch.int64)  # [V]
        self.distorted = bool((self.intrinsics[:, 4:] != 0).any())
        self.view = RayViews(self.offsets)

    @property
    def n_rays(self) -> int:
        """Pixels (rays) over all views."""
        return int(self.offsets[-1])

    @property
    def origins(self) -> Tensor:
        """[V, 3] float32 camera centres."""
        return self.world_from_cams[:, :3, 3].float()

    def rays(self, idx: Tensor) -> tuple[Tensor, Tensor]:
        """Rays idx [B] -> origins [B, 3], unit directions [B, 3] (float32, CPU), through the pixel centres."""
        idx = idx.long()
        v = self.view[idx].long()
        p = idx - self.offsets[v]
        w = self.widths[v]
        u, row = (p % w).double() + 0.5, (p // w).double() + 0.5
        k = self.intrinsics[v]  # [B, 9]
        cams = _Cameras(*k.unbind(-1), has_distortion=self.distorted)
        xy_distorted = torch.stack([(u - cams.cx) / cams.fx, (row - cams.cy) / cams.fy], dim=-1)
        xy = undistort(xy_distorted, cams)  # type: ignore[arg-type]  # per-ray coefficients, same arithmetic
        dirs_cam = torch.stack([xy[:, 0], -xy[:, 1], -torch.ones_like(xy[:, 0])], dim=-1)  # OpenCV -> OpenGL
        m = self.world_from_cams[v]  # [B, 4, 4]
        d = (dirs_cam[:, None, :] * m[:, :3, :3]).sum(-1)  # [B, 3] = R @ dirs_cam
        d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
        return m[:, :3, 3].float(), d.float()

    def batch(self, idx: Tensor, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Rays idx [B] -> origins [B, 3], directions [B, 3], rgb [B, 3] and alpha [B] in [0, 1] on device.
        `self.view[idx]` gives each ray's view."""
        o, d = self.rays(idx)
        c = self.rgba[idx].to(device).float() / 255.0
        return o.to(device), d.to(device), c[:, :3], c[:, 3]

    def mask_colour(self, colour: tuple[float, float, float], tolerance: int = 4, opaque_object: bool = False) -> float:
        """Pixels within `tolerance` (of 255) of `colour` on every channel AND connected to the image's border through
        such pixels become transparent (alpha 0): the background around the object, not the object's own parts of
        that colour (a white carton on a whitened background keeps its white faces; a rule on colour alone made
        them transparent). Returns the share of pixels made transparent.
        With `opaque_object` (pose refinement: `stages.train.setup`), only the other pixels of that colour (a hole or
        a face of that colour: either may be empty space) train on the plain colour (`plain_behind`); the object's
        pixels train on a random colour, as an object with alpha does, so they must be opaque (`random_behind`).
        Why only then: on the plain colour a field that misses an object pixel is always off by the object's
        contrast with it, so a camera a few pixels off pulls in density all round its silhouette, and refinement ran
        away. Without refinement the plain colour behind the object's edge pixels is worth keeping: an anti-aliased
        edge pixel mixes object and plain colour, and a random colour behind it forces an opaque halo (figures for
        both: docs/MEASUREMENTS.md, "Backgrounds")."""
        import cv2

        c = torch.tensor([round(v * 255) for v in colour], dtype=torch.int16)
        cleared = 0
        behind = torch.zeros(self.n_rays, dtype=torch.bool) if opaque_object else None
        for v, (h, w) in enumerate(self.shapes):
            part = self.rgba[int(self.offsets[v]) : int(self.offsets[v + 1])]
            close = ((part[:, :3].to(torch.int16) - c).abs() <= tolerance).all(dim=1).reshape(h, w)
            _, labels = cv2.connectedComponents(close.numpy().astype(np.uint8), connectivity=8)
            edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
            background = torch.from_numpy(np.isin(labels, edge[edge != 0]).reshape(-1))  # label 0: other colours
            part[background, 3] = 0
            cleared += int(background.sum())
            if behind is not None:
                behind[int(self.offsets[v]) : int(self.offsets[v + 1])] = close.reshape(-1) & ~background
        self.plain_behind = behind
        return cleared / max(self.n_rays, 1)

    def random_behind(self, idx: Tensor, transparent: Tensor) -> Tensor:
        """[B] bool: the rays idx [B] that train on a random background colour in `plain` mode (model.background):
        the transparent ones (`transparent` [B], alpha 0, on any device; the result is on its device) and, after
        `mask_colour(..., opaque_object=True)`, the opaque ones not of the plain colour."""
        if self.plain_behind is None:
            return transparent
        return transparent | ~self.plain_behind[idx].to(transparent.device)

    def any_transparent(self, chunk: int = 1 << 22) -> bool:
        """Whether any pixel has alpha < 255 (in chunks: a mask of every pixel would be a quarter of the images)."""
        return any(bool((self.rgba[i : i + chunk, 3] < 255).any()) for i in range(0, self.n_rays, chunk))

    def pixels_of(self, v: int) -> Tensor:
        """Ray indices [h * w] of view v."""
        return torch.arange(int(self.offsets[v]), int(self.offsets[v + 1]))


def load_views(scene: Scene, indices: tuple[int, ...], downscale: float = 1.0) -> Views:
    """The views `indices` with images shrunk by `downscale` (area filter, intrinsics scaled), colours in one
    preallocated uint8 array; UserError when an image's size disagrees with transforms.json."""
    import cv2

    intrs = [scene.frame_intrinsics(i) for i in indices]
    intrs = [intr.scaled(1.0 / downscale) if downscale != 1.0 else intr for intr in intrs]
    shapes = [(intr.h, intr.w) for intr in intrs]
    offsets = torch.tensor([0] + [h * w for h, w in shapes], dtype=torch.int64).cumsum(0)
    rgba = torch.empty((int(offsets[-1]), 4), dtype=torch.uint8)
    for k, i in enumerate(indices):
        img = load_masked_image(scene, i)  # a frame's mask_path makes its masked-out pixels transparent
        full = scene.frame_intrinsics(i)
        if img.shape[:2] != (full.h, full.w):
            raise UserError(
                f"{scene.image_path(i)}: image is {img.shape[1]}x{img.shape[0]}, transforms.json says {full.w}x{full.h}"
            )
        if downscale != 1.0:
            img = cv2.resize(img, (intrs[k].w, intrs[k].h), interpolation=cv2.INTER_AREA)
        out = rgba[int(offsets[k]) : int(offsets[k + 1])].numpy().reshape(*shapes[k], 4)
        out[..., : img.shape[-1]] = np.round(img * 255)
        if img.shape[-1] == 3:
            out[..., 3] = 255
    world_from_cams = torch.stack(
        [torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64) for i in indices]
    )
    return Views(rgba, offsets, world_from_cams, torch.tensor([_coeffs(intr) for intr in intrs]), shapes)


def _coeffs(intr: Intrinsics) -> list[float]:
    return [intr.fx, intr.fy, intr.cx, intr.cy, intr.k1, intr.k2, intr.k3, intr.p1, intr.p2]


def evenly_spaced(n: int, k: int | None) -> list[int]:
    """k indices spread evenly over range(n), first and last included (all n when k is None or >= n)."""
    if k is None or k >= n:
        return list(range(n))
    if k < 1:
        raise ValueError(f"expected k >= 1 views, got {k}")
    return sorted({int(i) for i in np.linspace(0, n - 1, k).round()})


def auto_downscale(scene: Scene, indices: tuple[int, ...], max_side: int) -> float:
    """The smallest power of two that brings the largest image's long side to at most max_side pixels."""
    side = max(max(scene.frame_intrinsics(i).w, scene.frame_intrinsics(i).h) for i in indices)
    factor = 1
    while side / factor > max_side:
        factor *= 2
    return float(factor)


@dataclass(frozen=True)
class DepthRays:
    """Rays from training cameras through their observed sparse points: o, d [K, 3], depth [K], view [K]."""

    o: Tensor
    d: Tensor
    depth: Tensor
    view: Tensor


def sparse_depth_rays(scene: Scene, rel: str, train_idx: tuple[int, ...]) -> DepthRays | None:
    """The rays through the sparse points (file `rel` in the scene folder) each training photo observed, `view`
    counting the training photos from 0; None when they observed none."""
    sparse = read_sparse_depth(inside(scene.root, rel, "sparse_depth_path"))  # confined to the scene folder
    os_, ds, depths, views = [], [], [], []
    for k, i in enumerate(train_idx):
        o, d, dist = sparse.rays(scene.frames[i].file_path, scene.frames[i].world_from_cam[:3, 3])
        os_.append(o), ds.append(d), depths.append(dist), views.append(np.full(len(dist), k))
    depth = np.concatenate(depths)
    if depth.size == 0:
        return None
    return DepthRays(
        torch.from_numpy(np.concatenate(os_)),
        torch.from_numpy(np.concatenate(ds)),
        torch.from_numpy(depth),
        torch.from_numpy(np.concatenate(views)).long(),
    )
